"""Brightness-dependent centroid shift (magnitude bias)."""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from rollingstar.sensors.effects.base import (
    STAGE_DETECTOR,
    Alias,
    Effect,
    EffectParameter,
    as_positions,
)

REFERENCE_MAG = 6.0  # magnitude with zero shift


class MagnitudeBias(Effect):
    """Centroids shift linearly with the star's magnitude: ``x' = x + b_x (m - 6)``,
    ``y' = y + b_y (m - 6)``; ``d x'/d b_x = m - 6``.
    """

    name: ClassVar[str] = "magnitude_bias"
    follows: ClassVar[str] = "the star's magnitude"
    shown_by: ClassVar[str] = "frames with a wide spread of magnitudes in the same region"
    synonyms: ClassVar[tuple[str, ...]] = ("brightness_bias", "charge_transfer_bias")
    stage: ClassVar[int] = STAGE_DETECTOR
    needs: ClassVar[tuple[str, ...]] = ("magnitude",)
    parameters: ClassVar[tuple[EffectParameter, ...]] = (
        EffectParameter("bx_px_per_mag", "px/mag", 0.0, 0.01, (-1.0, 1.0), "column shift per magnitude (zero at 6 mag)"),
        EffectParameter("by_px_per_mag", "px/mag", 0.0, 0.01, (-1.0, 1.0), "row shift per magnitude (zero at 6 mag)"),
    )
    explanation: ClassVar[str] = (
        "Detector and electronics non-idealities -- charge-transfer inefficiency, pixel "
        "non-linearity near saturation, a readout that lags behind bright signals -- shift the "
        "centroid of a star by an amount that depends on how bright it is, usually along the readout "
        "direction. Residuals then correlate with magnitude (bright and faint stars disagree in a "
        "fixed direction) but not with field position or motion."
    )
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("attitude", "the shift at the mean magnitude of a frame is a rigid shift of the field",
              "use frames with a wide spread of magnitudes in the same region of the field"),
        Alias("pixel_phase_bias", "both are star-by-star biases independent of field position",
              "let stars drift across pixel phases: only the pixel-phase bias oscillates with it"),
    )

    def _dm(self, ctx):
        self._require(ctx)
        return ctx.magnitude - REFERENCE_MAG

    def apply(self, x, y, ctx):
        x, y = as_positions(x, y)
        if self.is_identity:
            return x, y
        dm = self._dm(ctx)
        return x + self._values["bx_px_per_mag"] * dm, y + self._values["by_px_per_mag"] * dm

    def jacobian(self, x, y, ctx):
        x, _ = as_positions(x, y)
        dm = self._dm(ctx)
        jac = np.zeros((x.size, 2, 2))
        jac[:, 0, 0] = dm
        jac[:, 1, 1] = dm
        return jac
