"""The scenario: the sensor, its timing, the sky, the motion, the gyro and the effects to simulate.

A strict pydantic model loaded from YAML. Every key carries its unit in its name (``_mm``, ``_us``,
``_deg_s``...). It sits with the sensors so that every layer that makes or reads a recording (the
simulator, the importers, the pipelines) shares one description of the sensor.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from pydantic import (
    Field,
    NonNegativeFloat,
    PositiveFloat,
    PositiveInt,
    ValidationInfo,
    field_validator,
    model_validator,
)

from rollingstar.config import Strict, parse_yaml, read_yaml, register_kind, validate
from rollingstar.sensors.camera import Projection
from rollingstar.sensors.effects import UnknownEffectError, resolve

Vec3 = tuple[float, float, float]

#: Bounds that keep every time in int64 nanoseconds and every array a scenario asks for allocatable;
#: the memory a scenario needs is checked against this machine's in ``ScenarioConfig``.
MAX_TIME_MS = 3.6e6  # one hour per exposure or frame
MAX_FRAMES = 10**8
MAX_SIDE_PX = 65536


class SensorConfig(Strict):
    """Optics (a pinhole unless ``projection`` says otherwise) and detector geometry."""

    focal_length_mm: PositiveFloat
    pixel_size_um: PositiveFloat
    width_px: PositiveInt = Field(le=MAX_SIDE_PX)
    height_px: PositiveInt = Field(le=MAX_SIDE_PX)
    principal_point_px: tuple[float, float] | None = Field(
        None, description="(cx, cy); default the detector centre ((W-1)/2, (H-1)/2)"
    )
    projection: Projection = Field(
        "perspective", description="how the lens maps the angle theta from the boresight to the image radius r: "
        "perspective (pinhole, r = f tan theta), equidistant (r = f theta), equisolid (r = 2 f sin(theta/2)), "
        "stereographic (r = 2 f tan(theta/2)) or orthographic (r = f sin theta)")


class ShutterConfig(Strict):
    """Exposure timing; frame period defaults to exposure + rows * line delay (he2021a eq 5)."""

    mode: Literal["rolling", "global"] = "rolling"
    exposure_ms: PositiveFloat = Field(le=MAX_TIME_MS)
    line_delay_us: NonNegativeFloat = Field(0.0, le=1e6)
    frame_period_ms: PositiveFloat | None = Field(None, le=MAX_TIME_MS)


class CatalogConfig(Strict):
    """Star catalogue: real Hipparcos-2 stars, or synthetic stars placed at given pixels at t = 0."""

    source: Literal["hipparcos", "synthetic"] = "hipparcos"
    magnitude_limit: float = 6.0
    epoch_year: float = 2025.0
    positions_px: list[tuple[float, float]] | None = Field(
        None, description="synthetic: stars placed so that they image at these (x, y) at t = 0"
    )
    magnitude: float = 5.0
    proper_motion_mas_yr: list[tuple[float, float]] | None = Field(
        None, description="synthetic: (pm_ra*cos(dec), pm_dec) in mas/yr per position (default none)")
    min_separation_px: float = Field(
        8.0, ge=0.0, description="hipparcos: drop both stars of pairs imaged closer than this many pixels (they blend)"
    )


class AttitudeConfig(Strict):
    """Boresight right ascension and declination, and roll about the boresight."""

    ra_deg: float = Field(ge=-360, le=360)
    dec_deg: float = Field(ge=-90, le=90)
    roll_deg: float = 0.0


class SegmentConfig(Strict):
    duration_s: PositiveFloat
    rate_deg_s: Vec3 = (0.0, 0.0, 0.0)
    accel_deg_s2: Vec3 = (0.0, 0.0, 0.0)


class JitterConfig(Strict):
    amplitude_arcsec: Vec3
    frequency_hz: PositiveFloat
    phase_deg: Vec3 = (0.0, 0.0, 0.0)


class MotionConfig(Strict):
    """Attitude truth: constant rate (and acceleration) or piecewise segments, plus jitter.

    Rates are camera-frame angular velocities. With ``segments`` empty the motion is one
    segment with ``rate_deg_s`` and ``accel_deg_s2``.
    """

    initial_attitude: AttitudeConfig | None = Field(
        None, description="required to simulate; None in imported recordings whose attitude is unknown (no prior)")
    rate_deg_s: Vec3 = (0.0, 0.0, 0.0)
    accel_deg_s2: Vec3 = (0.0, 0.0, 0.0)
    segments: list[SegmentConfig] = []
    jitter: list[JitterConfig] = []


class GyroConfig(Strict):
    enabled: bool = False
    rate_hz: PositiveFloat = 200.0
    bias_deg_h: Vec3 = (0.0, 0.0, 0.0)
    arw_deg_sqrt_h: NonNegativeFloat = 0.0
    rrw_deg_h_sqrt_h: NonNegativeFloat = 0.0
    scale_ppm: Vec3 = (0.0, 0.0, 0.0)


class NoiseConfig(Strict):
    centroid_sigma_px: NonNegativeFloat = Field(
        0.05, description="1-sigma centroid noise per axis (px); 0 simulates noise-free centroids")


class ImageConfig(Strict):
    """Image-level rendering and detector noise (see rollingstar.sensors.image_sim.ImageModel, whose
    defaults are these)."""

    psf_sigma_px: PositiveFloat = 1.0
    photons_per_s_mag0: PositiveFloat = 2.0e7
    background_e_per_px_s: NonNegativeFloat = 50.0
    dark_e_per_px_s: NonNegativeFloat = 5.0
    read_noise_e: NonNegativeFloat = 5.0
    gain_e_per_adu: PositiveFloat = 1.0
    bias_adu: NonNegativeFloat = 100.0
    bit_depth: int = Field(12, ge=8, le=16)
    full_well_e: PositiveFloat = 20000.0
    hot_pixel_fraction: float = Field(0.0, ge=0.0, le=0.01)
    hot_pixel_e_per_s: NonNegativeFloat = 5000.0


class EffectConfig(Strict):
    """One effect of the library (``rollingstar.sensors.effects``): ``kind`` is its name (or a synonym), ``params``
    its parameter values by name (defaults: effect absent). Checked against the library on load."""

    kind: str
    params: dict[str, float] = {}

    @field_validator("kind")
    @classmethod
    def _known_kind(cls, v: str) -> str:
        try:
            resolve(v)
        except UnknownEffectError as exc:
            raise ValueError(str(exc)) from None
        return v

    @field_validator("params")
    @classmethod
    def _known_params(cls, v: dict, info: ValidationInfo) -> dict:
        kind = info.data.get("kind")
        if kind is None:  # the kind itself was invalid: reported there
            return v
        effect = resolve(kind)
        unknown = sorted(set(v) - set(effect.parameter_names()))
        if unknown:
            raise ValueError(f"unknown parameter(s) {', '.join(map(repr, unknown))} of effect {effect.name!r}; "
                             f"valid parameters: {', '.join(effect.parameter_names())}")
        try:
            effect(**v)
        except ValueError as exc:
            raise ValueError(str(exc)) from None
        return v


class CovariateConfig(Strict):
    """A logged covariate as a function of time since the recording start ``t`` (s):
    ``offset + slope_per_h * t / 3600 + amplitude * sin(2 pi t / period_s)``."""

    offset: float = 0.0
    slope_per_h: float = 0.0
    amplitude: float = 0.0
    period_s: PositiveFloat = 3600.0


class EnvironmentConfig(Strict):
    """Where and in what conditions the recording is made (context of the effects)."""

    elevation_deg: float | None = Field(
        None, ge=0.0, le=90.0,
        description="ground-based: boresight elevation at the initial attitude, zenith towards camera -y (increasing row); "
                    "None in space (refraction needs it)")
    covariates: dict[str, CovariateConfig] = Field(
        {}, description="covariates by name (e.g. temperature_c for thermal_focal_drift)")


class ScenarioConfig(Strict):
    """A simulated star tracker: sensor, shutter, catalogue, motion, gyro, noise, effects."""

    name: str = "scenario"
    description: str = ""
    level: Literal["centroid", "image"] = "centroid"
    sensor: SensorConfig
    shutter: ShutterConfig
    catalog: CatalogConfig = CatalogConfig()
    motion: MotionConfig = MotionConfig()
    gyro: GyroConfig = GyroConfig()
    noise: NoiseConfig = NoiseConfig()
    image: ImageConfig = ImageConfig()
    effects: list[EffectConfig] = []
    environment: EnvironmentConfig = EnvironmentConfig()
    frames: PositiveInt = Field(100, le=MAX_FRAMES)
    seed: int = Field(0, ge=0, lt=2**63)
    truth_rate_hz: PositiveFloat = Field(1000.0, description="truth attitude samples per second in the log")


    @model_validator(mode="after")
    def _fits_in_memory(self):
        """The largest arrays the simulator allocates at once must fit in this machine's memory."""
        memory = _physical_memory_bytes()
        sensor, period_s = self.sensor, self._frame_period_s()
        if self.frames * period_s > 9e9:
            raise ValueError(f"frames {self.frames} x frame period {period_s:g} s = {self.frames * period_s:.3g} s: "
                             "longer than the nanosecond clock holds (about 290 years)")
        needs = {"an image frame (level: image; sensor.width_px x sensor.height_px, ~32 bytes a pixel while "
                 "rendering)": 32 * sensor.width_px * sensor.height_px if self.level == "image" else 0,
                 "a frame's truth samples (truth_rate_hz x frame period)": 64 * period_s * self.truth_rate_hz,
                 "the gyro samples (gyro.rate_hz x frames x frame period)":
                     32 * self.frames * period_s * self.gyro.rate_hz if self.gyro.enabled else 0}
        for what, size in needs.items():
            if size > memory / 2:
                raise ValueError(f"{what} needs {size / 2**30:.3g} GiB, more than half this machine's "
                                 f"{memory / 2**30:.3g} GiB of memory")
        return self

    def _frame_period_s(self) -> float:
        sh = self.shutter
        if sh.frame_period_ms is not None:
            return sh.frame_period_ms * 1e-3
        return sh.exposure_ms * 1e-3 + self.sensor.height_px * sh.line_delay_us * 1e-6

    @model_validator(mode="after")
    def _timing_is_physical(self):
        """Every row's exposure and the readout of all rows fit in one frame period."""
        sh, rows = self.shutter, self.sensor.height_px
        readout_ms = (rows - 1) * sh.line_delay_us * 1e-3 if sh.mode == "rolling" else 0.0
        if sh.frame_period_ms is not None:
            if sh.exposure_ms > sh.frame_period_ms:
                raise ValueError(f"shutter.exposure_ms {sh.exposure_ms:g} exceeds shutter.frame_period_ms "
                                 f"{sh.frame_period_ms:g}: a row cannot expose longer than one frame period")
            if readout_ms > sh.frame_period_ms:
                raise ValueError(f"shutter.line_delay_us {sh.line_delay_us:g} x (sensor.height_px {rows} - 1) = "
                                 f"{readout_ms:g} ms of readout exceeds shutter.frame_period_ms {sh.frame_period_ms:g}")
        return self

    @model_validator(mode="after")
    def _effects_have_context(self):
        for i, e in enumerate(self.effects):
            cls = resolve(e.kind)
            if self.level == "image" and not cls.image_level:
                raise ValueError(f"effects[{i}].kind: {cls.name!r} is a centroid-estimation bias: simulate it at "
                                 "level: centroid (an image-level recording produces it through the centroider)")
            if cls.name == "refraction" and self.environment.elevation_deg is None:
                raise ValueError(f"effects[{i}].kind: 'refraction' needs environment.elevation_deg (a ground-based "
                                 "scenario)")
            if cls.name == "thermal_focal_drift" and e.params.get("ppm_per_degc", 0.0) != 0.0 \
                    and "temperature_c" not in self.environment.covariates:
                raise ValueError(f"effects[{i}].params.ppm_per_degc: needs environment.covariates.temperature_c")
            if cls.name == "catalog_epoch" and self.catalog.source == "synthetic" and not self.catalog.proper_motion_mas_yr:
                raise ValueError(f"effects[{i}].kind: 'catalog_epoch' needs proper motions: use catalog.source: "
                                 "hipparcos or give catalog.proper_motion_mas_yr")
        return self


register_kind("scenario", ScenarioConfig)


def load_scenario(path: str | Path) -> ScenarioConfig:
    return validate(ScenarioConfig, read_yaml(path), str(path))



def scenario_from_yaml(text: str, source: str = "<recording metadata>") -> ScenarioConfig:
    return validate(ScenarioConfig, parse_yaml(text, source), source)


def _physical_memory_bytes() -> float:
    try:
        return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):  # not reported: assume a small machine
        return float(4 << 30)
