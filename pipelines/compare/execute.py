"""Executors: run every task serially in this process, or on dask.distributed.

Both return the task results in task order whatever the completion order, so results.json is
identical. ``dask``: a ``LocalCluster`` of ``workers`` single-threaded worker processes, or an
existing cluster at ``scheduler`` (``tcp://host:8786``; its workers need rollingstar installed).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

from pipelines.errors import UserError


def run_serial(fn: Callable, tasks: Sequence, advance: Callable[[int], None]) -> list:
    out = []
    for task in tasks:
        out.append(fn(task))
        advance(1)
    return out


def run_dask(fn: Callable, tasks: Sequence, advance: Callable[[int], None], workers: int = 2,
             scheduler: str | None = None) -> list:
    try:
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
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   dashboard_address=None, silence_logs=40)
            client = Client(cluster)
        with client:
            futures = client.map(fn, list(tasks), pure=False)
            position = {f.key: k for k, f in enumerate(futures)}
            out: list = [None] * len(futures)
            for future in as_completed(futures):
                out[position[future.key]] = future.result()
                advance(1)
            return out
    finally:
        if cluster is not None:
            cluster.close()


def execute(fn: Callable, tasks: Sequence, advance: Callable[[int], None], executor: str = "serial",
            workers: int = 1, scheduler: str | None = None) -> list:
    if executor == "serial":
        return run_serial(fn, tasks, advance)
    if executor == "dask":
        return run_dask(fn, tasks, advance, workers, scheduler)
    raise UserError(f"--executor: unknown executor {executor!r}; expected serial or dask")
