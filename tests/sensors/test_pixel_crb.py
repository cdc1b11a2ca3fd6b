"""Pixel-level Cramér–Rao bound of one star's position: known answers and an estimator that reaches it."""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.special import ndtr

from rollingstar.sensors.pixel_crb import _smeared_mu, position_crb_px, smeared_spot_fisher, spot_fisher


def test_well_sampled_photon_limited_spot_has_the_closed_form_bound():
    """No background, no read noise, PSF 3 px: var(x) = var(y) = (s^2 + 1/12) / F, no correlation."""
    for flux in (1e3, 1e5):
        crb = position_crb_px(10.3, 20.7, flux, 3.0, background_e=1e-9)
        np.testing.assert_allclose(np.diag(crb), (9.0 + 1.0 / 12.0) / flux, rtol=2e-3)
        assert abs(crb[0, 1]) < 1e-6 * crb[0, 0]


def test_background_and_read_noise_only_add_uncertainty_and_the_fisher_matrix_is_symmetric():
    base = position_crb_px(5.2, 5.6, 2e4, 1.0)
    noisy = position_crb_px(5.2, 5.6, 2e4, 1.0, background_e=50.0, read_noise_e=5.0)
    assert np.all(np.diag(noisy) > np.diag(base))
    info = spot_fisher(5.2, 5.6, 2e4, 1.0, 50.0, 5.0)
    np.testing.assert_allclose(info, info.T)
    assert np.all(np.linalg.eigvalsh(info) > 0)


def _render(x, y, flux, s, b, h, rng):
    u = np.arange(-h, h + 1.0)
    gx = ndtr((u - x + 0.5) / s) - ndtr((u - x - 0.5) / s)
    gy = ndtr((u - y + 0.5) / s) - ndtr((u - y - 0.5) / s)
    return rng.poisson(flux * np.outer(gy, gx) + b).astype(float), u


def test_a_maximum_likelihood_fit_reaches_the_bound():
    """300 Poisson draws of a 1.2 px spot with background (rendered here, not by the simulator),
    fitted by weighted least squares (the Poisson likelihood's Gaussian limit at these counts):
    the position variance per axis is the bound within the Monte Carlo error (+-15 %)."""
    rng = np.random.default_rng(3)
    s, flux, b, h, x0, y0 = 1.2, 5000.0, 20.0, 7, 0.3, -0.2
    est = []
    for _ in range(300):
        img, u = _render(x0, y0, flux, s, b, h, rng)

        def resid(p):
            gx = ndtr((u - p[0] + 0.5) / s) - ndtr((u - p[0] - 0.5) / s)
            gy = ndtr((u - p[1] + 0.5) / s) - ndtr((u - p[1] - 0.5) / s)
            mu = p[2] * np.outer(gy, gx) + p[3]
            return ((img - mu) / np.sqrt(np.maximum(mu, 1.0))).ravel()

        est.append(least_squares(resid, [0.0, 0.0, img.sum(), np.median(img)]).x[:2])
    var = np.var(np.array(est), axis=0, ddof=1)
    crb = np.diag(position_crb_px(x0, y0, flux, s, background_e=b))
    np.testing.assert_allclose(var / crb, 1.0, atol=0.15)


def _position_block(info: np.ndarray, keep=(0, 1, 4, 5)) -> np.ndarray:
    keep = list(keep)
    return np.linalg.inv(info[np.ix_(keep, keep)])[:2, :2]


def test_a_motionless_smeared_spot_is_the_static_spot():
    static = position_crb_px(10.3, 20.7, 2e4, 1.0, background_e=50.0, read_noise_e=5.0)
    moving = _position_block(smeared_spot_fisher(10.3, 20.7, 0.0, 0.0, 2e4, 1.0, 0.045, 43.9e-6, 50.0, 5.0))
    np.testing.assert_allclose(moving, static, rtol=1e-6)


def test_a_smear_costs_information_along_it_not_across():
    """A 20 px smear along the columns: the along-smear bound grows several times, the across-smear
    one barely; the rolling shutter's row offsets do not change which axis pays."""
    still = np.diag(position_crb_px(10.3, 20.7, 2e4, 1.0, background_e=50.0, read_noise_e=5.0))
    smear = np.diag(_position_block(smeared_spot_fisher(10.3, 20.7, 0.0, 444.0, 2e4, 1.0, 0.045, 43.9e-6, 50.0, 5.0)))
    assert smear[1] > 10 * still[1]
    assert smear[0] < 2 * still[0]


def test_saturated_pixels_carry_no_information():
    """Clipping the peak costs little (the peak pixel's value hardly depends on the position); clipping
    the flanks, where the profile is steepest, costs much: the bound grows as the full well drops."""
    def bound(full_well):
        return np.diag(_position_block(smeared_spot_fisher(5.3, 5.6, 0.0, 0.0, 2e5, 1.0, 0.05, 0.0, 20.0, 5.0,
                                                           full_well_e=full_well)))
    free, peak_clipped, flanks_clipped = bound(np.inf), bound(2e4), bound(5e3)
    assert np.all(free < peak_clipped) and np.all(peak_clipped < 1.1 * free)
    assert np.all(flanks_clipped > 1.4 * free)


def _render_smear(x, y, vy, flux, s, b, exposure, h, rng, n=400):
    """A smear by summing point-sampled PSFs on a 5x finer grid (not the bound's pixel-integrated
    model), then Poisson noise."""
    fine = (np.arange(-h * 5 - 2, h * 5 + 3) + 0.5) / 5.0 - 0.5
    t = (np.arange(n) + 0.5) / n * exposure - 0.5 * exposure
    cy = y + vy * t
    px = np.exp(-0.5 * ((fine[None, :] - x) / s) ** 2)
    py = np.exp(-0.5 * ((fine[None, :] - cy[:, None]) / s) ** 2).mean(axis=0)
    img = np.outer(py, px.ravel())
    img = img.reshape(img.shape[0] // 5, 5, img.shape[1] // 5, 5).sum(axis=(1, 3))
    img *= flux / img.sum()
    return rng.poisson(img + b).astype(float)


def test_a_fit_of_smeared_spots_reaches_the_bound():
    """200 Poisson draws of a 6 px smear (global shutter, velocity known), fitted by weighted least
    squares with the bound's own model: position variance per axis within +-20 % of the bound
    (Monte Carlo error 10 %)."""
    rng = np.random.default_rng(5)
    s, flux, b, h, vy, exposure = 1.0, 8000.0, 10.0, 8, 120.0, 0.05
    cols = rows = np.arange(-h, h + 1.0)
    est = []
    for _ in range(200):
        img = _render_smear(0.2, -0.3, vy, flux, s, b, exposure, h, rng)

        def resid(p):
            mu = _smeared_mu(np.array([p[0], p[1], 0.0, vy, p[2], p[3]]), cols, rows, s, exposure, 0.0, 32)
            return ((img - mu) / np.sqrt(np.maximum(mu, 1.0))).ravel()

        est.append(least_squares(resid, [0.0, 0.0, img.sum(), np.median(img)]).x[:2])
    var = np.var(np.array(est), axis=0, ddof=1)
    crb = np.diag(_position_block(smeared_spot_fisher(0.2, -0.3, 0.0, vy, flux, s, exposure, 0.0, b)))
    np.testing.assert_allclose(var / crb, 1.0, atol=0.2)
