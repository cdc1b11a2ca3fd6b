"""When an imported recording was made, and the reference catalogue it declares (docs/log-format.md).

The observation time is the UTC time of the first frame, taken from the first of:

1. the sidecar's ``observation_time`` (ISO 8601 with its zone);
2. the frame times, when their column says they are Unix time (``t_unix_ns`` or ``time_unix_s``);
   frame times in ``t_ns``/``time_s`` are on the recording's own clock and never read as dates
   (a clock may count from power-on, from 1980 like GPS, ...), even when they look like Unix time:
   a warning then says how to state it;
3. the first image's header: a FITS file's ``DATE-OBS``
   (:func:`rollingstar.logs.importers.fits_images.fits_observation`); another file's EXIF
   ``DateTimeOriginal``, else its TIFF/EXIF ``DateTime``, shifted by
   ``OffsetTimeOriginal``/``OffsetTime`` when the file states one; without one the camera's
   local zone is unknown and the time is read as UTC, with a warning;
4. none.

The catalogue (scenario ``catalog``) is Hipparcos-2 propagated to ``epoch_year``: the sidecar's
``catalog.epoch_year``, else the observation time's Julian year
(:func:`rollingstar.sensors.catalog.julian_year`, rounded to 1e-4 yr = 53 min: no Hipparcos
star moves more than 0.6 mas in half of that), else the scenario default with a warning. Its
``magnitude_limit`` is the sidecar's, else :func:`rollingstar.sensors.catalog.magnitude_limit_for_field`
for the camera's field. The choice and its reasons go into ``import.details.catalog``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
from PIL import Image

from rollingstar.logs.importers.common import UNIX_TIME_COLUMNS, ImportDataError, WarningLog
from rollingstar.logs.importers.sidecar import EPOCH_YEARS, CameraSpec, ObservationSpec
from rollingstar.sensors.catalog import HIPPARCOS_COMPLETE_HP, julian_year, magnitude_limit_for_field
from rollingstar.sensors.conventions import NS_PER_S
from rollingstar.sensors.scenario import CatalogConfig

EPOCH_DECIMALS = 4
"""Decimals of the Julian year written as the catalogue epoch (1e-4 yr = 53 min)."""
DEFAULT_EPOCH_YEAR = CatalogConfig().epoch_year
_EXIF_IFD = 0x8769
_DATETIME, _DATETIME_ORIGINAL, _OFFSET, _OFFSET_ORIGINAL = 0x0132, 0x9003, 0x9010, 0x9011


@dataclass(frozen=True)
class Observation:
    """The observation time (UTC, first frame) and where it came from (``observation_time``: stated
    in the sidecar; a Unix time column's name; ``exif``; ``fits``; or ``none`` with ``time`` None)."""

    time: datetime | None = None
    source: str = "none"

    @property
    def iso(self) -> str | None:
        return None if self.time is None else self.time.astimezone(timezone.utc).isoformat().replace("+00:00", "Z")


NO_OBSERVATION = Observation()


def from_unix_ns(t0_ns: int, column: str, where: str) -> Observation:
    """The observation at Unix time ``t0_ns`` (a frame time from a :data:`UNIX_TIME_COLUMNS` column)."""
    when = datetime(1970, 1, 1, tzinfo=timezone.utc) + timedelta(microseconds=int(t0_ns) // 1000)
    if not EPOCH_YEARS[0] <= when.year <= EPOCH_YEARS[1]:
        raise ImportDataError(f"{where}: {column} {t0_ns} is {when:%Y-%m-%d} as Unix time, outside the years "
                              f"{EPOCH_YEARS[0]:.0f}-{EPOCH_YEARS[1]:.0f}: not an observation time")
    return Observation(when, column)


def unix_looking(t0_ns) -> str | None:
    """The first frame's time as ISO 8601 UTC when every frame time, read as Unix nanoseconds, falls
    between 1990 and the end of 2100, else None: a hint for the warning, never an observation time."""
    t = np.asarray(t0_ns, dtype=np.int64)
    lo = datetime(1990, 1, 1, tzinfo=timezone.utc).timestamp() * NS_PER_S
    hi = datetime(int(EPOCH_YEARS[1]), 12, 31, tzinfo=timezone.utc).timestamp() * NS_PER_S
    if t.size == 0 or not (lo <= t.min() and t.max() <= hi):
        return None
    return from_unix_ns(int(t[0]), "t", "").iso


def exif_observation(path: Path, log: WarningLog) -> Observation:
    """The observation time an image file's EXIF/TIFF tags state (module docstring), else none."""
    try:
        with Image.open(path) as im:
            exif = im.getexif()
            sub = exif.get_ifd(_EXIF_IFD)
    except Exception:  # noqa: BLE001 - an unreadable file is reported by the image reader itself
        return NO_OBSERVATION
    tag, offset_tag = ((_DATETIME_ORIGINAL, _OFFSET_ORIGINAL) if sub.get(_DATETIME_ORIGINAL)
                       else (_DATETIME, _OFFSET))
    text = sub.get(tag) or exif.get(tag)
    if not text:
        return NO_OBSERVATION
    name = "DateTimeOriginal" if tag == _DATETIME_ORIGINAL else "DateTime"
    try:
        when = datetime.strptime(str(text).strip("\x00 "), "%Y:%m:%d %H:%M:%S")
    except ValueError:
        log(f"{path}: EXIF {name} {str(text)!r} is not a time (YYYY:MM:DD HH:MM:SS); not used")
        return NO_OBSERVATION
    offset = sub.get(offset_tag) or exif.get(offset_tag)
    try:
        zone = datetime.strptime(str(offset).strip("\x00 "), "%z").tzinfo if offset else None
    except ValueError:
        zone = None
    if zone is None:
        log(f"{path}: EXIF {name} {text} states no time zone; read as UTC (a zone error of up to 14 h moves the "
            "catalogue epoch by 0.0016 yr, no Hipparcos star by more than 17 mas); give observation_time to state it")
        zone = timezone.utc
    when = when.replace(tzinfo=zone)
    if not EPOCH_YEARS[0] <= when.year <= EPOCH_YEARS[1]:
        log(f"{path}: EXIF {name} {text} is outside the years {EPOCH_YEARS[0]:.0f}-{EPOCH_YEARS[1]:.0f}; not used")
        return NO_OBSERVATION
    return Observation(when, "exif")


def catalog_for(camera: CameraSpec, spec: ObservationSpec, observation: Observation, log: WarningLog, *,
                source: str, detections_per_frame: float | None = None,
                unix_hint: str | None = None, warn_default: bool = True) -> tuple[CatalogConfig, dict]:
    """The scenario catalogue of an import and its ``import.details.catalog`` record.

    ``spec`` holds the sidecar's choices (``catalog.epoch_year``, ``catalog.magnitude_limit``);
    ``source`` names where they were read (for the messages); ``unix_hint`` is the first frame
    time as a date when the frame times look like Unix time (see :func:`unix_looking`).
    """
    epoch, epoch_source, epoch_reason = _epoch(spec, observation, source)
    if epoch_source == "default" and warn_default:
        hint = (f"; the frame times would be {unix_hint} read as Unix time: if they are, name their column "
                f"{' or '.join(UNIX_TIME_COLUMNS)}" if unix_hint else "")
        log(f"{source}: no observation time (observation_time, Unix-time frame times, FITS DATE-OBS or EXIF); the catalogue is "
            f"propagated to the default epoch {epoch:g}{hint}")
    limit, limit_source, limit_reason, field = _limit(camera, spec, detections_per_frame, source, log)
    details = {"epoch_year": epoch, "epoch_source": epoch_source, "epoch_reason": epoch_reason,
               "observation_time_utc": observation.iso, "observation_time_source": observation.source,
               "magnitude_limit": limit, "magnitude_source": limit_source, "magnitude_reason": limit_reason,
               "field": field}
    return CatalogConfig(epoch_year=epoch, magnitude_limit=limit), details


def _epoch(spec: ObservationSpec, observation: Observation, source: str) -> tuple[float, str, str]:
    if spec.catalog.epoch_year is not None:
        return spec.catalog.epoch_year, "sidecar", f"catalog.epoch_year in {source}"
    if observation.time is not None:
        year = round(julian_year(observation.time), EPOCH_DECIMALS)
        kind = observation.source if observation.source in ("observation_time", "exif", "fits") else "timestamps"
        where = {"observation_time": f"observation_time in {source}", "exif": "the first image's EXIF time",
                 "fits": "the first image's FITS header (DATE-OBS, MJD-OBS)"}.get(
            observation.source, f"the first frame's {observation.source} (Unix time)")
        return year, kind, f"Julian year of {observation.iso}, from {where}"
    return DEFAULT_EPOCH_YEAR, "default", "no observation time; the scenario default"


def _limit(camera: CameraSpec, spec: ObservationSpec, detections_per_frame: float | None, source: str,
           log: WarningLog) -> tuple[float, str, str, dict]:
    hfov, vfov = camera.field_deg
    depth = magnitude_limit_for_field(hfov, vfov, detections_per_frame=detections_per_frame)
    field = {"hfov_deg": hfov, "vfov_deg": vfov, "solid_angle_sr": depth.solid_angle_sr,
             "detections_per_frame": detections_per_frame, "target_per_field": depth.target_per_field,
             "rule_magnitude_limit": depth.magnitude_limit, "stars_per_field": depth.stars_per_field}
    given = spec.catalog.magnitude_limit
    if given is not None:
        if given > HIPPARCOS_COMPLETE_HP:
            log(f"{source}: catalog.magnitude_limit {given:g} is fainter than Hp {HIPPARCOS_COMPLETE_HP:g}, to which "
                "Hipparcos-2 is complete: fields will miss stars the camera sees")
        return given, "sidecar", f"catalog.magnitude_limit in {source} (the field rule gives Hp {depth.magnitude_limit:g})", field
    if not depth.reached:
        log(f"{source}: a {hfov:.3g} x {vfov:.3g} deg field holds on average {depth.stars_per_field:.1f} Hipparcos-2 "
            f"stars to Hp {depth.magnitude_limit:g} (complete to there), fewer than the {depth.target_per_field:g} "
            "wanted for a reliable identification")
    return depth.magnitude_limit, "field", depth.describe(), field


def mean_per_frame(counts) -> float | None:
    """Mean number of stars per frame (None for no frames)."""
    counts = np.asarray(counts, dtype=float)
    return float(counts.mean()) if counts.size and math.isfinite(counts.mean()) else None
