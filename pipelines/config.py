"""Configs as strict pydantic models loaded from YAML: a *scenario* and a *pipeline*.

Every key carries its unit in its name (``_mm``, ``_us``, ``_deg_s``...). Unknown keys are
rejected; errors name the file, the key path (``motion.rate_deg_s[0]``) and what was expected.
Pipeline stages are ``{kind: <plugin name>, params: {...}}``; ``kind`` is an open string checked
against the plugin registry (built-ins and entry points alike), never a closed union.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    NonNegativeFloat,
    PositiveFloat,
    PositiveInt,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from pipelines.errors import ConfigError

Vec3 = tuple[float, float, float]


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)


class SensorConfig(Strict):
    """Pinhole optics and detector geometry."""

    focal_length_mm: PositiveFloat
    pixel_size_um: PositiveFloat
    width_px: PositiveInt
    height_px: PositiveInt
    principal_point_px: tuple[float, float] | None = Field(
        None, description="(cx, cy); default the detector centre ((W-1)/2, (H-1)/2)"
    )


class ShutterConfig(Strict):
    """Exposure timing; frame period defaults to exposure + rows * line delay (he2021a eq 5)."""

    mode: Literal["rolling", "global"] = "rolling"
    exposure_ms: PositiveFloat
    line_delay_us: NonNegativeFloat = 0.0
    frame_period_ms: PositiveFloat | None = None


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
    centroid_sigma_px: NonNegativeFloat = 0.05


class ImageConfig(Strict):
    """Image-level rendering and detector noise (see sensors.simulate.ImageModel)."""

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
    """One effect of the library (``sensors.effects``): ``kind`` is its name (or a synonym), ``params``
    its parameter values by name (defaults: effect absent). Checked against the library on load."""

    kind: str
    params: dict[str, float] = {}

    @field_validator("kind")
    @classmethod
    def _known_kind(cls, v: str) -> str:
        from sensors.effects import UnknownEffectError, resolve

        try:
            resolve(v)
        except UnknownEffectError as exc:
            raise ValueError(str(exc)) from None
        return v

    @field_validator("params")
    @classmethod
    def _known_params(cls, v: dict, info: ValidationInfo) -> dict:
        from sensors.effects import resolve

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
        description="ground-based: boresight elevation at the initial attitude, zenith towards image up (-y); "
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
    motion: MotionConfig
    gyro: GyroConfig = GyroConfig()
    noise: NoiseConfig = NoiseConfig()
    image: ImageConfig = ImageConfig()
    effects: list[EffectConfig] = []
    environment: EnvironmentConfig = EnvironmentConfig()
    frames: PositiveInt = 100
    seed: int = 0
    truth_rate_hz: PositiveFloat = Field(1000.0, description="truth attitude samples per second in the log")


    @model_validator(mode="after")
    def _effects_have_context(self):
        from sensors.effects import resolve

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


class StageConfig(Strict):
    kind: str
    params: dict[str, Any] = {}


class PipelineConfig(Strict):
    """An ordered list of stages; each is checked against the plugin registry when built."""

    name: str = "pipeline"
    description: str = ""
    stages: list[StageConfig] = Field(min_length=1)


def _key_path(loc: tuple) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "<top level>"


def _known_keys(model, loc: tuple) -> list[str]:
    """The keys valid where ``loc`` (minus its last part) points inside ``model`` (best effort)."""
    import typing

    for part in loc[:-1]:
        if isinstance(part, int) or model is None:
            continue
        field = getattr(model, "model_fields", {}).get(part)
        if field is None:
            return []
        ann, model = field.annotation, None
        for cand in (ann, *typing.get_args(ann), *(a for t in typing.get_args(ann) for a in typing.get_args(t))):
            if isinstance(cand, type) and issubclass(cand, BaseModel):
                model = cand
                break
    return list(getattr(model, "model_fields", {}))


def format_validation_error(source: str, err: ValidationError, prefix: tuple = (), model=None) -> str:
    """One line per problem: ``file: key.path: message (got <input>)``; ``prefix`` is prepended to each key path.

    An unknown key gets the closest valid key as a hint (``exposure_s`` -> ``exposure_ms``: units are in
    the key names) when ``model`` is given."""
    import difflib

    lines = []
    for e in err.errors():
        path = _key_path(tuple(prefix) + tuple(e["loc"]))
        got = e.get("input")
        hint = "" if e["type"] == "missing" else f" (got {got!r})"
        msg = "unknown key" if e["type"] == "extra_forbidden" else e["msg"]
        if e["type"] == "extra_forbidden" and model is not None:
            close = difflib.get_close_matches(str(e["loc"][-1]), _known_keys(model, tuple(e["loc"])), n=1, cutoff=0.6)
            if close:
                key = str(e["loc"][-1])
                same_stem = "_" in key and close[0].rsplit("_", 1)[0] == key.rsplit("_", 1)[0]
                msg += f"; did you mean {close[0]!r}?" + (" (units are part of the key names)" if same_stem else "")
        lines.append(f"{source}: {path}: {msg}{hint}")
    return "\n".join(lines)


def read_yaml(path: str | Path) -> dict:
    """Parse a YAML mapping; syntax errors name the file and line."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config file: {exc.strerror}") from None
    return parse_yaml(text, str(path))


def parse_yaml(text: str, source: str) -> dict:
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"{source}:{where}: YAML syntax error: {problem}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a YAML mapping at the top level, got {type(data).__name__}")
    return data


def validate(model: type[Strict], data: dict, source: str):
    try:
        return model.model_validate(data)
    except ValidationError as err:
        raise ConfigError(format_validation_error(source, err, model=model)) from None


def load_scenario(path: str | Path) -> ScenarioConfig:
    return validate(ScenarioConfig, read_yaml(path), str(path))


def load_pipeline(path: str | Path) -> PipelineConfig:
    return validate(PipelineConfig, read_yaml(path), str(path))


def scenario_from_yaml(text: str, source: str = "<recording metadata>") -> ScenarioConfig:
    return validate(ScenarioConfig, parse_yaml(text, source), source)


def to_yaml(config: Strict) -> str:
    """The config as YAML (what goes into a log's metadata)."""
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)
