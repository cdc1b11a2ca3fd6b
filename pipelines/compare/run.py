"""``rollingstar compare``: load the config, run every task, write results.json / results.md / report.html."""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from rollingstar.errors import UserError
from rollingstar.pipelines.compare.aggregate import aggregate
from rollingstar.pipelines.compare.config import load_compare
from rollingstar.pipelines.compare.execute import execute, executor_profile
from rollingstar.pipelines.compare.regression import compare_to_baseline, load_baseline
from rollingstar.pipelines.compare.report import figures, html_report, markdown
from rollingstar.pipelines.compare.tasks import run_task
from rollingstar.progress import progress_bar


@dataclass
class CompareOutcome:
    results: dict
    output: Path
    regressions: list[str] = field(default_factory=list)
    baseline: str | None = None


def run_compare(config: str | Path, output: str | Path, executor: str | None = None, workers: int = 1,
                scheduler: str | None = None, baseline: str | Path | None = None, show_progress: bool = True,
                command: str = "") -> CompareOutcome:
    """Run the comparison; ``executor`` None: dask when ``workers > 1`` or ``scheduler`` is given, else serial."""
    if workers < 1:
        raise UserError(f"--workers must be >= 1 (got {workers})")
    executor = executor or ("dask" if workers > 1 or scheduler else "serial")
    if executor == "serial" and scheduler:
        raise UserError("--scheduler needs --executor dask")
    comp = load_compare(config)
    base = load_baseline(baseline) if baseline is not None else None  # fail before the long part
    tasks = comp.tasks()
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()[0]
    start = time.perf_counter()
    with progress_bar(f"compare {comp.config.name} ({executor})", len(tasks), show_progress) as advance:
        task_results = execute(run_task, tasks, advance, executor, workers, scheduler)
    wall = time.perf_counter() - start
    rows = [row for result in task_results for row in result["rows"]]
    run_info = {"executor": executor, "workers": workers if not scheduler else None, "scheduler": scheduler,
                "tasks": len(tasks), "pipeline_runs": len(rows), "wall_time_s": wall,
                "load_average_1min": {"before": load_before, "after": os.getloadavg()[0]},
                "profile": executor_profile(task_results, wall)}
    results = aggregate(comp, rows, run_info)
    command = command or f"rollingstar compare {config} -o {output}"
    (out / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    images = figures(results, out / "img")
    (out / "results.md").write_text(markdown(results, images, command))
    (out / "report.html").write_text(html_report(results, images, command))
    regressions = compare_to_baseline(results, base, comp.config.tolerances) if base is not None else []
    return CompareOutcome(results, out, regressions, None if baseline is None else str(baseline))
