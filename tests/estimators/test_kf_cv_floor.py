"""kf-cv on the paper's own motion model (uniform image velocity) reaches the least-squares floor.

For q -> 0 the constant-velocity Kalman filter started from frame differencing (eq 6, with its
exact initial covariance) is the least-squares straight-line fit of all measurements so far, whose
end-point errors after ``n`` frames of spacing ``dt`` and noise ``sigma`` are known in closed form:

    position: sigma * sqrt((4n - 2) / (n (n + 1))),   velocity: sigma / dt * sqrt(12 / (n (n^2 - 1))).

At he2021a's R = 0.05 px^2 and t_f = 89.85 ms this is 0.062 px and 0.024 px/s after 50 frames, 0.044 px
and 0.009 px/s after 100: the paper's "< 0.1 px, < 0.02 px/s after 50 frames" (Figs 6-7) is this floor
(docs/reproductions/he2021a.md).
"""
from __future__ import annotations

import numpy as np
import pytest

from rollingstar.estimators.filters.kf_cv import kf_cv_batch

DT = 0.08985
R = 0.05


@pytest.mark.parametrize("n", [10, 50, 100])
def test_filter_error_equals_line_fit_floor(n):
    rng = np.random.default_rng(n)
    tracks = 2000
    t = np.arange(n) * DT
    p0 = rng.uniform(0, 1000, (tracks, 2))
    v = rng.normal(0, 200, (tracks, 2))
    truth = p0[None] + t[:, None, None] * v[None]
    z = truth + rng.normal(0, np.sqrt(R), truth.shape)
    states, _ = kf_cv_batch(z, DT, q=1e-12, r=R)
    last = states[-1]
    pos_err = np.concatenate([last[:, 0] - truth[-1, :, 0], last[:, 2] - truth[-1, :, 1]])
    vel_err = np.concatenate([last[:, 1] - v[:, 0], last[:, 3] - v[:, 1]])
    sigma = np.sqrt(R)
    pos_floor = sigma * np.sqrt((4 * n - 2) / (n * (n + 1)))
    vel_floor = sigma / DT * np.sqrt(12 / (n * (n**2 - 1)))
    # 4000 samples: the RMS of Gaussian errors is within 3 * 1/sqrt(2 * 4000) = 3.4 % of its value
    assert np.sqrt(np.mean(pos_err**2)) == pytest.approx(pos_floor, rel=0.034)
    assert np.sqrt(np.mean(vel_err**2)) == pytest.approx(vel_floor, rel=0.034)
