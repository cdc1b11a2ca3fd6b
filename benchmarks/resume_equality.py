"""Kill ``rollingstar run`` at random points, resume, and compare with an uninterrupted run.

    .venv/bin/python benchmarks/resume_equality.py [--cases 10] [--frames 1000] [--every 25] [--seed 0]

A recording of ``--frames`` frames of configs/scenarios/he2021b.yaml (centroid level) is simulated
and run once through the baseline pipeline without interruption (the reference). Each case starts
the same ``rollingstar run`` with ``--checkpoint-every N``, sends it SIGKILL or SIGINT (half each,
in random order) at a random time while it writes, then runs it again with ``--resume``; in about
a third of the cases that resume is itself cut at a random time and resumed once more. The final
output must hold the reference's messages (topic, log time, decoded content, in log-time order) and
metadata (apart from ``rollingstar.created_utc``). One line per case, a summary line; exit status 1
when any case differs.
"""
from __future__ import annotations

import argparse
import json
import random
import signal
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

from rollingstar.logs.reader import LogReader
from rollingstar.pipelines.simulate import simulate_to_log
from rollingstar.sensors.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "configs" / "scenarios" / "he2021b.yaml"
PIPELINE = ROOT / "configs" / "pipelines" / "baseline.yaml"


def _command(rec: Path, out: Path, every: int, resume: bool = False) -> list[str]:
    args = [sys.executable, "-m", "rollingstar.cli", "run", str(PIPELINE), str(rec), "-o", str(out), "-q",
            "--checkpoint-every", str(every)]
    return [*args, "--resume"] if resume else args


def _content(path: Path):
    """The messages (topic, log time, decoded content) in log-time order and the metadata without the creation time."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reader = LogReader(path)
        messages = [(m.topic, m.log_time_ns, json.dumps(m.data, sort_keys=True) if isinstance(m.data, dict)
                     else m.data.SerializeToString()) for m in reader.messages()]
        meta = reader.metadata()
    meta["rollingstar"].pop("created_utc", None)
    return messages, meta


def _started(command: list[str], out: Path) -> subprocess.Popen:
    """``command`` started, once it has opened its output (``.<name>.tmp-<pid>``) or ended."""
    proc = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    while proc.poll() is None and not out.with_name(f".{out.name}.tmp-{proc.pid}").exists():
        time.sleep(0.005)
    return proc


def _writing_time(command: list[str], out: Path) -> float:
    """Seconds ``command`` spends from opening its output to its end."""
    proc = _started(command, out)
    t0 = time.monotonic()
    _, err = proc.communicate(timeout=300)
    if proc.returncode != 0:
        raise RuntimeError(f"the uninterrupted run failed: {err}")
    return time.monotonic() - t0


def _cut(command: list[str], out: Path, sig: signal.Signals, delay: float) -> str:
    """Run ``command``, send ``sig`` ``delay`` seconds after it opened its output; what happened, in words."""
    proc = _started(command, out)
    time.sleep(delay)
    if proc.poll() is not None:
        return f"finished before {sig.name}"
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    expected = {signal.SIGKILL: -signal.SIGKILL, signal.SIGINT: 130}[sig]
    if proc.returncode != expected:
        raise RuntimeError(f"{sig.name}: exit {proc.returncode}, expected {expected}: {err}")
    return f"{sig.name} after {delay:.2f} s"


def _resume(command: list[str]) -> str:
    res = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=300)
    if res.returncode != 0:
        raise RuntimeError(f"--resume: exit {res.returncode}: {res.stderr}")
    first = res.stdout.splitlines()[0] if res.stdout else ""
    return first.replace("resumed from a checkpoint after", "checkpoint at").replace(
        "resumed: no usable checkpoint, every frame re-run from the first", "no checkpoint")


def _case(i: int, rng: random.Random, sig: signal.Signals, rec: Path, work: Path, every: int, duration: float,
          reference) -> bool:
    out = work / f"case{i}" / "out.mcap"
    out.parent.mkdir()
    steps = [_cut(_command(rec, out, every), out, sig, rng.uniform(0.0, duration))]
    if not out.exists():
        if rng.random() < 1 / 3:  # cut the resume too, then resume again
            second = rng.choice([signal.SIGKILL, signal.SIGINT])
            steps.append("resume " + _cut(_command(rec, out, every, resume=True), out, second,
                                          rng.uniform(0.0, duration)))
        if not out.exists():
            steps.append("resume: " + _resume(_command(rec, out, every, resume=True)))
    equal = _content(out) == reference
    print(f"case {i}: {'; '.join(steps)} -> {'equal' if equal else 'DIFFERENT'}", flush=True)
    return equal


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=10)
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--every", type=int, default=25, help="--checkpoint-every of the runs that are cut")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = random.Random(args.seed)
    started = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        rec, ref = work / "rec.mcap", work / "ref.mcap"
        simulate_to_log(load_scenario(SCENARIO), rec, frames=args.frames, show_progress=False)
        duration = _writing_time(_command(rec, ref, args.every), ref)
        reference = _content(ref)
        signals = [signal.SIGKILL, signal.SIGINT] * (args.cases // 2) + [signal.SIGKILL] * (args.cases % 2)
        rng.shuffle(signals)
        print(f"{args.frames} frames, checkpoint every {args.every}; the uninterrupted run wrote "
              f"{len(reference[0])} messages in {duration:.1f} s", flush=True)
        results = [_case(i, rng, sig, rec, work, args.every, duration, reference) for i, sig in enumerate(signals)]
    bad = results.count(False)
    print(f"{len(results)} cases: {len(results) - bad} equal to the uninterrupted run, {bad} different "
          f"({time.monotonic() - started:.0f} s)")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
