"""Catalogue epoch: proper motion not applied, or applied to the wrong epoch."""
from __future__ import annotations

from typing import ClassVar

from rollingstar.sensors.effects.base import (
    STAGE_SKY,
    Alias,
    Effect,
    EffectParameter,
    as_positions,
)
from rollingstar.sensors.effects.geometry import displace_direction, to_camera


class CatalogEpoch(Effect):
    """The sky is ``d`` years ahead of the epoch the catalogue directions were propagated to.
    With ``mu`` the star's proper motion as an ICRS tangent vector (rad/yr), the true direction is
    ``u + d mu`` (the first-order propagation of :func:`rollingstar.sensors.catalog.propagate_proper_motion`), so
    ``w' = w + d R^T mu`` and ``d(x', y')/dd = P(w') R^T mu`` exactly (projection is homogeneous).
    """

    name: ClassVar[str] = "catalog_epoch"
    follows: ClassVar[str] = "each star's catalogue proper motion"
    shown_by: ClassVar[str] = "stars of large and small proper motion at equal magnitude"
    synonyms: ClassVar[tuple[str, ...]] = ("proper_motion", "epoch_error")
    stage: ClassVar[int] = STAGE_SKY
    needs: ClassVar[tuple[str, ...]] = ("attitude", "pm_rad_yr")
    parameters: ClassVar[tuple[EffectParameter, ...]] = (
        EffectParameter("epoch_error_yr", "yr", 0.0, 10.0, (-200.0, 200.0),
                        "observation epoch minus the epoch the catalogue was propagated to"),
    )
    explanation: ClassVar[str] = (
        "Stars move across the sky by their proper motion, up to several arcseconds per year for "
        "nearby stars and typically tens of milliarcseconds. A catalogue used at its own epoch "
        "(Hipparcos: 1991.25) instead of the observation date puts every star where it was decades "
        "ago. The error is different for every star -- its own proper motion times the epoch error -- "
        "so it does not look like a field distortion or an attitude error: the fast-moving stars have "
        "large, consistent residuals in every frame while most stars are unaffected."
    )
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("magnitude_bias", "both are star-specific constant offsets, and nearby (high proper motion) stars are "
              "often bright", "compare residuals of stars matched in magnitude but with different catalogue "
              "proper motions: only the epoch error follows the proper-motion vector"),
    )

    def _dw(self, ctx):
        self._require(ctx)
        return to_camera(ctx.attitude, ctx.pm_rad_yr)  # (n, 3) per year

    def apply(self, x, y, ctx):
        x, y = as_positions(x, y)
        if self.is_identity:
            return x, y
        x2, y2, _ = displace_direction(ctx.camera, x, y, self._dw(ctx) * self._values["epoch_error_yr"], jacobian=False)
        return x2, y2

    def jacobian(self, x, y, ctx):
        x, y = as_positions(x, y)
        a = self._dw(ctx)
        _, _, p = displace_direction(ctx.camera, x, y, a * self._values["epoch_error_yr"])
        return p @ a[:, :, None]
