"""Resources: disk full (a real ENOSPC from /dev/full, and one part-way through a run)."""
from __future__ import annotations

import errno
import functools
import os
import warnings

import pytest

from rollingstar.logs import writer as writer_module
from rollingstar.logs.errors import LogWriteError, TruncatedLogWarning
from rollingstar.logs.reader import LogReader
from rollingstar.outputs import PartialOutputWarning
from rollingstar.pipelines import runner as runner_module
from rollingstar.pipelines.config import PipelineConfig
from rollingstar.pipelines.runner import run_pipeline

from .helpers import PIPELINE, assert_exit_2


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="/dev/full (always ENOSPC) not on this system")
def test_disk_full_at_once_exits_2(small_recording):
    print(assert_exit_2(("run", PIPELINE, small_recording, "-o", "/dev/full"), "cannot write log /dev/full",
                        "No space left on device", "after 0 bytes"))


def test_disk_full_part_way_keeps_every_finished_chunk(tmp_path, small_recording, monkeypatch):
    real_write = os.write
    budget = {"left": 60_000}

    def write(fd, data):  # the disk fills up after 60 kB
        if budget["left"] <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        n = min(len(data), budget["left"])
        budget["left"] -= n
        return real_write(fd, bytes(data[:n]))

    monkeypatch.setattr(writer_module.os, "write", write)
    out = tmp_path / "o.mcap"
    pipeline = PipelineConfig(stages=[{"kind": "tracking"}, {"kind": "quest"}])
    with pytest.raises(LogWriteError, match=r"o\.mcap\.partial: No space left on device after 60000 bytes"), \
            pytest.warns(PartialOutputWarning, match="o.mcap.partial"):
        # small chunks, so that several are finished before the disk is full
        monkeypatch.setattr(runner_module, "LogWriter", functools.partial(writer_module.LogWriter, chunk_size=8192))
        run_pipeline(small_recording, pipeline, out, show_progress=False)
    monkeypatch.undo()
    partial = tmp_path / "o.mcap.partial"  # what was written; the output itself is not
    assert partial.stat().st_size == 60_000 and not out.exists()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        frames = [m.data["frame"] for m in LogReader(partial).messages("/estimate/frame")]
    assert any(issubclass(w.category, TruncatedLogWarning) for w in caught)
    assert 0 < len(frames) < 20 and frames == list(range(len(frames)))
