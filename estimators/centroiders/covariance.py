"""The 2 x 2 position covariance of a thresholded centre-of-gravity centroid, per spot.

Every centroider reports it in the star table's ``cov_xx, cov_xy, cov_yy`` (px^2, image axes)
and ``sigma_px = sqrt((cov_xx + cov_yy) / 2)``, the isotropic per-axis sigma of older readers.
It is the sum of four terms, each from the spot's own pixels (:func:`spot_covariance`):

1. Noise propagation (first order): the CoG ``r = sum_i d_i r_i / F`` (``d_i = I_i - b`` the
   pixel values above background, ``F = sum_i d_i``) moves by ``dr = sum_i (r_i - r) dd_i / F``
   when the pixel values move by independent ``dd_i`` of variance ``var_i``, so::

       Cov_noise = sum_i var_i (r_i - r)(r_i - r)^T / F^2,     var_i = s^2 + max(d_i, 0) / g

   ``s`` is the background noise the centroider measures (read noise and the background's own
   shot noise, ADU) and ``max(d_i, 0) / g`` the shot noise of the star's signal (``g`` the gain
   in electrons per ADU; left out when the gain is unknown). A pixel at the saturation level
   carries no noise (``var_i = 0``). A smeared spot is long, so this term is long along the smear.

2. The threshold mask (:func:`truncation_covariance`). The CoG sums only the spot's pixels:
   those above the threshold ``t`` and a grown ring. Which pixels pass depends on the noise, and
   the profile beyond the ring is cut off; both move the centroid. The term is small for a bright
   compact spot and grows as a faint smear's brightness approaches the threshold (its ends and
   sides drop in and out of the mask). A model of the spot's shape (:func:`spot_shape`: length
   ``L`` along its long axis ``u``, width ``w`` across, brightness ``rho`` in thresholds), fitted
   by Monte Carlo (``tests/estimators/test_centroid_covariance.py`` checks it)::

       Cov_mask = (t / F)^2 [A (1 + E c_w) w^5 (L / 2)^2 / m  u u^T  +  C w^7 (L + 2 w) / m^0.75  I]
                  + beta^2 c_L v v^T

   with ``m = max(rho - 1, 0.25)`` and ``v`` the axis across the smear. The last part is the
   pixel-phase bias of the truncated profile across a smear, ``beta = B (sigma_t / t)^-1.5
   rho^-0.95`` px (``sigma_t``: the pixel noise at the threshold), which is the same all along a
   smear that runs along a pixel axis and averages out along a tilted one: ``c_L = 1 / (1 +
   (pi L tan(theta))^2)``, ``theta`` the smear's angle to the nearest pixel axis
   (:func:`phase_coherence`). The ends of a smear along a pixel axis leave the mask a whole row
   or column at a time, which ``1 + E c_w`` accounts for (``c_w`` the same coherence over the
   ends' width ``2 w``). ``A``, ``E``, ``C`` and ``B`` are :data:`TRUNCATION_ALONG`,
   :data:`END_COHERENT`, :data:`TRUNCATION_ACROSS` and :data:`PHASE_BIAS`, measured for the
   default mask (one grown ring) and PSF sigma 0.8-1.4 px.

3. Saturation (:func:`clipping_covariance`): a clipped, flat-topped spot has lost its sub-pixel
   information; saturation.py gives the RMS CoG error of a round plateau (added on both axes), of
   a clipped ridge across a smear (added across it, with the coherence ``c_L``) and of the ridge's
   clipped ends along it.

4. The detector edge (edge.py): a spot cut by the edge adds its CoG bias along the cut axis.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.special import erf

from rollingstar.estimators.centroiders.saturation import (
    clipped_cog_sigma_px,
    clipped_streak_end_variance,
    clipped_streak_variance,
)

#: ``A``, ``C``, ``B``, ``E`` of the mask term (module docstring), fitted to Monte Carlo of smeared spots.
TRUNCATION_ALONG = 1.2
TRUNCATION_ACROSS = 0.15
PHASE_BIAS = 0.0042
END_COHERENT = 1.0
MIN_MARGIN = 0.25  # rho - 1 floor: a spot no brighter than the threshold still gets a finite term
MIN_WIDTH_PX = 0.3
STREAK_LENGTH_WIDTHS = 2.0  # a saturated spot longer than this many widths is a clipped ridge


class SpotShape(NamedTuple):
    """Per spot: the long axis ``(ux, uy)``, the smear length and width (px) and the central
    brightness in thresholds, ``rho`` (see :func:`spot_shape`)."""

    ux: np.ndarray
    uy: np.ndarray
    length: np.ndarray
    width: np.ndarray
    rho: np.ndarray


def pixel_variance(d: np.ndarray, noise, gain: float | None, clipped: np.ndarray | None = None) -> np.ndarray:
    """``var_i`` (ADU^2) of pixels with values ``d`` above background: ``noise^2`` plus the star's
    shot noise ``max(d, 0) / gain`` (no shot term without a gain); 0 where ``clipped``."""
    var = np.broadcast_to(np.asarray(noise, dtype=float) ** 2, np.shape(d)).astype(float)
    if gain is not None and gain > 0:
        var = var + np.maximum(d, 0.0) / gain
    if clipped is not None:
        var = np.where(clipped, 0.0, var)
    return var


def label_moments(labels: np.ndarray, size: int, weights: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Per label (1..size-1): ``sum w dx^2, sum w dx dy, sum w dy^2`` as a (3, size - 1) array."""
    return np.stack([np.bincount(labels, weights=weights * a * b, minlength=size)[1:]
                     for a, b in ((dx, dx), (dx, dy), (dy, dy))])


def effective_gain(gain_param: float | None, context) -> float | None:
    """The gain (e-/ADU) of the shot-noise term: the centroider's ``gain_e_per_adu`` parameter when
    set, else the sensor context's (None: unknown, the shot term is left out)."""
    if gain_param is not None:
        return float(gain_param)
    gain = getattr(context, "gain_e_per_adu", None)
    return float(gain) if gain else None


def spot_shape(moments: np.ndarray, flux: np.ndarray, threshold) -> SpotShape:
    """Shape of spots from their intensity-weighted second moments ``moments`` (rows ``xx, xy, yy``
    of ``sum d (r - r_c)(r - r_c)^T / F``, px^2), eigenvalues ``l1 >= l2``: the long axis, the
    smear length ``L = sqrt(12 (l1 - l2))`` (a uniform streak of length L adds ``L^2 / 12`` to the
    variance along it), the width ``w = sqrt(l2)`` and ``rho``, the peak of a line of length ``L``
    and flux ``F`` blurred by a Gaussian of sigma ``w``, ``F erf(L / (2 sqrt(2) w)) / (sqrt(2 pi)
    w L)`` (``F / (2 pi w^2)`` as ``L -> 0``), over the threshold."""
    xx, xy, yy = moments
    half_diff = np.hypot(0.5 * (xx - yy), xy)
    mean = 0.5 * (xx + yy)
    l1, l2 = mean + half_diff, np.maximum(mean - half_diff, MIN_WIDTH_PX**2)
    angle = 0.5 * np.arctan2(2 * xy, xx - yy)
    length = np.sqrt(np.maximum(12.0 * (l1 - l2), 0.0))
    w = np.sqrt(l2)
    short = length < 1e-3 * w
    line = np.where(short, 1.0 / (np.sqrt(2 * np.pi) * w), erf(length / (2 * np.sqrt(2) * w)) / np.where(short, 1.0, length))
    rho = flux * line / (np.sqrt(2 * np.pi) * w) / threshold
    return SpotShape(np.cos(angle), np.sin(angle), length, w, rho)


def phase_coherence(shape: SpotShape) -> np.ndarray:
    """``1 / (1 + (pi L tan(theta))^2)``: how much of a pixel-phase bias across a smear survives
    along it (``theta`` the smear's angle to the nearest pixel axis; 1 along an axis)."""
    ax, ay = np.abs(shape.ux), np.abs(shape.uy)
    sweep = shape.length * np.minimum(ax, ay) / np.maximum(np.maximum(ax, ay), 1e-12)  # pixel phases passed
    return 1.0 / (1.0 + (np.pi * sweep) ** 2)


def _along_across(along: np.ndarray, across: np.ndarray, shape: SpotShape) -> np.ndarray:
    """Rows ``xx, xy, yy`` of ``along u u^T + across v v^T`` (``u`` the long axis, ``v`` across)."""
    ux, uy = shape.ux, shape.uy
    return np.stack([along * ux * ux + across * uy * uy, (along - across) * ux * uy, along * uy * uy + across * ux * ux])


def truncation_covariance(shape: SpotShape, flux: np.ndarray, threshold, noise, gain: float | None) -> np.ndarray:
    """The scatter the threshold mask adds to a spot's centroid, rows ``xx, xy, yy`` (px^2; module
    docstring, term 2). ``threshold`` and ``noise`` in ADU above background, ``gain`` e-/ADU."""
    margin = np.maximum(shape.rho - 1.0, MIN_MARGIN)
    w = shape.width
    scale = (np.asarray(threshold, dtype=float) / flux) ** 2
    ends = END_COHERENT * phase_coherence(SpotShape(shape.ux, shape.uy, 2.0 * w, w, shape.rho))
    along = TRUNCATION_ALONG * (1.0 + ends) * scale * w**5 * (0.5 * shape.length) ** 2 / margin
    iso = TRUNCATION_ACROSS * scale * w**7 * (shape.length + 2 * w) / margin**0.75
    t = np.asarray(threshold, dtype=float)
    sigma_t = np.sqrt(np.asarray(noise, dtype=float) ** 2 + (t / gain if gain else 0.0))
    beta = PHASE_BIAS * (sigma_t / t) ** -1.5 * np.maximum(shape.rho, 1.0) ** -0.95
    cov = _along_across(along, beta**2 * phase_coherence(shape), shape)
    return cov + np.stack([iso, np.zeros_like(iso), iso])


def clipping_covariance(shape: SpotShape, flux: np.ndarray, n_saturated: np.ndarray, saturated: np.ndarray,
                        saturation_above_bg) -> np.ndarray:
    """What clipping adds to the covariance of the ``saturated`` spots, rows ``xx, xy, yy``: a
    round plateau's sampling error on both axes (:func:`~rollingstar.estimators.centroiders.saturation.clipped_cog_sigma_px`),
    and for a smear longer than :data:`STREAK_LENGTH_WIDTHS` widths the clipped ridge's across it
    (:func:`~rollingstar.estimators.centroiders.saturation.clipped_streak_variance`, ridge width
    ``n_saturated / L``, times :func:`phase_coherence`) and that of its clipped ends along it
    (:func:`~rollingstar.estimators.centroiders.saturation.clipped_streak_end_variance`)."""
    sat = np.asarray(saturated, dtype=bool)
    flux = np.where(sat, flux, 0.0)
    n_sat = np.where(sat, n_saturated, 0)
    iso = clipped_cog_sigma_px(flux, n_sat, saturation_above_bg) ** 2
    streak = sat & (shape.length > STREAK_LENGTH_WIDTHS * shape.width)
    if not streak.any():  # round spots: the streak terms are zero
        return _along_across(iso, iso, shape)
    length = np.where(streak, np.maximum(shape.length, 1.0), 1.0)
    flux_streak = np.where(streak, flux, 0.0)
    across = clipped_streak_variance(flux_streak / length, n_sat / length, saturation_above_bg)
    along = clipped_streak_end_variance(flux_streak, length, n_sat / length, n_sat, saturation_above_bg)
    coherence = phase_coherence(shape)
    return _along_across(iso + along, iso + across * coherence, shape)


def spot_covariance(noise_moments: np.ndarray, shape_moments: np.ndarray, flux: np.ndarray, threshold, noise,
                    gain: float | None, n_saturated: np.ndarray | None = None, saturated: np.ndarray | None = None,
                    saturation_above_bg=None) -> np.ndarray:
    """Rows ``xx, xy, yy`` (3, n) of each spot's position covariance (px^2) but for the edge term:
    the noise propagation from ``noise_moments`` (``sum var_i (r_i - r)(r_i - r)^T`` per spot, rows
    ``xx, xy, yy``), the mask term from ``shape_moments`` (``sum d_i (r_i - r)(r_i - r)^T / F``)
    and, for ``saturated`` spots, the clipping term (``n_saturated`` pixels at the level
    ``saturation_above_bg`` above background). Module docstring, terms 1-3."""
    shape = spot_shape(shape_moments, flux, threshold)
    cov = noise_moments / flux**2 + truncation_covariance(shape, flux, threshold, noise, gain)
    if saturated is not None and np.any(saturated):
        cov = cov + clipping_covariance(shape, flux, n_saturated, saturated, saturation_above_bg)
    return cov


def isotropic_sigma(cov: np.ndarray) -> np.ndarray:
    """``sqrt((cov_xx + cov_yy) / 2)`` of covariances given as rows ``(xx, xy, yy)`` (3, n)."""
    return np.sqrt(0.5 * (cov[0] + cov[2]))


def with_axes(cov: np.ndarray, bx: np.ndarray, by: np.ndarray) -> np.ndarray:
    """``cov + diag(bx^2, by^2)``: a bias of unknown sign along each image axis."""
    return np.stack([cov[0] + np.asarray(bx, dtype=float) ** 2, cov[1], cov[2] + np.asarray(by, dtype=float) ** 2])
