"""Pixel-phase (S-curve) centroid bias: the error depends on where in the pixel the star falls."""
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

TWO_PI = 2.0 * np.pi


class PixelPhaseBias(Effect):
    """First harmonic of the S-curve: ``x' = x + a_x sin(2 pi x)``, ``y' = y + a_y sin(2 pi y)``
    (pixel centres at integers, so the bias is zero at pixel centres and edges and extreme at
    quarter pixels; ``a < 0`` pulls centroids towards pixel centres, the usual sign for a PSF
    narrower than ~1 px). Linear in ``a``: ``d x'/d a_x = sin(2 pi x)``.
    """

    name: ClassVar[str] = "pixel_phase_bias"
    follows: ClassVar[str] = "the star's sub-pixel position"
    shown_by: ClassVar[str] = "a slow drift of the stars across several pixels"
    synonyms: ClassVar[tuple[str, ...]] = ("s_curve", "pixel_locking")
    stage: ClassVar[int] = STAGE_DETECTOR
    image_level: ClassVar[bool] = False  # a property of the centroid estimator: images produce it by themselves
    parameters: ClassVar[tuple[EffectParameter, ...]] = (
        EffectParameter("ax_px", "px", 0.0, 0.02, (-0.5, 0.5), "S-curve amplitude along columns"),
        EffectParameter("ay_px", "px", 0.0, 0.02, (-0.5, 0.5), "S-curve amplitude along rows"),
    )
    explanation: ClassVar[str] = (
        "A centre-of-mass centroid of a star image only a pixel or two wide is pulled towards the "
        "centre of the pixel it falls on (pixel locking), by an amount that depends on the star's "
        "sub-pixel position: zero at the pixel centre and edge, largest a quarter pixel away. The "
        "residuals therefore oscillate once per pixel as a function of the fractional pixel "
        "coordinate, independent of where in the field the star is and of the motion, and "
        "average out when stars drift across many pixel phases."
    )
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("magnitude_bias", "both are star-by-star biases uncorrelated with field position",
              "let the stars drift slowly across several pixels (a slow constant rate): the pixel-phase "
              "bias oscillates with the sub-pixel position, a brightness bias stays constant"),
    )

    def apply(self, x, y, ctx):
        x, y = as_positions(x, y)
        v = self._values
        return x + v["ax_px"] * np.sin(TWO_PI * x), y + v["ay_px"] * np.sin(TWO_PI * y)

    def jacobian(self, x, y, ctx):
        x, y = as_positions(x, y)
        jac = np.zeros((x.size, 2, 2))
        jac[:, 0, 0] = np.sin(TWO_PI * x)
        jac[:, 1, 1] = np.sin(TWO_PI * y)
        return jac
