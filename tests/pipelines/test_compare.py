"""rollingstar compare: config expansion and errors, serial == dask, the numbers are evaluate's, the gate."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from rollingstar.errors import ConfigError
from rollingstar.pipelines.compare import run_compare
from rollingstar.pipelines.compare.aggregate import deterministic_view
from rollingstar.pipelines.compare.config import Tolerance, load_compare
from rollingstar.pipelines.compare.regression import compare_to_baseline
from rollingstar.pipelines.config import load_pipeline
from rollingstar.pipelines.evaluate import evaluate_log
from rollingstar.pipelines.runner import run_pipeline
from rollingstar.pipelines.simulate import simulate_to_log
from rollingstar.sensors.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"

TINY = f"""
name: tiny
monte_carlo: 2
seed: 3
frames: 3
pipelines:
  - {CONFIGS}/pipelines/baseline.yaml
  - {{path: {CONFIGS}/pipelines/ls_rate.yaml, name: ls}}
scenarios:
  - path: {CONFIGS}/scenarios/fu2022.yaml
    sweep: {{motion.rate_deg_s: [[0.5, 0.5, 0.0], [1.0, 0.0, 2.0]]}}
  - path: {CONFIGS}/scenarios/he2021b.yaml
    pipelines: [ls]
tolerances:
  "attitude_error_arcsec.*": {{rel: 0.10}}
  "attitude_error_arcsec.x_rmse": {{rel: 0.01}}
"""


def cli(*args):
    """The command in-process (typer's runner): exit code, stdout, stderr."""
    from typer.testing import CliRunner

    from rollingstar.cli import app

    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("compare")
    (d / "tiny.yaml").write_text(TINY)
    return d / "tiny.yaml"


@pytest.fixture(scope="module")
def serial(tiny, tmp_path_factory):
    return run_compare(tiny, tmp_path_factory.mktemp("serial"), executor="serial", show_progress=False)


def test_expansion_product_of_sweeps_and_subsets(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(TINY.replace("sweep: {motion.rate_deg_s:", "sweep: {noise.centroid_sigma_px: [0.01, 0.03], motion.rate_deg_s:"))
    comp = load_compare(cfg)
    labels = [v.label for v in comp.variants]
    assert len(labels) == 2 * 2 + 1 and len(set(labels)) == 5
    v = comp.variants[3]
    assert v.params == {"noise.centroid_sigma_px": 0.03, "motion.rate_deg_s": [1.0, 0.0, 2.0]}
    assert v.config.noise.centroid_sigma_px == 0.03 and v.config.motion.rate_deg_s == (1.0, 0.0, 2.0)
    assert v.config.frames == 3 and v.config.sensor.focal_length_mm == 42.0  # the rest is the file's
    tasks = comp.tasks()  # one per (variant, seed); each runs the variant's pipelines on one simulation
    assert len(tasks) == (4 + 1) * 2 and [t.index for t in tasks] == list(range(len(tasks)))
    assert {tuple(name for name, _ in t.pipelines) for t in tasks if t.variant.startswith("he2021b")} == {("ls",)}
    assert {tuple(name for name, _ in t.pipelines) for t in tasks if t.variant.startswith("fu2022")} == {("baseline", "ls")}
    assert [(t.variant, t.seed) for t in tasks][:2] == [(labels[0], 3), (labels[0], 4)]
    assert sum(len(t.pipelines) for t in tasks) == (4 * 2 + 1) * 2


@pytest.mark.parametrize("edit, needles", [
    (("monte_carlo: 2", "monte_carlo: 2\nmonte_carlos: 3"), ["monte_carlos", "unknown key"]),
    (("scenarios/he2021b.yaml", "scenarios/nope.yaml"), ["scenarios[1].path", "file not found", "nope.yaml"]),
    (("pipelines: [ls]", "pipelines: [lss]"), ["scenarios[1].pipelines[0]", "lss", "ls"]),
    (("[1.0, 0.0, 2.0]", "[1.0, fast, 2.0]"), ["scenarios[0].sweep", "motion.rate_deg_s[1]"]),
    (("motion.rate_deg_s:", "motion.rate_dps:"), ["scenarios[0].sweep", "motion.rate_dps", "unknown key"]),
])
def test_config_errors_name_file_and_key(tmp_path, edit, needles):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(TINY.replace(*edit))
    with pytest.raises(ConfigError) as exc:
        load_compare(cfg)
    for needle in [str(cfg), *needles]:
        assert needle in str(exc.value), (needle, str(exc.value))


def test_numbers_are_evaluate_log_of_the_same_simulation(serial, tmp_path):
    """One row's per-seed metric equals an independent simulate -> run -> evaluate with that seed."""
    row = next(r for r in serial.results["results"] if r["pipeline"] == "ls" and r["variant"].startswith("fu2022[") and "(1, 0, 2)" in r["variant"])
    base = load_scenario(CONFIGS / "scenarios" / "fu2022.yaml")
    cfg = base.model_copy(update={"motion": base.motion.model_copy(update={"rate_deg_s": (1.0, 0.0, 2.0)})})
    # compare tasks run with single-threaded BLAS (as the CLI does): multi-threaded BLAS may sum in
    # another order and change the last digits, so the independent run uses the same setting
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        simulate_to_log(cfg, tmp_path / "r.mcap", frames=3, seed=4, show_progress=False)
        run_pipeline(tmp_path / "r.mcap", load_pipeline(CONFIGS / "pipelines" / "ls_rate.yaml"), tmp_path / "o.mcap",
                     show_progress=False)
        m = evaluate_log(tmp_path / "o.mcap")
    seed4 = next(s for s in row["per_seed"] if s["seed"] == 4)["metrics"]
    assert seed4["rate_error_deg_s.z_rmse"] == m["rate_error_deg_s"]["z_rmse"]
    assert seed4["attitude_error_arcsec.x_rmse"] == m["attitude_error_arcsec"]["x_rmse"]
    vals = [s["metrics"]["attitude_error_arcsec.x_rmse"] for s in row["per_seed"]]
    stats = row["metrics"]["attitude_error_arcsec.x_rmse"]
    assert stats["mean"] == pytest.approx(np.mean(vals)) and stats["std"] == pytest.approx(np.std(vals, ddof=1))
    assert row["timing"]["cpu_s_per_frame"]["n"] == 2 and row["timing"]["cpu_s_per_frame"]["mean"] > 0
    out = serial.output
    assert (out / "results.md").is_file() and (out / "report.html").is_file()
    assert (out / "img" / "error_vs_rate_fu2022.png").stat().st_size > 10_000
    assert "error_vs_rate_fu2022.png" in (out / "report.html").read_text()


def test_dask_gives_identical_results(serial, tiny, tmp_path):
    dask = run_compare(tiny, tmp_path, executor="dask", workers=2, show_progress=False)
    assert dask.results["run"]["executor"] == "dask"
    assert deterministic_view(dask.results) == deterministic_view(serial.results)
    # the work was shared by both worker processes (none of them this one); serial ran here
    prof, sprof = dask.results["run"]["profile"], serial.results["run"]["profile"]
    assert prof["processes"] == 2 and sprof["processes"] == 1
    assert 1.0 < prof["cpu_bound_speedup"] <= 2.0 and sprof["cpu_bound_speedup"] == 1.0
    assert json.loads((tmp_path / "results.json").read_text())["results"][0]["metrics"] == serial.results["results"][0]["metrics"]


def test_gate_names_every_worse_metric(serial):
    res = serial.results
    tol = load_compare_tolerances()
    assert compare_to_baseline(res, res, tol) == []
    doctored = copy.deepcopy(res)
    rows = {(r["variant"], r["pipeline"]): r for r in doctored["results"]}
    ls = rows[("he2021b", "ls")]
    x = ls["metrics"]["attitude_error_arcsec.x_rmse"]["mean"]
    ls["metrics"]["attitude_error_arcsec.x_rmse"]["mean"] = x / 1.02  # now 2 % worse: beyond rel 0.01
    y = ls["metrics"]["attitude_error_arcsec.y_rmse"]["mean"]
    ls["metrics"]["attitude_error_arcsec.y_rmse"]["mean"] = y / 1.02  # 2 % worse: within rel 0.10
    ls["metrics"]["rate_error_deg_s.z_rmse"]["mean"] *= 0.5  # 100 % worse (default rel 0.02)
    ls["metrics"]["attitude_updates"]["mean"] += 1  # fewer updates now
    ls["metrics"]["efficiency.attitude_x"]["mean"] *= 0.5  # not gated
    better = rows[next(k for k in rows if k[1] == "baseline")]
    better["metrics"]["attitude_error_arcsec.z_rmse"]["mean"] *= 2.0  # we are better now: not a regression
    doctored["results"].append({**ls, "variant": "gone", "metrics": {}})
    worse = compare_to_baseline(res, doctored, tol)
    text = "\n".join(worse)
    assert len(worse) == 4, text
    for needle in ("attitude_error_arcsec.x_rmse", "rate_error_deg_s.z_rmse", "attitude_updates", "gone: missing"):
        assert needle in text, (needle, text)
    assert not any("y_rmse" in w or "efficiency" in w or w.startswith("baseline on") for w in worse), text


def load_compare_tolerances():
    return {"attitude_error_arcsec.*": Tolerance(rel=0.10), "attitude_error_arcsec.x_rmse": Tolerance(rel=0.01)}


def test_cli_gate_exit_codes(tmp_path):
    """The command: exit 0 against its own numbers, 1 naming the metric against a doctored baseline, 2 on misuse."""
    micro = tmp_path / "micro.yaml"
    micro.write_text(f"name: micro\nframes: 3\npipelines: [{CONFIGS}/pipelines/ls_rate.yaml]\n"
                     f"scenarios: [{{path: {CONFIGS}/scenarios/fu2022.yaml}}]\n")
    proc = cli("compare", micro, "-o", tmp_path / "out", "-q")
    assert proc.exit_code == 0, (proc.stdout, proc.stderr)
    good = json.loads((tmp_path / "out" / "results.json").read_text())
    good["results"][0]["metrics"]["attitude_error_arcsec.z_rmse"]["mean"] /= 1.5
    bad = tmp_path / "baseline.json"
    bad.write_text(json.dumps(good))
    proc = cli("compare", micro, "-o", tmp_path / "out2", "-q", "--baseline", bad, "--fail-on-regression")
    assert proc.exit_code == 1, (proc.stdout, proc.stderr)
    assert "ls_rate on fu2022: attitude_error_arcsec.z_rmse" in proc.stderr, proc.stderr
    # the same run against the first run's own results: deterministic, so no regression
    proc = cli("compare", micro, "-o", tmp_path / "out3", "-q", "--baseline", tmp_path / "out" / "results.json",
               "--fail-on-regression")
    assert proc.exit_code == 0 and "no gated metric worse" in proc.stdout, (proc.stdout, proc.stderr)
    proc = cli("compare", micro, "-o", tmp_path / "out4", "--fail-on-regression")
    assert proc.exit_code == 2 and "--baseline" in proc.stderr and "Traceback" not in proc.stderr


def test_executor_profile_known_answer():
    from rollingstar.pipelines.compare.execute import executor_profile

    tasks = [{"task": {"cpu_s": c, "wall_s": 2 * c, "process": p}} for c, p in [(1.0, 7), (2.0, 8), (3.0, 7), (0.5, 8)]]
    prof = executor_profile(tasks + [{"error": "stage failed"}], wall_s=13.0)
    assert prof["task_cpu_s"] == 6.5 and prof["processes"] == 2 and prof["busiest_process_cpu_s"] == 4.0
    assert prof["cpu_bound_speedup"] == 6.5 / 4.0 and prof["wall_over_task_cpu"] == 2.0


def test_task_simulates_once_and_keeps_each_pipelines_failure_to_its_row():
    """A task runs every pipeline of its variant on one simulation: a pipeline that fails gets an
    ``error`` in its own row while the others are evaluated; a scenario that cannot be simulated
    gives every row the simulation's error."""
    from rollingstar.config import to_yaml
    from rollingstar.pipelines.compare.config import Task
    from rollingstar.pipelines.compare.tasks import run_task

    scenario = to_yaml(load_scenario(CONFIGS / "scenarios" / "fu2022.yaml"))
    good = to_yaml(load_pipeline(CONFIGS / "pipelines" / "baseline.yaml"))
    broken = "name: broken\nstages:\n  - {kind: no_such_stage}\n"
    out = run_task(Task(7, "fu2022", 3, 3, scenario, (("baseline", good), ("broken", broken), ("again", good))))
    assert (out["index"], out["variant"], out["seed"]) == (7, "fu2022", 3)
    rows = out["rows"]
    assert [r["pipeline"] for r in rows] == ["baseline", "broken", "again"] and {r["seed"] for r in rows} == {3}
    assert "error" not in rows[0] and "no_such_stage" in rows[1]["error"] and "metrics" not in rows[1]
    assert rows[0]["metrics"] == rows[2]["metrics"]  # same recording, same deterministic pipeline
    assert out["task"]["cpu_s"] > 0

    unsimulatable = scenario.replace("width_px: ", "width_px: -")
    rows = run_task(Task(0, "bad", 3, 3, unsimulatable, (("baseline", good), ("again", good))))["rows"]
    assert all(r["error"].startswith("simulate: ") and "width_px" in r["error"] for r in rows)


def test_terminal_table_shows_the_main_columns_with_variant_labels_intact(serial):
    from rollingstar.pipelines.compare.report import TERMINAL_COLUMNS, terminal_tables

    tables = terminal_tables(serial.results)
    assert [t for t, _, _ in tables] == ["fu2022", "he2021b"]
    for _, header, body in tables:
        assert set(header) <= set(TERMINAL_COLUMNS) and header[:3] == ["variant", "pipeline", "valid (%)"]
        assert all(len(row) == len(header) for row in body)
    variants = [row[0] for row in tables[0][2]]
    assert "fu2022[motion.rate_deg_s=(0.5, 0.5, 0)]" in variants
    # baseline estimates no rate, but ls does: the rate column stays; every frame of these runs is valid
    assert all(row[2] == "100" for _, _, body in tables for row in body)


def test_valid_percent_counts_frames_not_estimates():
    from rollingstar.pipelines.compare.report import _valid_percent

    def row(**metrics):
        return {"metrics": {k.replace("__", "."): {"mean": v, "std": 0.0} for k, v in metrics.items()}}

    assert _valid_percent(row(outcomes__valid_frames=18, outcomes__frames=20, attitude_updates=700, frames=20)) == "90"
    assert _valid_percent(row(attitude_updates=700, frames=20)) == "100"  # per-star estimates: capped at every frame
    assert _valid_percent(row()) == "n/a"


def test_log_axis_draws_zero_and_near_zero_means_honestly():
    from rollingstar.pipelines.compare.report import _log_errorbar, _pyplot

    plt = _pyplot()
    fig, ax = plt.subplots()
    _log_errorbar(ax, np.array([1.0, 2.0, 3.0]), np.array([0.0, 1e-3, 2.0]), np.array([0.0, 5e-3, 0.5]), "C0", "p")
    ax.set_yscale("log")
    bars = [c for c in ax.containers]
    lines = bars[0].lines[2][0].get_segments()  # the error bars of the positive means
    lows = [seg[0][1] for seg in lines]
    assert all(low > 0 for low in lows)  # no bar reaches zero or below on the log axis
    assert any(t.get_text() == "0" for t in ax.texts)  # the zero mean is marked, not dropped
    plt.close(fig)


def test_html_report_leads_with_its_main_figure(serial):
    from rollingstar.pipelines.compare.report import html_report

    images = [("img/error_vs_rate_fu2022.png", "fu2022: error vs rate per axis"), ("img/cpu_time.png", "CPU")]
    page = html_report(serial.results, images, "rollingstar compare tiny")
    assert page.index("error_vs_rate_fu2022.png") < page.index("<table>") < page.index("cpu_time.png")


def test_flagged_percent_names_the_commonest_flags():
    from rollingstar.pipelines.compare.report import _flagged_percent

    means = {"outcomes.flagged_frames": 15.0, "outcomes.frames": 20.0, "outcomes.flag_reasons.saturated_stars": 15.0,
             "outcomes.flag_reasons.edge_truncated_stars": 4.5, "outcomes.flag_reasons.fragments": 1.0}
    row = {"metrics": {k: {"mean": v, "std": 0.0} for k, v in means.items()}}
    assert _flagged_percent(row) == "75 (saturated_stars 15, edge_truncated_stars 4.5, ...)"
    assert _flagged_percent({"metrics": {}}) == "n/a"


def test_a_seed_without_a_flag_counts_zero_in_the_flag_means():
    """A run writes a flag's count only when some frame carries it: the aggregate counts a seed
    that ran without it as zero (every seed in the mean), and a seed that failed not at all."""
    from types import SimpleNamespace

    from rollingstar.pipelines.compare.aggregate import aggregate

    variant = SimpleNamespace(label="v", pipelines=["p"], scenario="s", params={}, rate_deg_s=(0.0, 0.0, 0.0),
                              config=SimpleNamespace(frames=10))
    comp = SimpleNamespace(variants=[variant], source="x", pipeline_paths={"p": "p.yaml"},
                           config=SimpleNamespace(name="n", description="", seed_list=lambda: [1, 2, 3, 4], plot_x="rate"))
    runs = [{"variant": "v", "pipeline": "p", "seed": 1, "metrics": {"outcomes": {"flag_reasons": {"saturated_stars": 6}}}},
            {"variant": "v", "pipeline": "p", "seed": 2, "metrics": {"outcomes": {"flag_reasons": {}}}},
            {"variant": "v", "pipeline": "p", "seed": 3, "metrics": {"outcomes": {"flag_reasons": {"saturated_stars": 3}}}},
            {"variant": "v", "pipeline": "p", "seed": 4, "error": "simulation failed"}]
    row = aggregate(comp, runs, {})["results"][0]
    stats = row["metrics"]["outcomes.flag_reasons.saturated_stars"]
    assert stats["mean"] == 3.0 and stats["n"] == 3 and stats["min"] == 0.0


def test_evaluates_sentence_on_a_convention_reaches_the_comparison_report():
    """evaluate's ``truth_convention`` (a sentence, which the metric tables leave out) is kept on the
    comparison row of the seeds that said it and listed under Warnings in results.md; a row whose
    seeds said nothing has no warnings key."""
    from types import SimpleNamespace

    from rollingstar.pipelines.compare.aggregate import aggregate
    from rollingstar.pipelines.compare.report import markdown

    variants = [SimpleNamespace(label=v, pipelines=["p"], scenario="s", params={}, rate_deg_s=(0.0, 0.0, 0.0),
                                config=SimpleNamespace(frames=10)) for v in ("a", "b")]
    comp = SimpleNamespace(variants=variants, source="x", pipeline_paths={"p": "p.yaml"},
                           config=SimpleNamespace(name="n", description="", seed_list=lambda: [1, 2], plot_x="rate"))
    said = "the estimates miss /truth/attitude by 180 deg (median) but agree with it within 2 arcsec when it is read ..."
    runs = [{"variant": "a", "pipeline": "p", "seed": 1, "metrics": {"frames": 10, "truth_convention": said}},
            {"variant": "a", "pipeline": "p", "seed": 2, "metrics": {"frames": 10}},
            {"variant": "b", "pipeline": "p", "seed": 1, "metrics": {"frames": 10}}]
    results = aggregate(comp, runs, {})
    a, b = results["results"]
    assert a["warnings"] == [f"seed 1: {said}"] and "warnings" not in b
    assert "truth_convention" not in a["metrics"]  # not a number: not a metric column
    text = markdown(results, [], "rollingstar compare x")
    assert "## Warnings" in text and f"- p on a: seed 1: {said}" in text
