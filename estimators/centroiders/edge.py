"""Centre-of-gravity bias of a spot cut by the detector edge, added to the reported ``sigma_px``.

A spot whose PSF reaches past the first or last row or column loses the light that fell beyond
the edge, and the centre of gravity of what remains is pulled inwards. The background-noise
``sigma_px`` of the centroiders does not see this: with the plain baseline, spots cut by the edge
pushed the attitude error to 2.5 times its reported sigma (docs/reliability.md).

Model (one axis; the detector's pixels cover ``[-0.5, N - 0.5]``): a Gaussian profile of standard
deviation ``s`` centred at ``mu``, cut to the detector, has its centre of gravity at the mean of a
doubly truncated normal (Johnson, Kotz & Balakrishnan, *Continuous Univariate Distributions* 1,
2nd ed. 1994, sec. 10.1)::

    m(mu) = mu + s (phi(a) - phi(b)) / T,   T = Phi(b) - Phi(a),   a = (-0.5 - mu) / s,  b = (N - 0.5 - mu) / s

``m`` increases with ``mu``, so the measured centroid ``x`` gives the model's centre by solving
``m(mu) = x`` and the bias ``x - mu``. ``T`` is the fraction of the profile on the detector. The
width comes from the spot itself: a pixel-sampled Gaussian spot of flux ``F`` has a peak pixel of
about ``F / (2 pi s^2)`` (its centre pixel: 8 % less for ``s`` = 1 px, so ``s`` comes out a little
large, which enlarges the bias: the safe side), and a cut spot has ``F`` times ``T_x T_y`` of the
whole, so ``s^2 = F / (2 pi peak T_x T_y)``; ``s`` and ``mu`` are solved together by fixed-point
iteration (``_ITERATIONS``; each step is a few vectorised array operations over the edge spots).

Reported: ``sigma_px`` with ``max(|bias_x|, |bias_y|)`` added in quadrature (``sigma_px`` is one
isotropic per-axis sigma; the larger axis keeps the cut axis from being under-reported). The
position is left as measured: the thresholded centroiders also drop the far wing on the inner
side, which pulls their centroid back towards the edge, so the model's bias is an upper estimate
rather than a correction (measured against simulation in tests/estimators/test_edge_sigma.py).
Spots with more than ``1 - ON_DETECTOR`` of their profile on the detector are returned unchanged.
"""
from __future__ import annotations

import numpy as np
from numba import njit
from scipy.special import ndtr

ON_DETECTOR = 0.999  # spots with T_x T_y above this are not cut (their sigma_px is returned as is)
_ITERATIONS = 20
_INV_SQRT_2PI = 1.0 / np.sqrt(2.0 * np.pi)


_MARGIN_SIGMAS = 3.3  # Phi(-3.3) = 5e-4 per side: an uncut spot this far inside has T_x T_y > 0.998


@njit(cache=True, nogil=True)
def any_near_edge(x, y, flux, peak, width, height) -> bool:
    """Whether any spot lies within ``_MARGIN_SIGMAS`` of its uncut width of the detector edge (the
    only spots :func:`edge_bias_px` can find cut). Compiled because the windowed centroider asks
    it on every tracking frame, whose whole budget is ~70 us: ~0.5 us here against ~5 us for the
    same test in numpy (six small-array calls)."""
    for i in range(x.size):
        if not (flux[i] > 0.0 and peak[i] > 0.0):
            continue
        m = _MARGIN_SIGMAS * np.sqrt(flux[i] / (2.0 * np.pi * peak[i]))
        if x[i] < m or y[i] < m or x[i] > width - 1 - m or y[i] > height - 1 - m:
            return True
    return False


def _truncated_shift(mu: np.ndarray, s: np.ndarray, n: float) -> tuple[np.ndarray, np.ndarray]:
    """(``m(mu) - mu``, ``T``) of a Gaussian of sigma ``s`` at ``mu`` cut to ``[-0.5, n - 0.5]``."""
    a = (-0.5 - mu) / s
    b = (n - 0.5 - mu) / s
    T = np.maximum(ndtr(b) - ndtr(a), 1e-300)
    shift = s * _INV_SQRT_2PI * (np.exp(-0.5 * a * a) - np.exp(-0.5 * b * b)) / T
    return shift, T


def edge_bias_px(x, y, flux, peak, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per spot: the model's CoG bias along x and y (px, pointing inwards) and whether it is cut.

    ``x, y``: measured centroids (column, row); ``flux``, ``peak``: above background, same units;
    ``shape``: the detector's (rows, columns). Vectorised over spots; spots whose flux or peak is
    not positive get no bias (nothing to estimate a width from) and are not reported cut.
    """
    H, W = shape
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    flux = np.asarray(flux, dtype=float)
    peak = np.asarray(peak, dtype=float)
    bx, by = np.zeros(x.shape), np.zeros(x.shape)
    ok = (flux > 0) & (peak > 0) & np.isfinite(x) & np.isfinite(y)
    s0 = np.sqrt(np.where(ok, flux, 1.0) / (2.0 * np.pi * np.where(ok, peak, 1.0)))
    # a spot whose uncut width already puts the whole profile on the detector is not cut: skip it
    # (the usual case; the cut makes s grow, so this is checked again after the iteration)
    margin = _MARGIN_SIGMAS * s0
    near = ok & ((x < margin) | (y < margin) | (x > W - 1 - margin) | (y > H - 1 - margin))
    cut = np.zeros(x.shape, dtype=bool)
    if not near.any():
        return bx, by, cut
    xm, ym, F, P = x[near], y[near], flux[near], peak[near]
    s = s0[near]
    mx, my = xm.copy(), ym.copy()
    for _ in range(_ITERATIONS):
        dx, tx = _truncated_shift(mx, s, W)
        dy, ty = _truncated_shift(my, s, H)
        mx, my = xm - dx, ym - dy  # fixed point of m(mu) = measured (the shift varies slowly with mu)
        s = np.sqrt(F / (2.0 * np.pi * P * tx * ty))
    dx, tx = _truncated_shift(mx, s, W)
    dy, ty = _truncated_shift(my, s, H)
    is_cut = tx * ty < ON_DETECTOR
    bx[near] = np.where(is_cut, dx, 0.0)
    by[near] = np.where(is_cut, dy, 0.0)
    cut[near] = is_cut
    return bx, by, cut


def with_edge_bias(sigma_px: np.ndarray, x, y, flux, peak, shape: tuple[int, int],
                   only: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(``sigma_px`` with the edge bias of cut spots added in quadrature, mask of cut spots).

    ``only``: the spots that can be cut (``cog`` passes those with a pixel on the outermost rows
    or columns: a thresholded spot that does not reach the edge has the same pixels, and so the same
    centroid, as on an endless detector); None: every spot the model finds cut."""
    bx, by, cut = edge_bias_px(x, y, flux, peak, shape)
    if only is not None:
        cut &= np.asarray(only, dtype=bool)
    if not cut.any():
        return sigma_px, cut
    return np.where(cut, np.hypot(sigma_px, np.maximum(np.abs(bx), np.abs(by))), sigma_px), cut
