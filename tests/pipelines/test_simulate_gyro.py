"""Gyro samples in simulated logs: every sample logged once, to the frame it precedes."""
from __future__ import annotations

import numpy as np
import yaml

from rollingstar.logs.reader import LogReader
from rollingstar.pipelines.simulate import TOPIC_GYRO, simulate_to_log
from rollingstar.sensors.scenario import ScenarioConfig

SCENARIO = """
name: gyro-period
sensor: {focal_length_mm: 25.0, pixel_size_um: 5.5, width_px: 512, height_px: 512}
shutter: {mode: rolling, exposure_ms: 10.0, frame_period_ms: 100.0}
catalog: {source: synthetic, magnitude: 3.0, positions_px: [[100.0, 100.0], [400.0, 300.0], [250.0, 450.0]]}
motion:
  initial_attitude: {ra_deg: 10.0, dec_deg: 20.0, roll_deg: 0.0}
  segments: [{duration_s: 1.0, rate_deg_s: [0.5, 0.0, 0.0]}]
gyro: {enabled: true, rate_hz: 128.0}
frames: 6
seed: 3
"""


def test_gyro_rate_not_dividing_the_frame_period_logs_every_sample_once(tmp_path):
    # 128 Hz gyro, 10 Hz frames: the last sample before frame 0 precedes t0 (it used to be logged
    # at a negative log time, which the writer refuses).
    cfg = ScenarioConfig.model_validate(yaml.safe_load(SCENARIO))
    out = tmp_path / "g.mcap"
    simulate_to_log(cfg, out, show_progress=False)
    times, log_times = [], []
    for msg in LogReader(out).messages([TOPIC_GYRO]):
        times.extend(msg.record.t_ns)
        log_times.append(msg.log_time_ns)
        assert max(msg.record.t_ns) <= msg.log_time_ns  # causal: published after its samples
    t = np.asarray(times)
    assert np.all(np.diff(t) > 0)  # each sample once, in order
    assert len(log_times) == cfg.frames and min(log_times) >= 0
    # the samples tile (-period, t0 of the last frame] at 128 Hz without gaps
    assert np.allclose(np.diff(t), 1e9 / 128.0, atol=1.0)
