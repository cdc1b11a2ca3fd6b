"""Common machinery of the time-stage effects: a shift ``dt = sum_j basis_j(ctx) p_j`` of the instant seen.

A star seen ``dt`` later than the nominal timing says is seen along ``w' = Exp(omega dt)^T w``
(body rate ``omega``, :mod:`rollingstar.sensors.motion` kinematics, exact for a constant rate), so with
:func:`rollingstar.sensors.effects.geometry.rotate_line_of_sight`::

    (x', y') = project(Exp(omega dt)^T w),     d(x', y')/dp_j = J_rot(omega dt) omega basis_j

To first order this is ``(x, y) + (vx, vy) dt``. The simulator does not call :meth:`apply` of
these effects: it evaluates the true motion at ``t + dt`` (:func:`rollingstar.sensors.effects.chain.time_shift_s`).
"""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from rollingstar.sensors.effects.base import (
    STAGE_TIME,
    Effect,
    EffectContext,
    as_positions,
)
from rollingstar.sensors.effects.geometry import rotate_line_of_sight


class TimeShiftEffect(Effect):
    """An effect whose only physics is a (parameter-linear) shift of the observation instant."""

    stage: ClassVar[int] = STAGE_TIME
    channels: ClassVar[frozenset[str]] = frozenset({"image", "time"})
    time_needs: ClassVar[tuple[str, ...]] = ()  # context fields :meth:`time_shift_s` needs (the rate is not one)

    def shift_basis(self, ctx: EffectContext) -> np.ndarray:  # pragma: no cover - interface
        """``d dt / d p`` (n, n_params) in seconds per parameter unit."""
        raise NotImplementedError

    def _offsets(self) -> np.ndarray:
        return self.vector - np.array([p.default for p in self.parameters])

    def time_shift_s(self, ctx):
        ctx.require(self.time_needs, f"effect {self.name!r}")
        return self.shift_basis(ctx) @ self._offsets()

    def time_shift_jacobian(self, ctx):
        ctx.require(self.time_needs, f"effect {self.name!r}")
        return self.shift_basis(ctx)

    def apply(self, x, y, ctx):
        x, y = as_positions(x, y)
        self._require(ctx)
        dt = self.time_shift_s(ctx)
        if not np.any(dt):
            return x, y
        x2, y2, _ = rotate_line_of_sight(ctx.camera, x, y, ctx.omega_rad_s * dt[:, None], jacobian=False)
        return x2, y2

    def jacobian(self, x, y, ctx):
        x, y = as_positions(x, y)
        self._require(ctx)
        basis = self.time_shift_jacobian(ctx)
        dt = basis @ self._offsets()
        _, _, jrot = rotate_line_of_sight(ctx.camera, x, y, ctx.omega_rad_s * dt[:, None])
        v = jrot @ ctx.omega_rad_s[:, :, None]  # (n, 2, 1): image velocity at the shifted instant
        return v * basis[:, None, :]
