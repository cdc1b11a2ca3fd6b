"""``rollingstar compare``: load the config, run every task, write results.json / results.md / report.html.

The output folder is written through :func:`rollingstar.outputs.safe_output`: the previous folder
stays as it was until the new one is complete. Each task's result is saved in ``tasks/`` as soon as
it completes, so an interrupted or failed comparison keeps its finished tasks in
``<output>.partial/tasks/``; ``--resume`` runs only the tasks that are missing there (a task is
matched by a hash of everything it computes from, so a changed config re-runs what changed).
"""
from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from rollingstar.errors import UserError
from rollingstar.outputs import PARTIAL_SUFFIX, safe_output
from rollingstar.pipelines.compare.aggregate import aggregate
from rollingstar.pipelines.compare.config import Task, load_compare
from rollingstar.pipelines.compare.execute import execute, executor_profile
from rollingstar.pipelines.compare.regression import compare_to_baseline, load_baseline
from rollingstar.pipelines.compare.report import figures, html_report, markdown
from rollingstar.pipelines.compare.tasks import run_task
from rollingstar.pipelines.interrupt import Interrupted
from rollingstar.progress import progress_bar

TASKS_DIR = "tasks"


@dataclass
class CompareOutcome:
    results: dict
    output: Path
    regressions: list[str] = field(default_factory=list)
    baseline: str | None = None
    resumed_tasks: int = 0


def task_key(task: Task) -> str:
    """A hash of everything a task's result depends on (its position in the config excluded)."""
    content = {k: v for k, v in asdict(task).items() if k != "index"}
    return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()[:20]


def _previous_task_results(output: Path) -> dict[str, dict]:
    """Saved task results of an earlier run into ``output``: its partial folder, a folder a killed run
    left (``.<name>.tmp-<pid>``) or the finished folder, keyed by :func:`task_key`."""
    folders = [output.with_name(output.name + PARTIAL_SUFFIX), *output.parent.glob(f".{output.name}.tmp-*"), output]
    found = {}
    for folder in folders:
        for path in sorted((folder / TASKS_DIR).glob("*.json")) if (folder / TASKS_DIR).is_dir() else []:
            try:
                saved = json.loads(path.read_text())
                found.setdefault(saved["key"], saved["result"])
            except (ValueError, KeyError, TypeError, RecursionError):
                continue  # a file cut short by a kill: that task runs again
    return found


def _run_tasks(tasks: list[Task], folder: Path, previous: dict[str, dict], run: dict, show_progress: bool,
               label: str) -> list[dict]:
    """Every task's result, in task order: saved ones reused, the others run and saved as they complete."""
    (folder / TASKS_DIR).mkdir()
    keys = {t.index: task_key(t) for t in tasks}
    todo = [t for t in tasks if keys[t.index] not in previous]
    results = {t.index: {**previous[keys[t.index]], "index": t.index} for t in tasks if keys[t.index] in previous}

    def save(result: dict, advance=lambda n: None) -> None:
        path = folder / TASKS_DIR / f"task-{result['index']:05d}.json"
        path.write_text(json.dumps({"key": keys[result["index"]], "result": result}) + "\n")
        results[result["index"]] = result
        advance(1)

    for result in results.values():
        save(result)
    with progress_bar(label, len(tasks), show_progress) as advance:
        advance(len(results))
        try:
            execute(run_task, todo, lambda r: save(r, advance), run["executor"], run["workers"], run["scheduler"])
        except KeyboardInterrupt:
            raise Interrupted(f"interrupted: {len(results)} of {len(tasks)} task(s) finished; they are kept in "
                              f"{run['output']}{PARTIAL_SUFFIX}/{TASKS_DIR}/ and `--resume` continues from them") from None
    return [results[t.index] for t in tasks]


def _write_reports(folder: Path, results: dict, command: str) -> None:
    (folder / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    images = figures(results, folder / "img")
    (folder / "results.md").write_text(markdown(results, images, command))
    (folder / "report.html").write_text(html_report(results, images, command))


def _executor(executor: str | None, workers: int, scheduler: str | None) -> str:
    if workers < 1:
        raise UserError(f"--workers must be >= 1 (got {workers})")
    executor = executor or ("dask" if workers > 1 or scheduler else "serial")
    if executor == "serial" and scheduler:
        raise UserError("--scheduler needs --executor dask")
    return executor


def run_compare(config: str | Path, output: str | Path, executor: str | None = None, workers: int = 1,
                scheduler: str | None = None, baseline: str | Path | None = None, show_progress: bool = True,
                command: str = "", resume: bool = False) -> CompareOutcome:
    """Run the comparison; ``executor`` None: dask when ``workers > 1`` or ``scheduler`` is given, else serial.

    The config and the baseline are checked before any task runs."""
    executor = _executor(executor, workers, scheduler)
    comp = load_compare(config)
    tasks = comp.tasks()
    base = load_baseline(baseline, tasks) if baseline is not None else None
    out = Path(output)
    previous = _previous_task_results(out) if resume else {}
    run = {"executor": executor, "workers": workers if not scheduler else None, "scheduler": scheduler, "output": out}
    with safe_output(out, [p for p in (config, baseline) if p is not None], directory=True) as folder:
        load_before = os.getloadavg()[0]
        start = time.perf_counter()
        task_results = _run_tasks(tasks, folder, previous, run, show_progress, f"compare {comp.config.name} ({executor})")
        wall = time.perf_counter() - start
        rows = [row for result in task_results for row in result["rows"]]
        run_info = {**{k: v for k, v in run.items() if k != "output"}, "tasks": len(tasks),
                    "pipeline_runs": len(rows), "wall_time_s": wall,
                    "load_average_1min": {"before": load_before, "after": os.getloadavg()[0]},
                    "profile": executor_profile(task_results, wall)}
        results = aggregate(comp, rows, run_info)
        _write_reports(folder, results, command or f"rollingstar compare {config} -o {output}")
    regressions = compare_to_baseline(results, base, comp.config.tolerances) if base is not None else []
    resumed = sum(task_key(t) in previous for t in tasks)
    return CompareOutcome(results, out, regressions, None if baseline is None else str(baseline), resumed)
