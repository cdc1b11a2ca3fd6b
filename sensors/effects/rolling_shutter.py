"""Rolling shutter: the rows expose one line delay after another (or the line delay is not the nominal one)."""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from rollingstar.sensors.effects.base import Alias, EffectParameter
from rollingstar.sensors.effects.timeshift import TimeShiftEffect


class RollingShutter(TimeShiftEffect):
    """Row ``r`` is seen ``r * d_ld`` later than the nominal timing says (he2021a eq 5 timing with
    line delay ``ld + d_ld``): ``dt = row * d_ld``, so to first order ``(x', y') = (x, y) + (vx, vy) y d_ld``
    -- an image shear along the motion growing with the row (see :mod:`rollingstar.sensors.effects.timeshift`).
    """

    name: ClassVar[str] = "rolling_shutter"
    follows: ClassVar[str] = "row x image velocity (flips sign with the rate)"
    shown_by: ClassVar[str] = "a rate reversal or an inertial hold"
    synonyms: ClassVar[tuple[str, ...]] = ("line_delay", "line_delay_error")
    needs: ClassVar[tuple[str, ...]] = ("omega_rad_s",)
    parameters: ClassVar[tuple[EffectParameter, ...]] = (
        EffectParameter("line_delay_error_us", "us", 0.0, 10.0, (-1000.0, 1000.0),
                        "true minus nominal delay between the exposure starts of adjacent rows"),
    )
    explanation: ClassVar[str] = (
        "A CMOS rolling shutter starts exposing each row one line delay after the previous one, so "
        "a moving tracker sees the stars of the bottom rows later than those of the top rows. If the "
        "model assumes a global shutter (or the wrong line delay), every star is displaced along its "
        "image velocity by velocity x row x line-delay error: a shear of the star field that grows "
        "from the first to the last row, vanishes when the tracker is inertially held, and reverses "
        "sign when the rotation reverses."
    )
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("focal_length", "at a constant rate along the columns the shear is a y-only scale (an aspect-ratio "
              "change), which a focal-length error partly mimics",
              "reverse the rotation (or hold inertially): the rolling-shutter shear flips sign with the rate, "
              "a focal-length / aspect-ratio error does not"),
        Alias("rate", "the part of the shear common to all rows is absorbed by a per-frame rate estimate",
              "compare the estimated rate with a gyro, or use frames at two different rates"),
        Alias("angular_acceleration", "both grow with the row; acceleration quadratically, line delay linearly",
              "fly a constant rate (no acceleration) and a rate ramp; only the acceleration signature changes"),
    )

    def shift_basis(self, ctx):
        return (np.asarray(ctx.rows, dtype=float) * 1e-6)[:, None]
