"""The documented input formats of ``rollingstar import``: ``camera.yaml`` and ``recording.yaml``.

Both are strict pydantic models (unknown keys rejected, units in key names, see
docs/log-format.md "Importing recordings"). A camera file describes the sensor (pinhole optics,
detector size, shutter); a recording sidecar describes one folder of images (which files, their
times, optional gyro and truth CSVs) and either holds the camera inline or names a camera file.

:func:`scenario_for` turns a camera into the :class:`~rollingstar.sensors.scenario.ScenarioConfig` a log must
declare (metadata ``scenario``) so that ``rollingstar run`` builds the sensor context from it.
"""
from __future__ import annotations

import math
from datetime import date, datetime
from pathlib import Path
from typing import Literal

from pydantic import (
    ConfigDict,
    Field,
    NonNegativeFloat,
    NonNegativeInt,
    PositiveFloat,
    PositiveInt,
    ValidationError,
    field_validator,
    model_validator,
)

from rollingstar.config import NoBooleanNumbers, format_validation_error, read_yaml
from rollingstar.errors import ConfigError
from rollingstar.logs.importers.common import ImportDataError
from rollingstar.sensors.camera import Projection, projection_rho, projection_theta
from rollingstar.sensors.scenario import (
    AttitudeConfig,
    CatalogConfig,
    ImageConfig,
    MotionConfig,
    NoiseConfig,
    ScenarioConfig,
    SensorConfig,
    ShutterConfig,
)

DEFAULT_EXPOSURE_MS = 100.0
"""Exposure assumed when a camera file does not state one (it only sets the stars' times)."""
DEFAULT_FRAME_RATE_HZ = 1.0
"""Frame rate assumed when a sidecar gives neither timestamps nor a frame rate."""
NOMINAL_PIXEL_SIZE_UM = 1.0
"""Pixel pitch written when only the field of view is known: only focal / pixel matters."""
MIN_FRAME_SPACING_NS = 100_000  # frames under 0.1 ms apart (10 kHz): times in another unit
MAX_PINHOLE_FIELD_DEG = 170.0  # a perspective (pinhole) lens with a wider diagonal field: units confused

FITS_SUFFIXES = (".fits", ".fit", ".fts")
IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".jpg", ".jpeg", *FITS_SUFFIXES)
EPOCH_YEARS = (1900.0, 2100.0)
"""Catalogue epochs and observation years accepted: a century either side of the Hipparcos epoch
J1991.25, over which the catalogue's linear space motion is meant to be used (3000 is a typo)."""
MAX_MAGNITUDE_LIMIT = 12.0
"""Faintest catalogue limit accepted: 99.5 % of the Hipparcos-2 stars are brighter (it is complete to about Hp 9)."""


class _Strict(NoBooleanNumbers):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)


class ShutterSpec(_Strict):
    """Exposure timing. Defaults: global shutter, 100 ms exposure, no line delay."""

    mode: Literal["rolling", "global"] = "global"
    exposure_ms: PositiveFloat = DEFAULT_EXPOSURE_MS
    line_delay_us: NonNegativeFloat = 0.0

    @model_validator(mode="after")
    def _rolling_has_delay(self) -> "ShutterSpec":
        if self.mode == "rolling" and self.line_delay_us <= 0:
            raise ValueError("a rolling shutter needs line_delay_us > 0 (the delay between the exposure "
                             "starts of adjacent rows)")
        return self


class CameraSpec(_Strict):
    """A camera: pinhole optics, detector size and shutter (``camera.yaml``).

    Optics are given either as ``focal_length_mm`` with ``pixel_size_um``, or as ``fov_deg`` (the
    full angle across ``fov_axis``: ``f_px = (N / 2) / tan(fov / 2)`` with ``N`` the width,
    height or diagonal in pixels; ``pixel_size_um`` then defaults to a nominal 1 um).
    """

    name: str = "camera"
    description: str = ""
    width_px: PositiveInt
    height_px: PositiveInt
    focal_length_mm: PositiveFloat | None = None
    pixel_size_um: PositiveFloat | None = None
    fov_deg: float | None = Field(None, gt=0, lt=180)
    fov_axis: Literal["horizontal", "vertical", "diagonal"] = "horizontal"
    principal_point_px: tuple[float, float] | None = Field(
        None, description="(cx, cy); default the detector centre ((W-1)/2, (H-1)/2)")
    projection: Projection = Field(
        "perspective", description="the lens's projection (perspective: a pinhole; equidistant, equisolid, "
        "stereographic or orthographic: wide-angle lenses, rollingstar.sensors.camera.PROJECTIONS); fov_deg is "
        "read through it")
    shutter: ShutterSpec = ShutterSpec()
    bit_depth: int | None = Field(None, ge=8, le=16, description="ADC bits; default from the image dtype (8 or 16)")
    mirrored: bool = Field(
        False, description="the images are the mirror image of what the camera sees (a star diagonal or another "
        "mirror in the light path): the importer reverses every row, so the recording holds the unmirrored view; "
        "principal_point_px is in the files' own pixels")
    gain_e_per_adu: PositiveFloat = Field(
        1.0, description="conversion gain, electrons per ADU: the centroiders' shot-noise term. The default 1 "
        "overstates the shot noise of most cameras' 8-12 bit output (several to tens of e-/ADU), so the "
        "reported centroid covariance errs on the large side until the camera states it")

    @model_validator(mode="after")
    def _optics(self) -> "CameraSpec":
        if (self.focal_length_mm is None) == (self.fov_deg is None):
            raise ValueError("give the optics as focal_length_mm with pixel_size_um, or as fov_deg "
                             "(with fov_axis), not both and not neither")
        if self.focal_length_mm is not None and self.pixel_size_um is None:
            raise ValueError("focal_length_mm needs pixel_size_um")
        diagonal = math.degrees(2.0 * math.atan(math.hypot(self.width_px, self.height_px) / 2.0 / self.focal_px))
        if self.projection == "perspective" and diagonal > MAX_PINHOLE_FIELD_DEG:
            raise ValueError(f"the optics give a focal length of {self.focal_px:.3g} px, a pinhole field of {diagonal:.1f} "
                             f"deg across the diagonal, beyond the {MAX_PINHOLE_FIELD_DEG:g} deg a perspective lens images: "
                             "focal_length_mm in millimetres and pixel_size_um in micrometres (or a wide-angle "
                             "projection) expected")
        return self

    @property
    def focal_px(self) -> float:
        """Focal length in pixels."""
        if self.focal_length_mm is not None:
            return self.focal_length_mm * 1e3 / self.pixel_size_um
        n = {"horizontal": self.width_px, "vertical": self.height_px,
             "diagonal": math.hypot(self.width_px, self.height_px)}[self.fov_axis]
        return (n / 2.0) / float(projection_rho(math.radians(self.fov_deg) / 2.0, self.projection)[0])

    @property
    def field_deg(self) -> tuple[float, float]:
        """Full angles (horizontal, vertical) of the detector seen through the lens, deg."""
        return tuple(2.0 * math.degrees(float(projection_theta(n / 2.0 / self.focal_px, self.projection)))
                     for n in (self.width_px, self.height_px))

    def sensor_config(self) -> SensorConfig:
        """The scenario sensor block (focal length and pixel size whose ratio is ``focal_px``)."""
        pixel_um = self.pixel_size_um if self.pixel_size_um is not None else NOMINAL_PIXEL_SIZE_UM
        pp = self.principal_point_px
        if pp is not None and self.mirrored:  # the recording holds the rows reversed
            pp = ((self.width_px - 1) - pp[0], pp[1])
        return SensorConfig(focal_length_mm=self.focal_px * pixel_um * 1e-3, pixel_size_um=pixel_um,
                            width_px=self.width_px, height_px=self.height_px, principal_point_px=pp,
                            projection=self.projection)


class TimestampsSpec(_Strict):
    """Frame times (``t0``, exposure start of row 0): a frame rate, a list, or a CSV.

    - ``frame_rate_hz``: ``t0_k = start_ns + round(k * 1e9 / frame_rate_hz)``;
    - ``t0_ns``: one integer per image, in file order, strictly increasing;
    - ``csv``: a file with columns ``file`` and ``t_ns`` (or ``time_s``), one row per image.
    - ``csv`` with ``t_unix_ns`` (or ``time_unix_s``) instead: the same, stated to be Unix time
      (UTC, since 1970-01-01T00:00:00Z), which also gives the observation time.

    Default: ``frame_rate_hz: 1.0`` from ``start_ns: 0``.
    """

    frame_rate_hz: PositiveFloat | None = None
    start_ns: NonNegativeInt = 0
    t0_ns: list[NonNegativeInt] | None = None
    csv: str | None = None

    @model_validator(mode="after")
    def _one_source(self) -> "TimestampsSpec":
        given = [k for k in ("frame_rate_hz", "t0_ns", "csv") if getattr(self, k) is not None]
        if len(given) > 1:
            raise ValueError(f"give one of frame_rate_hz, t0_ns, csv (got {', '.join(given)})")
        t = self.t0_ns or []
        gaps = sorted(b - a for a, b in zip(t, t[1:]))
        if gaps and 0 < gaps[len(gaps) // 2] < MIN_FRAME_SPACING_NS:  # order is checked with the images
            raise ValueError(f"t0_ns: frames {gaps[len(gaps) // 2]} ns apart (median): t0_ns holds integer "
                             "nanoseconds (these look like seconds or milliseconds; 1 s is 1000000000)")
        return self


class CatalogSpec(_Strict):
    """The reference catalogue a recording declares; an unset key is chosen by the importer."""

    epoch_year: float | None = Field(
        None, ge=EPOCH_YEARS[0], le=EPOCH_YEARS[1],
        description="Julian year the star positions are propagated to; default the observation time's")
    magnitude_limit: float | None = Field(
        None, gt=0.0, le=MAX_MAGNITUDE_LIMIT,
        description="faintest Hp magnitude; default from the camera's field (magnitude_limit_for_field)")


class ObservationSpec(_Strict):
    """When the recording was made and which catalogue it is identified against."""

    observation_time: datetime | None = Field(
        None, description="UTC time of the first frame, ISO 8601 with its zone (2019-07-29T20:47:26Z); "
                          "default from Unix-time frame times, else the first image's EXIF time")
    catalog: CatalogSpec = CatalogSpec()

    @field_validator("observation_time", mode="before")
    @classmethod
    def _iso_time_with_zone(cls, value):
        if value is None:
            return None
        if isinstance(value, str):
            try:
                value = datetime.fromisoformat(value.strip())
            except ValueError:
                raise ValueError("not an ISO 8601 time; write e.g. 2019-07-29T20:47:26Z") from None
        if not isinstance(value, datetime):
            what = ("a date without a time of day" if isinstance(value, date) else
                    "a number (seconds or milliseconds, since when?)" if isinstance(value, (int, float)) else
                    f"not a time ({type(value).__name__})")
            raise ValueError(f"{what}; write an ISO 8601 time with its zone, e.g. 2019-07-29T20:47:26Z")
        if value.utcoffset() is None:
            raise ValueError(f"{value.isoformat()} has no time zone; write it in UTC with a trailing Z "
                             "(2019-07-29T20:47:26Z) or with its offset (2019-07-29T22:47:26+02:00)")
        if not EPOCH_YEARS[0] <= value.year <= EPOCH_YEARS[1]:
            raise ValueError(f"year {value.year} is outside {EPOCH_YEARS[0]:.0f}-{EPOCH_YEARS[1]:.0f}")
        return value


class RecordingSidecar(ObservationSpec):
    """``recording.yaml`` beside a folder of images (paths relative to the sidecar's folder, ``files`` to the images')."""

    camera: CameraSpec | None = Field(None, description="the camera, inline; None: camera_file or --camera")
    camera_file: str | None = Field(None, description="path of a camera.yaml instead of an inline camera")
    files: str | list[str] | None = Field(
        None, description="a glob pattern or an explicit list of image files; default every *.tif, *.tiff, "
                          "*.png, *.jpg, *.jpeg, *.fits, *.fit, *.fts image in the folder, sorted by name (a number "
                          "at the end of the name compared by value)")
    timestamps: TimestampsSpec = TimestampsSpec()
    gyro_csv: str | None = Field(None, description="CSV: t_ns (or time_s), wx, wy, wz (rad/s, camera frame)")
    truth_csv: str | None = Field(
        None, description="CSV: t_ns (or time_s), qx, qy, qz, qw (camera-to-ICRS) and optionally wx, wy, wz")
    initial_attitude: AttitudeConfig | None = Field(
        None, description="a prior attitude (boresight ra/dec, roll) for the tracking identifier; default none")

    @model_validator(mode="after")
    def _one_camera(self) -> "RecordingSidecar":
        if self.camera is not None and self.camera_file is not None:
            raise ValueError("give camera (inline) or camera_file, not both")
        return self


def load_model(model: type[_Strict], path: str | Path):
    """Read and validate a YAML file; errors name the file and the key path."""
    return _validate(model, read_yaml(path), path)


def _validate(model: type[_Strict], data, path: str | Path):
    try:
        return model.model_validate(data)
    except ValidationError as err:
        raise ConfigError(format_validation_error(str(path), err)) from None


def load_camera(path: str | Path) -> CameraSpec:
    """A :class:`CameraSpec` from a ``camera.yaml``; a recording sidecar given instead is named as such."""
    data = read_yaml(path)
    sidecar_keys = sorted(set(data) & _SIDECAR_ONLY_KEYS) if isinstance(data, dict) else []
    if sidecar_keys and "width_px" not in data:
        raise ConfigError(f"{path}: a recording sidecar (it has {', '.join(sidecar_keys)}), not a camera file "
                          "(width_px, height_px and the optics, docs/log-format.md): give a sidecar with --sidecar, "
                          "and as the camera the camera file it names (camera_file)")
    return _validate(CameraSpec, data, path)


_SIDECAR_ONLY_KEYS = set(RecordingSidecar.model_fields) - set(CameraSpec.model_fields)


def load_sidecar(path: str | Path) -> RecordingSidecar:
    """A :class:`RecordingSidecar` from a ``recording.yaml``."""
    return load_model(RecordingSidecar, path)


def scenario_for(camera: CameraSpec, *, name: str, description: str, level: Literal["image", "centroid"],
                 frames: int, bit_depth: int = 16, centroid_sigma_px: float | None = None,
                 initial_attitude: AttitudeConfig | None = None, frame_period_ms: float | None = None,
                 catalog: CatalogConfig | None = None) -> ScenarioConfig:
    """The scenario (sensor model) an imported log declares in its ``scenario`` metadata.

    Only the sensor, shutter, bit depth, centroid noise, the reference catalogue and an optional
    prior attitude carry information; the motion has no rates (the truth, if any, is in the log's
    truth topics).
    """
    try:
        return _scenario(camera, name, description, level, frames, bit_depth, centroid_sigma_px, initial_attitude,
                         frame_period_ms, catalog or CatalogConfig())
    except ValidationError as exc:  # a value derived from the data that the sensor model cannot hold
        raise ImportDataError(f"the sensor model derived from the imported data is invalid:\n"
                              f"{format_validation_error(description, exc)}") from None


def _scenario(camera, name, description, level, frames, bit_depth, centroid_sigma_px, initial_attitude,
              frame_period_ms, catalog) -> ScenarioConfig:
    sh = camera.shutter
    if frame_period_ms is not None and "shutter" not in camera.model_fields_set and sh.exposure_ms > frame_period_ms:
        # no shutter given: the default exposure cannot be longer than the frames' spacing
        sh = sh.model_copy(update={"exposure_ms": frame_period_ms})
    shutter = ShutterConfig(mode=sh.mode, exposure_ms=sh.exposure_ms, line_delay_us=sh.line_delay_us,
                            frame_period_ms=frame_period_ms)
    noise = NoiseConfig() if centroid_sigma_px is None else NoiseConfig(centroid_sigma_px=centroid_sigma_px)
    return ScenarioConfig(
        name=name, description=description, level=level, sensor=camera.sensor_config(), shutter=shutter,
        catalog=catalog, motion=MotionConfig(initial_attitude=initial_attitude), noise=noise,
        image=ImageConfig(bit_depth=bit_depth, gain_e_per_adu=camera.gain_e_per_adu), frames=max(1, int(frames)))
