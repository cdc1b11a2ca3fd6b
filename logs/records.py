"""The JSON records of a rollingstar log (docs/log-format.md), as strict pydantic models.

Each model is one MCAP schema: its ``SCHEMA_NAME`` is the MCAP schema name and its JSON Schema
(``model_json_schema()``) the schema data. Models are strict (unknown fields, wrong types,
NaN/inf and columns of unequal length are rejected) so that a file that does not follow the
format fails loudly instead of giving silently wrong numbers.

JSON has no NaN: float columns hold ``null`` where the value is unknown. The array helpers at the
end of this module convert NaN <-> null (``arrays_to_stars`` / ``stars_to_arrays`` and friends).
"""
from __future__ import annotations

import math
from typing import Annotated, Any, ClassVar, Iterable

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from .topics import (
    TOPIC_CENTROIDS,
    TOPIC_EST_ATTITUDE,
    TOPIC_EST_ATTITUDE_ERROR,
    TOPIC_EST_FRAME,
    TOPIC_EST_RATE,
    TOPIC_EST_STARS,
    TOPIC_GYRO,
    TOPIC_TRUTH_ATTITUDE,
    TOPIC_TRUTH_STARS,
)

FORMAT_VERSION = "1.2"
"""The version of the whole format (all topics and records); written in the ``rollingstar``
metadata record. A reader rejects a major version it does not know."""

_FloatCol = list[float | None]
# Every integer of a log is read into numpy int64; a frame time is also a log time, so it is >= 0.
_Int = Annotated[int, Field(ge=-(2**63), le=2**63 - 1)]
_TimeNs = Annotated[int, Field(ge=0, le=2**63 - 1)]
UNIT_TOLERANCE = 1e-6
"""Largest departure from norm 1 of a unit quaternion or a unit direction in a log."""
_Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
_Cov9 = Annotated[list[float], Field(min_length=9, max_length=9)]


def _config(name: str) -> ConfigDict:
    return ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, title=name, frozen=True)


class _Record(BaseModel):
    """Base of the JSON records: knows its schema name and its default MCAP log time."""

    SCHEMA_NAME: ClassVar[str] = ""

    def default_log_time_ns(self) -> int:  # pragma: no cover - every record overrides
        raise NotImplementedError

    def _check_lengths(self, reference: str, columns: tuple[str, ...]) -> None:
        n = len(getattr(self, reference))
        for name in columns:
            value = getattr(self, name)
            if value is not None and len(value) != n:
                raise ValueError(
                    f"{self.SCHEMA_NAME}: column {name!r} has length {len(value)}, "
                    f"expected {n} (the length of {reference!r})"
                )


class Quaternion(BaseModel):
    """A unit quaternion with named components (scalar ``w``)."""

    model_config = _config("rollingstar.Quaternion")
    x: float
    y: float
    z: float
    w: float

    @model_validator(mode="after")
    def _unit(self) -> "Quaternion":
        norm = math.sqrt(self.x**2 + self.y**2 + self.z**2 + self.w**2)
        if abs(norm - 1.0) > UNIT_TOLERANCE:
            raise ValueError(f"quaternion must have unit norm (|q| = {norm:.9g})")
        return self


class Vector3(BaseModel):
    """A 3-vector with named components."""

    model_config = _config("rollingstar.Vector3")
    x: float
    y: float
    z: float


_STAR_COLUMNS = (
    "x", "y", "t_ns", "row_time_ns", "flux", "peak", "npix", "saturated", "snr", "sigma_px",
    "cov_xx", "cov_xy", "cov_yy", "vx", "vy", "catalog_id", "ref_icrs", "magnitude",
)


class StarsRecord(_Record):
    """``rollingstar.Stars``: the stars of one frame, a struct of arrays (all of length n)."""

    SCHEMA_NAME: ClassVar[str] = "rollingstar.Stars"
    model_config = _config(SCHEMA_NAME)

    frame: _Int = Field(description="frame index, 0-based, increasing")
    t0_ns: _TimeNs = Field(description="frame time: exposure start of row 0, ns")
    x: _FloatCol = Field(description="column position, px (pixel centres at integers)")
    y: _FloatCol = Field(description="row position, px")
    t_ns: list[_Int] = Field(description="time the position refers to, ns")
    row_time_ns: list[_Int] | None = Field(None, description="exposure start of the star's row, ns")
    flux: _FloatCol | None = Field(None, description="summed signal above background, ADU")
    peak: _FloatCol | None = Field(None, description="peak pixel value above background, ADU")
    npix: list[_Int] | None = Field(None, description="pixels in the spot")
    saturated: list[bool] | None = Field(None, description="spot has a saturated pixel")
    snr: _FloatCol | None = Field(None, description="signal-to-noise ratio")
    sigma_px: _FloatCol | None = Field(None, description="1-sigma position uncertainty per axis, px")
    cov_xx: _FloatCol | None = Field(None, description="position covariance, x x, px^2 (image axes)")
    cov_xy: _FloatCol | None = Field(None, description="position covariance, x y, px^2")
    cov_yy: _FloatCol | None = Field(None, description="position covariance, y y, px^2")
    vx: _FloatCol | None = Field(None, description="image velocity along x, px/s")
    vy: _FloatCol | None = Field(None, description="image velocity along y, px/s")
    catalog_id: list[_Int] | None = Field(None, description="catalogue id, -1 when unidentified")
    ref_icrs: list[_Vec3 | None] | None = Field(
        None, description="ICRS unit vector [x, y, z] of the catalogue star, null when unidentified"
    )
    magnitude: _FloatCol | None = Field(None, description="catalogue visual magnitude")

    @model_validator(mode="after")
    def _lengths(self) -> "StarsRecord":
        self._check_lengths("x", _STAR_COLUMNS[1:])
        self._check_unit_directions()
        return self

    def _check_unit_directions(self) -> None:
        """Each known ``ref_icrs`` is a unit vector (an unknown one is null, never a placeholder)."""
        for i, v in enumerate(self.ref_icrs or ()):
            norm = math.sqrt(sum(c * c for c in v)) if v is not None else 1.0
            if abs(norm - 1.0) > UNIT_TOLERANCE:
                raise ValueError(f"{self.SCHEMA_NAME}: ref_icrs of star {i} is not a unit vector (|v| = {norm:.9g}); "
                                 "an unknown direction is null")

    @property
    def n(self) -> int:
        return len(self.x)

    def default_log_time_ns(self) -> int:
        return self.t0_ns


class GyroSamplesRecord(_Record):
    """``rollingstar.GyroSamples``: one or more gyro samples, camera frame, rad/s."""

    SCHEMA_NAME: ClassVar[str] = "rollingstar.GyroSamples"
    model_config = _config(SCHEMA_NAME)

    t_ns: list[_Int] = Field(min_length=1, description="sample times, ns, non-decreasing")
    x: list[float] = Field(description="angular rate about camera x, rad/s")
    y: list[float] = Field(description="angular rate about camera y, rad/s")
    z: list[float] = Field(description="angular rate about camera z (boresight), rad/s")

    @model_validator(mode="after")
    def _lengths(self) -> "GyroSamplesRecord":
        self._check_lengths("t_ns", ("x", "y", "z"))
        _check_sorted(self.SCHEMA_NAME, self.t_ns)
        return self

    def default_log_time_ns(self) -> int:
        return self.t_ns[-1]


class AttitudeSamplesRecord(_Record):
    """``rollingstar.AttitudeSamples``: true attitude (camera-to-ICRS) and body rates."""

    SCHEMA_NAME: ClassVar[str] = "rollingstar.AttitudeSamples"
    model_config = _config(SCHEMA_NAME)

    t_ns: list[_Int] = Field(min_length=1, description="sample times, ns, non-decreasing")
    qx: list[float] = Field(description="camera-to-ICRS quaternion, x component")
    qy: list[float] = Field(description="camera-to-ICRS quaternion, y component")
    qz: list[float] = Field(description="camera-to-ICRS quaternion, z component")
    qw: list[float] = Field(description="camera-to-ICRS quaternion, scalar component")
    wx: list[float] | None = Field(None, description="body rate about camera x, rad/s")
    wy: list[float] | None = Field(None, description="body rate about camera y, rad/s")
    wz: list[float] | None = Field(None, description="body rate about camera z, rad/s")

    @model_validator(mode="after")
    def _lengths(self) -> "AttitudeSamplesRecord":
        self._check_lengths("t_ns", ("qx", "qy", "qz", "qw", "wx", "wy", "wz"))
        _check_sorted(self.SCHEMA_NAME, self.t_ns)
        rates = [self.wx is None, self.wy is None, self.wz is None]
        if any(rates) and not all(rates):
            raise ValueError(f"{self.SCHEMA_NAME}: give all of wx, wy, wz or none of them")
        norms = np.sqrt(np.square([self.qx, self.qy, self.qz, self.qw]).sum(axis=0))
        bad = np.flatnonzero(np.abs(norms - 1.0) > UNIT_TOLERANCE)
        if bad.size:
            raise ValueError(
                f"{self.SCHEMA_NAME}: quaternion {int(bad[0])} is not unit (|q| = {norms[bad[0]]:.9g})"
            )
        return self

    def default_log_time_ns(self) -> int:
        return self.t_ns[0]


class AttitudeEstimateRecord(_Record):
    """``rollingstar.AttitudeEstimate``: one attitude estimate (camera-to-ICRS)."""

    SCHEMA_NAME: ClassVar[str] = "rollingstar.AttitudeEstimate"
    model_config = _config(SCHEMA_NAME)

    frame: _Int = Field(description="frame index the estimate belongs to")
    t_ns: _Int = Field(description="time the attitude refers to, ns")
    q: Quaternion | None = Field(description="camera-to-ICRS quaternion; null when invalid")
    valid: bool
    reason: str = Field("", description="why the estimate is invalid (empty when valid)")
    n_stars: _Int = Field(description="stars used")
    covariance_rad2: _Cov9 | None = Field(
        None, description="3x3 attitude-error covariance in the camera frame, rad^2, row-major"
    )
    gyro_bias_rad_s: _Vec3 | None = Field(
        None, description="gyro bias estimated with the attitude (camera frame, rad/s); null when not estimated"
    )
    false_match_prob: float | None = Field(
        None, ge=0.0, le=1.0, description="probability that the frame's identified stars are chance coincidences; "
        "null when no identification check ran")

    @model_validator(mode="after")
    def _valid_has_q(self) -> "AttitudeEstimateRecord":
        if self.valid and self.q is None:
            raise ValueError(f"{self.SCHEMA_NAME}: a valid estimate needs q")
        return self

    @classmethod
    def from_values(cls, frame: int, t_ns: int, q_xyzw, n_stars: int, valid: bool = True,
                    reason: str = "", covariance_rad2=None) -> "AttitudeEstimateRecord":
        """Build from arrays (scalar-last ``q_xyzw``; NaN quaternion or None -> ``q: null``)."""
        q = None
        if q_xyzw is not None and np.all(np.isfinite(q_xyzw)):
            x, y, z, w = (float(v) for v in np.asarray(q_xyzw, dtype=float))
            q = Quaternion(x=x, y=y, z=z, w=w)
        return cls(frame=int(frame), t_ns=int(t_ns), q=q, valid=bool(valid), reason=str(reason),
                   n_stars=int(n_stars), covariance_rad2=_cov_list(covariance_rad2))

    def q_xyzw(self) -> np.ndarray:
        """Scalar-last quaternion array (NaN when ``q`` is null)."""
        if self.q is None:
            return np.full(4, np.nan)
        return np.array([self.q.x, self.q.y, self.q.z, self.q.w])

    def default_log_time_ns(self) -> int:
        return self.t_ns


class AttitudeErrorRecord(_Record):
    """``rollingstar.AttitudeError``: a valid attitude estimate against the recording's truth at its time."""

    SCHEMA_NAME: ClassVar[str] = "rollingstar.AttitudeError"
    model_config = _config(SCHEMA_NAME)

    frame: _Int = Field(description="frame index of the estimate")
    t_ns: _Int = Field(description="time the estimate refers to, ns")
    x_arcsec: float = Field(description="rotation from truth to estimate about camera x (cross-boresight), arcsec")
    y_arcsec: float = Field(description="rotation from truth to estimate about camera y (cross-boresight), arcsec")
    z_arcsec: float = Field(description="rotation from truth to estimate about camera z (roll), arcsec")

    def default_log_time_ns(self) -> int:
        return self.t_ns


class RateEstimateRecord(_Record):
    """``rollingstar.RateEstimate``: camera angular velocity in the camera frame, rad/s."""

    SCHEMA_NAME: ClassVar[str] = "rollingstar.RateEstimate"
    model_config = _config(SCHEMA_NAME)

    frame: _Int
    t_ns: _Int = Field(description="time the rate refers to, ns")
    omega: Vector3 | None = Field(description="angular velocity, rad/s, camera frame; null when invalid")
    valid: bool
    reason: str = ""
    covariance: _Cov9 | None = Field(None, description="3x3 covariance, (rad/s)^2, row-major")
    iterations: _Int | None = Field(None, description="solver iterations, when iterative")

    @model_validator(mode="after")
    def _valid_has_omega(self) -> "RateEstimateRecord":
        if self.valid and self.omega is None:
            raise ValueError(f"{self.SCHEMA_NAME}: a valid estimate needs omega")
        return self

    @classmethod
    def from_values(cls, frame: int, t_ns: int, omega_rad_s, valid: bool = True, reason: str = "",
                    covariance=None, iterations: int | None = None) -> "RateEstimateRecord":
        """Build from arrays (NaN or None ``omega_rad_s`` -> ``omega: null``)."""
        omega = None
        if omega_rad_s is not None and np.all(np.isfinite(omega_rad_s)):
            x, y, z = (float(v) for v in np.asarray(omega_rad_s, dtype=float))
            omega = Vector3(x=x, y=y, z=z)
        return cls(frame=int(frame), t_ns=int(t_ns), omega=omega, valid=bool(valid),
                   reason=str(reason), covariance=_cov_list(covariance),
                   iterations=None if iterations is None else int(iterations))

    def default_log_time_ns(self) -> int:
        return self.t_ns


class FittedCamera(BaseModel):
    """A camera model fitted on one frame: pinhole focal length and principal point (px) and radial
    distortion ``k1, k2`` (normalised coordinates, ``rollingstar.sensors.camera.PinholeCamera``)."""

    model_config = ConfigDict(extra="forbid")

    focal_px: float = Field(gt=0)
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0


class FrameStatusRecord(_Record):
    """``rollingstar.FrameStatus``: what happened to one frame."""

    SCHEMA_NAME: ClassVar[str] = "rollingstar.FrameStatus"
    model_config = _config(SCHEMA_NAME)

    frame: _Int
    t0_ns: _TimeNs = Field(description="frame time: exposure start of row 0, ns")
    flags: list[str] = Field(description="short machine-readable notes, e.g. 'too_few_stars'")
    n_detected: _Int
    n_identified: _Int
    camera: FittedCamera | None = Field(
        None, description="the camera model an identifier fitted on this frame, used by every later stage; "
        "null: the recording's declared camera")
    psf_sigma_px: float | None = Field(
        None, gt=0, description="the Gaussian PSF sigma (px) a stage measured from the camera's pixels and "
        "worked with on this frame (rs-bundle); null: none did")

    def default_log_time_ns(self) -> int:
        return self.t0_ns


RECORD_TYPES: dict[str, type[_Record]] = {
    cls.SCHEMA_NAME: cls
    for cls in (StarsRecord, GyroSamplesRecord, AttitudeSamplesRecord, AttitudeEstimateRecord,
                AttitudeErrorRecord, RateEstimateRecord, FrameStatusRecord)
}
"""Schema name -> record model, for every JSON schema of the format."""

TOPIC_RECORDS: dict[str, type[_Record]] = {
    TOPIC_CENTROIDS: StarsRecord,
    TOPIC_GYRO: GyroSamplesRecord,
    TOPIC_TRUTH_ATTITUDE: AttitudeSamplesRecord,
    TOPIC_TRUTH_STARS: StarsRecord,
    TOPIC_EST_STARS: StarsRecord,
    TOPIC_EST_ATTITUDE: AttitudeEstimateRecord,
    TOPIC_EST_RATE: RateEstimateRecord,
    TOPIC_EST_FRAME: FrameStatusRecord,
    TOPIC_EST_ATTITUDE_ERROR: AttitudeErrorRecord,
}
"""The record model of every standard JSON topic."""

# Short names (the schema names without the ``rollingstar.`` prefix).
GyroSamples = GyroSamplesRecord
AttitudeSamples = AttitudeSamplesRecord
AttitudeEstimate = AttitudeEstimateRecord
RateEstimate = RateEstimateRecord
AttitudeError = AttitudeErrorRecord
FrameStatus = FrameStatusRecord


def _check_sorted(name: str, t_ns: list[int]) -> None:
    for i in range(1, len(t_ns)):
        if t_ns[i] < t_ns[i - 1]:
            raise ValueError(f"{name}: t_ns must be non-decreasing (t_ns[{i}] < t_ns[{i - 1}])")


def _cov_list(cov) -> list[float] | None:
    if cov is None:
        return None
    arr = np.asarray(cov, dtype=float).reshape(-1)
    if arr.size != 9:
        raise ValueError(f"covariance must have 9 entries (3x3), got {arr.size}")
    if not np.all(np.isfinite(arr)):
        return None
    return arr.tolist()


# --- arrays <-> records ---------------------------------------------------------------------

_FLOAT_COLS = ("x", "y", "flux", "peak", "snr", "sigma_px", "cov_xx", "cov_xy", "cov_yy", "vx", "vy", "magnitude")
_INT_COLS = ("t_ns", "row_time_ns", "npix", "catalog_id")


def _nan_to_none(values: np.ndarray) -> list[float | None]:
    return [None if not math.isfinite(v) else v for v in values.tolist()]


def arrays_to_stars(frame: int, t0_ns: int, **columns: Any) -> StarsRecord:
    """A :class:`StarsRecord` from numpy columns (NaN -> null; a column given as None is omitted).

    ``x``, ``y`` and ``t_ns`` are required (``t_ns`` may be a scalar, broadcast to n);
    ``ref_icrs`` is (n, 3) with NaN rows for unidentified stars. Column names are those of
    :class:`StarsRecord`; an unknown name or a wrong length raises ``ValueError``.
    """
    unknown = set(columns) - set(_STAR_COLUMNS)
    if unknown:
        raise ValueError(f"unknown Stars columns: {sorted(unknown)}; known: {list(_STAR_COLUMNS)}")
    for required in ("x", "y", "t_ns"):
        if columns.get(required) is None:
            raise ValueError(f"Stars column {required!r} is required")
    x = np.asarray(columns["x"], dtype=float).reshape(-1)
    n = x.shape[0]
    out: dict[str, Any] = {"frame": int(frame), "t0_ns": int(t0_ns)}
    for name, value in columns.items():
        if value is None:
            continue
        arr = np.asarray(value)
        if name == "t_ns" and arr.ndim == 0:
            arr = np.full(n, arr, dtype=np.int64)
        expected = (n, 3) if name == "ref_icrs" else (n,)
        if arr.shape != expected:
            raise ValueError(f"Stars column {name!r}: expected shape {expected}, got {arr.shape}")
        if name in _FLOAT_COLS:
            out[name] = _nan_to_none(arr.astype(float))
        elif name in _INT_COLS:
            if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
                raise ValueError(f"Stars column {name!r} is an integer column and cannot hold NaN")
            out[name] = [int(v) for v in arr.astype(np.int64)]
        elif name == "saturated":
            out[name] = [bool(v) for v in arr.astype(bool)]
        else:  # ref_icrs
            rows = arr.astype(float)
            out[name] = [r.tolist() if np.all(np.isfinite(r)) else None for r in rows]
    return StarsRecord(**out)


def _as_record(record: Any, cls: type[_Record]) -> Any:
    if isinstance(record, cls):
        return record
    if isinstance(record, dict):
        return cls.model_validate(record)
    raise TypeError(f"expected a {cls.__name__} or its JSON dict, got {type(record).__name__}")


def stars_to_arrays(record: StarsRecord | dict) -> dict[str, np.ndarray]:
    """Numpy columns of a ``rollingstar.Stars`` record (null -> NaN).

    Only the columns present in the record are returned: ``x, y`` float, ``t_ns``,
    ``row_time_ns``, ``npix``, ``catalog_id`` int64, ``saturated`` bool, ``ref_icrs`` (n, 3) with
    NaN rows, the rest float. Apart from ``magnitude`` the names match
    ``rollingstar.estimators.data.StarTable.build``, which gives a column the record leaves out
    its unknown value (NaN for the position covariance ``cov_xx, cov_xy, cov_yy`` of a record
    written before those columns existed).
    """
    rec = _as_record(record, StarsRecord)
    out: dict[str, np.ndarray] = {}
    for name in _STAR_COLUMNS:
        value = getattr(rec, name)
        if value is None:
            continue
        if name in _FLOAT_COLS:
            out[name] = np.array([np.nan if v is None else v for v in value], dtype=float)
        elif name in _INT_COLS:
            out[name] = np.array(value, dtype=np.int64)
        elif name == "saturated":
            out[name] = np.array(value, dtype=bool)
        else:
            out[name] = np.array([[np.nan] * 3 if v is None else v for v in value],
                                 dtype=float).reshape(-1, 3)
    return out


def gyro_samples_from_arrays(t_ns, omega_rad_s) -> GyroSamplesRecord:
    """A gyro record from times (n,) and rates (n, 3) in rad/s, camera frame."""
    t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
    w = np.asarray(omega_rad_s, dtype=float).reshape(-1, 3)
    if w.shape[0] != t.shape[0]:
        raise ValueError(f"gyro: {t.shape[0]} times but {w.shape[0]} rate samples")
    return GyroSamplesRecord(t_ns=t.tolist(), x=w[:, 0].tolist(), y=w[:, 1].tolist(), z=w[:, 2].tolist())


def gyro_samples_to_arrays(record: GyroSamplesRecord | dict) -> dict[str, np.ndarray]:
    """``{"t_ns": (n,) int64, "omega_rad_s": (n, 3)}`` from a gyro record."""
    rec = _as_record(record, GyroSamplesRecord)
    return {"t_ns": np.array(rec.t_ns, dtype=np.int64),
            "omega_rad_s": np.column_stack([rec.x, rec.y, rec.z]).astype(float).reshape(-1, 3)}


def attitude_samples_from_arrays(t_ns, q_xyzw, omega_rad_s=None) -> AttitudeSamplesRecord:
    """A truth-attitude record from times (n,), scalar-last quaternions (n, 4), rates (n, 3)."""
    t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
    q = np.asarray(q_xyzw, dtype=float).reshape(-1, 4)
    if q.shape[0] != t.shape[0]:
        raise ValueError(f"attitude samples: {t.shape[0]} times but {q.shape[0]} quaternions")
    fields: dict[str, Any] = {"t_ns": t.tolist(), "qx": q[:, 0].tolist(), "qy": q[:, 1].tolist(),
                              "qz": q[:, 2].tolist(), "qw": q[:, 3].tolist()}
    if omega_rad_s is not None:
        w = np.asarray(omega_rad_s, dtype=float).reshape(-1, 3)
        if w.shape[0] != t.shape[0]:
            raise ValueError(f"attitude samples: {t.shape[0]} times but {w.shape[0]} rate samples")
        fields.update(wx=w[:, 0].tolist(), wy=w[:, 1].tolist(), wz=w[:, 2].tolist())
    return AttitudeSamplesRecord(**fields)


def attitude_samples_to_arrays(record: AttitudeSamplesRecord | dict) -> dict[str, np.ndarray]:
    """``{"t_ns": (n,) int64, "q_xyzw": (n, 4), "omega_rad_s": (n, 3)}``; rates NaN when absent."""
    rec = _as_record(record, AttitudeSamplesRecord)
    n = len(rec.t_ns)
    omega = (np.full((n, 3), np.nan) if rec.wx is None
             else np.column_stack([rec.wx, rec.wy, rec.wz]).astype(float).reshape(n, 3))
    return {"t_ns": np.array(rec.t_ns, dtype=np.int64),
            "q_xyzw": np.column_stack([rec.qx, rec.qy, rec.qz, rec.qw]).astype(float).reshape(n, 4),
            "omega_rad_s": omega}


def join_gyro_samples(records: Iterable[GyroSamplesRecord | dict]) -> dict[str, np.ndarray]:
    """The samples of several gyro records, in the order given: ``{"t_ns": (n,) int64,
    "omega_rad_s": (n, 3)}`` (n = 0 without records)."""
    parts = [gyro_samples_to_arrays(r) for r in records]
    if not parts:
        return {"t_ns": np.zeros(0, dtype=np.int64), "omega_rad_s": np.zeros((0, 3))}
    return {name: np.concatenate([p[name] for p in parts]) for name in ("t_ns", "omega_rad_s")}


def join_attitude_samples(records: Iterable[AttitudeSamplesRecord | dict]) -> dict[str, np.ndarray]:
    """The samples of several truth-attitude records, in the order given: ``{"t_ns": (n,) int64,
    "q_xyzw": (n, 4), "omega_rad_s": (n, 3)}`` (rates NaN where a record has none; n = 0 without
    records)."""
    parts = [attitude_samples_to_arrays(r) for r in records]
    if not parts:
        return {"t_ns": np.zeros(0, dtype=np.int64), "q_xyzw": np.zeros((0, 4)), "omega_rad_s": np.zeros((0, 3))}
    return {name: np.concatenate([p[name] for p in parts]) for name in ("t_ns", "q_xyzw", "omega_rad_s")}
