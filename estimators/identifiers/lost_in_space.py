"""Lost-in-space identifier: identify stars with no prior attitude (tetra3rs), verify, then track."""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial.transform import Rotation
from scipy.stats import binom

from rollingstar.estimators.data import FrameData, frame_camera
from rollingstar.estimators.identifiers.base import Identifier
from rollingstar.estimators.identifiers.camera_fit import RadialCamera, fit_camera
from rollingstar.estimators.identifiers.integrity import RATE_FIT_MIN_MATCHES, check_frame, fit_rate
from rollingstar.estimators.identifiers.tetra3_database import solver_database
from rollingstar.estimators.identifiers.tracking import (
    BodyMotion,
    TrackingIdentifier,
    TrackingParams,
    predict_at_rows,
)
from rollingstar.sensors.conventions import S_PER_NS
from rollingstar.sensors.so3 import skew

# the narrowest field whose pattern database fits in memory (tetra3 lattice of field centres)
MIN_FIELD_DEG = 1.0


class LostInSpaceParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    fov_tolerance: float = Field(default=0.05, ge=0, lt=0.5,
                                 description="Relative error of the camera's field of view the pattern search allows.")
    magnitude_limit: float | None = Field(default=None, description="Only index catalogue stars at most this magnitude; None: all.")
    pattern_catalog_magnitude: float | None = Field(
        default=None, description="Build the pattern database from Hipparcos-2 to this Hp magnitude (at the context "
        "catalogue's epoch) instead of the context catalogue; identifications still come from the context catalogue.")
    pattern_checking_stars: int = Field(default=24, ge=4, description="Brightest detections the 4-star patterns are formed from.")
    match_threshold: float = Field(default=1e-5, gt=0, lt=1,
                                   description="tetra3rs' false-positive budget for accepting a pattern hypothesis.")
    max_patterns_checked: int = Field(default=2_000_000, ge=1,
                                      description="Work bound of the pattern search (deterministic, unlike a timeout).")
    min_matches: int = Field(default=4, ge=3, description="Fewest identified stars an identification is accepted with.")
    max_residual_px: float = Field(default=2.0, gt=0, description="RMS residual (px) of the verified attitude fit "
                                   "accepted whatever the residuals' spread (see residual_spread).")
    residual_spread: float = Field(default=0.0, ge=0, description="Also accept an RMS residual up to this many times "
                                   "the fit's robust scatter (1.4826 x median |r|): residuals that are uniformly large "
                                   "(a lens model off by pixels everywhere) rather than a few large ones (mismatches); "
                                   "the false-match bound still applies. 0: the fixed max_residual_px only.")
    max_false_match_prob: float = Field(default=1e-9, gt=0, lt=1,
                                        description="Largest chance probability of the match count (binomial test, see docstring).")
    gate_px: float = Field(default=10.0, gt=0, description="Match gate (px) of the catalogue re-matching after the pattern solve.")
    solved_scale: bool = Field(default=True, description="Re-match, verify and track with the focal length of the field of view "
                                                         "tetra3rs solved (within fov_tolerance) instead of the camera's nominal one.")
    track: bool = Field(default=True, description="After an accepted identification, identify the next frames by tracking; "
                                                  "fall back to lost-in-space when tracking keeps fewer than min_matches "
                                                  "or its matches fail the false-match bound.")
    track_min_matches: int | None = Field(default=None, ge=2, description="Fewest stars a tracked frame keeps before "
                                          "lost-in-space is tried again; None: min_matches. Every tracked frame is "
                                          "also verified against the false-match bound.")
    start_from_prior: bool = Field(default=True, description="With track, when the sensor context declares an initial "
                                   "attitude, track from it on the first frame (verified as every tracked frame) "
                                   "instead of a pattern search.")
    tracking: TrackingParams = Field(default_factory=TrackingParams, description="Parameters of the tracking identifier used after.")
    pattern_match_max_error: float | None = Field(
        default=None, gt=0, lt=0.5, description="tetra3rs' largest edge-ratio error of a 4-star pattern match; None: the "
        "database's (0.001 + quantisation). Raise it (e.g. 0.01) for lenses whose distortion is not known.")
    k1: float = Field(default=0.0, ge=-1.0, le=1.0, description="Known radial distortion k1 of the camera (normalised "
                      "coordinates, sensors/effects/radial_distortion.py convention); centroids are undistorted with it before "
                      "the pattern search, and it starts the fit with fit_distortion='radial'.")
    k2: float = Field(default=0.0, ge=-1e3, le=1e3, description="Known radial distortion k2 (as k1; a narrow field constrains it "
                      "poorly, so fitted values can be large while k2 r^4 stays small).")
    fit_distortion: Literal["none", "focal", "radial", "auto"] = Field(
        default="none", description="'radial': after the pattern match fit focal length and radial distortion (k1, and k2 "
        "with distortion_terms=2) jointly with the attitude to the matched stars, re-match with the fitted model and "
        "verify with it (see the class docstring); every later stage then uses the fitted camera. 'focal': the same "
        "with the focal length alone (the known k1, k2 kept). 'none': pinhole with the known focal length, k1, k2. "
        "'auto': 'radial' for fields wider than auto_distortion_fov_deg, else 'focal'; 'none' on a camera that is "
        "not a pinhole with k1, k2.")
    auto_distortion_fov_deg: float = Field(default=20.0, gt=0, description="Horizontal field (deg) above which "
                                           "fit_distortion='auto' fits the distortion (below, the focal length only).")
    distortion_terms: Literal[1, 2] = Field(default=2, description="Radial terms fitted: 1 (k1) or 2 (k1, k2).")
    fit_principal_point: bool = Field(default=False, description="With fit_distortion='radial', also fit the principal point.")
    distortion_min_matches: int = Field(default=8, ge=4, description="Fewest matches the distortion is fitted with; below, "
                                                                     "the known k1, k2 are kept and only the attitude is fitted.")
    refer_motion: bool = Field(default=True, description="Refer the detections to the frame's reference time with the "
                               "body rate fitted to their image velocities (vx, vy) before the pattern search, and "
                               "re-match each star at its own row time with that rate, or with the rate fitted to the "
                               "matches (see the class docstring).")
    motion_threshold_px: float = Field(default=1.0, ge=0, description="A rate fitted to the matches is used when the "
                                       "motion it implies between the matched stars' times exceeds this (px).")
    fit_max_motion_px: float = Field(default=1.0, ge=0, description="With fit_distortion, the intrinsics are fitted "
                                     "only on a frame whose body rate moves the matched stars by at most this (px) "
                                     "between their row times; a faster frame keeps the camera fitted last (or the "
                                     "known one): its fit would trade the focal length and k1 against the rolling "
                                     "shutter's stretch (see the class docstring, 5).")


@dataclass(frozen=True)
class LostInSpaceSolution:
    """Diagnostics of the last lost-in-space attempt (also for the real-data figures).

    ``attitude`` is the camera-to-ICRS fit to the verified matches (None when rejected), at
    ``t_ns`` (the frame's reference time) when a body rate was used (``rate_rad_s``, camera frame,
    rad/s; None: the frame was treated as motionless).
    """

    accepted: bool
    reason: str
    attitude: Rotation | None
    n_detections: int
    n_matched: int
    residual_rms_px: float
    false_match_prob: float
    solver_matches: int
    solver_probability: float
    solver_fov_deg: float
    solve_seconds: float
    focal_px: float = float("nan")
    camera: RadialCamera | None = None
    camera_sigma: dict = field(default_factory=dict)
    rate_rad_s: np.ndarray | None = None
    t_ns: int | None = None


class LostInSpaceIdentifier(Identifier):
    """Lost-in-space star identification by 4-star pattern hashing (tetra3 / tetra3rs), verified.

    1. Pattern solve: the detections (brightest first, ``x - cx, y - cy`` so the principal point
       is the origin; tetra3rs' +x right, +y down convention) go to
       ``tetra3rs.SolverDatabase.solve_from_centroids`` with a pinhole ``CameraModel`` of the
       context's focal length. The database is built once from the context's own catalogue
       (:mod:`rollingstar.estimators.identifiers.tetra3_database`) for horizontal fields within
       ``fov_tolerance`` of the camera's, so the ids it returns are our catalogue ids (with
       ``pattern_catalog_magnitude``, from a deeper Hipparcos-2 list: a recording's catalogue cut
       at Hp 6 leaves too few pattern stars in a 10 deg field).
       tetra3rs hashes the edge ratios of 4-star patterns of the brightest
       ``pattern_checking_stars`` detections, looks them up, and accepts a hypothesis when its
       verification p-value passes ``match_threshold`` (Brown & Stubis 2017; tetra3, ESA).
    2. Re-match on our camera model: the attitude is refitted to tetra3rs' matches (Wahba's
       problem, SVD, ``Rotation.align_vectors`` with he2021b eq 2 directions), then every
       detection is matched to the catalogue predicted from that attitude exactly as the
       ``tracking`` identifier does (mutual nearest neighbours within ``gate_px``, refit, rematch
       with a residual-scaled gate). With ``solved_scale`` (default) the camera's focal length is
       replaced by the one of tetra3rs' solved horizontal field, ``f = (W / 2) / tan(fov / 2)``,
       here and in the verification and tracking that follow: a nominal focal length 1 % off
       (a lens' tolerance) moves corner stars by several pixels, which is calibration, not
       misidentification.
    3. Verification, all three required, else the frame is flagged
       ``lost_in_space_rejected:<reason>`` and no star is identified (never a guess):

       - ``k >= min_matches`` identified stars;
       - RMS residual of the refitted attitude ``sqrt(mean |x_i - proj(R^T r_i)|^2) <= max_residual_px``;
       - false-match probability ``P = sum_{i>=k} C(n,i) p^i (1-p)^(n-i)`` (binomial tail,
         ``scipy.stats.binom.sf(k-1, n, p)``) ``<= max_false_match_prob``, where ``n`` is the
         number of detections and ``p = min(1, N pi g^2 / (W H))`` the chance that one random
         detection falls within ``g`` of one of the ``N`` catalogue stars predicted on the
         ``W x H`` detector, ``g`` the largest residual of the ``k`` matches (at least the
         tracking ``refine_gate_px``): the probability that ``k`` or more of ``n`` random spots
         match as well by chance (the verification test of tetra3). Overlapping discs make the
         true ``p`` smaller, so ``P`` is conservative. It is the probability of one hypothesis; the
         default bound 1e-9 leaves room for the ~1e4 hypotheses a search may test.
    4. With ``track`` the next frames are identified by an internal ``tracking`` identifier whose
       prior is the verified attitude, then (via :meth:`update_prior`, called by the runner) the
       pipeline's attitude estimates; a frame where tracking keeps fewer than ``track_min_matches``
       (default ``min_matches``) stars, or whose matches fail the false-match bound
       (:func:`rollingstar.estimators.identifiers.integrity.check_identification`), is flagged
       ``track_lost`` and identified lost-in-space again. With ``start_from_prior`` and a sensor
       context that declares an initial attitude, the first frame is tracked from it, verified the
       same way.
    5. The camera: when the intrinsics were fitted (``fit_distortion``), the identified frames carry
       the fitted model in ``frame.camera`` (focal length, principal point, k1, k2), and every later
       stage (correction, attitude, smoother) projects with it. A published focal length is often
       0.5-1 % off the lens' (tetra3 images: 11.53 deg nominal, 11.43 deg fitted); with stars off the
       image centre a scale error tilts the attitude a solver fits, so ``auto`` fits the focal
       length on every field and the radial terms on wide ones. The fit needs stars that hold
       still: on a rolling-shutter frame of a turning camera the rate stretches the pattern along
       the columns by ``omega x (row time)``, and a focal length and ``k1`` fitted with an imperfect
       rate take up part of that stretch (several-fold worse attitudes at 6-10 deg/s on he2021a).
       So the intrinsics are fitted only on frames whose rate moves the matched stars by at most
       ``fit_max_motion_px`` between their row times. A faster frame is matched and verified as
       without the fit (with the solved field's scale) and hands on the camera fitted last (the
       known one before any fit). ``auto`` on a camera whose projection or ``k3`` the fit does not
       model fits nothing.

    6. Motion (``refer_motion``). A rolling-shutter frame of a turning camera images its stars at
       different times (up to ``rows x line delay``, 45 ms on he2021a: 34 px at 10 deg/s), which
       stretches and shears the pattern. When the detections carry image velocities (``vx, vy``,
       a streak centroider's), the body rate of the rigid rotation that explains them
       (:func:`fit_body_rate`, robust) refers every detection to the frame's reference time,
       ``R(t_ref)^T r_i = Exp(omega (t_i - t_ref)) b_i``, before the pattern search; without
       velocities (or when the velocities' rate and its opposite are both rejected: a cold-start
       streak's direction of travel is ambiguous) the search sees the detections as they are, and once five or more stars at
       distinct times are matched the attitude and rate are fitted to them
       (:func:`rollingstar.estimators.identifiers.integrity.fit_rate`, with the nominal camera: a
       field of view solved on a stretched frame holds part of the stretch) and used when the
       motion they imply between the stars exceeds ``motion_threshold_px``. With a rate, the
       re-matching predicts each catalogue star at its own row time (tracking's
       ``predict_at_rows``) and the verification's residuals are taken there; the accepted
       solution (``rate_rad_s``, ``t_ns``) seeds the tracker, which then predicts the next frame
       with that rate (else with the rate the lost tracker held). A lost track is re-acquired
       lost-in-space in the same frame (4).

    Output: as every identifier, ``frame.stars`` = identified detections with ``catalog_id`` and
    ``ref_icrs``, ``frame.unmatched`` = the rest. :attr:`last_solution` holds the diagnostics of
    the last lost-in-space attempt.
    """

    verifies_identification = True  # tracked frames carry their check (see _check)
    name = "lost-in-space"
    Params = LostInSpaceParams

    def setup(self, context) -> None:
        super().setup(context)
        if context.catalog is None:
            raise ValueError("the 'lost-in-space' identifier needs a star catalogue in the sensor context")
        cam = context.camera
        self._pinhole = cam.projection == "perspective" and not cam.k3
        if not self._pinhole and self.params.fit_distortion not in ("none", "auto"):
            raise ValueError(f"the 'lost-in-space' identifier fits a pinhole with radial terms k1, k2; the camera "
                             f"declares projection {cam.projection!r}, k3 = {cam.k3:g}: use fit_distortion 'none'")
        self._fov_deg = float(cam.fov_deg[0])
        self._db = None  # built on the first pattern search (_database): tracking from a prior never needs it
        import tetra3rs

        self._camera_model = tetra3rs.CameraModel(float(cam.focal_px), int(cam.width), int(cam.height))
        # the re-matcher and the tracker: tracking identifiers whose prior we set ourselves
        self._matcher_params = self.params.tracking.model_copy(update={
            "initial_attitude": None, "gate_px": self.params.gate_px, "extrapolate": False, "refine": True,
            "magnitude_limit": self.params.magnitude_limit})
        self._tracker: TrackingIdentifier | None = None
        self._track_model = RadialCamera.from_pinhole(cam, *self._known_distortion())
        mode = self.params.fit_distortion
        if mode == "auto" and not self._pinhole:
            mode = "none"  # a projection or k3 the fit does not model: the declared camera
        elif mode == "auto":
            mode = "radial" if self._fov_deg > self.params.auto_distortion_fov_deg else "focal"
        self._fitting = mode != "none"
        self._fit_names = ("focal_px", *(("k1", "k2")[:self.params.distortion_terms] if mode == "radial" else ()),
                           *(("cx", "cy") if self.params.fit_principal_point else ()))
        if self.params.track and self.params.start_from_prior and context.initial_attitude is not None:
            self._tracker = self._tracking_identifier(context.initial_attitude, self.params.tracking,
                                                      self._track_model.camera(cam))
        self.last_solution: LostInSpaceSolution | None = None
        self.last_mode = ""

    # ------------------------------------------------------------------ helpers
    def __getstate__(self) -> dict:
        """For run checkpoints: everything but the pattern database (a tetra3rs object that does not
        pickle); it is rebuilt, from the memo or anew, on the next pattern search."""
        return {**self.__dict__, "_db": None}

    def _database(self):
        """The pattern database (and its catalogue, ``self._catalog``), built on first use: about a
        second per catalogue and field, memoised across instances (tetra3_database.py)."""
        if self._db is None:
            cat = self.context.catalog
            if self.params.pattern_catalog_magnitude is not None:
                from rollingstar.sensors.catalog import StarCatalog

                cat = StarCatalog.from_hipparcos(cat.epoch_year, self.params.pattern_catalog_magnitude)
            if self.params.magnitude_limit is not None:
                cat = cat.subset(cat.magnitude <= self.params.magnitude_limit)
            self._catalog = cat
            # the field range is widened to a quarter-degree grid so that cameras a little apart (one
            # lens' per-image or calibrated focal lengths) share one memoised database
            tol = self.params.fov_tolerance
            if self._fov_deg < MIN_FIELD_DEG:  # the pattern lattice of a narrower field is beyond memory
                raise ValueError(f"the camera's field is {self._fov_deg:.3g} deg, narrower than the {MIN_FIELD_DEG:g} deg "
                                 "lost-in-space's pattern database covers: check focal_length_mm and pixel_size_um "
                                 "(a focal length given in pixels?), or start from a declared attitude (tracking)")
            lo = np.floor(self._fov_deg * (1 - tol) * 4.0) / 4.0
            hi = np.ceil(self._fov_deg * (1 + tol) * 4.0) / 4.0
            self._db = solver_database(cat, lo, hi, self.params.magnitude_limit)
        return self._db

    def _tracking_identifier(self, attitude: Rotation, params: TrackingParams, camera) -> TrackingIdentifier:
        t = TrackingIdentifier(**params.model_dump())
        t.setup(replace(self.context, initial_attitude=attitude, camera=camera))
        return t

    def update_prior(self, frame: FrameData) -> bool:
        """Pass the frame's estimates to the tracker (called by the runner after every frame)."""
        return self._tracker.update_prior(frame) if self._tracker is not None else False

    # ------------------------------------------------------------------ processing
    def process(self, frame: FrameData) -> FrameData:
        det = frame.stars
        if det is None:
            raise ValueError(f"frame {frame.index}: no detections (frame.stars is None); "
                             "the 'lost-in-space' identifier needs a centroider or centroid-level recording before it")
        flags = frame.flags
        frame = frame.evolve(identification=None)
        if self._tracker is not None:
            out = self._with_camera(self._tracker.process(frame))
            least = self.params.track_min_matches or self.params.min_matches
            check = self._check(out) if out.stars.n >= least else None
            if check is not None and check.passed:
                self.last_mode = "tracking"
                return out.evolve(identification=check)
            flags = flags + ("track_lost",)
        lost, self._tracker = self._tracker, None
        self.last_mode = "lost-in-space"
        out, sol = self._lost_in_space(frame.evolve(flags=flags))
        self.last_solution = sol
        if sol.accepted and (sol.camera_sigma or not self._fitting):
            # with fit_distortion, only a camera fitted to this frame replaces the known one: a frame
            # too fast (or with too few matches) to fit was matched with the solved field's scale,
            # which is not handed on
            self._track_model = sol.camera
        if sol.accepted and self.params.track:
            self._tracker = self._tracking_identifier(sol.attitude, self.params.tracking, sol.camera.camera(self.context.camera))
            # the rate: the one the solution found, else the one the lost tracker held
            omega = sol.rate_rad_s if sol.rate_rad_s is not None else (lost.motion().omega if lost is not None else None)
            if omega is not None:
                self._tracker.seed(sol.attitude, sol.t_ns, omega)
        return self._with_camera(out) if sol.accepted else out

    def _check(self, out: FrameData):
        """The integrity check (integrity.py) of the tracked matches, on the camera the frame carries
        to the later stages (the stage mechanics' check of this frame: :attr:`verifies_identification`)."""
        return check_frame(out, frame_camera(out, self.context), self.context.catalog, self.params.max_false_match_prob)

    def _with_camera(self, out: FrameData) -> FrameData:
        """``out`` carrying the camera model later stages should use (class docstring, 5): the fitted
        one when the intrinsics were fitted; the sensor context's with the ``k1``, ``k2`` this
        identifier's parameters state when those differ from its own; else none (the context's). The focal length
        of tetra3rs' solved field (``solved_scale``) helps matching only: it is never handed on."""
        cam = self.context.camera
        if self._fitting:
            return out.evolve(camera=self._track_model.camera(cam))
        known = self._known_distortion()
        if known != (cam.k1, cam.k2):
            return out.evolve(camera=replace(cam, k1=known[0], k2=known[1]))
        return out

    def _known_distortion(self) -> tuple[float, float]:
        """``(k1, k2)``: the parameters' when they state a distortion, else the sensor context camera's."""
        p, cam = self.params, self.context.camera
        return (p.k1, p.k2) if (p.k1, p.k2) != (0.0, 0.0) else (float(cam.k1), float(cam.k2))

    def _reject(self, frame: FrameData, reason: str, **diag) -> tuple[FrameData, LostInSpaceSolution]:
        det = frame.stars
        sol = LostInSpaceSolution(
            accepted=False, reason=reason, attitude=None, n_detections=det.n,
            n_matched=diag.get("n_matched", 0), residual_rms_px=diag.get("residual_rms_px", np.nan),
            false_match_prob=diag.get("false_match_prob", np.nan), solver_matches=diag.get("solver_matches", 0),
            solver_probability=diag.get("solver_probability", np.nan), solver_fov_deg=diag.get("solver_fov_deg", np.nan),
            solve_seconds=diag.get("solve_seconds", 0.0))
        out = frame.evolve(stars=det.take(np.zeros(det.n, dtype=bool)), unmatched=det.take(np.ones(det.n, dtype=bool)),
                           flags=frame.flags + (f"lost_in_space_rejected:{reason}",))
        return out, sol

    def _predict(self, R: Rotation, model: RadialCamera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Catalogue indices and predicted (distorted) pixels of the stars on the detector for ``R``."""
        cam = self.context.camera
        cat = self.context.catalog
        radius = cam.half_diagonal_rad + np.radians(self._matcher_params.margin_deg)
        idx = np.asarray(cat.cone(R.apply([0.0, 0.0, 1.0]), radius), dtype=np.intp)
        if self.params.magnitude_limit is not None:
            idx = idx[cat.magnitude[idx] <= self.params.magnitude_limit]
        x, y, front = model.project(R.inv().apply(cat.unit_icrs[idx]) if idx.size else np.zeros((0, 3)))
        ok = front & cam.contains(x, y, margin_px=-self.params.gate_px)
        return idx[ok], x[ok], y[ok]

    def _predict_moving(self, R: Rotation, model: RadialCamera, motion: BodyMotion, t0_ns: int):
        """As :meth:`_predict` for ``R`` at the motion's origin, each star at its own row time."""
        if motion.static:
            return self._predict(R, model)
        cam, cat, timing = self.context.camera, self.context.catalog, self.context.timing
        sweep = float(np.linalg.norm(motion.omega)) * timing.frame_period_ns * S_PER_NS
        radius = cam.half_diagonal_rad + np.radians(self._matcher_params.margin_deg) + sweep
        center = (R * Rotation.from_rotvec(motion.phi(np.int64(timing.frame_reference_ns(t0_ns))))).apply([0.0, 0.0, 1.0])
        idx = np.asarray(cat.cone(center, radius), dtype=np.intp)
        if self.params.magnitude_limit is not None:
            idx = idx[cat.magnitude[idx] <= self.params.magnitude_limit]
        w0 = R.inv().apply(cat.unit_icrs[idx]) if idx.size else np.zeros((0, 3))
        x, y, front, _, _ = predict_at_rows(w0, motion, model.project, timing, t0_ns)
        ok = front & cam.contains(x, y, margin_px=-self.params.gate_px)
        return idx[ok], x[ok], y[ok]

    @staticmethod
    def _referred(det, rows: np.ndarray, model: RadialCamera, motion: BodyMotion) -> np.ndarray:
        """Camera directions of detections ``rows`` referred to the motion's origin, ``Exp(phi(t_i)) b_i``."""
        body = model.unproject(det.x[rows], det.y[rows])
        return body if motion.static else Rotation.from_rotvec(motion.phi(det.t_ns[rows])).apply(body)

    def _rematch(self, det, R: Rotation, model: RadialCamera, motion: BodyMotion, t0_ns: int):
        """Match every detection to the catalogue predicted with ``R`` (at the motion's origin), the
        motion and ``model``, as the ``tracking`` identifier does (mutual nearest neighbours within
        ``gate_px``, attitude refit, second pass with the gate ``max(refine_gate_px, 5 * 1.4826 *
        median residual)``). Returns (detection indices, catalogue indices, attitude fitted to the
        first pass, n predicted)."""
        match = TrackingIdentifier._match
        cat = self.context.catalog
        gate = self.params.gate_px
        idx, px, py = self._predict_moving(R, model, motion, t0_ns)
        d, j = match(det, px, py, gate)
        if d.size >= 3:
            R, _ = Rotation.align_vectors(cat.unit_icrs[idx[j]], self._referred(det, d, model, motion))
            idx, px, py = self._predict_moving(R, model, motion, t0_ns)
            d, j = match(det, px, py, gate)
            resid = np.hypot(det.x[d] - px[j], det.y[d] - py[j])
            g2 = max(self._matcher_params.refine_gate_px, 5.0 * 1.4826 * float(np.median(resid))) if resid.size else gate
            d, j = match(det, px, py, min(g2, gate))
        return d, idx[j], R, idx.size

    def _velocity_motion(self, det, model: RadialCamera, t_ref: int) -> BodyMotion:
        """The rigid body rate fitted to the detections' image velocities (:func:`fit_body_rate`) from
        ``t_ref``; no motion without ``refer_motion`` or three stars with a finite velocity."""
        if not self.params.refer_motion:
            return BodyMotion()
        omega = fit_body_rate(model.camera(self.context.camera), det.x, det.y, det.vx, det.vy)
        return BodyMotion() if omega is None else BodyMotion(t_ref, omega=omega)

    def _matched_motion(self, det, d: np.ndarray, c: np.ndarray, model: RadialCamera, t_ref: int):
        """The attitude at ``t_ref`` and body rate fitted to matches ``d`` (detections) / ``c``
        (catalogue) at their own times (integrity.fit_rate), when there are enough of them at
        distinct times and the motion the rate implies between them exceeds ``motion_threshold_px``;
        else None."""
        t = det.t_ns[d].astype(np.int64)
        if not self.params.refer_motion or d.size < RATE_FIT_MIN_MATCHES or np.ptp(t) == 0:
            return None
        body, ref = model.unproject(det.x[d], det.y[d]), self.context.catalog.unit_icrs[c]
        dt = (t - t_ref) * S_PER_NS
        R0, _ = Rotation.align_vectors(ref, body)
        phi, omega = fit_rate(R0, body, ref, dt, np.ones(d.size))
        if np.linalg.norm(omega) * np.ptp(dt) * model.focal_px <= self.params.motion_threshold_px:
            return None
        delta = np.mean(phi - dt[:, None] * omega[None, :], axis=0)
        return R0 * Rotation.from_rotvec(delta), BodyMotion(t_ref, omega=omega)

    def _lost_in_space(self, frame: FrameData) -> tuple[FrameData, LostInSpaceSolution]:
        det = frame.stars
        cam = self.context.camera
        if not self._pinhole:  # tetra3rs' patterns and our re-matching are a pinhole's
            return self._reject(frame, f"pattern_search_needs_a_pinhole({cam.projection})")
        finite = np.flatnonzero(np.isfinite(det.x) & np.isfinite(det.y))
        if finite.size < self.params.min_matches:
            return self._reject(frame, f"too_few_detections({finite.size}<{self.params.min_matches})")
        model = RadialCamera.from_pinhole(cam, *self._known_distortion())
        t_ref = int(self.context.timing.frame_reference_ns(frame.t0_ns))
        motion = self._velocity_motion(det, model, t_ref)
        # a streak's pixels tell its direction of travel only through the rolling shutter: when the
        # velocities' rate is rejected, its opposite and then no motion are tried
        tries = [motion] if motion.static else [motion, BodyMotion(t_ref, omega=-motion.omega), BodyMotion()]
        for motion in tries:
            out, sol = self._solve(frame, finite, model, motion, t_ref)
            if sol.accepted:
                break
        return out, sol

    def _solve(self, frame: FrameData, finite: np.ndarray, model: RadialCamera, motion: BodyMotion, t_ref: int):
        """Pattern search, re-matching and verification of ``frame`` with ``motion`` (steps 1-3 and 6)."""
        det, cam = frame.stars, self.context.camera
        res, order, seconds = self._pattern_solve(det, finite, model, motion)
        if not res:
            return self._reject(frame, f"solver_{res.status}", solve_seconds=seconds)
        diag = dict(solver_matches=int(res.num_matches), solver_probability=float(res.probability),
                    solver_fov_deg=float(res.fov_deg), solve_seconds=seconds)
        if res.parity_flip:
            return self._reject(frame, "mirrored_image", **diag)
        if self.params.solved_scale and np.isfinite(res.fov_deg) and res.fov_deg > 0:
            model = replace(model, focal_px=(cam.width / 2.0) / np.tan(np.radians(res.fov_deg) / 2.0))
        det_idx = order[np.asarray(res.matched_centroids, dtype=np.intp)]
        cat_idx = self._catalog.index_of(np.asarray(res.matched_catalog_ids, dtype=np.int64))
        ok = cat_idx >= 0
        if ok.sum() < 3:
            return self._reject(frame, "solver_ids_not_in_catalogue", **diag)
        R, _ = Rotation.align_vectors(self._catalog.unit_icrs[cat_idx[ok]], self._referred(det, det_idx[ok], model, motion))
        d, c, R, model, motion, sigma = self._match_all(det, R, model, motion, frame.t0_ns, t_ref)
        return self._verify(frame, d, c, model, motion, sigma, diag)

    def _pattern_solve(self, det, finite: np.ndarray, model: RadialCamera, motion: BodyMotion):
        """tetra3rs' pattern search on the detections (brightest first; referred to the motion's
        origin when a motion is known). Returns (result, detection order, seconds)."""
        cam = self.context.camera
        flux = np.where(np.isfinite(det.flux[finite]), det.flux[finite], 0.0)
        order = finite[np.argsort(-flux, kind="stable")]
        if motion.static:
            xu, yu = model.undistort(det.x[order], det.y[order])  # the pattern search sees a pinhole image
        else:
            w = self._referred(det, order, model, motion)
            xu, yu = model.cx - model.focal_px * w[:, 0] / w[:, 2], model.cy - model.focal_px * w[:, 1] / w[:, 2]
        cents = np.nan_to_num(np.column_stack([xu - cam.cx, yu - cam.cy, np.maximum(det.flux[order], 0.0)]))
        start = time.perf_counter()
        res = self._database().solve_from_centroids(
            cents, camera_model=self._camera_model, fov_max_error_deg=self._fov_deg * self.params.fov_tolerance,
            match_threshold=self.params.match_threshold, solve_timeout_ms=None,
            max_patterns_checked=self.params.max_patterns_checked,
            pattern_checking_stars=self.params.pattern_checking_stars, match_max_error=self.params.pattern_match_max_error)
        return res, order, time.perf_counter() - start

    def _match_all(self, det, R: Rotation, model: RadialCamera, motion: BodyMotion, t0_ns: int, t_ref: int):
        """Re-match every detection against our catalogue and camera model; with fit_distortion the
        intrinsics are refitted to the matches (on a frame that holds still: :meth:`_may_fit`) and
        the matching repeated until the set is stable; without a known motion, then with the rate
        fitted to the matches (:meth:`_matched_motion`). Returns (detections, catalogue indices,
        attitude, camera model, motion, camera sigmas: empty when the camera was not fitted to these
        matches, and ``model`` is then the one matched with, not one to hand on)."""
        fitting = self._fitting
        sigma: dict = {}
        previous = None
        for _ in range(6 if fitting else 1):
            d, c, R, _ = self._rematch(det, R, model, motion, t0_ns)
            key = (tuple(d), tuple(c))
            if d.size < 3 or key == previous:
                break
            previous = key
            ref = self.context.catalog.unit_icrs[c]
            if self._may_fit(det, d, model, motion):
                x, y = (det.x[d], det.y[d]) if motion.static else model.project(self._referred(det, d, model, motion))[:2]
                cf = fit_camera([(x, y, ref)], [R], model, fit=self._fit_names)
                model, R, sigma = cf.camera, cf.attitudes[0], cf.sigma
            else:
                R, _ = Rotation.align_vectors(ref, self._referred(det, d, model, motion))
        if motion.static:
            # the field of view solved on (or the intrinsics fitted to) a frame stretched by the rolling
            # shutter hold part of the stretch: a rate is fitted with the known camera instead (the one
            # fitted last on a frame that held still, or the declared one)
            known = self._track_model if fitting else RadialCamera.from_pinhole(self.context.camera,
                                                                                *self._known_distortion())
            for _ in range(2):  # the second pass fits the rate to the stars the first one added
                got = self._matched_motion(det, d, c, known, t_ref)
                if got is None:
                    break
                (R, motion), model, sigma = got, known, {}
                d, c, R, _ = self._rematch(det, R, model, motion, t0_ns)
            if not motion.static and self._may_fit(det, d, model, motion):
                x, y = model.project(self._referred(det, d, model, motion))[:2]
                cf = fit_camera([(x, y, self.context.catalog.unit_icrs[c])], [R], model, fit=self._fit_names)
                model, sigma = cf.camera, cf.sigma
        return d, c, R, model, motion, sigma

    def _may_fit(self, det, d: np.ndarray, model: RadialCamera, motion: BodyMotion) -> bool:
        """Whether the intrinsics are fitted to matches ``d``: with ``fit_distortion``, enough of them,
        and a motion that moves them by at most ``fit_max_motion_px`` between their row times."""
        if not self._fitting or d.size < self.params.distortion_min_matches:
            return False
        if motion.static:
            return True
        span_s = np.ptp(det.t_ns[d].astype(np.int64)) * S_PER_NS
        return float(np.linalg.norm(motion.omega)) * span_s * model.focal_px <= self.params.fit_max_motion_px

    def _verify(self, frame: FrameData, d: np.ndarray, c: np.ndarray, model: RadialCamera, motion: BodyMotion,
                sigma: dict, diag: dict) -> tuple[FrameData, LostInSpaceSolution]:
        """The verification of the class docstring (3) on matches ``d`` / ``c``, each star at its own time."""
        det, cam = frame.stars, self.context.camera
        k, n = d.size, det.n
        if k < 3:
            return self._reject(frame, f"too_few_matches({k}<{self.params.min_matches})", n_matched=k, **diag)
        ref = self.context.catalog.unit_icrs[c]
        R, _ = Rotation.align_vectors(ref, self._referred(det, d, model, motion))
        n_pred = self._predict(R, model)[0].size
        if motion.static:
            px, py, _ = model.project(R.inv().apply(ref))
        else:
            px, py, _ = model.project((R * Rotation.from_rotvec(motion.phi(det.t_ns[d]))).inv().apply(ref))
        r = np.hypot(px - det.x[d], py - det.y[d])
        rms = float(np.sqrt(np.mean(r**2)))
        gate = max(float(r.max()), self._matcher_params.refine_gate_px)
        p = min(1.0, n_pred * np.pi * gate**2 / (cam.width * cam.height))
        p_false = float(binom.sf(k - 1, n, p))
        diag.update(n_matched=k, residual_rms_px=rms, false_match_prob=p_false)
        if k < self.params.min_matches:
            return self._reject(frame, f"too_few_matches({k}<{self.params.min_matches})", **diag)
        bound = max(self.params.max_residual_px, self.params.residual_spread * 1.4826 * float(np.median(r)))
        if not rms <= bound:
            return self._reject(frame, f"residual({rms:.2f}px>{bound:.2f}px)", **diag)
        if not p_false <= self.params.max_false_match_prob:
            return self._reject(frame, f"false_match_probability({p_false:.1e}>{self.params.max_false_match_prob:.0e})", **diag)
        sol = LostInSpaceSolution(accepted=True, reason="", attitude=R, n_detections=n, focal_px=model.focal_px,
                                  camera=model, camera_sigma=sigma, rate_rad_s=None if motion.static else motion.omega,
                                  t_ns=int(self.context.timing.frame_reference_ns(frame.t0_ns)), **diag)
        stars = det.take(d).with_columns(catalog_id=self.context.catalog.ids[c], ref_icrs=ref)
        rest = np.ones(n, dtype=bool)
        rest[d] = False
        return frame.evolve(stars=stars, unmatched=det.take(rest)), sol


def fit_body_rate(camera, x, y, vx, vy, iterations: int = 8) -> np.ndarray | None:
    """The body rate (camera frame, rad/s) of a rigid rotation that best explains the image
    velocities ``vx, vy`` (px/s) of stars at ``x, y``: ``v_i = P(w_i) [w_i]x omega`` with
    ``w_i = camera.unproject(x_i, y_i)`` (a camera turning at ``omega`` moves the direction ``w``
    of a fixed star at ``w x omega``), linear least squares in ``omega`` made robust by
    iteratively reweighting the stars by their residual ``r`` against the robust scatter
    ``s = 1.4826 median |r|``: Huber weights (``min(1, 2 s / r)``) for the first half of the
    iterations, then Tukey's biweight (``(1 - (r / 4.685 s)^2)^2``, zero beyond), so that a blend or
    a spurious streak does not pull the others. None with fewer than three finite velocities."""
    ok = np.flatnonzero(np.isfinite(x) & np.isfinite(y) & np.isfinite(vx) & np.isfinite(vy))
    if ok.size < 3:
        return None
    w = camera.unproject(x[ok], y[ok])
    A = camera.projection_jacobian(w) @ skew(w)  # (n, 2, 3)
    v = np.column_stack([vx[ok], vy[ok]])
    weight = np.ones(ok.size)
    omega = np.zeros(3)
    for k in range(iterations):
        rw = np.repeat(np.sqrt(weight), 2)
        omega, *_ = np.linalg.lstsq(A.reshape(-1, 3) * rw[:, None], v.reshape(-1) * rw, rcond=None)
        r = np.linalg.norm(v - A @ omega, axis=1)
        scale = 1.4826 * float(np.median(r)) + 1e-12
        if k < iterations // 2:
            weight = np.minimum(1.0, 2.0 * scale / np.maximum(r, 1e-300))
        else:
            weight = np.clip(1.0 - (r / (4.685 * scale)) ** 2, 0.0, None) ** 2
    return omega

