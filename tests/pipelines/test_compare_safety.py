"""compare keeps finished work, resumes to the same results, and checks its baseline before running."""
from __future__ import annotations

import json

import pytest

import rollingstar.pipelines.compare.run as run_module
from rollingstar.errors import UserError
from rollingstar.pipelines.compare import run_compare
from rollingstar.pipelines.compare.aggregate import deterministic_view
from rollingstar.pipelines.interrupt import Interrupted
from tests.pipelines.test_compare import TINY, cli


@pytest.fixture
def tiny(tmp_path):
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY)
    return path


def _counting(monkeypatch, stop_after: int | None = None) -> list:
    """Make run_task count its calls (and raise Ctrl-C on call ``stop_after + 1``)."""
    calls, real = [], run_module.run_task

    def task(t):
        if stop_after is not None and len(calls) == stop_after:
            raise KeyboardInterrupt
        calls.append(t.index)
        return real(t)

    monkeypatch.setattr(run_module, "run_task", task)
    return calls


def test_interrupted_compare_keeps_finished_tasks_and_resume_gives_the_same_results(tiny, tmp_path, monkeypatch):
    reference = run_compare(tiny, tmp_path / "ref", show_progress=False)
    out = tmp_path / "out"
    calls = _counting(monkeypatch, stop_after=4)
    with pytest.raises(Interrupted, match=r"4 of 6 task\(s\) finished.*--resume"):
        run_compare(tiny, out, show_progress=False)
    assert not out.exists()
    assert len(list((tmp_path / "out.partial" / "tasks").glob("*.json"))) == 4
    monkeypatch.undo()
    calls = _counting(monkeypatch)
    resumed = run_compare(tiny, out, show_progress=False, resume=True)
    assert resumed.resumed_tasks == 4 and len(calls) == 2
    assert deterministic_view(resumed.results) == deterministic_view(reference.results)
    assert len(list((out / "tasks").glob("*.json"))) == 6


@pytest.mark.filterwarnings("ignore::rollingstar.outputs.OverwriteWarning")
def test_a_changed_config_reruns_what_changed(tiny, tmp_path, monkeypatch):
    run_compare(tiny, tmp_path / "out", show_progress=False)
    tiny.write_text(TINY.replace("frames: 3", "frames: 4"))
    calls = _counting(monkeypatch)
    res = run_compare(tiny, tmp_path / "out", show_progress=False, resume=True)
    assert res.resumed_tasks == 0 and len(calls) == 6


def _baseline(tmp_path, content) -> str:
    path = tmp_path / "baseline.json"
    path.write_text(content if isinstance(content, str) else json.dumps(content))
    return str(path)


@pytest.mark.parametrize("content, needle", [
    ({"results": []}, "holds no results"),
    ("{not json", "not JSON"),
    ("[" * 100000 + "]" * 100000, "not JSON"),
    ({"results": [{"variant": "x"}]}, "results[0]: expected"),
    ({"results": [{"variant": "other[rate=1]", "pipeline": "quest", "metrics": {}}]}, "does not produce"),
])
def test_bad_baselines_are_errors_before_any_task_runs(tiny, tmp_path, monkeypatch, content, needle):
    calls = _counting(monkeypatch)
    res = cli("compare", tiny, "-o", tmp_path / "out", "-q", "--baseline", _baseline(tmp_path, content),
              "--fail-on-regression")
    assert res.exit_code == 2 and needle in res.output, res.output
    assert calls == [] and not (tmp_path / "out").exists()


def test_output_that_is_the_config_or_baseline_is_refused(tiny, tmp_path):
    with pytest.raises(UserError, match="destroy the input"):
        run_compare(tiny, tiny, show_progress=False)
