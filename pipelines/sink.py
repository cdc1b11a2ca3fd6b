"""The sink of a run: the output log's estimate topics, and the recording's truth passed through.

:class:`EstimateSink` writes each finished frame (:func:`write_frame`: its stars, spot labels,
attitude estimates and poses, rate, and last its ``/estimate/frame`` status) and counts what it
wrote. The writer's own :class:`~rollingstar.logs.digest.MessageDigest` (``LogWriter(digest=True)``)
counts and hashes every message, for the checkpoints of ``run --resume``.
"""
from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from rollingstar.estimators.data import FrameData, StarTable
from rollingstar.logs.reader import Message
from rollingstar.logs.records import AttitudeEstimate as AttitudeRecord
from rollingstar.logs.records import FrameStatus, arrays_to_stars
from rollingstar.logs.records import RateEstimate as RateRecord
from rollingstar.logs.topics import (
    TOPIC_EST_ATTITUDE,
    TOPIC_EST_FRAME,
    TOPIC_EST_POSE,
    TOPIC_EST_RATE,
    TOPIC_EST_SPOTS,
    TOPIC_EST_STARS,
)
from rollingstar.logs.writer import LogWriter
from rollingstar.pipelines.outcomes import Outcomes
from rollingstar.sensors.conventions import quat_to_fields


def new_counts() -> Outcomes:
    """The sink's counters before the first frame (:class:`~rollingstar.pipelines.outcomes.Outcomes`)."""
    return Outcomes()


class EstimateSink:
    """Writes finished frames and truth messages to ``writer``.

    ``counts`` (see :func:`new_counts`) go on from a checkpoint's when given.
    """

    def __init__(self, writer: LogWriter, counts: Outcomes | None = None) -> None:
        self.writer = writer
        self.counts = counts if counts is not None else new_counts()

    def write_truth(self, messages: Iterable[Message]) -> None:
        """Pass the recording's truth messages through."""
        for m in messages:
            self.writer.write_json(m.topic, m.data, m.log_time_ns)

    def write(self, frames: Iterable[FrameData]) -> None:
        """Write and count finished frames."""
        for frame in frames:
            write_frame(self.writer, frame)
            self.counts.add(frame.flags, [(a.valid, a.reason) for a in frame.attitudes])


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
                                                   camera=_fitted_camera(frame)), t0)
