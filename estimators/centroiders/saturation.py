"""Position uncertainty of a saturated (clipped, flat-topped) spot's centre of gravity.

A saturated spot has lost its peak: every pixel above the saturation level ``S`` reads ``S``.
The background-noise propagation of the CoG (``sigma_px`` of :mod:`rollingstar.estimators.centroiders.cog`)
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

The reported per-axis sigma of a saturated spot is ``sqrt(sigma_noise^2 + sigma_clip^2)``.
Checked against simulated clipped Gaussian spots (PSF sigma 0.8-2.2 px, peak 1.2-300 x the
saturation level): tests/estimators/test_saturation_sigma.py.
"""
from __future__ import annotations

import numpy as np
from scipy.special import jv

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
    r0 = np.sqrt(n / np.pi)
    slope = 2.0 * (n * S / F_u) * S / r0  # s = 2 L S_d / r_s
    r = np.maximum(r0[:, None] + _RADIUS_OFFSETS[None], 0.05)[:, :, None]  # (spots, radii, 1)
    k = 2.0 * np.pi * _RHO[None, None]  # (1, 1, freqs)
    z = k * r
    dC = 4.0 * np.pi**2 * slope[:, None, None] * r * (r * jv(1, z) / k**2 - 4.0 * jv(2, z) / k**3)
    var = np.mean(np.sum(_AXIS_WEIGHT * dC**2, axis=2), axis=1) / (2.0 * np.pi * F) ** 2
    out[sat] = np.sqrt(var)
    return out


def with_clipping(sigma_px: np.ndarray, flux: np.ndarray, n_saturated: np.ndarray, saturated: np.ndarray,
                  saturation_above_bg) -> np.ndarray:
    """``sigma_px`` with the clipped-spot term added in quadrature for the ``saturated`` spots (the
    centroiders' reported per-axis sigma; :func:`clipped_cog_sigma_px` for the arguments)."""
    saturated = np.asarray(saturated, dtype=bool)
    if not saturated.any():
        return sigma_px
    clip = clipped_cog_sigma_px(np.where(saturated, flux, 0.0), np.where(saturated, n_saturated, 0), saturation_above_bg)
    return np.hypot(sigma_px, clip)
