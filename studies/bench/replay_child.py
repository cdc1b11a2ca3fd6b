"""The replay measured by ``rollingstar bench perf``'s ``replay_*`` lines, run in a fresh interpreter.

A module of its own so that the child process loads only what a replay needs: the process's peak
RSS is one of the reported numbers, and ``perf.py``'s own imports (the compiled window kernel's
numba among them, ~60 MiB) would be counted in it.
"""
from __future__ import annotations

import resource
import tempfile
import time
import tracemalloc
from pathlib import Path

from rollingstar.pipelines.config import load_pipeline
from rollingstar.pipelines.runner import run_pipeline


def replay_child(recording: str, pipeline: str, max_frames: int, trace: bool = False) -> dict:
    """Replay ``max_frames`` frames; frames per CPU second and peak RSS.

    ``trace``: also the peak of memory allocated *during* the replay (tracemalloc, which numpy
    reports its buffers to), the number that must not grow with the log length; traced runs are
    slower, so their times are not used.
    """
    cfg = load_pipeline(pipeline)
    with tempfile.TemporaryDirectory() as tmp:
        base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        if trace:
            tracemalloc.start()
        t, c = time.perf_counter(), time.process_time()
        summary = run_pipeline(recording, cfg, Path(tmp) / "out.mcap", show_progress=False, max_frames=max_frames)
        wall, cpu = time.perf_counter() - t, time.process_time() - c
        traced = tracemalloc.get_traced_memory()[1] / 2**20 if trace else None
        tracemalloc.stop()
    frames = int(summary.frames)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    return {"frames": frames, "wall_s": wall, "seconds": cpu, "fps": frames / cpu, "fps_wall": frames / wall,
            "peak_rss_mib": peak / 1024.0, "rss_before_run_mib": base_rss / 1024.0, "traced_peak_mib": traced}
