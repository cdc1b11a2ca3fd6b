"""Position uncertainty of a saturated (clipped, flat-topped) spot's centre of gravity.

A saturated spot has lost its peak: every pixel above the saturation level ``S`` reads ``S``.
The noise propagation of the CoG (the covariance of :mod:`rollingstar.estimators.centroiders.covariance`)
then claims an accuracy the spot does not have: the clipped pixels carry no noise *and* no
sub-pixel information. What remains is a deterministic, sub-pixel-phase dependent sampling error.

Derivation (one axis; the other is the same by symmetry)
--------------------------------------------------------
Let ``P(u)`` be the pixel-integrated PSF above background at offset ``u`` from the true position
``x0`` (pixel ``i`` reads ``P(i - x0)``), ``g = min(P, S_d)`` its clipped version
(``S_d = S - background``) and ``F_m = sum_i g(i - x0)`` the measured flux. By the Poisson
summation formula the sampled CoG of ``g`` is off by::

    e_x(x0) = (1 / F_m) sum_{(k,l) != 0} (i / 2 pi) d_kx G(k, l) exp(-2 pi i (k x0 + l y0))

(``G`` the 2-D Fourier transform of ``g``). Averaged over the unknown sub-pixel phase
``(x0, y0)`` (uniform) the frequencies are orthogonal, so::

    sigma_clip^2 = (1 / (2 pi F_m))^2 sum_{(k,l) != 0} (k / rho)^2 |G'(rho)|^2,   rho = sqrt(k^2 + l^2)

for a radially symmetric ``g``. ``g = P - c`` with the cap ``c = (P - S_d)+`` clipped off; the
smooth PSF ``P`` contributes nothing at integer frequencies (its transform there is below 1e-8
for a PSF sigma >= 0.8 px), the cap does, through the slope discontinuity at the plateau edge
``r_s``. Near its edge the cap is a paraboloid ``c(r) = s (r_s^2 - r^2) / (2 r_s)`` with the edge
slope ``s = |P'(r_s)|``, whose Hankel transform is closed-form
(``int_0^R (R^2 - r^2) J0(k r) r dr = 2 R^2 J2(k R) / k^2``)::

    C(rho) = 2 pi s r_s J2(k r_s) / k^2,      k = 2 pi rho
    C'(rho) = 4 pi^2 s r_s (r_s J1(k r_s) / k^2 - 4 J2(k r_s) / k^3)

The plateau and its edge slope come from the measured spot, for a Gaussian PSF
``P = A exp(-r^2 / 2 s_e^2)``: ``n_sat`` saturated pixels give ``r_s = sqrt(n_sat / pi)``; the
flux outside the plateau is ``F_u = F_m - n_sat S_d = 2 pi s_e^2 S_d``, so
``L = ln(A / S_d) = r_s^2 / (2 s_e^2) = n_sat S_d / F_u`` and ``s = S_d r_s / s_e^2 = 2 L S_d / r_s``.
``n_sat`` counts whole pixels, so the continuous plateau radius is known to about half a pixel:
``sigma_clip^2`` is averaged over ``r_s + t``, ``t`` uniform in ``[-0.5, 0.5]`` px (9 points; this
also smooths the Bessel oscillations, which the pixel count cannot resolve). The sum runs over
``|k|, |l| <= 4`` (the terms decay as ``rho^-5``).

A saturated spot's reported covariance is its noise covariance plus ``sigma_clip^2 I`` (its clipped
pixels themselves carry no noise), so its per-axis sigma is ``sqrt(sigma_noise^2 + sigma_clip^2)``.
Checked against simulated clipped Gaussian spots (PSF sigma 0.8-2.2 px, peak 1.2-300 x the
saturation level): tests/estimators/test_saturation_sigma.py.

A saturated smear is a clipped ridge rather than a round plateau: :func:`clipped_streak_variance`
is the same derivation in one dimension, across the ridge, and :func:`clipped_streak_end_variance`
the error along it from the ridge's clipped ends (computed directly from a model of the ridge);
estimators/centroiders/covariance.py adds them to a smeared spot's covariance across and along
the smear.
"""
from __future__ import annotations

import functools

import numpy as np
from scipy.special import erfcx, j0, j1, ndtr

_MAX_FREQ = 4
_KL = np.array([(k, m) for k in range(-_MAX_FREQ, _MAX_FREQ + 1) for m in range(-_MAX_FREQ, _MAX_FREQ + 1) if (k, m) != (0, 0)],
               dtype=float)
_RHO = np.hypot(_KL[:, 0], _KL[:, 1])
_AXIS_WEIGHT = (_KL[:, 0] / _RHO) ** 2  # (k / rho)^2: the x-axis share of each frequency
_RADIUS_OFFSETS = np.linspace(-0.5, 0.5, 9)  # px: the plateau radius known from a pixel count


def clipped_cog_sigma_px(flux: np.ndarray, n_saturated: np.ndarray, saturation_above_bg: np.ndarray) -> np.ndarray:
    """Per-axis RMS (over sub-pixel phase) CoG error of clipped spots, in pixels (see module docstring).

    ``flux``: measured flux above background ``F_m``; ``n_saturated``: pixels at the saturation
    level; ``saturation_above_bg``: ``S_d``, the saturation level minus the spot's background (same
    units as ``flux``). Returns 0 for spots without a saturated pixel. Vectorised over spots.
    """
    flux = np.asarray(flux, dtype=float)
    n_sat = np.asarray(n_saturated, dtype=float)
    s_d = np.broadcast_to(np.asarray(saturation_above_bg, dtype=float), flux.shape)
    out = np.zeros(flux.shape)
    sat = (n_sat > 0) & (flux > 0) & (s_d > 0)
    if not sat.any():
        return out
    F, n, S = flux[sat], n_sat[sat], s_d[sat]
    F_u = np.maximum(F - n * S, S)  # flux outside the plateau; at least one pixel's worth (noise, truncated wings)
    slope = 2.0 * (n * S / F_u) * S / np.sqrt(n / np.pi)  # s = 2 L S_d / r_s
    shape = np.array([_plateau_sum(float(v)) for v in n])
    var = shape * (slope / (2.0 * np.pi * F)) ** 2
    out[sat] = np.sqrt(var)
    return out


@functools.lru_cache(maxsize=4096)
def _plateau_sum(n_saturated: float) -> float:
    """``mean_t sum_(k,l) (k / rho)^2 (C'(rho) / s)^2`` of the module docstring: the part of a
    clipped spot's ``sigma_clip^2 (2 pi F_m)^2 / s^2`` that depends only on its plateau radius
    ``r_s = sqrt(n_sat / pi)``, so only on the pixel count ``n_sat``. Cached per count: the Bessel
    sums (9 radii x 80 frequencies) would otherwise be most of a tracked frame's covariance time."""
    r = np.maximum(np.sqrt(n_saturated / np.pi) + _RADIUS_OFFSETS, 0.05)[:, None]  # (radii, 1)
    k = 2.0 * np.pi * _RHO[None]  # (1, freqs)
    z = k * r
    bessel_1 = j1(z)  # J1 and J2 = 2 J1 / z - J0 (the recurrence): the order-specific kernels are ~8x faster than jv
    bessel_2 = 2.0 * bessel_1 / z - j0(z)
    dC = 4.0 * np.pi**2 * r * (r * bessel_1 / k**2 - 4.0 * bessel_2 / k**3)
    return float(np.mean(np.sum(_AXIS_WEIGHT * dC**2, axis=1)))


_FREQS_1D = np.arange(1, _MAX_FREQ + 1, dtype=float)
_HALF_WIDTH_OFFSETS = np.linspace(-0.25, 0.25, 9)  # px: the ridge's half-width known from a pixel count


def _ridge_sigma(h: np.ndarray, flux_outside: np.ndarray, s_d: np.ndarray) -> np.ndarray:
    """The sigma of a Gaussian profile clipped at ``s_d`` over ``[-h, h]`` that has ``flux_outside``
    beyond the plateau: the root of ``2 s_d sigma M(h / sigma) = flux_outside`` with ``M(z) =
    sqrt(2 pi) exp(z^2 / 2) (1 - Phi(z))`` (Mills' ratio; the left side grows with sigma), by
    bisection on ``log(sigma)`` over ``[0.05, 50]`` px (40 steps: relative precision 2e-5)."""
    target = flux_outside / (2.0 * s_d)
    lo, hi = np.full(h.shape, np.log(0.05)), np.full(h.shape, np.log(50.0))
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        sigma = np.exp(mid)
        z = h / sigma
        side = sigma * np.sqrt(2 * np.pi) * erfcx(z / np.sqrt(2)) / 2  # sigma M(z), overflow-free
        below = side < target
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return np.exp(0.5 * (lo + hi))


def clipped_streak_variance(flux_per_px: np.ndarray, ridge_width_px: np.ndarray, saturation_above_bg) -> np.ndarray:
    """Mean square (over sub-pixel phase, px^2) of the CoG error across a saturated streak: the
    1-D form of :func:`clipped_cog_sigma_px` for a ridge clipped ``ridge_width_px`` wide
    (``2 h``) of flux ``flux_per_px`` per pixel along it.

    Per pixel along the ridge the profile across is a Gaussian clipped at ``S_d`` on ``[-h, h]``;
    its cap ``c(x) ~ s (h^2 - x^2) / (2 h)`` (edge slope ``s = S_d h / sigma^2``, ``sigma`` from the
    flux outside the plateau, :func:`_ridge_sigma`) has the transform ``C(k) = (2 s / h) (sin kh -
    kh cos kh) / k^3`` (``k = 2 pi nu``), so the 1-D Poisson-summation form of the module docstring,
    ``sigma^2 = 2 sum_{n >= 1} C'(n)^2 / (2 pi F)^2`` with ``C'(nu) = 4 pi (s / h) (h^2 sin(kh) /
    k^2 - 3 (sin kh - kh cos kh) / k^4)``, averaged over ``h +- 0.25`` px (the width is a pixel
    count). Checked against noise-free clipped profiles in tests/estimators/test_centroid_covariance.py."""
    F = np.asarray(flux_per_px, dtype=float)
    S = np.broadcast_to(np.asarray(saturation_above_bg, dtype=float), F.shape)
    h0 = 0.5 * np.asarray(ridge_width_px, dtype=float)
    out = np.zeros(F.shape)
    ok = (h0 > 0) & (F > 0) & (S > 0)
    if not ok.any():
        return out
    F, S, h0 = F[ok], S[ok], h0[ok]
    h = np.maximum(h0[:, None] + _HALF_WIDTH_OFFSETS[None], 0.05)  # (spots, widths)
    F_u = np.maximum(F[:, None] - 2 * h * S[:, None], S[:, None])  # flux outside the ridge per pixel along
    sigma = _ridge_sigma(h, F_u, S[:, None])
    slope = (S[:, None] * h / sigma**2)[:, :, None]
    h = h[:, :, None]
    k = 2.0 * np.pi * _FREQS_1D[None, None]
    z = k * h
    dC = 4.0 * np.pi * (slope / h) * (h * h * np.sin(z) / k**2 - 3.0 * (np.sin(z) - z * np.cos(z)) / k**4)
    out[ok] = 2.0 * np.mean(np.sum(dC**2, axis=2), axis=1) / (2.0 * np.pi * F) ** 2
    return out


_END_PHASES = (np.arange(32) + 0.5) / 32 - 0.5  # px: sub-pixel phases along the smear
_LENGTH_OFFSETS = np.array([-0.5, 0.0, 0.5])  # px: the smear's length known from moments


def clipped_streak_end_variance(flux: np.ndarray, length_px: np.ndarray, ridge_width_px: np.ndarray,
                                n_saturated: np.ndarray, saturation_above_bg) -> np.ndarray:
    """Mean square (over sub-pixel phase, px^2) of the CoG error *along* a saturated smear: its
    clipped ridge ends where the profile along the smear falls through the saturation level,
    with a kink in slope whose sampling moves the centroid (the along twin of
    :func:`clipped_streak_variance`).

    The ridge's central row is modelled as a line of length ``L`` blurred by the across sigma of
    :func:`_ridge_sigma` (the PSF is round), pixel-integrated, with plateau ``S_d exp(h^2 / 2
    sigma^2)``, clipped at ``S_d``; its CoG error is computed directly at 32 phases and scaled by
    the share of the spot's flux in the clipped rows (``n_saturated S_d / flux``; unclipped rows
    are smooth and only dilute it), averaged over ``L +- 0.5`` and ``h +- 0.25`` px."""
    F = np.asarray(flux, dtype=float)
    S = np.broadcast_to(np.asarray(saturation_above_bg, dtype=float), F.shape)
    L0, h0 = np.asarray(length_px, dtype=float), 0.5 * np.asarray(ridge_width_px, dtype=float)
    out = np.zeros(F.shape)
    ok = (h0 > 0) & (F > 0) & (S > 0) & (L0 > 0)
    for k in np.flatnonzero(ok):
        f_px = F[k] / L0[k]  # flux per pixel along
        h = np.maximum(h0[k] + _HALF_WIDTH_OFFSETS[::4], 0.05)  # 3 widths
        sigma = _ridge_sigma(h, np.maximum(f_px - 2 * h * S[k], S[k]), np.full(h.shape, S[k]))
        plateau = S[k] * np.exp(0.5 * (h / sigma) ** 2)
        L = np.maximum(L0[k] + _LENGTH_OFFSETS, 0.5)
        half = int(np.ceil(L.max() / 2 + 6 * sigma.max())) + 1
        i = np.arange(-half, half + 1, dtype=float)
        # (widths, lengths, phases, pixels): pixel integral of Phi((u + L/2)/s) - Phi((u - L/2)/s)
        s_ = sigma[:, None, None, None]
        u = i[None, None, None, :] - _END_PHASES[None, None, :, None]
        Lh = 0.5 * L[None, :, None, None]
        v = plateau[:, None, None, None] * (_ramp(u + Lh, s_) - _ramp(u - Lh, s_))
        c = np.minimum(v, S[k])
        e = np.sum(c * u, axis=-1) / np.sum(c, axis=-1)
        share = min(1.0, float(n_saturated[k]) * S[k] / F[k])
        out[k] = share**2 * np.mean(e**2)
    return out


def _ramp(a: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The integral of ``Phi(t / s)`` over the pixel ``t in [a - 1/2, a + 1/2]`` (``s`` the sigma):
    with ``g(t) = t Phi(t / s) + s phi(t / s)``, ``g(a + 1/2) - g(a - 1/2)``."""
    def g(t):
        z = t / s
        return t * ndtr(z) + s * np.exp(-0.5 * z * z) / np.sqrt(2 * np.pi)

    return g(a + 0.5) - g(a - 0.5)
