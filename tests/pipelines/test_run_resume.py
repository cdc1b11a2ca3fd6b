"""SIGINT at a known frame, in process: the partial output ``<output>.partial`` is finalised, and
``resume`` gives the output of an uninterrupted run, for a pipeline that checkpoints and for one with
a smoother (which restarts from the first frame). The subprocess kill-and-resume cases are in
tests/reliability/test_crash.py."""
from __future__ import annotations

import json
import os
import signal

import pytest

from rollingstar.estimators.attitude.base import AttitudeSolver
from rollingstar.logs.reader import LogReader
from rollingstar.pipelines import runner as runner_module
from rollingstar.pipelines.checkpoint import checkpoint_dir
from rollingstar.pipelines.config import PipelineConfig
from rollingstar.pipelines.interrupt import Interrupted
from rollingstar.pipelines.runner import run_pipeline


class SigintAt(AttitudeSolver):
    """Passes frames on; sends this process SIGINT while processing frame ``SigintAt.frame`` (once)."""

    name = "sigint-at"
    frame: int | None = None

    def process(self, frame):
        if frame.index == SigintAt.frame:
            SigintAt.frame = None
            os.kill(os.getpid(), signal.SIGINT)
        return frame


@pytest.fixture
def with_sigint_stage(monkeypatch):
    real = runner_module.get_plugin_class
    monkeypatch.setattr(runner_module, "get_plugin_class", lambda kind: SigintAt if kind == "sigint-at" else real(kind))
    yield
    SigintAt.frame = None


def _messages(path):
    return [(m.topic, m.log_time_ns, json.dumps(m.data, sort_keys=True) if isinstance(m.data, dict)
             else m.data.SerializeToString()) for m in LogReader(path).messages()]


@pytest.mark.parametrize("stages, checkpoints", [
    ([{"kind": "tracking"}, {"kind": "quest"}, {"kind": "sigint-at"}], True),
    ([{"kind": "tracking"}, {"kind": "sigint-at"}, {"kind": "mekf"}], True),
    ([{"kind": "tracking"}, {"kind": "sigint-at"}, {"kind": "gtsam", "params": {"mode": "fixed-lag"}}], False),
])
def test_sigint_finalises_and_resume_equals_an_uninterrupted_run(tmp_path, small_recording, with_sigint_stage,
                                                               stages, checkpoints):
    pipeline = PipelineConfig(stages=stages)
    ref, out = tmp_path / "ref.mcap", tmp_path / "out.mcap"
    full = run_pipeline(small_recording, pipeline, ref, show_progress=False)
    SigintAt.frame = 7
    with pytest.raises(Interrupted, match=r"holds the 8 frame\(s\) processed before SIGINT; continue with "
                                          r"`rollingstar run \.\.\. -o .*out\.mcap --resume`"):
        run_pipeline(small_recording, pipeline, out, show_progress=False)
    partial = tmp_path / "out.mcap.partial"
    assert not out.exists()
    frames = [m.data["frame"] for m in LogReader(partial).messages("/estimate/frame")]  # a finalised log
    assert frames == list(range(8 if checkpoints else len(frames))) and len(frames) <= 8
    assert checkpoint_dir(out).exists() == checkpoints
    resumed = run_pipeline(small_recording, pipeline, out, show_progress=False, resume=True)
    assert resumed.resumed_after_frames == (8 if checkpoints else 0)
    assert (resumed.frames, resumed.attitude_estimates, resumed.valid_estimates, resumed.flagged_frames) == \
        (full.frames, full.attitude_estimates, full.valid_estimates, full.flagged_frames)
    assert _messages(out) == _messages(ref)
    assert not checkpoint_dir(out).exists() and not partial.exists()
