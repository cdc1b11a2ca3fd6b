"""Tracking identifier: match detections to catalogue stars predicted from a prior attitude and body motion."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numba import njit
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from rollingstar.estimators.centroiders.cog import median
from rollingstar.estimators.centroiders.window_gyro import FastGyroIntegrator
from rollingstar.estimators.data import FrameData, default_sigma_px
from rollingstar.estimators.identifiers.base import Identifier
from rollingstar.sensors.conventions import S_PER_NS, attitude_from_radec_roll
from rollingstar.sensors.so3 import rotate_by_rotvec, skew, wahba

ARCSEC = np.pi / (180.0 * 3600.0)
#: Extra radius (rad) of the catalogue cone the tracker caches and reuses between frames.
CONE_SLACK_RAD = np.radians(1.0)
#: Largest detections x predictions product matched by all pairwise distances (else k-d trees).
BRUTE_FORCE_PAIRS = 40_000
#: Chi-square (3 dof) above which a rate change between estimates is taken as an angular acceleration (99.9 %).
ACCELERATION_CHI2 = float(chi2.ppf(0.999, 3))


class RaDecRoll(BaseModel):
    """A camera-to-ICRS attitude given as boresight (ra, dec) and roll, degrees (see conventions)."""

    model_config = ConfigDict(extra="forbid")

    ra_deg: float
    dec_deg: float = Field(ge=-90.0, le=90.0)
    roll_deg: float = 0.0

    def rotation(self) -> Rotation:
        return attitude_from_radec_roll(self.ra_deg, self.dec_deg, self.roll_deg)


class TrackingParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    initial_attitude: RaDecRoll | None = Field(
        default=None, description="Prior attitude; None: the sensor context's (recording's) initial attitude.")
    gate_px: float = Field(default=10.0, gt=0, description="Largest detection-to-prediction distance of a match (px): "
                           "the whole gate while the prior's covariance is unknown (or with gate: fixed), an upper "
                           "bound of the covariance gate after.")
    margin_deg: float = Field(default=0.5, ge=0, description="Extra cone radius beyond the detector's half diagonal (deg).")
    magnitude_limit: float | None = Field(default=None, description="Only predict stars at most this magnitude; None: all.")
    extrapolate: bool = Field(default=True, description="Predict with the body motion since the last estimate (rate, "
                              "angular acceleration, gyro; see the class docstring).")
    refine: bool = Field(default=True, description="Fit the attitude to the first matches and match again (drops mismatches).")
    refine_gate_px: float = Field(default=2.0, gt=0, description="Smallest gate of the second matching pass (px).")
    gate: Literal["covariance", "fixed"] = Field(
        default="covariance", description="'covariance': once a prior with a covariance is known, match within the "
        "chi-square gate of each prediction's pixel covariance plus the detection's own (Mahalanobis distance), "
        "never beyond gate_px; 'fixed': always the gate_px circle.")
    gate_probability: float = Field(default=0.9999, gt=0, lt=1, description="Probability mass of the chi-square "
                                    "gate (2 degrees of freedom): 0.9999 is 4.3 sigma.")
    attitude_sigma_arcsec: float = Field(default=10.0, ge=0, description="Per-axis attitude error (arcsec) added to "
                                         "an estimate's stated covariance (what the estimate does not state); the "
                                         "whole attitude covariance of an estimate without one.")
    rate_sigma_deg_s: float = Field(default=0.02, ge=0, description="Per-axis body-rate error (deg/s) added to the "
                                    "rate's covariance (the whole of it when the rate comes without one; also the gyro's).")
    accel_sigma_deg_s2: float = Field(default=2.0, ge=0, description="Per-axis unmodelled angular acceleration "
                                      "(deg/s^2) the gate allows for.")
    acceleration: bool = Field(default=True, description="Extrapolate with the angular acceleration between the last "
                               "two rates when it is significant (chi-square, 99.9 %) against their covariances.")
    use_gyro: bool = Field(default=True, description="Propagate with the frames' gyro samples when they carry any.")
    row_times: bool = Field(default=True, description="Predict each star at its own row's mid-exposure time "
                            "(rolling shutter); False: every star at the frame's reference time.")


@dataclass
class BodyMotion:
    """The camera's rotation since ``origin_ns``: ``R(t) = R(origin) Exp(phi(t))`` (camera frame).

    ``phi(t) = omega dt + alpha dt^2 / 2`` with ``dt = t - origin``; with a ``gyro`` integrator
    (:class:`rollingstar.sensors.gyro.GyroIntegrator`) instead the integrated gyro angle minus
    ``bias dt``. ``origin_ns`` None: no motion is known (``phi = 0``).
    """

    origin_ns: int | None = None
    omega: np.ndarray = field(default_factory=lambda: np.zeros(3))
    alpha: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro: object = None
    bias: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def static(self) -> bool:
        return self.origin_ns is None or (self.gyro is None and not np.any(self.omega) and not np.any(self.alpha))

    def dt(self, t_ns) -> np.ndarray:
        """Seconds from the origin (zeros without one)."""
        t = np.asarray(t_ns, dtype=np.int64)
        return np.zeros(t.shape) if self.origin_ns is None else (t - self.origin_ns) * S_PER_NS

    def phi(self, t_ns) -> np.ndarray:
        """Body rotation vectors (..., 3) from the origin to ``t_ns``."""
        t = np.asarray(t_ns, dtype=np.int64)
        dt = self.dt(t)[..., None]
        if self.origin_ns is None:
            return np.zeros(t.shape + (3,))
        if self.gyro is not None:
            return self.gyro.angle(t) - self.gyro.angle(np.int64(self.origin_ns)) - self.bias * dt
        return self.omega * dt + 0.5 * self.alpha * dt * dt


def predict_at_rows(w0: np.ndarray, motion: BodyMotion, project, timing, t0_ns: int, row_times: bool = True,
                    iterations: int = 2, t_start: np.ndarray | None = None):
    """Pixel positions of directions ``w0`` (camera frame at the motion's origin, (n, 3)) seen at their
    own row's mid-exposure: the fixed point ``t = t0 + y(t) ld + E / 2``, ``w(t) = Exp(phi(t))^T w0``,
    started at ``t_start`` (default: the frame's reference time); each iteration shrinks the time
    error by ``|v_y| ld`` (0.03 at 10 deg/s on he2021a). Returns ``(x, y, front, t_ns, w)``, ``t_ns``
    the times the positions refer to.
    """
    n = w0.shape[0]
    t = np.full(n, timing.frame_reference_ns(t0_ns), dtype=np.int64) if t_start is None else t_start
    rows_max = float(timing.rows - 1)
    steps = iterations if row_times and timing.effective_line_delay_ns > 0 and not motion.static else 0
    for k in range(steps + 1):
        w = w0 if motion.static else rotate_by_rotvec(-motion.phi(t), w0)
        x, y, front = project(w)
        if k < steps:
            t = timing.row_mid_exposure_ns(t0_ns, np.clip(np.nan_to_num(y, nan=rows_max / 2), 0.0, rows_max))
    return x, y, front, t, w


def prediction_covariance(camera, w: np.ndarray, dt: np.ndarray, att_cov: np.ndarray, rate_cov: np.ndarray,
                          accel_cov: np.ndarray) -> np.ndarray:
    """Pixel covariance (n, 2, 2) of predictions ``w`` made ``dt`` seconds from an attitude with
    covariance ``att_cov``, a rate with ``rate_cov`` and an unknown acceleration with ``accel_cov``
    (all 3 x 3, camera frame): ``J (P_att + P_rate dt^2 + P_accel dt^4 / 4) J^T`` with
    ``J = P(w) [w]x`` (a body rotation ``delta`` moves ``w`` by ``[w]x delta``)."""
    jac = camera.projection_jacobian(w) @ skew(w)
    d2 = (dt * dt)[:, None, None]
    p = att_cov[None] + rate_cov[None] * d2 + 0.25 * accel_cov[None] * d2 * d2
    return jac @ p @ np.swapaxes(jac, 1, 2)


def match_mahalanobis(dpos: np.ndarray, dcov: np.ndarray, ppos: np.ndarray, pcov: np.ndarray, chi2_gate: float,
                      gate_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours in Mahalanobis distance: (detection indices, prediction indices).

    A pair (i, j) is a candidate when ``|d_i - p_j| <= gate_px`` and
    ``r^T (C_i + S_j)^-1 r <= chi2_gate`` (``C`` detection, ``S`` prediction covariances); it is
    matched when ``j`` is ``i``'s nearest candidate and ``i`` is ``j``'s (ties go to the lower
    index). Hence one detection per star and one star per detection, independent of order.
    """
    empty = np.zeros(0, dtype=np.intp)
    fin = np.flatnonzero(np.isfinite(dpos).all(axis=1))
    if fin.size == 0 or ppos.shape[0] == 0:
        return empty, empty
    if fin.size * ppos.shape[0] <= BRUTE_FORCE_PAIRS:  # every pair at once (a frame's few tens of stars)
        i, j = _mutual_nearest(np.ascontiguousarray(dpos[fin], dtype=float), np.ascontiguousarray(dcov[fin], dtype=float),
                               np.ascontiguousarray(ppos, dtype=float), np.ascontiguousarray(pcov, dtype=float),
                               float(chi2_gate), float(gate_px))
        return fin[i], j
    pairs = cKDTree(dpos[fin]).sparse_distance_matrix(cKDTree(ppos), gate_px, output_type="ndarray")
    if pairs.size == 0:
        return empty, empty
    i, j = fin[pairs["i"]], pairs["j"].astype(np.intp)
    r = dpos[i] - ppos[j]
    s = dcov[i] + pcov[j]
    det = s[:, 0, 0] * s[:, 1, 1] - s[:, 0, 1] * s[:, 1, 0]
    d2 = (s[:, 1, 1] * r[:, 0] ** 2 - 2.0 * s[:, 0, 1] * r[:, 0] * r[:, 1] + s[:, 0, 0] * r[:, 1] ** 2) / det
    keep = d2 <= chi2_gate
    i, j, d2 = i[keep], j[keep], d2[keep]
    order = np.lexsort((j, i, d2))
    i, j = i[order], j[order]
    best_i = np.unique(i, return_index=True)[1]
    best_j = np.unique(j, return_index=True)[1]
    both = np.intersect1d(best_i, best_j)
    out = np.argsort(i[both], kind="stable")
    return i[both][out], j[both][out]


@njit(cache=True, nogil=True)
def _mutual_nearest(dpos, dcov, ppos, pcov, chi2_gate, gate_px):  # pragma: no cover - compiled
    """:func:`match_mahalanobis` over every pair: the candidate test and the mutual nearest
    neighbours (first index on ties, as ``numpy.argmin``). Compiled: a tracked frame matches
    twice, and the pairwise arrays' dozen numpy temporaries cost more than the arithmetic."""
    n, m = dpos.shape[0], ppos.shape[0]
    d2 = np.full((n, m), np.inf)
    for a in range(n):
        for b in range(m):
            rx, ry = dpos[a, 0] - ppos[b, 0], dpos[a, 1] - ppos[b, 1]
            s00, s01 = dcov[a, 0, 0] + pcov[b, 0, 0], dcov[a, 0, 1] + pcov[b, 0, 1]
            s10, s11 = dcov[a, 1, 0] + pcov[b, 1, 0], dcov[a, 1, 1] + pcov[b, 1, 1]
            d = (s11 * rx * rx - 2.0 * s01 * rx * ry + s00 * ry * ry) / (s00 * s11 - s01 * s10)
            if not (d > chi2_gate or rx * rx + ry * ry > gate_px * gate_px):
                d2[a, b] = d
    best_pred = np.zeros(n, dtype=np.intp)
    for a in range(n):
        for b in range(1, m):
            if d2[a, b] < d2[a, best_pred[a]]:
                best_pred[a] = b
    best_det = np.zeros(m, dtype=np.intp)
    for b in range(m):
        for a in range(1, n):
            if d2[a, b] < d2[best_det[b], b]:
                best_det[b] = a
    keep = np.zeros(n, dtype=np.bool_)
    for a in range(n):
        keep[a] = np.isfinite(d2[a, best_pred[a]]) and best_det[best_pred[a]] == a
    rows = np.flatnonzero(keep)
    return rows, best_pred[rows]


class TrackingIdentifier(Identifier):
    """Identification by tracking: predict the catalogue into the image from the previous attitude and motion.

    Prediction: catalogue stars within ``camera.half_diagonal_rad + margin`` (plus the frame's sweep)
    of the predicted boresight (``StarCatalog.cone``), optionally magnitude-limited, rotated into
    the camera frame and projected with the pinhole model (he2021b eq 2), each at **its own row's
    mid-exposure** ``t = t0 + y ld + E / 2`` (a fixed point in ``y``, :func:`predict_at_rows`),
    with the attitude ``R(t) = R_last Exp(phi(t))`` propagated from the last estimate
    (:class:`BodyMotion`): by the integrated gyro when the frames carry gyro samples (minus the
    estimate's gyro bias when it has one), else by ``phi = omega dt + alpha dt^2 / 2`` with the
    body rate ``omega`` of the frame's rate estimate (``frame.rate``) or, without one, of the last
    two valid attitude estimates, ``omega = Log(R0^T R1) / (t1 - t0)``, and the angular
    acceleration ``alpha`` between the last two rates when it is significant against their
    covariances (``acceleration``). Predictions are kept when in front of the camera and within
    ``gate_px`` of the detector.

    Gate: while the prior has no covariance (the configured or recorded initial attitude) or with
    ``gate: fixed``, a detection matches within ``gate_px``. Once an estimate has been passed back,
    each prediction carries the pixel covariance :func:`prediction_covariance` of the attitude
    (the estimate's stated covariance plus ``attitude_sigma_arcsec^2``), the rate (its covariance,
    else from the two estimates', plus ``rate_sigma_deg_s^2``) times ``dt^2`` and an unmodelled
    acceleration (``accel_sigma_deg_s2``) times ``dt^4 / 4``; a detection with its own 2 x 2
    covariance (``StarTable.position_covariance``) matches within the chi-square gate
    ``gate_probability`` (2 degrees of freedom) of the sum, never beyond ``gate_px``. The gate
    needs a rate (a rate estimate, two attitude estimates or the gyro; without one the prediction
    ignores the motion and the ``gate_px`` circle is used), and when it keeps fewer than half the
    stars it could (a prediction off its stated covariance: an estimator that understates its
    errors, a rate outlier) the frame is matched again within ``gate_px``.

    Matching: mutual nearest neighbours (Euclidean, ``scipy.spatial.cKDTree`` both ways, or
    Mahalanobis, :func:`match_mahalanobis`): a detection is matched to star ``j`` iff ``j`` is its
    nearest candidate and it is ``j``'s nearest detection. Hence at most one detection per star
    and one star per detection, and the result does not depend on the detections' order (barring
    exact distance ties).

    Output: ``frame.stars`` = matched detections (in their input order) with ``catalog_id`` and
    ``ref_icrs`` (catalogue unit vector at the catalogue epoch); ``frame.unmatched`` = the rest.

    Prior: ``params.initial_attitude`` else ``context.initial_attitude`` at :meth:`setup` (without
    either, setup raises: use a lost-in-space identifier). **The prior is advanced by the runner**:
    after all stages of a frame have run it calls :meth:`update_prior` with the final frame, and the
    last valid attitude estimate becomes the next frame's prior, its rate estimate the next rate
    (the identifier runs before the solver, so it cannot see the estimates of the frame it is
    identifying). ``extrapolate: false`` predicts every frame at the last attitude.

    Verification (``refine``): with at least three first-pass matches, the attitude that best fits
    them, each detection referred to the motion's origin by its own time (Wahba's problem, SVD,
    :func:`wahba`), re-predicts the catalogue, and matching runs again with the gate
    ``max(refine_gate_px, 5 * 1.4826 * median residual)`` (at most ``gate_px``): a detection
    matched to a neighbour of its true star leaves a residual of the neighbours' separation and is
    dropped.

    Cost: about 0.7 ms of CPU per frame of 38 stars (he2021a sensor, 3-10 deg/s, one core): the
    catalogue cone is cached with ``CONE_SLACK_RAD`` of slack and
    reused while the boresight stays within it; a frame's few tens of stars are matched over all
    pairs (k-d trees beyond ``BRUTE_FORCE_PAIRS``).
    """

    name = "tracking"
    Params = TrackingParams

    def setup(self, context) -> None:
        super().setup(context)
        if context.catalog is None:
            raise ValueError("the 'tracking' identifier needs a star catalogue in the sensor context")
        if self.params.initial_attitude is not None:
            prior = self.params.initial_attitude.rotation()
        elif context.initial_attitude is not None:
            prior = context.initial_attitude
        else:
            raise ValueError(
                "the 'tracking' identifier needs a prior attitude: set params.initial_attitude "
                "{ra_deg, dec_deg, roll_deg} or use a recording that declares an initial attitude; "
                "otherwise a lost-in-space identifier is needed")
        self._last_attitude: Rotation = prior
        self._last_t_ns: int | None = None
        self._att_cov: np.ndarray | None = None  # None: unknown (the cold gate_px circle)
        self._rate_rad_s = np.zeros(3)
        self._rate_cov = np.zeros((3, 3))
        self._rate_t_ns: int | None = None  # None: no rate known yet
        self._rate_measured = False  # the held rate came from a rate estimate (not from two attitudes)
        self._prior_estimated = False  # the prior is an estimate passed back (not a seed or the initial attitude)
        self._alpha = np.zeros(3)
        self._gyro: FastGyroIntegrator | None = None
        self._bias = np.zeros(3)
        cam = context.camera
        self._radius = cam.half_diagonal_rad + np.radians(self.params.margin_deg)
        catalog = context.catalog
        self._cat_sel = (np.arange(len(catalog.ids)) if self.params.magnitude_limit is None
                         else np.flatnonzero(catalog.magnitude <= self.params.magnitude_limit))
        self._cat_keep = np.zeros(len(catalog.ids), dtype=bool)
        self._cat_keep[self._cat_sel] = True
        self._chi2_gate = float(chi2.ppf(self.params.gate_probability, 2))
        self._det_sigma = default_sigma_px(None, context)

    @property
    def prior(self) -> Rotation:
        """The attitude (camera-to-ICRS) the next frame's predictions are made from."""
        return self._last_attitude

    def seed(self, attitude: Rotation, t_ns: int, omega_rad_s=None) -> None:
        """Start from ``attitude`` at ``t_ns`` (and the body rate ``omega_rad_s``, camera frame, when
        known; else the rate held so far), its covariance unknown: e.g. a lost-in-space solution."""
        self._last_attitude, self._last_t_ns, self._att_cov = attitude, int(t_ns), None
        self._prior_estimated = False
        if omega_rad_s is not None and np.all(np.isfinite(omega_rad_s)):
            self._rate_rad_s, self._rate_t_ns, self._alpha = np.asarray(omega_rad_s, dtype=float), int(t_ns), np.zeros(3)
            self._rate_measured = False

    def update_prior(self, frame: FrameData) -> bool:
        """Take the last valid estimate of ``frame.attitudes`` as the next prior, and the frame's rate
        (or the rate between the last two estimates) as the next rate; True if an estimate was found.

        The runner calls this with each frame after all of the frame's stages have run.
        """
        for est in reversed(frame.attitudes):
            if est.valid and np.all(np.isfinite(est.q_xyzw)):
                new = Rotation.from_quat(est.q_xyzw)
                floor = (self.params.attitude_sigma_arcsec * ARCSEC) ** 2 * np.eye(3)
                stated = est.covariance_rad2
                cov = floor + (np.asarray(stated) if stated is not None and np.all(np.isfinite(stated)) else 0.0)
                rate = frame.rate
                if rate is not None and rate.valid and np.all(np.isfinite(rate.omega_rad_s)):
                    rcov = rate.covariance if rate.covariance is not None and np.all(np.isfinite(rate.covariance)) else 0.0
                    self._set_rate(int(rate.t_ns), np.asarray(rate.omega_rad_s, dtype=float), rcov, measured=True)
                elif self._prior_estimated and est.t_ns > self._last_t_ns:
                    dt = (int(est.t_ns) - self._last_t_ns) * S_PER_NS
                    self._set_rate((int(est.t_ns) + self._last_t_ns) // 2,
                                   (self._last_attitude.inv() * new).as_rotvec() / dt, (self._att_cov + cov) / dt**2)
                if est.gyro_bias_rad_s is not None and np.all(np.isfinite(est.gyro_bias_rad_s)):
                    self._bias = np.asarray(est.gyro_bias_rad_s, dtype=float)
                self._last_attitude, self._last_t_ns, self._att_cov = new, int(est.t_ns), cov
                self._prior_estimated = True
                return True
        return False

    def _set_rate(self, t_ns: int, omega: np.ndarray, cov, measured: bool = False) -> None:
        """Hold ``omega`` (at ``t_ns``, covariance ``cov`` plus the floor) and, between two rate
        estimates (``measured``; a rate from two attitudes is a first difference, its change a
        second difference too noisy to extrapolate with), the angular acceleration when significant
        (chi-square, 3 dof, 99.9 %)."""
        cov = cov + (np.radians(self.params.rate_sigma_deg_s)) ** 2 * np.eye(3)
        self._alpha = np.zeros(3)
        if (self.params.acceleration and measured and self._rate_measured and self._rate_t_ns is not None
                and t_ns > self._rate_t_ns):
            dt = (t_ns - self._rate_t_ns) * S_PER_NS
            alpha = (omega - self._rate_rad_s) / dt
            c_alpha = (cov + self._rate_cov) / dt**2
            if alpha @ np.linalg.solve(c_alpha, alpha) > ACCELERATION_CHI2:
                self._alpha = alpha
        self._rate_rad_s, self._rate_cov, self._rate_t_ns, self._rate_measured = omega, cov, t_ns, measured

    def motion(self) -> BodyMotion:
        """The body motion since the last estimate (:class:`BodyMotion`; static without ``extrapolate``)."""
        if not self.params.extrapolate or self._last_t_ns is None:
            return BodyMotion()
        if self._gyro is not None:
            return BodyMotion(self._last_t_ns, gyro=self._gyro, bias=self._bias)
        t_rate = self._rate_t_ns if self._rate_t_ns is not None else self._last_t_ns
        omega = self._rate_rad_s + self._alpha * (self._last_t_ns - t_rate) * S_PER_NS
        return BodyMotion(self._last_t_ns, omega=omega, alpha=self._alpha)

    def prior_at(self, t_ns: int) -> Rotation:
        """The prior propagated to ``t_ns`` with :meth:`motion` (no change without a motion)."""
        motion = self.motion()
        if motion.static:
            return self._last_attitude
        return self._last_attitude * Rotation.from_rotvec(motion.phi(np.int64(t_ns)))

    def predict(self, attitude: Rotation | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Catalogue indices and predicted pixel positions ``(idx, x, y)`` for ``attitude`` (default: prior), motionless."""
        R = self._last_attitude if attitude is None else attitude
        cam = self.context.camera
        idx = self._cone(R.apply([0.0, 0.0, 1.0]), self._radius)
        w = self.context.catalog.unit_icrs[idx] @ R.as_matrix() if idx.size else np.zeros((0, 3))  # R^T r
        x, y, front = cam.project(w)
        ok = front & cam.contains(x, y, margin_px=-self.params.gate_px)
        return idx[ok], x[ok], y[ok]

    def _cone(self, boresight: np.ndarray, radius: float) -> np.ndarray:
        idx = np.asarray(self.context.catalog.cone(boresight, radius), dtype=np.intp)
        return idx[self._cat_keep[idx]]

    def _cone_cached(self, boresight: np.ndarray, radius: float) -> np.ndarray:
        """:meth:`_cone` with ``CONE_SLACK_RAD`` more radius, reused while the boresight stays within
        the slack of the cached one (the stars beyond the detector are dropped by the projection)."""
        cached = getattr(self, "_cone_cache", None)
        if cached is not None and cached[1] >= radius and np.dot(cached[0], boresight) >= np.cos(cached[1] - radius):
            return cached[2]
        idx = self._cone(boresight, radius + CONE_SLACK_RAD)
        self._cone_cache = (np.asarray(boresight, dtype=float), radius + CONE_SLACK_RAD, idx)
        return idx

    def predict_frame(self, t0_ns: int, attitude: Rotation | np.ndarray | None = None, motion: BodyMotion | None = None,
                      t_start: np.ndarray | None = None, stars: np.ndarray | None = None):
        """The catalogue stars the frame starting at ``t0_ns`` images, each at its own row time:
        ``(idx, x, y, t_ns, w)`` for ``attitude`` (a Rotation or its 3 x 3 matrix) at the origin of
        ``motion`` (defaults: the prior and :meth:`motion`), ``w`` the camera-frame directions at those times. ``stars`` and
        ``t_start``: the catalogue indices to project (instead of a cone query) and their first
        times, e.g. of a prediction for an attitude arcseconds away (no fixed-point iteration then: a
        star moved by ``d`` px changes its time by ``d ld``, its position by ``d |v_y| ld``)."""
        R = self._last_attitude if attitude is None else attitude
        R = R.as_matrix() if isinstance(R, Rotation) else R
        motion = self.motion() if motion is None else motion
        cam, timing = self.context.camera, self.context.timing
        if stars is None:
            ends = np.array([t0_ns, timing.frame_reference_ns(t0_ns), timing.frame_end_ns(t0_ns)], dtype=np.int64)
            phi = motion.phi(ends)
            sweep = float(max(np.linalg.norm(phi[0] - phi[1]), np.linalg.norm(phi[2] - phi[1])))
            center = R @ rotate_by_rotvec(phi[1], np.array([0.0, 0.0, 1.0]))
            stars = self._cone_cached(center, self._radius + sweep)
        idx = stars
        w0 = self.context.catalog.unit_icrs[idx] @ R  # R^T r for every star
        x, y, front, t, w = predict_at_rows(w0, motion, cam.project, timing, t0_ns, self.params.row_times,
                                            iterations=2 if t_start is None else 0, t_start=t_start)
        ok = front & cam.contains(x, y, margin_px=-self.params.gate_px)
        return idx[ok], x[ok], y[ok], t[ok], w[ok]

    def process(self, frame: FrameData) -> FrameData:
        det = frame.stars
        if det is None:
            raise ValueError(f"frame {frame.index}: no detections (frame.stars is None); "
                             "the 'tracking' identifier needs a centroider or centroid-level recording before it")
        self._add_gyro(frame)
        motion = self.motion()
        idx, px, py, pt, w = self.predict_frame(frame.t0_ns, motion=motion)
        det = _imageable(det, self.context.camera)
        matched_det, matched_star = self._first_match(det, px, py, pt, w, motion)
        if self.params.refine and matched_det.size >= 3:
            fit = self._refit(det, matched_det, idx[matched_star], motion)
            idx, px, py, _, _ = self.predict_frame(frame.t0_ns, fit, motion, t_start=pt, stars=idx)
            first = self._match(det, px, py, self.params.gate_px)
            resid = np.hypot(det.x[first[0]] - px[first[1]], det.y[first[0]] - py[first[1]])
            gate = max(self.params.refine_gate_px, 5.0 * 1.4826 * median(resid)) if resid.size else self.params.gate_px
            matched_det, matched_star = self._match(det, px, py, min(gate, self.params.gate_px))
        det = frame.stars  # the detections as given (those no direction images were only kept from matching)
        n = det.n
        cat_idx = idx[matched_star]
        catalog = self.context.catalog
        stars = det.take(matched_det).with_columns(
            catalog_id=catalog.ids[cat_idx], ref_icrs=catalog.unit_icrs[cat_idx])
        rest = np.ones(n, dtype=bool)
        rest[matched_det] = False
        flags = frame.flags if idx.size else frame.flags + ("no_catalog_stars_in_view",)
        return frame.evolve(stars=stars, unmatched=det.take(rest), flags=flags)

    def _add_gyro(self, frame: FrameData) -> None:
        """Feed the frame's gyro samples to the integrator the motion is propagated with."""
        if not self.params.use_gyro or frame.gyro is None or len(frame.gyro.t_ns) == 0:
            return
        if self._gyro is None:
            self._gyro = FastGyroIntegrator()
        self._gyro.add(frame.gyro)
        if self._last_t_ns is not None:
            self._gyro.trim(self._last_t_ns)

    def _first_match(self, det, px, py, pt, w, motion: BodyMotion) -> tuple[np.ndarray, np.ndarray]:
        """The first matching pass: the covariance gate once the prior's and the rate's covariances
        are known (else, or when it keeps fewer than half the stars it could, the gate_px circle)."""
        gyro = motion.gyro is not None
        if self.params.gate == "fixed" or self._att_cov is None or not (gyro or self._rate_t_ns is not None):
            return self._match(det, px, py, self.params.gate_px)
        rad2 = np.radians(1.0) ** 2
        rate_cov = (np.radians(self.params.rate_sigma_deg_s) ** 2 * np.eye(3)) if gyro else self._rate_cov
        pcov = prediction_covariance(self.context.camera, w, motion.dt(pt), self._att_cov, rate_cov,
                                     self.params.accel_sigma_deg_s2 ** 2 * rad2 * np.eye(3))
        dcov = det.position_covariance(self._det_sigma)
        d, s = match_mahalanobis(np.column_stack([det.x, det.y]), dcov, np.column_stack([px, py]), pcov,
                                 self._chi2_gate, self.params.gate_px)
        possible = min(int(np.count_nonzero(np.isfinite(det.x) & np.isfinite(det.y))), px.size)
        if d.size < max(3, possible // 2):  # a prediction off its stated covariance: the cold gate
            return self._match(det, px, py, self.params.gate_px)
        return d, s

    def _refit(self, det, matched_det: np.ndarray, cat_idx: np.ndarray, motion: BodyMotion) -> np.ndarray:
        """The attitude at the motion's origin that best fits the matches, each detection referred
        back by its own time: ``R^T r_i = Exp(phi(t_i)) b_i``."""
        body = self.context.camera.unproject(det.x[matched_det], det.y[matched_det])
        if not motion.static:
            body = rotate_by_rotvec(motion.phi(det.t_ns[matched_det]), body)
        return wahba(self.context.catalog.unit_icrs[cat_idx], body)

    @staticmethod
    def _match(det, px, py, gate: float) -> tuple[np.ndarray, np.ndarray]:
        """Mutual nearest neighbours within ``gate``: (detection indices, prediction indices).

        All pairwise distances for up to :data:`BRUTE_FORCE_PAIRS` pairs (a frame's few tens of
        stars: cheaper than building trees), else ``scipy.spatial.cKDTree`` both ways."""
        idx_size = px.size
        n = det.n
        matched_det = np.zeros(0, dtype=np.intp)
        matched_star = np.zeros(0, dtype=np.intp)
        if n and idx_size:
            dpos = np.column_stack([det.x, det.y])
            finite = np.isfinite(dpos).all(axis=1)
            ppos = np.column_stack([px, py])
            if n * idx_size <= BRUTE_FORCE_PAIRS:
                d2 = (dpos[:, None, 0] - ppos[None, :, 0]) ** 2 + (dpos[:, None, 1] - ppos[None, :, 1]) ** 2
                d2[~finite] = np.inf
                j = np.argmin(d2, axis=1)
                back = np.argmin(d2, axis=0)
                rows = np.arange(n)
                mutual = finite & (d2[rows, j] <= gate * gate) & (back[j] == rows)
                matched_det = np.flatnonzero(mutual)
                return matched_det, j[matched_det]
            # detection -> nearest prediction
            d1, j = cKDTree(ppos).query(np.where(finite[:, None], dpos, 0.0), k=1, distance_upper_bound=gate)
            # prediction -> nearest (finite) detection
            fin_idx = np.flatnonzero(finite)
            if fin_idx.size:
                _, i_back = cKDTree(dpos[fin_idx]).query(ppos, k=1, distance_upper_bound=gate)
                back = np.full(idx_size + 1, -1, dtype=np.intp)  # index idx_size = "no neighbour"
                has = i_back < fin_idx.size
                back[:-1][has] = fin_idx[i_back[has]]
                cand = finite & np.isfinite(d1) & (d1 <= gate)
                mutual = cand & (back[np.where(cand, j, idx_size)] == np.arange(n))
                matched_det = np.flatnonzero(mutual)
                matched_star = j[matched_det]
        return matched_det, matched_star


def _imageable(det, camera):
    """``det`` with the positions no direction images set to NaN, so that nothing matches them: past
    a fisheye's image circle, or where a radial map folds over (a distortion the camera does not
    model can put a detection there)."""
    if not camera.distorted and camera.projection == "perspective":
        return det
    ok = np.all(np.isfinite(camera.unproject(det.x, det.y)), axis=1)
    return det if ok.all() else det.with_columns(x=np.where(ok, det.x, np.nan), y=np.where(ok, det.y, np.nan))
