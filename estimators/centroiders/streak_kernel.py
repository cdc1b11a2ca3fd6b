"""Compiled sums of the ``streak`` centroider's fit: weighted normal equations of a batch of stars
read in place from the frame (numba).

For each star ``k`` with parameters ``p_k = (x, y, vx, vy, F, b)`` on its window (top-left pixel
``(row0_k, col0_k)``, ``nrows x ncols``, clipped to the frame) the model ``mu`` and its Jacobian
``J`` are those of :mod:`rollingstar.sensors.streak_model` (the same per-pixel function,
:func:`~rollingstar.sensors.streak_model.pixel_profile`), in the image's units (ADU). Each pixel
has the variance

    var = noise^2 + max(mu - b, 0) / gain

(``noise`` the frame's background noise, which holds read noise, background shot noise and
quantisation; the second term the star's own shot noise, left out when the gain is unknown:
``inv_gain = 0``). Pixels at or above the saturation level carry no information (they read the
saturation level whatever ``p``) and are left out. :func:`normal_equations` returns per star
``H = J^T W J`` (the Fisher information), ``g = J^T W (I - mu)`` and ``chi2 = sum (I - mu)^2 W``;
:func:`nuisance_equations` the flux-and-background block of the first two;
:func:`normal_equations_at_fitted_nuisance` fits each star's flux and background on its profile
and returns :func:`normal_equations` there, the profile evaluated once per pixel for both;
:func:`star_pixels` the footprint summary of the fitted stars and :func:`window_moments` the fit's
starting point. Why compiled: the Jacobian of a frame's ~30 streaks is ~20 000 pixels x 6, built
and summed ten times per frame; the loops keep one window's profile at a time, never the Jacobian.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from rollingstar.sensors.streak_model import pixel_profile, star_geometry

# Floating-point licences of the fit's sums (reassociation, contraction to fused multiply-adds,
# approximate reciprocals and libm functions): ~20 % less time per pixel. Not licensed: assuming
# no NaN or infinity (an unknown saturation level is +inf, and pixels are compared against it).
_FAST = {"reassoc", "contract", "arcp", "afn", "nsz"}


@njit(cache=True, nogil=True, inline="always")
def _star_profiles(p, k, r0, c0, nrows, ncols, image, saturation, se, exposure, ld, prof, raw,
                   dts):  # pragma: no cover - compiled
    """Star ``k``'s unit-flux profile ``G`` and its derivatives ``(G, dG/ddx, dG/ddy, dG/dvx,
    dG/dvy)`` at each live pixel of its window (:func:`~rollingstar.sensors.streak_model.pixel_profile`
    at the row's segment midpoint) into ``prof`` (m, 5), the pixel's value into ``raw`` and its
    row's time from the star's ``dt`` into ``dts``; returns ``m``, the live pixels (saturated ones
    are left out). The star's direction and speed are computed once, not per pixel."""
    height, width = image.shape
    x, y, vx, vy = p[k, 0], p[k, 1], p[k, 2], p[k, 3]
    ux, uy, speed = star_geometry(vx, vy)
    m = 0
    for i in range(max(r0, 0), min(r0 + nrows, height)):
        v = float(i)
        dt = (v - y) * ld
        for j in range(max(c0, 0), min(c0 + ncols, width)):
            value = float(image[i, j])
            if value >= saturation:
                continue
            g, gdx, gdy, gvx, gvy = pixel_profile(float(j) - x - vx * dt, v - y - vy * dt, ux, uy, speed, exposure, se)
            prof[m, 0], prof[m, 1], prof[m, 2], prof[m, 3], prof[m, 4] = g, gdx, gdy, gvx, gvy
            raw[m], dts[m] = value, dt
            m += 1
    return m


@njit(cache=True, nogil=True, inline="always")
def _accumulate(flux, background, vx, vy, ld, prof, raw, dts, m, noise2, inv_gain, hess,
                grad_sum):  # pragma: no cover - compiled
    """``J^T W J`` into ``hess`` (6, 6) and ``J^T W r`` into ``grad_sum`` (6,) of a star of flux
    ``flux`` on ``background`` over its ``m`` live pixels (:func:`_star_profiles`); returns its
    chi-square. The model ``mu - b = F G`` and its Jacobian ``d`` in ``(x, y, vx, vy, F, b)``. The
    21 sums of the lower triangle are scalars (registers) rather than array elements."""
    chi2 = 0.0
    h00 = h10 = h11 = h20 = h21 = h22 = h30 = h31 = h32 = h33 = h40 = h41 = h42 = h43 = h44 = 0.0
    h50 = h51 = h52 = h53 = h54 = h55 = s0 = s1 = s2 = s3 = s4 = s5 = 0.0
    for t in range(m):
        g, gdx, gdy, gvx, gvy, dt = prof[t, 0], prof[t, 1], prof[t, 2], prof[t, 3], prof[t, 4], dts[t]
        d0 = -flux * gdx
        d1 = flux * (gdx * vx * ld - gdy * (1.0 - vy * ld))
        d2 = flux * (gvx - gdx * dt)
        d3 = flux * (gvy - gdy * dt)
        star = flux * g
        w = 1.0 / (noise2 + max(star, 0.0) * inv_gain)
        r = raw[t] - star - background
        chi2 += r * r * w
        a0, a1, a2, a3, a4 = d0 * w, d1 * w, d2 * w, d3 * w, g * w
        s0 += a0 * r
        s1 += a1 * r
        s2 += a2 * r
        s3 += a3 * r
        s4 += a4 * r
        s5 += w * r
        h00 += a0 * d0
        h10 += a1 * d0
        h11 += a1 * d1
        h20 += a2 * d0
        h21 += a2 * d1
        h22 += a2 * d2
        h30 += a3 * d0
        h31 += a3 * d1
        h32 += a3 * d2
        h33 += a3 * d3
        h40 += a4 * d0
        h41 += a4 * d1
        h42 += a4 * d2
        h43 += a4 * d3
        h44 += a4 * g
        h50 += a0
        h51 += a1
        h52 += a2
        h53 += a3
        h54 += a4
        h55 += w
    lower = (h00, h10, h11, h20, h21, h22, h30, h31, h32, h33, h40, h41, h42, h43, h44, h50, h51, h52, h53, h54, h55)
    n = 0
    for a in range(6):
        for b in range(a + 1):
            hess[a, b] = hess[b, a] = lower[n]
            n += 1
    grad_sum[0], grad_sum[1], grad_sum[2], grad_sum[3], grad_sum[4], grad_sum[5] = s0, s1, s2, s3, s4, s5
    return chi2


@njit(cache=True, nogil=True, inline="always")
def _star_normal(p, k, r0, c0, nrows, ncols, image, saturation, noise2, inv_gain, se, exposure, ld, hess,
                 grad_sum, prof, raw, dts):  # pragma: no cover - compiled
    """Star ``k``'s ``J^T W J`` into ``hess`` and ``J^T W r`` into ``grad_sum`` (:func:`_accumulate`
    over :func:`_star_profiles`, with the scratch buffers ``prof, raw, dts`` of a window's size);
    returns its chi-square and the pixels used."""
    m = _star_profiles(p, k, r0, c0, nrows, ncols, image, saturation, se, exposure, ld, prof, raw, dts)
    chi2 = _accumulate(p[k, 4], p[k, 5], p[k, 2], p[k, 3], ld, prof, raw, dts, m, noise2, inv_gain, hess, grad_sum)
    return chi2, m


@njit(cache=True, nogil=True, inline="always")
def _scratch(nrows, ncols):  # pragma: no cover - compiled
    """Buffers for one window's live pixels (:func:`_star_profiles`)."""
    return np.empty((nrows * ncols, 5)), np.empty(nrows * ncols), np.empty(nrows * ncols)


@njit(cache=True, nogil=True, fastmath=_FAST)
def normal_equations(p, row0, col0, nrows, ncols, image, saturation, noise2, inv_gain, se, exposure,
                     ld):  # pragma: no cover - compiled
    """``(H (n, 6, 6), g (n, 6), chi2 (n,), pixels used (n,))`` of the stars ``p`` (module docstring)."""
    n = p.shape[0]
    hess = np.zeros((n, 6, 6))
    grad_sum = np.zeros((n, 6))
    chi2 = np.zeros(n)
    used = np.zeros(n, dtype=np.int64)
    prof, raw, dts = _scratch(nrows, ncols)
    for k in range(n):
        chi2[k], used[k] = _star_normal(p, k, row0[k], col0[k], nrows, ncols, image, saturation, noise2, inv_gain,
                                        se, exposure, ld, hess[k], grad_sum[k], prof, raw, dts)
    return hess, grad_sum, chi2, used


@njit(cache=True, nogil=True, fastmath=_FAST)
def normal_equations_at_fitted_nuisance(pv, row0, col0, nrows, ncols, image, saturation, noise2, inv_gain, se,
                                        exposure, ld):  # pragma: no cover - compiled
    """For stars ``pv`` (n, 4) = (x, y, vx, vy): each star's flux and background ``(n, 2)`` by
    weighted linear least squares on its profile (the flux-and-background block of
    :func:`normal_equations` at unit flux and zero background, solved: the model is linear in
    both), its live pixels, and :func:`normal_equations` at that flux and background, with the
    profile evaluated once per pixel for both."""
    n = pv.shape[0]
    nuis = np.zeros((n, 2))
    hess = np.zeros((n, 6, 6))
    grad_sum = np.zeros((n, 6))
    chi2 = np.zeros(n)
    used = np.zeros(n, dtype=np.int64)
    prof, raw, dts = _scratch(nrows, ncols)
    p = np.zeros((n, 6))
    for k in range(n):
        p[k, :4] = pv[k, :4]
        m = _star_profiles(p, k, row0[k], col0[k], nrows, ncols, image, saturation, se, exposure, ld, prof, raw, dts)
        n00 = n01 = n11 = h0 = h1 = 0.0
        for t in range(m):  # unit flux, zero background
            g = prof[t, 0]
            w = 1.0 / (noise2 + max(g, 0.0) * inv_gain)
            r = raw[t] - g
            n00 += g * g * w
            n01 += g * w
            n11 += w
            h0 += g * w * r
            h1 += w * r
        n00, n11 = n00 + 1e-12, n11 + 1e-12  # a window without live pixels keeps the start
        det = n00 * n11 - n01 * n01
        nuis[k, 0] = 1.0 + (n11 * h0 - n01 * h1) / det
        nuis[k, 1] = (n00 * h1 - n01 * h0) / det
        used[k] = m
        chi2[k] = _accumulate(nuis[k, 0], nuis[k, 1], pv[k, 2], pv[k, 3], ld, prof, raw, dts, m, noise2, inv_gain,
                              hess[k], grad_sum[k])
    return nuis, hess, grad_sum, chi2, used


@njit(cache=True, nogil=True, fastmath=_FAST)
def nuisance_equations(p, row0, col0, nrows, ncols, image, saturation, noise2, inv_gain, se, exposure,
                       ld):  # pragma: no cover - compiled
    """The flux and background block of :func:`normal_equations` alone: ``(N (n, 2, 2), h (n, 2),
    pixels used (n,))``, equal to ``H[:, 4:, 4:]``, ``g[:, 4:]`` and ``used`` of it. The model is
    linear in flux and background, so one solve of this gives both exactly for a given shape; it
    evaluates only the profile, not its derivatives (about half the work per pixel)."""
    n = p.shape[0]
    height, width = image.shape
    hess = np.zeros((n, 2, 2))
    grad_sum = np.zeros((n, 2))
    used = np.zeros(n, dtype=np.int64)
    for k in range(n):
        x, y, vx, vy, flux, b = p[k, 0], p[k, 1], p[k, 2], p[k, 3], p[k, 4], p[k, 5]
        ux, uy, speed = star_geometry(vx, vy)
        for i in range(max(row0[k], 0), min(row0[k] + nrows, height)):
            dt = (i - y) * ld
            for j in range(max(col0[k], 0), min(col0[k] + ncols, width)):
                raw = float(image[i, j])
                if raw >= saturation:
                    continue
                g = pixel_profile(j - x - vx * dt, i - y - vy * dt, ux, uy, speed, exposure, se)[0]
                star = flux * g
                w = 1.0 / (noise2 + max(star, 0.0) * inv_gain)
                r = raw - star - b
                hess[k, 0, 0] += g * g * w
                hess[k, 0, 1] += g * w
                hess[k, 1, 1] += w
                grad_sum[k, 0] += g * w * r
                grad_sum[k, 1] += w * r
                used[k] += 1
        hess[k, 1, 0] = hess[k, 0, 1]
    return hess, grad_sum, used


@njit(cache=True, nogil=True, inline="always")
def _within_sigmas(hess, v_weight, step, step_sigmas, ridge):  # pragma: no cover - compiled
    """True when the step of position and velocity is below ``step_sigmas`` of each one's standard
    deviation (the inverse of the information ``hess`` with the velocity prior ``v_weight``; the
    ridge keeps a window without usable pixels invertible)."""
    info = hess.copy()
    info[2, 2] += v_weight
    info[3, 3] += v_weight
    for a in range(6):
        info[a, a] += ridge
    cov = np.linalg.inv(info)
    for a in range(4):
        if not step[a] * step[a] < step_sigmas * step_sigmas * cov[a, a]:
            return False
    return True


@njit(cache=True, nogil=True, fastmath=_FAST)
def levenberg_marquardt(p, row0, col0, nrows, ncols, image, saturation, noise2, inv_gain, se, exposure, ld,
                        v_mean, v_weight, iterations, frozen_iterations, tolerance, step_sigmas,
                        converged_damping, ridge):  # pragma: no cover - compiled
    """Damped Gauss-Newton fit of each star ``p`` (n, 6) on its own window, star by star (the
    rules of :func:`rollingstar.estimators.centroiders.streak._levenberg_marquardt`, which
    documents them): returns the parameters (a copy), the information matrices with the velocity
    prior, the chi-squares and the pixels used at the solution."""
    n = p.shape[0]
    p = p.copy()
    hess = np.zeros((n, 6, 6))
    grad_sum = np.zeros((n, 6))
    chi2 = np.zeros(n)
    used = np.zeros(n, dtype=np.int64)
    trial = np.empty((1, 6))
    t_hess = np.zeros((6, 6))
    t_grad = np.zeros(6)
    damped = np.empty((6, 6))
    g = np.empty(6)
    prof, raw, dts = _scratch(nrows, ncols)
    for k in range(n):
        chi2[k], used[k] = _star_normal(p, k, row0[k], col0[k], nrows, ncols, image, saturation, noise2, inv_gain, se,
                                        exposure, ld, hess[k], grad_sum[k], prof, raw, dts)
        lam = 1e-3
        for it in range(iterations):
            frozen = it < frozen_iterations
            for a in range(6):
                g[a] = grad_sum[k, a]
                for b in range(6):
                    damped[a, b] = hess[k, a, b]
            for a in (2, 3):
                damped[a, a] += v_weight[k]
                g[a] -= (p[k, a] - v_mean[k, a - 2]) * v_weight[k]
            for a in range(6):
                damped[a, a] += lam * damped[a, a] + ridge
            if frozen:  # position, flux and background first, at the expected velocity
                for a in (2, 3):
                    for b in range(6):
                        damped[a, b] = 0.0
                        damped[b, a] = 0.0
                    damped[a, a] = 1.0
                    g[a] = 0.0
            step = np.linalg.solve(damped, g)
            for a in range(6):
                trial[0, a] = p[k, a] + step[a]
            if trial[0, 4] <= 0.0:
                trial[0, 4] = 0.5 * p[k, 4]
            t_chi2, t_used = _star_normal(trial, 0, row0[k], col0[k], nrows, ncols, image, saturation, noise2,
                                          inv_gain, se, exposure, ld, t_hess, t_grad, prof, raw, dts)
            prior_now = ((p[k, 2] - v_mean[k, 0]) ** 2 + (p[k, 3] - v_mean[k, 1]) ** 2) * v_weight[k]
            prior_trial = ((trial[0, 2] - v_mean[k, 0]) ** 2 + (trial[0, 3] - v_mean[k, 1]) ** 2) * v_weight[k]
            if t_chi2 + prior_trial < chi2[k] + prior_now:
                lam /= 3.0
                p[k, :] = trial[0, :]
                hess[k, :, :] = t_hess
                grad_sum[k, :] = t_grad
                chi2[k], used[k] = t_chi2, t_used
            else:
                lam *= 5.0
            small = lam <= converged_damping and (max(abs(step[0]), abs(step[1])) < tolerance
                                                   or _within_sigmas(hess[k], v_weight[k], step, step_sigmas, ridge))
            if (small and not frozen) or lam > 1e3:
                break
        hess[k, 2, 2] += v_weight[k]
        hess[k, 3, 3] += v_weight[k]
    return p, hess, chi2, used


@njit(cache=True, nogil=True)
def star_pixels(p, row0, col0, nrows, ncols, image, saturation, level, se, exposure, ld):  # pragma: no cover
    """Per star: the pixels of its window (in the frame) where the fitted star signal exceeds
    ``level``, the largest fitted star signal there (the peak above background), and how many of
    those pixels are saturated."""
    n = p.shape[0]
    height, width = image.shape
    npix = np.zeros(n, dtype=np.int64)
    nsat = np.zeros(n, dtype=np.int64)
    peak = np.zeros(n)
    for k in range(n):
        x, y, vx, vy, flux = p[k, 0], p[k, 1], p[k, 2], p[k, 3], p[k, 4]
        ux, uy, speed = star_geometry(vx, vy)
        for i in range(max(row0[k], 0), min(row0[k] + nrows, height)):
            dt = (i - y) * ld
            for j in range(max(col0[k], 0), min(col0[k] + ncols, width)):
                star = flux * pixel_profile(j - x - vx * dt, i - y - vy * dt, ux, uy, speed, exposure, se)[0]
                if star > level:
                    npix[k] += 1
                    peak[k] = max(peak[k], star)
                    if float(image[i, j]) >= saturation:
                        nsat[k] += 1
    return npix, peak, nsat


@njit(cache=True, nogil=True)
def window_moments(image, row0, col0, nrows, ncols, background, level):  # pragma: no cover - compiled
    """Per window (clipped to the frame): the sum of ``d = image - background`` over all its pixels
    (scaled up to the whole window when the frame clips it), and the centroid of the pixels with
    ``d > level`` (the window's centre when there are none): the fit's starting flux and position."""
    n = row0.shape[0]
    height, width = image.shape
    out = np.zeros((n, 3))
    for k in range(n):
        total = 0.0
        sw = 0.0
        sx = 0.0
        sy = 0.0
        inside = 0
        for i in range(max(row0[k], 0), min(row0[k] + nrows, height)):
            for j in range(max(col0[k], 0), min(col0[k] + ncols, width)):
                d = float(image[i, j]) - background[k]
                total += d
                inside += 1
                if d > level:
                    sw += d
                    sx += d * j
                    sy += d * i
        out[k, 0] = total * (nrows * ncols) / max(inside, 1)
        if sw > 0.0:
            out[k, 1] = sx / sw
            out[k, 2] = sy / sw
        else:
            out[k, 1] = col0[k] + 0.5 * (ncols - 1)
            out[k, 2] = row0[k] + 0.5 * (nrows - 1)
    return out
