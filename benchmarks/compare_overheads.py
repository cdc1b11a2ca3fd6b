"""Two measurements behind choices in ``pipelines/compare`` (docs/performance.md, compare line):

1. ``compression``: one compare task's work (simulate 30 frames of the he2021a image-level scenario
   into a temporary recording, run the baseline pipeline on it) with the recording zstd-compressed
   vs uncompressed, CPU time per part; compare tasks write it uncompressed (pipelines/compare/tasks.py).
2. ``start``: ``rollingstar compare configs/compare/ci.yaml`` on a 2-worker dask cluster whose
   workers are started by ``spawn`` (used) vs ``fork`` (not used: forking a process that already
   runs threads can deadlock), wall time of the whole comparison.

    .venv/bin/python benchmarks/compare_overheads.py [--repeats 2] [--only compression|start] [--json]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def compression(repeats: int) -> dict:
    from threadpoolctl import threadpool_limits

    from pipelines.config import load_pipeline, load_scenario
    from pipelines.runner import run_pipeline
    from pipelines.simulate import simulate_to_log

    scenario = load_scenario(ROOT / "configs" / "scenarios" / "he2021a.yaml")
    pipeline = load_pipeline(ROOT / "configs" / "pipelines" / "baseline.yaml")
    out: dict = {}
    with threadpool_limits(limits=1), tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeats):
            for comp in ("zstd", "none"):
                rec, res = Path(tmp) / f"{comp}.mcap", Path(tmp) / f"{comp}_out.mcap"
                c = time.process_time()
                simulate_to_log(scenario, rec, frames=30, seed=1, show_progress=False, compression=comp)
                sim = time.process_time() - c
                c = time.process_time()
                run_pipeline(rec, pipeline, res, show_progress=False)
                run = time.process_time() - c
                best = out.setdefault(comp, {"simulate_cpu_s": sim, "run_cpu_s": run, "recording_mb": 0.0})
                best["simulate_cpu_s"] = min(best["simulate_cpu_s"], sim)
                best["run_cpu_s"] = min(best["run_cpu_s"], run)
                best["recording_mb"] = rec.stat().st_size / 1e6
    total = {k: v["simulate_cpu_s"] + v["run_cpu_s"] for k, v in out.items()}
    out["none_saves_fraction"] = 1.0 - total["none"] / total["zstd"]
    return out


def start(repeats: int) -> dict:
    import dask
    import distributed  # noqa: F401  (registers its config defaults before we set one of its keys)

    from pipelines.compare import run_compare

    config = ROOT / "configs" / "compare" / "ci.yaml"
    out: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeats):
            for method in ("spawn", "fork"):
                with dask.config.set({"distributed.worker.multiprocessing-method": method}):
                    t = time.perf_counter()
                    run_compare(config, Path(tmp) / method, executor="dask", workers=2, show_progress=False)
                    out.setdefault(method, []).append(time.perf_counter() - t)
    out["fork_saves_s"] = min(out["spawn"]) - min(out["fork"])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--only", choices=["compression", "start"])
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    result = {}
    if args.only in (None, "compression"):
        result["compression"] = compression(args.repeats)
    if args.only in (None, "start"):
        result["start"] = start(args.repeats)
    if args.json:
        print(json.dumps(result, indent=1))
        return
    if "compression" in result:
        c = result["compression"]
        for comp in ("zstd", "none"):
            print(f"task recording {comp:4s}: simulate {c[comp]['simulate_cpu_s']:.2f} s, run {c[comp]['run_cpu_s']:.2f} s "
                  f"CPU, recording {c[comp]['recording_mb']:.1f} MB")
        print(f"uncompressed saves {100 * c['none_saves_fraction']:.0f} % of the task's CPU")
    if "start" in result:
        s = result["start"]
        print(f"compare ci.yaml on dask-2: spawn {', '.join(f'{v:.2f}' for v in s['spawn'])} s, "
              f"fork {', '.join(f'{v:.2f}' for v in s['fork'])} s; fork saves {s['fork_saves_s']:.2f} s (best of each)")


if __name__ == "__main__":
    main()
