"""Gyro scale-factor error: the gyro reports rates too large or too small by a fixed fraction."""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from rollingstar.sensors.effects.base import (
    STAGE_GYRO,
    Alias,
    Effect,
    EffectParameter,
    as_positions,
)

PPM = 1e-6


class GyroScale(Effect):
    """Measured rate ``omega'_i = omega_i (1 + s_i 1e-6)`` per body axis; ``d omega'_i/d s_i = omega_i 1e-6``.
    No image-plane signature."""

    name: ClassVar[str] = "gyro_scale"
    follows: ClassVar[str] = "the gyro's rate, in proportion"
    shown_by: ClassVar[str] = "two rates (or a reversal) with the gyro logged"
    synonyms: ClassVar[tuple[str, ...]] = ("gyro_scale_factor",)
    stage: ClassVar[int] = STAGE_GYRO
    channels: ClassVar[frozenset[str]] = frozenset({"gyro"})
    parameters: ClassVar[tuple[EffectParameter, ...]] = tuple(
        EffectParameter(f"s{a}_ppm", "ppm", 0.0, 100.0, (-1e5, 1e5), f"gyro scale-factor error about camera {a}") for a in "xyz"
    )
    explanation: ClassVar[str] = (
        "A gyro's output is proportional to the rate, but the constant of proportionality differs "
        "from the nominal one by tens to hundreds of ppm. The error is proportional to the rate: "
        "invisible while the vehicle is still, it makes the gyro over- or under-estimate every "
        "rotation by the same fraction, and the error reverses with the direction of rotation."
    )
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("gyro_bias", "at a single constant rate a scale error is also a constant rate offset",
              "rotate at two different rates, or reverse the rotation: a scale error follows the rate, a bias does not"),
    )

    def apply(self, x, y, ctx):
        return as_positions(x, y)

    def jacobian(self, x, y, ctx):
        x, _ = as_positions(x, y)
        return np.zeros((x.size, 2, 3))

    def apply_gyro(self, t_ns, omega_rad_s):
        w = np.asarray(omega_rad_s, dtype=float)
        return w * (1.0 + self.vector * PPM)

    def gyro_jacobian(self, t_ns, omega_rad_s):
        w = np.asarray(omega_rad_s, dtype=float).reshape(-1, 3)
        jac = np.zeros((w.shape[0], 3, 3))
        for i in range(3):  # three axes, not a per-sample loop
            jac[:, i, i] = w[:, i] * PPM
        return jac
