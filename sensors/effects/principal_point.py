"""Principal-point offset: the optical axis meets the detector away from its nominal pixel."""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from rollingstar.sensors.effects.base import (
    STAGE_OPTICS,
    Alias,
    Effect,
    EffectParameter,
    as_positions,
)


class PrincipalPointOffset(Effect):
    """The true principal point is ``(cx + dx, cy + dy)`` instead of the nominal ``(cx, cy)``.

    The pinhole projection ``x = cx - f w_x / w_z`` is linear in ``cx``, so every true position
    shifts rigidly: ``x' = x + dx``, ``y' = y + dy``; the Jacobian is the identity for every star.
    """

    name: ClassVar[str] = "principal_point"
    follows: ClassVar[str] = "nothing on the detector: a uniform shift of the field (plus a small scale term)"
    shown_by: ClassVar[str] = "an external attitude reference, or a wide field"
    synonyms: ClassVar[tuple[str, ...]] = ("principal_point_offset", "boresight_offset")
    stage: ClassVar[int] = STAGE_OPTICS
    channels: ClassVar[frozenset[str]] = frozenset({"image", "attitude"})
    parameters: ClassVar[tuple[EffectParameter, ...]] = (
        EffectParameter("dx", "px", 0.0, 5.0, (-500.0, 500.0), "column offset of the true principal point"),
        EffectParameter("dy", "px", 0.0, 5.0, (-500.0, 500.0), "row offset of the true principal point"),
    )
    explanation: ClassVar[str] = (
        "The optical axis crosses the detector a few pixels away from the pixel assumed in the "
        "camera model (mounting and lens-centring tolerances). Every star is then displaced by the "
        "same (dx, dy) in every frame. A single tracker cannot tell this from a small constant "
        "attitude offset about the cross-boresight axes (dx of one pixel looks like a rotation of "
        "one IFOV), so it appears as a fixed bias against an external attitude reference, and as "
        "a slight field-dependent scale error when the attitude absorbs it."
    )
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("attitude", "a uniform shift of the field is, to first order, a cross-boresight rotation",
              "compare with an external attitude reference (e.g. a second tracker or a gyro-propagated attitude "
              "through a known rotation), or use a wide field where the residual scale error is measurable"),
        Alias("tangential_distortion", "the mean of a decentring distortion over the field is a shift",
              "use stars over the whole detector: decentring grows as r^2"),
    )

    def apply(self, x, y, ctx):
        x, y = as_positions(x, y)
        return x + self._values["dx"], y + self._values["dy"]

    def jacobian(self, x, y, ctx):
        x, _ = as_positions(x, y)
        return np.broadcast_to(np.eye(2), (x.size, 2, 2)).copy()
