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
