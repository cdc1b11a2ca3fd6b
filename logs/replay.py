"""Replay a log frame by frame: group side-topic messages with the frame they lead up to.

:func:`iter_frames` streams the log (through the index when the file has one) and yields one
:class:`FrameMessages` per frame message; :func:`image_from_raw` turns a ``foxglove.RawImage``
into a numpy array.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Any, Iterable, Iterator

import numpy as np

from .errors import LogFormatError
from .reader import LogReader, Message
from .topics import TOPIC_IMAGE


@dataclass(frozen=True)
class FrameMessages:
    """One frame message and, per side topic, the messages that belong to it.

    ``side[topic]`` holds the messages whose log time is after the previous frame's log time and
    at or before this frame's (for the first frame: every earlier message), in log-time order.
    Every requested side topic has an entry, possibly empty.
    """

    index: int
    frame: Message
    side: dict[str, tuple[Message, ...]] = field(default_factory=dict)
    dropped: tuple[tuple[str, str], ...] = ()  # (topic, reason) of side messages that could not be decoded

    @property
    def t0_ns(self) -> int:
        return self.frame.log_time_ns


def iter_frames(reader: LogReader, frame_topic: str = TOPIC_IMAGE,
                side_topics: Iterable[str] = (), *, tolerate_bad_side: bool = False) -> Iterator[FrameMessages]:
    """Yield a :class:`FrameMessages` per message on ``frame_topic``, in log-time order.

    Side messages logged after the last frame belong to no frame and are not yielded. Two different frame
    messages with the same log time raise :class:`LogFormatError` (frame times must increase); an identical repeat is skipped with a DuplicateFrameWarning.
    With ``tolerate_bad_side`` a side message that cannot be decoded or validated (e.g. a NaN in a
    gyro record) is left out with a :class:`BadSideMessageWarning` and listed in the frame's
    ``dropped`` (topic, reason), so the consumer can flag that frame; a bad *frame* message always raises.
    """
    side = tuple(side_topics)
    if frame_topic in side:
        raise ValueError(f"frame topic {frame_topic} cannot also be a side topic")
    reader.require_topics([frame_topic])
    buckets: dict[str, list[Message]] = {t: [] for t in side}
    pending: Message | None = None
    index = 0
    dropped: list[tuple[str, str]] = []
    for msg in _decoded(reader, (frame_topic, *side), frame_topic, tolerate_bad_side):
        if pending is not None and msg.log_time_ns > pending.log_time_ns:
            yield FrameMessages(index, pending, {t: tuple(v) for t, v in buckets.items()}, tuple(dropped))
            index += 1
            buckets = {t: [] for t in side}
            dropped = []
            pending = None
        if isinstance(msg, _Dropped):
            dropped.append((msg.topic, msg.reason))
            continue
        if msg.topic == frame_topic:
            if pending is not None:
                if _payload(msg) == _payload(pending):  # an exact duplicate (e.g. a re-sent frame): keep one
                    warnings.warn(f"{reader.path}: duplicate frame on {frame_topic} at log time {msg.log_time_ns} ns "
                                  "(identical content) skipped", DuplicateFrameWarning, stacklevel=2)
                    continue
                raise LogFormatError(
                    f"{reader.path}: two messages on {frame_topic} at log time {msg.log_time_ns} ns with different "
                    "content; frame log times must strictly increase")
            pending = msg
        else:
            buckets[msg.topic].append(msg)
    if pending is not None:
        yield FrameMessages(index, pending, {t: tuple(v) for t, v in buckets.items()}, tuple(dropped))


@dataclass(frozen=True)
class _Dropped:
    topic: str
    log_time_ns: int
    reason: str


def _decoded(reader: LogReader, topics: tuple[str, ...], frame_topic: str, tolerate: bool):
    """Decoded messages; with ``tolerate``, side messages that fail to decode become :class:`_Dropped`."""
    if not tolerate:
        yield from reader.messages(topics=topics)
        return
    for raw in reader._raw_messages(topics):  # same package: decode one by one to keep going past a bad one
        try:
            yield reader._decode(raw)
        except LogFormatError as exc:
            if raw.channel.topic == frame_topic:
                raise
            warnings.warn(f"{exc}; message skipped", BadSideMessageWarning, stacklevel=3)
            yield _Dropped(raw.channel.topic, raw.message.log_time, str(exc))


class BadSideMessageWarning(UserWarning):
    """A side-topic message (gyro, truth) that could not be decoded was skipped; its frame is flagged."""


def _payload(msg: Message):
    data = msg.data
    return data.SerializeToString(deterministic=True) if hasattr(data, "SerializeToString") else data


class DuplicateFrameWarning(UserWarning):
    """A frame message repeated with identical content was skipped."""


_BYTES_PER_PIXEL = {"mono8": 1, "mono16": 2}


def image_from_raw(msg: Message | Any, topic: str | None = None) -> np.ndarray:
    """A (H, W) uint8 / uint16 array from a ``foxglove.RawImage`` (a :class:`Message` or the protobuf).

    Supports ``mono8`` and little-endian ``mono16``; rows may be padded (``step`` >= width * bytes
    per pixel). Raises :class:`LogFormatError` naming the topic and frame time on a size mismatch.
    """
    if isinstance(msg, Message):
        raw, topic, t_ns = msg.data, msg.topic, msg.log_time_ns
    else:
        raw = msg
        t_ns = raw.timestamp.seconds * 1_000_000_000 + raw.timestamp.nanos
    where = f"image on {topic or '(unknown topic)'} at {t_ns} ns"
    bpp = _BYTES_PER_PIXEL.get(raw.encoding)
    if bpp is None:
        raise LogFormatError(f"{where}: encoding {raw.encoding!r} not supported (expected mono8 or mono16)")
    width, height, step = int(raw.width), int(raw.height), int(raw.step)
    if step < width * bpp:
        raise LogFormatError(f"{where}: step {step} is less than width {width} x {bpp} bytes per pixel")
    if len(raw.data) != step * height:
        hint = ""
        if bpp == 2 and len(raw.data) == width * height:
            hint = " (that is the size of 8-bit pixels: an 8-bit image declared as mono16?)"
        elif bpp == 1 and len(raw.data) == 2 * width * height:
            hint = " (that is the size of 16-bit pixels: a 16-bit image declared as mono8?)"
        raise LogFormatError(
            f"{where}: {raw.encoding} {width}x{height} with step {step} needs {step * height} bytes, "
            f"data has {len(raw.data)}{hint}")
    dtype = np.dtype("<u2") if bpp == 2 else np.dtype(np.uint8)
    rows = np.frombuffer(raw.data, dtype=np.uint8).reshape(height, step)[:, : width * bpp]
    image = np.ascontiguousarray(rows).view(dtype).reshape(height, width)
    return image.astype(np.uint16) if bpp == 2 else image.copy()
