"""Adversarial identification: no frame that cannot be identified may come out with a valid attitude.

    rollingstar figures adversarial [--frames N] [--seed S] [--json]

Every identifier configuration shipped with rollingstar (each identifier stage of
``configs/pipelines/*.yaml`` and of the ``diagnose`` default pipeline, deduplicated) runs, followed
by ``quest``, through the run's stage mechanics (:class:`rollingstar.pipelines.stages.StagePipeline`
with its identification check) on frames built to fool it. The sensor is the he2021a camera
(1024 x 1024, 10 deg field) with the Hipparcos-2 catalogue to Hp 6; the star field is the real
sky at a random attitude, each star at its projected position plus 0.1 px of noise. Cases:

- ``control``: the true stars, prior 20 arcsec from the truth (every identifier should succeed);
- ``stars_plus_false_spots``: the true stars and as many random spots;
- ``unrelated_prior``: the true stars, prior at an independent random attitude;
- ``prior_few_gates_off``: the true stars, prior turned 2-5 match gates away from the truth;
- ``shuffled``: the stars' x coordinates permuted among them (no true star position remains);
- ``mirrored``: the field mirrored left-right;
- ``random_points``: uniformly random spots, as many as there were stars.

The last three are also run without a prior (a cold start) on identifiers that can start without
one. A frame is *wrong* when it has a valid attitude off the truth, on some camera axis, by more
than both 1 arcmin and 10 of its own reported sigmas on that axis (the truth of the shuffled,
mirrored and random cases is the attitude the field was drawn at). A shuffled field keeps some
stars where they were (fixed points of the permutation, and stars whose x values are close), so a
correct identification of those with an honestly large covariance is possible there.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from rollingstar.config import CONFIGS
from rollingstar.estimators.data import FrameData, SensorContext, StarTable
from rollingstar.estimators.identifiers.base import Identifier
from rollingstar.pipelines.config import load_pipeline
from rollingstar.pipelines.diagnose import default_pipeline
from rollingstar.pipelines.registry import get_plugin_class
from rollingstar.pipelines.stages import StagePipeline
from rollingstar.progress import progress_bar
from rollingstar.sensors.scenario import load_scenario

CASES = ("control", "stars_plus_false_spots", "unrelated_prior", "prior_few_gates_off", "shuffled", "mirrored",
         "random_points")
COLD_CASES = ("shuffled", "mirrored", "random_points")
WRONG_ARCSEC = 60.0
WRONG_SIGMAS = 10.0
CENTROID_NOISE_PX = 0.1


@dataclass(frozen=True)
class Frame:
    stars: StarTable
    truth: Rotation
    prior: Rotation | None


def identifier_configs() -> list[tuple[str, dict]]:
    """``(label, stage config)`` of every distinct identifier stage shipped in configs/ and diagnose;
    the label names the pipelines that ship it (``high_dynamic / real_images``; past two, the first
    and how many more)."""
    pipelines = [(p.stem, load_pipeline(p)) for p in sorted((CONFIGS / "pipelines").glob("*.yaml"))]
    pipelines.append(("diagnose", default_pipeline()))
    shipped: dict[tuple, tuple[list[str], dict]] = {}  # insertion-ordered: the first pipeline's place
    for label, pipe in pipelines:
        for stage in pipe.stages:
            if issubclass(get_plugin_class(stage.kind), Identifier):
                key = (stage.kind, repr(sorted(stage.params.items())))
                names, _ = shipped.setdefault(key, ([], {"kind": stage.kind, "params": dict(stage.params)}))
                if label not in names:
                    names.append(label)
    return [(" / ".join(names) if len(names) <= 2 else f"{names[0]} and {len(names) - 1} more", config)
            for names, config in shipped.values()]


def sensor_context() -> SensorContext:
    return SensorContext.from_scenario(load_scenario(CONFIGS / "scenarios" / "he2021a.yaml"))


def _visible(context: SensorContext, attitude: Rotation) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    cam, cat = context.camera, context.catalog
    idx = np.asarray(cat.cone(attitude.apply([0.0, 0.0, 1.0]), cam.half_diagonal_rad), dtype=np.intp)
    x, y, front = cam.project(attitude.inv().apply(cat.unit_icrs[idx]))
    ok = front & cam.contains(x, y, margin_px=-2.0)
    return x[ok], y[ok], cat.magnitude[idx[ok]]


def _sky(context: SensorContext, rng, min_stars: int = 6) -> tuple[Rotation, np.ndarray, np.ndarray, np.ndarray]:
    while True:
        truth = Rotation.random(random_state=rng)
        x, y, mag = _visible(context, truth)
        if x.size >= min_stars:
            return truth, x, y, mag


def _table(context: SensorContext, x, y, mag) -> StarTable:
    timing = context.timing
    t = timing.row_mid_exposure_ns(0, np.clip(y, 0, None))
    flux = 1000.0 * 10 ** (-0.4 * (np.asarray(mag) - 6.0))
    return StarTable.build(x, y, t, flux=flux, sigma_px=np.full(len(x), CENTROID_NOISE_PX))


def make_frame(case: str, context: SensorContext, gate_px: float, rng, cold: bool = False) -> Frame:
    """One adversarial frame of ``case`` (module docstring)."""
    cam = context.camera
    truth, x, y, mag = _sky(context, rng)
    x = x + rng.normal(0.0, CENTROID_NOISE_PX, x.size)
    y = y + rng.normal(0.0, CENTROID_NOISE_PX, y.size)
    prior = truth * Rotation.from_rotvec(rng.normal(size=3) * np.radians(20.0 / 3600.0))
    spots_x, spots_y = rng.uniform(-0.5, cam.width - 0.5, x.size), rng.uniform(-0.5, cam.height - 0.5, x.size)
    if case == "stars_plus_false_spots":
        x, y, mag = np.concatenate([x, spots_x]), np.concatenate([y, spots_y]), np.concatenate([mag, rng.uniform(3, 6, x.size)])
    elif case == "unrelated_prior":
        prior = Rotation.random(random_state=rng)
    elif case == "prior_few_gates_off":
        axis = np.array([np.cos(a := rng.uniform(0, 2 * np.pi)), np.sin(a), 0.0])
        prior = truth * Rotation.from_rotvec(axis * rng.uniform(2.0, 5.0) * gate_px / cam.focal_px)
    elif case == "shuffled":
        x = x[rng.permutation(x.size)]
    elif case == "mirrored":
        x = (cam.width - 1.0) - x
    elif case == "random_points":
        x, y = spots_x, spots_y
    return Frame(_table(context, x, y, mag), truth, None if cold else prior)


def _gate(stage: dict) -> float:
    p = stage["params"]
    return float(p.get("gate_px", p.get("tracking", {}).get("gate_px", 10.0)))


def run_frame(stage: dict, frame: Frame, context: SensorContext):
    """The identifier and ``quest`` on one frame, fresh (no state from other frames)."""
    stages = [get_plugin_class(stage["kind"])(**stage["params"]), get_plugin_class("quest")()]
    ctx = replace(context, initial_attitude=frame.prior)
    for s in stages:
        s.setup(ctx)
    run = StagePipeline(stages, holds_centroids=True, context=ctx)
    return run.process(FrameData(index=0, t0_ns=0, stars=frame.stars))[0]


def is_wrong(estimate, truth: Rotation) -> bool:
    """A valid estimate off ``truth`` on some camera axis by more than both 1 arcmin and 10 of its
    reported sigmas on that axis (1 arcmin alone when it reports no covariance)."""
    if not estimate.valid:
        return False
    err = np.abs(np.degrees((truth.inv() * Rotation.from_quat(estimate.q_xyzw)).as_rotvec())) * 3600.0
    limit = np.full(3, WRONG_ARCSEC)
    if estimate.covariance_rad2 is not None:
        limit = np.maximum(limit, WRONG_SIGMAS * np.degrees(np.sqrt(np.diag(estimate.covariance_rad2))) * 3600.0)
    return bool(np.any(err > limit))


def _runs(configs, frames_per_case: int):
    for label, stage in configs:
        cold_ok = stage["kind"] != "tracking"
        for case in CASES:
            yield label, stage, case, False, frames_per_case
            if case in COLD_CASES and cold_ok:
                yield label, stage, case, True, frames_per_case


def _flag_kind(flag: str) -> str:
    """A frame flag without its numbers: ``covariance_scaled:41.7`` -> ``covariance_scaled``."""
    kind = flag.split("(")[0]
    return kind.split(":")[0] if kind.startswith("covariance_scaled") else kind


def run_adversarial(frames_per_case: int = 10, seed: int = 0, show_progress: bool = False) -> dict:
    """Every shipped identifier configuration on every case; the tally (module docstring)."""
    context = sensor_context()
    configs = identifier_configs()
    rng = np.random.default_rng(seed)
    runs = list(_runs(configs, frames_per_case))
    rows, reasons = [], Counter()
    with progress_bar("adversarial identification", sum(r[-1] for r in runs), show_progress) as advance:
        for label, stage, case, cold, n in runs:
            valid = wrong = 0
            for _ in range(n):
                frame = make_frame(case, context, _gate(stage), rng, cold)
                out = run_frame(stage, frame, context)
                valid += any(a.valid for a in out.attitudes)
                wrong += any(is_wrong(a, frame.truth) for a in out.attitudes)
                reasons.update(_flag_kind(f) for f in out.flags)
                advance(1)
            rows.append({"config": label, "identifier": stage["kind"], "params": stage["params"],
                         "case": case + (" (cold start)" if cold else ""), "frames": n, "valid": valid, "wrong": wrong})
    return {"seed": seed, "frames": sum(r["frames"] for r in rows), "configurations": len(configs),
            "wrong_valid": sum(r["wrong"] for r in rows), "rows": rows, "flags": dict(sorted(reasons.items()))}


def adversarial_table(result: dict) -> str:
    """Markdown table of :func:`run_adversarial`'s result."""
    lines = [f"{result['frames']} frames, {result['configurations']} identifier configurations, seed {result['seed']}: "
             f"**{result['wrong_valid']}** valid attitudes more than 1 arcmin (or 10 sigma) from the truth.", "",
             "| configuration | identifier | case | frames | valid | wrong valid |", "|---|---|---|---:|---:|---:|"]
    for r in result["rows"]:
        lines.append(f"| {r['config']} | {r['identifier']} | {r['case']} | {r['frames']} | {r['valid']} | {r['wrong']} |")
    lines += ["", "| frame flag | frames |", "|---|---:|"]
    lines += [f"| `{k}` | {v} |" for k, v in result["flags"].items()]
    return "\n".join(lines)
