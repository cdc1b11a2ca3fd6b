"""``rollingstar run`` never loses what the user has, and ``--resume`` proves what it continues.

The output goes through rollingstar.outputs.safe_output: never over the recording or the pipeline
file, one writer at a time (tests/reliability/test_crash.py::test_a_second_run_to_one_output_is_refused_naming_the_first),
an earlier output replaced only when the run completes. A resume refuses a partial output or a
checkpoint made from another recording, scenario or pipeline, and never recognises frames by their
``frame`` field (which a recording may repeat).
"""
from __future__ import annotations

import hashlib
import json
import os
import signal
import stat

import pytest

from rollingstar.estimators.attitude.base import AttitudeSolver
from rollingstar.logs.reader import LogReader
from rollingstar.logs.writer import LogWriter
from rollingstar.pipelines import runner as runner_module
from rollingstar.pipelines.checkpoint import checkpoint_dir

from .helpers import assert_exit_2, cli, rewrite

PIPELINE_YAML = "name: test\nstages:\n  - kind: tracking\n  - kind: quest\n  - kind: {extra}\n"


class CountingStage(AttitudeSolver):
    """Passes frames on. The ``action`` ("sigint" or "raise") happens on the ``at``-th frame this
    class processes (counted across instances, so a checkpointed copy does not count again), once."""

    name = "counting"
    at: int | None = None
    action = "sigint"
    seen = 0

    def process(self, frame):
        CountingStage.seen += 1
        if CountingStage.seen == CountingStage.at:
            CountingStage.at = None
            if CountingStage.action == "raise":
                raise RuntimeError("broken on purpose")
            os.kill(os.getpid(), signal.SIGINT)
        return frame


@pytest.fixture
def counting_stage(monkeypatch):
    real = runner_module.get_plugin_class
    monkeypatch.setattr(runner_module, "get_plugin_class", lambda kind: CountingStage if kind == "counting" else real(kind))
    CountingStage.at, CountingStage.action, CountingStage.seen = None, "sigint", 0
    yield CountingStage


def _pipeline(tmp_path, extra="counting"):
    path = tmp_path / f"pipeline_{extra}.yaml"
    path.write_text(PIPELINE_YAML.format(extra=extra))
    return path


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _messages(path):
    return [(m.topic, m.log_time_ns, json.dumps(m.data, sort_keys=True) if isinstance(m.data, dict)
             else m.data.SerializeToString()) for m in LogReader(path).messages()]


def _metadata(path):
    meta = LogReader(path).metadata()
    meta["rollingstar"].pop("created_utc")
    return meta


def _assert_equivalent(a, b):
    assert _messages(a) == _messages(b)
    assert _metadata(a) == _metadata(b)


@pytest.mark.parametrize("make", ["same", "symlink", "hardlink", "pipeline"])
def test_an_output_that_is_the_recording_or_the_pipeline_is_refused(tmp_path, small_recording, make):
    rec = tmp_path / "rec.mcap"
    rec.write_bytes(small_recording.read_bytes())
    pipeline = _pipeline(tmp_path, "quest")
    before = {p: _sha(p) for p in (rec, pipeline)}
    out = {"same": rec, "pipeline": pipeline}.get(make, tmp_path / "alias.mcap")
    if make in ("symlink", "hardlink"):
        (os.symlink if make == "symlink" else os.link)(rec, out)
    assert_exit_2(("run", pipeline, rec, "-o", out), "writing it would destroy the input")
    assert {p: _sha(p) for p in (rec, pipeline)} == before


def test_a_failing_rerun_keeps_the_earlier_output_and_writes_a_partial(tmp_path, small_recording, counting_stage):
    out = tmp_path / "out.mcap"
    code, _, err = cli("run", _pipeline(tmp_path), small_recording, "-o", out, "-q")
    assert code == 0, err
    good = _sha(out)
    counting_stage.at, counting_stage.action, counting_stage.seen = 10, "raise", 0
    flat = assert_exit_2(("run", _pipeline(tmp_path), small_recording, "-o", out, "-q"),
                         "stage 'counting' (attitude) failed on frame 9", "broken on purpose")
    assert "exists: it is replaced when this command completes" in flat
    assert _sha(out) == good  # the earlier output, untouched
    frames = [m.data["frame"] for m in LogReader(tmp_path / "out.mcap.partial").messages("/estimate/frame")]
    assert frames == list(range(9))  # the frames finished before the failure


def test_resume_refuses_a_partial_output_of_another_recording(tmp_path, small_recording, counting_stage):
    rec, out, pipeline = tmp_path / "rec.mcap", tmp_path / "out.mcap", _pipeline(tmp_path)
    rec.write_bytes(small_recording.read_bytes())
    counting_stage.at = 12
    code, _, err = cli("run", pipeline, rec, "-o", out, "-q", "--checkpoint-every", "5")
    assert code == 130 and "out.mcap.partial holds the 12 frame(s)" in " ".join(err.split()), err
    partial = _sha(tmp_path / "out.mcap.partial")
    rec.unlink()  # replaced by another recording of the same scenario: one centroid fewer in frame 15
    rewrite(small_recording, rec, lambda ms: [
        type(m)(m.topic, m.log_time_ns, m.schema_name, {k: (v[:-1] if isinstance(v, list) else v) for k, v in m.data.items()})
        if m.topic == "/camera/centroids" and m.data["frame"] == 15 else m for m in ms])
    assert LogReader(rec).metadata()["scenario"] == LogReader(small_recording).metadata()["scenario"]
    assert_exit_2(("run", pipeline, rec, "-o", out, "--resume", "-q"), "out.mcap.partial was made from other "
                  "inputs (the recording differs")
    assert_exit_2(("run", _pipeline(tmp_path, "mekf"), rec, "-o", out, "--resume", "-q"),
                  "(the recording and the pipeline differ")
    assert _sha(tmp_path / "out.mcap.partial") == partial and not out.exists()
    (tmp_path / "out.mcap.partial").unlink()  # no partial output: the checkpoints are of no use, run from the start
    code, stdout, err = cli("run", pipeline, rec, "-o", out, "--resume", "-q")
    assert code == 0 and "found no partial output" in err and "every frame re-run from the first" in stdout, err


@pytest.fixture
def repeated_frame_fields(tmp_path, small_recording):
    """The small recording with the centroid records' ``frame`` field repeating 0, 1, 2, 0, 1, 2, ..."""
    def edit(messages):
        return [type(m)(m.topic, m.log_time_ns, m.schema_name, dict(m.data, frame=m.data["frame"] % 3))
                if m.topic == "/camera/centroids" else m for m in messages]
    return rewrite(small_recording, tmp_path / "repeated.mcap", edit)


@pytest.mark.parametrize("every", [5, 0])
def test_resume_with_repeated_frame_fields_equals_an_uninterrupted_run(tmp_path, repeated_frame_fields,
                                                                      counting_stage, every):
    rec, pipeline = repeated_frame_fields, _pipeline(tmp_path)
    ref, out = tmp_path / "ref.mcap", tmp_path / "out.mcap"
    code, stdout, err = cli("run", pipeline, rec, "-o", ref, "-q")
    assert code == 0 and "wrote" in stdout and ": 20 frames" in stdout, err
    counting_stage.at, counting_stage.seen = 13, 0
    code, _, err = cli("run", pipeline, rec, "-o", out, "-q", "--checkpoint-every", str(every))
    assert code == 130, err
    code, stdout, err = cli("run", pipeline, rec, "-o", out, "--resume", "-q", "--checkpoint-every", str(every))
    assert code == 0, err
    assert ("resumed from a checkpoint after 13 frames" if every else "every frame re-run from the first") in stdout
    assert ": 20 frames" in stdout
    _assert_equivalent(out, ref)
    assert len([k for k in _messages(out) if k[0] == "/estimate/frame"]) == 20
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(("out", ".out"))) == ["out.mcap"]


def test_a_file_where_the_checkpoint_folder_goes_is_an_error(tmp_path, small_recording):
    out = tmp_path / "out.mcap"
    checkpoint_dir(out).write_text("not a folder")
    for extra in ((), ("--resume",)):
        assert_exit_2(("run", _pipeline(tmp_path, "quest"), small_recording, "-o", out, "-q", *extra),
                      "out.mcap.checkpoints: exists and is not a folder")
    assert not out.exists() and checkpoint_dir(out).read_text() == "not a folder"


@pytest.mark.skipif(not os.path.exists("/dev/null"), reason="no /dev/null")
def test_a_device_output_is_written_directly_and_stays_a_device(tmp_path, small_recording):
    code, stdout, err = cli("run", _pipeline(tmp_path, "quest"), small_recording, "-o", "/dev/null", "-q")
    assert code == 0 and "wrote /dev/null: 20 frames" in stdout, err
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)
    assert not [p for p in os.listdir("/dev") if p.startswith((".null.", "null."))]


def test_resume_takes_the_furthest_checkpoint_any_partial_output_holds(tmp_path, small_recording, counting_stage):
    """SIGINT at frame 13 leaves ``out.mcap.partial`` and a checkpoint there; a resume killed right
    after opening its output leaves a newer ``.out.mcap.tmp-<pid>`` holding no message yet. The next
    resume continues from frame 13 with the older partial output, and removes both once it completes."""
    rec, pipeline, out = small_recording, _pipeline(tmp_path), tmp_path / "out.mcap"
    ref = tmp_path / "ref.mcap"
    assert cli("run", pipeline, rec, "-o", ref, "-q")[0] == 0
    counting_stage.at, counting_stage.seen = 13, 0
    assert cli("run", pipeline, rec, "-o", out, "-q", "--checkpoint-every", "5")[0] == 130
    partial = tmp_path / "out.mcap.partial"
    meta = {k: v for k, v in LogReader(partial).metadata().items() if k != "rollingstar"}
    with LogWriter(tmp_path / ".out.mcap.tmp-99999", kind="run", metadata=meta):
        pass
    code, stdout, err = cli("run", pipeline, rec, "-o", out, "--resume", "-q", "--checkpoint-every", "5")
    assert code == 0 and "resumed from a checkpoint after 13 frames" in stdout, (stdout, err)
    _assert_equivalent(out, ref)
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(("out", ".out"))) == ["out.mcap"]
