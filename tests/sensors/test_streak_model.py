"""The fast streak model against the pixel-integrated time-sampled model of pixel_crb, its Jacobian
against finite differences, and its Fisher information against smeared_spot_fisher."""
from __future__ import annotations

import numpy as np
import pytest

from rollingstar.sensors.pixel_crb import _smeared_mu, smeared_spot_fisher
from rollingstar.sensors.streak_model import streak_fisher, streak_mu, streak_mu_jac, streak_window

E, LD, S = 0.0449, 43.9e-6, 1.0  # he2021a: exposure, line delay, PSF sigma
# motionless, 1 deg/s and 10 deg/s about camera x (764 px/s along the columns), along the rows,
# oblique, slow (a sub-pixel smear) and a barely moving star
VELOCITIES = [(0.0, 0.0), (0.0, 76.4), (0.0, 764.0), (764.0, 0.0), (300.0, -500.0), (-40.0, 20.0), (5.0, 5.0),
              (1e-3, 0.0)]


def _window(p):
    return streak_window(*p[:4], S, E, LD)


@pytest.mark.parametrize("vx, vy", VELOCITIES)
def test_the_closed_form_matches_the_sampled_pixel_integrated_model(vx, vy):
    """The closed form replaces the pixel-integrated PSF by a Gaussian of the same variance: its
    largest error is 0.16 % of the peak (motionless spot), less for streaks."""
    p = np.array([20.3, 30.7, vx, vy, 1e4, 3.0])
    r0, c0, nr, nc = _window(p)
    mu = streak_mu(p, r0, c0, nr, nc, S, E, LD)[0]
    exact = _smeared_mu(p, np.arange(c0, c0 + nc, dtype=float), np.arange(r0, r0 + nr, dtype=float), S, E, LD, 2000)
    peak = (exact - p[5]).max()
    assert np.abs(mu - exact).max() < 2e-3 * peak
    np.testing.assert_allclose(mu.sum() - p[5] * mu.size, exact.sum() - p[5] * mu.size, rtol=1e-3)


@pytest.mark.parametrize("vx, vy", VELOCITIES)
def test_the_jacobian_is_the_derivative_of_the_model(vx, vy):
    p = np.array([20.3, 30.7, vx, vy, 1e4, 3.0])
    r0, c0, nr, nc = _window(p)
    _, jac = streak_mu_jac(p, r0, c0, nr, nc, S, E, LD)
    for k, step in enumerate([1e-5, 1e-5, 1e-3, 1e-3, 1e-2, 1e-3]):
        dp = np.zeros(6)
        dp[k] = step
        fd = (streak_mu(p + dp, r0, c0, nr, nc, S, E, LD) - streak_mu(p - dp, r0, c0, nr, nc, S, E, LD))[0] / (2 * step)
        scale = max(np.abs(fd).max(), 1e-6 * p[4])  # the velocity derivatives of a motionless star vanish
        assert np.abs(jac[0, k] - fd).max() < 1e-5 * scale, f"parameter {k}"


def test_a_batch_is_the_stars_one_by_one():
    rng = np.random.default_rng(0)
    p = np.column_stack([rng.uniform(5, 9, 5), rng.uniform(20, 30, 5), rng.normal(0, 300, 5), rng.normal(0, 300, 5),
                         rng.uniform(1e3, 1e5, 5), rng.uniform(0, 10, 5)])
    r0, c0 = rng.integers(-3, 3, 5), rng.integers(-3, 3, 5)
    mu, jac = streak_mu_jac(p, r0, c0, 50, 14, S, E, LD)
    for k in range(5):
        one_mu, one_jac = streak_mu_jac(p[k], r0[k], c0[k], 50, 14, S, E, LD)
        np.testing.assert_array_equal(mu[k], one_mu[0])
        np.testing.assert_array_equal(jac[k], one_jac[0])


@pytest.mark.parametrize("vx, vy", VELOCITIES[:6])
def test_the_fisher_information_agrees_with_the_pixel_level_bound(vx, vy):
    """Position bound (velocity, flux and background marginalised) within 1 % of smeared_spot_fisher
    (the exact pixel integration), with read noise, quantisation and a full well that clips the peak."""
    for full_well in (np.inf, 3000.0):
        p = np.array([20.3, 30.7, vx, vy, 3e4, 3.0])
        ours = np.linalg.inv(streak_fisher(p, S, E, LD, 5.0, 1.0, full_well))[:2, :2]
        exact = np.linalg.inv(smeared_spot_fisher(*p[:5], S, E, LD, p[5], 5.0, 1.0, full_well, n_sub=256))[:2, :2]
        np.testing.assert_allclose(np.diag(ours), np.diag(exact), rtol=0.01)


def test_the_rolling_shutter_stretches_a_streak_along_the_columns():
    """Motion along +y over a rolling shutter: later rows see the star later, further down, so the
    streak is longer by 1 / (1 - vy ld) than the global-shutter one; opposite motion compresses it."""
    def extent(vy, ld):
        p = np.array([7.0, 60.0, 0.0, vy, 1e4, 0.0])
        mu = streak_mu(p, 0, 0, 120, 14, S, E, ld)[0].sum(axis=1)
        rows = np.arange(120)
        mean = (rows * mu).sum() / mu.sum()
        return np.sqrt(((rows - mean) ** 2 * mu).sum() / mu.sum())
    still = extent(764.0, 0.0)
    assert extent(764.0, LD) > 1.02 * still and extent(-764.0, LD) < 0.98 * still
