"""Atmospheric refraction (ground-based tests): stars are lifted towards the zenith."""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from rollingstar.sensors.conventions import ARCSEC_TO_RAD
from rollingstar.sensors.effects.base import (
    STAGE_SKY,
    Alias,
    Effect,
    EffectParameter,
    as_positions,
)
from rollingstar.sensors.effects.geometry import project, to_camera

MIN_ELEVATION_RAD = np.radians(3.0)  # cot(e) is clipped below this elevation (the formula fails there anyway)


class Refraction(Effect):
    """Plane-parallel refraction ``R = r0 cot(e)`` (``e`` the star's elevation, ``r0`` the
    refraction constant, about 58 arcsec at sea level; accurate to ~1 arcsec above 15 deg).
    Each line of sight ``w`` is rotated by ``R`` towards the zenith ``z`` (camera frame
    ``R_att^T zenith``) in the vertical plane: with ``s = w.z``, ``t = (z - s w)/|z - s w|``::

        w' = w cos R + t sin R,       dw'/dr0 = (-w sin R + t cos R) cot(e) ARCSEC

    and ``d(x', y')/dr0 = P(w') dw'/dr0``.
    """

    name: ClassVar[str] = "refraction"
    follows: ClassVar[str] = "the zenith direction and cot(elevation)"
    shown_by: ClassVar[str] = "several elevations, or a turn about the boresight"
    synonyms: ClassVar[tuple[str, ...]] = ("atmospheric_refraction",)
    stage: ClassVar[int] = STAGE_SKY
    needs: ClassVar[tuple[str, ...]] = ("attitude", "zenith_icrs")
    parameters: ClassVar[tuple[EffectParameter, ...]] = (
        EffectParameter("r0_arcsec", "arcsec", 0.0, 60.0, (-120.0, 300.0),
                        "refraction constant: R = r0 cot(elevation) (58 arcsec at sea level, 15 C, 1013 hPa)"),
    )
    explanation: ClassVar[str] = (
        "Seen through the atmosphere, every star appears higher above the horizon than it is, by "
        "about one arcminute times the cotangent of its elevation. In a ground test or a "
        "night-sky recording this lifts the whole field towards the zenith (an attitude-like shift) "
        "and, because stars lower in the field are lifted more, compresses the field vertically: an "
        "image-plane scale change along the direction of the zenith that grows as the camera "
        "points lower. Space-borne trackers never see it."
    )
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("attitude", "the mean lift is a rigid rotation towards the zenith",
              "observe at several elevations: the lift follows cot(elevation)"),
        Alias("focal_length", "the differential part is a one-directional scale change of the field",
              "rotate the camera about its boresight (or observe at several elevations): refraction "
              "compresses along the vertical only and its size follows cot(elevation)^2"),
    )

    def _geometry(self, x, y, ctx):
        self._require(ctx)
        w = ctx.camera.unproject(x, y).reshape(-1, 3)
        z = to_camera(ctx.attitude, ctx.zenith_icrs)
        z = z / np.linalg.norm(z, axis=1, keepdims=True)
        s = np.sum(w * z, axis=1)
        e = np.maximum(np.arcsin(np.clip(s, -1.0, 1.0)), MIN_ELEVATION_RAD)
        cot = 1.0 / np.tan(e)
        t = z - s[:, None] * w
        t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-15)
        r = self._values["r0_arcsec"] * ARCSEC_TO_RAD * cot
        return w, t, r, cot

    def apply(self, x, y, ctx):
        x, y = as_positions(x, y)
        if self.is_identity:
            return x, y
        w, t, r, _ = self._geometry(x, y, ctx)
        return project(ctx.camera, w * np.cos(r)[:, None] + t * np.sin(r)[:, None])

    def jacobian(self, x, y, ctx):
        x, y = as_positions(x, y)
        w, t, r, cot = self._geometry(x, y, ctx)
        w2 = w * np.cos(r)[:, None] + t * np.sin(r)[:, None]
        dw = (-w * np.sin(r)[:, None] + t * np.cos(r)[:, None]) * (cot * ARCSEC_TO_RAD)[:, None]
        return ctx.camera.projection_jacobian(w2) @ dw[:, :, None]
