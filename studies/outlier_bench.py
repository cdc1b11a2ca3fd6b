"""Attitude error with planted false matches per frame, every solver, robust gate vs plain.

The he2021b Table 1 sensor with the 15 stars of Table 2 (``configs/scenarios/he2021b_table2.yaml``),
0.05 deg/s, 0.05 px centroid noise, simulated at centroid level; every centroid is identified with
its true star (the benchmark is about the solvers, not the identifier). Then ``k`` false matches
are planted per frame: detections at uniformly random pixels, each "identified" with the catalogue
direction of a different uniformly random pixel of the same frame (seen through the true attitude)
and a random catalogue id. That is what a planet, satellite or hot pixel matched to a catalogue
star, or a misidentified star, looks like to a solver: a direction off by up to the field width.

The error of an estimate is the rotation angle of ``truth(t)^-1 * estimate`` (arcsec,
:func:`rollingstar.sensors.conventions.attitude_error_body_arcsec`); per case the RMS over the valid estimates.
Used by ``benchmarks/outliers.py`` (the table in docs/reliability.md) and by the reliability tests.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from rollingstar.config import CONFIGS
from rollingstar.estimators.data import FrameData, SensorContext, StarTable
from rollingstar.pipelines.registry import get_plugin_class
from rollingstar.pipelines.simulate import build_simulator
from rollingstar.sensors.conventions import attitude_error_body_arcsec
from rollingstar.sensors.scenario import load_scenario

SCENARIO = CONFIGS / "scenarios" / "he2021b_table2.yaml"
SOLVERS = {  # kind -> params (besides the gate)
    "quest": {},
    "request": {"group_size": "frame", "rate_source": "fixed", "rate_deg_s": (0.05, 0.0, 0.0)},
    "mekf": {"motion_model": "constant_rate"},
    "gtsam": {"mode": "fixed-lag", "motion_model": "constant_rate"},
}


@dataclass(frozen=True)
class Scene:
    frames: list[FrameData]
    motion: object
    context: object


def clean_scene(n_frames: int, seed: int, root=".") -> Scene:
    """Frames of identified true stars (no false matches)."""
    from pathlib import Path

    cfg = load_scenario(Path(root) / SCENARIO)
    cfg = cfg.model_copy(update={"frames": n_frames, "seed": seed})
    sim = build_simulator(cfg)
    ctx = SensorContext.from_scenario(cfg)
    frames = []
    for f in sim.frames(n_frames):
        c, tr = f.centroids, f.truth
        j = np.argmin(np.hypot(tr.x[None] - c["x"][:, None], tr.y[None] - c["y"][:, None]), axis=1)
        stars = StarTable.build(c["x"], c["y"], c["t_ns"], c["row_time_ns"], catalog_id=tr.catalog_id[j],
                                ref_icrs=tr.unit_icrs[j], sigma_px=np.full(len(c["x"]), cfg.noise.centroid_sigma_px))
        frames.append(FrameData(index=f.index, t0_ns=f.t0_ns, stars=stars))
    return Scene(frames, sim.motion, ctx)


def plant_false_matches(scene: Scene, k: int, seed: int) -> list[FrameData]:
    """The scene's frames with ``k`` false matches added to each (see the module docstring)."""
    if k == 0:
        return list(scene.frames)
    rng = np.random.default_rng(seed)
    cam = scene.context.camera
    W, H = cam.width, cam.height
    out = []
    for f in scene.frames:
        s = f.stars
        t = np.full(k, int(np.median(s.t_ns)), dtype=np.int64)
        x, y = rng.uniform(0, W - 1, k), rng.uniform(0, H - 1, k)
        # wrong reference: the ICRS direction of another random pixel, seen through the true attitude
        rx, ry = rng.uniform(0, W - 1, k), rng.uniform(0, H - 1, k)
        ref = scene.motion.attitude(t).apply(cam.unproject(rx, ry).reshape(-1, 3))
        ref /= np.linalg.norm(ref, axis=1, keepdims=True)
        row_t = s.row_time_ns[:1].repeat(k) if s.n else t
        false = StarTable.build(x, y, t, row_t, catalog_id=rng.integers(10**6, 2 * 10**6, k), ref_icrs=ref,
                                sigma_px=np.full(k, float(np.nanmedian(s.sigma_px))))
        merged = StarTable.concat(s, false)
        out.append(f.evolve(stars=merged))
    return out


def run_solver(kind: str, params: dict, frames: list[FrameData], context) -> list:
    """Drive one attitude plugin as the runner does; every estimate of the final frames."""
    plugin = get_plugin_class(kind)(**params)
    plugin.setup(context)
    outs = []
    for f in frames:
        o = plugin.process(f)
        outs += plugin.release() if plugin.defers_output else [o]
    outs += list(plugin.finish())
    return [a for o in outs for a in o.attitudes]


def rms_error_arcsec(estimates, motion) -> tuple[float, int]:
    """RMS rotation angle of truth^-1 * estimate over the valid estimates (arcsec), and their number."""
    valid = [a for a in estimates if a.valid]
    if not valid:
        return float("nan"), 0
    t = np.array([a.t_ns for a in valid])
    err = attitude_error_body_arcsec(motion.attitude(t), Rotation.from_quat([a.q_xyzw for a in valid]))
    return float(np.sqrt(np.mean(np.sum(err ** 2, axis=1)))), len(valid)


def measure(solvers=tuple(SOLVERS), ks=(0, 1, 2, 3), gates=("none", "ransac", "huber"), n_frames: int = 30,
            seed: int = 1, root=".", advance=lambda: None) -> list[dict]:
    """One row per (solver, gate, k): RMS error (arcsec), valid estimates, total estimates."""
    scene = clean_scene(n_frames, seed, root)
    rows = []
    for k in ks:
        frames = plant_false_matches(scene, k, seed + 1000 * k)
        for solver in solvers:
            for gate in gates:
                ests = run_solver(solver, {**SOLVERS[solver], "robust": gate}, frames, scene.context)
                rms, n_valid = rms_error_arcsec(ests, scene.motion)
                rows.append({"solver": solver, "gate": gate, "false_matches": k, "rms_arcsec": rms,
                             "valid": n_valid, "estimates": len(ests)})
                advance()
    return rows
