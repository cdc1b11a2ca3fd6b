"""The frame source of a run: a recording's frames in log-time order, checked, with their side data.

:func:`open_recording` reads what a run needs to know about a recording before its first frame
(the sensor model it declares, which topic holds its frames). :class:`FrameSource` then replays
it: one :class:`RecordedFrame` per frame message, the frame built from the message, checked by
the :class:`~rollingstar.pipelines.frame_checks.FrameChecker`, carrying the gyro samples logged
since the previous frame (and the truth attitude samples, for pipelines with an oracle stage),
with the truth messages to pass on to the output.
"""
from __future__ import annotations

import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rollingstar.estimators.data import (
    DEFAULT_CENTROID_SIGMA_PX,
    FrameData,
    GyroSamples,
    SensorContext,
    StarTable,
    TruthSamples,
)
from rollingstar.logs.errors import LogFormatError
from rollingstar.logs.reader import LogReader, Message
from rollingstar.logs.records import join_attitude_samples, join_gyro_samples, stars_to_arrays
from rollingstar.logs.replay import FrameMessages, image_from_raw, iter_frames
from rollingstar.logs.topics import (
    TOPIC_CENTROIDS,
    TOPIC_GYRO,
    TOPIC_IMAGE,
    TOPIC_TRUTH_ATTITUDE,
    TRUTH_TOPICS,
)
from rollingstar.pipelines.frame_checks import FrameChecker
from rollingstar.pipelines.interrupt import StopFlag


@dataclass(frozen=True)
class Recording:
    """An opened recording and what a run needs from it before the first frame."""

    path: str | Path  # as given (messages name it so)
    reader: LogReader
    scenario: dict  # the metadata record 'scenario' (its 'yaml' is the sensor model)
    context: SensorContext
    frame_topic: str  # images, or centroids when the recording holds no images
    n_frame_messages: int  # frame messages in the file (duplicates and unreadable ones included), for the progress bar

    @property
    def holds_centroids(self) -> bool:
        """True for a centroid-level recording: the centroiders of a pipeline have nothing to do."""
        return self.frame_topic == TOPIC_CENTROIDS

    @property
    def provides(self) -> frozenset[str]:
        """What the recording holds in place of a stage's output (``Plugin.needs`` words): ``image``; or
        ``spots``, with ``identified`` when its stars arrive identified (:meth:`arrives_identified`)."""
        if not self.holds_centroids:
            return frozenset({"image"})
        return frozenset({"spots", "identified"} if self.arrives_identified() else {"spots"})

    def arrives_identified(self) -> bool:
        """True for an import of astrometry.net tables, and for a recording whose first frame's stars
        all carry a catalogue id and direction (the run then skips the identifiers on such frames).
        A first frame that cannot be read counts as identified: the run itself reports it."""
        if self.reader.metadata().get("import", {}).get("format") == "corr":
            return True
        try:
            first = next(iter(self.reader.messages(topics=[TOPIC_CENTROIDS])), None)
            stars = None if first is None else stars_to_arrays(first.data)
        except ValueError:  # LogFormatError, or a record the reader let through
            return True
        if stars is None or "catalog_id" not in stars or "ref_icrs" not in stars or stars["x"].size == 0:
            return False
        return bool((stars["catalog_id"] >= 0).all() and np.isfinite(stars["ref_icrs"]).all())


def open_recording(path: str | Path) -> Recording:
    """Open ``path``; a :class:`UserError` when it declares no sensor model, a
    :class:`LogFormatError` when it holds no frame."""
    reader = LogReader(path)
    meta = reader.metadata()
    scenario = reader.scenario("import real data with `rollingstar import` so that it does")
    context = SensorContext.from_scenario(scenario)
    if scenario.level == "centroid" and not scenario.noise.centroid_sigma_px:
        warnings.warn(f"{path}: the recording states no centroid noise (scenario noise.centroid_sigma_px is 0): the "
                      f"stages weight stars without their own sigma_px as {DEFAULT_CENTROID_SIGMA_PX:g} px, and the "
                      "attitude covariances they report assume it")
    topics = reader.summary_info().topics
    frame_topic = TOPIC_IMAGE if TOPIC_IMAGE in topics else TOPIC_CENTROIDS
    reader.require_topics([frame_topic])
    total = topics[frame_topic].message_count
    if total == 0:
        raise LogFormatError(f"{path}: the recording holds no frame: no message on {frame_topic} (a frame "
                             f"is one message on {TOPIC_IMAGE} or {TOPIC_CENTROIDS}, docs/log-format.md)")
    return Recording(path, reader, meta["scenario"], context, frame_topic, total)


@dataclass(frozen=True)
class RecordedFrame:
    """One frame message of the recording.

    ``truth``: the truth messages logged with it, to pass on to the output. ``frame``: the frame for
    the stages, or None when it is not to be processed: it was read before the checkpoint the run
    resumed from (its truth is in the messages copied from the partial output: ``truth`` is empty),
    or it is an exact duplicate of the previous frame (``duplicate``, warned).
    """

    truth: tuple[Message, ...]
    frame: FrameData | None
    duplicate: bool = False


class FrameSource:
    """The frames of ``recording`` in log-time order, checked by ``checker``.

    ``with_truth``: frames carry the recording's truth attitude samples (``frame.truth``).
    ``skip``: the first ``skip`` frame messages were read before a checkpoint: they are read past
    without a frame or truth (the checker's state comes from the same checkpoint, their truth was
    copied with the checkpoint's messages). ``delivered``: frames handed to the stages before that
    checkpoint (it numbers the frames of an image recording).

    ``frames_read`` counts the frame messages read (duplicates and skipped ones included),
    ``delivered`` the frames handed on.
    """

    def __init__(self, recording: Recording, checker: FrameChecker, with_truth: bool = False, skip: int = 0,
                 delivered: int = 0) -> None:
        self.recording = recording
        self.checker = checker
        self.with_truth = with_truth
        self.skip = skip
        self.frames_read = 0
        self.delivered = delivered

    def frames(self, max_frames: int | None, stop: StopFlag) -> Iterator[RecordedFrame]:
        """Every frame message in turn; ends before the next one once ``max_frames`` frames were
        delivered or ``stop.requested`` (SIGINT), but never among the skipped ones (a checkpoint
        saved then would pair the restored stages with a source that is not yet where they were)."""
        groups = iter_frames(self.recording.reader, self.recording.frame_topic, [TOPIC_GYRO, *TRUTH_TOPICS],
                             tolerate_bad_side=True)
        for group in groups:
            if self.frames_read >= self.skip and (
                    (max_frames is not None and self.delivered >= max_frames) or stop.requested):
                return
            self.frames_read += 1
            if self.frames_read <= self.skip:
                yield RecordedFrame((), None)
                continue
            truth = tuple(m for topic in TRUTH_TOPICS for m in group.side.get(topic, []))
            frame = self._frame(group)
            if frame is None:
                yield RecordedFrame(truth, None, duplicate=True)
                continue
            self.delivered += 1
            yield RecordedFrame(truth, frame)

    def _frame(self, group: FrameMessages) -> FrameData | None:
        """The checked frame of ``group`` with its side data; None for a duplicate of the previous frame."""
        msg, topic = group.frame, self.recording.frame_topic
        try:
            frame = frame_from_message(msg, topic, self.delivered)
        except LogFormatError as exc:  # a record that cannot be a frame: name the file and frame
            raise LogFormatError(f"{self.recording.path}: {topic} frame {self.delivered}: {exc}") from None
        frame = self.checker.check(frame, msg.data)
        if frame is None:
            return None
        if frame.t0_ns != int(msg.log_time_ns):
            # gyro and truth messages join the frame whose log time follows theirs: a frame logged at
            # another time (a wall clock) would take the wrong ones, silently
            raise LogFormatError(f"{self.recording.path}: {topic} frame {frame.index}: log time {int(msg.log_time_ns)} "
                                 f"ns differs from its t0_ns {frame.t0_ns} ns; a frame message is logged at its t0 "
                                 "(docs/log-format.md), since gyro and truth messages are grouped into frames by "
                                 "log time")
        frame = frame.evolve(gyro=gyro_from_messages(group.side.get(TOPIC_GYRO, [])))
        for side_topic in sorted({t for t, _ in group.dropped}):  # undecodable side messages were skipped (warned)
            frame = frame.flagged(f"side_message_invalid:{side_topic}")
        if self.with_truth:
            frame = frame.evolve(truth=truth_from_messages(group.side.get(TOPIC_TRUTH_ATTITUDE, [])))
        return frame


def frame_from_message(msg: Message, frame_topic: str, ordinal: int) -> FrameData:
    """The frame a recording's image or centroid message holds (``ordinal``: the index of an image frame)."""
    if frame_topic == TOPIC_IMAGE:
        image = image_from_raw(msg)
        return FrameData(index=ordinal, t0_ns=int(msg.log_time_ns), image=image)
    index = int(msg.data.get("frame", ordinal))
    stars, dropped = stars_from_record(msg.data)
    frame = FrameData(index=index, t0_ns=int(msg.data.get("t0_ns", msg.log_time_ns)), stars=stars)
    if dropped:
        warnings.warn(f"{frame_topic} frame {index}: {dropped} centroid(s) with NaN/inf position dropped")
        frame = frame.flagged(f"non_finite_input:{dropped}")
    return frame


def stars_from_record(data: dict) -> tuple[StarTable, int]:
    """The centroids of a star record with a finite position, and how many were dropped."""
    cols = stars_to_arrays(data)
    n = len(cols["x"])
    keep = np.isfinite(cols["x"]) & np.isfinite(cols["y"])
    fields = {k: v for k, v in cols.items()
              if k in StarTable.__dataclass_fields__ and k not in ("x", "y", "t_ns", "row_time_ns")}
    table = StarTable.build(cols["x"], cols["y"], cols["t_ns"], cols.get("row_time_ns"), **fields)
    return table.take(keep), int(n - keep.sum())


def gyro_from_messages(messages) -> GyroSamples:
    """The gyro samples of ``/gyro`` messages in time order (a logger may write its batches out of
    order; each batch's own samples are in order, :class:`~rollingstar.logs.records.GyroSamplesRecord`)."""
    if not messages:
        return GyroSamples.empty()
    samples = _time_ordered(join_gyro_samples(m.record for m in messages))
    return GyroSamples(samples["t_ns"], samples["omega_rad_s"])


def truth_from_messages(messages) -> TruthSamples | None:
    """The truth attitude samples of ``/truth/attitude`` messages in time order; None without any."""
    if not messages:
        return None
    samples = _time_ordered(join_attitude_samples(m.record for m in messages))
    return TruthSamples(samples["t_ns"], samples["q_xyzw"], samples["omega_rad_s"])


def _time_ordered(samples: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Joined samples sorted by ``t_ns`` (stable: samples of equal time keep their order)."""
    t = samples["t_ns"]
    if t.size < 2 or np.all(np.diff(t) >= 0):
        return samples
    order = np.argsort(t, kind="stable")
    return {k: v[order] for k, v in samples.items()}
