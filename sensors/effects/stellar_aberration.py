"""Stellar aberration: the observer's velocity tilts the apparent direction of every star."""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from rollingstar.sensors.effects.base import (
    STAGE_SKY,
    Alias,
    Effect,
    EffectParameter,
    as_positions,
)
from rollingstar.sensors.effects.geometry import displace_direction, to_camera

C_KM_S = 299_792.458


class StellarAberration(Effect):
    """Classical aberration for an observer moving with ICRS velocity ``v`` (km/s) not accounted
    for by the model: ``u' ~ u + v / c`` (first order in ``v/c``; the neglected terms are
    ``(v/c)^2 ~ 1e-8`` rad for Earth's orbital speed). In the camera frame ``w' = w + R^T v / c``
    (``R`` the camera->ICRS attitude) and, because the projection is homogeneous,
    ``d(x', y')/dv_j = P(w') R^T e_j / c`` exactly.
    """

    name: ClassVar[str] = "stellar_aberration"
    follows: ClassVar[str] = "the angle to the observer's velocity (compression towards the apex)"
    shown_by: ClassVar[str] = "pointings at different angles from the velocity vector"
    synonyms: ClassVar[tuple[str, ...]] = ("aberration", "velocity_aberration")
    stage: ClassVar[int] = STAGE_SKY
    needs: ClassVar[tuple[str, ...]] = ("attitude",)
    parameters: ClassVar[tuple[EffectParameter, ...]] = tuple(
        EffectParameter(f"v{a}_km_s", "km/s", 0.0, 30.0, (-300.0, 300.0),
                        f"observer velocity (ICRS {a}) not applied by the model") for a in "xyz"
    )
    explanation: ClassVar[str] = (
        "Light from a star arrives from a direction tilted towards the observer's direction of "
        "motion by about v/c radians: 20 arcsec for Earth's orbital speed around the Sun, 5 arcsec "
        "for a low-Earth orbit. If the model forgets it, the whole star field is displaced almost "
        "rigidly, which looks like an attitude error, plus a tiny field-dependent compression "
        "towards the apex of motion. The attitude part changes slowly and predictably with the "
        "orbit and the season."
    )
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("attitude", "over a field of view of a few degrees the displacement is a near-rigid rotation",
              "compare with an external attitude reference while the velocity changes (along an orbit, or "
              "over months), or use a very wide field where the differential compression is measurable"),
        Alias("focal_length", "the differential part is a slight scale change of the field towards the apex",
              "point at different angles from the velocity vector: the aberration scale changes, a focal error does not"),
    )

    def _beta_cam(self, ctx):
        self._require(ctx)
        n = ctx.n
        att = ctx.attitude
        basis = np.stack([to_camera(att, np.broadcast_to(e, (n, 3))) for e in np.eye(3)], axis=-1)  # (n, 3, 3)
        return basis / C_KM_S  # camera-frame dw per km/s of each ICRS velocity component

    def apply(self, x, y, ctx):
        x, y = as_positions(x, y)
        if self.is_identity:
            return x, y
        self._require(ctx)
        dw = to_camera(ctx.attitude, np.broadcast_to(self.vector / C_KM_S, (ctx.n, 3)))
        x2, y2, _ = displace_direction(ctx.camera, x, y, dw, jacobian=False)
        return x2, y2

    def jacobian(self, x, y, ctx):
        x, y = as_positions(x, y)
        b = self._beta_cam(ctx)
        _, _, p = displace_direction(ctx.camera, x, y, b @ self.vector)
        return p @ b
