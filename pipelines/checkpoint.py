"""Checkpoints of a run's state, so that ``rollingstar run --resume`` continues from the last one.

Without a checkpoint a resumed run re-runs every stage from the recording's first frame (the stages
carry state -- tracking priors, filters -- that only the frames before can rebuild; see
:mod:`rollingstar.pipelines.resume`). With one, it restores that state and reads on from the frame after it.

What is saved, every ``every`` frames read (and once more on SIGINT): the stages, the frame checker
(previous frame, for the time-order and duplicate checks), the run's counters and the frame indices
written so far (as ranges). Saved only when no stage holds frames back (a smoother's held frames
are neither written nor safely restartable), so pipelines with a smoother never checkpoint and
resume from frame 0 as before.

Where: ``<output>.checkpoints/frames-<n>.pkl``, written to a temporary name and renamed (a kill
while saving leaves the previous checkpoints intact); the newest ``KEEP`` are kept. The output log
reaches the disk a chunk at a time, so the newest checkpoint may be ahead of what a killed run left
readable: the resume takes the newest checkpoint whose written frames are all complete in the
partial output, else runs from the start. The directory is removed when the run completes.

Format: pickle (the stages' state is whatever numpy arrays and Python objects each plugin keeps; a
hand-written format per plugin would be a second description of every plugin's state). The sensor
context (camera, catalogue) is not stored: it is rebuilt from the recording and re-attached. A
stage that cannot be pickled (gtsam's ``BatchFixedLagSmoother``) turns checkpoints off for the run
with one warning. A checkpoint names the recording (path, size, modification time), the scenario
and the pipeline (their YAML) by a SHA-256 key and is used only when all match. Pickle runs code
when loaded: a checkpoint is read only from beside the output the user names, written by this
program; never resume from a checkpoint directory you did not write.
"""
from __future__ import annotations

import hashlib
import io
import os
import pickle
import shutil
import warnings
from dataclasses import dataclass, field
from pathlib import Path

KEEP = 3
DEFAULT_EVERY = 500
_CONTEXT_ID = "rollingstar-sensor-context"


def checkpoint_dir(output: Path) -> Path:
    return output.with_name(output.name + ".checkpoints")


def run_key(recording: Path, metadata: dict) -> str:
    """SHA-256 of the recording's identity and the scenario and pipeline YAML."""
    st = Path(recording).stat()
    h = hashlib.sha256()
    for part in (str(Path(recording).resolve()), str(st.st_size), str(st.st_mtime_ns),
                 metadata["scenario"].get("yaml", ""), metadata["pipeline"].get("yaml", "")):
        h.update(part.encode() + b"\0")
    return h.hexdigest()


@dataclass
class RunState:
    """Everything the runner's loop needs to continue after ``frames_read`` frame messages."""

    key: str
    frames_read: int  # frame messages consumed from the recording (duplicates included)
    n_frames: int  # frames processed
    stages: list
    checker: object
    counts: dict
    stage_seconds: dict
    written: list[tuple[int, int]] = field(default_factory=list)  # frame indices written, as [start, stop) ranges

    def written_within(self, done: set[int]) -> bool:
        return all(i in done for a, b in self.written for i in range(a, b))


def add_index(ranges: list[tuple[int, int]], index: int) -> None:
    """Record frame ``index`` as written (ranges stay short for frames written in order)."""
    if ranges and ranges[-1][1] == index:
        ranges[-1] = (ranges[-1][0], index + 1)
    else:
        ranges.append((index, index + 1))


class _Pickler(pickle.Pickler):
    def __init__(self, file, context) -> None:
        super().__init__(file, protocol=pickle.HIGHEST_PROTOCOL)
        self._context = context

    def persistent_id(self, obj):
        return _CONTEXT_ID if obj is self._context else None


class _Unpickler(pickle.Unpickler):
    def __init__(self, file, context) -> None:
        super().__init__(file)
        self._context = context

    def persistent_load(self, pid):
        if pid != _CONTEXT_ID:
            raise pickle.UnpicklingError(f"unknown persistent id {pid!r}")
        return self._context


class CheckpointWriter:
    """Saves :class:`RunState` every ``every`` frames read; off after the first state that cannot be pickled."""

    def __init__(self, output: Path, context, every: int = DEFAULT_EVERY, keep: int | None = None) -> None:
        self.dir = checkpoint_dir(Path(output))
        self.context = context
        self.every = every
        self.enabled = every > 0
        self.keep = keep  # frames_read of the checkpoint a resume started from: never pruned
        self._last = None

    def due(self, frames_read: int) -> bool:
        return self.enabled and frames_read % self.every == 0 and frames_read != self._last

    def save(self, state: RunState) -> None:
        if not self.enabled:
            return
        if any(s.defers_output for s in state.stages):
            self.enabled = False  # a smoother holds frames: resume runs from the start (module docstring)
            return
        buf = io.BytesIO()
        try:
            _Pickler(buf, self.context).dump(state)
        except (pickle.PicklingError, TypeError, AttributeError) as exc:
            self.enabled = False
            warnings.warn(f"checkpoints off for this run (a resume would start from frame 0): the stages' state "
                          f"cannot be saved ({type(exc).__name__}: {exc})")
            return
        self.dir.mkdir(parents=True, exist_ok=True)
        final = self.dir / f"frames-{state.frames_read:09d}.pkl"
        tmp = final.with_suffix(".tmp")
        with open(tmp, "wb") as fh:
            fh.write(buf.getvalue())
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, final)
        self._last = state.frames_read
        for old in sorted(self.dir.glob("frames-*.pkl"))[:-KEEP]:
            if self.keep is None or old.name != f"frames-{self.keep:09d}.pkl":  # a resume killed again falls back to it
                old.unlink(missing_ok=True)

    def remove(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)


def load_checkpoint(output: Path, key: str, done: set[int], context) -> RunState | None:
    """The newest checkpoint beside ``output`` for this run whose written frames are all in ``done``."""
    folder = checkpoint_dir(Path(output))
    for path in sorted(folder.glob("frames-*.pkl"), reverse=True):
        try:
            with open(path, "rb") as fh:
                state = _Unpickler(fh, context).load()
        except Exception as exc:  # a damaged checkpoint: try the one before
            warnings.warn(f"--resume: checkpoint {path} unreadable ({type(exc).__name__}: {exc}); trying an older one")
            continue
        if not isinstance(state, RunState) or state.key != key:
            warnings.warn(f"--resume: checkpoint {path} belongs to another recording, scenario or pipeline; not used")
            continue
        if state.written_within(done):
            return state
    return None
