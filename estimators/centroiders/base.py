"""Centroiders: raw image -> detected spots (``frame.stars``, unidentified)."""
from __future__ import annotations

from rollingstar.estimators.plugin import Plugin


class Centroider(Plugin):
    """Reads ``frame.image`` and sets ``frame.stars`` to the detected spots.

    Every spot gets ``x, y`` (px), ``row_time_ns`` (exposure start of its centroid row, from the
    sensor timing), ``t_ns`` (mid-exposure of that row), ``flux``, ``peak``, ``npix``,
    ``saturated`` and ``snr``, and its 2 x 2 position covariance ``cov_xx, cov_xy, cov_yy`` (px^2,
    image axes) from its own pixels and the noise model (the shipped centroiders:
    :mod:`rollingstar.estimators.centroiders.covariance`; a smeared spot's is long along the smear).
    ``sigma_px`` is then the derived isotropic per-axis sigma ``sqrt((cov_xx + cov_yy) / 2)``, kept
    for readers that weight by one number; a centroider that cannot say more than one number
    leaves the ``cov_*`` NaN and sets ``sigma_px``. ``catalog_id`` stays -1.
    """

    role = "centroider"
    needs = frozenset({"image"})
    provides = frozenset({"spots"})
