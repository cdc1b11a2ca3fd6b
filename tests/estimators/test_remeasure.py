"""Stars another tool listed, measured again on their image (``estimators/centroiders/remeasure.py``).

The images are drawn here, not by the project's smear model: each star's PSF is a Gaussian
integrated exactly over each pixel (differences of ``erf``, where the fit's model approximates the
pixel by a widened Gaussian), with Poisson shot noise and Gaussian read noise, quantised to 16-bit
counts. The listed positions are the truth plus 0.3 px of another tool's noise.
"""
from __future__ import annotations

import sys

import numpy as np
import pytest
from scipy.special import erf

from rollingstar.estimators.centroiders.remeasure import remeasure_stars

SIZE, PSF, BACKGROUND, READ_NOISE, GAIN = 256, 1.3, 100.0, 4.0, 1.0


def _pixel_integrated(x0: float, y0: float, flux: float, sigma: float) -> np.ndarray:
    edges = np.arange(SIZE + 1) - 0.5
    cx = np.diff(0.5 * (1 + erf((edges - x0) / (np.sqrt(2) * sigma))))
    cy = np.diff(0.5 * (1 + erf((edges - y0) / (np.sqrt(2) * sigma))))
    return flux * np.outer(cy, cx)


def draw(rng, x, y, flux, full_scale=65535) -> np.ndarray:
    mean = np.full((SIZE, SIZE), BACKGROUND)
    for xi, yi, fi in zip(x, y, flux):
        mean += _pixel_integrated(xi, yi, fi, PSF)
    counts = rng.poisson(mean * GAIN) / GAIN + rng.normal(0, READ_NOISE, mean.shape)
    return np.clip(np.rint(counts), 0, full_scale).astype(np.uint16)


def field(rng, n=25):
    grid = np.stack(np.meshgrid(np.arange(5) * 48 + 30, np.arange(5) * 48 + 30), -1).reshape(-1, 2)[:n]
    return grid[:, 0] + rng.uniform(-0.5, 0.5, n), grid[:, 1] + rng.uniform(-0.5, 0.5, n)


def test_remeasured_positions_beat_the_listed_ones_and_match_their_covariance():
    """Monte Carlo over 20 images: errors 4x smaller than the listed 0.3 px, and z^2 of the stated
    2 x 2 covariances averaging 2 (chi-square with 2 degrees of freedom) within its sampling error."""
    rng = np.random.default_rng(3)
    z2, err, listed_err = [], [], []
    for _ in range(20):
        x, y = field(rng)
        flux = rng.uniform(3000, 20000, x.size)
        img = draw(rng, x, y, flux)
        lx, ly = x + rng.normal(0, 0.3, x.size), y + rng.normal(0, 0.3, x.size)
        r = remeasure_stars(img, lx, ly, gain_e_per_adu=GAIN)
        assert r.measured.all(), r.reason
        assert r.psf_measured and r.psf_sigma_px == pytest.approx(PSF, rel=0.1)
        d = np.column_stack([r.x - x, r.y - y])
        z2.append(np.einsum("ni,nij,nj->n", d, np.linalg.inv(r.cov), d))
        err.append(d)
        listed_err.append(np.column_stack([lx - x, ly - y]))
    z2, err = np.concatenate(z2), np.concatenate(err)
    assert np.sqrt(np.mean(err**2)) < 0.25 * np.sqrt(np.mean(np.concatenate(listed_err) ** 2))
    # mean of chi2(2) is 2 with sd 2/sqrt(n); 4 sd, and 15 % for the model's widened-Gaussian pixel
    assert abs(z2.mean() - 2.0) < 4 * 2.0 / np.sqrt(z2.size) + 0.3


def _z2_of_listed_stars(render, gain, images: int) -> np.ndarray:
    """z^2 of every measured star's error under its stated covariance, over ``images`` images drawn
    by ``render(rng, x, y, flux)``, the stars listed 0.3 px off."""
    rng = np.random.default_rng(11)
    z2 = []
    for _ in range(images):
        x, y = field(rng)
        img = render(rng, x, y, rng.uniform(3000, 20000, x.size))
        r = remeasure_stars(img, x + rng.normal(0, 0.3, x.size), y + rng.normal(0, 0.3, x.size), gain_e_per_adu=gain)
        d = np.column_stack([r.x - x, r.y - y])[r.measured]
        z2.append(np.einsum("ni,nij,nj->n", d, np.linalg.inv(r.cov[r.measured]), d))
    return np.concatenate(z2)


@pytest.mark.parametrize("psf, gain", [(1.3, None), (0.4, None), (0.4, GAIN)])
def test_covariances_hold_without_a_gain_and_for_an_undersampled_psf(psf, gain, monkeypatch):
    """The corr import states no gain (an 8-bit PNG has none), and the creusot 16 mm PSF is 0.4 px
    wide: the shot noise measured from the stars' residuals, the core pixels' misfit and the
    model's own bias keep the stated covariances honest (mean z^2 within 1.2-3.2 of its 2)."""
    monkeypatch.setattr(sys.modules[__name__], "PSF", psf)
    z2 = _z2_of_listed_stars(draw, gain, images=8)
    assert z2.size >= 190 and 1.2 < z2.mean() < 3.2, z2.mean()


def test_stars_that_are_not_measurements_keep_the_listed_position_with_the_reason():
    rng = np.random.default_rng(5)
    x, y = field(rng, 6)
    flux = np.array([5000.0, 5000.0, 5e6, 5000.0, 5000.0, 0.0])  # a saturated core; an empty listing
    img = draw(rng, x, y, flux)
    lx, ly = x.copy(), y.copy()
    lx[4] += 4.0  # listed 4 px from its star: the fit finds the star, not this listing's spot
    r = remeasure_stars(img, lx, ly)
    assert r.reason[2] == "saturated" and r.reason[4] in ("moved", "low_snr") and r.reason[5] in ("moved", "low_snr")
    assert list(r.measured) == [True, True, False, True, False, False]
    for k in (2, 4, 5):
        assert (r.x[k], r.y[k]) == (lx[k], ly[k]) and np.isnan(r.cov[k]).all()
    assert np.hypot(r.x[0] - x[0], r.y[0] - y[0]) < 0.1


def test_a_shifted_or_mirrored_listing_is_not_measured():
    """A table whose positions belong to another image (shifted by 20 px, or mirrored) finds
    nothing at its stars: no position is replaced by a fit to noise."""
    rng = np.random.default_rng(8)
    x, y = field(rng)
    img = draw(rng, x, y, np.full(x.size, 8000.0))
    for lx, ly in ((x + 20.0, y), (SIZE - 1 - x, y + 13.0)):
        r = remeasure_stars(img, lx, ly, psf_sigma_px=PSF)
        assert not r.measured.any(), r.reason


def test_a_listed_neighbour_within_the_window_is_not_measured():
    """Two stars 3.5 px apart share a window's light: the fit of either would be pulled towards the
    other, so both keep the listed position (``blended``)."""
    rng = np.random.default_rng(2)
    x, y = np.array([60.0, 63.5, 150.2]), np.array([80.3, 80.3, 150.7])
    img = draw(rng, x, y, np.full(3, 8000.0))
    r = remeasure_stars(img, x, y, psf_sigma_px=PSF, gain_e_per_adu=GAIN)
    assert list(r.reason) == ["blended", "blended", ""]


def test_inputs_that_are_not_an_image_and_star_list_are_refused():
    from rollingstar.errors import UserError

    img = np.zeros((32, 32), dtype=np.uint16)
    empty = remeasure_stars(img, np.zeros(0), np.zeros(0))
    assert empty.x.size == 0 and not empty.measured.any()
    for bad, x, match in ((np.zeros((4, 32, 32)), [1.0], "2-D image"), (np.full((32, 32), np.nan), [1.0], "NaN"),
                          (img, [np.nan], "finite")):
        with pytest.raises(UserError, match=match):
            remeasure_stars(bad, np.array(x), np.array([1.0]))


def test_stars_listed_outside_the_image_are_reported_not_fitted():
    rng = np.random.default_rng(9)
    x, y = np.array([60.0, 300.0, -40.0]), np.array([70.0, 80.0, 90.0])
    img = draw(rng, x[:1], y[:1], np.array([8000.0]))
    r = remeasure_stars(img, x, y, gain_e_per_adu=GAIN)
    assert list(r.reason) == ["", "outside", "outside"] and (r.x[1:] == x[1:]).all()


def test_a_core_clipped_on_one_pixel_is_not_taken_as_a_measurement():
    """12-bit counts in a 16-bit container: a star whose peak pixel alone reached 4095."""
    rng = np.random.default_rng(12)
    x, y = np.array([60.3, 150.0]), np.array([70.2, 160.0])
    img = np.minimum(draw(rng, x, y, np.array([3000.0, 46000.0])), 4095)
    assert np.count_nonzero(img == 4095) == 1  # the second star's centre pixel alone
    r = remeasure_stars(img, x, y, psf_sigma_px=PSF)
    assert r.reason[1] == "saturated" and r.reason[0] == ""


def _elliptical(rng, x, y, flux, sx=1.6, sy=0.9) -> np.ndarray:
    edges = np.arange(SIZE + 1) - 0.5
    mean = np.full((SIZE, SIZE), BACKGROUND)
    for xi, yi, fi in zip(x, y, flux):
        cx = np.diff(0.5 * (1 + erf((edges - xi) / (np.sqrt(2) * sx))))
        cy = np.diff(0.5 * (1 + erf((edges - yi) / (np.sqrt(2) * sy))))
        mean += fi * np.outer(cy, cx)
    counts = rng.poisson(mean * GAIN) / GAIN + rng.normal(0, READ_NOISE, mean.shape)
    return np.clip(np.rint(counts), 0, 65535).astype(np.uint16)


@pytest.mark.parametrize("gain", [GAIN, None])
def test_a_psf_the_gaussian_does_not_draw_leaves_the_covariances_conservative(gain):
    """An elliptical PSF (1.6 x 0.9 px) fitted with the round model: the misfit shows in the core
    pixels and in the measured shot noise, and the stated covariances then err on the large side
    (mean z^2 about 0.1 here: sigmas about 3x the errors, the documented cost of a symmetric misfit
    that moves no position), never on the small one."""
    z2 = _z2_of_listed_stars(_elliptical, gain, images=6)
    assert z2.size >= 140 and z2.mean() < 2.0 and np.mean(z2 > 9.21) < 0.01
