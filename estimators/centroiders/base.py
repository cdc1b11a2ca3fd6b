"""Centroiders: raw image -> detected spots (``frame.stars``, unidentified)."""
from __future__ import annotations

from rollingstar.estimators.plugin import Plugin


class Centroider(Plugin):
    """Reads ``frame.image`` and sets ``frame.stars`` to the detected spots.

    Every spot gets ``x, y`` (px), ``row_time_ns`` (exposure start of its centroid row, from the
    sensor timing), ``t_ns`` (mid-exposure of that row), ``flux``, ``peak``, ``npix``,
    ``saturated`` and ``snr``. ``catalog_id`` stays -1.
    """

    role = "centroider"
    needs = frozenset({"image"})
    provides = frozenset({"spots"})
