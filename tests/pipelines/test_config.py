"""Config loading: strict validation with errors naming the file, key path and expectation."""
from pathlib import Path

import pytest

from rollingstar.config import parse_yaml, to_yaml, validate
from rollingstar.errors import ConfigError
from rollingstar.pipelines.config import load_pipeline
from rollingstar.pipelines.runner import build_stages
from rollingstar.sensors.scenario import ScenarioConfig, load_scenario

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@pytest.mark.parametrize("path", sorted((CONFIGS / "scenarios").glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_scenario_validates_and_round_trips(path):
    cfg = load_scenario(path)
    again = validate(ScenarioConfig, parse_yaml(to_yaml(cfg), "roundtrip"), "roundtrip")
    assert again == cfg


@pytest.mark.parametrize("path", sorted((CONFIGS / "pipelines").glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_pipeline_builds(path):
    stages = build_stages(load_pipeline(path), str(path))
    assert stages and all(s.role for s in stages)


def test_unknown_key_names_file_and_key_path(tmp_path):
    text = (CONFIGS / "scenarios" / "he2021b.yaml").read_text().replace("line_delay_us: 49.0", "line_delay_us: 49.0, line_dealy_us: 3")
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_scenario(p)
    assert str(p) in str(exc.value) and "shutter.line_dealy_us" in str(exc.value) and "unknown key" in str(exc.value)


def test_mistyped_value_names_key_path_and_expectation(tmp_path):
    text = (CONFIGS / "scenarios" / "he2021b.yaml").read_text().replace("rate_deg_s: [0.05, 0.0, 0.0]", "rate_deg_s: [0.05, fast, 0.0]")
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=r"motion\.rate_deg_s\[1\].*valid number"):
        load_scenario(p)


def test_out_of_range_value_rejected(tmp_path):
    text = (CONFIGS / "scenarios" / "he2021b.yaml").read_text().replace("exposure_ms: 50.0", "exposure_ms: -50.0")
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=r"shutter\.exposure_ms.*greater than 0"):
        load_scenario(p)


def test_nan_in_config_rejected(tmp_path):
    text = (CONFIGS / "scenarios" / "he2021b.yaml").read_text().replace("centroid_sigma_px: 0.05", "centroid_sigma_px: .nan")
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=r"noise\.centroid_sigma_px"):
        load_scenario(p)


def test_yaml_syntax_error_gives_line_number(tmp_path):
    p = tmp_path / "broken.yaml"
    p.write_text("name: x\nstages:\n  - {kind: quest\n  - {kind: none}\n")
    with pytest.raises(ConfigError, match=r"broken\.yaml: line \d+, column \d+: YAML syntax error"):
        load_pipeline(p)


def test_missing_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_pipeline(tmp_path / "nope.yaml")


def test_unknown_plugin_kind_lists_valid_kinds(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text("stages:\n  - {kind: quset}\n")
    with pytest.raises(ConfigError) as exc:
        build_stages(load_pipeline(p), str(p))
    msg = str(exc.value)
    assert "stages[0].kind" in msg and "'quset'" in msg and "quest" in msg and "tracking" in msg


def test_bad_plugin_param_names_stage_key_path(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text("stages:\n  - {kind: tracking, params: {gate_pix: 3}}\n")
    with pytest.raises(ConfigError, match=r"stages\[0\]\.params\.gate_pix: unknown key"):
        build_stages(load_pipeline(p), str(p))


def test_empty_pipeline_rejected(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text("stages: []\n")
    with pytest.raises(ConfigError, match="stages"):
        load_pipeline(p)


@pytest.mark.parametrize("shutter, needles", [
    ("{exposure_ms: 50, frame_period_ms: 40, line_delay_us: 10}", ["exposure_ms 50", "frame_period_ms 40"]),
    ("{exposure_ms: 20, frame_period_ms: 40, line_delay_us: 60}", ["line_delay_us 60", "height_px 1000", "59.94 ms"]),
])
def test_physically_impossible_timing_names_the_keys_and_numbers(tmp_path, shutter, needles):
    from rollingstar.sensors.scenario import load_scenario

    path = tmp_path / "s.yaml"
    path.write_text("sensor: {focal_length_mm: 20, pixel_size_um: 5, width_px: 100, height_px: 1000}\n"
                    f"shutter: {shutter}\nmotion: {{initial_attitude: {{ra_deg: 0, dec_deg: 0}}}}\n")
    with pytest.raises(ConfigError) as info:
        load_scenario(path)
    for needle in needles:
        assert needle in str(info.value)
    path.write_text(path.read_text().replace("frame_period_ms: 40", "frame_period_ms: 100"))
    load_scenario(path)  # the same sensor with a long enough frame period is fine


@pytest.mark.parametrize("edit, needle", [
    (("width_px: 1024", "width_px: 60000"), "image frame"),
    (("frames: 100", "frames: 100000001"), "less than or equal to 100000000"),
    (("exposure_ms: 44.9", "exposure_ms: 1e300"), "shutter.exposure_ms"),
    (("seed: 1", "seed: -1"), "seed"),
    (("seed: 1", "seed: 99999999999999999999999"), "seed"),
])
def test_sizes_a_scenario_asks_for_are_checked_before_anything_is_allocated(tmp_path, edit, needle):
    from rollingstar.sensors.scenario import load_scenario

    text = (CONFIGS / "scenarios" / "he2021a.yaml").read_text()
    assert edit[0] in text, edit
    path = tmp_path / "s.yaml"
    path.write_text(text.replace(edit[0], edit[1]).replace("height_px: 1024", "height_px: 60000"
                                                           if "60000" in edit[1] else "height_px: 1024"))
    with pytest.raises(ConfigError, match=needle):
        load_scenario(path)
