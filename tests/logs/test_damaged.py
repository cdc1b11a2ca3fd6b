"""Damaged files: every truncation yields a clean prefix; a corrupt chunk is skipped with its offset."""
import io
import os
import subprocess
import sys
import warnings

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.records import Message as McapMessage
from mcap.stream_reader import breakup_chunk

from rollingstar.logs import LogFormatError, LogReader, TruncatedLogWarning

from .helpers import write_recording


def _key(m):
    data = m.data if isinstance(m.data, dict) else m.data.SerializeToString()
    return (m.topic, m.log_time_ns, repr(data))


@pytest.fixture(scope="module")
def layout(tmp_path_factory):
    """A log with many small chunks: its bytes, messages, chunk spans and messages per chunk prefix."""
    path = tmp_path_factory.mktemp("rec") / "full.mcap"
    write_recording(path, n_frames=12, chunk_size=2048, image_shape=(16, 20))
    data = path.read_bytes()
    messages = [_key(m) for m in LogReader(path).messages()]
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    chunks, counts = [], [0]
    for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        end = ci.chunk_start_offset + ci.chunk_length
        chunks.append((ci.chunk_start_offset, end))
        chunk = Chunk.read(ReadDataStream(io.BytesIO(data[ci.chunk_start_offset + 9 : end])))
        counts.append(counts[-1] + sum(isinstance(r, McapMessage) for r in breakup_chunk(chunk)))
    assert len(chunks) >= 8 and counts[-1] == len(messages)
    meta_end = min(m.offset + m.length for m in summary.metadata_indexes if m.name == "rollingstar")
    return {"data": data, "messages": messages, "chunks": chunks, "prefix_counts": counts,
            "meta_end": meta_end}


def _read_cut(recording, tmp_dir, cut):
    path = tmp_dir / "cut.mcap"
    path.write_bytes(recording["data"][:cut])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            reader = LogReader(path)
        except LogFormatError:
            return None, caught
        got = [_key(m) for m in reader.messages()]
    return got, caught


def _check_cut(recording, tmp_dir, cut):
    got, caught = _read_cut(recording, tmp_dir, cut)
    if cut < recording["meta_end"]:
        assert got is None, f"cut at {cut}: expected LogFormatError before the metadata is complete"
        return
    assert got is not None, f"cut at {cut} raised LogFormatError"
    full = recording["messages"]
    assert got == full[: len(got)], f"cut at {cut}: not a prefix of the original messages"
    complete = [c for c in recording["chunks"] if c[1] <= cut]
    assert len(got) >= recording["prefix_counts"][len(complete)], f"cut at {cut}: lost a complete chunk"
    if cut < len(recording["data"]):
        assert any(issubclass(w.category, TruncatedLogWarning) for w in caught)


def test_cuts_at_every_chunk_boundary(layout, tmp_path):
    for start, end in layout["chunks"]:
        for cut in (start - 1, start, start + 1, end - 1, end, end + 1):
            _check_cut(layout, tmp_path, cut)


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(fraction=st.floats(0, 1))
def test_any_cut_yields_a_prefix(layout, tmp_path, fraction):
    _check_cut(layout, tmp_path, int(fraction * len(layout["data"])))


@pytest.mark.parametrize("cut", [0, 1, 7, 8, 20])
def test_tiny_files_raise_log_format_error(layout, tmp_path, cut):
    got, _ = _read_cut(layout, tmp_path, cut)
    assert got is None


def _corrupt(recording, tmp_path, k, cut=None):
    start, end = recording["chunks"][k]
    data = bytearray(recording["data"])
    middle = (start + end) // 2
    data[middle : middle + 8] = bytes(b ^ 0xFF for b in data[middle : middle + 8])
    path = tmp_path / "corrupt.mcap"
    path.write_bytes(bytes(data[:cut]))
    return path, start


@pytest.mark.filterwarnings("ignore::rollingstar.logs.TruncatedLogWarning")
@pytest.mark.parametrize("truncate", [False, True])
def test_corrupt_chunk_is_skipped_with_its_offset(layout, tmp_path, truncate):
    k = 3
    path, offset = _corrupt(layout, tmp_path, k, cut=len(layout["data"]) - 50 if truncate else None)
    with pytest.warns(TruncatedLogWarning, match=f"byte offset {offset}"):
        got = [_key(m) for m in LogReader(path).messages()]
    full = layout["messages"]
    lost = layout["prefix_counts"][k + 1] - layout["prefix_counts"][k]
    assert got[: layout["prefix_counts"][k]] == full[: layout["prefix_counts"][k]]
    if not truncate:
        assert len(got) == len(full) - lost
        assert got[layout["prefix_counts"][k]:] == full[layout["prefix_counts"][k + 1]:]
    assert set(got) <= set(full)


KILLED_WRITER = """
import os, sys
import numpy as np
from rollingstar.logs import LogWriter, gyro_samples_from_arrays
w = LogWriter(sys.argv[1], chunk_size=1024)
for i in range(200):
    w.write_json("/gyro", gyro_samples_from_arrays([i], [[0.0, 0.0, float(i)]]))
os._exit(0)   # killed: no summary, no footer, the chunk in progress is lost
"""


def test_killed_writer_keeps_finished_chunks(tmp_path):
    path = tmp_path / "killed.mcap"
    subprocess.run([sys.executable, "-c", KILLED_WRITER, str(path)], check=True, cwd=os.getcwd())
    with pytest.warns(TruncatedLogWarning, match="no valid footer"):
        reader = LogReader(path)
    times = [m.log_time_ns for m in reader.messages()]
    assert 100 < len(times) < 200
    assert times == list(range(len(times)))
    assert reader.metadata()["rollingstar"]["format_version"] == "1.2"
    assert reader.summary_info().truncated


def test_a_cut_log_is_warned_about_once_per_command(small_recording, tmp_path):
    """Every step that opens a cut log warns; the command line prints the message once."""
    from typer.testing import CliRunner

    from rollingstar.cli import app

    cut = tmp_path / "cut.mcap"
    data = small_recording.read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    res = CliRunner().invoke(app, ["diagnose", "--recording", str(cut), "-o", str(tmp_path / "report"), "-q"])
    assert res.exit_code == 0, res.output
    assert res.output.count("has no valid footer") == 1, res.output  # diagnose opens the log four times
