"""Checks on every frame of a recording before the stages see it (docs/reliability.md).

- an image whose size differs from the declared sensor (``sensor.width_px`` x ``height_px``,
  zero-size included), or an 8-bit image where the sensor model declares more bits
  (``image.bit_depth``): :class:`~rollingstar.logs.errors.LogFormatError` naming the file, topic, frame,
  what was found and what was expected;
- a frame whose time ``t0`` does not increase: an exact repeat of the previous frame (same time,
  same content) is skipped with a warning; otherwise the recording is out of time order:
  :class:`~rollingstar.logs.errors.LogFormatError`;
- a star whose time ``t_ns`` lies outside its frame's exposure by more than a frame period (times
  in another unit, or copied from another frame): :class:`~rollingstar.logs.errors.LogFormatError`,
  since every stage places the star at that time;
- a gap between frames longer than 1.5 declared frame periods (frames lost or a clock jump): the
  frame is processed and flagged ``time_gap:<ms>`` with a warning, so stages and readers of the
  output know its predecessor is not the previous frame;
- frames over 100 times closer than one camera can take them (:func:`min_frame_spacing_ns`: a row
  cannot expose twice at once, and a frame cannot start before the last one is read out): times
  in another unit (microseconds in ``t0_ns`` are 1000 times closer),
  :class:`~rollingstar.logs.errors.LogFormatError`. Only a unit error is refused: a burst, or a
  sensor model whose exposure is a default and not the camera's, can put frames closer than
  that bound by far less.
"""
from __future__ import annotations

import hashlib
import json
import warnings

import numpy as np

from rollingstar.estimators.data import FrameData
from rollingstar.logs.errors import LogFormatError

GAP_FACTOR = 1.5
UNIT_FACTOR = 0.01  # frames this much closer than one camera allows: times in another unit


class FrameChecker:
    """Stateful per-recording checker; :meth:`check` returns the frame (maybe flagged) or None to skip it."""

    # (earliest, latest) star time relative to t0, ns; None (a checker restored from a checkpoint
    # that does not hold it) leaves star times unchecked
    _star_span_ns: tuple[int, int] | None = None

    def __init__(self, recording, frame_topic: str, context) -> None:
        self.recording = recording
        self.topic = frame_topic
        self.width = int(context.camera.width)
        self.height = int(context.camera.height)
        self.bit_depth = getattr(context, "bit_depth", None)
        self.period_ns = getattr(context.timing, "frame_period_ns", None)
        self.min_gap_ns = min_frame_spacing_ns(context.timing)
        if self.period_ns:
            self._star_span_ns = (-self.period_ns, context.timing.frame_end_ns(0) + self.period_ns)
        self._prev: tuple[int, int] | None = None  # (index, t0_ns) of the previous frame
        self._prev_payload = None  # its content (a digest after a checkpoint round trip, __getstate__)
        self.skipped = 0

    def _where(self, frame: FrameData) -> str:
        return f"{self.recording}: {self.topic} frame {frame.index} (t0 = {frame.t0_ns} ns)"

    def check(self, frame: FrameData, payload) -> FrameData | None:
        if frame.image is not None:
            self._check_image(frame)
        prev = self._prev
        if prev is not None and frame.t0_ns <= prev[1]:
            if frame.t0_ns == prev[1] and _digest(payload) == _digest(self._prev_payload):
                self.skipped += 1
                warnings.warn(f"{self._where(frame)}: duplicate of the previous frame (same time and content) skipped")
                return None
            raise LogFormatError(
                f"{self._where(frame)}: frame time does not increase (previous frame {prev[0]} at t0 = "
                f"{prev[1]} ns); frames must be in time order with distinct times")
        if frame.stars is not None:
            self._check_star_times(frame)
        if prev is not None and self.min_gap_ns and frame.t0_ns - prev[1] < UNIT_FACTOR * self.min_gap_ns:
            raise LogFormatError(
                f"{self._where(frame)}: {frame.t0_ns - prev[1]} ns after the previous frame, over {1 / UNIT_FACTOR:g} times "
                f"closer than the recording's sensor model lets one camera take frames ({self.min_gap_ns * 1e-6:.3g} "
                "ms: its shutter's exposure or its readout of every row): frame times must be in nanoseconds "
                "(t0_ns, t_ns; docs/log-format.md)")
        if prev is not None and self.period_ns:
            gap = frame.t0_ns - prev[1]
            if gap > GAP_FACTOR * self.period_ns:
                ms = gap * 1e-6
                warnings.warn(f"{self._where(frame)}: {ms:.1f} ms after the previous frame, expected "
                              f"{self.period_ns * 1e-6:.1f} ms (the declared frame period): frames lost or a clock "
                              "jump; frame flagged time_gap")
                frame = frame.flagged(f"time_gap:{ms:.0f}ms")
        self._prev, self._prev_payload = (frame.index, frame.t0_ns), payload
        return frame

    def __setstate__(self, state: dict) -> None:
        state.setdefault("min_gap_ns", 0)  # a checkpoint written before this check: frames not checked for it
        self.__dict__.update(state)

    def __getstate__(self) -> dict:
        """For run checkpoints: the previous frame's content as its digest (protobuf messages do not
        pickle; hashing only here keeps the per-frame cost at zero)."""
        state = dict(self.__dict__)
        if state["_prev_payload"] is not None:
            state["_prev_payload"] = _digest(state["_prev_payload"])
        return state

    def _check_star_times(self, frame: FrameData) -> None:
        """Every star's time lies within a frame period of the frame's exposure (row 0's start to the
        last row's end)."""
        t = frame.stars.t_ns
        if self._star_span_ns is None or t.size == 0:
            return
        lo = max(0, frame.t0_ns + self._star_span_ns[0])
        hi = frame.t0_ns + self._star_span_ns[1]
        outside = t[(t < lo) | (t > hi)]
        if outside.size:
            raise LogFormatError(
                f"{self._where(frame)}: a star has t_ns = {int(outside[0])} ns ({outside.size} of {t.size} stars "
                f"outside); expected a time from {lo} to {hi} ns: the frame's exposure, a frame period either side, "
                "in nanoseconds on the frame's clock (docs/log-format.md, rollingstar.Stars)")

    def _check_image(self, frame: FrameData) -> None:
        img = frame.image
        h, w = img.shape
        if (w, h) != (self.width, self.height):
            raise LogFormatError(
                f"{self._where(frame)}: image is {w}x{h} px, the recording's sensor model declares "
                f"{self.width}x{self.height} (sensor.width_px x sensor.height_px in metadata 'scenario')")
        if img.dtype == np.uint8 and self.bit_depth is not None and self.bit_depth > 8:
            raise LogFormatError(
                f"{self._where(frame)}: 8-bit image (mono8), the sensor model declares {self.bit_depth}-bit pixels "
                "(image.bit_depth); expected mono16")


def _digest(payload) -> bytes:
    """SHA-256 of a frame message's content (protobuf bytes, or the record's canonical JSON); a
    digest (bytes) is returned unchanged."""
    if isinstance(payload, bytes):
        return payload
    if hasattr(payload, "SerializeToString"):
        data = payload.SerializeToString(deterministic=True)
    else:
        data = json.dumps(payload, sort_keys=True, default=repr).encode()
    return hashlib.sha256(data).digest()


def min_frame_spacing_ns(timing) -> int:
    """The least time between two frames' starts one camera allows: its exposure (a row cannot
    expose twice at once) or the readout of every row, whichever is longer; 0 without a timing."""
    if timing is None or not hasattr(timing, "exposure_ns"):
        return 0
    return int(max(timing.exposure_ns, timing.rows * timing.effective_line_delay_ns))
