"""Executors: run every task serially in this process, or on dask.distributed.

Both return the task results in task order whatever the completion order, so results.json is
identical. ``dask``: a ``LocalCluster`` of ``workers`` single-threaded worker processes, or an
existing cluster at ``scheduler`` (``tcp://host:8786``; its workers need rollingstar installed).

Local cluster choices (measured with ``rollingstar compare configs/compare/rate_sweep.yaml``, see
docs/comparison.md "Scaling"): processes, not threads (the tasks are many small numpy calls: the
GIL would serialise threads); one thread per worker; the housekeeping timers slowed
(``LOCAL_CLUSTER_CONFIG``); glibc's default memory trimming (``WORKER_ENVIRON``: dask's default environment disabled glibc's
adaptive mmap threshold, which cost a third more CPU per image-level task).
The fixed costs are the cluster start (~1-3 s: a scheduler and, per worker, a nanny and a fresh
interpreter) and each worker's first task importing the project (~0.5 s CPU); per task, dask adds
only the task's (small, plain-data) arguments and result. Workers are started by ``spawn`` (dask's
default): ``fork`` saved 0.8-1.1 s on configs/compare/ci.yaml (benchmarks/compare_overheads.py --only start) because the
children inherit the parent's imports, but forking a process that already runs threads (dask's
event loop, the progress bar) can deadlock on a lock held at the fork; not worth 1 s.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

from rollingstar.errors import UserError

# The worker processes' environment. dask's default also sets MALLOC_TRIM_THRESHOLD_=65536, which
# turns off glibc's adaptive mmap threshold: every large temporary array (image-level frames) is
# then mmap'ed and unmapped, and its pages faulted in and zeroed again on each allocation -- measured
# +33% CPU per task, most of it system time, on configs/compare/he2021a_sweep.yaml. The tasks free
# what they allocate, so nothing is gained by trimming; the one-thread BLAS settings stay.
WORKER_ENVIRON = {"OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1, "OPENBLAS_NUM_THREADS": 1}

# dask's housekeeping timers, which run in every process of a local cluster (the scheduler and the
# two nannies share this process's event loop; each worker has its own) on the same cores as the
# tasks. On 16 image-level tasks (benchmarks/compare_overheads.py --only housekeeping), with the
# defaults each worker's tasks lost 1.0-1.6 s of wall time to other threads (task wall - task CPU)
# and this process used 0.8-1.0 CPU s; with these, 0.2-0.4 s and 0.25 s, and the executor's wall
# time fell from 21.7-23.2 s to 20.1-20.7 s. None of them changes what runs or where.
LOCAL_CLUSTER_CONFIG = {
    # the statistical profiler samples every worker's stack every 10 ms for the dashboard (off here)
    "distributed.worker.profile.enabled": False,
    # the event-loop health check wakes every loop every 20 ms only to warn when one was blocked > 3 s
    "distributed.admin.tick.interval": "1s",
    # CPU / memory / network time series for the dashboard, every 500 ms by default
    "distributed.admin.system-monitor.interval": "2s",
    # RSS polled every 100 ms by each worker and nanny; spill / pause / terminate still act, <= 1 s later
    "distributed.worker.memory.monitor-interval": "1s",
    # the nannies hand this environment to their worker processes
    "distributed.nanny.pre-spawn-environ": WORKER_ENVIRON,
}


def run_serial(fn: Callable, tasks: Sequence, on_done: Callable[[object], None]) -> list:
    """``fn`` over ``tasks`` in order; ``on_done(result)`` as each one completes."""
    out = []
    for task in tasks:
        out.append(fn(task))
        on_done(out[-1])
    return out


def run_dask(fn: Callable, tasks: Sequence, on_done: Callable[[object], None], workers: int = 2,
             scheduler: str | None = None) -> list:
    try:
        import dask
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError as exc:  # pragma: no cover - dask is a dependency
        raise UserError(f"--executor dask needs dask[distributed]: {exc}") from None
    cluster = None
    try:
        if scheduler:
            try:
                client = Client(scheduler, timeout="10s")
            except (OSError, TimeoutError) as exc:
                raise UserError(f"--scheduler {scheduler}: cannot connect to a dask scheduler: {exc}") from None
        else:
            # the nannies hand the config to their worker processes
            with dask.config.set(LOCAL_CLUSTER_CONFIG):
                cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                       dashboard_address=None, silence_logs=40)
            client = Client(cluster)
        with client:
            futures = client.map(fn, list(tasks), pure=False)
            position = {f.key: k for k, f in enumerate(futures)}
            out: list = [None] * len(futures)
            for future in as_completed(futures):
                out[position[future.key]] = future.result()
                on_done(out[position[future.key]])
            return out
    finally:
        if cluster is not None:
            cluster.close()


def executor_profile(task_results: list[dict], wall_s: float) -> dict:
    """Where the wall time went: the tasks' own CPU time (``task.cpu_s``: simulate, run, evaluate),
    summed and per process, and the CPU-bound estimate of the speed-up over one process,
    ``sum / busiest process`` -- what the executor would reach with a free core per worker and no
    fixed costs. A supplement to the measured wall time, never a substitute: on a shared machine
    the wall time also shows the other load (``load_average``)."""
    per_process: dict[int, float] = {}
    for r in task_results:
        t = r.get("task")
        if t:
            per_process[t["process"]] = per_process.get(t["process"], 0.0) + t["cpu_s"]
    total = sum(per_process.values())
    busiest = max(per_process.values(), default=0.0)
    return {"task_cpu_s": total, "processes": len(per_process), "busiest_process_cpu_s": busiest,
            "cpu_bound_speedup": total / busiest if busiest > 0 else None,
            "wall_over_task_cpu": wall_s / total if total > 0 else None}


def execute(fn: Callable, tasks: Sequence, on_done: Callable[[object], None], executor: str = "serial",
            workers: int = 1, scheduler: str | None = None) -> list:
    """Results of ``fn`` over ``tasks``, in task order; ``on_done(result)`` is called in this process as
    each task completes (in completion order), so finished work can be kept before the rest ends."""
    if executor not in ("serial", "dask"):
        raise UserError(f"--executor: unknown executor {executor!r}; expected serial or dask")
    if not tasks:
        return []
    if executor == "serial":
        return run_serial(fn, tasks, on_done)
    return run_dask(fn, tasks, on_done, workers, scheduler)
