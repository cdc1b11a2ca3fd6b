"""The foundation figures (quick run) assert the physics they document."""
import numpy as np
import pytest

from rollingstar.studies.figures import run_foundation


@pytest.fixture(scope="module")
def quick():
    return run_foundation(quick=True, seed=1)


def test_static_attitude_error_is_at_the_cramer_rao_bound(quick):
    s = quick["static_vs_crb"]
    # 30 frames: the RMSE of a chi distribution with 30 samples is within ~ +-25 % of sigma at 2.5 sigma
    for eff in s["efficiency"]:
        assert 0.7 < eff < 1.3, s


def test_rolling_shutter_pair_error_linear_in_rate_and_global_at_noise_floor(quick):
    rows = quick["rolling_shutter"]["rows"]
    rates = np.array([r["rate_deg_s"] for r in rows])
    rolling = np.array([r["rolling"]["pair_rmse_px"] for r in rows])
    glob = np.array([r["global"]["pair_rmse_px"] for r in rows])
    noise_floor = glob[rates == 0][0]  # sqrt(2) * 0.05 px for independent noise on both stars
    assert noise_floor == pytest.approx(np.sqrt(2) * 0.05, rel=0.15)
    assert np.all(glob < 1.2 * noise_floor)  # a global shutter shows no rate dependence
    # the rolling-shutter part grows linearly with rate: error^2 - floor^2 proportional to rate^2
    signal = np.sqrt(np.maximum(rolling**2 - noise_floor**2, 0))
    per_rate = signal[rates > 0] / rates[rates > 0]
    assert np.ptp(per_rate) < 0.1 * per_rate.mean()
    # and it stays below the first-order bound (the pair only sees the along-pair component)
    predicted = np.array([r["rolling"]["predicted_shift_rms_px"] for r in rows])
    assert np.all(signal[rates > 0] < predicted[rates > 0]) and np.all(signal[rates > 0] > 0.5 * predicted[rates > 0])


def test_every_row_time_is_row_times_line_delay_to_the_ns(quick):
    assert quick["rolling_shutter"]["row_time_max_error_ns"] == 0


def test_image_level_centroids_and_smear_length(quick):
    im = quick["image_level"]
    assert im["cog_centroid_rmse_px"] < 0.08
    assert abs(im["smear"]["relative_error"]) < 0.02
    assert im["smear"]["stars_measured"] >= 5
