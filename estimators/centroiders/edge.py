"""Centre-of-gravity bias of a spot cut by the detector edge, added to the reported position covariance.

A spot whose PSF reaches past the first or last row or column loses the light that fell beyond
the edge, and the centre of gravity of what remains is pulled inwards. The background-noise
covariance of the centroiders does not see this: with the plain baseline, spots cut by the edge
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
iteration (``_ITERATIONS`` steps per spot that reaches the edge, compiled: on a handful of spots
a vectorised numpy loop is all per-call overhead, 0.3-0.7 ms a frame, more than a tracked frame's
whole window fit; `benchmarks/centroid_speed.py`, edge term column).

Reported: the position covariance with ``diag(bias_x^2, bias_y^2)`` added (the bias lies along
the axis the edge cuts; ``sigma_px`` follows from the covariance, covariance.py). The position
is left as measured: the thresholded centroiders also drop the far wing on the inner
side, which pulls their centroid back towards the edge, so the model's bias is an upper estimate
rather than a correction (measured against simulation in tests/estimators/test_edge_sigma.py).
Spots with more than ``1 - ON_DETECTOR`` of their profile on the detector are returned unchanged.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from rollingstar.estimators.centroiders.covariance import with_axes

ON_DETECTOR = 0.999  # spots with T_x T_y above this are not cut (their covariance is returned as is)
MARGIN_SIGMAS = 3.3  # Phi(-3.3) = 5e-4 per side: an uncut spot this far inside has T_x T_y > 0.998
_ITERATIONS = 20
_INV_SQRT_2PI = 1.0 / np.sqrt(2.0 * np.pi)


@njit(cache=True, nogil=True)
def _fixed_point(meas, width_sq, n_x, n_y, iterations):  # pragma: no cover - compiled
    """(``m(mu) - mu``, ``T``) at the fixed point of ``m(mu) = measured``, spot by spot, as
    :func:`edge_bias_px` defines it: ``meas`` holds the spots' x then their y (2k,), ``width_sq``
    their uncut ``s^2`` (k,); ``n_x, n_y`` the detector's columns and rows. Both outputs are laid
    out as ``meas``."""
    k = width_sq.size
    d = np.empty(2 * k)
    T = np.empty(2 * k)
    mu = np.empty(2)
    n = np.array([n_x, n_y])
    for i in range(k):
        s = math.sqrt(width_sq[i])
        for a in range(2):
            mu[a] = min(max(meas[a * k + i], -0.5), n[a] - 0.5)
        for step in range(iterations + 1):
            for a in range(2):
                d[a * k + i], T[a * k + i] = _shift(mu[a], s, n[a])
            if step == iterations:
                break
            for a in range(2):
                mu[a] = min(max(meas[a * k + i] - d[a * k + i], -0.5), n[a] - 0.5)
            s = math.sqrt(width_sq[i] / (T[i] * T[k + i]))
    return d, T


@njit(cache=True, nogil=True, inline="always")
def _shift(mu, s, n):  # pragma: no cover - compiled
    """(``m(mu) - mu``, ``T``) of a Gaussian of sigma ``s`` at ``mu`` cut to ``[-0.5, n - 0.5]``
    (``T >= 0.5`` while ``mu`` is on the detector; the iteration keeps it there)."""
    a = (-0.5 - mu) / s
    b = (n - 0.5 - mu) / s
    T = 0.5 * (math.erfc(-b / math.sqrt(2.0)) - math.erfc(-a / math.sqrt(2.0)))
    return s * _INV_SQRT_2PI * (math.exp(-0.5 * a * a) - math.exp(-0.5 * b * b)) / T, T


def near_edge(x, y, flux, peak, shape: tuple[int, int]) -> np.ndarray:
    """Spots within ``MARGIN_SIGMAS`` uncut widths of the edge: the only ones the cut can move."""
    H, W = shape
    ok = (flux > 0) & (peak > 0) & np.isfinite(x) & np.isfinite(y)
    margin = MARGIN_SIGMAS * np.sqrt(np.where(ok, flux, 1.0) / (2.0 * np.pi * np.where(ok, peak, 1.0)))
    return ok & ((x < margin) | (y < margin) | (x > W - 1 - margin) | (y > H - 1 - margin))


def edge_bias_px(x, y, flux, peak, shape: tuple[int, int],
                 candidates: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per spot: the model's CoG bias along x and y (px, pointing inwards) and whether it is cut.

    ``x, y``: measured centroids (column, row); ``flux``, ``peak``: above background, same units;
    ``shape``: the detector's (rows, columns). Vectorised over the spots near the edge; spots whose
    flux or peak is not positive get no bias (nothing to estimate a width from) and are not cut.
    ``candidates``: a mask of the spots that can be cut at all (see :func:`with_edge_bias`); the
    others are not modelled.

    The model's centre is kept on the detector (``[-0.5, N - 0.5]``): a detected spot's centre is
    there or just beyond it, and outside the peak pixel is no longer the profile's peak, so the
    width relation would let ``s`` and ``mu`` run away together. On the detector ``T >= 1/2`` per
    axis, so ``s`` stays within 2x its uncut value. For a fixed width the centre's update contracts
    by ``1 - Var/s^2`` of the truncated normal (<= 0.64 with the centre on the detector); the width
    is updated alongside, which slows it, and the iterates approach the fixed point from below.
    ``_ITERATIONS`` = 20 steps give 87-100 % of the 200-step bias for spots from 0.4 px outside to
    4 px inside the edge (the slowest: a 2 px PSF centred at the edge, whose centre ends on the
    clamp; tests/estimators/test_edge_sigma.py::test_the_fixed_point_has_converged). What counts,
    the 20-step bias against the true CoG bias, is tested directly (0.92-3.1x).
    """
    H, W = shape
    x, y, flux, peak = (np.asarray(v, dtype=float).reshape(-1) for v in (x, y, flux, peak))
    bx, by, cut = np.zeros(x.size), np.zeros(x.size), np.zeros(x.size, dtype=bool)
    near = near_edge(x, y, flux, peak, shape)
    if candidates is not None:
        near &= np.asarray(candidates, dtype=bool).reshape(-1)
    if not near.any():
        return bx, by, cut
    d, T = _fixed_point(np.concatenate([x[near], y[near]]), flux[near] / (2.0 * np.pi * peak[near]),
                        float(W), float(H), max(int(_ITERATIONS), 0))
    k = int(near.sum())
    dx, dy, tx, ty = d[:k], d[k:], T[:k], T[k:]
    is_cut = tx * ty < ON_DETECTOR
    bx[near] = np.where(is_cut, dx, 0.0)
    by[near] = np.where(is_cut, dy, 0.0)
    cut[near] = is_cut
    return bx, by, cut


def with_edge_covariance(cov: np.ndarray, x, y, flux, peak, shape: tuple[int, int],
                         only: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(``cov`` with the edge bias of cut spots added along the axes of the cut, mask of cut spots).

    ``cov``: rows ``(xx, xy, yy)`` (3, n), px^2; a cut spot gets ``diag(bias_x^2, bias_y^2)``
    added (its bias points inwards along the axis the edge cuts; its size is an upper estimate,
    module docstring). ``only``: the spots that can be cut (``cog`` passes those with a pixel on
    the outermost rows or columns: a thresholded spot that does not reach the edge has the same
    pixels, and so the same centroid, as on an endless detector); None: every spot the model
    finds cut. ``cov`` is returned as is (the same object) when no spot is cut."""
    bx, by, cut = edge_bias_px(x, y, flux, peak, shape, candidates=only)
    if not cut.any():
        return cov, cut
    return with_axes(cov, np.where(cut, bx, 0.0), np.where(cut, by, 0.0)), cut
