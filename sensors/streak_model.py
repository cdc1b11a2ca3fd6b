"""Fast model of a star streaked by its image motion over each row's rolling-shutter exposure.

The expected electrons of pixel ``(u, v)`` (column, row, pixel centres at integers) of a star with
parameters ``p = (x, y, vx, vy, F, b)``: ``(x, y)`` its position at the mid-exposure of its own
row ``y`` (px), ``(vx, vy)`` its image velocity (px/s), ``F`` its electrons and ``b`` the
background electrons per pixel. Row ``v`` starts ``(v - y) ld`` after row ``y`` (``ld`` the line
delay) and exposes for ``E``, so during that row's window the star sweeps the segment of length
``L = |vel| E`` centred on

    m_v = (x, y) + vel (v - y) ld

(the definition of :func:`rollingstar.sensors.pixel_crb.smeared_spot_fisher`). The PSF
integrated over a square pixel is replaced by a Gaussian of variance ``se^2 = s^2 + 1/12`` (the
PSF's plus the pixel's: same second moment, 0.1 % peak error at ``s = 1``), which is isotropic,
so the time average over the segment has a closed form. With ``a`` and ``q`` the offsets of the
pixel from ``m_v`` along and across the motion,

    mu = F / L * phi_se(q) * [Phi((a + L/2) / se) - Phi((a - L/2) / se)] + b

(``phi_se`` the normal density of width ``se``). Below ``L = 0.05 se`` the bracket divided by
``L`` is replaced by its series ``phi_se(a) (1 + L^2 (a^2 - se^2) / (24 se^4))`` (relative error
below 1e-8), which is also the motionless limit. The Jacobian ``d mu / d p`` is analytic: the
derivatives in ``a``, ``q`` and ``L`` chained through the row midpoint ``m_v`` and the direction
of the motion (a rotation of the segment about its midpoint changes ``a`` by ``q d theta`` and
``q`` by ``-a d theta``).

:func:`streak_mu_jac` evaluates a batch of stars, each on its own window of one common size (the
fit of a frame's stars runs on all of them at once); :func:`streak_fisher` is the Fisher
information of one star with Poisson, read and quantisation noise (the noise model of
``smeared_spot_fisher``). Compiled with numba: the per-pixel work is a few exponentials and two
``erfc``, and a frame's stars are ~20 000 pixels.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
_INV_SQRT2 = 1.0 / math.sqrt(2.0)
SMALL_SEGMENT = 0.05  # below this length (in units of se) the series form is used
SHORT_SEGMENT = 4.0  # below this length (in units of se) the exact erfc is used
_AS_P, _AS_A1, _AS_A2, _AS_A3, _AS_A4, _AS_A5 = (0.3275911, 0.254829592, -0.284496736, 1.421413741, -1.453152027,
                                                  1.061405429)


@njit(cache=True, nogil=True, inline="always")
def _upper_tail(z, ez):  # pragma: no cover - compiled
    """``1 - Phi(z)`` for ``z >= 0`` given ``ez = exp(-z^2 / 2)``: Abramowitz & Stegun 7.1.26
    (absolute error below 1e-7), which reuses the exponential the profile needs anyway."""
    t = 1.0 / (1.0 + _AS_P * z * _INV_SQRT2)
    poly = t * (_AS_A1 + t * (_AS_A2 + t * (_AS_A3 + t * (_AS_A4 + t * _AS_A5))))
    return 0.5 * poly * ez


@njit(cache=True, nogil=True, inline="always")
def _phi_difference(zp, zm, ep, em):  # pragma: no cover - compiled
    """``Phi(zp) - Phi(zm)`` for ``zp >= zm`` (``ep, em = exp(-z^2 / 2)``) without cancelling two
    numbers near 1. A short segment (``zp - zm < SHORT_SEGMENT``) takes libm's ``erfc``: there the
    difference is small and the approximation's absolute error would be a large part of it."""
    if zp - zm < SHORT_SEGMENT:
        if zm >= 0.0:
            return 0.5 * (math.erfc(zm * _INV_SQRT2) - math.erfc(zp * _INV_SQRT2))
        if zp <= 0.0:
            return 0.5 * (math.erfc(-zp * _INV_SQRT2) - math.erfc(-zm * _INV_SQRT2))
        return 1.0 - 0.5 * (math.erfc(zp * _INV_SQRT2) + math.erfc(-zm * _INV_SQRT2))
    if zm >= 0.0:
        return _upper_tail(zm, em) - _upper_tail(zp, ep)
    if zp <= 0.0:
        return _upper_tail(-zp, ep) - _upper_tail(-zm, em)
    return 1.0 - _upper_tail(zp, ep) - _upper_tail(-zm, em)


@njit(cache=True, nogil=True, inline="always")
def pixel_profile(dx, dy, ux, uy, speed, exposure, se):  # pragma: no cover - compiled
    """The streak's unit-flux profile at offset ``(dx, dy)`` from the row's segment midpoint, and
    its derivatives: returns ``(G, dG/ddx, dG/ddy, dG/dvx, dG/dvy)`` (velocity derivatives at
    fixed offset); ``(ux, uy)`` the unit direction of motion, ``speed`` ``|vel|`` px/s."""
    inv2 = 1.0 / (se * se)
    norm = _INV_SQRT_2PI / se
    length = speed * exposure
    a = dx * ux + dy * uy
    q = dy * ux - dx * uy
    eq = norm * math.exp(-0.5 * q * q * inv2)
    if length > SMALL_SEGMENT * se:
        h = 0.5 * length
        zp = (a + h) / se
        zm = (a - h) / se
        xp = math.exp(-0.5 * zp * zp)
        xm = math.exp(-0.5 * zm * zm)
        ep = norm * xp
        em = norm * xm
        g = eq * _phi_difference(zp, zm, xp, xm) / length
        ga = eq * (ep - em) / length
        gq = -q * inv2 * g
        gl = (eq * 0.5 * (ep + em) - g) / length
        rot = (ga * q - gq * a) / speed  # the segment's turn about its midpoint
        gvx = -rot * uy + gl * exposure * ux
        gvy = rot * ux + gl * exposure * uy
    else:
        g0 = eq * norm * math.exp(-0.5 * a * a * inv2)
        l2 = length * length
        c = (a * a - se * se) * inv2 * inv2
        g = g0 * (1.0 + l2 * c / 24.0)
        ga = g0 * (-a * inv2 * (1.0 + l2 * c / 24.0) + l2 * a * inv2 * inv2 / 12.0)
        gq = -q * inv2 * g
        rot = q * a * g0 * speed * exposure * exposure * inv2 * inv2 / 12.0
        glv = g0 * exposure * exposure * c / 12.0  # dG/dL * E * u = glv * vel
        gvx = -rot * uy + glv * speed * ux
        gvy = rot * ux + glv * speed * uy
    return g, ga * ux - gq * uy, ga * uy + gq * ux, gvx, gvy


@njit(cache=True, nogil=True, inline="always")
def star_geometry(vx, vy):  # pragma: no cover - compiled
    """Unit direction and speed of a velocity (``(1, 0)`` and 0 when motionless)."""
    speed = math.sqrt(vx * vx + vy * vy)
    if speed > 0.0:
        return vx / speed, vy / speed, speed
    return 1.0, 0.0, 0.0


@njit(cache=True, nogil=True)
def _mu_jac_kernel(p, row0, col0, nrows, ncols, se, exposure, ld, want_jac):  # pragma: no cover - compiled
    n = p.shape[0]
    mu = np.empty((n, nrows, ncols))
    jac = np.empty((n, 6, nrows, ncols) if want_jac else (0, 6, nrows, ncols))
    for k in range(n):
        x, y, vx, vy, flux, b = p[k, 0], p[k, 1], p[k, 2], p[k, 3], p[k, 4], p[k, 5]
        ux, uy, speed = star_geometry(vx, vy)
        for i in range(nrows):
            v = row0[k] + i
            dt = (v - y) * ld
            my = y + vy * dt
            mx = x + vx * dt
            for j in range(ncols):
                g, gdx, gdy, gvx, gvy = pixel_profile(col0[k] + j - mx, v - my, ux, uy, speed, exposure, se)
                mu[k, i, j] = flux * g + b
                if want_jac:
                    jac[k, 0, i, j] = -flux * gdx
                    jac[k, 1, i, j] = flux * (gdx * vx * ld - gdy * (1.0 - vy * ld))
                    jac[k, 2, i, j] = flux * (gvx - gdx * dt)
                    jac[k, 3, i, j] = flux * (gvy - gdy * dt)
                    jac[k, 4, i, j] = g
                    jac[k, 5, i, j] = 1.0
    return mu, jac


def _args(p, row0, col0):
    p = np.ascontiguousarray(np.asarray(p, dtype=float).reshape(-1, 6))
    row0 = np.ascontiguousarray(np.broadcast_to(np.asarray(row0, dtype=np.int64), (p.shape[0],)))
    col0 = np.ascontiguousarray(np.broadcast_to(np.asarray(col0, dtype=np.int64), (p.shape[0],)))
    return p, row0, col0


def effective_sigma(psf_sigma_px: float) -> float:
    """Width of the Gaussian standing for the pixel-integrated PSF: ``sqrt(s^2 + 1/12)``."""
    return math.sqrt(float(psf_sigma_px) ** 2 + 1.0 / 12.0)


def streak_mu_jac(p, row0, col0, nrows: int, ncols: int, psf_sigma_px: float, exposure_s: float,
                  line_delay_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Expected electrons ``mu`` (n, nrows, ncols) of ``n`` stars ``p`` (n, 6) = ``(x, y, vx, vy, F, b)``
    on windows whose top-left pixels are ``(row0, col0)`` (n,), and ``jac`` (n, 6, nrows, ncols)
    ``= d mu / d p`` (module docstring)."""
    p, row0, col0 = _args(p, row0, col0)
    return _mu_jac_kernel(p, row0, col0, int(nrows), int(ncols), effective_sigma(psf_sigma_px),
                          float(exposure_s), float(line_delay_s), True)


def streak_mu(p, row0, col0, nrows: int, ncols: int, psf_sigma_px: float, exposure_s: float,
              line_delay_s: float) -> np.ndarray:
    """:func:`streak_mu_jac` without the Jacobian."""
    p, row0, col0 = _args(p, row0, col0)
    return _mu_jac_kernel(p, row0, col0, int(nrows), int(ncols), effective_sigma(psf_sigma_px),
                          float(exposure_s), float(line_delay_s), False)[0]


def streak_window(x: float, y: float, vx: float, vy: float, psf_sigma_px: float, exposure_s: float,
                  line_delay_s: float) -> tuple[int, int, int, int]:
    """``(row0, col0, nrows, ncols)`` of a window holding the streak and 6 PSF widths around it
    (the window of :func:`rollingstar.sensors.pixel_crb.smeared_spot_fisher`)."""
    reach = abs(vx) + abs(vy)
    h = int(np.ceil(6.0 * psf_sigma_px + 0.5 * reach * (exposure_s + 12.0 * psf_sigma_px * line_delay_s))) + 1
    return int(np.floor(y)) - h, int(np.floor(x)) - h, 2 * h + 1, 2 * h + 1


def streak_fisher(p, psf_sigma_px: float, exposure_s: float, line_delay_s: float, read_noise_e: float,
                  gain_e_per_adu: float = 0.0, full_well_e: float = np.inf) -> np.ndarray:
    """Fisher information (6 x 6) of ``p = (x, y, vx, vy, F, b)`` of one star from a window that holds
    it: pixel variance ``mu + r^2 + gain^2 / 12`` (Poisson, read noise, ADC quantisation); pixels
    whose expectation reaches ``full_well_e`` read the saturation level whatever ``p`` and are left
    out."""
    p = np.asarray(p, dtype=float).reshape(6)
    row0, col0, nrows, ncols = streak_window(*p[:4], psf_sigma_px, exposure_s, line_delay_s)
    mu, jac = streak_mu_jac(p[None], row0, col0, nrows, ncols, psf_sigma_px, exposure_s, line_delay_s)
    mu, jac = mu.reshape(-1), jac.reshape(6, -1)
    live = mu < full_well_e
    var = mu[live] + float(read_noise_e) ** 2 + float(gain_e_per_adu) ** 2 / 12.0
    return (jac[:, live] / var) @ jac[:, live].T
