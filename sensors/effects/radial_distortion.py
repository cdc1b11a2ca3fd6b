"""Radial lens distortion (Brown-Conrady, radial terms k1, k2)."""
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


class RadialDistortion(Effect):
    """Brown-Conrady radial distortion about the nominal principal point.

    With normalised image coordinates ``xn = (x - cx) / f_px``, ``yn = (y - cy) / f_px`` and
    ``r^2 = xn^2 + yn^2``::

        x' = cx + f_px * xn * (1 + k1 r^2 + k2 r^4)
        y' = cy + f_px * yn * (1 + k1 r^2 + k2 r^4)

    so ``d x' / d k1 = (x - cx) r^2`` and ``d x' / d k2 = (x - cx) r^4`` (same for y).
    """

    name: ClassVar[str] = "radial_distortion"
    follows: ClassVar[str] = "r^3 and r^5 from the principal point, radially"
    shown_by: ClassVar[str] = "stars out to the detector corners"
    synonyms: ClassVar[tuple[str, ...]] = ("radial", "brown_conrady_radial", "distortion")
    stage: ClassVar[int] = STAGE_OPTICS
    parameters: ClassVar[tuple[EffectParameter, ...]] = (
        EffectParameter("k1", "1", 0.0, 1e-2, (-1.0, 1.0), "second-order radial coefficient (normalised coordinates)"),
        EffectParameter("k2", "1", 0.0, 1e-1, (-10.0, 10.0), "fourth-order radial coefficient (normalised coordinates)"),
    )
    explanation: ClassVar[str] = (
        "The lens does not map angles to pixels exactly as a pinhole: stars are pushed outwards "
        "(pincushion, k1 > 0) or pulled inwards (barrel, k1 < 0) by an amount that grows with the "
        "cube of their distance from the optical centre. It shows up as residuals that point "
        "radially away from (or towards) the image centre and grow towards the corners, the same "
        "in every frame and independent of motion; a focal-length error instead grows only "
        "linearly with radius."
    )
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("focal_length", "over a narrow field the r^3 displacement is partly fitted by a linear scale",
              "use stars out to the detector corners (or a wider field): distortion grows as r^3, a focal error as r"),
        Alias("refraction", "refraction compresses the field like a (one-directional) scale/distortion",
              "rotate about the boresight or change elevation: refraction follows the zenith, lens distortion the detector"),
    )

    def apply(self, x, y, ctx):
        x, y = as_positions(x, y)
        cam = ctx.camera
        dx, dy = x - cam.cx, y - cam.cy
        r2 = (dx * dx + dy * dy) / cam.focal_px**2
        scale = 1.0 + r2 * (self._values["k1"] + self._values["k2"] * r2)
        return cam.cx + dx * scale, cam.cy + dy * scale

    def jacobian(self, x, y, ctx):
        x, y = as_positions(x, y)
        cam = ctx.camera
        dx, dy = x - cam.cx, y - cam.cy
        r2 = (dx * dx + dy * dy) / cam.focal_px**2
        d = np.stack([dx, dy], axis=-1)  # (n, 2)
        return np.stack([d * r2[:, None], d * (r2 * r2)[:, None]], axis=-1)  # (n, 2, 2)
