"""A recording cannot make the reader allocate more than a chunk ceiling, nor block on a pipe."""
from __future__ import annotations

import os
import struct
import warnings

import pytest
import zstandard
from mcap.reader import SeekingReader
from mcap.writer import CompressionType, Writer

from rollingstar.logs import LogFormatError, LogReader, TruncatedLogWarning
from rollingstar.logs.reader import MAX_CHUNK_ENV, default_max_chunk_bytes
from tests.logs.helpers import write_recording

# byte offset of uncompressed_size inside a chunk record: opcode (1) + length (8) + start/end times (16)
_SIZE_AT = 1 + 8 + 16


def _first_chunk_offset(path) -> int:
    with open(path, "rb") as fh:
        return min(ci.chunk_start_offset for ci in SeekingReader(fh).get_summary().chunk_indexes)


def _patch_declared_size(path, size: int) -> None:
    offset = _first_chunk_offset(path)
    with open(path, "r+b") as fh:
        fh.seek(offset + _SIZE_AT)
        fh.write(struct.pack("<Q", size))


def test_a_chunk_declaring_more_than_its_index_is_skipped_unread(tmp_path):
    path = tmp_path / "rec.mcap"
    write_recording(path, n_frames=3)
    _patch_declared_size(path, 6 << 30)  # 6 GiB claimed by a chunk of a few kB
    with pytest.warns(TruncatedLogWarning, match="declares 6442450944 uncompressed bytes, its index"):
        messages = list(LogReader(path).messages())
    assert len(messages) < 3 * 10


def test_a_chunk_over_the_ceiling_is_an_error_naming_the_limit(tmp_path, monkeypatch):
    """A genuine zstd bomb: 64 MiB of zeros compress to a few kB; the index agrees with the chunk."""
    path = tmp_path / "bomb.mcap"
    with open(path, "wb") as fh:
        writer = Writer(fh, compression=CompressionType.ZSTD, chunk_size=1 << 30)
        writer.start(profile="", library="test")
        schema = writer.register_schema("raw", "jsonschema", b"{}")
        channel = writer.register_channel("/camera/centroids", "json", schema)
        writer.add_message(channel, 0, b"\0" * (64 << 20), 0)
        writer.finish()
    assert path.stat().st_size < 1 << 20
    monkeypatch.setenv(MAX_CHUNK_ENV, "16")
    assert default_max_chunk_bytes() == 16 << 20
    with pytest.raises(LogFormatError, match=f"more than the limit of {16 << 20}.*{MAX_CHUNK_ENV}"):
        list(LogReader(path, check_version=False).messages())


def test_a_frame_that_expands_past_its_declared_size_is_not_decompressed_whole():
    from mcap.records import Chunk

    from rollingstar.logs.reader import _decompressed

    data = zstandard.ZstdCompressor().compress(b"\0" * (8 << 20))
    chunk = Chunk(message_start_time=0, message_end_time=0, uncompressed_size=1000, uncompressed_crc=0,
                  compression="zstd", data=data)
    with pytest.raises(ValueError, match="decompresses to more bytes"):
        _decompressed(chunk)


def test_bad_ceiling_setting_is_named(monkeypatch):
    monkeypatch.setenv(MAX_CHUNK_ENV, "lots")
    with pytest.raises(LogFormatError, match=MAX_CHUNK_ENV):
        default_max_chunk_bytes()


@pytest.mark.parametrize("kind", ["fifo", "folder"])
def test_a_pipe_or_folder_is_refused_without_blocking(tmp_path, kind):
    path = tmp_path / "rec.mcap"
    os.mkfifo(path) if kind == "fifo" else path.mkdir()
    with pytest.raises(LogFormatError, match="not a regular file"):
        LogReader(path)


def test_recordings_within_the_ceiling_read_as_before(tmp_path):
    path = tmp_path / "rec.mcap"
    write_recording(path, n_frames=3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(list(LogReader(path).messages())) == 3 * 10  # ten topics a frame
