"""Tracking identifier: match detections to catalogue stars predicted from a prior attitude."""
from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from rollingstar.estimators.data import FrameData
from rollingstar.estimators.identifiers.base import Identifier
from rollingstar.sensors.conventions import S_PER_NS, attitude_from_radec_roll


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
    gate_px: float = Field(default=10.0, gt=0, description="Largest detection-to-prediction distance of a match (px).")
    margin_deg: float = Field(default=0.5, ge=0, description="Extra cone radius beyond the detector's half diagonal (deg).")
    magnitude_limit: float | None = Field(default=None, description="Only predict stars at most this magnitude; None: all.")
    extrapolate: bool = Field(default=True, description="Predict with the rate implied by the last two estimates.")
    refine: bool = Field(default=True, description="Fit the attitude to the first matches and match again (drops mismatches).")
    refine_gate_px: float = Field(default=2.0, gt=0, description="Smallest gate of the second matching pass (px).")


class TrackingIdentifier(Identifier):
    """Identification by tracking: predict the catalogue into the image from the previous attitude.

    Prediction: catalogue stars within ``camera.half_diagonal_rad + margin`` of the prior boresight
    (``StarCatalog.cone``), optionally magnitude-limited, rotated into the camera frame
    (``w = R^T v``) and projected with the pinhole model (he2021b eq 2); predictions are kept when in
    front of the camera and within ``gate_px`` of the detector.

    Matching: mutual nearest neighbours within the gate (``scipy.spatial.cKDTree`` both ways): a
    detection is matched to star ``j`` iff ``j`` is its nearest prediction, it is ``j``'s nearest
    detection and their distance is ``<= gate_px``. Hence at most one detection per star and one
    star per detection, and the result does not depend on the detections' order (barring exact
    distance ties).

    Output: ``frame.stars`` = matched detections (in their input order) with ``catalog_id`` and
    ``ref_icrs`` (catalogue unit vector at the catalogue epoch); ``frame.unmatched`` = the rest.

    Prior: ``params.initial_attitude`` else ``context.initial_attitude`` at :meth:`setup` (without
    either, setup raises: use a lost-in-space identifier). **The prior is advanced by the runner**:
    after all stages of a frame have run it calls :meth:`update_prior` with the final frame, and the
    last valid attitude estimate becomes the next frame's prior (the identifier runs before the
    solver, so it cannot see the estimate of the frame it is identifying). With ``extrapolate`` the
    prior is propagated to the frame's reference time (middle row, mid-exposure) at the constant
    body rate implied by the last two valid estimates, ``omega = Log(R0^T R1) / (t1 - t0)``, so the
    gate only has to cover the change of rate between frames, not the motion itself.

    Verification (``refine``): with at least three first-pass matches, the attitude that best fits
    them (Wahba's problem, SVD via ``Rotation.align_vectors``) re-predicts the catalogue, and
    matching runs again with the gate ``max(refine_gate_px, 5 * 1.4826 * median residual)``: a
    detection matched to a neighbour of its true star leaves a residual of the neighbours'
    separation and is dropped, while the rolling-shutter distortion common to all stars is absorbed
    by the fit.
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
        self._rate_rad_s = np.zeros(3)
        cam = context.camera
        self._radius = cam.half_diagonal_rad + np.radians(self.params.margin_deg)
        catalog = context.catalog
        self._cat_sel = (np.arange(len(catalog.ids)) if self.params.magnitude_limit is None
                         else np.flatnonzero(catalog.magnitude <= self.params.magnitude_limit))
        self._cat_keep = np.zeros(len(catalog.ids), dtype=bool)
        self._cat_keep[self._cat_sel] = True

    @property
    def prior(self) -> Rotation:
        """The attitude (camera-to-ICRS) the next frame's predictions are made from."""
        return self._last_attitude

    def update_prior(self, frame: FrameData) -> bool:
        """Take the last valid estimate of ``frame.attitudes`` as the next prior; True if one was found.

        The runner calls this with each frame after all of the frame's stages have run.
        """
        for est in reversed(frame.attitudes):
            if est.valid and np.all(np.isfinite(est.q_xyzw)):
                new = Rotation.from_quat(est.q_xyzw)
                if self._last_t_ns is not None and est.t_ns > self._last_t_ns:
                    dt = (int(est.t_ns) - self._last_t_ns) * S_PER_NS
                    self._rate_rad_s = (self._last_attitude.inv() * new).as_rotvec() / dt
                self._last_attitude, self._last_t_ns = new, int(est.t_ns)
                return True
        return False

    def prior_at(self, t_ns: int) -> Rotation:
        """The prior propagated to ``t_ns`` at the last estimated body rate (no change without it)."""
        if not self.params.extrapolate or self._last_t_ns is None:
            return self._last_attitude
        dt = (int(t_ns) - self._last_t_ns) * S_PER_NS
        return self._last_attitude * Rotation.from_rotvec(self._rate_rad_s * dt)

    def predict(self, attitude: Rotation | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Catalogue indices and predicted pixel positions ``(idx, x, y)`` for ``attitude`` (default: prior)."""
        R = self._last_attitude if attitude is None else attitude
        cam = self.context.camera
        catalog = self.context.catalog
        boresight = R.apply([0.0, 0.0, 1.0])
        idx = np.asarray(catalog.cone(boresight, self._radius), dtype=np.intp)
        idx = idx[self._cat_keep[idx]]
        w = R.inv().apply(catalog.unit_icrs[idx]) if idx.size else np.zeros((0, 3))
        x, y, front = cam.project(w)
        ok = front & cam.contains(x, y, margin_px=-self.params.gate_px)
        return idx[ok], x[ok], y[ok]

    def process(self, frame: FrameData) -> FrameData:
        det = frame.stars
        if det is None:
            raise ValueError(f"frame {frame.index}: no detections (frame.stars is None); "
                             "the 'tracking' identifier needs a centroider or centroid-level recording before it")
        prior = self.prior_at(self.context.timing.frame_reference_ns(frame.t0_ns))
        idx, px, py = self.predict(prior)
        matched_det, matched_star = self._match(det, px, py, self.params.gate_px)
        if self.params.refine and matched_det.size >= 3:
            cam, catalog = self.context.camera, self.context.catalog
            w = cam.unproject(det.x[matched_det], det.y[matched_det])
            fit, _ = Rotation.align_vectors(catalog.unit_icrs[idx[matched_star]], w)
            idx, px, py = self.predict(fit)
            first = self._match(det, px, py, self.params.gate_px)
            resid = np.hypot(det.x[first[0]] - px[first[1]], det.y[first[0]] - py[first[1]])
            gate = max(self.params.refine_gate_px, 5.0 * 1.4826 * float(np.median(resid))) if resid.size else self.params.gate_px
            matched_det, matched_star = self._match(det, px, py, min(gate, self.params.gate_px))
        n = det.n
        cat_idx = idx[matched_star]
        catalog = self.context.catalog
        stars = det.take(matched_det).with_columns(
            catalog_id=catalog.ids[cat_idx], ref_icrs=catalog.unit_icrs[cat_idx])
        rest = np.ones(n, dtype=bool)
        rest[matched_det] = False
        flags = frame.flags if idx.size else frame.flags + ("no_catalog_stars_in_view",)
        return frame.evolve(stars=stars, unmatched=det.take(rest), flags=flags)

    @staticmethod
    def _match(det, px, py, gate: float) -> tuple[np.ndarray, np.ndarray]:
        """Mutual nearest neighbours within ``gate``: (detection indices, prediction indices)."""
        idx_size = px.size
        n = det.n
        matched_det = np.zeros(0, dtype=np.intp)
        matched_star = np.zeros(0, dtype=np.intp)
        if n and idx_size:
            dpos = np.column_stack([det.x, det.y])
            finite = np.isfinite(dpos).all(axis=1)
            ppos = np.column_stack([px, py])
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
