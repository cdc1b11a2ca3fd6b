"""Write rollingstar MCAP logs (docs/log-format.md).

:class:`LogWriter` writes straight to the final path, in zstd-compressed chunks of about 256 KiB,
and hands every finished chunk to the operating system at once, so a killed writer loses at most
the chunk in progress; the reader recovers everything before it. Leaving the ``with`` block
(normally or through an exception) always writes the summary and footer.
"""
from __future__ import annotations

import importlib.metadata
import json
import math
import os
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from foxglove_schemas_protobuf.CircleAnnotation_pb2 import CircleAnnotation
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.Point2_pb2 import Point2
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.TextAnnotation_pb2 import TextAnnotation
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer
from mcap_protobuf.schema import register_schema

from rollingstar.errors import UserError
from rollingstar.sensors.conventions import pixel_to_foxglove

from .digest import MessageDigest
from .errors import LogWriteError
from .records import FORMAT_VERSION, TOPIC_RECORDS, _Record

KINDS = ("simulation", "run", "import")
RECORDING = (MCAP0_MAGIC, "an MCAP recording")  # what an output a recording replaces must be (outputs.safe_output)
CHUNK_SIZE = 256 * 1024
PROFILE = "rollingstar"


def software_version() -> str:
    """The installed rollingstar version, or ``"0+unknown"`` when not installed."""
    try:
        return importlib.metadata.version("rollingstar")
    except importlib.metadata.PackageNotFoundError:
        return "0+unknown"


def creation_time() -> datetime:
    """Now (UTC), or ``SOURCE_DATE_EPOCH`` (reproducible-builds.org) when set: the only wall-clock
    value in a log, so two runs with the same inputs and that variable give byte-identical files."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    if epoch is not None:
        try:
            return datetime.fromtimestamp(int(epoch), timezone.utc)
        except ValueError:
            raise UserError(f"SOURCE_DATE_EPOCH must be a whole number of seconds, got {epoch[:40]!r}") from None
    return datetime.now(timezone.utc)


def timestamp_ns(t_ns: int) -> Timestamp:
    """Integer ns to a protobuf Timestamp (seconds, nanos), for non-negative times."""
    t = int(t_ns)
    if t < 0:
        raise ValueError(f"times must be >= 0 ns to fit foxglove timestamps, got {t}")
    return Timestamp(seconds=t // 1_000_000_000, nanos=t % 1_000_000_000)


class _UnbufferedFile:
    """The output file, with every write handed to the OS at once (no user-space buffer).

    The mcap writer builds a whole chunk in memory and writes it in one call, so this only costs
    a few system calls per chunk and makes finished chunks survive a killed process.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self._pos = 0
        self.failed: OSError | None = None

    def write(self, data: bytes) -> int:
        if self.failed is not None:
            raise self.failed
        view = memoryview(data)
        while view:
            try:
                n = os.write(self._fd, view)
            except OSError as exc:  # disk full, I/O error: what is on disk stays; no further writes
                self.failed = LogWriteError(
                    f"cannot write log {self.path}: {exc.strerror or exc} after {self._pos} bytes; the chunks "
                    "finished before stay readable (`rollingstar info` reads them), the rest was not written")
                self.failed.errno = exc.errno
                raise self.failed from exc
            view = view[n:]
            self._pos += n
        return len(data)

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        pass

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


def _check_metadata(name: str, data: Mapping[str, Any]) -> dict[str, str]:
    if not isinstance(data, Mapping):
        raise TypeError(f"metadata {name!r} must be a mapping of str to str, got {type(data).__name__}")
    bad = [k for k, v in data.items() if not isinstance(k, str) or not isinstance(v, str)]
    if bad:
        raise TypeError(f"metadata {name!r}: keys and values must be str (offending keys: {bad!r})")
    return dict(data)


class LogWriter:
    """Write one rollingstar log. Use as a context manager::

        with LogWriter(path, kind="simulation", metadata={"scenario": {"yaml": text}}) as w:
            w.write_image("/camera/image", image, t0_ns)
            w.write_json("/truth/stars", stars_record)   # log time from the record

    ``metadata`` maps record names to str->str dicts (``scenario``, ``pipeline``, ``sensor``);
    the ``rollingstar`` record (format version, software version, creation time, kind) is
    written by the writer. Metadata is written at once, before any message. ``digest=True``: keep a
    :class:`~rollingstar.logs.digest.MessageDigest` of every message written (:attr:`digest`).
    """

    def __init__(self, path: str | os.PathLike, kind: str = "simulation",
                 metadata: Mapping[str, Mapping[str, str]] | None = None, *,
                 chunk_size: int = CHUNK_SIZE, compression: str = "zstd", digest: bool = False) -> None:
        self.path = Path(path)
        self.digest = MessageDigest() if digest else None
        if kind not in KINDS:
            raise ValueError(f"log kind must be one of {KINDS}, got {kind!r}")
        if compression not in ("zstd", "lz4", "none"):
            raise ValueError(f"compression must be 'zstd', 'lz4' or 'none', got {compression!r}")
        checked = {name: _check_metadata(name, data) for name, data in (metadata or {}).items()}
        if "rollingstar" in checked:
            raise ValueError("the 'rollingstar' metadata record is written by LogWriter itself")
        parent = self.path.parent
        if not parent.is_dir():
            raise FileNotFoundError(f"cannot write log {self.path}: directory {parent} does not exist")
        try:
            self._file = _UnbufferedFile(self.path)
        except OSError as exc:
            raise OSError(exc.errno, f"cannot write log {self.path}: {exc.strerror}") from exc
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
        self._mcap = Writer(self._file, chunk_size=chunk_size, compression=comp[compression])
        self._mcap.start(profile=PROFILE, library=f"rollingstar {software_version()}")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}
        self._topics: dict[int, str] = {}  # channel id -> topic
        self._closed = False
        self.add_metadata("rollingstar", {
            "format_version": FORMAT_VERSION,
            "software_version": software_version(),
            "created_utc": creation_time().isoformat(timespec="seconds"),
            "kind": kind,
        })
        for name, data in checked.items():
            self.add_metadata(name, data)

    # --- context manager ---------------------------------------------------------------------
    def __enter__(self) -> "LogWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()

    def close(self) -> None:
        """Write the summary and footer and close the file (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            if self._file.failed is None:  # after a failed write the summary cannot be written either
                self._mcap.finish()
        finally:
            self._file.close()

    # --- registration ------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f"log {self.path} is closed")

    def _channel(self, topic: str, schema_name: str, register) -> int:
        """Channel id for ``topic``, registering its schema and channel the first time."""
        known = self._channels.get(topic)
        if known is not None:
            if known[1] != schema_name:
                raise ValueError(f"{self.path}: topic {topic} carries {known[1]}, cannot write {schema_name}")
            return known[0]
        if schema_name not in self._schemas:
            self._schemas[schema_name] = register()
        encoding = "json" if schema_name.startswith("rollingstar.") else "protobuf"
        channel_id = self._mcap.register_channel(topic=topic, message_encoding=encoding,
                                                 schema_id=self._schemas[schema_name])
        self._channels[topic] = (channel_id, schema_name)
        self._topics[channel_id] = topic
        return channel_id

    def _add(self, channel_id: int, log_time_ns: int, data: bytes) -> None:
        t = int(log_time_ns)
        if t < 0:
            raise ValueError(f"{self.path}: log times must be >= 0 ns, got {t}")
        self._mcap.add_message(channel_id=channel_id, log_time=t, publish_time=t, data=data)
        if self.digest is not None:
            self.digest.add(self._topics[channel_id], t, data)

    def _write_proto(self, topic: str, message: Any, log_time_ns: int) -> None:
        self._check_open()
        cls = type(message)
        channel_id = self._channel(topic, cls.DESCRIPTOR.full_name, lambda: register_schema(self._mcap, cls))
        self._add(channel_id, log_time_ns, message.SerializeToString())

    # --- public writing API ------------------------------------------------------------------
    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Write an MCAP metadata record (str -> str)."""
        self._check_open()
        self._mcap.add_metadata(name, _check_metadata(name, data))

    def write_json(self, topic: str, record: _Record | Mapping[str, Any], log_time_ns: int | None = None) -> None:
        """Write a JSON record (a model from :mod:`rollingstar.logs.records`).

        A plain dict is accepted on the standard topics (``TOPIC_RECORDS``, e.g. copying
        ``Message.data`` from one log to another) and validated against the topic's model.
        ``log_time_ns`` defaults to the record's own time as the format prescribes
        (``t0_ns`` for Stars and FrameStatus, the last sample for gyro, ...).
        """
        self._check_open()
        if isinstance(record, Mapping):
            model = TOPIC_RECORDS.get(topic)
            if model is None:
                raise TypeError(f"write_json({topic!r}): a dict is only accepted on the standard topics "
                                f"{sorted(TOPIC_RECORDS)}; pass a rollingstar.logs.records model")
            record = model.model_validate(dict(record))
        if not isinstance(record, _Record):
            raise TypeError(f"write_json({topic!r}) needs a rollingstar.logs.records model, got {type(record).__name__}")
        cls = type(record)

        def register() -> int:
            schema = json.dumps(cls.model_json_schema()).encode()
            return self._mcap.register_schema(name=cls.SCHEMA_NAME, encoding="jsonschema", data=schema)

        channel_id = self._channel(topic, cls.SCHEMA_NAME, register)
        t = record.default_log_time_ns() if log_time_ns is None else log_time_ns
        self._add(channel_id, t, record.model_dump_json().encode())

    def write_message(self, message) -> None:
        """Copy a message read by :class:`rollingstar.logs.reader.LogReader` (JSON record or protobuf) into this log."""
        if hasattr(message.data, "SerializeToString"):
            self._write_proto(message.topic, message.data, message.log_time_ns)
        else:
            self.write_json(message.topic, message.data, message.log_time_ns)

    def write_image(self, topic: str, image: np.ndarray, t_ns: int, frame_id: str = "camera") -> None:
        """Write a ``foxglove.RawImage`` (mono8 for uint8, little-endian mono16 for uint16)."""
        img = np.asarray(image)
        if img.ndim != 2:
            raise ValueError(f"{topic}: image must be 2-D (H, W), got shape {img.shape}")
        if img.dtype == np.uint8:
            encoding, data = "mono8", np.ascontiguousarray(img).tobytes()
        elif img.dtype == np.uint16:
            encoding, data = "mono16", np.ascontiguousarray(img, dtype="<u2").tobytes()
        else:
            raise ValueError(f"{topic}: image dtype must be uint8 or uint16, got {img.dtype}")
        height, width = img.shape
        msg = RawImage(timestamp=timestamp_ns(t_ns), frame_id=frame_id, width=width, height=height,
                       encoding=encoding, step=width * img.itemsize, data=data)
        self._write_proto(topic, msg, t_ns)

    def write_pose(self, topic: str, t_ns: int, q_xyzw, frame_id: str = "icrs") -> None:
        """Write a ``foxglove.PoseInFrame`` at the origin with orientation ``q_xyzw`` (camera-to-ICRS)."""
        q = np.asarray(q_xyzw, dtype=float).reshape(-1)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or abs(np.linalg.norm(q) - 1.0) > 1e-6:
            raise ValueError(f"{topic}: pose needs a finite unit quaternion (x, y, z, w), got {q_xyzw!r}")
        msg = PoseInFrame(timestamp=timestamp_ns(t_ns), frame_id=frame_id)
        o = msg.pose.orientation
        o.x, o.y, o.z, o.w = (float(v) for v in q)
        msg.pose.position.x = msg.pose.position.y = msg.pose.position.z = 0.0
        self._write_proto(topic, msg, t_ns)

    def write_annotations(self, topic: str, t_ns: int, x, y, labels: Sequence[str | None] | None = None,
                          diameter_px: float = 12.0) -> None:
        """Write a ``foxglove.ImageAnnotations``: a circle at every (x, y) and its label beside it.

        ``x, y`` are pixels in the project's convention (pixel centres at integers), written in
        Foxglove's (origin at the top-left corner of the top-left pixel) by
        :func:`~rollingstar.sensors.conventions.pixel_to_foxglove`. Points with a NaN coordinate
        are skipped; a ``None`` or empty label draws no text. No points give an empty message,
        which clears the previous frame's overlay in Foxglove.
        """
        xs, ys = pixel_to_foxglove(np.asarray(x, dtype=float).reshape(-1), np.asarray(y, dtype=float).reshape(-1))
        if xs.shape != ys.shape:
            raise ValueError(f"{topic}: x and y differ in length ({xs.size} vs {ys.size})")
        if labels is not None and len(labels) != xs.size:
            raise ValueError(f"{topic}: {len(labels)} labels for {xs.size} points")
        stamp = timestamp_ns(t_ns)
        outline = Color(r=0.1, g=1.0, b=0.3, a=1.0)
        msg = ImageAnnotations()
        for i, (px, py) in enumerate(zip(xs.tolist(), ys.tolist())):
            if not (math.isfinite(px) and math.isfinite(py)):
                continue
            msg.circles.append(CircleAnnotation(
                timestamp=stamp, position=Point2(x=px, y=py), diameter=diameter_px, thickness=1.5,
                outline_color=outline, fill_color=Color(r=0, g=0, b=0, a=0)))
            label = None if labels is None else labels[i]
            if label:
                msg.texts.append(TextAnnotation(
                    timestamp=stamp, position=Point2(x=px + diameter_px / 2 + 2, y=py),
                    text=str(label), font_size=12.0, text_color=outline,
                    background_color=Color(r=0, g=0, b=0, a=0.5)))
        self._write_proto(topic, msg, t_ns)
