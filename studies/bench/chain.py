"""``rollingstar bench perf`` lines of the per-frame chain: detection, centroiding, identification,
correction and attitude of one 1024 x 1024 he2021a frame, CPU time against the floor.

Frames: the he2021a scenario (1024 x 1024, ~36 Hipparcos stars to magnitude 6) rendered by the
project's simulator at 0.5 deg/s (a tracking frame at low rate) and at 10 deg/s about the camera x
axis (34 px streaks). Each pipeline runs through the stage mechanics the runner uses
(:class:`rollingstar.pipelines.stages.StagePipeline`, identification check included); the first
frame is its cold start and is not timed; the line reports the median CPU time per frame of the
others (single-threaded pools) against the memory-bandwidth floor, one ``frame.sum()`` of the same
frame, and the mean in its note (the mean holds the streak centroider's periodic full-frame search,
every 16 tracked frames, which the median leaves out). Pipelines: ``high_dynamic`` (the candidate) and ``baseline`` (the chain before it), each at
both rates. Checks (not timings): every timed frame kept its lock (no lost-in-space search after
the first frame) and gave a valid attitude.
"""
from __future__ import annotations

import time

import numpy as np
from threadpoolctl import threadpool_limits

from rollingstar.config import CONFIGS
from rollingstar.estimators.data import FrameData, SensorContext
from rollingstar.pipelines.config import load_pipeline
from rollingstar.pipelines.runner import build_stages
from rollingstar.pipelines.simulate import build_simulator
from rollingstar.pipelines.stages import StagePipeline
from rollingstar.sensors.scenario import load_scenario

CHAIN_BUDGET_MS = {"0.5": 5.0, "10": 20.0}  # CPU budget of a tracking frame at low rate, and of the streak fit (4x)


def render_frames(rate_deg_s: float, n_frames: int, seed: int = 1):
    """``n_frames`` he2021a frames at ``rate_deg_s`` about camera x and their sensor context."""
    cfg = load_scenario(CONFIGS / "scenarios" / "he2021a.yaml")
    cfg = cfg.model_copy(update={"frames": n_frames, "seed": seed,
                                 "motion": cfg.motion.model_copy(update={"rate_deg_s": (rate_deg_s, 0.0, 0.0)})})
    sim = build_simulator(cfg)
    frames = [FrameData(index=f.index, t0_ns=f.t0_ns, image=f.image) for f in sim.frames(n_frames)]
    return frames, SensorContext.from_scenario(cfg)


def chain_times(pipeline: str, frames: list[FrameData], context) -> tuple[np.ndarray, list[FrameData], dict]:
    """CPU seconds of every frame after the first through ``pipeline`` (a shipped pipeline's name), the
    processed frames, and each stage's median seconds per frame after the first (the stage
    mechanics' own timer, wall clock on one thread)."""
    config = load_pipeline(CONFIGS / "pipelines" / f"{pipeline}.yaml")
    stages = build_stages(config, pipeline)
    for stage in stages:
        stage.setup(context)
    run = StagePipeline(stages, holds_centroids=False, context=context,
                        max_false_match_prob=config.max_false_match_prob)
    times, out, per_stage = [], [], {}
    with threadpool_limits(1):
        for k, frame in enumerate(frames):
            before = dict(run.stage_seconds)
            start = time.process_time()
            done = run.process(frame)
            if k:
                times.append(time.process_time() - start)
                for name, total in run.stage_seconds.items():
                    per_stage.setdefault(name, []).append(total - before.get(name, 0.0))
            out.extend(done)
    return np.array(times), out, {name: float(np.median(t)) for name, t in per_stage.items()}


def kept_lock(frames: list[FrameData]) -> tuple[float, float]:
    """Frames after the first that searched lost-in-space again, and frames without a valid attitude."""
    later = frames[1:]
    searched = sum(1 for f in later if "track_lost" in f.flags or any(fl.startswith("lost_in_space") for fl in f.flags))
    invalid = sum(1 for f in later if not any(a.valid for a in f.attitudes))
    return float(searched), float(invalid)
