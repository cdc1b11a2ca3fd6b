"""YAML configs nobody here wrote: a wrong kind of value is refused (exit 2) naming the file and key.

YAML reads ``true``, ``yes`` and ``on`` as booleans, and a model that accepted them for numbers
would take them as 1 (a 1 mm lens, a one-pixel-wide detector) without a word.
"""
from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = (ROOT / "configs" / "scenarios" / "he2021b.yaml").read_text()
PIPELINE = ROOT / "configs" / "pipelines" / "baseline.yaml"
CAMERA = "width_px: 1280\nheight_px: 1024\nfocal_length_mm: 25.0\npixel_size_um: 5.3\n"


def cli(*args) -> tuple[int, str]:
    """``rollingstar ARGS`` in-process: (exit code, stderr on one line)."""
    from rollingstar.cli import app

    res = CliRunner().invoke(app, [str(a) for a in args])
    return res.exit_code, " ".join(res.stderr.split())


def assert_refused(result: tuple[int, str], *needles: str) -> None:
    code, err = result
    assert code == 2, (code, err)
    assert "Traceback" not in err and "unexpected" not in err, err
    for needle in needles:
        assert needle in err, (needle, err)


@pytest.mark.parametrize("old, new, key", [
    ("frames: 300", "frames: true", "frames"),
    ("exposure_ms: 50.0", "exposure_ms: yes", "shutter.exposure_ms"),
    ("rate_deg_s: [0.05, 0.0, 0.0]", "rate_deg_s: [on, 0.0, 0.0]", "motion.rate_deg_s"),
])
def test_a_boolean_for_a_scenario_number_is_refused(tmp_path, old, new, key):
    path = tmp_path / "s.yaml"
    path.write_text(SCENARIO.replace(old, new))
    assert_refused(cli("simulate", path, "-o", tmp_path / "r.mcap", "--frames", "2", "-q"),
                   f"s.yaml: {key}: expected a number, got a boolean")
    assert not (tmp_path / "r.mcap").exists()


@pytest.mark.parametrize("text, key", [
    (CAMERA.replace("25.0", "yes"), "focal_length_mm"),
    (CAMERA.replace("1280", "true"), "width_px"),
    (CAMERA + "shutter: {mode: rolling, exposure_ms: 10.0, line_delay_us: on}\n", "shutter.line_delay_us"),
])
def test_a_boolean_for_a_camera_number_is_refused(tmp_path, text, key):
    camera, table = tmp_path / "camera.yaml", tmp_path / "c.csv"
    camera.write_text(text)
    table.write_text("frame,t_ns,x,y,flux\n0,1000000000,100,40,5200\n1,1100000000,101,41,5000\n")
    assert_refused(cli("import", "centroids", table, "-o", tmp_path / "r.mcap", "--camera", camera),
                   f"camera.yaml: {key}: expected a number, got a boolean")


def test_a_set_key_the_scenario_lacks_names_the_comparison_file(tmp_path):
    path = tmp_path / "cmp.yaml"
    path.write_text(f"name: x\npipelines: [{PIPELINE}]\nscenarios:\n  - path: he2021b\n    set: {{nonexistent.key: 5}}\n")
    assert_refused(cli("compare", path, "-o", tmp_path / "out", "-q"),
                   "cmp.yaml: scenarios[0].set: 'nonexistent.key': no scenario section 'nonexistent'")


def test_a_folder_where_a_comparison_names_a_scenario_file_is_named_as_a_folder(tmp_path):
    (tmp_path / "scenario.yaml").mkdir()
    path = tmp_path / "cmp.yaml"
    path.write_text(f"name: x\npipelines: [{PIPELINE}]\nscenarios:\n  - path: scenario.yaml\n")
    assert_refused(cli("compare", path, "-o", tmp_path / "out", "-q"),
                   "cmp.yaml: scenarios[0].path:", "scenario.yaml is a folder, not a config file")


def test_a_config_of_another_kind_is_named_as_such(tmp_path, small_recording):
    """A scenario given where a pipeline is expected (and the other way round) is refused with its
    unknown keys and the kind its keys belong to, not only a list of unknown keys."""
    assert_refused(cli("run", ROOT / "configs" / "scenarios" / "he2021b.yaml", small_recording, "-o", tmp_path / "o.mcap"),
                   "its keys are those of a scenario config, not of a pipeline config")
    assert_refused(cli("simulate", PIPELINE, "-o", tmp_path / "r.mcap", "--frames", "2"),
                   "its keys are those of a pipeline config, not of a scenario config")
