"""liu2013 quick reproduction: windowed Kalman spot std below full-frame CoG std (no timing asserts)."""
from __future__ import annotations

import numpy as np
import pytest

from rollingstar.studies.reproduce import liu2013

pytestmark = pytest.mark.slow  # whole reproductions, benchmarks or killed processes: `-m 'not slow'` skips them


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



def test_std_reduction_factor_at_least_the_papers(summary):
    # paper: windowed Kalman / full-frame std = 0.041 / 0.102 = 0.40 (x), 0.037 / 0.098 = 0.38 (y).
    # Ours: full run 0.40 / 0.42, quick 0.34 / 0.34; the quick runs' run-to-run spread of the ratio is
    # ~0.03, so 0.5 is > 3 sigma above ours and the paper's factor would fail it only if we lost the gain.
    ratio = summary["std_win"].mean(axis=0) / summary["std_full"].mean(axis=0)
    assert np.all(ratio < 0.5), ratio


@pytest.mark.xfail(strict=True, reason="absolute windowed-Kalman std: ours 0.069 / 0.068 px (full run; quick 0.045 / "
                   "0.057) vs the paper's 0.041 / 0.037 px: our full-frame CoG baseline is noisier too (0.17 vs 0.10 px), "
                   "the paper's noise model is not fully specified (see docs/reproductions/liu2013.md)")
def test_windowed_kalman_std_within_papers_values(summary):
    assert np.all(summary["std_win"].mean(axis=0) <= np.array([0.041, 0.037]))


def test_batched_windows_same_spots_as_the_per_window_loop(summary):
    # the numpy window pass (kernel=numpy) against one cog call per window (batch=False), same frames
    assert summary["loop_max_diff_px"] < 1e-9


def test_default_windowed_spots_close_to_the_per_window_background_path(summary):
    # the default (compiled kernel, tracked background) against the numpy window pass with each window's
    # own median background: RMS 0.004 px here (quick), 0.023 px in the full run, 0.030 px in
    # benchmarks/windowed_speed.py; both far below the 0.16 px centroid noise per frame
    assert summary["win_before_n"] > 0 and summary["win_before_rms_px"] < 0.05
