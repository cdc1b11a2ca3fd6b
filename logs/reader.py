"""Read rollingstar MCAP logs (docs/log-format.md), including damaged ones.

A complete file is read through its index, streaming one chunk at a time in log-time order. A
file without a valid footer (a killed writer) is read by a linear pass over its records that
keeps every complete message before the cut and warns with :class:`TruncatedLogWarning`. A chunk
that fails to decompress or fails its CRC is skipped with a warning naming its byte offset.
Anything that is not a rollingstar log at all raises :class:`LogFormatError`.
"""
from __future__ import annotations

import dataclasses
import heapq
import io
import json
import os
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Iterator

import lz4.frame
import numpy as np
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.reader import FOOTER_SIZE, SeekingReader
from mcap.records import Channel, Chunk, ChunkIndex, Metadata, Schema
from mcap.records import Message as McapMessage
from mcap.stream_reader import MAGIC_SIZE, breakup_chunk
from mcap_protobuf.decoder import DecoderFactory
from pydantic import ValidationError

from rollingstar.errors import UserError
from rollingstar.sensors.scenario import ScenarioConfig, scenario_from_yaml

from .errors import LogFormatError, TruncatedLogWarning
from .records import (
    FORMAT_VERSION,
    RECORD_TYPES,
    TOPIC_RECORDS,
    join_attitude_samples,
    join_gyro_samples,
    stars_to_arrays,
)
from .topics import TOPIC_EST_POSE, TOPIC_EST_SPOTS, TOPIC_GYRO, TOPIC_IMAGE, TOPIC_TRUTH_ATTITUDE

MAGIC = b"\x89MCAP0\r\n"
# The schema of every standard topic (docs/log-format.md); another schema there is an unknown version.
STANDARD_SCHEMAS = {**{topic: model.SCHEMA_NAME for topic, model in TOPIC_RECORDS.items()},
                    TOPIC_IMAGE: "foxglove.RawImage", TOPIC_EST_POSE: "foxglove.PoseInFrame",
                    TOPIC_EST_SPOTS: "foxglove.ImageAnnotations"}
# The message encoding of every standard topic: its schema can only be decoded from this one.
STANDARD_ENCODINGS = {topic: "json" if topic in TOPIC_RECORDS else "protobuf" for topic in STANDARD_SCHEMAS}
_KNOWN_MAJOR, _KNOWN_MINOR = (int(p) for p in FORMAT_VERSION.split("."))


@dataclass(frozen=True)
class Message:
    """One decoded message.

    ``data`` is the JSON object (dict) for JSON channels, the protobuf message for protobuf
    channels, and the raw bytes otherwise. ``record`` is the validated pydantic model for the
    rollingstar JSON schemas (None for other schemas).
    """

    topic: str
    log_time_ns: int
    schema_name: str
    data: Any
    record: Any = None


@dataclass(frozen=True)
class TopicInfo:
    """Per-topic summary of a log."""

    topic: str
    schema_name: str
    encoding: str
    message_count: int
    start_ns: int | None
    end_ns: int | None


@dataclass(frozen=True)
class LogInfo:
    """Summary of a whole log (``rollingstar info``)."""

    path: Path
    format_version: str | None
    truncated: bool
    message_count: int
    start_ns: int | None
    end_ns: int | None
    topics: dict[str, TopicInfo]
    """Topic -> its summary, sorted by topic name."""


@dataclass(frozen=True)
class _Raw:
    schema: Schema | None
    channel: Channel
    message: McapMessage


MAX_CHUNK_ENV = "ROLLINGSTAR_MAX_CHUNK_MIB"
DEFAULT_MAX_CHUNK_MIB = 1024


def default_max_chunk_bytes() -> int:
    """The ceiling on one chunk's uncompressed size: ``ROLLINGSTAR_MAX_CHUNK_MIB`` (MiB), default 1 GiB."""
    text = os.environ.get(MAX_CHUNK_ENV)
    try:
        mib = DEFAULT_MAX_CHUNK_MIB if text is None else int(text)
    except ValueError:
        raise LogFormatError(f"{MAX_CHUNK_ENV} must be a whole number of MiB, got {text[:40]!r}") from None
    return max(mib, 1) << 20


def _decompressed(chunk: Chunk) -> Chunk:
    """``chunk`` with its data decompressed, reading at most one byte more than it declares (the
    compressed frames' own size headers are not trusted: a small chunk may claim to expand to GiB)."""
    if chunk.compression not in ("zstd", "lz4"):
        return chunk
    limit = chunk.uncompressed_size
    if chunk.compression == "zstd":
        data = zstandard.ZstdDecompressor().stream_reader(io.BytesIO(chunk.data)).read(limit + 1)
    else:
        data = lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=limit + 1)
    if len(data) != limit:
        raise ValueError(f"decompresses to {'more' if len(data) > limit else len(data)} bytes, "
                         f"it declares {limit}")
    return dataclasses.replace(chunk, compression="", data=data)


class LogReader:
    """Read a rollingstar log.

    ``LogReader(path)`` checks the magic and the ``rollingstar`` metadata (format version)
    at once. Set ``check_version=False`` to read a plain MCAP file without that record.
    """

    def __init__(self, path: str | os.PathLike, *, check_version: bool = True, max_chunk_bytes: int | None = None
                 ) -> None:
        self.path = Path(path)
        self.max_chunk_bytes = max_chunk_bytes if max_chunk_bytes is not None else default_max_chunk_bytes()
        if self.path.exists() and not self.path.is_file():
            raise LogFormatError(f"{self.path} is not a regular file (a folder, pipe or device): expected an MCAP file")
        try:
            size = self.path.stat().st_size
            with open(self.path, "rb") as f:
                head = f.read(MAGIC_SIZE)
                f.seek(max(0, size - MAGIC_SIZE))
                tail = f.read(MAGIC_SIZE)
        except FileNotFoundError:
            raise FileNotFoundError(f"log file {self.path} does not exist") from None
        if head != MAGIC:
            raise LogFormatError(f"{self.path} is not an MCAP file (it does not start with the MCAP magic bytes)")
        self._summary = None
        self._truncated = False
        self._streamed: tuple[dict[int, Schema], dict[int, Channel], list[McapMessage], list[Metadata]] | None = None
        self._streamed_in_write_order: list[McapMessage] = []
        if size >= 2 * MAGIC_SIZE + FOOTER_SIZE and tail == MAGIC:
            try:
                self._summary = self._read_summary()
            except Exception:  # any garbage where a footer should be means: not finished
                self._summary = None
                self._truncated = True
        else:
            self._truncated = True
        if self._truncated:
            warnings.warn(
                f"{self.path} has no valid footer (the writer was stopped before finishing); "
                "reading every complete message before the cut",
                TruncatedLogWarning, stacklevel=2)
        self._decoders = DecoderFactory()
        self._decoder_cache: dict[int, Any] = {}
        self._warned_channels: set[int] = set()
        self._metadata = self._read_metadata()
        self.format_version = self._metadata.get("rollingstar", {}).get("format_version")
        self._ignore_unknown_fields = False
        if check_version:
            self._check_version()

    # --- low level: summary, records ------------------------------------------------------------
    def _read_summary(self):
        """The summary section (schemas, channels, chunk and metadata indexes), or None."""
        with open(self.path, "rb") as f:
            return SeekingReader(f).get_summary()

    def _iter_records(self) -> Iterator[tuple[int, Any]]:
        """Linear pass over the top-level records: (byte offset, record); stops at a cut."""
        size = self.path.stat().st_size
        with open(self.path, "rb") as f:
            f.seek(MAGIC_SIZE)
            while True:
                offset = f.tell()
                head = f.read(9)
                if len(head) < 9:
                    return
                opcode, length = head[0], struct.unpack("<Q", head[1:])[0]
                if length > size - offset - 9:  # runs past the end: a cut (or a damaged length); never allocate it
                    return
                body = f.read(length)
                if opcode == Opcode.FOOTER:
                    return
                try:
                    record = _parse_record(opcode, body)
                except Exception:
                    warnings.warn(f"{self.path}: unreadable record (opcode {opcode}) at byte offset {offset}; skipped",
                                  TruncatedLogWarning, stacklevel=3)
                    continue
                if record is not None:
                    yield offset, record

    def _stream_all(self):
        """Everything from a linear pass (used when the file has no usable index)."""
        if self._streamed is None:
            schemas: dict[int, Schema] = {}
            channels: dict[int, Channel] = {}
            messages: list[tuple[int, int, int, McapMessage]] = []
            metadata: list[Metadata] = []
            order = 0
            for offset, record in self._iter_records():
                items = [record]
                if isinstance(record, Chunk):
                    items = self._open_chunk(record, offset)
                for item in items:
                    if isinstance(item, Schema):
                        schemas[item.id] = item
                    elif isinstance(item, Channel):
                        channels[item.id] = item
                    elif isinstance(item, McapMessage):
                        messages.append((item.log_time, order, item))
                        order += 1
                    elif isinstance(item, Metadata):
                        metadata.append(item)
            self._streamed_in_write_order = [m[2] for m in messages]
            messages.sort(key=lambda m: (m[0], m[1]))
            self._streamed = (schemas, channels, [m[2] for m in messages], metadata)
        return self._streamed

    def _open_chunk(self, chunk: Chunk, offset: int) -> list:
        """The records of a chunk; [] with a warning when it is damaged. A chunk that declares more
        uncompressed bytes than :data:`max_chunk_bytes` is an error: nothing is allocated for it."""
        if chunk.uncompressed_size > self.max_chunk_bytes:
            raise LogFormatError(
                f"{self.path}: the chunk at byte offset {offset} declares {chunk.uncompressed_size} bytes "
                f"uncompressed, more than the limit of {self.max_chunk_bytes} (a writer's chunks are a few MB; "
                f"set {MAX_CHUNK_ENV} to a number of MiB to read larger ones)")
        try:
            return breakup_chunk(_decompressed(chunk), validate_crc=True)
        except Exception as exc:
            warnings.warn(f"{self.path}: damaged chunk at byte offset {offset} skipped ({exc})",
                          TruncatedLogWarning, stacklevel=4)
            return []

    def _indexed_raw(self, topics: set[str] | None) -> Iterator[_Raw]:
        """Messages through the chunk index, merged across chunks in log-time order."""
        summary = self._summary
        wanted = None
        if topics is not None:
            wanted = {cid for cid, ch in summary.channels.items() if ch.topic in topics}
        chunks: list[ChunkIndex] = sorted(
            (ci for ci in summary.chunk_indexes
             if wanted is None or not ci.message_index_offsets or wanted & set(ci.message_index_offsets)),
            key=lambda ci: (ci.message_start_time, ci.chunk_start_offset))
        heap: list[tuple[int, int, int, McapMessage]] = []
        i = 0
        with open(self.path, "rb") as f:
            while i < len(chunks) or heap:
                while i < len(chunks) and (not heap or chunks[i].message_start_time <= heap[0][0]):
                    ci = chunks[i]
                    i += 1
                    for index, rec in enumerate(self._load_chunk(f, ci)):
                        if isinstance(rec, McapMessage) and (wanted is None or rec.channel_id in wanted):
                            heapq.heappush(heap, (rec.log_time, ci.chunk_start_offset, index, rec))
                if heap:
                    msg = heapq.heappop(heap)[3]
                    raw = self._resolve(msg, summary.schemas, summary.channels)
                    if raw is not None:
                        yield raw

    def _load_chunk(self, f, ci: ChunkIndex) -> list:
        try:
            f.seek(ci.chunk_start_offset)
            head = f.read(9)
            if len(head) < 9 or head[0] != Opcode.CHUNK:
                raise ValueError("no chunk record at the indexed offset")
            length = struct.unpack("<Q", head[1:])[0]
            body = f.read(length)
            if len(body) < length:
                raise ValueError("chunk runs past the end of the file")
            chunk = Chunk.read(ReadDataStream(io.BytesIO(body)))
            if chunk.uncompressed_size != ci.uncompressed_size:
                raise ValueError(f"it declares {chunk.uncompressed_size} uncompressed bytes, its index "
                                 f"{ci.uncompressed_size}")
        except Exception as exc:
            warnings.warn(f"{self.path}: damaged chunk at byte offset {ci.chunk_start_offset} skipped ({exc})",
                          TruncatedLogWarning, stacklevel=4)
            return []
        return self._open_chunk(chunk, ci.chunk_start_offset)

    def _resolve(self, msg: McapMessage, schemas, channels) -> _Raw | None:
        channel = channels.get(msg.channel_id)
        if channel is None:
            if msg.channel_id not in self._warned_channels:
                self._warned_channels.add(msg.channel_id)
                warnings.warn(f"{self.path}: messages on channel {msg.channel_id} skipped: its channel record "
                              "is missing (lost in a damaged chunk)", TruncatedLogWarning, stacklevel=4)
            return None
        return _Raw(schemas.get(channel.schema_id), channel, msg)

    def _raw_messages(self, topics: Iterable[str] | None = None) -> Iterator[_Raw]:
        wanted = None if topics is None else set([topics] if isinstance(topics, str) else topics)
        if self._summary is not None and self._summary.chunk_indexes:
            yield from self._indexed_raw(wanted)
            return
        schemas, channels, messages, _ = self._stream_all()
        for msg in messages:
            raw = self._resolve(msg, schemas, channels)
            if raw is not None and (wanted is None or raw.channel.topic in wanted):
                yield raw

    def _raw_in_write_order(self) -> Iterator[_Raw]:
        """Every message in file order: chunk after chunk, each chunk's messages as they were added."""
        if self._summary is not None and self._summary.chunk_indexes:
            summary = self._summary
            with open(self.path, "rb") as f:
                for ci in sorted(summary.chunk_indexes, key=lambda ci: ci.chunk_start_offset):
                    for rec in self._load_chunk(f, ci):
                        raw = self._resolve(rec, summary.schemas, summary.channels) \
                            if isinstance(rec, McapMessage) else None
                        if raw is not None:
                            yield raw
            return
        schemas, channels, _, _ = self._stream_all()
        for msg in self._streamed_in_write_order:
            raw = self._resolve(msg, schemas, channels)
            if raw is not None:
                yield raw

    # --- metadata and version ----------------------------------------------------------------
    def _read_metadata(self) -> dict[str, dict[str, str]]:
        out: dict[str, dict[str, str]] = {}
        if self._summary is not None and self._summary.metadata_indexes:
            with open(self.path, "rb") as f:
                for index in self._summary.metadata_indexes:
                    f.seek(index.offset)
                    body = f.read(index.length)
                    try:
                        record = _parse_record(body[0], body[9:])
                        if not isinstance(record, Metadata):
                            raise ValueError("not a metadata record")
                    except Exception:
                        raise LogFormatError(f"{self.path}: metadata record {index.name!r} at byte offset "
                                             f"{index.offset} is unreadable") from None
                    out[record.name] = dict(record.metadata)
            return out
        if self._truncated:
            records = self._stream_all()[3]  # the linear pass is needed for the messages anyway
        else:  # finished file without metadata indexes: scan the top-level records only
            records = [r for _, r in self._iter_records() if isinstance(r, Metadata)]
        for record in records:
            out[record.name] = dict(record.metadata)
        return out

    def _check_version(self) -> None:
        version = self.format_version
        if version is None:
            why = " (the file was cut short before it)" if self._truncated else ""
            raise LogFormatError(
                f"{self.path} is not a rollingstar log: no 'rollingstar' metadata record with a "
                f"format_version{why}; expected format {FORMAT_VERSION} (docs/log-format.md)")
        try:
            major, minor = (int(p) for p in version.split("."))
        except ValueError:
            raise LogFormatError(f"{self.path}: format_version {version!r} is not 'MAJOR.MINOR'") from None
        if major != _KNOWN_MAJOR:
            raise LogFormatError(
                f"{self.path} has rollingstar format_version {version}; this reader understands "
                f"{_KNOWN_MAJOR}.x (up to {FORMAT_VERSION}); use a rollingstar version that reads {major}.x")
        if minor > _KNOWN_MINOR:
            self._ignore_unknown_fields = True
            warnings.warn(f"{self.path} has format_version {version}, newer than {FORMAT_VERSION}: "
                          "fields this reader does not know are ignored", UserWarning, stacklevel=3)

    # --- public API ------------------------------------------------------------------------------
    @property
    def truncated(self) -> bool:
        """True when the file had no valid footer and was read by a linear pass."""
        return self._truncated

    def metadata(self) -> dict[str, dict[str, str]]:
        """Metadata records by name (``rollingstar``, ``scenario``, ``pipeline``, ``sensor``, ...)."""
        return {k: dict(v) for k, v in self._metadata.items()}

    def _channel_table(self):
        if self._summary is not None and self._summary.chunk_indexes:
            return self._summary.schemas, self._summary.channels
        return self._stream_all()[:2]

    def topics(self) -> dict[str, str]:
        """Topic -> schema name of every channel in the file."""
        schemas, channels = self._channel_table()
        return {ch.topic: (schemas[ch.schema_id].name if ch.schema_id in schemas else "")
                for ch in channels.values()}

    def require_topics(self, topics: Iterable[str]) -> None:
        """Raise :class:`LogFormatError` unless every topic is present in the file."""
        present = self.topics()
        missing = [t for t in topics if t not in present]
        if missing:
            raise LogFormatError(
                f"{self.path}: missing topic(s) {', '.join(missing)}; topics present: "
                f"{', '.join(sorted(present)) or '(none)'}")

    def summary_info(self) -> LogInfo:
        """Per-topic schema, encoding, message count and first/last log time (one pass, no decoding)."""
        stats: dict[str, list] = {}
        schemas, channels = self._channel_table()
        for ch in channels.values():
            name = schemas[ch.schema_id].name if ch.schema_id in schemas else ""
            stats[ch.topic] = [name, ch.message_encoding, 0, None, None]
        for raw in self._raw_messages():
            s = stats.setdefault(raw.channel.topic, [raw.schema.name if raw.schema else "",
                                                     raw.channel.message_encoding, 0, None, None])
            t = raw.message.log_time
            s[2] += 1
            s[3] = t if s[3] is None else min(s[3], t)
            s[4] = t if s[4] is None else max(s[4], t)
        infos = {topic: TopicInfo(topic, s[0], s[1], s[2], s[3], s[4])
                 for topic, s in sorted(stats.items())}
        starts = [i.start_ns for i in infos.values() if i.start_ns is not None]
        ends = [i.end_ns for i in infos.values() if i.end_ns is not None]
        return LogInfo(path=self.path, format_version=self.format_version, truncated=self._truncated,
                       message_count=sum(i.message_count for i in infos.values()),
                       start_ns=min(starts) if starts else None, end_ns=max(ends) if ends else None,
                       topics=infos)

    def messages(self, topics: Iterable[str] | str | None = None) -> Iterator[Message]:
        """Decoded messages in log-time order (file order among equal times), optionally only some topics."""
        for raw in self._raw_messages(topics):
            yield self._decode(raw)

    def written_messages(self) -> Iterator[tuple[Message, bytes]]:
        """Every message in the order it was written (not log-time order), decoded, with its payload
        bytes as stored (for :class:`~rollingstar.logs.digest.MessageDigest`)."""
        for raw in self._raw_in_write_order():
            yield self._decode(raw), raw.message.data

    # --- typed accessors -------------------------------------------------------------------------
    def scenario(self, missing_hint: str = "") -> ScenarioConfig:
        """The recording's sensor model: the scenario in its ``scenario`` metadata record.

        Raises :class:`~rollingstar.errors.UserError` naming the file when the recording declares
        none (``missing_hint``, what to do instead, ends the message) and
        :class:`~rollingstar.errors.ConfigError` naming the file and the key when the YAML is not a
        valid scenario.
        """
        record = self._metadata.get("scenario", {})
        if "yaml" not in record:
            hint = f"; {missing_hint}" if missing_hint else ""
            raise UserError(f"{self.path}: the recording declares no sensor model (metadata record 'scenario' "
                            f"with key 'yaml'){hint}")
        return scenario_from_yaml(record["yaml"], f"{self.path} (metadata 'scenario')")

    def stars(self, topic: str) -> dict[int, dict[str, Any]]:
        """Frame index -> the stars of that frame on ``topic`` (a ``rollingstar.Stars`` topic).

        Each value holds the numpy columns of the record (:func:`~rollingstar.logs.records.stars_to_arrays`)
        and the frame time ``t0_ns`` (int). Frames are in log-time order; when a frame has two
        records, the later one is kept.
        """
        out: dict[int, dict[str, Any]] = {}
        for m in self.messages(topic):
            out[m.record.frame] = {**stars_to_arrays(m.record), "t0_ns": m.record.t0_ns}
        return out

    def gyro(self) -> dict[str, np.ndarray]:
        """Every ``/gyro`` sample in log-time order: ``{"t_ns": (n,), "omega_rad_s": (n, 3)}``, n = 0
        without any (:func:`~rollingstar.logs.records.join_gyro_samples`)."""
        return join_gyro_samples(m.record for m in self.messages(TOPIC_GYRO))

    def truth_attitude(self) -> dict[str, np.ndarray]:
        """Every ``/truth/attitude`` sample in log-time order: ``{"t_ns": (n,), "q_xyzw": (n, 4),
        "omega_rad_s": (n, 3)}``, n = 0 without any (:func:`~rollingstar.logs.records.join_attitude_samples`)."""
        return join_attitude_samples(m.record for m in self.messages(TOPIC_TRUTH_ATTITUDE))

    # --- decoding --------------------------------------------------------------------------------
    def _decode(self, raw: _Raw) -> Message:
        channel, msg = raw.channel, raw.message
        schema_name = raw.schema.name if raw.schema is not None else ""
        where = f"{self.path}: topic {channel.topic} at log time {msg.log_time} ns"
        _check_standard_channel(channel, schema_name, where)
        record = None
        if channel.message_encoding == "json":
            try:
                data = json.loads(msg.data)
            except (ValueError, UnicodeDecodeError) as exc:
                raise LogFormatError(f"{where}: message is not valid JSON ({exc})") from None
            model = RECORD_TYPES.get(schema_name)
            if model is not None:
                payload = data
                if self._ignore_unknown_fields and isinstance(data, dict):
                    payload = {k: v for k, v in data.items() if k in model.model_fields}
                try:
                    record = model.model_validate(payload)
                except ValidationError as exc:
                    raise LogFormatError(f"{where}: not a valid {schema_name} record: {_errors(exc)}") from None
        elif channel.message_encoding == "protobuf":
            decoder = self._decoder_cache.get(channel.id)
            if decoder is None:
                try:
                    decoder = self._decoders.decoder_for("protobuf", raw.schema)
                except Exception as exc:
                    raise LogFormatError(f"{where}: unusable protobuf schema {schema_name!r} ({exc})") from None
                if decoder is None:
                    raise LogFormatError(f"{where}: protobuf channel without a protobuf schema")
                self._decoder_cache[channel.id] = decoder
            try:
                data = decoder(msg.data)
            except Exception as exc:
                raise LogFormatError(f"{where}: cannot decode {schema_name} ({exc})") from None
        else:
            data = msg.data
        return Message(topic=channel.topic, log_time_ns=msg.log_time, schema_name=schema_name,
                       data=data, record=record)


def _check_standard_channel(channel: Channel, schema_name: str, where: str) -> None:
    """A standard topic must carry the format's schema in the format's message encoding; anything else
    cannot be decoded as the format says (``where`` names the file, topic and log time)."""
    expected = STANDARD_SCHEMAS.get(channel.topic)
    if expected is None:
        return
    if schema_name != expected:
        raise LogFormatError(f"{where}: schema {schema_name!r} is not the format's {expected!r} for this topic "
                             f"(an unknown schema version?); this reader understands format {FORMAT_VERSION} "
                             "(docs/log-format.md)")
    encoding = STANDARD_ENCODINGS[channel.topic]
    if channel.message_encoding != encoding:
        raise LogFormatError(f"{where}: message encoding {channel.message_encoding!r} is not the format's "
                             f"{encoding!r} for this topic (docs/log-format.md)")


def _errors(exc: ValidationError) -> str:
    parts = []
    for err in exc.errors()[:5]:
        loc = ".".join(str(p) for p in err["loc"]) or "(record)"
        parts.append(f"{loc}: {err['msg']}")
    more = exc.error_count() - len(parts)
    return "; ".join(parts) + (f"; and {more} more" if more > 0 else "")


def _parse_record(opcode: int, body: bytes):
    """Parse the records the reader needs; None for the others."""
    stream = ReadDataStream(io.BytesIO(body))
    if opcode == Opcode.CHUNK:
        return Chunk.read(stream)
    if opcode == Opcode.SCHEMA:
        return Schema.read(stream)
    if opcode == Opcode.CHANNEL:
        return Channel.read(stream)
    if opcode == Opcode.MESSAGE:
        return McapMessage.read(stream, len(body))
    if opcode == Opcode.METADATA:
        return Metadata.read(stream)
    return None

