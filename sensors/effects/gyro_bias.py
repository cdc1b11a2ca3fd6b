"""Gyro bias: a constant rate offset in the gyro samples."""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from rollingstar.sensors.conventions import DEG_TO_RAD, S_PER_HOUR
from rollingstar.sensors.effects.base import (
    STAGE_GYRO,
    Alias,
    Effect,
    EffectParameter,
    as_positions,
)

DEG_H = DEG_TO_RAD / S_PER_HOUR  # rad/s per deg/h


class GyroBias(Effect):
    """Measured rate ``omega' = omega + b`` (body frame, ``b`` in deg/h); ``d omega'/d b = DEG_H I``.
    No image-plane signature (the Jacobian is zero)."""

    name: ClassVar[str] = "gyro_bias"
    follows: ClassVar[str] = "a constant rate offset of the gyro"
    shown_by: ClassVar[str] = "an inertial hold with the gyro logged"
    synonyms: ClassVar[tuple[str, ...]] = ("gyro_offset",)
    stage: ClassVar[int] = STAGE_GYRO
    channels: ClassVar[frozenset[str]] = frozenset({"gyro"})
    parameters: ClassVar[tuple[EffectParameter, ...]] = tuple(
        EffectParameter(f"b{a}_deg_h", "deg/h", 0.0, 1.0, (-3600.0, 3600.0), f"gyro bias about camera {a}") for a in "xyz"
    )
    explanation: ClassVar[str] = (
        "Every gyro reports a small non-zero rate when it is not turning. Integrated over time the "
        "bias makes a gyro-propagated attitude drift away from the star tracker's at a constant "
        "rate, whatever the vehicle is doing. It leaves the star images untouched; it is seen by "
        "comparing the gyro with the rate the star tracker measures."
    )
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("gyro_scale", "at a single constant rate a scale error is also a constant rate offset",
              "hold inertially and rotate at two rates (or reverse): the bias is the same, the scale error "
              "follows the rate"),
    )

    def apply(self, x, y, ctx):
        return as_positions(x, y)

    def jacobian(self, x, y, ctx):
        x, _ = as_positions(x, y)
        return np.zeros((x.size, 2, 3))

    def apply_gyro(self, t_ns, omega_rad_s):
        return np.asarray(omega_rad_s, dtype=float) + self.vector * DEG_H

    def gyro_jacobian(self, t_ns, omega_rad_s):
        m = np.asarray(omega_rad_s, dtype=float).reshape(-1, 3).shape[0]
        return np.broadcast_to(np.eye(3) * DEG_H, (m, 3, 3)).copy()
