"""``rollingstar preview --layout`` on Foxglove layouts nobody here made: a layout that is not one,
or whose panels name the wrong kind of topic, is refused (exit 2) naming the file, the panel and
what was expected."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

ROOT = Path(__file__).resolve().parents[2]
LAYOUT = json.loads((ROOT / "configs" / "foxglove" / "run.json").read_text())


def preview(log: Path, layout: Path, tmp_path: Path) -> tuple[int, str]:
    """``rollingstar preview LOG -o p.png --layout LAYOUT`` in-process: (exit code, stderr on one line)."""
    from rollingstar.cli import app

    res = CliRunner().invoke(app, ["preview", str(log), "-o", str(tmp_path / "p.png"), "--layout", str(layout)])
    return res.exit_code, " ".join(res.stderr.split())


def with_panel(panel_id: str, config: dict) -> dict:
    return {**LAYOUT, "configById": {**LAYOUT["configById"], panel_id: config}}


CASES = {
    "not_json": ("{configById: ", ["not valid JSON (line 1, column 2"]),
    "a_list": ([], ["expected a JSON object (a Foxglove layout) at the top level, got list"]),
    "no_panels": ({"layout": "x"}, ["configById: Field required"]),
    "a_path_without_a_field": (with_panel("Plot!mine", {"paths": [{"value": "/estimate/attitude"}]}),
                               ["configById.Plot!mine.paths[0].value: String should match pattern"]),
    "an_image_panel_on_records": (with_panel("Image!rs-image", {"imageMode": {"imageTopic": "/estimate/attitude"}}),
                                  ["configById.Image!rs-image.imageMode.imageTopic: /estimate/attitude holds "
                                   "rollingstar.AttitudeEstimate messages, expected foxglove.RawImage"]),
    "a_pose_panel_on_records": (with_panel("3D!rs-pose", {"topics": {"/estimate/frame": {"visible": True}}}),
                                ["configById.3D!rs-pose.topics: /estimate/frame holds rollingstar.FrameStatus "
                                 "messages, expected foxglove.PoseInFrame"]),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_hostile_layout_is_refused_naming_file_and_panel(tmp_path, small_output, case):
    content, needles = CASES[case]
    layout = tmp_path / "layout.json"
    layout.write_text(content if isinstance(content, str) else json.dumps(content))
    code, err = preview(small_output, layout, tmp_path)
    assert code == 2, err
    assert "Traceback" not in err and "unexpected" not in err, err
    for needle in (str(layout), *needles):
        assert needle in err, (needle, err)
    assert not (tmp_path / "p.png").exists()


def test_the_shipped_layout_and_panels_preview_does_not_draw_are_accepted(tmp_path, small_output):
    layout = tmp_path / "layout.json"
    layout.write_text(json.dumps(with_panel("RawMessages!extra", {"topicPath": "/estimate/frame"})))
    code, err = preview(small_output, layout, tmp_path)
    assert code == 0, err
    assert (tmp_path / "p.png").is_file()


def test_an_output_that_is_an_input_is_refused_before_anything_is_drawn(tmp_path, small_output, monkeypatch):
    """``-o`` naming the log itself: refused (exit 2) with the log untouched, and no figure is
    drawn first (the drawing is the slow part)."""
    from rollingstar.cli import app
    from rollingstar.pipelines import preview as preview_module

    def no_drawing():
        raise AssertionError("the figure was drawn before the output was checked")

    monkeypatch.setattr(preview_module, "pyplot", no_drawing)
    before = small_output.read_bytes()
    res = CliRunner().invoke(app, ["preview", str(small_output), "-o", str(small_output)])
    assert res.exit_code == 2 and "Traceback" not in res.output and "the figure was drawn" not in res.output
    assert small_output.read_bytes() == before
