"""Outputs never destroy what the user has: inputs refused as outputs, atomic replace, partial kept, lock."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from rollingstar.errors import UserError
from rollingstar.outputs import (
    FOLDER_MARK,
    OverwriteWarning,
    PartialOutputWarning,
    check_not_an_input,
    output_lock,
    safe_output,
)


@pytest.fixture
def recording(tmp_path):
    path = tmp_path / "rec.mcap"
    path.write_bytes(b"precious")
    return path


@pytest.mark.parametrize("make", ["same", "symlink", "hardlink", "relative"])
def test_an_output_that_is_an_input_is_refused(tmp_path, recording, make, monkeypatch):
    out = {"same": lambda: recording, "relative": lambda: tmp_path / "sub" / ".." / "rec.mcap"}.get(make)
    if out is None:
        out = tmp_path / "alias.mcap"
        (os.symlink if make == "symlink" else os.link)(recording, out)
    else:
        out = out()
        (tmp_path / "sub").mkdir(exist_ok=True)
    with pytest.raises(UserError, match="destroy the input"):
        with safe_output(out, inputs=[recording]) as tmp:
            tmp.write_bytes(b"x")
    assert recording.read_bytes() == b"precious"


def test_an_output_inside_an_input_folder_is_refused(tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    (folder / "a.tiff").write_bytes(b"img")
    with pytest.raises(UserError, match="inside the input folder"):
        check_not_an_input(folder / "x.tiff", [folder])
    check_not_an_input(tmp_path / "x.mcap", [folder])  # beside the folder is fine


def test_success_replaces_the_target_and_says_so(tmp_path):
    target = tmp_path / "out.mcap"
    target.write_bytes(b"old")
    with pytest.warns(OverwriteWarning, match="replaced when this command completes"):
        with safe_output(target) as tmp:
            assert tmp.parent == target.parent and tmp != target
            tmp.write_bytes(b"new")
            assert target.read_bytes() == b"old"  # untouched until complete
    assert target.read_bytes() == b"new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mcap"]


@pytest.mark.parametrize("exc", [RuntimeError("stage failed"), KeyboardInterrupt()])
def test_failure_keeps_the_previous_output_and_the_partial_under_its_own_name(tmp_path, exc):
    target = tmp_path / "out.mcap"
    target.write_bytes(b"good 20-frame log")
    with pytest.raises(type(exc)), pytest.warns(UserWarning) as warned:
        with safe_output(target) as tmp:
            tmp.write_bytes(b"10 frames")
            raise exc
    assert any(w.category is OverwriteWarning for w in warned)
    said = [str(w.message) for w in warned if w.category is PartialOutputWarning]
    # a failure says where its partial result is; an interruption says it in its own message
    assert said == ([] if isinstance(exc, KeyboardInterrupt) else [f"what was written before the failure is kept "
                                                                  f"as {target}.partial; {target} is untouched"])
    assert target.read_bytes() == b"good 20-frame log"
    assert (tmp_path / "out.mcap.partial").read_bytes() == b"10 frames"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mcap", "out.mcap.partial"]


def test_folder_outputs_are_swapped_whole(tmp_path):
    target = tmp_path / "report"
    target.mkdir()
    (target / "index.html").write_text("old")
    (target / FOLDER_MARK).write_text("")
    with pytest.warns(OverwriteWarning):
        with safe_output(target, directory=True) as tmp:
            (tmp / "index.html").write_text("new")
    assert (target / "index.html").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]


def test_wrong_kind_and_missing_parent_are_errors(tmp_path):
    (tmp_path / "adir").mkdir()
    (tmp_path / "afile").write_text("x")
    with pytest.raises(UserError, match="is a folder, but this output is a file"):
        with safe_output(tmp_path / "adir"):
            pass
    with pytest.raises(UserError, match="is a file, but this output is a folder"):
        with safe_output(tmp_path / "afile", directory=True):
            pass
    with pytest.raises(UserError, match="does not exist"):
        with safe_output(tmp_path / "nope" / "out.mcap"):
            pass


def test_a_second_writer_is_refused_naming_the_holder(tmp_path):
    target = tmp_path / "out.mcap"
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from pathlib import Path; from rollingstar.outputs import output_lock\n"
        f"with output_lock(Path({str(target)!r})):\n    print('held', flush=True); sys.stdin.read()")],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(UserError, match=f"another rollingstar command is writing this output \\(pid {holder.pid}\\)"):
            with output_lock(target):
                pass
    finally:
        holder.communicate("", timeout=60)
    with output_lock(target):  # free again once the holder is gone
        pass
    assert not (tmp_path / ".out.mcap.lock").exists()


def test_a_folder_of_other_files_is_never_replaced(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    (home / "thesis.tex").write_text("years of work")
    with pytest.raises(UserError, match="holds files that no rollingstar command wrote"):
        with safe_output(home, directory=True):
            pass
    assert (home / "thesis.tex").read_text() == "years of work"
    empty = tmp_path / "empty"
    empty.mkdir()
    with safe_output(empty, directory=True) as tmp:  # an empty folder is fine, and not announced
        (tmp / "results.json").write_text("{}")
    with pytest.warns(OverwriteWarning):  # its own earlier output is replaced
        with safe_output(empty, directory=True) as tmp:
            (tmp / "results.json").write_text("{}")


def test_an_output_folder_that_contains_an_input_is_refused(tmp_path, recording):
    with pytest.raises(UserError, match="contains the input"):
        with safe_output(tmp_path, inputs=[recording], directory=True):
            pass
    assert recording.read_bytes() == b"precious"
