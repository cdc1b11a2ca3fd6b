"""``rollingstar compare``: scenarios x pipelines x seeds, run serially or on dask, aggregated and gated.

One module per job: :mod:`.config` (the comparison config and its expansion into tasks),
:mod:`.tasks` (one task: simulate once -> run and evaluate each pipeline), :mod:`.execute` (serial / dask executors),
:mod:`.aggregate` (results.json), :mod:`.report` (results.md, report.html, PNGs),
:mod:`.regression` (the baseline gate), :mod:`.run` (the command's orchestration).
"""
from rollingstar.pipelines.compare.run import run_compare

__all__ = ["run_compare"]
