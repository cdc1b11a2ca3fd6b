"""One vocabulary of frame outcomes (run and evaluate agree), evaluate's start-up skip, its reasons for
every n/a, the rate-unknown attitude bound, the evaluation plots and the demo."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rollingstar.errors import UserError
from rollingstar.logs.reader import LogReader
from rollingstar.pipelines.config import PipelineConfig
from rollingstar.pipelines.evaluate import evaluate_log
from rollingstar.pipelines.outcomes import NO_ESTIMATE, Outcomes, reason_key
from rollingstar.pipelines.plots import CELLS, _cell_means, evaluation_plots
from rollingstar.pipelines.runner import run_pipeline
from rollingstar.pipelines.truth import attitude_crb_rad2, joint_crb_rad2
from rollingstar.sensors.camera import PinholeCamera
from tests.pipelines.test_runner_bad_input import _copy_with_edits

ROOT = Path(__file__).resolve().parents[2]
PIPELINE = PipelineConfig(stages=[{"kind": "tracking"}, {"kind": "none"}, {"kind": "quest"}])
PNG = b"\x89PNG\r\n\x1a\n"


def test_reasons_group_by_kind_not_by_their_numbers():
    assert reason_key("saturated_stars:7") == reason_key("saturated_stars:12") == "saturated_stars"
    assert reason_key("fewer than 2 identified stars with finite positions (1)") == \
        "fewer than 2 identified stars with finite positions"
    assert reason_key("identification_rejected:3.1e-05") == "identification_rejected"
    # a named kind after the colon is the reason itself, and is kept; its values are not
    assert reason_key("lost_in_space_rejected:mirrored_image") == "lost_in_space_rejected:mirrored_image"
    assert reason_key("lost_in_space_rejected:residual(2.68px>2.00px)") == "lost_in_space_rejected:residual"
    assert reason_key("pixel_step_skipped:model_misfit(6 of 15 stars explained)") == "pixel_step_skipped:model_misfit"
    assert reason_key("identification_rejected:false_match_probability(2.0e-03>1e-09)") == \
        "identification_rejected:false_match_probability"
    # a sentence or a value after the colon is not a kind
    assert reason_key("provisional: fewer than 2 identified stars or collinear") == "provisional"
    assert reason_key("covariance_scaled:inf") == reason_key("covariance_scaled:nan") == "covariance_scaled"
    assert reason_key("time_gap:120ms") == "time_gap"
    o = Outcomes()
    o.add(["saturated_stars:3", "edge_truncated_stars:1"], [(True, "")])
    o.add(["saturated_stars:9"], [(False, "too few stars (1)")])
    o.add([], [])
    assert (o.frames, o.valid, o.invalid, o.flagged) == (3, 1, 2, 2)
    assert o.flag_reasons == {"saturated_stars": 2, "edge_truncated_stars": 1}
    assert o.invalid_reasons == {"too few stars": 1, NO_ESTIMATE: 1}
    assert Outcomes.from_dict(o.as_dict()) == o
    assert o.sentence() == ("3 frames: 1 valid, 2 invalid (no attitude estimate 1, too few stars 1); "
                            "2 flagged (saturated_stars 2, edge_truncated_stars 1); 1/2 attitude estimates valid")


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(st.lists(st.sampled_from(["a:1", "b", "c:2"]), max_size=3),
                          st.lists(st.tuples(st.booleans(), st.sampled_from(["", "r (1)", "s:2"])), max_size=3)),
                max_size=12))
def test_every_frame_is_valid_or_invalid_and_counts_add_up(frames):
    o = Outcomes()
    for flags, atts in frames:
        o.add(flags, atts)
    assert o.valid + o.invalid == o.frames == len(frames)
    assert sum(o.invalid_reasons.values()) == o.invalid
    assert o.flagged == sum(1 for flags, _ in frames if flags) <= sum(o.flag_reasons.values())
    assert o.valid_estimates == sum(v for _, atts in frames for v, _ in atts)


@pytest.fixture(scope="module")
def run_with_a_bad_frame(tmp_path_factory, small_recording):
    """The baseline over the small recording with frame 5 cut to one star: invalid and flagged."""
    tmp = tmp_path_factory.mktemp("outcomes")

    def one_star_in_frame_5(d):
        return d if d["frame"] != 5 else {k: (v[:1] if isinstance(v, list) else v) for k, v in d.items()}

    rec = tmp / "sparse.mcap"
    _copy_with_edits(small_recording, rec, one_star_in_frame_5)
    out = tmp / "out.mcap"
    return run_pipeline(rec, PIPELINE, out, show_progress=False), out


def test_run_and_evaluate_report_the_same_outcomes(run_with_a_bad_frame):
    summary, out = run_with_a_bad_frame
    m = evaluate_log(out)
    assert summary.outcomes.as_dict() == m["outcomes"]
    o = m["outcomes"]
    assert (o["frames"], o["valid_frames"], o["invalid_frames"]) == (20, 19, 1)
    assert sum(o["invalid_reasons"].values()) == 1 and o["flagged_frames"] >= 1
    proc = subprocess.run([sys.executable, "-m", "rollingstar.cli", "evaluate", str(out)], capture_output=True,
                          text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert summary.outcomes.sentence() in proc.stdout.replace("\n", " ") or "19 valid, 1 invalid" in proc.stdout
    assert "camera z: the boresight" in proc.stdout  # the axes are named


def test_skip_first_leaves_the_start_out_of_every_metric(run_with_a_bad_frame):
    _, out = run_with_a_bad_frame
    full = evaluate_log(out)
    later = evaluate_log(out, skip_first=6)  # past the bad frame 5
    assert later["frames"] == 14 and later["skipped_frames"] == 6
    assert later["outcomes"]["invalid_frames"] == 0 and later["attitude_updates"] == 14
    assert full["outcomes"]["invalid_frames"] == 1
    period_s = 0.100176  # he2021b's frame period
    by_time = evaluate_log(out, skip_first_s=5.5 * period_s)  # frames 0-5 start before 5.5 periods
    assert by_time["frames"] == 14
    assert by_time["attitude_error_arcsec"] == later["attitude_error_arcsec"]


def _missing(m: dict) -> set[str]:
    """Metrics that are null, or dicts whose every value is null."""
    skip = {"notes", "axes", "outcomes", "series"}
    return {k for k, v in m.items() if k not in skip and (v is None or (isinstance(v, dict) and v
                                                                            and all(x is None for x in v.values())))}


def test_every_missing_metric_says_why(small_output):
    m = evaluate_log(small_output)
    assert _missing(m) <= set(m["notes"]), _missing(m) - set(m["notes"])
    for key in ("pixel_crb_arcsec", "efficiency_pixel", "rate_error_deg_s"):
        assert key in m["notes"] and m["notes"][key]
    assert "centroid-level" in m["notes"]["pixel_crb_arcsec"]
    assert "attitude_error_arcsec" not in m["notes"]  # present: no reason given
    # a log without truth (a real recording): every error and bound says so
    reader = LogReader(small_output)
    no_truth = small_output.with_name("no_truth.mcap")
    from rollingstar.logs.records import TOPIC_RECORDS
    from rollingstar.logs.writer import LogWriter

    with LogWriter(no_truth, kind="run", metadata={k: v for k, v in reader.metadata().items() if k != "rollingstar"}) \
            as w:
        for msg in reader.messages():
            if msg.topic in TOPIC_RECORDS and not msg.topic.startswith("/truth"):
                w.write_json(msg.topic, msg.data, msg.log_time_ns)
    m = evaluate_log(no_truth)
    assert _missing(m) <= set(m["notes"]), _missing(m) - set(m["notes"])
    assert m["attitude_error_arcsec"]["x_rmse"] is None
    assert "truth" in m["notes"]["attitude_error_arcsec"] and "truth" in m["notes"]["attitude_crb_arcsec"]


def test_the_attitude_bound_with_the_rate_unknown_is_never_below_the_rate_known_one():
    """Marginalising the rate can only lose information: joint attitude block - rate-known bound is
    positive semi-definite, with equality when the stars share one time."""
    rng = np.random.default_rng(3)
    cam = PinholeCamera(focal_length_m=0.02409, pixel_size_m=5.5e-6, width=1024, height=1024)
    for _ in range(20):
        x, y = rng.uniform(0, 1023, 12), rng.uniform(0, 1023, 12)
        w = cam.unproject(x, y)
        known = attitude_crb_rad2(cam, w, 0.05)
        dt = (y - 511.5) * 49e-6
        joint = joint_crb_rad2(cam, w, dt, 0.05)[:3, :3]
        assert np.linalg.eigvalsh(joint - known).min() > -1e-9 * np.abs(known).max()
        same_time = joint_crb_rad2(cam, w, np.zeros(12), 0.05)[:3, :3]  # no rate information: pinv drops it
        np.testing.assert_allclose(same_time, known, rtol=1e-6)


def test_cell_means_of_a_constant_offset_are_that_offset():
    rng = np.random.default_rng(1)
    x, y = rng.uniform(0, 1024, 500), rng.uniform(0, 1024, 500)
    cx, cy, mx, my, n = _cell_means(x, y, np.full(500, 0.3), np.full(500, -0.1), (1024, 1024))
    np.testing.assert_allclose(mx, 0.3)
    np.testing.assert_allclose(my, -0.1)
    assert n.sum() == 500 and len(n) <= CELLS * CELLS
    assert np.all((cx >= 0) & (cx < 1024) & (cy >= 0) & (cy < 1024))


def test_evaluate_plots_writes_each_figure_it_has_data_for(tmp_path, small_recording):
    from rollingstar.pipelines.config import load_pipeline

    out = tmp_path / "ls.mcap"
    run_pipeline(small_recording, load_pipeline(ROOT / "configs" / "pipelines" / "ls_rate.yaml"), out,
                 show_progress=False)
    m = evaluate_log(out, series=True)
    written = evaluation_plots(m, tmp_path / "plots", (1024, 1024), inputs=[out])
    assert sorted(p.name for p in written) == ["attitude_error.png", "centroid_residuals.png", "rate_error.png"]
    assert all(p.read_bytes()[:8] == PNG for p in written)
    assert len(m["series"]["attitude_t_s"]) == m["attitude_updates"]
    with pytest.raises(UserError, match="input"):  # a figure that would replace an input is refused
        evaluation_plots(m, tmp_path / "plots", (1024, 1024), inputs=[tmp_path / "plots" / "attitude_error.png"])


def test_demo_shows_what_the_rolling_shutter_costs_and_writes_its_plot(tmp_path):
    from typer.testing import CliRunner

    from rollingstar.cli import app

    res = CliRunner().invoke(app, ["demo", "--frames", "40", "-q", "-o", str(tmp_path / "demo")])
    assert res.exit_code == 0, res.output
    text = res.output
    for needle in ("What you are looking at", "bound, rate unknown", "baseline / rs-bundle", "next"):
        assert needle in text, needle
    for name in ("recording.mcap", "baseline.mcap", "rs-bundle.mcap"):
        assert (tmp_path / "demo" / name).is_file()
    assert (tmp_path / "demo" / "attitude_error.png").read_bytes()[:8] == PNG
    base, rs = (evaluate_log(tmp_path / "demo" / f"{n}.mcap") for n in ("baseline", "rs-bundle"))
    # the roll error the rolling shutter causes: the bundle removes most of it and reaches the bound
    assert base["attitude_error_arcsec"]["z_rmse"] > 1.5 * rs["attitude_error_arcsec"]["z_rmse"]
    assert rs["attitude_error_arcsec"]["z_rmse"] < 1.5 * rs["attitude_crb_rate_unknown_arcsec"]["z"]
    row = next(line for line in text.splitlines() if line.lstrip("│ ").startswith("z (roll"))
    assert f"{base['attitude_error_arcsec']['z_rmse']:.3g}" in row  # the table prints what evaluate measures
    json.dumps(base)  # the metrics stay JSON


def test_a_flag_on_most_frames_brings_its_hint():
    """A run whose lost-in-space rejected most frames as mirror images says what to do (the camera
    file's ``mirrored``); the same flag on a minority of frames, or a flag without advice, says nothing."""
    from rollingstar.pipelines.outcomes import HINTS

    o = Outcomes()
    for k in range(10):
        o.add(["lost_in_space_rejected:mirrored_image", "too_few_stars"] if k < 6 else [], [(k >= 6, "no stars")])
    assert o.hints() == [HINTS["lost_in_space_rejected:mirrored_image"]]
    assert "mirrored: true" in o.hints()[0]
    few = Outcomes()
    for k in range(10):
        few.add(["lost_in_space_rejected:mirrored_image"] if k < 5 else ["saturated_stars:3"], [(True, "")])
    assert few.hints() == []
