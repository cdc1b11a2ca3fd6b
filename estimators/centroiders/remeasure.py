"""Stars another tool located, measured again on the image they came from.

A table of star positions made by another tool (astrometry.net's ``corr`` table, a vendor's
centroid list) carries that tool's centroid noise. When the image is at hand, each listed star is
fitted again by maximum likelihood with the project's spot model: a Gaussian PSF (sigma measured
from the listed stars themselves, :func:`~rollingstar.estimators.centroiders.psf_width.measure_psf_sigma`)
on a local background (an undersampled PSF gets the narrowest width that fits it, down to 0.3 px;
1 px when too few stars can be fitted), the compiled Levenberg-Marquardt fit the ``streak`` centroider uses
(:func:`~rollingstar.estimators.centroiders.streak_kernel.levenberg_marquardt`) with the spot at
rest. Pixel noise: the image's background scatter
(:func:`~rollingstar.estimators.attitude.pixel_bundle.background_variance`), plus each star's own
shot noise when the conversion gain is known; pixels at the saturation level are left out.
Each star's 2 x 2 position covariance is the inverse of its Fisher information, scaled by its
reduced chi-square when that is implausibly large for a right model (a PSF unlike a Gaussian, a
neighbour in the window, shot noise left out for want of a gain).

A star is kept only when the fit is a measurement of the listed star: finite, with positive flux
and signal-to-noise of at least ``MIN_SNR``, at most ``MAX_SHIFT_PX`` from the listed position and
with no saturated pixel in its window (a saturated core's position comes from its wings alone). The
others keep the listed position and the table's own accuracy; :class:`Remeasured` says which and why.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from rollingstar.estimators.attitude.pixel_bundle import background_variance
from rollingstar.estimators.centroiders.psf_width import measure_psf_sigma
from rollingstar.estimators.centroiders.streak import (
    CONVERGED_DAMPING,
    DEFAULT_PSF_SIGMA_PX,
    FIT_TOLERANCE_PX,
    MARGIN_SIGMAS,
    RIDGE,
    STEP_SIGMAS,
    _misfit_scale,
)
from rollingstar.estimators.centroiders.streak_kernel import levenberg_marquardt, window_moments
from rollingstar.sensors.streak_model import effective_sigma

MAX_SHIFT_PX = 1.5  # a fit further than this from the listed position found another spot
MIN_SNR = 5.0  # flux over its standard deviation below which a fit is no measurement
ITERATIONS = 30  # most Levenberg-Marquardt iterations per star


class Remeasured(NamedTuple):
    """Positions (px), 2 x 2 covariances (px^2; NaN where not measured), which stars were measured,
    why each other one was not (``""`` for a measured star), and the PSF sigma used (px)."""

    x: np.ndarray
    y: np.ndarray
    cov: np.ndarray
    measured: np.ndarray
    reason: np.ndarray
    psf_sigma_px: float
    psf_measured: bool


def remeasure_stars(image: np.ndarray, x: np.ndarray, y: np.ndarray, saturation: float | None = None,
                    gain_e_per_adu: float | None = None, psf_sigma_px: float | None = None) -> Remeasured:
    """Fit each star listed at ``(x, y)`` (px, pixel centres at integers) on ``image`` again (module
    docstring). ``saturation``: the level (ADU) at and above which pixels are left out (None: the
    image's maximum when it is the full scale of an 8- or 16-bit integer type, else none);
    ``psf_sigma_px``: the Gaussian PSF sigma (None: measured from these stars)."""
    img = np.ascontiguousarray(image, dtype=float)
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    sat = _saturation(image) if saturation is None else float(saturation)
    noise2 = background_variance(img)
    inv_gain = 1.0 / gain_e_per_adu if gain_e_per_adu else 0.0
    pv = np.column_stack([x, y, np.zeros_like(x), np.zeros_like(x)])
    measured_psf = psf_sigma_px is None
    if measured_psf:  # an undersampled PSF gets the narrowest width tried: the model that fits it best
        psf_sigma_px = measure_psf_sigma(img, pv, 0.0, 0.0, sat, noise2, inv_gain, narrow_end=True)
        measured_psf = psf_sigma_px is not None
        psf_sigma_px = psf_sigma_px or DEFAULT_PSF_SIGMA_PX
    p, cov, chi2, used, size = _fit(img, x, y, sat, noise2, inv_gain, float(psf_sigma_px))
    reason = _rejections(img, p, cov, x, y, sat, size)
    ok = reason == ""
    cov2 = np.where(ok[:, None, None], cov[:, :2, :2], np.nan)
    return Remeasured(np.where(ok, p[:, 0], x), np.where(ok, p[:, 1], y), cov2, ok, reason, float(psf_sigma_px),
                      measured_psf)


def _fit(img, x, y, sat, noise2, inv_gain, psf_sigma_px):
    """Levenberg-Marquardt of every star at rest on a square window: parameters, covariances
    (misfit-scaled), chi-squares, pixels used and the window's side."""
    half = int(np.ceil(MARGIN_SIGMAS * psf_sigma_px + 1.0))
    size = 2 * half + 1
    row0 = np.rint(y).astype(np.int64) - half
    col0 = np.rint(x).astype(np.int64) - half
    b0 = np.array([_window_median(img, r, c, size) for r, c in zip(row0, col0)])
    start = window_moments(img, row0, col0, size, size, b0, 3.0 * np.sqrt(noise2))
    n = len(x)
    p = np.ascontiguousarray(np.column_stack([x, y, np.zeros((n, 2)), np.maximum(start[:, 0], 10.0 * np.sqrt(noise2)),
                                              b0]))
    # at rest (no exposure sweep): the velocity moves nothing; its unit prior keeps the matrix invertible
    p, hess, chi2, used = levenberg_marquardt(p, row0, col0, size, size, img, sat, noise2, inv_gain,
                                              effective_sigma(psf_sigma_px), 0.0, 0.0, np.zeros((n, 2)), np.ones(n),
                                              ITERATIONS, 0, FIT_TOLERANCE_PX, STEP_SIGMAS, CONVERGED_DAMPING, RIDGE)
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = np.linalg.pinv(hess, hermitian=True) * _misfit_scale(chi2, used)[:, None, None]
    return p, cov, chi2, used, size


def _rejections(img, p, cov, x, y, sat, size) -> np.ndarray:
    """Why each fit is not a measurement of its listed star (``""``: it is)."""
    half = size // 2
    reason = np.full(len(x), "", dtype=object)
    with np.errstate(invalid="ignore", divide="ignore"):
        snr = p[:, 4] / np.sqrt(cov[:, 4, 4])
    finite = np.all(np.isfinite(p), axis=1) & np.isfinite(cov[:, 0, 0]) & np.isfinite(cov[:, 1, 1])
    saturated = np.array([_window_max(img, int(round(yy)) - half, int(round(xx)) - half, size) >= sat
                          for xx, yy in zip(x, y)])
    shift = np.hypot(p[:, 0] - x, p[:, 1] - y)
    reason[~(snr >= MIN_SNR)] = "low_snr"
    reason[~(shift <= MAX_SHIFT_PX)] = "moved"
    reason[saturated] = "saturated"
    reason[~finite | ~(cov[:, 0, 0] > 0) | ~(cov[:, 1, 1] > 0)] = "no_fit"
    return reason.astype(str)


def _window(img, r0: int, c0: int, size: int) -> np.ndarray:
    return img[max(r0, 0): max(r0 + size, 0), max(c0, 0): max(c0 + size, 0)]


def _window_median(img, r0: int, c0: int, size: int) -> float:
    w = _window(img, r0, c0, size)
    return float(np.median(w)) if w.size else 0.0


def _window_max(img, r0: int, c0: int, size: int) -> float:
    w = _window(img, r0, c0, size)
    return float(w.max()) if w.size else np.inf


def _saturation(image: np.ndarray) -> float:
    """The full scale of an integer image when a pixel reaches it (+inf otherwise: no pixel is
    known to be clipped)."""
    a = np.asarray(image)
    if a.dtype.kind in "ui" and a.size and a.max() >= np.iinfo(a.dtype).max:
        return float(np.iinfo(a.dtype).max)
    return np.inf
