"""Camera clock offset: frames are stamped a constant time away from when they were exposed."""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from rollingstar.sensors.effects.base import Alias, EffectParameter
from rollingstar.sensors.effects.timeshift import TimeShiftEffect


class TimeOffset(TimeShiftEffect):
    """Every observation is seen ``dt = offset`` later than its timestamp says (camera clock minus
    the gyro/truth clock): ``(x', y') = (x, y) + (vx, vy) dt`` to first order."""

    name: ClassVar[str] = "time_offset"
    follows: ClassVar[str] = "image velocity x a constant time (a shift along the motion)"
    shown_by: ClassVar[str] = "two exposure times, or a gyro through a rate reversal"
    synonyms: ClassVar[tuple[str, ...]] = ("clock_offset", "timestamp_offset")
    channels: ClassVar[frozenset[str]] = frozenset({"image", "time", "attitude"})
    needs: ClassVar[tuple[str, ...]] = ("omega_rad_s",)
    parameters: ClassVar[tuple[EffectParameter, ...]] = (
        EffectParameter("offset_ms", "ms", 0.0, 5.0, (-1000.0, 1000.0),
                        "true exposure time minus the frame's timestamp"),
    )
    explanation: ClassVar[str] = (
        "The camera's clock and the clock of the gyro (or of the reference attitude) disagree by a "
        "constant offset, e.g. from a trigger latency or an unsynchronised time base. Each frame then "
        "shows the sky as it was a little earlier or later than its timestamp: the whole star field is "
        "displaced by image velocity x offset. Within one frame this is indistinguishable from an "
        "attitude error, so it shows up as an attitude error proportional to the body rate, visible "
        "only against the gyro or a truth reference, and absent when the tracker is inertially held."
    )
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("attitude", "at any rate the displacement is a rigid rotation omega * offset, absorbed by the per-frame attitude",
              "compare the star-tracker attitude with the gyro-propagated attitude through a rate reversal: the "
              "attitude error follows omega * offset and flips sign with the rate"),
        Alias("exposure_smear", "a centroid bias along the streak is also image velocity times a time",
              "record at two exposure times: the smear bias scales with the exposure time, the clock offset does not"),
    )

    def shift_basis(self, ctx):
        return np.full((ctx.n, 1), 1e-3)
