"""Tracking identifier: match detections to catalogue stars predicted from a prior attitude."""
from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from estimators.data import FrameData, StarTable
from estimators.identifiers.base import Identifier
from sensors.conventions import attitude_from_radec_roll


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
    solver, so it cannot see the estimate of the frame it is identifying). Rates are not used yet:
    the gate must cover the image motion between frames.
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
                self._last_attitude = Rotation.from_quat(est.q_xyzw)
                return True
        return False

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
        idx, px, py = self.predict()
        n = det.n
        matched_det = np.zeros(0, dtype=np.intp)
        matched_star = np.zeros(0, dtype=np.intp)
        if n and idx.size:
            dpos = np.column_stack([det.x, det.y])
            finite = np.isfinite(dpos).all(axis=1)
            ppos = np.column_stack([px, py])
            gate = self.params.gate_px
            # detection -> nearest prediction
            d1, j = cKDTree(ppos).query(np.where(finite[:, None], dpos, 0.0), k=1, distance_upper_bound=gate)
            # prediction -> nearest (finite) detection
            fin_idx = np.flatnonzero(finite)
            if fin_idx.size:
                _, i_back = cKDTree(dpos[fin_idx]).query(ppos, k=1, distance_upper_bound=gate)
                back = np.full(idx.size + 1, -1, dtype=np.intp)  # index idx.size = "no neighbour"
                has = i_back < fin_idx.size
                back[:-1][has] = fin_idx[i_back[has]]
                cand = finite & np.isfinite(d1) & (d1 <= gate)
                mutual = cand & (back[np.where(cand, j, idx.size)] == np.arange(n))
                matched_det = np.flatnonzero(mutual)
                matched_star = j[matched_det]
        cat_idx = idx[matched_star]
        catalog = self.context.catalog
        stars = det.take(matched_det).with_columns(
            catalog_id=catalog.ids[cat_idx], ref_icrs=catalog.unit_icrs[cat_idx])
        rest = np.ones(n, dtype=bool)
        rest[matched_det] = False
        flags = frame.flags if idx.size else frame.flags + ("no_catalog_stars_in_view",)
        return frame.evolve(stars=stars, unmatched=det.take(rest), flags=flags)
