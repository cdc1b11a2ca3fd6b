"""Focal-length error: the plate scale differs from the nominal one."""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from rollingstar.sensors.effects.base import (
    STAGE_OPTICS,
    Alias,
    Effect,
    EffectParameter,
    as_positions,
    stack_jacobian,
)

PPM = 1e-6


class FocalLength(Effect):
    """The true focal length is ``f (1 + s)``, ``s = df_ppm 1e-6``. The pinhole projection is linear
    in ``f`` about the principal point, so ``x' = cx + (x - cx)(1 + s)`` (same for y) and
    ``d(x', y')/d df_ppm = (x - cx, y - cy) 1e-6``.
    """

    name: ClassVar[str] = "focal_length"
    follows: ClassVar[str] = "the distance r from the principal point, radially, as r"
    shown_by: ClassVar[str] = "stars out to the detector corners"
    synonyms: ClassVar[tuple[str, ...]] = ("plate_scale", "focal_length_error")
    stage: ClassVar[int] = STAGE_OPTICS
    parameters: ClassVar[tuple[EffectParameter, ...]] = (
        EffectParameter("df_ppm", "ppm", 0.0, 300.0, (-1e5, 1e5), "relative focal-length error (true / nominal - 1)"),
    )
    explanation: ClassVar[str] = (
        "The effective focal length differs from the value in the camera model (lens tolerance, "
        "focus setting, a calibration done at another temperature). Every star is displaced radially "
        "from the principal point in proportion to its distance: the star field looks uniformly "
        "magnified or shrunk, so angles between stars are all wrong by the same fraction while the "
        "attitude of the field's centre is unaffected. It does not change with time or motion."
    )
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("radial_distortion", "over a small field the k1 r^3 term is partly fitted by a linear scale",
              "use stars out to the detector corners: the distortion grows as r^3, the focal error as r"),
        Alias("thermal_focal_drift", "a constant temperature offset is a constant focal-length error",
              "record over a temperature (or time) swing: only the drift follows the covariate"),
        Alias("rolling_shutter", "at a constant rate along the columns the rolling-shutter shear scales y only",
              "reverse the rotation or hold inertially: the rolling-shutter part flips or vanishes"),
    )

    def apply(self, x, y, ctx):
        x, y = as_positions(x, y)
        s = 1.0 + self._values["df_ppm"] * PPM
        cam = ctx.camera
        return cam.cx + (x - cam.cx) * s, cam.cy + (y - cam.cy) * s

    def jacobian(self, x, y, ctx):
        x, y = as_positions(x, y)
        d = np.stack([x - ctx.camera.cx, y - ctx.camera.cy], axis=-1) * PPM
        return stack_jacobian(d)
