"""Data passed between pipeline stages: one frame's stars, estimates, and the sensor context.

Data flows one way: the runner builds a :class:`FrameData` from the recording, every stage returns
a new :class:`FrameData` (inputs are never mutated), and the runner writes the result.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from rollingstar.sensors import build

_INT_COLUMNS = ("t_ns", "row_time_ns", "catalog_id", "npix")


# The optional StarTable columns' "unknown" value, dtype and row width (None: one value per star).
_DEFAULTS = {"flux": (np.nan, float, None), "peak": (np.nan, float, None), "npix": (0, np.int64, None),
             "saturated": (False, bool, None), "snr": (np.nan, float, None), "sigma_px": (np.nan, float, None),
             "cov_xx": (np.nan, float, None), "cov_xy": (np.nan, float, None), "cov_yy": (np.nan, float, None),
             "vx": (np.nan, float, None), "vy": (np.nan, float, None), "catalog_id": (-1, np.int64, None),
             "ref_icrs": (np.nan, float, 3)}


@dataclass(frozen=True, eq=False)
class StarTable:
    """Per-star columns of one frame; every array has length ``n`` (``ref_icrs`` is (n, 3)).

    - ``x, y``: position in pixels (column, row).
    - ``t_ns``: the time the position refers to. Raw centroids refer to the mid-exposure of their
      own row; a rolling-shutter correction moves every star to one common time and says so here.
    - ``row_time_ns``: exposure start of the star's (fractional) centroid row, ``t0 + y * line_delay``.
    - ``flux`` (ADU or electrons above background), ``peak``, ``npix``, ``saturated``, ``snr``.
    - ``sigma_px``: 1-sigma position uncertainty per axis (NaN when unknown); with a 2-D covariance
      it is the derived isotropic equivalent ``sqrt((cov_xx + cov_yy) / 2)``.
    - ``cov_xx, cov_xy, cov_yy``: the 2 x 2 position covariance (px^2) in image axes (NaN when
      unknown; then ``sigma_px`` stands for ``diag(sigma_px^2, sigma_px^2)``). A smeared spot's
      covariance is long along the smear and short across it.
    - ``vx, vy``: image velocity in px/s (NaN when unknown; star-motion filters fill it).
    - ``catalog_id``: identified catalogue star (-1 when unidentified); ``ref_icrs`` its ICRS unit
      vector (NaN rows when unidentified).
    """

    x: np.ndarray
    y: np.ndarray
    t_ns: np.ndarray
    row_time_ns: np.ndarray
    flux: np.ndarray
    peak: np.ndarray
    npix: np.ndarray
    saturated: np.ndarray
    snr: np.ndarray
    sigma_px: np.ndarray
    cov_xx: np.ndarray
    cov_xy: np.ndarray
    cov_yy: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    catalog_id: np.ndarray
    ref_icrs: np.ndarray

    @property
    def n(self) -> int:
        return int(self.x.shape[0])

    def __len__(self) -> int:
        return self.n

    @classmethod
    def build(cls, x, y, t_ns, row_time_ns=None, **columns) -> "StarTable":
        """Make a table from the required columns; the others get their 'unknown' defaults."""
        x = np.asarray(x, dtype=float).reshape(-1)
        n = x.shape[0]
        t_ns = np.broadcast_to(np.asarray(t_ns, dtype=np.int64), (n,)).copy()
        values: dict[str, Any] = {
            "x": x,
            "y": np.asarray(y, dtype=float).reshape(-1),
            "t_ns": t_ns,
            "row_time_ns": t_ns.copy() if row_time_ns is None else np.broadcast_to(np.asarray(row_time_ns, dtype=np.int64), (n,)).copy(),
        }
        unknown = set(columns) - _DEFAULTS.keys()
        if unknown:
            raise TypeError(f"unknown StarTable columns: {sorted(unknown)}")
        for name, (fill, dtype, width) in _DEFAULTS.items():
            shape = (n,) if width is None else (n, width)
            value = columns.get(name)
            if value is None:
                values[name] = np.full(shape, fill, dtype=dtype)
            else:
                arr = np.asarray(value, dtype=dtype)
                values[name] = arr.copy() if arr.shape == shape else np.broadcast_to(arr, shape).copy()
        return cls(**values)

    @classmethod
    def empty(cls) -> "StarTable":
        return cls.build(np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64))

    @classmethod
    def concat(cls, *tables: "StarTable") -> "StarTable":
        """The rows of ``tables``, in order (copies)."""
        return cls(**{f.name: np.concatenate([getattr(t, f.name) for t in tables]) for f in fields(cls)})

    def take(self, index) -> "StarTable":
        """Rows selected by an integer index or boolean mask (copies)."""
        return StarTable(*(np.asarray(getattr(self, name))[index].copy() for name in _STAR_COLUMNS))

    def with_columns(self, **columns) -> "StarTable":
        """A copy with some columns replaced (shapes checked)."""
        for name, value in columns.items():
            old = getattr(self, name)
            if np.shape(value) != old.shape:
                raise ValueError(f"column {name!r}: expected shape {old.shape}, got {np.shape(value)}")
        return replace(self, **{k: np.asarray(v, dtype=getattr(self, k).dtype).copy() for k, v in columns.items()})

    def position_covariance(self, default_sigma_px: float, use_star_sigma: bool = True) -> np.ndarray:
        """Each star's 2 x 2 position covariance (n, 2, 2), px^2: its own ``cov_*`` when finite and
        positive definite, else ``sigma_px^2 I`` when ``sigma_px`` is finite and positive, else
        ``default_sigma_px^2 I``. With ``use_star_sigma=False`` every star gets the default."""
        n = self.n
        cov = np.zeros((n, 2, 2))
        cov[:, 0, 0] = cov[:, 1, 1] = float(default_sigma_px) ** 2
        if not use_star_sigma or n == 0:
            return cov
        sig = self.sigma_px
        iso = np.isfinite(sig) & (sig > 0)
        cov[iso, 0, 0] = cov[iso, 1, 1] = sig[iso] ** 2
        xx, xy, yy = self.cov_xx, self.cov_xy, self.cov_yy
        with np.errstate(invalid="ignore"):
            full = np.isfinite(xx) & np.isfinite(xy) & np.isfinite(yy) & (xx > 0) & (yy > 0) & (xx * yy - xy * xy > 0)
        cov[full, 0, 0], cov[full, 0, 1], cov[full, 1, 0], cov[full, 1, 1] = xx[full], xy[full], xy[full], yy[full]
        return cov

    @property
    def identified(self) -> np.ndarray:
        """Boolean mask of stars with a catalogue identification."""
        return self.catalog_id >= 0


_STAR_COLUMNS = tuple(f.name for f in fields(StarTable))  # in the constructor's order


@dataclass(frozen=True)
class AttitudeEstimate:
    """One attitude estimate.

    ``q_xyzw`` is the camera-to-ICRS rotation (scalar-last); ``covariance_rad2`` the 3x3
    covariance of the attitude error in the camera frame (rad^2), or None. ``valid`` is False when
    the estimate could not be made (``reason`` says why); then ``q_xyzw`` is NaN.
    ``gyro_bias_rad_s``: the gyro bias (camera frame, rad/s) estimated with the attitude by filters
    and smoothers that estimate one (``mekf``, ``gtsam``), else None.
    """

    t_ns: int
    q_xyzw: np.ndarray
    n_stars: int
    valid: bool = True
    reason: str = ""
    covariance_rad2: np.ndarray | None = None
    gyro_bias_rad_s: np.ndarray | None = None

    @property
    def rotation(self) -> Rotation:
        return Rotation.from_quat(self.q_xyzw)

    @classmethod
    def invalid(cls, t_ns: int, n_stars: int, reason: str) -> "AttitudeEstimate":
        return cls(t_ns=int(t_ns), q_xyzw=np.full(4, np.nan), n_stars=int(n_stars), valid=False, reason=reason)


@dataclass(frozen=True)
class RateEstimate:
    """Angular velocity of the camera in the camera frame (rad/s) at ``t_ns``."""

    t_ns: int
    omega_rad_s: np.ndarray
    valid: bool = True
    reason: str = ""
    covariance: np.ndarray | None = None
    iterations: int | None = None


@dataclass(frozen=True)
class GyroSamples:
    """Gyro samples (camera frame, rad/s) received since the previous frame."""

    t_ns: np.ndarray
    omega_rad_s: np.ndarray

    @classmethod
    def empty(cls) -> "GyroSamples":
        return cls(np.zeros(0, dtype=np.int64), np.zeros((0, 3)))


@dataclass(frozen=True)
class TruthSamples:
    """Truth attitude samples of a simulated recording (``/truth/attitude``) around one frame.

    Only filled by the runner for stages that declare ``needs_truth = True`` (oracle baselines such
    as ``request`` with ``rate_source: truth``); ``q_xyzw`` camera-to-ICRS, ``omega_rad_s`` the body
    rate (camera frame, rad/s), both at ``t_ns``.
    """

    t_ns: np.ndarray
    q_xyzw: np.ndarray
    omega_rad_s: np.ndarray


@dataclass(frozen=True)
class IdentificationCheck:
    """How likely a frame's identified stars are chance coincidences (identifiers/integrity.py).

    ``false_match_prob``: the probability that ``n_matched`` or more of ``n_detections`` random
    detections would fall within ``gate_px`` of one of the ``n_predicted`` catalogue stars on the
    detector; ``bound`` the largest accepted; ``passed`` whether it was accepted; ``reason`` why
    not ("" when passed); ``chi2_dof`` the fit's normalised residual (chi^2 per degree of freedom
    with the stars' stated position covariances, ``dof`` degrees of freedom; NaN without them);
    ``scatter_scale`` the variance factor of the majority of the stars (robust: from the median
    normalised residual) and ``n_outliers`` the stars beyond 5 sigma of their covariance.
    """

    false_match_prob: float
    n_detections: int
    n_matched: int
    n_predicted: int
    gate_px: float
    bound: float
    passed: bool
    reason: str = ""
    chi2_dof: float = float("nan")
    dof: int = 0
    scatter_scale: float = float("nan")
    n_outliers: int = 0


@dataclass(frozen=True)
class FrameData:
    """Everything the stages know about one frame.

    ``image`` is the raw frame (H, W) when the recording has images; ``stars`` the current star
    table (detections, then identified, filtered, corrected stars); ``unmatched`` the detections an
    identifier could not match; ``attitudes`` one or more estimates (several per frame for
    sub-frame solvers); ``flags`` short machine-readable notes (e.g. ``"too_few_stars"``);
    ``truth`` the recording's truth samples of this frame, present only when a stage of the
    pipeline declares ``needs_truth`` (None otherwise, and always on real data);
    ``camera`` the camera model an identifier fitted on this frame (focal length, principal point,
    distortion), which later stages use instead of the sensor context's (None: the context's, see
    :func:`frame_camera`); ``identification`` the integrity check of the frame's identified stars
    (:class:`IdentificationCheck`, None before an identifier ran); ``psf_sigma_px`` the Gaussian PSF
    sigma (px) a stage measured from the camera's pixels (None: none did), which earlier stages may
    take for the next frame (:meth:`~rollingstar.estimators.plugin.Plugin.update_prior`).
    """

    index: int
    t0_ns: int
    image: np.ndarray | None = None
    stars: StarTable | None = None
    unmatched: StarTable | None = None
    gyro: GyroSamples = field(default_factory=GyroSamples.empty)
    attitudes: tuple[AttitudeEstimate, ...] = ()
    rate: RateEstimate | None = None
    flags: tuple[str, ...] = ()
    truth: TruthSamples | None = None
    camera: Any = None
    identification: "IdentificationCheck | None" = None
    psf_sigma_px: float | None = None

    def evolve(self, **changes) -> "FrameData":
        """A new frame with some fields replaced (frames are immutable). ``dataclasses.replace``
        without its re-run of ``__init__``: stages evolve each frame a dozen times."""
        unknown = changes.keys() - _FRAME_FIELDS
        if unknown:
            raise TypeError(f"FrameData has no field(s) {sorted(unknown)}")
        new = object.__new__(FrameData)
        new.__dict__.update(self.__dict__)
        new.__dict__.update(changes)
        return new

    def flagged(self, flag: str) -> "FrameData":
        return self.evolve(flags=self.flags + (flag,))


_FRAME_FIELDS = frozenset(f.name for f in fields(FrameData))


@dataclass(frozen=True)
class SensorContext:
    """What a stage may know about the sensor, given once before the first frame.

    Built by the runner from the recording's declared sensor model (metadata). ``catalog`` is a
    :class:`rollingstar.sensors.catalog.StarCatalog`; ``initial_attitude`` a prior (camera-to-ICRS) when the
    recording or config declares one. ``gain_e_per_adu``: the detector's conversion gain (electrons
    per ADU) when the sensor model states it (the centroiders' shot-noise term), else None.
    """

    camera: Any  # rollingstar.sensors.camera.PinholeCamera
    timing: Any  # rollingstar.sensors.timing.DetectorTiming
    catalog: Any  # rollingstar.sensors.catalog.StarCatalog
    initial_attitude: Rotation | None = None
    centroid_sigma_px: float | None = None
    bit_depth: int | None = None
    gain_e_per_adu: float | None = None

    @classmethod
    def from_scenario(cls, cfg, catalog=None) -> SensorContext:
        """The context the stages receive for a recording made with scenario ``cfg``
        (a :class:`rollingstar.sensors.scenario.ScenarioConfig`); ``catalog`` defaults to the
        scenario's own."""
        camera = build.build_camera(cfg)
        return cls(
            camera=camera,
            timing=build.build_timing(cfg),
            catalog=catalog if catalog is not None else build.build_catalog(cfg, camera),
            initial_attitude=build.initial_attitude(cfg),
            centroid_sigma_px=cfg.noise.centroid_sigma_px if cfg.level == "centroid" else None,
            bit_depth=cfg.image.bit_depth if cfg.level == "image" else None,
            gain_e_per_adu=cfg.image.gain_e_per_adu if cfg.level == "image" else None,
        )


def frame_camera(frame: FrameData, context):
    """The camera model for ``frame``: the one an identifier fitted on it, else the context's."""
    return frame.camera if frame.camera is not None else context.camera


#: Centroid 1-sigma (px per axis) the estimators assume when neither the stars, their parameters
#: nor the sensor context state one.
DEFAULT_CENTROID_SIGMA_PX = 0.05


def default_sigma_px(sigma_px: float | None, context) -> float:
    """The centroid sigma (px) for stars without their own: ``sigma_px`` (a plugin parameter) when
    given, else the context's non-zero ``centroid_sigma_px``, else :data:`DEFAULT_CENTROID_SIGMA_PX`."""
    if sigma_px is not None:
        return float(sigma_px)
    if getattr(context, "centroid_sigma_px", None):
        return float(context.centroid_sigma_px)
    return DEFAULT_CENTROID_SIGMA_PX
