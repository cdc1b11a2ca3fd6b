"""Stars another tool located, measured again on the image they came from.

A table of star positions made by another tool (astrometry.net's ``corr`` table, a vendor's
centroid list) carries that tool's centroid noise. When the image is at hand, each listed star is
fitted again by maximum likelihood with the project's spot model: a Gaussian PSF (sigma measured
from the listed stars themselves, :func:`~rollingstar.estimators.centroiders.psf_width.measure_psf_sigma`;
an undersampled PSF gets the narrowest width that fits it, down to 0.3 px; 1 px when no width could
be measured) on a local background, the compiled Levenberg-Marquardt fit the ``streak``
centroider uses (:func:`~rollingstar.estimators.centroiders.streak_kernel.levenberg_marquardt`)
with the spot at rest.

Pixel noise (ADU^2): ``var = noise^2 + a s`` with ``noise^2`` the image's background scatter
(:func:`~rollingstar.estimators.attitude.pixel_bundle.background_variance`) and ``s`` the star's
model signal at the pixel. ``a`` is ``1 / gain`` when the conversion gain is given; otherwise (an
8-bit PNG states none) it is measured from the stars' own residuals after a first fit
(:func:`_noise_per_signal`), and the stars are fitted again with it. Each star's 2 x 2 position
covariance is the inverse of its Fisher information under that noise, scaled by the reduced chi-square of its core pixels (``s`` above the background noise)
when that exceeds 1: what the Gaussian model does not draw of a real PSF (an undersampled one
above all) shows there, and a window's background pixels would dilute it; plus the model's own
bias on an exactly pixel-integrated Gaussian of the measured width (:func:`model_bias_px`).
Pixels at the saturation level are left out. A misfit that moves no position (a symmetric PSF
of another shape: an elliptical one, 1.6 x 0.9 px) inflates the covariances all the same, up to
about 3x in sigma: the stated accuracy then errs on the large side, which the residuals of one
fit cannot tell from a misfit that does move it (``tests/estimators/test_remeasure.py``).

A star is kept only when the fit is a measurement of the listed star: finite, with positive flux
and signal-to-noise of at least ``MIN_SNR`` under the first fit's pixel noise (the background's, plus
the stated gain's shot noise), at most ``MAX_SHIFT_PX`` from the listed position, with
no saturated pixel in its window (a saturated core's position comes from its wings alone), no
other listed star within ``BLEND_SIGMAS`` PSF widths (a neighbour's light pulls the fit), and
listed inside the image (``outside`` otherwise). The
others keep the listed position and the table's own accuracy; :class:`Remeasured` says which and why.
"""
from __future__ import annotations

import warnings
from functools import lru_cache
from typing import NamedTuple

import numpy as np
from scipy.optimize import nnls
from scipy.special import erf

from rollingstar.errors import UserError
from rollingstar.estimators.attitude.pixel_bundle import background_variance
from rollingstar.estimators.centroiders.psf_width import measure_psf_sigma
from rollingstar.estimators.centroiders.streak import (
    CONVERGED_DAMPING,
    DEFAULT_PSF_SIGMA_PX,
    FIT_TOLERANCE_PX,
    MARGIN_SIGMAS,
    RIDGE,
    STEP_SIGMAS,
)
from rollingstar.estimators.centroiders.streak_kernel import levenberg_marquardt, window_moments
from rollingstar.sensors.streak_model import effective_sigma, streak_mu

MAX_SHIFT_PX = 1.5  # a fit further than this from the listed position found another spot
MIN_SNR = 5.0  # flux over its standard deviation below which a fit is no measurement
BLEND_SIGMAS = 6.0  # another listed star closer than this many PSF widths (and 3 px) shares the window's light
ITERATIONS = 30  # most Levenberg-Marquardt iterations per star
MIN_CORE_PIXELS = 6  # fewer core pixels: the star's misfit scale is the image's pooled one
MAX_PSF_SIGMA_PX = 20.0  # a stated PSF wider than this is no star tracker's (and its windows would not fit memory)


class Remeasured(NamedTuple):
    """Positions (px), 2 x 2 covariances (px^2; NaN where not measured), which stars were measured,
    why each other one was not (``""`` for a measured star), the PSF sigma used (px), whether it
    was measured, and the shot-noise factor ``a`` (ADU per ADU of signal) used."""

    x: np.ndarray
    y: np.ndarray
    cov: np.ndarray
    measured: np.ndarray
    reason: np.ndarray
    psf_sigma_px: float
    psf_measured: bool
    noise_per_signal: float


class _Fit(NamedTuple):
    p: np.ndarray  # (n, 6) x, y, vx, vy, flux, background
    cov: np.ndarray  # (n, 6, 6)
    row0: np.ndarray
    col0: np.ndarray
    size: int


def remeasure_stars(image: np.ndarray, x: np.ndarray, y: np.ndarray, saturation: float | None = None,
                    gain_e_per_adu: float | None = None, psf_sigma_px: float | None = None) -> Remeasured:
    """Fit each star listed at ``(x, y)`` (px, pixel centres at integers) on ``image`` again (module
    docstring). ``saturation``: the level (ADU) at and above which pixels are left out (None:
    :func:`_saturation`); ``gain_e_per_adu``: the conversion gain (None: the shot noise is measured
    from the stars); ``psf_sigma_px``: the Gaussian PSF sigma (None: measured from these stars)."""
    img, x, y = _checked(image, x, y, gain_e_per_adu, psf_sigma_px)
    inside = (x > -0.5) & (x < img.shape[1] - 0.5) & (y > -0.5) & (y < img.shape[0] - 0.5)
    if not inside.all():  # measured on the stars the image holds, the others reported as outside
        r = remeasure_stars(image, x[inside], y[inside], saturation, gain_e_per_adu, psf_sigma_px)
        return _scattered(r, inside, x, y)
    sat = _saturation(image) if saturation is None else float(saturation)
    noise2 = background_variance(img)
    a = 1.0 / gain_e_per_adu if gain_e_per_adu else 0.0
    measured_psf = psf_sigma_px is None
    if measured_psf and x.size:  # an undersampled PSF gets the narrowest width tried: the model that fits it best
        pv = np.column_stack([x, y, np.zeros_like(x), np.zeros_like(x)])
        psf_sigma_px = measure_psf_sigma(img, pv, 0.0, 0.0, sat, noise2, a, narrow_end=True)
        measured_psf = psf_sigma_px is not None
    psf = float(psf_sigma_px or DEFAULT_PSF_SIGMA_PX)
    fit = _fit(img, x, y, sat, noise2, a, psf)
    reason = _rejections(img, fit, x, y, sat, psf)  # a star's significance against the background's noise
    if not gain_e_per_adu and x.size:  # the shot noise from the stars' residuals, then the fit under it
        a = _noise_per_signal(img, fit, sat, noise2, psf)
        fit = _fit(img, x, y, sat, noise2, a, psf)
        again = _rejections(img, fit, x, y, sat, psf)
        reason = np.where((reason == "") & np.isin(again, ("moved", "no_fit")), again, reason)
    cov = fit.cov * _core_scale(img, fit, sat, noise2, a, psf)[:, None, None]
    cov[:, :2, :2] += model_bias_px(psf) ** 2 * np.eye(2)
    ok = reason == ""
    cov2 = np.where(ok[:, None, None], cov[:, :2, :2], np.nan)
    return Remeasured(np.where(ok, fit.p[:, 0], x), np.where(ok, fit.p[:, 1], y), cov2, ok, reason, psf, measured_psf,
                      float(a))


def _scattered(r: Remeasured, inside: np.ndarray, x: np.ndarray, y: np.ndarray) -> Remeasured:
    """``r`` (of the stars ``inside``) spread back over every listed star, the others ``outside``."""
    cov = np.full((x.size, 2, 2), np.nan)
    cov[inside] = r.cov
    reason = np.full(x.size, "outside", dtype=object)
    reason[inside] = r.reason
    measured = np.zeros(x.size, dtype=bool)
    measured[inside] = r.measured
    xs, ys = x.copy(), y.copy()
    xs[inside], ys[inside] = r.x, r.y
    return r._replace(x=xs, y=ys, cov=cov, measured=measured, reason=reason.astype(str))


def _checked(image, x, y, gain, psf_sigma_px) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if gain is not None and not (np.isfinite(gain) and gain > 0):
        raise UserError(f"remeasure: gain_e_per_adu must be a positive number, got {gain}")
    if psf_sigma_px is not None and not (np.isfinite(psf_sigma_px) and 0 < psf_sigma_px <= MAX_PSF_SIGMA_PX):
        raise UserError(f"remeasure: psf_sigma_px must be in (0, {MAX_PSF_SIGMA_PX:g}] px, got {psf_sigma_px}")
    img = np.ascontiguousarray(image, dtype=float)
    if img.ndim != 2 or img.size == 0:
        raise UserError(f"remeasure: expected a 2-D image of pixels, got an array of shape {img.shape}")
    if not np.all(np.isfinite(img)):
        raise UserError(f"remeasure: the image holds {int(np.count_nonzero(~np.isfinite(img)))} NaN or infinite pixels")
    x, y = np.asarray(x, dtype=float).reshape(-1), np.asarray(y, dtype=float).reshape(-1)
    if x.shape != y.shape or not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise UserError("remeasure: x and y must be finite and of one length")
    return img, x, y


def _fit(img, x, y, sat, noise2, a, psf_sigma_px) -> _Fit:
    """Levenberg-Marquardt of every star at rest on a square window: parameters and the inverse of
    their information under the pixel noise ``noise2 + a s``."""
    half = int(np.ceil(MARGIN_SIGMAS * psf_sigma_px + 1.0))
    size = 2 * half + 1
    row0 = np.rint(y).astype(np.int64) - half
    col0 = np.rint(x).astype(np.int64) - half
    n = len(x)
    with np.errstate(all="ignore"), warnings.catch_warnings():  # a window wholly outside: no median (0)
        warnings.simplefilter("ignore", RuntimeWarning)
        b0 = np.nan_to_num(np.nanmedian(_windows(img, row0, col0, size), axis=(1, 2)))
    start = window_moments(img, row0, col0, size, size, b0, 3.0 * np.sqrt(noise2))
    p = np.ascontiguousarray(np.column_stack([x, y, np.zeros((n, 2)), np.maximum(start[:, 0], 10.0 * np.sqrt(noise2)),
                                              b0]))
    # at rest (no exposure sweep): the velocity moves nothing; its unit prior keeps the matrix invertible
    p, hess, _, _ = levenberg_marquardt(p, row0, col0, size, size, img, sat, noise2, a, effective_sigma(psf_sigma_px),
                                        0.0, 0.0, np.zeros((n, 2)), np.ones(n), ITERATIONS, 0, FIT_TOLERANCE_PX,
                                        STEP_SIGMAS, CONVERGED_DAMPING, RIDGE)
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = np.linalg.pinv(hess, hermitian=True)
    return _Fit(p, cov, row0, col0, size)


def _residuals(img, fit: _Fit, sat, psf_sigma_px) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per star and window pixel: the residual ``r``, the model signal ``s`` (ADU) and which pixels
    count (inside the image, below saturation, of a finite fit)."""
    h = fit.size
    win = _windows(img, fit.row0, fit.col0, h)
    finite = np.all(np.isfinite(fit.p), axis=1)
    p = np.where(finite[:, None], fit.p, 0.0)
    mu = streak_mu(p, fit.row0, fit.col0, h, h, psf_sigma_px, 0.0, 0.0)
    signal = mu - p[:, 5][:, None, None]
    live = np.isfinite(win) & (win < sat) & finite[:, None, None]
    return np.where(live, win - mu, 0.0), signal, live


def _noise_per_signal(img, fit: _Fit, sat, noise2, psf_sigma_px) -> float:
    """``a`` of the pixel variance ``noise2 + a s``: non-negative least squares of ``r^2 - noise2`` on
    ``s`` and ``s^2`` over every live star pixel (``s > 0``). The ``s^2`` term takes what the model
    does not draw of a bright star (its misfit grows with the flux, shot noise as its square
    root), which would otherwise pass for shot noise; the per-star core scale then takes it."""
    r, s, live = _residuals(img, fit, sat, psf_sigma_px)
    use = live & (s > 0)
    if np.count_nonzero(use) < 2:
        return 0.0
    ss = s[use]
    scale = float(ss.max())
    coef, _ = nnls(np.column_stack([ss / scale, (ss / scale) ** 2]), r[use] ** 2 - noise2)
    return float(coef[0] / scale)


def _core_scale(img, fit: _Fit, sat, noise2, a, psf_sigma_px) -> np.ndarray:
    """Each star's covariance scale: the reduced chi-square of its core pixels (signal above the
    background noise) when above 1, pooled over the stars for one with fewer than
    ``MIN_CORE_PIXELS`` of them."""
    r, s, live = _residuals(img, fit, sat, psf_sigma_px)
    core = live & (s > np.sqrt(noise2))
    chi2 = np.sum(np.where(core, r * r / (noise2 + a * np.maximum(s, 0.0)), 0.0), axis=(1, 2))
    npix = np.count_nonzero(core, axis=(1, 2))
    dof = np.maximum(npix - 4, 1)  # position, flux and background
    pooled = float(chi2.sum() / dof.sum()) if npix.sum() else 1.0
    own = np.where(npix >= MIN_CORE_PIXELS, chi2 / dof, pooled)
    return np.maximum(own, 1.0)


@lru_cache(maxsize=64)
def model_bias_px(psf_sigma_px: float) -> float:
    """RMS per axis, over sub-pixel phases, of the position error of this fit on noiseless spots
    drawn exactly (a Gaussian of sigma ``psf_sigma_px`` integrated over each pixel): the spot model
    approximates the pixel's integration by a widened Gaussian, which an undersampled PSF shows
    (0.01 px at sigma 0.4 px; nothing measurable from 0.8 px). Added to every star's variance."""
    phases = (np.arange(8) + 0.5) / 8.0 - 0.5
    px, py = (g.ravel() for g in np.meshgrid(phases, phases))
    spacing = 2 * int(np.ceil(MARGIN_SIGMAS * psf_sigma_px + 1.0)) + 5
    k = np.arange(px.size)
    x, y = (k % 8) * spacing + spacing // 2 + px, (k // 8) * spacing + spacing // 2 + py
    edges = np.arange(8 * spacing + 1) - 0.5
    img = np.zeros((8 * spacing, 8 * spacing))
    for xi, yi in zip(x, y):
        cx = np.diff(erf((edges - xi) / (np.sqrt(2.0) * psf_sigma_px)))
        cy = np.diff(erf((edges - yi) / (np.sqrt(2.0) * psf_sigma_px)))
        img += 250.0 * np.outer(cy, cx)  # flux 1000
    fit = _fit(img, x, y, np.inf, 1.0, 0.0, psf_sigma_px)
    return float(np.sqrt(0.5 * np.mean((fit.p[:, 0] - x) ** 2 + (fit.p[:, 1] - y) ** 2)))


def _rejections(img, fit: _Fit, x, y, sat, psf_sigma_px) -> np.ndarray:
    """Why each fit is not a measurement of its listed star (``""``: it is)."""
    p, cov = fit.p, fit.cov
    reason = np.full(len(x), "", dtype=object)
    with np.errstate(invalid="ignore", divide="ignore"):
        snr = p[:, 4] / np.sqrt(cov[:, 4, 4])
    finite = np.all(np.isfinite(p), axis=1) & np.isfinite(cov[:, 0, 0]) & np.isfinite(cov[:, 1, 1])
    win = _windows(img, fit.row0, fit.col0, fit.size)  # centred on the listed positions
    saturated = np.any(win >= sat, axis=(1, 2))
    d = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :])
    np.fill_diagonal(d, np.inf)
    blended = d.min(axis=1, initial=np.inf) < max(BLEND_SIGMAS * psf_sigma_px, 3.0)
    shift = np.hypot(p[:, 0] - x, p[:, 1] - y)
    reason[~(snr >= MIN_SNR)] = "low_snr"
    reason[~(shift <= MAX_SHIFT_PX)] = "moved"
    reason[blended] = "blended"
    reason[saturated] = "saturated"
    reason[~finite | ~(cov[:, 0, 0] > 0) | ~(cov[:, 1, 1] > 0)] = "no_fit"
    return reason.astype(str)


def _windows(img, row0: np.ndarray, col0: np.ndarray, size: int) -> np.ndarray:
    """The stars' ``size x size`` windows (n, size, size) from their top-left pixels, NaN beyond
    the image."""
    padded = np.pad(img, size, constant_values=np.nan)
    rows = row0[:, None] + np.arange(size) + size
    cols = col0[:, None] + np.arange(size) + size
    return padded[rows[:, :, None], cols[:, None, :]]


def _saturation(image: np.ndarray) -> float:
    """The level an integer image clips at: its maximum when that is ``2^k - 1`` (k >= 8: the full
    scale of 8-bit data, of 10-, 12- or 14-bit data in a 16-bit container, or of 16-bit data);
    +inf otherwise (no pixel is known to be clipped). A hot pixel at full scale only costs the
    stars whose window holds it their measurement; a clipped core taken as unclipped would bias one."""
    a = np.asarray(image)
    if a.dtype.kind not in "ui" or not a.size:
        return np.inf
    top = int(a.max())
    return float(top) if top >= 255 and (top + 1) & top == 0 else np.inf
