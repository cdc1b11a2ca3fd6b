"""One comparison task: simulate the variant with the task's seed -> run the pipeline -> evaluate.

A pure function of the :class:`~pipelines.compare.config.Task` (plain YAML text and numbers, so it
pickles to any dask worker): the simulator draws from ``default_rng([seed, frame, stream])`` and
every stage is deterministic, so the metrics do not depend on where or when the task runs.
Timings are measured too and returned apart from the metrics (they do depend on the machine).
"""
from __future__ import annotations

import tempfile
import time
import warnings
from pathlib import Path

from pipelines.compare.config import Task


def run_task(task: Task) -> dict:
    """``{"index", "variant", "pipeline", "seed", "metrics" | "error", "timing", "task"}`` for one task;
    ``task``: the whole task's CPU time (this thread: simulate, run, evaluate), wall time and the
    process that ran it (the executors' profile, :func:`pipelines.compare.execute.executor_profile`)."""
    import os

    import numpy  # noqa: F401  (loaded before limiting its BLAS)
    from threadpoolctl import threadpool_limits

    cpu, wall = time.thread_time(), time.perf_counter()
    # One BLAS thread in every executor: the same arithmetic whether the task runs here or on a
    # dask worker (and no thread oversubscription with several workers per machine).
    with threadpool_limits(limits=1):
        out = _run(task)
    out["task"] = {"cpu_s": time.thread_time() - cpu, "wall_s": time.perf_counter() - wall, "process": os.getpid()}
    return out


def _run(task: Task) -> dict:
    from pipelines.config import PipelineConfig, ScenarioConfig, parse_yaml, validate
    from pipelines.errors import UserError
    from pipelines.evaluate import evaluate_log
    from pipelines.runner import build_stages, run_pipeline
    from pipelines.simulate import simulate_to_log

    out = {"index": task.index, "variant": task.variant, "pipeline": task.pipeline, "seed": task.seed}
    scenario = validate(ScenarioConfig, parse_yaml(task.scenario_yaml, task.variant), task.variant)
    pipeline = validate(PipelineConfig, parse_yaml(task.pipeline_yaml, task.pipeline), task.pipeline)
    with tempfile.TemporaryDirectory(prefix="rollingstar-compare-") as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # per-frame warnings (e.g. dropped centroids) stay out of the bar
        rec, res = Path(tmp) / "rec.mcap", Path(tmp) / "out.mcap"
        try:
            # uncompressed: the recording is temporary and read once (run_pipeline below); zstd took 19-22 %
            # of a 30-frame image-level task's CPU (benchmarks/compare_overheads.py --only compression)
            simulate_to_log(scenario, rec, frames=task.frames, seed=task.seed, show_progress=False, compression="none")
            build_stages(pipeline, task.pipeline)  # plugin modules imported before the clock starts
            cpu, wall = time.process_time(), time.perf_counter()
            summary = run_pipeline(rec, pipeline, res, pipeline_source=task.pipeline, show_progress=False)
            cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
            out["metrics"] = evaluate_log(res)
        except UserError as exc:  # a stage that fails on this scenario: recorded, not fatal
            out["error"] = str(exc)
            return out
    n = max(summary.frames, 1)
    out["timing"] = {
        "cpu_s_per_frame": cpu / n,
        "wall_s_per_frame": wall / n,
        "stage_s_per_frame": {k: v / n for k, v in summary.stage_seconds.items()},
    }
    return out
