"""Exposure smear bias: the centroid of a streaked star does not refer to the middle of the exposure."""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from rollingstar.sensors.conventions import NS_PER_S
from rollingstar.sensors.effects.base import Alias, EffectParameter
from rollingstar.sensors.effects.timeshift import TimeShiftEffect


class ExposureSmear(TimeShiftEffect):
    """The centroid of a star smeared over the exposure ``T`` lies a fraction ``b`` of the streak
    ahead of its mid-exposure position: ``dt = b T``, ``(x', y') = (x, y) + (vx, vy) b T`` to first
    order (a uniform streak has ``b = 0``; thresholding, saturation or non-uniform exposure
    weighting make ``b != 0``)."""

    name: ClassVar[str] = "exposure_smear"
    follows: ClassVar[str] = "image velocity x exposure time"
    shown_by: ClassVar[str] = "two exposure times at the same rate"
    synonyms: ClassVar[tuple[str, ...]] = ("smear", "smear_bias")
    needs: ClassVar[tuple[str, ...]] = ("omega_rad_s", "timing")
    time_needs: ClassVar[tuple[str, ...]] = ("timing",)
    image_level: ClassVar[bool] = False  # the image simulator renders the streak exactly; the bias is the centroider's
    parameters: ClassVar[tuple[EffectParameter, ...]] = (
        EffectParameter("fraction", "1", 0.0, 0.05, (-0.5, 0.5),
                        "centroid offset along the streak as a fraction of the streak length (positive: ahead)"),
    )
    explanation: ClassVar[str] = (
        "While the tracker turns, every star is drawn out into a short streak during the exposure. A "
        "centroid refers to the middle of the exposure only when the streak is weighted uniformly; "
        "thresholding of the faint ends, saturation, or a detector whose sensitivity varies over the "
        "exposure move it towards one end. The result is a shift of each star along its own direction "
        "of motion, proportional to the streak length (image speed x exposure time): zero when "
        "inertially held, larger for longer exposures and faster rotation."
    )
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("time_offset", "both displace stars by image velocity times a time",
              "record at two exposure times: the smear bias scales with the exposure time, a clock offset does not"),
        Alias("attitude", "for a uniform image velocity the shift is a rigid rotation",
              "compare against a gyro-propagated attitude at two exposure times"),
    )

    def shift_basis(self, ctx):
        return np.full((ctx.n, 1), ctx.timing.exposure_ns / NS_PER_S)
