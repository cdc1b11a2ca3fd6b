"""Empirical corrections: shapes a diagnosis measured outside the physics library.

When a recording's residual keeps a systematic no library effect explains, the diagnosis describes
it by the smallest generic shape that does (:mod:`rollingstar.estimators.diagnosis.describe`) and
writes it to the updated scenario as one of these effects, so that the simulation matches the
recording before the physics is known. They are never candidates of a diagnosis (``empirical``):
a measured shape says where and how big, not why.

Discrete choices (which axis moves, which coordinate the shape runs along) are parameters with the
values 0 (x, column) and 1 (y, row), so that a scenario file can state them like any other effect.
"""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from rollingstar.sensors.effects.base import STAGE_DETECTOR, Alias, Effect, EffectParameter, as_positions

AXIS_BOUNDS = (0.0, 1.0)


def _moved(x, y, axis: int, shift):
    """``(x, y)`` with ``shift`` added to the chosen axis (0: x, 1: y)."""
    return (x, y + shift) if axis else (x + shift, y)


def _choice(value: float, name: str) -> int:
    if value not in (0.0, 1.0):
        raise ValueError(f"{name} must be 0 (x / column) or 1 (y / row), got {value}")
    return int(value)


class EmpiricalStep(Effect):
    """One axis's position steps by ``size_px`` for stars beyond a column (or row):
    ``p'[axis] = p[axis] + size_px * (coord > at_px)``, with ``coord`` the star's column
    (``across = 0``) or row (``across = 1``)."""

    name: ClassVar[str] = "empirical_step"
    follows: ClassVar[str] = "which side of one detector column (or row) the star is on"
    shown_by: ClassVar[str] = "stars crossing that column (or row)"
    empirical: ClassVar[bool] = True
    stage: ClassVar[int] = STAGE_DETECTOR
    parameters: ClassVar[tuple[EffectParameter, ...]] = (
        EffectParameter("axis", "", 0.0, 1.0, AXIS_BOUNDS, "axis that moves: 0 x, 1 y"),
        EffectParameter("across", "", 0.0, 1.0, AXIS_BOUNDS, "coordinate of the step: 0 a column, 1 a row"),
        EffectParameter("at_px", "px", 0.0, 1.0, (-1e5, 1e5), "column (or row) where the step is"),
        EffectParameter("size_px", "px", 0.0, 0.05, (-50.0, 50.0), "size of the step"),
    )
    explanation: ClassVar[str] = (
        "An empirical correction measured by rollingstar diagnose: the stars on one side of a detector "
        "column (or row) are displaced by a constant amount along one axis, as a detector made of two "
        "stitched dies, a readout split or a mounting discontinuity would do. It says where and how "
        "big, not why.")
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("principal_point", "over a frame whose stars lie mostly on one side the step is a shift of the field",
              "stars on both sides of the step in the same frame"),
    )

    def _step(self, x, y):
        v = self._values
        axis, across = _choice(v["axis"], "axis"), _choice(v["across"], "across")
        beyond = ((y if across else x) > v["at_px"]).astype(float)
        return axis, beyond

    def apply(self, x, y, ctx):
        x, y = as_positions(x, y)
        axis, beyond = self._step(x, y)
        return _moved(x, y, axis, self._values["size_px"] * beyond)

    def jacobian(self, x, y, ctx):
        x, y = as_positions(x, y)
        axis, beyond = self._step(x, y)
        jac = np.zeros((x.size, 2, 4))
        jac[:, axis, 3] = beyond
        return jac


class EmpiricalRipple(Effect):
    """One axis's position ripples along a coordinate:
    ``p'[axis] = p[axis] + amplitude_px * sin(2 pi coord / period_px + phase_rad)``, with ``coord``
    the star's column (``along = 0``) or row (``along = 1``)."""

    name: ClassVar[str] = "empirical_ripple"
    follows: ClassVar[str] = "a sine of one detector coordinate"
    shown_by: ClassVar[str] = "stars spread over several periods of the ripple"
    empirical: ClassVar[bool] = True
    stage: ClassVar[int] = STAGE_DETECTOR
    parameters: ClassVar[tuple[EffectParameter, ...]] = (
        EffectParameter("axis", "", 0.0, 1.0, AXIS_BOUNDS, "axis that moves: 0 x, 1 y"),
        EffectParameter("along", "", 0.0, 1.0, AXIS_BOUNDS, "coordinate the ripple runs along: 0 columns, 1 rows"),
        EffectParameter("period_px", "px", 100.0, 10.0, (1.0, 1e5), "period of the ripple"),
        EffectParameter("amplitude_px", "px", 0.0, 0.05, (-50.0, 50.0), "amplitude of the ripple"),
        EffectParameter("phase_rad", "rad", 0.0, 1.0, (-np.pi, np.pi), "phase at coordinate 0"),
    )
    explanation: ClassVar[str] = (
        "An empirical correction measured by rollingstar diagnose: positions along one axis oscillate "
        "with the column (or row), as a periodic detector defect (mask stitching, a column-parallel "
        "readout pattern) would do. It says where and how big, not why.")
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("pixel_phase_bias", "a ripple with a period of one pixel along the same axis is the pixel-phase bias",
              "stars drifting across many pixels: the pixel-phase bias repeats every pixel, a ripple at its own period"),
    )

    def _wave(self, x, y):
        v = self._values
        axis, along = _choice(v["axis"], "axis"), _choice(v["along"], "along")
        arg = 2.0 * np.pi * (y if along else x) / v["period_px"] + v["phase_rad"]
        return axis, arg

    def apply(self, x, y, ctx):
        x, y = as_positions(x, y)
        axis, arg = self._wave(x, y)
        return _moved(x, y, axis, self._values["amplitude_px"] * np.sin(arg))

    def jacobian(self, x, y, ctx):
        x, y = as_positions(x, y)
        axis, arg = self._wave(x, y)
        v = self._values
        jac = np.zeros((x.size, 2, 5))
        coord = y if v["along"] else x
        jac[:, axis, 2] = -v["amplitude_px"] * np.cos(arg) * 2.0 * np.pi * coord / v["period_px"] ** 2
        jac[:, axis, 3] = np.sin(arg)
        jac[:, axis, 4] = v["amplitude_px"] * np.cos(arg)
        return jac
