"""Detector roll: the pixel grid is rotated about the boresight relative to the camera body frame."""
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
from rollingstar.sensors.effects.geometry import rotate_line_of_sight


class BoresightRotation(Effect):
    """The detector is rolled by ``gamma`` about the camera z axis: a body-frame direction ``w`` is
    seen at ``Rz(gamma)^T w`` -- exactly a rotation of the image about the principal point::

        (x', y') = project(Exp([0, 0, gamma])^T w),    d(x', y')/d gamma = P(w') [w']x e_z   (x ARCSEC)

    (``J_r`` of a single-axis rotation leaves its axis unchanged).
    """

    name: ClassVar[str] = "boresight_rotation"
    follows: ClassVar[str] = "a rotation of the field about the principal point (tangential, growing as r)"
    shown_by: ClassVar[str] = "a turn about a cross-boresight axis measured by a gyro"
    synonyms: ClassVar[tuple[str, ...]] = ("detector_roll", "roll_misalignment")
    stage: ClassVar[int] = STAGE_SKY
    channels: ClassVar[frozenset[str]] = frozenset({"image", "attitude"})
    parameters: ClassVar[tuple[EffectParameter, ...]] = (
        EffectParameter("roll_arcsec", "arcsec", 0.0, 60.0, (-36000.0, 36000.0),
                        "rotation of the pixel grid about the boresight (right-handed about +z)"),
    )
    explanation: ClassVar[str] = (
        "The detector is mounted slightly rotated about the optical axis relative to the frame the "
        "camera's attitude (and its gyro) refers to. Every star image is rotated by that angle about "
        "the principal point, which within one image is exactly the same as the tracker being rolled "
        "about its boresight. It is therefore invisible to a star tracker on its own; it appears as a "
        "constant roll offset against an external attitude, and as image motion that is not parallel "
        "to the direction the gyro says the camera is turning."
    )
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("attitude", "an image rotation about the principal point is exactly a roll of the camera",
              "turn about a cross-boresight axis measured by the gyro: the star trails make the angle gamma "
              "with the gyro-predicted direction (or compare with a second, co-aligned tracker)"),
    )

    def _rotvec(self, n):
        d = np.zeros((n, 3))
        d[:, 2] = self._values["roll_arcsec"] * ARCSEC_TO_RAD
        return d

    def apply(self, x, y, ctx):
        x, y = as_positions(x, y)
        if self.is_identity:
            return x, y
        x2, y2, _ = rotate_line_of_sight(ctx.camera, x, y, self._rotvec(x.size), jacobian=False)
        return x2, y2

    def jacobian(self, x, y, ctx):
        x, y = as_positions(x, y)
        _, _, jrot = rotate_line_of_sight(ctx.camera, x, y, self._rotvec(x.size))
        return jrot[:, :, 2:3] * ARCSEC_TO_RAD
