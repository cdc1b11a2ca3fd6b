"""Checkpoints for ``run --resume`` (pipelines/checkpoint.py); the kill-and-resume equivalence is
tested with real subprocesses in tests/reliability/test_crash.py."""
from __future__ import annotations

import threading

import pytest

from rollingstar.pipelines.checkpoint import (
    CheckpointWriter,
    RunState,
    add_index,
    checkpoint_dir,
    load_checkpoint,
)


class Stage:
    defers_output = False

    def __init__(self, context, payload=None):
        self.context, self.payload, self.frames_seen = context, payload, 0


class Context:
    """Stands for the sensor context: never stored, re-attached on load."""


def _state(stages, frames_read=10, key="k", written=None):
    return RunState(key, frames_read, frames_read, stages, None, {"att": 1}, {"0:x": 0.5},
                    written if written is not None else [(0, frames_read)])


def test_written_ranges():
    ranges = []
    for i in [0, 1, 2, 5, 6, 9]:
        add_index(ranges, i)
    assert ranges == [(0, 3), (5, 7), (9, 10)]
    state = _state([], written=ranges)
    assert state.written_within({0, 1, 2, 5, 6, 9, 11})
    assert not state.written_within({0, 1, 2, 5, 9})


def test_round_trip_reattaches_the_context_and_picks_the_newest_usable(tmp_path):
    ctx, out = Context(), tmp_path / "o.mcap"
    saver = CheckpointWriter(out, ctx, every=10)
    for n in (10, 20, 30, 40):
        stage = Stage(ctx)
        stage.frames_seen = n
        saver.save(_state([stage], frames_read=n))
    files = sorted(p.name for p in checkpoint_dir(out).iterdir())
    assert files == ["frames-000000020.pkl", "frames-000000030.pkl", "frames-000000040.pkl"]  # newest 3 kept
    ctx2 = Context()
    state = load_checkpoint(out, "k", set(range(35)), ctx2)  # the output holds frames 0..34 complete
    assert state.frames_read == 30 and state.stages[0].frames_seen == 30
    assert state.stages[0].context is ctx2  # not a copy of the old one
    assert load_checkpoint(out, "k", set(range(15)), ctx2) is None  # 20 and later are ahead of the output
    with pytest.warns(UserWarning, match="another recording, scenario or pipeline"):
        assert load_checkpoint(out, "other", set(range(100)), ctx2) is None
    saver.remove()
    assert not checkpoint_dir(out).exists()


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
        state = load_checkpoint(out, "k", set(range(50)), ctx)
    assert state.frames_read == 10
