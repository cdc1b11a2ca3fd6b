"""The image simulator's shot-noise generator (guide-table Poisson inversion) is exactly Poisson.

Chi-square goodness of fit of :func:`rollingstar.sensors.image_sim.poisson_constant` against the Poisson pmf
at small, medium and large means, and of :func:`shot_noise` on a non-uniform mean map (the sum
decomposition ``Poisson(m0) + Poisson(m - m0)``) per pixel class; fixed seeds, 1e-4 false-alarm
level per test.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from rollingstar.sensors.image_sim import (
    ImageModel,
    digitise,
    poisson_constant,
    shot_noise,
)


def _chi2_pvalue(samples: np.ndarray, lam: float) -> float:
    k = samples.astype(np.int64)
    lo, hi = int(stats.poisson.ppf(1e-4, lam)), int(stats.poisson.isf(1e-4, lam))
    edges = np.arange(lo, hi + 1)
    observed = np.array([np.sum(k < lo)] + [np.sum(k == e) for e in edges] + [np.sum(k > hi)])
    p = np.concatenate([[stats.poisson.cdf(lo - 1, lam)], stats.poisson.pmf(edges, lam), [stats.poisson.sf(hi, lam)]])
    expected = p * k.size
    good = expected >= 5  # pool the sparse bins into the tails' cells
    obs = np.append(observed[good], observed[~good].sum())
    exp = np.append(expected[good], expected[~good].sum())
    if exp[-1] == 0:
        obs, exp = obs[:-1], exp[:-1]
    return float(stats.chisquare(obs, exp * obs.sum() / exp.sum()).pvalue)


@pytest.mark.parametrize("lam", [0.05, 2.47, 37.0, 5000.0])
def test_poisson_constant_is_poisson(lam):
    x = poisson_constant(lam, 400_000, np.random.default_rng(int(lam * 100)))
    assert x.dtype == np.float32 and np.all(x == np.round(x)) and x.min() >= 0
    assert _chi2_pvalue(x, lam) > 1e-4


def test_shot_noise_of_a_mean_map():
    """Background pixels and a bright patch each follow Poisson of their own mean."""
    mean = np.full((400, 400), 2.47)
    mean[:100, :100] += 700.0  # a bright region (the excess draw)
    x = shot_noise(mean, np.random.default_rng(3))
    assert _chi2_pvalue(x[100:, :].ravel(), 2.47) > 1e-4
    assert _chi2_pvalue(x[:100, :100].ravel(), 702.47) > 1e-4


def test_shot_noise_rejects_bad_means():
    with pytest.raises(ValueError, match="finite and >= 0"):
        shot_noise(np.array([1.0, np.nan]), np.random.default_rng(0))
    with pytest.raises(ValueError, match="finite and >= 0"):
        shot_noise(np.array([1.0, -1.0]), np.random.default_rng(0))


def test_digitise_moments():
    """Mean and variance of the ADU of a flat field: bias + m / g and (m + read^2) / g^2 + 1/12."""
    model = ImageModel(read_noise_e=5.0, gain_e_per_adu=2.0, bias_adu=100.0, bit_depth=16, full_well_e=60000.0)
    m = 400.0
    adu = digitise(np.full((500, 500), m), model, np.random.default_rng(1), np.random.default_rng(2)).astype(float)
    n = adu.size
    var = (m + 25.0) / 4.0 + 1.0 / 12.0
    assert abs(adu.mean() - (100.0 + m / 2.0)) < 5 * np.sqrt(var / n)
    assert abs(adu.var() - var) < 5 * var * np.sqrt(2.0 / n) + 0.02  # + kurtosis of the Poisson part (small)
