"""Checkpoints of a run's state, so that ``rollingstar run --resume`` continues from the last one.

Without a checkpoint a resumed run re-runs every stage from the recording's first frame (the stages
carry state -- tracking priors, filters -- that only the frames before can rebuild; see
:mod:`rollingstar.pipelines.resume`). With one, it restores that state and reads on from the frame after it.

What is saved, every ``every`` frames read (and once more on SIGINT): the stages, the frame checker
(previous frame, for the time-order and duplicate checks), the run's counters, and how many
messages the output log had been given with their :class:`~rollingstar.logs.digest.MessageDigest`
(a resume copies exactly those messages from the partial output and checks the digest). Saved only
when no stage holds frames back (a smoother's held frames are neither written nor safely
restartable), so pipelines with a smoother never checkpoint and resume from the first frame.

Where: ``<output>.checkpoints/frames-<n>.pkl``, written to a temporary name and renamed (a kill
while saving leaves the previous checkpoints intact); the newest ``KEEP`` are kept, and the one a
resume started from. The output log reaches the disk a chunk at a time, so the newest checkpoint
may be ahead of what a killed run left readable: the resume takes the newest checkpoint whose
messages the partial output holds, else runs from the start. The folder is removed when the run
completes.

Identity: a checkpoint holds the :class:`RunIdentity` of its run (SHA-256 of the recording's
content, of the scenario and of the pipeline); a checkpoint of another run is refused
(:class:`~rollingstar.errors.UserError` naming what differs), never used.

Format: pickle (the stages' state is whatever numpy arrays and Python objects each plugin keeps; a
hand-written format per plugin would be a second description of every plugin's state). The sensor
context (camera, catalogue) is not stored: it is rebuilt from the recording and re-attached. A
stage that cannot be pickled (gtsam's ``BatchFixedLagSmoother``) turns checkpoints off for the run
with one warning. Pickle runs code when loaded: a checkpoint is read only from beside the output
the user names, written by this program; never resume from a checkpoint folder you did not write.
"""
from __future__ import annotations

import hashlib
import io
import os
import pickle
import shutil
import warnings
from dataclasses import dataclass
from pathlib import Path

from rollingstar.errors import UserError

KEEP = 3
DEFAULT_EVERY = 500
_CONTEXT_ID = "rollingstar-sensor-context"


def checkpoint_dir(output: Path) -> Path:
    return output.with_name(output.name + ".checkpoints")


def check_checkpoint_dir(output: Path) -> None:
    """A :class:`UserError` when something other than a folder (a file, a symbolic link) is where the
    checkpoints of ``output`` go."""
    folder = checkpoint_dir(Path(output))
    if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
        raise UserError(f"{folder}: exists and is not a folder; `rollingstar run` keeps the checkpoints of "
                        f"{Path(output).name} there (for --resume). Remove it or choose another output path.")


def _sha256_text(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass(frozen=True)
class RunIdentity:
    """What a run's output is made from: SHA-256 of the recording's content, of the scenario YAML
    and of the pipeline YAML, and whether the recording's images are copied into it
    (``run --with-images``). Written to the output (metadata record ``run``) and to each checkpoint."""

    recording_sha256: str
    scenario_sha256: str
    pipeline_sha256: str
    with_images: bool = False

    @classmethod
    def of(cls, recording: str | Path, scenario_yaml: str, pipeline_yaml: str, with_images: bool = False) -> RunIdentity:
        with open(recording, "rb") as fh:
            content = hashlib.file_digest(fh, "sha256").hexdigest()
        return cls(content, _sha256_text(scenario_yaml), _sha256_text(pipeline_yaml), bool(with_images))

    def as_metadata(self) -> dict[str, str]:
        out = {"recording_sha256": self.recording_sha256, "scenario_sha256": self.scenario_sha256,
               "pipeline_sha256": self.pipeline_sha256}
        return out | ({"with_images": "true"} if self.with_images else {})

    @classmethod
    def from_metadata(cls, record: dict[str, str]) -> RunIdentity | None:
        """The identity in a ``run`` metadata record; None when the record lacks one of its keys."""
        try:
            return cls(record["recording_sha256"], record["scenario_sha256"], record["pipeline_sha256"],
                       record.get("with_images") == "true")
        except (KeyError, TypeError, AttributeError):
            return None

    def differences(self, other: RunIdentity) -> str:
        """Which inputs differ from ``other``'s, in words (``"the recording and the pipeline
        differ"``); empty when none does."""
        names = [f"the {name}" for name in ("recording", "scenario", "pipeline")
                 if getattr(self, f"{name}_sha256") != getattr(other, f"{name}_sha256")]
        if self.with_images != getattr(other, "with_images", False):
            names.append("the --with-images choice")
        if not names:
            return ""
        return f"{' and '.join(names)} {'differs' if len(names) == 1 else 'differ'}"


@dataclass
class RunState:
    """Everything the runner's loop needs to continue after ``frames_read`` frame messages."""

    identity: RunIdentity
    frames_read: int  # frame messages consumed from the recording (duplicates included)
    n_frames: int  # frames processed
    stages: list
    checker: object
    counts: object  # the sink's Outcomes
    stage_seconds: dict
    messages: int = 0  # messages given to the output log so far (in write order)
    digest: str = ""  # their MessageDigest


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


def load_checkpoints(output: Path, identity: RunIdentity, context) -> list[RunState]:
    """Every readable checkpoint beside ``output``, newest first; a :class:`UserError` naming what
    differs when one was saved by a run of another recording, scenario or pipeline."""
    states = []
    for path in sorted(checkpoint_dir(Path(output)).glob("frames-*.pkl"), reverse=True):
        try:
            with open(path, "rb") as fh:
                state = _Unpickler(fh, context).load()
        except Exception as exc:  # a damaged checkpoint: try the one before
            warnings.warn(f"--resume: checkpoint {path} unreadable ({type(exc).__name__}: {exc}); trying an older one")
            continue
        saved = getattr(state, "identity", None) if isinstance(state, RunState) else None
        if not isinstance(saved, RunIdentity):
            warnings.warn(f"--resume: checkpoint {path} is not one this version of rollingstar wrote; not used")
            continue
        differ = saved.differences(identity)
        if differ:
            raise UserError(f"--resume: checkpoint {path} belongs to a run of other inputs "
                            f"({differ}); remove {path.parent} or run without --resume")
        states.append(state)
    return states
