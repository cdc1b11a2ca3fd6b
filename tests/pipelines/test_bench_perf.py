"""``rollingstar bench perf --quick --json``: structure, ratio arithmetic and the equality checks.

No timing is asserted (performance targets live in the benchmark, not in tests); what is
asserted is that every line compares the same answers (QUEST vs scipy, batched KF vs filterpy,
windowed vs full-frame centroids, guide-table shot noise vs Generator.poisson, replayed frame counts) and
that the reported ratios and pass/fail follow from the reported numbers.
"""
from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from rollingstar.cli import app

pytestmark = [pytest.mark.slow, pytest.mark.long_study]  # every benchmark line, quick: `make test-long` runs it

EXPECTED = {"quest", "kf", "rate", "centroid_full", "centroid_windowed", "render", "render_speedup",
            "replay_centroid", "replay_image", "compare",
            "chain_high_dynamic_0_5", "chain_baseline_0_5", "chain_high_dynamic_10", "chain_baseline_10", "diagnose",
            "diagnose_outside"}


@pytest.fixture(scope="module")
def quick_result() -> dict:
    res = CliRunner().invoke(app, ["bench", "perf", "--quick", "--json"])
    assert res.exit_code == 0, res.output
    return json.loads(res.stdout)


def test_structure(quick_result):
    r = quick_result
    assert r["benchmark"] == "perf" and r["quick"] is True
    assert r["machine"]["cpu_count"] >= 1
    assert {ln["id"] for ln in r["lines"]} == EXPECTED
    for ln in r["lines"]:
        assert set(ln) >= {"id", "title", "status", "measured", "peer", "ratio", "ratio_kind", "target", "pass", "checks"}
        if ln["status"] != "measured":
            assert ln["ratio"] is None and ln["pass"] is None and ln["note"]
            continue
        m, p = ln["measured"]["value"], ln["peer"]["value"]
        assert m > 0 and p > 0
        expect = p / m if ln["ratio_kind"] == "speedup" else m / p
        assert ln["ratio"] == pytest.approx(expect, rel=1e-12)
        if ln["target"] is None:
            assert ln["pass"] is None
        else:
            op, value = ln["target"]["op"], ln["target"]["value"]
            assert ln["pass"] == (ln["ratio"] >= value if op == ">=" else ln["ratio"] <= value)


def test_same_answers(quick_result):
    """Every equality check holds: same attitudes, same KF states, same spots, same noise law."""
    lines = {ln["id"]: ln for ln in quick_result["lines"]}
    assert quick_result["checks_ok"]
    for ln in lines.values():
        for c in ln["checks"]:
            assert c["ok"] and c["value"] <= c["limit"], (ln["id"], c)
    quest = {c["name"]: c for c in lines["quest"]["checks"]}
    assert quest["max |QUEST - scipy| angle"]["value"] < 1e-3  # arcsec
    kf = lines["kf"]["checks"]
    assert len(kf) == 2 and all(c["limit"] == 1e-9 for c in kf)
    assert len(lines["render_speedup"]["checks"]) == 4  # mean and variance at two signal levels


def test_replay_lines(quick_result):
    lines = {ln["id"]: ln for ln in quick_result["lines"]}
    for level in ("centroid", "image"):
        ln = lines[f"replay_{level}"]
        assert ln["measured"]["unit"] == "MiB" and ln["frames_long"] > ln["frames_short"]
        assert ln["peak_alloc_ratio"] == pytest.approx(ln["ratio"])
        assert ln["fps"] > 0


def test_compare_line_not_invented(quick_result):
    line = next(ln for ln in quick_result["lines"] if ln["id"] == "compare")
    assert line["status"] == "not available" and "--quick" in line["note"]


def test_markdown_has_one_row_per_line(quick_result):
    """`--markdown` (the docs/performance.md table): a header, then one row per line in order."""
    from rollingstar.studies.bench.perf import format_markdown

    rows = [r for r in format_markdown(quick_result).splitlines() if r.startswith("| ") and not r.startswith("| line ")]
    assert len(rows) == len(quick_result["lines"])
    for row, ln in zip(rows, quick_result["lines"]):
        assert row.startswith(f"| {ln['title']} |") and row.replace("\\|", "").count("|") == 9


def test_compare_line_takes_the_faster_of_interleaved_runs(monkeypatch):
    """The compare line runs serial and dask alternately, quotes the faster run of each, and checks
    every run's results against the first serial one (a stand-in ``run_compare`` whose wall times
    are scripted: no dask cluster, no timing assertion)."""
    import rollingstar.studies.bench.perf as perf

    clock = iter([0.0, 10.0, 10.0, 16.0, 16.0, 25.0, 25.0, 30.0])  # serial 10, dask 6, serial 9, dask 5
    calls = []

    def fake_run_compare(config, output, executor, workers, show_progress):
        calls.append(executor)
        metric = 1.0 + (1e-3 if executor == "dask" and len(calls) == 4 else 0.0)  # last dask run differs
        results = {"run": {"executor": executor, "tasks": 3, "wall_time_s": 1.0,
                           "profile": {"task_cpu_s": 2.0, "busiest_process_cpu_s": 1.0, "cpu_bound_speedup": 2.0}},
                   "comparison": {"name": "fake"}, "results": [{"metrics": {"x": metric}, "timing": {"cpu_s": 1.0}}]}
        return type("Outcome", (), {"results": results})()

    monkeypatch.setattr(perf, "run_compare", fake_run_compare)
    monkeypatch.setattr(perf.time, "perf_counter", lambda: next(clock))
    line = perf.bench_compare(quick=False)
    assert calls == ["serial", "dask", "serial", "dask"]
    assert line["measured"]["value"] == 5.0 and line["peer"]["value"] == 9.0
    assert line["ratio"] == pytest.approx(9.0 / 5.0) and line["pass"] is True
    assert line["runs_s"] == {"serial": [10.0, 9.0], "dask": [6.0, 5.0]}
    rel = next(c for c in line["checks"] if "relative" in c["name"])
    assert rel["value"] == pytest.approx(1e-3 / 1.001) and rel["ok"] is False  # relative to the larger
