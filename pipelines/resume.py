"""``rollingstar run --resume``: continue a run that was cut short (killed, interrupted or failed).

A run writes its output through :func:`rollingstar.outputs.safe_output`: an interrupted or failed
run leaves what it wrote in ``<output>.partial``, a killed one in ``.<output name>.tmp-<pid>``. The
resume takes the newest of these (:func:`find_partial`; the resumed run holds the output's lock, so
no live process writes them) and refuses it, with a :class:`~rollingstar.errors.UserError` naming
what differs, when it was made from another recording, scenario or pipeline (its ``run`` metadata
record, :class:`~rollingstar.pipelines.checkpoint.RunIdentity`).

Frames are never recognised by their content or their ``frame`` field. Either

a. a checkpoint (:mod:`rollingstar.pipelines.checkpoint`) says how many messages ``K`` the run had
   written when it was saved, with their digest, and the partial output's first ``K`` messages *in
   write order* have that digest: they are copied, the stages' state is restored, and the run
   reads on from the frame after the checkpoint; or
b. no checkpoint is usable: nothing is copied and the run starts again from the first frame.

*Equivalent* (what the tests check): the resumed log and an uninterrupted run's log hold the same
messages -- topic, log time and decoded content, in log-time order -- and the same metadata apart
from the wall-clock ``rollingstar.created_utc``. This holds because the runner is deterministic:
the first ``K`` messages of every run of one recording, scenario and pipeline are the same.
"""
from __future__ import annotations

import contextlib
import dataclasses
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from rollingstar.errors import PipelineError, UserError
from rollingstar.logs.digest import MessageDigest
from rollingstar.logs.errors import LogFormatError, TruncatedLogWarning
from rollingstar.logs.reader import LogReader
from rollingstar.logs.writer import LogWriter
from rollingstar.outputs import PARTIAL_SUFFIX
from rollingstar.pipelines.checkpoint import RunIdentity, RunState, load_checkpoints

#: The output's metadata record that holds its :class:`RunIdentity`.
IDENTITY_RECORD = "run"


@dataclass(frozen=True)
class ResumePoint:
    """Where a resumed run starts: the partial output it continues (None: there is none) and the
    checkpoint whose messages it copies from it (None: it runs from the first frame, copying nothing)."""

    partial: Path | None = None
    reader: LogReader | None = None
    state: RunState | None = None
    partials: tuple[Path, ...] = ()  # every partial output of this run: obsolete once it completes

    def copy_into(self, writer: LogWriter) -> None:
        """Copy the checkpoint's messages from the partial output, in write order, and check that
        ``writer`` (made with ``digest=True``) now holds exactly them."""
        if self.state is None:
            return
        count = self.state.messages
        with _quiet():
            for i, (message, _) in enumerate(self.reader.written_messages()):
                if i == count:
                    break
                writer.write_message(message)
        if (writer.digest.count, writer.digest.hexdigest()) != (count, self.state.digest):
            raise PipelineError(f"--resume: the {count} message(s) copied from {self.partial} were not written back "
                                "as they were read (a bug in copying); run again without --resume")


def leftovers(output: Path) -> list[Path]:
    """What earlier runs of ``output`` left: ``<output>.partial`` and killed runs' temporary files."""
    killed = [p for p in output.parent.iterdir() if p.name.startswith(f".{output.name}.tmp-")]
    candidates = [output.with_name(output.name + PARTIAL_SUFFIX), *killed]
    return [p for p in candidates if p.is_file() and not p.is_symlink()]


def find_partials(output: Path, identity: RunIdentity) -> list[tuple[Path, LogReader]]:
    """The partial outputs of ``output`` made from ``identity``'s inputs, opened, newest first.

    The newest one that reads as a log must be such a one (else a :class:`UserError` naming what
    differs); an older one of another run is left alone, with a warning. Empty (with a warning)
    when there is none."""
    found: list[tuple[Path, LogReader]] = []
    for path in sorted(leftovers(output), key=lambda p: p.stat().st_mtime_ns, reverse=True):
        try:
            with _quiet():
                reader = LogReader(path)
        except LogFormatError as exc:
            warnings.warn(f"--resume: {path} is not a readable log ({exc}); not used")
            continue
        try:
            check_identity(path, reader, identity)
        except UserError as exc:
            if not found:
                raise
            warnings.warn(f"{exc}: not used")
            continue
        found.append((path, reader))
    if not found:
        warnings.warn(f"--resume: found no partial output of {output} ({output.name}{PARTIAL_SUFFIX} or a killed "
                      f"run's .{output.name}.tmp-*); running from the first frame")
    return found


def check_identity(path: Path, reader: LogReader, identity: RunIdentity) -> None:
    """A :class:`UserError` unless ``reader`` is a ``run`` log made from ``identity``'s inputs."""
    meta = reader.metadata()
    saved = RunIdentity.from_metadata(meta.get(IDENTITY_RECORD, {}))
    if meta.get("rollingstar", {}).get("kind") != "run" or saved is None:
        raise UserError(f"--resume: {path} is not the output of a `rollingstar run` that records what it was made "
                        f"from (metadata '{IDENTITY_RECORD}'); remove it or run without --resume")
    differ = saved.differences(identity)
    if differ:
        raise UserError(f"--resume: {path} was made from other inputs ({differ}: the recording, scenario and "
                        f"pipeline SHA-256 and the --with-images choice it records are not this run's); remove it or "
                        f"run without --resume")


def find_resume_point(output: Path, identity: RunIdentity, context) -> ResumePoint:
    """The furthest checkpoint whose messages one of the partial outputs holds, with that partial
    output (see the module docstring); without one, the newest partial output and no checkpoint."""
    partials = find_partials(output, identity)
    if not partials:
        return ResumePoint()
    states = load_checkpoints(output, identity, context)
    best = ResumePoint(*partials[0])
    for path, reader in partials:
        held = prefix_digests(reader, {state.messages for state in states})
        usable = [state for state in states if held.get(state.messages) == state.digest]
        if usable and (best.state is None or usable[0].frames_read > best.state.frames_read):
            best = ResumePoint(path, reader, usable[0])
    return dataclasses.replace(best, partials=tuple(path for path, _ in partials))


def prefix_digests(reader: LogReader, counts: set[int]) -> dict[int, str]:
    """For each ``k`` in ``counts`` that the log holds that many messages of: the digest of its first
    ``k`` messages in write order."""
    digest, out = MessageDigest(), {}
    if 0 in counts:
        out[0] = digest.hexdigest()
    last = max(counts, default=0)
    with _quiet():
        for message, data in _readable(reader):
            if digest.count >= last:
                break
            digest.add(message.topic, message.log_time_ns, data)
            if digest.count in counts:
                out[digest.count] = digest.hexdigest()
    return out


def _readable(reader: LogReader) -> Iterator:
    """The log's messages in write order, up to the first that cannot be decoded."""
    try:
        yield from reader.written_messages()
    except LogFormatError:
        return


@contextlib.contextmanager
def _quiet():
    """A cut or damaged partial output is what a resume is for: the reader's warnings about it are not news."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TruncatedLogWarning)
        yield
