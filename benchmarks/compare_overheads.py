"""Three measurements behind choices in ``pipelines/compare`` (docs/performance.md, compare line):

1. ``compression``: one compare task's work (simulate 30 frames of the he2021a image-level scenario
   into a temporary recording, run the baseline pipeline on it) with the recording zstd-compressed
   vs uncompressed, CPU time per part; compare tasks write it uncompressed (pipelines/compare/tasks.py).
2. ``start``: ``rollingstar compare configs/compare/ci.yaml`` on a 2-worker dask cluster whose
   workers are started by ``spawn`` (used) vs ``fork`` (not used: forking a process that already
   runs threads can deadlock), wall time of the whole comparison.
3. ``housekeeping``: the first 16 tasks of configs/compare/scaling.yaml on a 2-worker dask cluster
   with dask's housekeeping timers at their defaults vs ``LOCAL_CLUSTER_CONFIG``
   (pipelines/compare/execute.py): executor wall time, this process's CPU time while the tasks run
   (scheduler, nannies, client) and, per worker, the wall time of its tasks not spent on their CPU;
   and, apart from them, the cluster start alone (``LocalCluster`` until both workers are connected).

    .venv/bin/python benchmarks/compare_overheads.py [--repeats 2] [--only compression|start|housekeeping] [--json]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

from threadpoolctl import threadpool_limits

import rollingstar.pipelines.compare.execute as ex
from rollingstar.pipelines.compare import run_compare
from rollingstar.pipelines.compare.config import load_compare
from rollingstar.pipelines.compare.tasks import run_task
from rollingstar.pipelines.config import load_pipeline
from rollingstar.pipelines.runner import run_pipeline
from rollingstar.pipelines.simulate import simulate_to_log
from rollingstar.sensors.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def compression(repeats: int) -> dict:
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


def _cluster_start(config: dict) -> float:
    """Seconds from creating a 2-worker ``LocalCluster`` with ``config`` until both workers are connected."""
    import dask
    from dask.distributed import Client, LocalCluster

    t = time.perf_counter()
    with dask.config.set(config), LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                                silence_logs=40) as cluster, Client(cluster) as client:
        client.wait_for_workers(2)
        return time.perf_counter() - t


def housekeeping(repeats: int) -> dict:
    tasks = load_compare(ROOT / "configs" / "compare" / "scaling.yaml").tasks()[:16]
    settings = {"defaults": {"distributed.nanny.pre-spawn-environ": ex.WORKER_ENVIRON},
                "LOCAL_CLUSTER_CONFIG": ex.LOCAL_CLUSTER_CONFIG}
    tuned = ex.LOCAL_CLUSTER_CONFIG
    out: dict = {name: [] for name in settings}
    try:
        for _ in range(repeats):
            for name, config in settings.items():
                ex.LOCAL_CLUSTER_CONFIG = config
                cpu, wall = time.process_time(), time.perf_counter()
                results = ex.run_dask(run_task, tasks, lambda n: None, workers=2)
                cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
                idle: dict[int, float] = {}
                for r in results:
                    idle[r["task"]["process"]] = idle.get(r["task"]["process"], 0.0) + r["task"]["wall_s"] - r["task"]["cpu_s"]
                out[name].append({"wall_s": wall, "main_process_cpu_s": cpu,
                                  "worker_task_wall_minus_cpu_s": sorted(idle.values())})
    finally:
        ex.LOCAL_CLUSTER_CONFIG = tuned
    out["cluster_start_s"] = [_cluster_start(tuned) for _ in range(repeats)]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--only", choices=["compression", "start", "housekeeping"])
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    result = {}
    if args.only in (None, "compression"):
        result["compression"] = compression(args.repeats)
    if args.only in (None, "start"):
        result["start"] = start(args.repeats)
    if args.only in (None, "housekeeping"):
        result["housekeeping"] = housekeeping(args.repeats)
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
    for name, runs in result.get("housekeeping", {}).items():
        if name == "cluster_start_s":
            print(f"2-worker LocalCluster start (until both workers are connected): {', '.join(f'{v:.2f}' for v in runs)} s")
            continue
        for r in runs:
            print(f"16 scaling tasks on dask-2, housekeeping {name:20s}: wall {r['wall_s']:.2f} s, this process "
                  f"{r['main_process_cpu_s']:.2f} CPU s, workers' task wall - task CPU "
                  f"{', '.join(f'{v:.2f}' for v in r['worker_task_wall_minus_cpu_s'])} s")


if __name__ == "__main__":
    main()
