"""Angular acceleration: the body rate changes during the rolling readout of one frame."""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from rollingstar.sensors.conventions import DEG_TO_RAD, NS_PER_S
from rollingstar.sensors.effects.base import (
    STAGE_SKY,
    Alias,
    Effect,
    EffectParameter,
    as_positions,
)
from rollingstar.sensors.effects.geometry import rotate_line_of_sight


class AngularAcceleration(Effect):
    """A body angular acceleration ``alpha`` (deg/s^2) not in the nominal constant-rate-per-frame
    model. Relative to the frame's reference time ``t_ref`` (mid-exposure of the middle row,
    :meth:`~rollingstar.sensors.timing.DetectorTiming.frame_reference_ns`), an observation at ``t`` sees the
    camera turned further by the body rotation ``d = alpha tau^2 / 2``, ``tau = t - t_ref``
    (the quadratic term of ``theta(tau) = omega tau + alpha tau^2 / 2``, :mod:`rollingstar.sensors.motion`)::

        w' = Exp(d)^T w,    d(x', y')/d alpha = P(w') [w']x J_r(d) tau^2 / 2     (per axis, x DEG)

    The constant and linear parts are what the per-frame attitude and rate absorb; only the
    quadratic part is this effect. The gyro channel is not altered.
    """

    name: ClassVar[str] = "angular_acceleration"
    follows: ClassVar[str] = "the square of each row's time from the frame centre (a rate change within the frame)"
    shown_by: ClassVar[str] = "a rate ramp against a constant rate"
    synonyms: ClassVar[tuple[str, ...]] = ("rate_change", "acceleration")
    stage: ClassVar[int] = STAGE_SKY
    needs: ClassVar[tuple[str, ...]] = ("timing", "t0_ns")
    parameters: ClassVar[tuple[EffectParameter, ...]] = tuple(
        EffectParameter(f"alpha_{a}_deg_s2", "deg/s^2", 0.0, 1.0, (-1000.0, 1000.0),
                        f"body angular acceleration about camera {a} within a frame")
        for a in "xyz"
    )
    explanation: ClassVar[str] = (
        "Star-tracker models usually assume the rate is constant over one frame. When the vehicle "
        "is accelerating (slew start and stop, reaction-wheel torque, vibration), the rate changes "
        "while a rolling shutter reads the frame out row by row, so the rows see attitudes that lie "
        "on a curve rather than a line. After the frame's attitude and rate are fitted, what is left "
        "grows with the square of the time from the middle of the frame: largest in the first and "
        "last rows, absent with a global shutter, and proportional to the acceleration, not the rate."
    )
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("rolling_shutter", "both displace stars according to their row",
              "fly a constant rate and a rate ramp: the line-delay shear depends on the rate, the acceleration "
              "signature only on the rate change (and is quadratic, not linear, in the row)"),
        Alias("rate", "the part linear in the row time is absorbed by a per-frame rate",
              "use a gyro: it measures the rate change directly"),
    )

    def _rotvec_basis(self, ctx):
        self._require(ctx)
        t_ref = ctx.t0_ns + np.int64(ctx.timing.frame_reference_ns(0))  # reference time relative to t0
        tau = (ctx.t_ns - t_ref).astype(float) / NS_PER_S
        return 0.5 * tau * tau * DEG_TO_RAD  # rad per (deg/s^2), (n,)

    def apply(self, x, y, ctx):
        x, y = as_positions(x, y)
        if self.is_identity:
            return x, y
        d = self._rotvec_basis(ctx)[:, None] * self.vector[None, :]
        x2, y2, _ = rotate_line_of_sight(ctx.camera, x, y, d, jacobian=False)
        return x2, y2

    def jacobian(self, x, y, ctx):
        x, y = as_positions(x, y)
        b = self._rotvec_basis(ctx)
        _, _, jrot = rotate_line_of_sight(ctx.camera, x, y, b[:, None] * self.vector[None, :])
        return jrot * b[:, None, None]
