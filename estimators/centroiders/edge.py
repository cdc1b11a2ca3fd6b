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
iteration (``_ITERATIONS``, compiled, spot by spot).

Reported: ``sigma_px`` with ``max(|bias_x|, |bias_y|)`` added in quadrature (``sigma_px`` is one
isotropic per-axis sigma; the larger axis keeps the cut axis from being under-reported). The
position is left as measured: the thresholded centroiders also drop the far wing on the inner
side, which pulls their centroid back towards the edge, so the model's bias is an upper estimate
rather than a correction (measured against simulation in tests/estimators/test_edge_sigma.py).
Spots with more than ``1 - ON_DETECTOR`` of their profile on the detector are returned unchanged.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

ON_DETECTOR = 0.999  # spots with T_x T_y above this are not cut (their sigma_px is returned as is)
_ITERATIONS = 20
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
_INV_SQRT_2 = 1.0 / math.sqrt(2.0)
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
        m = _MARGIN_SIGMAS * math.sqrt(flux[i] / (2.0 * math.pi * peak[i]))
        if x[i] < m or y[i] < m or x[i] > width - 1 - m or y[i] > height - 1 - m:
            return True
    return False


@njit(cache=True, nogil=True)
def _truncated_shift(mu: float, s: float, n: float) -> tuple[float, float]:
    """(``m(mu) - mu``, ``T``) of a Gaussian of sigma ``s`` at ``mu`` cut to ``[-0.5, n - 0.5]``."""
    a = (-0.5 - mu) / s
    b = (n - 0.5 - mu) / s
    T = max(0.5 * (math.erfc(-b * _INV_SQRT_2) - math.erfc(-a * _INV_SQRT_2)), 1e-300)  # Phi(b) - Phi(a)
    return s * _INV_SQRT_2PI * (math.exp(-0.5 * a * a) - math.exp(-0.5 * b * b)) / T, T


@njit(cache=True, nogil=True)
def _solve(x, y, flux, peak, width, height, bx, by, cut) -> None:
    """The module docstring's fixed point, spot by spot (compiled: scalar maths over a handful of
    spots, where numpy's per-call cost made it ~0.5 ms per frame with cut spots)."""
    for i in range(x.size):
        if not (flux[i] > 0.0 and peak[i] > 0.0 and math.isfinite(x[i]) and math.isfinite(y[i])):
            continue
        s = math.sqrt(flux[i] / (2.0 * math.pi * peak[i]))
        m = _MARGIN_SIGMAS * s
        if not (x[i] < m or y[i] < m or x[i] > width - 1 - m or y[i] > height - 1 - m):
            continue  # the uncut width puts the whole profile on the detector (the usual case)
        mx, my = x[i], y[i]
        for _ in range(_ITERATIONS):
            dx, tx = _truncated_shift(mx, s, width)
            dy, ty = _truncated_shift(my, s, height)
            mx, my = x[i] - dx, y[i] - dy  # fixed point of m(mu) = measured (|dm/dmu - 1| < 1)
            s = math.sqrt(flux[i] / (2.0 * math.pi * peak[i] * tx * ty))
        dx, tx = _truncated_shift(mx, s, width)
        dy, ty = _truncated_shift(my, s, height)
        if tx * ty < ON_DETECTOR:
            bx[i], by[i], cut[i] = dx, dy, True


def edge_bias_px(x, y, flux, peak, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per spot: the model's CoG bias along x and y (px, pointing inwards) and whether it is cut.

    ``x, y``: measured centroids (column, row); ``flux``, ``peak``: above background, same units;
    ``shape``: the detector's (rows, columns). Spots whose flux or peak is not positive get no
    bias (nothing to estimate a width from) and are not reported cut.
    """
    H, W = shape
    x, y, flux, peak = (np.ascontiguousarray(v, dtype=float).reshape(-1) for v in (x, y, flux, peak))
    bx, by, cut = np.zeros(x.size), np.zeros(x.size), np.zeros(x.size, dtype=bool)
    _solve(x, y, flux, peak, float(W), float(H), bx, by, cut)
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
