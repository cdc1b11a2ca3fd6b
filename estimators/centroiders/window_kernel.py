"""Compiled CoG of a few readout windows, read in place from the frame (liu2013 sec 2.1; numba).

The same spot definition as :func:`rollingstar.estimators.centroiders.window_cog.centroid_windows` (the ``cog``
centroider's, applied per window; see that module's docstring, steps 3-5), given each window's
background ``b_k`` and noise ``s_k``:

1. ``d = I - b_k`` over window ``k`` (read straight from the frame at ``(r0_k, c0_k)``: no copy of
   the windows); pixels with ``d > threshold_k`` are grouped into connected components (8- or
   4-connectivity) by a flood fill started at each not yet labelled pixel in raster order, so the
   labels are numbered in the order of each component's first pixel (as ``scipy.ndimage.label``
   and ``cog`` number them); components with fewer than ``min_pixels`` (more than ``max_pixels``)
   pixels above threshold are dropped;
2. ``grow_px`` rings of in-window neighbours are added, a ring pixel taking the highest label among
   its labelled neighbours (``cog``'s rule);
3. per component: ``flux = sum d``, ``x = sum d x / flux``, ``y = sum d y / flux``, ``peak = max d``,
   ``npix``, ``saturated = max I >= saturation`` (over the pixels above threshold),
   ``snr = flux / sqrt(npix s^2 + flux / g)`` and the number of pixels at the saturation level;
   components with ``flux <= 0`` (or, with ``reject_border``, touching the window edge) are dropped;
4. per window the component whose centroid is nearest to the predicted position ``(px_k, py_k)``
   (window coordinates) is returned, ties to the brighter, with its second moments: the noise
   moments ``sum var_i (r_i - r)(r_i - r)^T`` and the shape moments ``sum d_i (r_i - r)(r_i - r)^T /
   flux``, from which the callers compute its position covariance in numpy
   (:func:`window_covariance`: the model and the clipped-spot Bessel sums are scipy's).

It also returns, per window, the sums over the *background* pixels (every ``BG_STEP``-th row,
outside every grown spot, ``|d| < clip_sigma s_k`` with ``clip_sigma = min(3, threshold_sigma)``)
that the ``windowed`` centroider's tracked background needs: ``count``, ``sum d`` and
``sum d^2``; :func:`track_windows` does a whole windowed frame (prediction included) in one call.

Why compiled code (numba; hand-written because no library centroids a handful of windows in
place): the work per frame is tiny (two 64 x 64 windows are 8192 pixels, ~1 % of a 1000 x 1000
frame), so a numpy implementation is bound by the fixed cost per array operation, not by pixels:
measured on this machine, cutting two windows, thresholding and ``ndimage.label`` alone take
~0.25 ms, already more than the 0.11 ms a 20x speed-up over the 2.2 ms full-frame ``cog`` allows,
and the complete vectorised numpy pass (``centroid_windows``) takes ~1 ms. Compiled, the loop over
the windows' pixels costs microseconds (``benchmarks/windowed_speed.py``).
"""
from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit

from rollingstar.estimators.centroiders.covariance import (
    END_COHERENT,
    MIN_MARGIN,
    MIN_WIDTH_PX,
    PHASE_BIAS,
    TRUNCATION_ACROSS,
    TRUNCATION_ALONG,
    clipping_covariance,
    isotropic_sigma,
    spot_shape,
)
from rollingstar.estimators.centroiders.edge import MARGIN_SIGMAS
from rollingstar.estimators.centroiders.window_cog import WindowSpots
from rollingstar.estimators.centroiders.window_gyro import gyro_increment

N_VALS = 12  # rows of the kernel's per-window values (centroid_windows_kernel)
BG_STEP = 4  # background sums over every 4th row (all columns, contiguous): 1024 of a 64 x 64 window's pixels


@njit(cache=True, nogil=True, error_model="numpy")
def centroid_windows_kernel(image, integer, r0, c0, h, w, px, py, bg, noise, threshold_sigma, min_pixels, max_pixels,
                            eight, grow_px, saturation, reject_border, gain, cov_gain, alpha, noise_floor, clip_sigma,
                            trunc, iwork, fwork, bwork):  # pragma: no cover
    """See the module docstring. ``image`` 2-D (any real dtype; ``integer``: an integer dtype, then
    ``I - b > t`` is tested as ``I > floor(b + t)`` in integers, as ``cog`` does); ``r0, c0`` (n,)
    int64 window origins with the windows inside the frame; ``px, py, bg, noise`` (n,) float64;
    ``max_pixels < 0``: no limit; ``gain <= 0``: no shot-noise term. ``px, py`` and the returned
    ``x, y`` are in frame coordinates. Background sums over
    ``|d| < clip_sigma s``; ``alpha > 0``: afterwards ``bg`` and ``noise`` are updated in place
    by the running mean (:func:`update_background`, ``trunc``: the std of a unit normal truncated
    to ``+-clip_sigma``). ``iwork``, ``fwork`` and ``bwork`` are scratch buffers from
    :func:`workspace` (allocated once: zeroing fresh buffers costs more than the windows).

    Returns ``found (n,) bool, vals (12, n) float64 [x, y, flux, peak, snr, n_saturated, noise moments
    sum var (r - r_c)(r - r_c)^T as xx, xy, yy, shape moments sum d (r - r_c)(r - r_c)^T / flux as
    xx, xy, yy]`` (``var = s^2 + max(d, 0) / cov_gain``, no shot term when ``cov_gain <= 0``, 0 for
    pixels at the saturation level; the callers turn the moments into the covariance with
    :func:`rollingstar.estimators.centroiders.covariance.spot_covariance`),
    npix (n,) int64, saturated (n,) bool, bgsum (n, 3) float64 [count, sum d, sum d^2]``
    (compiled; the tests call it with and without numba's JIT through the wrapper)."""
    n = r0.shape[0]
    m = h * w
    found = np.zeros(n, dtype=np.bool_)
    vals = np.full((N_VALS, n), np.nan)
    npix_out = np.zeros(n, dtype=np.int64)
    sat_out = np.zeros(n, dtype=np.bool_)
    bgsum = np.zeros((n, 3))
    d = fwork[:m]
    raw_max = fwork[m:2 * m + 1]
    cand = iwork[:m]  # pixels above threshold, raster order
    lab = iwork[m:2 * m]  # zero between windows (only touched pixels are reset)
    tmp = iwork[2 * m:3 * m]  # zero between rings
    stack = iwork[3 * m:4 * m]
    pix = iwork[4 * m:5 * m]  # pixels grouped by component (flood-fill order), then ring pixels
    ring = iwork[5 * m:6 * m]
    n_above = iwork[6 * m:7 * m + 1]
    start = iwork[7 * m + 1:8 * m + 3]
    cnt = iwork[8 * m + 3:9 * m + 4]
    nsat = iwork[9 * m + 4:10 * m + 5]  # per component: pixels at the saturation level
    above = bwork[:m]  # marks the pixels above threshold (reset after labelling)
    keep = bwork[m:2 * m + 1]
    border = bwork[2 * m + 1:3 * m + 2]
    flux = fwork[2 * m + 1:3 * m + 2]  # per component
    sx = fwork[3 * m + 2:4 * m + 3]
    sy = fwork[4 * m + 3:5 * m + 4]
    peak = fwork[5 * m + 4:6 * m + 5]
    if eight:
        dr = np.array([-1, 1, 0, 0, -1, -1, 1, 1])
        dc = np.array([0, 0, -1, 1, -1, 1, -1, 1])
    else:
        dr = np.array([-1, 1, 0, 0])
        dc = np.array([0, 0, -1, 1])
    nn = dr.shape[0]
    for k in range(n):
        b = bg[k]
        s = noise[k]
        t = threshold_sigma * s
        rk = r0[k]
        ck = c0[k]
        clip = clip_sigma * s
        # one pass over the window for the pixels above threshold (d of the others is not kept)
        nc = 0
        if integer:  # I - b > t  <=>  I > floor(b + t) for integer I: compared in integers (vectorises)
            lev = np.int64(np.floor(b + t))
            for i in range(h):
                row = image[rk + i, ck:ck + w]
                hits = 0
                for j in range(w):  # a branch-free count first: most rows have no pixel above
                    hits += row[j] > lev
                if hits:
                    base = i * w
                    for j in range(w):
                        if row[j] > lev:
                            cand[nc] = base + j
                            nc += 1
        else:
            for i in range(h):
                row = image[rk + i, ck:ck + w]
                hits = 0
                for j in range(w):
                    hits += row[j] - b > t
                if hits:
                    base = i * w
                    for j in range(w):
                        if row[j] - b > t:
                            cand[nc] = base + j
                            nc += 1
        # background sums over every BG_STEP-th row within +-clip (below
        # threshold: clip_sigma <= threshold_sigma); ring pixels are taken out again below
        c_n, c_s, c_s2 = _background_sums(image, rk, ck, h, w, b, clip)
        for e0 in range(nc):
            q = cand[e0]
            qi = q // w
            d[q] = image[rk + qi, ck + q - qi * w] - b
            above[q] = True
        # 1. components above threshold, labelled in raster order of their first pixel
        ncomp = 0
        npx = 0
        for e0 in range(nc):
            p = cand[e0]
            if lab[p] == 0:
                ncomp += 1
                start[ncomp] = npx
                n_above[ncomp] = 0
                raw_max[ncomp] = -np.inf
                nsat[ncomp] = 0
                lab[p] = ncomp
                top = 0
                stack[0] = p
                top = 1
                while top > 0:
                    top -= 1
                    q = stack[top]
                    pix[npx] = q
                    npx += 1
                    n_above[ncomp] += 1
                    qi = q // w
                    qj = q - qi * w
                    v = float(image[rk + qi, ck + qj])
                    if v > raw_max[ncomp]:
                        raw_max[ncomp] = v
                    if v >= saturation:
                        nsat[ncomp] += 1
                    for a in range(nn):
                        ii = qi + dr[a]
                        jj = qj + dc[a]
                        if ii >= 0 and ii < h and jj >= 0 and jj < w:
                            nb = ii * w + jj
                            if lab[nb] == 0 and above[nb]:
                                lab[nb] = ncomp
                                stack[top] = nb
                                top += 1
        start[ncomp + 1] = npx
        for e0 in range(nc):
            above[cand[e0]] = False
        if ncomp == 0:
            bgsum[k, 0] = c_n
            bgsum[k, 1] = c_s
            bgsum[k, 2] = c_s2
            continue
        # drop rejected components (before growing: they do not grow into their neighbours)
        nk = 0
        for c in range(1, ncomp + 1):
            keep[c] = n_above[c] >= min_pixels and (max_pixels < 0 or n_above[c] <= max_pixels)
            for e in range(start[c], start[c + 1]):
                q = pix[e]
                if keep[c]:
                    pix[nk] = q
                    nk += 1
                else:
                    lab[q] = 0
        # 2. grow rings; a ring pixel takes the highest neighbouring label
        f0 = 0
        f1 = nk
        for _ in range(grow_px):
            nr = 0
            for e in range(f0, f1):
                q = pix[e]
                L = lab[q]
                qi = q // w
                qj = q - qi * w
                for a in range(nn):
                    ii = qi + dr[a]
                    jj = qj + dc[a]
                    if ii >= 0 and ii < h and jj >= 0 and jj < w:
                        nb = ii * w + jj
                        if lab[nb] == 0:
                            if tmp[nb] == 0:
                                ring[nr] = nb
                                nr += 1
                                tmp[nb] = L
                            elif L > tmp[nb]:
                                tmp[nb] = L
            for e in range(nr):
                q = ring[e]
                lab[q] = tmp[q]
                tmp[q] = 0
                pix[f1 + e] = q
                qi = q // w
                d[q] = image[rk + qi, ck + q - qi * w] - b
            f0 = f1
            f1 = f1 + nr
        # 3. moments per component over its grown pixels
        for c in range(ncomp + 1):
            cnt[c] = 0
            flux[c] = 0.0
            sx[c] = 0.0
            sy[c] = 0.0
            peak[c] = -np.inf
            border[c] = False
        for e in range(f1):
            q = pix[e]
            L = lab[q]
            qi = q // w
            qj = q - qi * w
            dv = d[q]
            cnt[L] += 1
            flux[L] += dv
            sx[L] += dv * qj
            sy[L] += dv * qi
            if dv > peak[L]:
                peak[L] = dv
            if qi == 0 or qi == h - 1 or qj == 0 or qj == w - 1:
                border[L] = True
        # 4. the kept spot nearest to the prediction (ties: the brighter)
        best = -1
        best_d2 = np.inf
        for c in range(1, ncomp + 1):
            if not keep[c] or not flux[c] > 0 or (reject_border and border[c]):
                continue
            x = sx[c] / flux[c]
            y = sy[c] / flux[c]
            d2 = (x - (px[k] - ck)) ** 2 + (y - (py[k] - rk)) ** 2
            if d2 < best_d2 or (d2 == best_d2 and flux[c] > flux[best]):
                best = c
                best_d2 = d2
        if best > 0:
            c = best
            found[k] = True
            vals[0, k] = sx[c] / flux[c] + ck
            vals[1, k] = sy[c] / flux[c] + rk
            vals[2, k] = flux[c]
            vals[3, k] = peak[c]
            shot = 0.0 if gain <= 0 else flux[c] / gain
            vals[4, k] = flux[c] / np.sqrt(cnt[c] * s * s + shot)
            vals[5, k] = nsat[c]
            npix_out[k] = cnt[c]
            sat_out[k] = raw_max[c] >= saturation
            for a in range(6, N_VALS):
                vals[a, k] = 0.0
            for e in range(f1):  # second moments of the picked spot
                q = pix[e]
                if lab[q] != c:
                    continue
                qi = q // w
                qj = q - qi * w
                dv = d[q]
                ex = qj - sx[c] / flux[c]
                ey = qi - sy[c] / flux[c]
                var = s * s + (max(dv, 0.0) / cov_gain if cov_gain > 0 else 0.0)
                if image[rk + qi, ck + qj] >= saturation:
                    var = 0.0
                vals[6, k] += var * ex * ex
                vals[7, k] += var * ex * ey
                vals[8, k] += var * ey * ey
                vals[9, k] += dv * ex * ex / flux[c]
                vals[10, k] += dv * ex * ey / flux[c]
                vals[11, k] += dv * ey * ey / flux[c]
        # background sums: without the ring pixels (below threshold, inside a grown spot)
        for e in range(nk, f1):
            q = pix[e]
            qi = q // w
            if qi % BG_STEP:
                continue
            dv = d[q]
            if abs(dv) < clip:
                c_n -= 1.0
                c_s -= dv
                c_s2 -= dv * dv
        bgsum[k, 0] = c_n
        bgsum[k, 1] = c_s
        bgsum[k, 2] = c_s2
        for e in range(f1):
            lab[pix[e]] = 0
    if alpha > 0:
        update_background(bg, noise, bgsum, alpha, noise_floor, trunc)
    return found, vals, npix_out, sat_out, bgsum


@njit(cache=True, nogil=True, fastmath=True)
def _background_sums(image, r0, c0, h, w, b, lim):  # pragma: no cover - compiled
    """``count, sum d, sum d^2`` over every ``BG_STEP``-th row of the window with ``-lim < d = I - b <
    lim`` (branch-free so that it vectorises; fastmath lets the sums be reordered: they only
    feed a running mean)."""
    cn = 0.0
    cs = 0.0
    cs2 = 0.0
    for i in range(0, h, BG_STEP):
        row = image[r0 + i, c0:c0 + w]
        for j in range(w):
            dv = row[j] - b
            m = 1.0 if abs(dv) < lim else 0.0
            cn += m
            cs += m * dv
            cs2 += m * dv * dv
    return cn, cs, cs2


@njit(cache=True, nogil=True, error_model="numpy")
def update_background(bg, noise, bgsum, alpha, noise_floor, trunc):  # pragma: no cover - compiled
    """Running-mean update of each window's background and noise from its background sums
    (``windowed`` centroider, ``background: tracked``): with ``m``, ``v`` the mean and variance
    of ``d = I - b`` over the background pixels, ``b += alpha m`` and
    ``s^2 = (1 - alpha) s^2 + alpha v / trunc^2`` (``trunc``: the std of a unit normal truncated
    to the clip of the sums, 0.98658 for +-3), floored at ``noise_floor``; windows with fewer
    than 16 background pixels keep their values."""
    for k in range(bg.shape[0]):
        c = bgsum[k, 0]
        if c < 16:
            continue
        mean = bgsum[k, 1] / c
        var = max(bgsum[k, 2] / c - mean * mean, 0.0) / (trunc * trunc)
        bg[k] += alpha * mean
        noise[k] = max(np.sqrt((1.0 - alpha) * noise[k] * noise[k] + alpha * var), noise_floor)


@njit(cache=True, nogil=True, error_model="numpy")
def predict_windows(x, y, dtheta, cx, cy, f, height, width, h, w):  # pragma: no cover - compiled
    """liu2013 eqs (8)-(10) and the window placement, per star: ``u = x - cx``, ``v = y - cy``,
    ``dx = -(u v / f) dtheta_x + (f + u^2 / f) dtheta_y + v dtheta_z``,
    ``dy = -(f + v^2 / f) dtheta_x + (u v / f) dtheta_y - u dtheta_z`` (the Jacobian of
    :func:`rollingstar.estimators.filters.gyro_kf.star_motion_jacobian`, applied without building it),
    ``(px, py) = (x + dx, y + dy)``; the ``h x w`` window centred on the rounded prediction and
    shifted onto the ``height x width`` detector starts at ``(r0, c0)``. Returns
    ``px, py, r0, c0`` (non-finite predictions give ``r0 = c0 = 0``)."""
    n = x.shape[0]
    px = np.empty(n)
    py = np.empty(n)
    r0 = np.zeros(n, dtype=np.int64)
    c0 = np.zeros(n, dtype=np.int64)
    for k in range(n):
        u = x[k] - cx
        v = y[k] - cy
        uv = u * v / f
        px[k] = x[k] + (-uv * dtheta[k, 0] + (f + u * u / f) * dtheta[k, 1] + v * dtheta[k, 2])
        py[k] = y[k] + (-(f + v * v / f) * dtheta[k, 0] + uv * dtheta[k, 1] - u * dtheta[k, 2])
        if np.isfinite(px[k]) and np.isfinite(py[k]):
            c0[k] = min(max(np.int64(np.rint(px[k])) - w // 2, 0), width - w)
            r0[k] = min(max(np.int64(np.rint(py[k])) - h // 2, 0), height - h)
    return px, py, r0, c0


def workspace(m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Zeroed scratch buffers ``(iwork, fwork, bwork)`` of :func:`centroid_windows_kernel` for
    windows of ``m`` pixels."""
    return np.zeros(10 * m + 5, dtype=np.int64), np.zeros(6 * m + 5), np.zeros(3 * m + 2, dtype=bool)


@functools.lru_cache(maxsize=16)
def truncated_normal_std(c: float) -> float:
    """Standard deviation of a unit normal truncated to ``+-c`` (0.98658 for c = 3); cached: building
    scipy's frozen distribution costs ~1.5 ms a call, several times the windowed frame itself."""
    from scipy.stats import truncnorm

    return float(truncnorm(-c, c).std())


def centroid_windows_at(image: np.ndarray, r0: np.ndarray, c0: np.ndarray, h: int, w: int, px: np.ndarray,
                        py: np.ndarray, bg: np.ndarray, noise: np.ndarray, *, threshold_sigma: float, min_pixels: int,
                        max_pixels: int | None, connectivity: int, grow_px: int, saturation_adu: float,
                        reject_border: bool = False, gain_e_per_adu: float | None = None,
                        cov_gain_e_per_adu: float | None = None):
    """:func:`centroid_windows_kernel` on the windows ``image[r0_k : r0_k + h, c0_k : c0_k + w]``
    (inside the frame) with background ``bg`` and noise ``noise`` per window (threshold
    ``threshold_sigma * noise``); ``px, py`` and the spots' ``x, y`` in frame coordinates.
    ``gain_e_per_adu``: the shot-noise term of ``snr``; ``cov_gain_e_per_adu``: that of the
    covariance (None: left out).

    Returns ``(WindowSpots, bgsum)`` (``bgsum`` (n, 3): count, sum d, sum d^2 over each window's
    background pixels, see the module docstring)."""
    img = np.asarray(image)
    clip = min(3.0, float(threshold_sigma))
    if img.dtype == bool:
        img = img.astype(np.uint8)
    found, vals, npix, sat, bgsum = centroid_windows_kernel(
        img, bool(np.issubdtype(img.dtype, np.integer)), np.asarray(r0, dtype=np.int64), np.asarray(c0, dtype=np.int64),
        int(h), int(w), np.asarray(px, dtype=float), np.asarray(py, dtype=float), np.array(bg, dtype=float),
        np.array(noise, dtype=float), float(threshold_sigma), int(min_pixels), -1 if max_pixels is None else int(max_pixels),
        connectivity == 8, int(grow_px), float(saturation_adu), bool(reject_border),
        0.0 if gain_e_per_adu is None else float(gain_e_per_adu),
        0.0 if cov_gain_e_per_adu is None else float(cov_gain_e_per_adu), 0.0, 0.0, clip, truncated_normal_std(clip),
        *workspace(int(h) * int(w)))
    cov = window_covariance(vals, sat, np.asarray(bg, dtype=float), np.asarray(noise, dtype=float), float(threshold_sigma),
                            cov_gain_e_per_adu, float(saturation_adu))
    spots = WindowSpots(found, vals[0], vals[1], vals[2], vals[3], npix, sat, vals[4], isotropic_sigma(cov), cov)
    return spots, bgsum


def window_covariance(vals: np.ndarray, saturated: np.ndarray, bg: np.ndarray, noise: np.ndarray,
                      threshold_sigma: float, gain: float | None, saturation: float) -> np.ndarray:
    """Rows ``xx, xy, yy`` (3, n) of the position covariance of the kernel's spots (``vals`` as
    :func:`centroid_windows_kernel` returns them; ``bg``, ``noise`` per window as the kernel used
    them): :func:`rollingstar.estimators.centroiders.covariance.spot_covariance`, its noise and mask
    terms compiled (:func:`model_covariance`; a tracking frame's whole budget is ~70 us, the numpy
    form costs ~120 us of per-call overhead on a handful of spots) and the clipping term of
    saturated spots in numpy."""
    cov = model_covariance(vals, np.asarray(noise, dtype=float), float(threshold_sigma), float(gain or 0.0))
    sat = np.flatnonzero(saturated)
    if sat.size:  # the clipping term, zero for the others, of the saturated spots alone
        flux = vals[2, sat]
        limit = np.broadcast_to(saturation - np.asarray(bg, dtype=float), saturated.shape)[sat]
        with np.errstate(invalid="ignore", divide="ignore"):
            shape = spot_shape(vals[9:12, sat], flux, threshold_sigma * np.broadcast_to(noise, saturated.shape)[sat])
            cov[:, sat] += clipping_covariance(shape, flux, vals[5, sat], np.ones(sat.size, dtype=bool), limit)
    return cov


@njit(cache=True, nogil=True, error_model="numpy")
def model_covariance(vals, noise, threshold_sigma, gain):  # pragma: no cover - compiled
    """The noise and mask terms of :func:`rollingstar.estimators.centroiders.covariance.spot_covariance`
    (its :func:`~rollingstar.estimators.centroiders.covariance.spot_shape` and
    :func:`~rollingstar.estimators.centroiders.covariance.truncation_covariance`, the same formulas
    spot by spot; tested equal) from the kernel's moments ``vals[6:12]``, flux ``vals[2]``, each
    window's ``noise`` and the threshold ``threshold_sigma * noise``; ``gain <= 0``: no shot term."""
    n = vals.shape[1]
    out = np.empty((3, n))
    r2pi = np.sqrt(2.0 * np.pi)
    for k in range(n):
        F = vals[2, k]
        s = noise[k]
        t = threshold_sigma * s
        xx, xy, yy = vals[9, k], vals[10, k], vals[11, k]
        half_diff = np.hypot(0.5 * (xx - yy), xy)
        mean = 0.5 * (xx + yy)
        l1, l2 = mean + half_diff, max(mean - half_diff, MIN_WIDTH_PX * MIN_WIDTH_PX)
        angle = 0.5 * np.arctan2(2.0 * xy, xx - yy)
        ux, uy = np.cos(angle), np.sin(angle)
        length = np.sqrt(max(12.0 * (l1 - l2), 0.0))
        w = np.sqrt(l2)
        line = 1.0 / (r2pi * w) if length < 1e-3 * w else math.erf(length / (2.0 * np.sqrt(2.0) * w)) / length
        rho = F * line / (r2pi * w) / t
        margin = max(rho - 1.0, MIN_MARGIN)
        scale = (t / F) ** 2
        tilt = min(abs(ux), abs(uy)) / max(max(abs(ux), abs(uy)), 1e-12)
        ends = END_COHERENT / (1.0 + (np.pi * 2.0 * w * tilt) ** 2)
        along = TRUNCATION_ALONG * (1.0 + ends) * scale * w**5 * (0.5 * length) ** 2 / margin
        iso = TRUNCATION_ACROSS * scale * w**7 * (length + 2.0 * w) / margin**0.75
        sigma_t = np.sqrt(s * s + (t / gain if gain > 0 else 0.0))
        beta = PHASE_BIAS * (sigma_t / t) ** -1.5 * max(rho, 1.0) ** -0.95
        across = beta * beta / (1.0 + (np.pi * length * tilt) ** 2)
        out[0, k] = vals[6, k] / (F * F) + along * ux * ux + across * uy * uy + iso
        out[1, k] = vals[7, k] / (F * F) + (along - across) * ux * uy
        out[2, k] = vals[8, k] / (F * F) + along * uy * uy + across * ux * ux + iso
    return out


@njit(cache=True, nogil=True)
def any_coincident(x, y, tol):  # pragma: no cover - compiled
    """True when two of the points ``(x_k, y_k)`` are within ``tol`` of each other on both axes
    (two guide stars that took the same spot)."""
    n = x.shape[0]
    for i in range(n):
        for j in range(i + 1, n):
            if abs(x[i] - x[j]) < tol and abs(y[i] - y[j]) < tol:
                return True
    return False



@njit(cache=True, nogil=True, error_model="numpy")
def predict_step(x, y, t_prev, tau, psi, theta, rate, origin_ns, exposure_mean, t0_ns, line_delay_ns, exposure_ns,
                 cx, cy, f, height, width, h, w):  # pragma: no cover - compiled
    """The ``windowed`` centroider's prediction (its class docstring, step 1), compiled: the gyro
    increment (:func:`~rollingstar.estimators.centroiders.window_gyro.gyro_increment`) from each track's
    ``t_prev`` (its row start with ``exposure_mean``, else its ``t_ns``) to the predicted row's
    start (mid-exposure) in the frame starting at ``t0_ns``, then eqs (8)-(10) and the windows
    (:func:`predict_windows`). With a rolling shutter (``line_delay_ns > 0``) twice, the second
    time at the row predicted by the first. Row times as ``DetectorTiming.row_start_ns``:
    ``t0 + rint(y line_delay)`` (+ ``exposure // 2`` for the mid-exposure).

    Returns ``px, py, r0, c0, dtheta (n, 3), t_new (n,) int64``."""
    n = x.shape[0]
    y_guess = y.copy()
    t_new = np.empty(n, dtype=np.int64)
    for it in range(2 if line_delay_ns > 0 else 1):
        for k in range(n):
            t_new[k] = t0_ns + np.int64(np.rint(y_guess[k] * line_delay_ns))
            if not exposure_mean:
                t_new[k] += exposure_ns // 2
        dtheta = gyro_increment(tau, psi, theta, rate, origin_ns, t_prev, t_new, exposure_ns, exposure_mean)
        px, py, r0, c0 = predict_windows(x, y, dtheta, cx, cy, f, height, width, h, w)
        y_guess = py
    return px, py, r0, c0, dtheta, t_new


@njit(cache=True, nogil=True, error_model="numpy")
def track_windows(image, integer, x, y, t_prev, tau, psi, theta, rate, origin_ns, exposure_mean, t0_ns, line_delay_ns,
                  exposure_ns, cx, cy, f, height, width, h, w, bg, noise, threshold_sigma, min_pixels, max_pixels,
                  eight, grow_px, saturation, reject_border, gain, cov_gain, alpha, noise_floor, clip_sigma, trunc,
                  iwork, fwork, bwork):  # pragma: no cover - compiled
    """One windowed frame in one compiled call: :func:`predict_step`, then
    :func:`centroid_windows_kernel` (which updates ``bg``/``noise`` when ``alpha > 0``), then the
    check that no two guide stars took the same spot. Returns ``status`` (0: every star found;
    1: a prediction not finite or a window without a spot; 2: two stars on one spot), ``vals``
    (:data:`N_VALS`, n), ``npix``, ``saturated`` and ``times`` (2, n) int64: each spot's mid-exposure and row
    start, ``DetectorTiming.row_mid_exposure_ns`` / ``row_start_ns`` of its ``y`` (same formulas)."""
    px, py, r0, c0, _, _ = predict_step(x, y, t_prev, tau, psi, theta, rate, origin_ns, exposure_mean, t0_ns,
                                        line_delay_ns, exposure_ns, cx, cy, f, height, width, h, w)
    n = x.shape[0]
    times = np.zeros((2, n), dtype=np.int64)
    for k in range(n):
        if not (np.isfinite(px[k]) and np.isfinite(py[k])):
            return 1, np.full((N_VALS, n), np.nan), np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.bool_), times
    found, vals, npix, sat, _ = centroid_windows_kernel(image, integer, r0, c0, h, w, px, py, bg, noise, threshold_sigma,
                                                        min_pixels, max_pixels, eight, grow_px, saturation,
                                                        reject_border, gain, cov_gain, alpha, noise_floor, clip_sigma,
                                                        trunc, iwork, fwork, bwork)
    for k in range(n):
        if not found[k]:
            return 1, vals, npix, sat, times
    if any_coincident(vals[0], vals[1], 1e-6):
        return 2, vals, npix, sat, times
    for k in range(n):
        times[1, k] = t0_ns + np.int64(np.rint(vals[1, k] * line_delay_ns))
        times[0, k] = times[1, k] + exposure_ns // 2
    return 0, vals, npix, sat, times


@njit(cache=True, nogil=True)
def any_near_edge(x, y, flux, peak, width, height) -> bool:
    """Whether any spot lies within ``MARGIN_SIGMAS`` of its uncut width of the detector edge (the
    only spots :func:`rollingstar.estimators.centroiders.edge.edge_bias_px` can find cut; the same test as its
    ``near_edge``, which stays the reference). Compiled because the windowed centroider asks it on
    every tracking frame, whose whole budget is ~70 us: one call instead of six small-array numpy
    calls (the windowed line of `rollingstar bench perf` times the tracking frame with it)."""
    for i in range(x.size):
        if not (flux[i] > 0.0 and peak[i] > 0.0):
            continue
        m = MARGIN_SIGMAS * np.sqrt(flux[i] / (2.0 * np.pi * peak[i]))
        if x[i] < m or y[i] < m or x[i] > width - 1 - m or y[i] > height - 1 - m:
            return True
    return False
