"""The sink of a run: the output log's estimate topics, and the recording's truth passed through.

:class:`EstimateSink` writes each finished frame (:func:`write_frame`: its stars, spot labels,
attitude estimates and poses, rate, and last its ``/estimate/frame`` status) and counts what it
wrote. When the recording carries ``/truth/attitude``, each valid attitude estimate also gets its
error against the truth at its own time on ``/estimate/attitude_error`` (the definition
``evaluate`` uses, :func:`~rollingstar.sensors.conventions.attitude_error_body_arcsec`), so a
replay in Foxglove can plot it; an estimate outside the truth samples seen so far gets none. With
``with_images`` the recording's frames are copied to ``/camera/image`` as they are read, so the
output opens complete. The writer's own :class:`~rollingstar.logs.digest.MessageDigest` (``LogWriter(digest=True)``)
counts and hashes every message, for the checkpoints of ``run --resume``.
"""
from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from rollingstar.estimators.data import FrameData, StarTable
from rollingstar.logs.reader import Message
from rollingstar.logs.records import AttitudeError as AttitudeErrorRecord
from rollingstar.logs.records import AttitudeEstimate as AttitudeRecord
from rollingstar.logs.records import FrameStatus, arrays_to_stars
from rollingstar.logs.records import RateEstimate as RateRecord
from rollingstar.logs.topics import (
    TOPIC_EST_ATTITUDE,
    TOPIC_EST_ATTITUDE_ERROR,
    TOPIC_EST_FRAME,
    TOPIC_EST_POSE,
    TOPIC_EST_RATE,
    TOPIC_EST_SPOTS,
    TOPIC_EST_STARS,
    TOPIC_IMAGE,
    TOPIC_TRUTH_ATTITUDE,
)
from rollingstar.logs.writer import LogWriter
from rollingstar.pipelines.outcomes import Outcomes
from rollingstar.sensors.conventions import attitude_error_body_arcsec, quat_to_fields


def new_counts() -> Outcomes:
    """The sink's counters before the first frame (:class:`~rollingstar.pipelines.outcomes.Outcomes`)."""
    return Outcomes()


class _TruthAttitude:
    """Every ``/truth/attitude`` sample passed through so far (a smoother can release its frames at the
    end of the run), in time order, and the truth at a time between two of them (spherical linear
    interpolation). The samples are appended to arrays that double when full, so a long run costs
    amortised constant time per sample."""

    def __init__(self) -> None:
        self._t = np.zeros(64, dtype=np.int64)
        self._q = np.zeros((64, 4))
        self._n = 0
        self._sorted = True

    @property
    def t(self) -> np.ndarray:
        self._order()
        return self._t[: self._n]

    @property
    def q(self) -> np.ndarray:
        self._order()
        return self._q[: self._n]

    def add(self, record: dict) -> None:
        t = np.asarray(record["t_ns"], dtype=np.int64)
        q = np.column_stack([record["qx"], record["qy"], record["qz"], record["qw"]])
        while self._n + t.size > self._t.size:
            self._t = np.concatenate([self._t, np.zeros_like(self._t)])
            self._q = np.concatenate([self._q, np.zeros_like(self._q)])
        if t.size and self._n and (t[0] < self._t[self._n - 1] or np.any(np.diff(t) < 0)):
            self._sorted = False
        self._t[self._n: self._n + t.size] = t
        self._q[self._n: self._n + t.size] = q
        self._n += t.size

    def _order(self) -> None:
        if not self._sorted:  # messages out of time order: sort once, before the next lookup
            order = np.argsort(self._t[: self._n], kind="stable")
            self._t[: self._n] = self._t[: self._n][order]
            self._q[: self._n] = self._q[: self._n][order]
            self._sorted = True

    def at(self, t_ns: np.ndarray):
        """The true attitudes at the times ``t_ns`` (a scipy ``Rotation`` of them, interpolated along
        the rotation between the two samples around each) and which times the samples cover."""
        from scipy.spatial.transform import Rotation

        t_ns = np.asarray(t_ns, dtype=np.int64)
        covered = (self.t.size >= 2) & (t_ns >= (self.t[0] if self.t.size else 0)) & \
            (t_ns <= (self.t[-1] if self.t.size else -1))
        if not covered.any():
            return None, covered
        t = t_ns[covered]
        i = np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, self.t.size - 2)
        span = (self.t[i + 1] - self.t[i]).astype(float)
        frac = np.divide((t - self.t[i]).astype(float), span, out=np.zeros(t.size), where=span > 0)
        r0, r1 = Rotation.from_quat(self.q[i]), Rotation.from_quat(self.q[i + 1])
        return r0 * Rotation.from_rotvec((r0.inv() * r1).as_rotvec() * frac[:, None]), covered


class EstimateSink:
    """Writes finished frames and truth messages to ``writer`` (module docstring).

    ``counts`` (see :func:`new_counts`) go on from a checkpoint's when given.
    """

    def __init__(self, writer: LogWriter, counts: Outcomes | None = None, with_images: bool = False) -> None:
        self.writer = writer
        self.counts = counts if counts is not None else new_counts()
        self.with_images = with_images
        self._truth = _TruthAttitude()

    def write_truth(self, messages: Iterable[Message]) -> None:
        """Pass the recording's truth messages through."""
        for m in messages:
            self.writer.write_json(m.topic, m.data, m.log_time_ns)
            if m.topic == TOPIC_TRUTH_ATTITUDE:
                self._truth.add(m.data)

    def write_source(self, frame: FrameData) -> None:
        """The frame as read from the recording: its image, when ``with_images``."""
        if self.with_images and frame.image is not None:
            self.writer.write_image(TOPIC_IMAGE, frame.image, int(frame.t0_ns))

    def write(self, frames: Iterable[FrameData]) -> None:
        """Write and count finished frames."""
        for frame in frames:
            write_frame(self.writer, frame)
            self._write_errors(frame)
            self.counts.add(frame.flags, [(a.valid, a.reason) for a in frame.attitudes])

    def _write_errors(self, frame: FrameData) -> None:
        from scipy.spatial.transform import Rotation

        valid = [a for a in frame.attitudes if a.valid]
        if not valid or not self._truth.t.size:
            return
        truth, covered = self._truth.at(np.array([a.t_ns for a in valid], dtype=np.int64))
        if truth is None:
            return
        est = [a for a, c in zip(valid, covered) if c]
        err = attitude_error_body_arcsec(truth, Rotation.from_quat(np.array([a.q_xyzw for a in est])))
        for a, e in zip(est, np.atleast_2d(err)):
            self.writer.write_json(TOPIC_EST_ATTITUDE_ERROR, AttitudeErrorRecord(
                frame=frame.index, t_ns=int(a.t_ns), x_arcsec=float(e[0]), y_arcsec=float(e[1]), z_arcsec=float(e[2])))


def _fitted_camera(frame: FrameData) -> dict | None:
    """The camera an identifier fitted on the frame, as the frame status records it (None: the declared one)."""
    cam = frame.camera
    if cam is None:
        return None
    return {"focal_px": float(cam.focal_px), "cx": float(cam.cx), "cy": float(cam.cy), "k1": float(cam.k1), "k2": float(cam.k2)}


def _false_match_prob(frame: FrameData) -> float | None:
    """The frame's identification chance probability for its attitude records (None: not checked)."""
    check = frame.identification
    return None if check is None or check.n_matched < 2 else float(check.false_match_prob)


def write_frame(writer: LogWriter, frame: FrameData) -> None:
    """One finished frame's estimates; its ``/estimate/frame`` status last."""
    t0 = int(frame.t0_ns)
    stars = frame.stars if frame.stars is not None else StarTable.empty()
    writer.write_json(TOPIC_EST_STARS, arrays_to_stars(
        frame.index, t0, x=stars.x, y=stars.y, t_ns=stars.t_ns, row_time_ns=stars.row_time_ns, flux=stars.flux,
        peak=stars.peak, npix=stars.npix, saturated=stars.saturated, snr=stars.snr, sigma_px=stars.sigma_px,
        cov_xx=stars.cov_xx, cov_xy=stars.cov_xy, cov_yy=stars.cov_yy,
        vx=stars.vx, vy=stars.vy, catalog_id=stars.catalog_id, ref_icrs=stars.ref_icrs), t0)
    labels = [str(int(c)) if c >= 0 else "?" for c in stars.catalog_id]
    writer.write_annotations(TOPIC_EST_SPOTS, t0, stars.x, stars.y, labels)  # none: clears the last overlay
    for est in frame.attitudes:
        cov = None if est.covariance_rad2 is None else np.asarray(est.covariance_rad2, dtype=float).reshape(-1).tolist()
        writer.write_json(TOPIC_EST_ATTITUDE, AttitudeRecord(
            frame=frame.index, t_ns=int(est.t_ns), q=quat_to_fields(est.q_xyzw) if est.valid else None, valid=bool(est.valid),
            reason=est.reason, n_stars=int(est.n_stars), covariance_rad2=cov,
            gyro_bias_rad_s=None if est.gyro_bias_rad_s is None else [float(v) for v in np.ravel(est.gyro_bias_rad_s)],
            false_match_prob=_false_match_prob(frame)),
            int(est.t_ns))
        if est.valid:
            writer.write_pose(TOPIC_EST_POSE, int(est.t_ns), est.q_xyzw)
    if frame.rate is not None:
        r = frame.rate
        writer.write_json(TOPIC_EST_RATE, RateRecord(
            frame=frame.index, t_ns=int(r.t_ns),
            omega=dict(zip("xyz", map(float, r.omega_rad_s))) if r.valid else None, valid=bool(r.valid), reason=r.reason,
            covariance=None if r.covariance is None else np.asarray(r.covariance, dtype=float).reshape(-1).tolist(),
            iterations=r.iterations), int(r.t_ns))
    n_det = (stars.n + (frame.unmatched.n if frame.unmatched is not None else 0))
    writer.write_json(TOPIC_EST_FRAME, FrameStatus(frame=frame.index, t0_ns=t0, flags=list(frame.flags),
                                                   n_detected=int(n_det), n_identified=int(stars.identified.sum()),
                                                   camera=_fitted_camera(frame), psf_sigma_px=frame.psf_sigma_px), t0)
