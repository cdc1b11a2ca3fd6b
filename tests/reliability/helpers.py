"""Hostile recordings made from good ones, and the CLI run in-process (exit code, stderr)."""
from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from rollingstar.logs.reader import LogReader
from rollingstar.logs.writer import LogWriter

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = ROOT / "configs" / "scenarios" / "he2021b.yaml"
PIPELINE = ROOT / "configs" / "pipelines" / "baseline.yaml"


def rewrite(src, dst, edit=None, metadata_edit=None, chunk_size: int = 262144):
    """Copy a log; ``edit(messages) -> messages`` (a list of reader Messages) may drop, add, reorder."""
    reader = LogReader(src)
    meta = {k: v for k, v in reader.metadata().items() if k != "rollingstar"}
    if metadata_edit:
        meta = metadata_edit(meta)
    msgs = list(reader.messages())
    if edit:
        msgs = edit(msgs)
    with LogWriter(dst, kind="simulation", metadata=meta, chunk_size=chunk_size) as w:
        for m in msgs:
            w.write_message(m)
    return dst


def cli(*args):
    """``rollingstar ARGS`` in-process: (exit code, stdout, stderr)."""
    from rollingstar.cli import app

    res = CliRunner().invoke(app, [str(a) for a in args])
    return res.exit_code, res.stdout, res.stderr


def assert_exit_2(args, *needles):
    code, out, err = cli(*args)
    assert code == 2, (code, out, err)
    assert "Traceback" not in err + out
    flat = " ".join(err.split())
    for n in needles:
        assert n in flat, (n, err)
    return flat
