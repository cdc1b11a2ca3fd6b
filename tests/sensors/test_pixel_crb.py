"""Pixel-level Cramér–Rao bound of one star's position: known answers and an estimator that reaches it."""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.special import ndtr

from rollingstar.sensors.pixel_crb import position_crb_px, spot_fisher


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
