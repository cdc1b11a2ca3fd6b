"""A logger may write its gyro and truth batches out of order: the samples a frame gets are in
time order whatever the order of the messages that carried them."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from rollingstar.logs.records import AttitudeSamplesRecord, GyroSamplesRecord
from rollingstar.pipelines.source import gyro_from_messages, truth_from_messages


def _gyro(t0: int, n: int) -> SimpleNamespace:
    t = [t0 + 1000 * k for k in range(n)]
    return SimpleNamespace(record=GyroSamplesRecord(t_ns=t, x=[float(v) for v in t], y=[0.0] * n, z=[0.0] * n))


def test_gyro_batches_written_out_of_order_come_out_in_time_order():
    g = gyro_from_messages([_gyro(10_000, 4), _gyro(0, 5), _gyro(5_000, 3)])
    assert np.all(np.diff(g.t_ns) >= 0) and g.t_ns.size == 12
    np.testing.assert_array_equal(g.omega_rad_s[:, 0], g.t_ns.astype(float))  # each sample kept its value


def test_truth_batches_written_out_of_order_come_out_in_time_order():
    def batch(t0):
        t = [t0, t0 + 10]
        return SimpleNamespace(record=AttitudeSamplesRecord(t_ns=t, qx=[0.0, 0.0], qy=[0.0, 0.0], qz=[0.0, 0.0],
                                                            qw=[1.0, 1.0]))
    s = truth_from_messages([batch(100), batch(0)])
    assert list(s.t_ns) == [0, 10, 100, 110]
