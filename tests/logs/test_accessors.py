"""The topic names and the typed accessors of LogReader (scenario, stars, gyro, truth attitude)."""
import re
from pathlib import Path

import numpy as np
import pytest

from rollingstar.config import CONFIGS, to_yaml
from rollingstar.errors import ConfigError, UserError
from rollingstar.logs import LogReader, LogWriter, stars_to_arrays, topics
from rollingstar.logs.records import (
    attitude_samples_to_arrays,
    gyro_samples_to_arrays,
    join_attitude_samples,
    join_gyro_samples,
)
from rollingstar.sensors.scenario import load_scenario

from .helpers import write_recording

DOC = Path(__file__).resolve().parents[2] / "docs" / "log-format.md"


def test_topic_constants_are_the_documented_topics():
    table = DOC.read_text().split("## Topics", 1)[1].split("\n\n", 2)[1]
    documented = set(re.findall(r"^\| `(/[a-z_/]+)`", table, re.M))
    defined = {v for k, v in vars(topics).items() if k.startswith("TOPIC_")}
    assert defined == documented
    assert topics.TRUTH_TOPICS == (topics.TOPIC_TRUTH_ATTITUDE, topics.TOPIC_TRUTH_STARS)


def test_scenario_is_the_recordings_scenario(tmp_path):
    scenario = load_scenario(CONFIGS / "scenarios" / "he2021b.yaml")
    path = tmp_path / "rec.mcap"
    with LogWriter(path, metadata={"scenario": {"yaml": to_yaml(scenario)}}):
        pass
    assert LogReader(path).scenario() == scenario


def test_scenario_missing_names_the_file_and_the_hint(tmp_path):
    path = tmp_path / "bare.mcap"
    with LogWriter(path):
        pass
    with pytest.raises(UserError, match=r"bare\.mcap: the recording declares no sensor model .*; pass --sim"):
        LogReader(path).scenario("pass --sim SCENARIO.yaml")


def test_scenario_invalid_names_the_file_and_the_key(tmp_path):
    path = tmp_path / "bad.mcap"
    with LogWriter(path, metadata={"scenario": {"yaml": "name: x\nframez: 3\n"}}):
        pass
    with pytest.raises(ConfigError, match=r"bad\.mcap \(metadata 'scenario'\).*framez"):
        LogReader(path).scenario()


def test_stars_gyro_and_truth_are_the_records_joined_in_log_order(tmp_path):
    path = tmp_path / "sim.mcap"
    write_recording(path, n_frames=3)
    reader = LogReader(path)
    stars = reader.stars(topics.TOPIC_TRUTH_STARS)
    records = [m.record for m in reader.messages(topics.TOPIC_TRUTH_STARS)]
    assert list(stars) == [r.frame for r in records] == [0, 1, 2]
    for r in records:
        expected = stars_to_arrays(r)
        assert stars[r.frame]["t0_ns"] == r.t0_ns
        assert set(stars[r.frame]) == {*expected, "t0_ns"}
        for name, column in expected.items():
            np.testing.assert_array_equal(stars[r.frame][name], column)

    gyro = reader.gyro()
    parts = [gyro_samples_to_arrays(m.record) for m in reader.messages(topics.TOPIC_GYRO)]
    np.testing.assert_array_equal(gyro["t_ns"], np.concatenate([p["t_ns"] for p in parts]))
    np.testing.assert_array_equal(gyro["omega_rad_s"], np.concatenate([p["omega_rad_s"] for p in parts]))
    assert gyro["t_ns"].dtype == np.int64 and gyro["omega_rad_s"].shape == (9, 3)

    truth = reader.truth_attitude()
    parts = [attitude_samples_to_arrays(m.record) for m in reader.messages(topics.TOPIC_TRUTH_ATTITUDE)]
    for name in ("t_ns", "q_xyzw", "omega_rad_s"):
        np.testing.assert_array_equal(truth[name], np.concatenate([p[name] for p in parts]))


def test_accessors_of_a_log_without_the_topics_are_empty(tmp_path):
    path = tmp_path / "bare.mcap"
    with LogWriter(path):
        pass
    reader = LogReader(path)
    assert reader.stars(topics.TOPIC_EST_STARS) == {}
    assert reader.gyro()["t_ns"].shape == (0,) and reader.gyro()["omega_rad_s"].shape == (0, 3)
    truth = reader.truth_attitude()
    assert truth["t_ns"].shape == (0,) and truth["q_xyzw"].shape == (0, 4) and truth["omega_rad_s"].shape == (0, 3)
    assert join_gyro_samples([])["t_ns"].dtype == np.int64
    assert join_attitude_samples([])["t_ns"].dtype == np.int64
