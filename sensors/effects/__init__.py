"""The effect library: named physical effects shared by the simulator and the diagnosis.

``EFFECTS`` maps each effect's ``name`` to its class (one module per effect); :func:`build_effect`
also accepts the ``synonyms`` an effect declares. See :mod:`rollingstar.sensors.effects.base` for the
interface, :mod:`rollingstar.sensors.effects.chain` for chains (prediction, stacked Jacobians, gyro hook),
:mod:`rollingstar.sensors.effects.design` for detection limits and :mod:`rollingstar.sensors.effects.doc` for the
generated ``docs/effects.md``.
"""
from __future__ import annotations

from rollingstar.sensors.effects.angular_acceleration import AngularAcceleration
from rollingstar.sensors.effects.base import (
    CHANNELS,
    NUISANCE,
    STAGE_DETECTOR,
    STAGE_GYRO,
    STAGE_OPTICS,
    STAGE_SKY,
    STAGE_TIME,
    Alias,
    Effect,
    EffectContext,
    EffectParameter,
    MissingContextError,
)
from rollingstar.sensors.effects.boresight_rotation import BoresightRotation
from rollingstar.sensors.effects.catalog_epoch import CatalogEpoch
from rollingstar.sensors.effects.empirical import EmpiricalRipple, EmpiricalStep
from rollingstar.sensors.effects.exposure_smear import ExposureSmear
from rollingstar.sensors.effects.focal_length import FocalLength
from rollingstar.sensors.effects.gyro_bias import GyroBias
from rollingstar.sensors.effects.gyro_scale import GyroScale
from rollingstar.sensors.effects.magnitude_bias import MagnitudeBias
from rollingstar.sensors.effects.pixel_phase_bias import PixelPhaseBias
from rollingstar.sensors.effects.principal_point import PrincipalPointOffset
from rollingstar.sensors.effects.radial_distortion import RadialDistortion
from rollingstar.sensors.effects.refraction import Refraction
from rollingstar.sensors.effects.rolling_shutter import RollingShutter
from rollingstar.sensors.effects.stellar_aberration import StellarAberration
from rollingstar.sensors.effects.tangential_distortion import TangentialDistortion
from rollingstar.sensors.effects.thermal_focal_drift import ThermalFocalDrift
from rollingstar.sensors.effects.time_offset import TimeOffset

_CLASSES = (
    RollingShutter, ExposureSmear, RadialDistortion, TangentialDistortion, PrincipalPointOffset, FocalLength,
    BoresightRotation, StellarAberration, TimeOffset, GyroBias, GyroScale, ThermalFocalDrift, PixelPhaseBias,
    MagnitudeBias, AngularAcceleration, CatalogEpoch, Refraction, EmpiricalStep, EmpiricalRipple,
)
EFFECTS: dict[str, type[Effect]] = {cls.name: cls for cls in _CLASSES}


class UnknownEffectError(ValueError):
    """Raised for an effect name nobody registered; the message lists the valid names."""


def resolve(name: str) -> type[Effect]:
    """The effect class registered as ``name`` or declaring it as a synonym."""
    if name in EFFECTS:
        return EFFECTS[name]
    for cls in EFFECTS.values():
        if name in cls.synonyms:
            return cls
    raise UnknownEffectError(f"unknown effect {name!r}; valid effects: {', '.join(sorted(EFFECTS))}")


def build_effect(name: str, params: dict | None = None) -> Effect:
    """Instantiate the effect registered as ``name`` (or one of its synonyms) with ``params``."""
    return resolve(name)(**(params or {}))


__all__ = [
    "CHANNELS", "EFFECTS", "NUISANCE", "STAGE_DETECTOR", "STAGE_GYRO", "STAGE_OPTICS", "STAGE_SKY", "STAGE_TIME",
    "Alias", "AngularAcceleration", "BoresightRotation", "CatalogEpoch", "Effect", "EffectContext", "EffectParameter",
    "EmpiricalRipple", "EmpiricalStep",
    "ExposureSmear", "FocalLength", "GyroBias", "GyroScale", "MagnitudeBias", "MissingContextError", "PixelPhaseBias",
    "PrincipalPointOffset", "RadialDistortion", "Refraction", "RollingShutter", "StellarAberration",
    "TangentialDistortion", "ThermalFocalDrift", "TimeOffset", "UnknownEffectError", "build_effect", "resolve",
]
