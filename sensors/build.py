"""Turn a validated :class:`~rollingstar.pipelines.config.ScenarioConfig` into the sensor objects.

This is the only place that converts config units (mm, us, deg/s, deg/h) into the SI units and
integer nanoseconds the ``sensors`` package works in.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from rollingstar.errors import ConfigError
from rollingstar.sensors.camera import PinholeCamera
from rollingstar.sensors.catalog import StarCatalog, proper_motion_vector
from rollingstar.sensors.conventions import (
    ARCSEC_TO_RAD,
    DEG_TO_RAD,
    S_PER_HOUR,
    S_PER_NS,
    attitude_from_radec_roll,
    seconds_to_ns,
    unit_to_radec,
)
from rollingstar.sensors.effects import UnknownEffectError, build_effect
from rollingstar.sensors.gyro import GyroModel
from rollingstar.sensors.motion import (
    AttitudeMotion,
    JitterMotion,
    PiecewiseMotion,
    Segment,
)
from rollingstar.sensors.scenario import ScenarioConfig
from rollingstar.sensors.timing import DetectorTiming


def build_camera(cfg: ScenarioConfig) -> PinholeCamera:
    s = cfg.sensor
    cx, cy = s.principal_point_px if s.principal_point_px is not None else (None, None)
    return PinholeCamera(s.focal_length_mm * 1e-3, s.pixel_size_um * 1e-6, s.width_px, s.height_px, cx, cy,
                         projection=s.projection)


def build_timing(cfg: ScenarioConfig) -> DetectorTiming:
    sh = cfg.shutter
    period = None if sh.frame_period_ms is None else seconds_to_ns(sh.frame_period_ms * 1e-3)
    return DetectorTiming(
        mode=sh.mode,
        exposure_ns=seconds_to_ns(sh.exposure_ms * 1e-3),
        line_delay_ns=seconds_to_ns(sh.line_delay_us * 1e-6),
        rows=cfg.sensor.height_px,
        frame_period_ns=period,
    )


def initial_attitude(cfg: ScenarioConfig, required: bool = False) -> Rotation | None:
    """The scenario's initial attitude; None when it declares none (imported real recordings)."""
    a = cfg.motion.initial_attitude
    if a is None:
        if required:
            raise ConfigError("motion.initial_attitude: required to simulate (ra_deg, dec_deg, roll_deg)")
        return None
    return attitude_from_radec_roll(a.ra_deg, a.dec_deg, a.roll_deg)


def build_motion(cfg: ScenarioConfig) -> AttitudeMotion:
    m = cfg.motion
    if m.segments:
        segments = [
            Segment(seconds_to_ns(s.duration_s), np.asarray(s.rate_deg_s) * DEG_TO_RAD, np.asarray(s.accel_deg_s2) * DEG_TO_RAD)
            for s in m.segments
        ]
    else:
        long_ns = seconds_to_ns(1e6)  # the last segment's law continues past its end anyway
        segments = [Segment(long_ns, np.asarray(m.rate_deg_s) * DEG_TO_RAD, np.asarray(m.accel_deg_s2) * DEG_TO_RAD)]
    motion: AttitudeMotion = PiecewiseMotion(initial_attitude(cfg, required=True), segments)
    if m.jitter:
        motion = JitterMotion(
            motion,
            amplitude_rad=np.array([j.amplitude_arcsec for j in m.jitter]) * ARCSEC_TO_RAD,
            frequency_hz=np.array([j.frequency_hz for j in m.jitter]),
            phase_rad=np.array([j.phase_deg for j in m.jitter]) * DEG_TO_RAD,
        )
    return motion


def build_catalog(cfg: ScenarioConfig, camera: PinholeCamera | None = None) -> StarCatalog:
    """Hipparcos-2 at the scenario epoch, or synthetic stars that image at ``positions_px`` at t=0."""
    c = cfg.catalog
    if c.source == "hipparcos":
        camera = camera or build_camera(cfg)
        catalog = StarCatalog.from_hipparcos(epoch_year=c.epoch_year, magnitude_limit=c.magnitude_limit)
        return catalog.without_close_pairs(c.min_separation_px * camera.ifov_rad)
    if not c.positions_px:
        raise ConfigError("catalog.positions_px: a synthetic catalogue needs at least one (x, y) position")
    camera = camera or build_camera(cfg)
    xy = np.asarray(c.positions_px, dtype=float)
    w_cam = camera.unproject(xy[:, 0], xy[:, 1])
    unit_icrs = initial_attitude(cfg, required=True).apply(w_cam)
    pm = None
    if c.proper_motion_mas_yr:
        if len(c.proper_motion_mas_yr) != len(xy):
            raise ConfigError(f"catalog.proper_motion_mas_yr: expected one (pm_ra, pm_dec) per position "
                              f"({len(xy)}), got {len(c.proper_motion_mas_yr)}")
        ra, dec = unit_to_radec(unit_icrs)
        mu = np.asarray(c.proper_motion_mas_yr, dtype=float)
        pm = proper_motion_vector(ra, dec, mu[:, 0], mu[:, 1])
    return StarCatalog.synthetic(unit_icrs, magnitude=np.full(len(xy), c.magnitude), epoch_year=c.epoch_year,
                                 pm_rad_yr=pm)


def build_effects(cfg: ScenarioConfig) -> list:
    effects = []
    for i, e in enumerate(cfg.effects):
        try:
            effects.append(build_effect(e.kind, dict(e.params)))
        except UnknownEffectError as exc:
            raise ConfigError(f"effects[{i}].kind: {exc}") from None
        except ValueError as exc:
            raise ConfigError(f"effects[{i}].params: {exc}") from None
    return effects


def build_zenith(cfg: ScenarioConfig) -> np.ndarray | None:
    """ICRS zenith of a ground-based scenario (``environment.elevation_deg``), else None.

    At the initial attitude the boresight has elevation ``e`` and the zenith lies towards camera
    -y (increasing row, docs/conventions.md): ``zenith_cam = (0, -cos e, sin e)``. It is held
    fixed in ICRS (the sky's diurnal rotation, 15 arcsec/s, is neglected over a recording).
    """
    e = cfg.environment.elevation_deg
    att = initial_attitude(cfg)
    if e is None or att is None:
        return None
    e = e * DEG_TO_RAD
    return att.apply([0.0, -np.cos(e), np.sin(e)])


def build_covariates(cfg: ScenarioConfig) -> dict:
    """Covariates as functions of int64 ns times (``environment.covariates``, see CovariateConfig)."""
    out = {}
    for name, c in cfg.environment.covariates.items():
        def f(t_ns, c=c):
            t = np.asarray(t_ns, dtype=np.int64).astype(float) * S_PER_NS
            return c.offset + c.slope_per_h * t / S_PER_HOUR + c.amplitude * np.sin(2.0 * np.pi * t / c.period_s)
        out[name] = f
    return out


def build_gyro(cfg: ScenarioConfig) -> GyroModel | None:
    g = cfg.gyro
    if not g.enabled:
        return None
    return GyroModel(
        rate_hz=g.rate_hz,
        bias_rad_s=np.asarray(g.bias_deg_h) * DEG_TO_RAD / S_PER_HOUR,
        arw_rad_sqrt_s=g.arw_deg_sqrt_h * DEG_TO_RAD / np.sqrt(S_PER_HOUR),
        rrw_rad_s_sqrt_s=g.rrw_deg_h_sqrt_h * DEG_TO_RAD / S_PER_HOUR / np.sqrt(S_PER_HOUR),
        scale_factor=np.asarray(g.scale_ppm) * 1e-6,
    )
