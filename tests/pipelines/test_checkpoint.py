"""Checkpoints for ``run --resume`` (pipelines/checkpoint.py) and how a resume picks one against a
partial output (pipelines/resume.py); the kill-and-resume equivalence is tested with real
subprocesses in tests/reliability/test_crash.py."""
from __future__ import annotations

import threading

import pytest

from rollingstar.errors import UserError
from rollingstar.logs.digest import MessageDigest
from rollingstar.logs.reader import LogReader
from rollingstar.logs.records import FrameStatus
from rollingstar.logs.writer import LogWriter
from rollingstar.pipelines.checkpoint import (
    CheckpointWriter,
    RunIdentity,
    RunState,
    check_checkpoint_dir,
    checkpoint_dir,
    load_checkpoints,
)
from rollingstar.pipelines.resume import prefix_digests

IDENTITY = RunIdentity("r" * 64, "s" * 64, "p" * 64)


class Stage:
    defers_output = False

    def __init__(self, context, payload=None):
        self.context, self.payload, self.frames_seen = context, payload, 0


class Context:
    """Stands for the sensor context: never stored, re-attached on load."""


def _state(stages, frames_read=10, identity=IDENTITY, messages=0, digest=""):
    return RunState(identity, frames_read, frames_read, stages, None, {"att": 1}, {"0:x": 0.5}, messages, digest)


def test_round_trip_reattaches_the_context_and_keeps_the_newest(tmp_path):
    ctx, out = Context(), tmp_path / "o.mcap"
    saver = CheckpointWriter(out, ctx, every=10)
    for n in (10, 20, 30, 40):
        stage = Stage(ctx)
        stage.frames_seen = n
        saver.save(_state([stage], frames_read=n, messages=3 * n))
    files = sorted(p.name for p in checkpoint_dir(out).iterdir())
    assert files == ["frames-000000020.pkl", "frames-000000030.pkl", "frames-000000040.pkl"]  # newest 3 kept
    ctx2 = Context()
    states = load_checkpoints(out, IDENTITY, ctx2)
    assert [s.frames_read for s in states] == [40, 30, 20]  # newest first
    assert [s.messages for s in states] == [120, 90, 60] and states[1].stages[0].frames_seen == 30
    assert states[0].stages[0].context is ctx2  # not a copy of the old one
    saver.remove()
    assert not checkpoint_dir(out).exists()


@pytest.mark.parametrize("other, what", [
    (RunIdentity("x" * 64, "s" * 64, "p" * 64), "the recording differs"),
    (RunIdentity("r" * 64, "x" * 64, "x" * 64), "the scenario and the pipeline differ"),
    (RunIdentity("r" * 64, "s" * 64, "p" * 64, with_images=True), "the --with-images choice differs"),
])
def test_a_checkpoint_of_another_run_is_refused_naming_what_differs(tmp_path, other, what):
    ctx, out = Context(), tmp_path / "o.mcap"
    CheckpointWriter(out, ctx, every=10).save(_state([Stage(ctx)], identity=other))
    with pytest.raises(UserError, match=f"other inputs \\({what}\\)"):
        load_checkpoints(out, IDENTITY, ctx)


def test_something_other_than_a_folder_where_the_checkpoints_go_is_a_user_error(tmp_path):
    out = tmp_path / "o.mcap"
    check_checkpoint_dir(out)  # nothing there: fine
    checkpoint_dir(out).write_text("a file")
    with pytest.raises(UserError, match="exists and is not a folder"):
        check_checkpoint_dir(out)
    checkpoint_dir(out).unlink()
    checkpoint_dir(out).symlink_to(tmp_path)
    with pytest.raises(UserError, match="exists and is not a folder"):
        check_checkpoint_dir(out)


def test_unpicklable_state_turns_checkpoints_off_with_a_warning(tmp_path):
    ctx = Context()
    saver = CheckpointWriter(tmp_path / "o.mcap", ctx, every=5)
    with pytest.warns(UserWarning, match="checkpoints off for this run"):
        saver.save(_state([Stage(ctx, payload=threading.Lock())]))
    assert not saver.enabled and not saver.due(5) and not checkpoint_dir(tmp_path / "o.mcap").exists()


def test_a_stage_holding_frames_back_turns_checkpoints_off(tmp_path):
    ctx = Context()
    smoother = Stage(ctx)
    smoother.defers_output = True
    saver = CheckpointWriter(tmp_path / "o.mcap", ctx, every=5)
    saver.save(_state([Stage(ctx), smoother]))
    assert not saver.enabled and not checkpoint_dir(tmp_path / "o.mcap").exists()


def test_damaged_checkpoint_falls_back_to_the_one_before(tmp_path):
    ctx, out = Context(), tmp_path / "o.mcap"
    saver = CheckpointWriter(out, ctx, every=10)
    saver.save(_state([Stage(ctx)], frames_read=10))
    saver.save(_state([Stage(ctx)], frames_read=20))
    (checkpoint_dir(out) / "frames-000000020.pkl").write_bytes(b"\x80\x05garbage")
    with pytest.warns(UserWarning, match="unreadable"):
        states = load_checkpoints(out, IDENTITY, ctx)
    assert [s.frames_read for s in states] == [10]


def _frames_log(path, n, chunk_size=1024):
    """A log of ``n`` frame records, and the writer's (count, digest) after each one."""
    after = {}
    with LogWriter(path, kind="run", chunk_size=chunk_size, digest=True) as w:
        for i in range(n):
            w.write_json("/estimate/frame", FrameStatus(frame=i % 3, t0_ns=1000 * i, flags=[], n_detected=i,
                                                        n_identified=0))
            after[w.digest.count] = w.digest.hexdigest()
    return after


def test_the_digest_of_a_logs_first_messages_matches_what_the_writer_recorded(tmp_path):
    """A checkpoint is usable when the partial output's first K messages (in write order) have the
    digest the writer had after K messages; a log cut short holds only its complete chunks."""
    path = tmp_path / "o.mcap"
    after = _frames_log(path, 200)
    assert prefix_digests(LogReader(path), {0, 50, 200, 201}) == {0: MessageDigest().hexdigest(), 50: after[50],
                                                                   200: after[200]}
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.warns(UserWarning):
        held = prefix_digests(LogReader(cut), {10, 190})
    assert held == {10: after[10]}
    other = tmp_path / "other.mcap"
    _frames_log(other, 9)
    assert prefix_digests(LogReader(other), {10}) == {}
