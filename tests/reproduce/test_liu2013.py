"""liu2013 quick reproduction: windowed Kalman spot std below full-frame CoG std (no timing asserts)."""
from __future__ import annotations

import numpy as np
import pytest

from pipelines.reproduce import liu2013


@pytest.fixture(scope="module")
def summary():
    return liu2013.summarise(liu2013.experiment(quick=True, seed=1))


def test_windowed_kalman_beats_full_frame(summary):
    sf, sw = summary["std_full"], summary["std_win"]  # (runs, 2)
    n = sf.shape[0]
    # margin: 3 standard errors of the run-mean difference, from the run-to-run spread
    margin = 3 * np.sqrt(np.var(sf, axis=0, ddof=1) / n + np.var(sw, axis=0, ddof=1) / n)
    assert np.all(sw.mean(axis=0) + margin < sf.mean(axis=0)), (sf, sw, margin)


def test_every_frame_measured_and_windows_used(summary):
    assert summary["valid_full"] == 1.0 and summary["valid_win"] == 1.0
    assert summary["window_frac"] > 0.9
    assert np.all(summary["pred_max"] < 1.0)  # the paper's 1 px coarse-position accuracy

