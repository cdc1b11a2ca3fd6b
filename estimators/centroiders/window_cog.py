"""Centre-of-gravity centroiding of many small windows in one vectorised pass (liu2013 sec 2.1).

The ``windowed`` centroider's ``kernel: numpy`` path: an independent check of the compiled kernel
``window_kernel.py`` (which gives the same spots for the same background and noise) and the
"before" of ``benchmarks/windowed_speed.py``.

The windowed centroider (``estimators/centroiders/windowed.py``) reads a few ``h x w`` windows per
frame. Centroiding them one ``cog`` call at a time costs a fixed Python/numpy overhead per window
(measured: ~1 ms per 64 x 64 window, most of the windowed chain); here all windows are stacked
into one ``(n, h, w)`` array and every step runs once for the stack:

1. background ``b_k``: the median of window ``k`` (the ``cog`` "median" background per window);
2. noise ``s_k``: ``1.4826 MAD``, then the standard deviation of the pixels within ``5 s0`` of the
   median, then the RMS about the median of those within ``3 s1`` divided by 0.98658 (the std of a
   unit normal truncated to +-3; the clipped steps remove the quantisation bias of the MAD on
   integer pixels), floored at ``noise_floor_adu`` -- the ``cog`` robust sigma, per window;
3. pixels with ``I - b_k > threshold_sigma * s_k`` are labelled in 3-D with a structuring element
   that is empty across windows (``scipy.ndimage.label``), so components never join two windows;
   components with fewer than ``min_pixels`` (more than ``max_pixels``) pixels are dropped
   (before growing, so that they do not grow into their neighbours);
4. each component grows by ``grow_px`` rings of below-threshold pixels inside its window (the
   higher label wins where rings meet), then per component (``np.bincount``) with ``d = I - b``:
   ``flux = sum d``, ``x = sum d x / flux``, ``y = sum d y / flux``, ``peak``, ``npix``,
   ``saturated``, ``snr = flux / sqrt(npix s^2 + flux / g)`` (no shot term without a gain ``g``),
   the 2 x 2 position covariance ``cov`` of :func:`rollingstar.estimators.centroiders.covariance.spot_covariance`
   (noise propagation with the window's noise ``s``, threshold mask, clipping) and
   ``sigma_px = sqrt((cov_xx + cov_yy) / 2)``;
5. per window the kept component nearest to the window's predicted position is returned.

This is the ``cog`` centroider's definition (Liebe 2002; see ``estimators/centroiders/cog.py``)
applied per window, re-implemented for a stack because ``cog`` works on one image at a time.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from rollingstar.estimators.centroiders.covariance import (
    isotropic_sigma,
    label_moments,
    pixel_variance,
    spot_covariance,
)

_MAD_TO_SIGMA = 1.482602218505602
_TRUNC3 = 0.98658  # std of a unit normal truncated to +-3


@dataclass(frozen=True)
class WindowSpots:
    """The spot picked in each window (window pixel coordinates); ``found`` False where none."""

    found: np.ndarray
    x: np.ndarray
    y: np.ndarray
    flux: np.ndarray
    peak: np.ndarray
    npix: np.ndarray
    saturated: np.ndarray
    snr: np.ndarray
    sigma_px: np.ndarray
    cov: np.ndarray  # (3, n): xx, xy, yy (px^2)


def cut_windows(image: np.ndarray, r0: np.ndarray, c0: np.ndarray, h: int, w: int) -> np.ndarray:
    """``(n, h, w)`` stack of ``image[r0_k : r0_k + h, c0_k : c0_k + w]`` (one fancy-indexing gather)."""
    rows = np.asarray(r0, dtype=np.intp)[:, None, None] + np.arange(h)[None, :, None]
    cols = np.asarray(c0, dtype=np.intp)[:, None, None] + np.arange(w)[None, None, :]
    return image[rows, cols]


def median_rows(a: np.ndarray) -> np.ndarray:
    """Median of every row of ``a`` (n, m) by one ``np.partition`` (np.median's overhead is most of
    its cost on 64 x 64 windows)."""
    m = a.shape[1]
    k = m // 2
    if m % 2:
        return np.partition(a, k, axis=1)[:, k]
    part = np.partition(a, (k - 1, k), axis=1)
    return 0.5 * (part[:, k - 1] + part[:, k])


def robust_sigma_rows(r: np.ndarray, med: np.ndarray | None = None) -> np.ndarray:
    """The ``cog`` robust noise sigma (module docstring step 2) of every row of ``r`` (n, m);
    ``med``: the rows' medians when already known (0 for background-subtracted windows)."""
    med = (median_rows(r) if med is None else np.asarray(med, dtype=float))[:, None]
    dev = np.abs(r - med)
    s0 = _MAD_TO_SIGMA * median_rows(dev)[:, None]
    m5 = dev < 5.0 * s0
    c5 = np.maximum(m5.sum(axis=1, keepdims=True), 1)
    mean5 = np.sum(r * m5, axis=1, keepdims=True) / c5
    s1 = np.sqrt(np.sum((r - mean5) ** 2 * m5, axis=1, keepdims=True) / c5)
    m3 = dev < 3.0 * s1
    s = np.sqrt(np.sum((r - med) ** 2 * m3, axis=1, keepdims=True) / np.maximum(m3.sum(axis=1, keepdims=True), 1)) / _TRUNC3
    s = np.where(s1 > 0, s, s0)  # s0 when the clipped std vanishes
    return np.where(s0[:, 0] > 0, s[:, 0], 0.0)


def _grow(flat: np.ndarray, labels: np.ndarray, shape: tuple[int, int, int], eight: bool) -> tuple[np.ndarray, np.ndarray]:
    """Add the ring of in-window neighbours around labelled pixels (flat indices into ``shape``);
    core pixels keep their label, elsewhere the higher label wins."""
    n, H, W = shape
    k, rem = np.divmod(flat, H * W)
    r, c = np.divmod(rem, W)
    offsets = [(-1, 0), (1, 0), (0, -1), (0, 1)] + ([(-1, -1), (-1, 1), (1, -1), (1, 1)] if eight else [])
    dr = np.array([o[0] for o in offsets])[:, None]
    dc = np.array([o[1] for o in offsets])[:, None]
    rr, cc = r[None, :] + dr, c[None, :] + dc
    ok = (rr >= 0) & (rr < H) & (cc >= 0) & (cc < W)
    nb_flat = ((k[None, :] * H + rr) * W + cc)[ok]
    nb_lab = np.broadcast_to(labels, rr.shape)[ok]
    all_flat = np.concatenate([flat, nb_flat])
    all_lab = np.concatenate([labels, nb_lab])
    rank = np.concatenate([labels.astype(np.int64) + (1 << 40), nb_lab.astype(np.int64)])
    order = np.lexsort((-rank, all_flat))
    all_flat, all_lab = all_flat[order], all_lab[order]
    first = np.concatenate([[True], all_flat[1:] != all_flat[:-1]])
    return all_flat[first], all_lab[first]


def centroid_windows(stack: np.ndarray, px: np.ndarray, py: np.ndarray, *, threshold_sigma: float, min_pixels: int,
                     max_pixels: int | None, connectivity: int, grow_px: int, noise_floor_adu: float,
                     saturation_adu: float, reject_border: bool = False, gain_e_per_adu: float | None = None,
                     cov_gain_e_per_adu: float | None = None) -> WindowSpots:
    """CoG of every window of ``stack`` (n, h, w) in one pass; per window the spot nearest to
    ``(px_k, py_k)`` (window coordinates). See the module docstring for the steps.
    ``gain_e_per_adu``: the shot-noise term of ``snr``; ``cov_gain_e_per_adu``: that of the
    covariance (None: left out)."""
    raw = np.asarray(stack)
    n, H, W = raw.shape
    img = raw.astype(float)
    bg = median_rows(img.reshape(n, -1))
    resid = img - bg[:, None, None]
    noise = np.maximum(robust_sigma_rows(resid.reshape(n, -1), np.zeros(n)), noise_floor_adu)
    labels, n_lab = _label_windows(resid > threshold_sigma * noise[:, None, None], connectivity)
    if n_lab == 0:
        empty = np.full(n, np.nan)
        return WindowSpots(np.zeros(n, dtype=bool), empty, empty.copy(), empty.copy(), empty.copy(),
                           np.zeros(n, dtype=int), np.zeros(n, dtype=bool), empty.copy(), empty.copy(),
                           np.full((3, n), np.nan))
    size = n_lab + 1
    flat = np.flatnonzero(labels)
    lab = labels.ravel()[flat]
    n_above = np.bincount(lab, minlength=size)[1:]
    raw_max = np.full(size, -np.inf)
    np.maximum.at(raw_max, lab, raw.ravel()[flat].astype(float))
    win_of = np.zeros(size, dtype=np.intp)
    win_of[lab] = flat // (H * W)
    keep = n_above >= min_pixels
    if max_pixels is not None:
        keep &= n_above <= max_pixels
    sel = keep[lab - 1]  # rejected components do not grow into their neighbours
    flat, lab = flat[sel], lab[sel]
    for _ in range(grow_px):
        flat, lab = _grow(flat, lab, (n, H, W), connectivity == 8)
    d = resid.ravel()[flat]
    rem = flat % (H * W)
    rows, cols = np.divmod(rem, W)
    rows = rows.astype(float)
    cols = cols.astype(float)
    npix = np.bincount(lab, minlength=size)[1:]
    flux = np.bincount(lab, weights=d, minlength=size)[1:]
    sx = np.bincount(lab, weights=d * cols, minlength=size)[1:]
    sy = np.bincount(lab, weights=d * rows, minlength=size)[1:]
    peak = np.full(size, -np.inf)
    np.maximum.at(peak, lab, d)
    keep &= flux > 0
    if reject_border:
        border = np.zeros(size, dtype=bool)
        border[lab[(rows == 0) | (rows == H - 1) | (cols == 0) | (cols == W - 1)]] = True
        keep &= ~border[1:]
    win = win_of[1:]
    s = noise[win]
    with np.errstate(invalid="ignore", divide="ignore"):
        x = sx / flux
        y = sy / flux
        saturated = raw_max[1:] >= saturation_adu
        clipped = raw.ravel()[flat] >= saturation_adu
        n_sat = np.bincount(lab, weights=clipped, minlength=size)[1:]
        dx, dy = cols - np.r_[0.0, x][lab], rows - np.r_[0.0, y][lab]
        var = pixel_variance(d, noise[win_of[lab]], cov_gain_e_per_adu, clipped)
        cov = spot_covariance(label_moments(lab, size, var, dx, dy), label_moments(lab, size, d, dx, dy) / flux, flux,
                              threshold_sigma * s, s, cov_gain_e_per_adu, n_sat, saturated, saturation_adu - bg[win])
        shot = 0.0 if gain_e_per_adu is None else np.maximum(flux, 0.0) / gain_e_per_adu
        snr = flux / np.sqrt(npix * s**2 + shot)
    pick = _nearest_kept(keep, x, y, flux, win, px, py)
    found = np.zeros(n, dtype=bool)
    found[win[pick]] = True

    def per_window(values, fill=np.nan, dtype=float):
        out = np.full(n, fill, dtype=dtype)
        out[win[pick]] = values[pick]
        return out

    cov_w = np.stack([per_window(c) for c in cov])
    return WindowSpots(found, per_window(x), per_window(y), per_window(flux), per_window(peak[1:]),
                       per_window(npix, 0, int), per_window(saturated, False, bool),
                       per_window(snr), isotropic_sigma(cov_w), cov_w)


def _label_windows(mask: np.ndarray, connectivity: int) -> tuple[np.ndarray, int]:
    """Connected components of the above-threshold pixels of a window stack (n, h, w), labelled in
    3-D with a structuring element that is empty across windows: no component joins two windows."""
    plane = np.ones((3, 3), dtype=bool) if connectivity == 8 else ndimage.generate_binary_structure(2, 1)
    structure = np.zeros((3, 3, 3), dtype=bool)
    structure[1] = plane  # no connection between windows
    return ndimage.label(mask, structure=structure)


def _nearest_kept(keep, x, y, flux, win, px, py) -> np.ndarray:
    """Per window, the kept spot nearest to the prediction ``(px, py)`` (ties: the brighter, as cog
    orders by flux); spot indices, at most one per window."""
    cand = np.flatnonzero(keep)
    d2 = (x[cand] - np.asarray(px, dtype=float)[win[cand]]) ** 2 + (y[cand] - np.asarray(py, dtype=float)[win[cand]]) ** 2
    order = np.lexsort((-flux[cand], d2, win[cand]))
    cand = cand[order]
    first = np.concatenate([[True], win[cand][1:] != win[cand][:-1]]) if cand.size else np.zeros(0, dtype=bool)
    return cand[first]
