"""Simulated frames (he2021b Table 1 sensor, 15 Table 2 stars) for the mekf / gtsam tests.

Centroid level from the project's simulator; stars are identified by matching each centroid to
its true star (the tests are about the estimators, not the identifier).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from rollingstar.estimators.data import FrameData, GyroSamples, SensorContext, StarTable
from rollingstar.pipelines.simulate import build_simulator
from rollingstar.pipelines.truth import attitude_crb_rad2
from rollingstar.sensors import build
from rollingstar.sensors.gyro import simulate_gyro
from rollingstar.sensors.scenario import GyroConfig, load_scenario

SCENARIO = "configs/scenarios/he2021b_table2.yaml"
ARCSEC = np.pi / 180 / 3600


def sim_frames(n_frames: int, seed: int = 1, sigma_px: float = 0.05, rate_deg_s=(0.05, 0.0, 0.0), gyro: dict | None = None):
    """(frames, motion, context, per-frame single-frame CRB (3x3 rad^2) of frame 0)."""
    cfg = load_scenario(SCENARIO)
    update = {"frames": n_frames, "seed": seed,
              "noise": cfg.noise.model_copy(update={"centroid_sigma_px": sigma_px}),
              "motion": cfg.motion.model_copy(update={"rate_deg_s": tuple(rate_deg_s)})}
    if gyro is not None:
        update["gyro"] = GyroConfig(enabled=True, **gyro)
    cfg = cfg.model_copy(update=update)
    sim = build_simulator(cfg)
    ctx = SensorContext.from_scenario(cfg)
    period = int(sim.timing.frame_period_ns)
    g = None
    if gyro is not None:
        g = simulate_gyro(build.build_gyro(cfg), sim.motion, sim.timing.frame_start_ns(0) - period,
                          sim.timing.frame_start_ns(n_frames), seed)
    frames, crb = [], None
    for f in sim.frames(n_frames):
        c, tr = f.centroids, f.truth
        j = np.argmin(np.hypot(tr.x[None] - c["x"][:, None], tr.y[None] - c["y"][:, None]), axis=1)
        stars = StarTable.build(c["x"], c["y"], c["t_ns"], c["row_time_ns"], catalog_id=tr.catalog_id[j],
                                ref_icrs=tr.unit_icrs[j], sigma_px=np.full(len(c["x"]), max(sigma_px, 1e-6)))
        frame = FrameData(index=f.index, t0_ns=f.t0_ns, stars=stars)
        if g is not None:
            sel = (g.t_ns > f.t0_ns - period) & (g.t_ns <= f.t0_ns)
            frame = frame.evolve(gyro=GyroSamples(g.t_ns[sel], g.omega_rad_s[sel]))
        if crb is None and sigma_px > 0:
            w = sim.motion.attitude(tr.t_ns).inv().apply(tr.unit_icrs)
            crb = attitude_crb_rad2(ctx.camera, w, sigma_px)
        frames.append(frame)
    return frames, sim.motion, ctx, crb


def run_plugin(plugin, frames, ctx):
    """Drive a plugin as the runner does; the final frames in order (released/finished for smoothers)."""
    plugin.setup(ctx)
    outs = []
    for f in frames:
        o = plugin.process(f)
        if plugin.defers_output:
            outs += plugin.release()
        else:
            outs.append(o)
    return outs + list(plugin.finish())


def valid_estimates(outs):
    return [a for o in outs for a in o.attitudes if a.valid]


def errors_rad(ests, motion) -> np.ndarray:
    """Error rotation vectors ``Log(est^-1 truth)`` (rad, camera frame), (n, 3): the estimator's error
    state convention (``truth = est Exp(d)``); per axis the negative of attitude_error_body_arcsec."""
    t = np.array([a.t_ns for a in ests])
    return (Rotation.from_quat([a.q_xyzw for a in ests]).inv() * motion.attitude(t)).as_rotvec()


def nees(ests, motion) -> np.ndarray:
    d = errors_rad(ests, motion)
    P = np.array([a.covariance_rad2 for a in ests])
    return np.einsum("ni,ni->n", d, np.linalg.solve(P, d[..., None])[..., 0])
