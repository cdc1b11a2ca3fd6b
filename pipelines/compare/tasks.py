"""One comparison task: simulate the variant with the task's seed once -> run each pipeline -> evaluate.

A pure function of the :class:`~rollingstar.pipelines.compare.config.Task` (plain YAML text and numbers, so it
pickles to any dask worker): the simulator draws from ``default_rng([seed, frame, stream])`` and
every stage is deterministic, so the metrics do not depend on where or when the task runs.
The recording is simulated once for all the variant's pipelines (it depends on the variant and the
seed only): on the he2021a image-level sweep, simulating took ~70 % of a (variant, pipeline, seed)
task, so sharing it between three pipelines halves the comparison's work.
Timings are measured too and returned apart from the metrics (they do depend on the machine).
"""
from __future__ import annotations

import tempfile
import time
import warnings
from pathlib import Path

from rollingstar.config import parse_yaml, validate
from rollingstar.errors import UserError
from rollingstar.pipelines.compare.config import Task
from rollingstar.pipelines.config import PipelineConfig
from rollingstar.pipelines.evaluate import evaluate_log
from rollingstar.pipelines.runner import build_stages, run_pipeline
from rollingstar.pipelines.simulate import simulate_to_log
from rollingstar.sensors.scenario import ScenarioConfig


def run_task(task: Task) -> dict:
    """``{"index", "variant", "seed", "rows", "task"}``; ``rows``: one ``{"variant", "pipeline", "seed",
    "metrics" | "error", "timing"}`` per pipeline, in the task's order; ``task``: the whole task's CPU
    time (this thread: simulate, runs, evaluations), wall time and the process that ran it (the
    executors' profile, :func:`rollingstar.pipelines.compare.execute.executor_profile`)."""
    import os

    import numpy  # noqa: F401  (loaded before limiting its BLAS)
    from threadpoolctl import threadpool_limits

    cpu, wall = time.thread_time(), time.perf_counter()
    # One BLAS thread in every executor: the same arithmetic whether the task runs here or on a
    # dask worker (and no thread oversubscription with several workers per machine).
    with threadpool_limits(limits=1):
        rows = _run(task)
    return {"index": task.index, "variant": task.variant, "seed": task.seed, "rows": rows,
            "task": {"cpu_s": time.thread_time() - cpu, "wall_s": time.perf_counter() - wall, "process": os.getpid()}}


def _run(task: Task) -> list[dict]:
    rows = [{"variant": task.variant, "pipeline": name, "seed": task.seed} for name, _ in task.pipelines]
    with tempfile.TemporaryDirectory(prefix="rollingstar-compare-") as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # per-frame warnings (e.g. dropped centroids) stay out of the bar
        rec = Path(tmp) / "rec.mcap"
        try:
            scenario = validate(ScenarioConfig, parse_yaml(task.scenario_yaml, task.variant), task.variant)
            # uncompressed: the recording is temporary (benchmarks/compare_overheads.py --only compression:
            # zstd took 19-22 % of a 30-frame image-level simulate + run)
            simulate_to_log(scenario, rec, frames=task.frames, seed=task.seed, show_progress=False, compression="none")
        except UserError as exc:  # the variant cannot be simulated: every pipeline's row says why
            for row in rows:
                row["error"] = f"simulate: {exc}"
            return rows
        for k, (row, (name, pipeline_yaml)) in enumerate(zip(rows, task.pipelines)):
            _run_pipeline(row, rec, Path(tmp) / f"out{k}.mcap", name, pipeline_yaml)
    return rows


def _run_pipeline(row: dict, rec: Path, out: Path, name: str, pipeline_yaml: str) -> None:
    """Run one pipeline on the recording and evaluate it into ``row`` (``metrics`` and ``timing``, or
    ``error`` when a stage fails on this scenario: recorded, not fatal)."""
    try:
        pipeline = validate(PipelineConfig, parse_yaml(pipeline_yaml, name), name)
        build_stages(pipeline, name)  # plugin modules imported before the clock starts
        cpu, wall = time.process_time(), time.perf_counter()
        summary = run_pipeline(rec, pipeline, out, pipeline_source=name, show_progress=False)
        cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
        row["metrics"] = evaluate_log(out)
    except UserError as exc:
        row["error"] = str(exc)
        return
    finally:
        out.unlink(missing_ok=True)
    n = max(summary.frames, 1)
    row["timing"] = {
        "cpu_s_per_frame": cpu / n,
        "wall_s_per_frame": wall / n,
        "stage_s_per_frame": {k: v / n for k, v in summary.stage_seconds.items()},
    }
