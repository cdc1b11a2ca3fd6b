"""Crash safety and determinism with real subprocesses (docs/reliability.md).

Killed (SIGKILL) or interrupted (SIGINT) part-way, ``rollingstar run`` leaves a log whose every
complete message reads back (a killed run in ``.<output>.tmp-<pid>``, an interrupted one in
``<output>.partial``; the output itself is not written); ``run --resume`` then produces an output
*equivalent* to an uninterrupted run: the same messages (topic, log time, decoded content) in
log-time order and the same metadata apart from the wall-clock ``rollingstar.created_utc``.
"""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
import warnings

import pytest

from rollingstar.logs.errors import TruncatedLogWarning
from rollingstar.logs.reader import LogReader
from rollingstar.pipelines.simulate import simulate_to_log
from rollingstar.sensors.scenario import load_scenario

from .helpers import PIPELINE, ROOT, SCENARIO, assert_exit_2, rewrite

pytestmark = pytest.mark.slow  # whole reproductions, benchmarks or killed processes: `-m 'not slow'` skips them

FRAMES = 250


def _key(m):
    data = json.dumps(m.data, sort_keys=True) if isinstance(m.data, dict) else m.data.SerializeToString()
    return (m.topic, m.log_time_ns, data)


def _read(path):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        reader = LogReader(path)
        msgs = [_key(m) for m in reader.messages()]
        meta = reader.metadata()
    truncated = any(issubclass(w.category, TruncatedLogWarning) for w in caught)
    return msgs, meta, truncated


def _assert_equivalent(a, b):
    ma, meta_a, _ = _read(a)
    mb, meta_b, _ = _read(b)
    assert ma == mb
    for meta in (meta_a, meta_b):
        meta["rollingstar"].pop("created_utc")
    assert meta_a == meta_b


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    d = tmp_path_factory.mktemp("crash")
    rec = d / "rec.mcap"
    simulate_to_log(load_scenario(SCENARIO), rec, frames=FRAMES, show_progress=False)
    ref = d / "ref.mcap"  # the uninterrupted run, by the same command (same environment, e.g. BLAS threads)
    p = subprocess.run([sys.executable, "-m", "rollingstar.cli", "run", PIPELINE, rec, "-o", ref, "-q"], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    return rec, ref


def _written(out) -> int:
    """Bytes on disk of ``out`` or of the temporary file it is written to (``.<name>.tmp-<pid>``)."""
    candidates = [out, *out.parent.glob(f".{out.name}.tmp-*")]
    return max((c.stat().st_size for c in candidates if c.exists()), default=-1)


def _leftovers(out) -> list:
    """What a cut run of ``out`` left: ``<name>.partial`` and killed runs' ``.<name>.tmp-<pid>``."""
    return sorted(p.name for p in out.parent.iterdir() if p.name == f"{out.name}.partial"
                  or p.name.startswith(f".{out.name}.tmp-"))


def _start(args, out, min_bytes):
    """Start ``rollingstar ARGS`` and return once ``out`` (or its temporary file) has ``min_bytes``
    on disk (finished chunks)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "rollingstar.cli", *map(str, args)], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while _written(out) < min_bytes:
        assert proc.poll() is None, f"finished before it could be killed: {proc.communicate()}"
        assert time.monotonic() < deadline
        time.sleep(0.01)
    return proc


@pytest.mark.parametrize("sig,every", [("SIGKILL", 500), ("SIGKILL", 20), ("SIGINT", 500)])
def test_killed_run_keeps_complete_messages_and_resumes_to_an_equivalent_output(tmp_path, recording, sig, every):
    """``every``: checkpoint interval (frames). 500 > the 250 frames: a SIGKILLed run leaves no
    checkpoint and the resume re-runs every frame; 20: it continues from the newest checkpoint the
    partial output covers; SIGINT saves one after the last frame written and continues right there."""
    rec, ref = recording
    out = tmp_path / "out.mcap"
    proc = _start(["run", PIPELINE, rec, "-o", out, "-q", "--checkpoint-every", every], out, 520_000)
    proc.send_signal(getattr(signal, sig))
    _, err = proc.communicate(timeout=60)
    assert not out.exists()
    cut = tmp_path / ("out.mcap.partial" if sig == "SIGINT" else f".out.mcap.tmp-{proc.pid}")
    assert _leftovers(out) == [cut.name]
    partial, _, truncated = _read(cut)
    full, _, _ = _read(ref)
    assert set(partial) <= set(full)  # every message read back is one the full run writes, intact
    frames = [json.loads(k[2])["frame"] for k in partial if k[0] == "/estimate/frame"]
    assert 0 < len(frames) < FRAMES and frames == list(range(len(frames)))
    if sig == "SIGINT":
        assert proc.returncode == 130, err
        assert "interrupted" in err and "--resume" in err and "Traceback" not in err
        assert not truncated  # finalised: summary and footer written
        # a clean stop ends at a frame boundary: every message of the written frames is there
        assert len(partial) == sum(1 for k in full if k[1] <= max(k2[1] for k2 in partial))
    else:
        assert proc.returncode == -signal.SIGKILL and truncated
    res = subprocess.run([sys.executable, "-m", "rollingstar.cli", "run", PIPELINE, rec, "-o", out, "--resume", "-q",
                          "--checkpoint-every", str(every)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    _assert_equivalent(out, ref)
    resumed = re.search(r"resumed from a checkpoint after (\d+) frames", res.stdout)
    if sig == "SIGINT":
        assert resumed and int(resumed.group(1)) == len(frames), res.stdout
    elif every < FRAMES:
        assert resumed and 0 < int(resumed.group(1)) <= len(frames) and int(resumed.group(1)) % every == 0, res.stdout
    else:
        assert not resumed and "every frame re-run" in res.stdout, res.stdout
    assert not (tmp_path / "out.mcap.checkpoints").exists()  # removed once the run completes
    assert _leftovers(out) == [] and not list(tmp_path.glob(".out.mcap.lock"))


def test_killed_run_of_a_recording_with_repeated_frame_fields_resumes_to_an_equivalent_output(tmp_path, recording):
    """The ``frame`` field of the centroid records repeats (0..6, 0..6, ...): a resume counts
    messages, never frame fields, and writes every frame."""
    rec = rewrite(recording[0], tmp_path / "repeated.mcap", lambda ms: [
        type(m)(m.topic, m.log_time_ns, m.schema_name, dict(m.data, frame=m.data["frame"] % 7))
        if m.topic == "/camera/centroids" else m for m in ms])
    ref, out = tmp_path / "ref.mcap", tmp_path / "out.mcap"
    args = ["run", PIPELINE, rec, "-q", "--checkpoint-every", "20"]
    p = subprocess.run([sys.executable, "-m", "rollingstar.cli", *map(str, args), "-o", ref], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and f"{FRAMES} frames" in p.stdout, p.stderr
    proc = _start([*args, "-o", out], out, 520_000)
    proc.kill()
    proc.communicate(timeout=60)
    res = subprocess.run([sys.executable, "-m", "rollingstar.cli", *map(str, args), "-o", out, "--resume"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and f"wrote {out}: {FRAMES} frames" in res.stdout, res.stderr
    assert "resumed from a checkpoint after" in res.stdout, res.stdout
    _assert_equivalent(out, ref)
    assert sum(1 for k in _read(out)[0] if k[0] == "/estimate/frame") == FRAMES


def test_a_second_run_to_one_output_is_refused_naming_the_first(tmp_path, recording):
    rec, ref = recording
    out = tmp_path / "out.mcap"
    first = _start(["run", PIPELINE, rec, "-o", out, "-q"], out, 1)
    lock = tmp_path / ".out.mcap.lock"
    assert lock.read_text() == f"pid {first.pid}"
    assert_exit_2(("run", PIPELINE, rec, "-o", out, "-q"), "another rollingstar command is writing this output",
                  f"(pid {first.pid})")
    _, err = first.communicate(timeout=120)
    assert first.returncode == 0, err  # the first run is not disturbed
    _assert_equivalent(out, ref)


def test_interrupted_simulate_exits_130_keeping_a_finalised_partial_log(tmp_path):
    out = tmp_path / "sim.mcap"
    earlier = b"\x89MCAP0\r\n an earlier recording"  # a recording (another kind of file is never replaced)
    out.write_bytes(earlier)
    proc = _start(["simulate", SCENARIO, "-o", out, "--frames", "3000", "-q"], out, 300_000)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "interrupted" in err and "Traceback" not in err, err
    assert out.read_bytes() == earlier  # the previous output is untouched
    assert "sim.mcap.partial" in err
    msgs, _, truncated = _read(tmp_path / "sim.mcap.partial")
    assert not truncated
    frames = [json.loads(k[2])["frame"] for k in msgs if k[0] == "/camera/centroids"]
    assert 0 < len(frames) < 3000 and frames == list(range(len(frames)))
    stars = [json.loads(k[2])["frame"] for k in msgs if k[0] == "/truth/stars"]
    assert stars == frames  # whole frames only


def test_same_inputs_and_seed_give_byte_identical_logs(tmp_path, recording):
    rec, _ = recording
    env = dict(os.environ, SOURCE_DATE_EPOCH="1700000000")
    digests = []
    for name in ("a", "b"):
        sim, out = tmp_path / f"{name}.mcap", tmp_path / f"{name}.out.mcap"
        for args in (["simulate", SCENARIO, "-o", sim, "--frames", "8", "--seed", "5", "-q"],
                     ["run", PIPELINE, sim, "-o", out, "-q"]):
            p = subprocess.run([sys.executable, "-m", "rollingstar.cli", *map(str, args)], cwd=ROOT, env=env,
                               capture_output=True, text=True, timeout=120)
            assert p.returncode == 0, p.stderr
        digests.append((sim.read_bytes(), out.read_bytes()))
    assert digests[0][0] == digests[1][0] and digests[0][1] == digests[1][1]
    assert LogReader(tmp_path / "a.out.mcap").metadata()["rollingstar"]["created_utc"] == "2023-11-14T22:13:20+00:00"
