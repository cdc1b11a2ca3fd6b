"""Tangential (decentring) lens distortion, Brown-Conrady terms p1, p2."""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from rollingstar.sensors.effects.base import (
    STAGE_OPTICS,
    Alias,
    Effect,
    EffectParameter,
    as_positions,
)


class TangentialDistortion(Effect):
    """Brown-Conrady decentring distortion (Brown 1966; OpenCV's p1, p2) about the nominal
    principal point, with ``xn = (x - cx)/f_px``, ``yn = (y - cy)/f_px``, ``r^2 = xn^2 + yn^2``::

        x' = x + f_px [2 p1 xn yn + p2 (r^2 + 2 xn^2)]
        y' = y + f_px [p1 (r^2 + 2 yn^2) + 2 p2 xn yn]

    linear in ``p1, p2``, so the Jacobian is the bracket times ``f_px``.
    """

    name: ClassVar[str] = "tangential_distortion"
    follows: ClassVar[str] = "r^2 from the principal point, decentred"
    shown_by: ClassVar[str] = "stars over the whole detector"
    synonyms: ClassVar[tuple[str, ...]] = ("tangential", "decentering_distortion", "decentring_distortion")
    stage: ClassVar[int] = STAGE_OPTICS
    parameters: ClassVar[tuple[EffectParameter, ...]] = (
        EffectParameter("p1", "1", 0.0, 1e-3, (-0.1, 0.1), "first decentring coefficient (normalised coordinates)"),
        EffectParameter("p2", "1", 0.0, 1e-3, (-0.1, 0.1), "second decentring coefficient (normalised coordinates)"),
    )
    explanation: ClassVar[str] = (
        "When the lens elements are not perfectly centred on a common axis (or the detector is "
        "tilted), the image is distorted asymmetrically: stars on one side of the field are pushed "
        "further than on the other, along a preferred direction. Residuals grow with the square of "
        "the distance from the image centre and have both radial and tangential components; the "
        "pattern is fixed in the image, the same in every frame and independent of motion."
    )
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("principal_point", "near the centre decentring looks like a small shift of the optical centre",
              "use stars over the whole detector: the decentring term grows as r^2, a principal-point shift is uniform"),
        Alias("attitude", "the mean displacement over a small field is a rigid shift",
              "cover the full field of view with stars in every frame"),
    )

    def _basis(self, x, y, cam):
        f = cam.focal_px
        xn, yn = (x - cam.cx) / f, (y - cam.cy) / f
        r2, xy = xn * xn + yn * yn, 2 * xn * yn
        out = np.empty(xn.shape + (2, 2))  # columns: d(x, y)/d p1, d(x, y)/d p2
        out[..., 0, 0], out[..., 1, 0] = xy * f, (r2 + 2 * yn * yn) * f
        out[..., 0, 1], out[..., 1, 1] = (r2 + 2 * xn * xn) * f, xy * f
        return out

    def apply(self, x, y, ctx):
        x, y = as_positions(x, y)
        if self.is_identity:
            return x, y
        d = self._basis(x, y, ctx.camera) @ self.vector
        return x + d[:, 0], y + d[:, 1]

    def jacobian(self, x, y, ctx):
        x, y = as_positions(x, y)
        return self._basis(x, y, ctx.camera)
