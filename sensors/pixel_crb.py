"""Pixel-level Cramér–Rao bound of one star's position: the Fisher information of its pixels.

The centroid-level bound the evaluation quotes takes a centroid sigma as given; this one derives
it from the pixels. Model of one spot on a pixel grid: the expected signal of pixel ``j`` (column
``u_j``, row ``v_j``, electrons) is

    mu_j = F * g(u_j - x) * g(v_j - y) + b,   g(d) = Phi((d + 1/2) / s) - Phi((d - 1/2) / s)

(a Gaussian PSF of width ``s`` integrated over the square pixel, ``F`` the star's electrons, ``b``
the background electrons per pixel); each pixel's noise is Poisson (shot noise of star and
background) plus Gaussian read noise ``r``. The Fisher information for parameters ``theta`` is

    I = sum_j (d mu_j / d theta)(d mu_j / d theta)^T / (mu_j + r^2)

exact for Poisson pixels (``r = 0``) and the usual approximation with read noise (Mortensen et
al. 2010, Nat. Methods 7:377, for the same model). Parameters: ``x, y`` and the nuisances ``F``
and ``b``; the bound on the position is the ``(x, y)`` block of ``I^-1``. Known answer: a
well-sampled spot without background or read noise gives ``var(x) = (s^2 + 1/12) / F`` (the PSF
variance plus the pixel's).

A moving star (:func:`smeared_spot_fisher`) is the same PSF swept along its image velocity
``(vx, vy)`` (px/s) over each row's own exposure window: row ``v`` starts ``(v - y) * line_delay``
after the star's own row, so its segment is ``x + vx (tau + (v - y) ld)``, ``tau`` over the exposure
``E``, and the pixel's expectation is the average of the PSF over that segment (``n_sub`` points).
Parameters ``(x, y, vx, vy, F, b)``: the position at the star's own row's mid-exposure (the time
a raw centroid refers to), its velocity, flux and background; derivatives by central differences.
ADC quantisation adds ``gain^2 / 12`` e^2 to each pixel's variance, and a pixel whose expectation
reaches the full well carries no information (it reads the saturation level whatever the
parameters).
Written by hand: the sum is a dozen numpy lines, and no maintained package computes it.
"""
from __future__ import annotations

import numpy as np
from scipy.special import ndtr

_SQRT_2PI = np.sqrt(2.0 * np.pi)


def _pixel_profile(d: np.ndarray, s: float) -> tuple[np.ndarray, np.ndarray]:
    """The PSF integrated over pixels at offsets ``d`` from the centre, and its derivative in the centre."""
    hi, lo = (d + 0.5) / s, (d - 0.5) / s
    g = ndtr(hi) - ndtr(lo)
    # d g / d centre = -d g / d d = -(phi(hi) - phi(lo)) / s
    dg = -(np.exp(-0.5 * hi**2) - np.exp(-0.5 * lo**2)) / (_SQRT_2PI * s)
    return g, dg


def spot_fisher(x: float, y: float, flux_e: float, psf_sigma_px: float, background_e: float = 0.0,
                read_noise_e: float = 0.0, half_width_px: int | None = None) -> np.ndarray:
    """Fisher information (4 x 4) of ``(x, y, flux, background)`` from the pixels around the spot
    (module docstring); ``half_width_px`` the window's half width (default ``ceil(6 s) + 1``)."""
    s = float(psf_sigma_px)
    h = int(np.ceil(6.0 * s)) + 1 if half_width_px is None else int(half_width_px)
    cols = np.arange(np.floor(x) - h, np.floor(x) + h + 1)
    rows = np.arange(np.floor(y) - h, np.floor(y) + h + 1)
    gx, dgx = _pixel_profile(cols - x, s)
    gy, dgy = _pixel_profile(rows - y, s)
    shape = np.outer(gy, gx)  # rows x columns
    mu = flux_e * shape + background_e
    grads = np.stack([flux_e * np.outer(gy, dgx), flux_e * np.outer(dgy, gx), shape,
                      np.ones_like(shape)]).reshape(4, -1)
    var = mu.reshape(-1) + float(read_noise_e) ** 2
    return (grads / var) @ grads.T


def position_crb_px(x: float, y: float, flux_e: float, psf_sigma_px: float, background_e: float = 0.0,
                    read_noise_e: float = 0.0) -> np.ndarray:
    """The Cramér–Rao bound (2 x 2 covariance, px^2) of the spot's ``(x, y)`` with its flux and the
    background unknown too."""
    info = spot_fisher(x, y, flux_e, psf_sigma_px, background_e, read_noise_e)
    return np.linalg.inv(info)[:2, :2]


def _smeared_mu(p: np.ndarray, cols: np.ndarray, rows: np.ndarray, s: float, exposure_s: float,
                line_delay_s: float, n_sub: int) -> np.ndarray:
    """Expected electrons (rows x columns) of a swept spot, ``p = (x, y, vx, vy, F, b)``."""
    x, y, vx, vy, flux, b = p
    tau = (np.arange(n_sub) + 0.5) / n_sub * exposure_s - 0.5 * exposure_s  # about mid-exposure
    shift = tau[:, None] + (rows[None, :] - y) * line_delay_s  # (n_sub, rows): time from the reference
    cx = x + vx * shift  # (n_sub, rows)
    cy = y + vy * shift
    hi_x = (cols[None, None, :] - cx[:, :, None] + 0.5) / s
    lo_x = (cols[None, None, :] - cx[:, :, None] - 0.5) / s
    hi_y = (rows[None, :] - cy + 0.5) / s
    lo_y = (rows[None, :] - cy - 0.5) / s
    gx = ndtr(hi_x) - ndtr(lo_x)  # (n_sub, rows, cols)
    gy = (ndtr(hi_y) - ndtr(lo_y))[:, :, None]
    return flux * np.mean(gx * gy, axis=0) + b


def smeared_spot_fisher(x: float, y: float, vx: float, vy: float, flux_e: float, psf_sigma_px: float,
                        exposure_s: float, line_delay_s: float = 0.0, background_e: float = 0.0,
                        read_noise_e: float = 0.0, gain_e_per_adu: float = 0.0, full_well_e: float = np.inf,
                        n_sub: int = 64) -> np.ndarray:
    """Fisher information (6 x 6) of ``(x, y, vx, vy, flux, background)`` of a star moving during
    its rolling-shutter exposure (module docstring); ``gain_e_per_adu`` 0: no quantisation."""
    s = float(psf_sigma_px)
    reach = abs(vx) + abs(vy)
    h = int(np.ceil(6.0 * s + 0.5 * reach * (exposure_s + 12.0 * s * line_delay_s))) + 1
    cols = np.arange(np.floor(x) - h, np.floor(x) + h + 1)
    rows = np.arange(np.floor(y) - h, np.floor(y) + h + 1)
    p = np.array([x, y, vx, vy, flux_e, background_e], dtype=float)
    steps = np.array([1e-4, 1e-4, 1e-2, 1e-2, 1e-3 * max(flux_e, 1.0), 1e-3 * max(background_e, 1.0)])
    mu = _smeared_mu(p, cols, rows, s, exposure_s, line_delay_s, n_sub)
    grads = np.empty((6, mu.size))
    for k in range(6):
        dp = np.zeros(6)
        dp[k] = steps[k]
        grads[k] = ((_smeared_mu(p + dp, cols, rows, s, exposure_s, line_delay_s, n_sub)
                     - _smeared_mu(p - dp, cols, rows, s, exposure_s, line_delay_s, n_sub)) / (2.0 * steps[k])).ravel()
    var = mu.ravel() + float(read_noise_e) ** 2 + float(gain_e_per_adu) ** 2 / 12.0
    live = mu.ravel() < full_well_e
    return (grads[:, live] / var[live]) @ grads[:, live].T
