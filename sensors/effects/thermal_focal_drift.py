"""Thermal focal drift: the focal length follows a logged temperature (or time)."""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from rollingstar.sensors.conventions import NS_PER_S, S_PER_HOUR
from rollingstar.sensors.effects.base import (
    STAGE_OPTICS,
    Alias,
    Effect,
    EffectParameter,
    as_positions,
)

PPM = 1e-6
COVARIATE = "temperature_c"
REFERENCE_C = 20.0  # temperature at which the nominal focal length is defined


class ThermalFocalDrift(Effect):
    """Focal length ``f (1 + s)`` with ``s = 1e-6 [a (t - t_start) / 1 h + b (T - 20 C)]`` where ``T``
    is the logged covariate ``temperature_c`` and ``t_start`` the recording start. As for
    :class:`~rollingstar.sensors.effects.focal_length.FocalLength`, ``x' = cx + (x - cx)(1 + s)``, so
    ``d x'/da = (x - cx) 1e-6 (t - t_start)/h`` and ``d x'/db = (x - cx) 1e-6 (T - 20)``. Without
    the covariate in the context the ``b`` column of the Jacobian is zero (nothing to detect it by).
    """

    name: ClassVar[str] = "thermal_focal_drift"
    follows: ClassVar[str] = "temperature (or time) x r"
    shown_by: ClassVar[str] = "a temperature swing (or a long recording)"
    synonyms: ClassVar[tuple[str, ...]] = ("focal_drift", "thermal_drift")
    stage: ClassVar[int] = STAGE_OPTICS
    parameters: ClassVar[tuple[EffectParameter, ...]] = (
        EffectParameter("ppm_per_hour", "ppm/h", 0.0, 50.0, (-1e5, 1e5), "focal-length drift per hour since the recording start"),
        EffectParameter("ppm_per_degc", "ppm/degC", 0.0, 20.0, (-1e4, 1e4),
                        f"focal-length change per degree of the logged covariate {COVARIATE!r} (reference {REFERENCE_C} C)"),
    )
    explanation: ClassVar[str] = (
        "Lens and spacer materials expand with temperature, so the focal length -- and with it the "
        "plate scale -- follows the camera's temperature, typically by ten to a few tens of ppm per "
        "degree. In a recording this is a focal-length error that is not constant: the star field "
        "slowly breathes in and out, with residuals pointing radially from the principal point whose "
        "size tracks the logged temperature (or, without a temperature log, elapsed time)."
    )
    aliases: ClassVar[tuple[Alias, ...]] = (
        Alias("focal_length", "the temperature or time offset from the reference gives a constant focal error",
              "record through a temperature swing (or over a long time): only the drift follows it"),
    )

    @property
    def needs(self) -> tuple[str, ...]:  # the covariate is needed only when its coefficient is used
        return (f"covariate:{COVARIATE}",) if self._values["ppm_per_degc"] != 0.0 else ()

    def _basis(self, ctx):
        hours = (ctx.t_ns - np.int64(ctx.t_start_ns)).astype(float) / NS_PER_S / S_PER_HOUR
        temp = ctx.covariates.get(COVARIATE)
        dtemp = np.zeros(ctx.n) if temp is None else temp - REFERENCE_C
        return np.stack([hours, dtemp], axis=-1) * PPM  # (n, 2)

    def apply(self, x, y, ctx):
        x, y = as_positions(x, y)
        if self.is_identity:
            return x, y
        self._require(ctx)
        s = 1.0 + self._basis(ctx) @ self.vector
        cam = ctx.camera
        return cam.cx + (x - cam.cx) * s, cam.cy + (y - cam.cy) * s

    def jacobian(self, x, y, ctx):
        x, y = as_positions(x, y)
        d = np.stack([x - ctx.camera.cx, y - ctx.camera.cy], axis=-1)  # (n, 2)
        return d[:, :, None] * self._basis(ctx)[:, None, :]
