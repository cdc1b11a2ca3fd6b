"""Writing outputs without losing what the user already has.

Every command that writes a file or a report folder goes through :func:`safe_output`:

- the output is refused before anything is opened when it resolves to one of the command's inputs
  (the same path, a symbolic or hard link to it, or a path inside an input folder);
- a lock file beside the output (``.<name>.lock``) keeps a second command from writing the same
  output; the second one fails naming the process that holds it;
- the command writes to a temporary path beside the target (same folder, so the final rename is
  atomic) and the temporary path is renamed over the target only when the command completes;
- when the command fails or is interrupted, the target is left as it was and what was written is
  kept as ``<name>.partial`` (a file or folder whose name says it is incomplete).

Replacing an existing output is announced with an :class:`OverwriteWarning` (the command line
prints it as one line).
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import shutil
import stat
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path

from rollingstar.errors import UserError

PARTIAL_SUFFIX = ".partial"
#: Written into every output folder, so that a later run knows the folder is one it may replace.
FOLDER_MARK = ".rollingstar-output"


class PartialOutputWarning(UserWarning):
    """A command failed; what it wrote is kept under the ``.partial`` name."""


class OverwriteWarning(UserWarning):
    """An existing output is being replaced (it stays untouched until the new one is complete)."""


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def check_not_an_input(output: str | Path, inputs: Iterable[str | Path]) -> None:
    """Raise :class:`UserError` when ``output`` is, links to, or lies inside one of ``inputs``."""
    out = Path(output)
    resolved = out.resolve()
    for given in inputs:
        source = Path(given)
        if not source.exists():
            continue
        src = source.resolve()
        inside = source.is_dir() and (resolved == src or src in resolved.parents)
        if resolved == src or _same_file(out, source) or inside:
            what = "a path inside the input folder" if inside and resolved != src else "the input"
            raise UserError(f"{out}: the output is {what} {source}; writing it would destroy the input. "
                            "Choose another output path.")
        if resolved in src.parents:
            raise UserError(f"{out}: the output folder contains the input {source}, and an output folder is "
                            "replaced as a whole. Choose another output path.")


def _acquire(lock_path: Path, target: Path) -> int:
    """An open, exclusively locked descriptor of ``lock_path``.

    The holder removes the lock file when it is done, so a lock taken on a file that was removed
    meanwhile is no lock: it is retried on the current file."""
    while True:
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "another process"
            os.close(fd)
            if exc.errno not in (errno.EAGAIN, errno.EACCES):
                raise
            raise UserError(f"{target}: another rollingstar command is writing this output ({holder}); "
                            "wait for it to finish or choose another output path") from None
        try:
            current = os.stat(lock_path).st_ino
        except FileNotFoundError:
            current = None
        if current == os.fstat(fd).st_ino:
            return fd
        os.close(fd)


@contextlib.contextmanager
def output_lock(target: Path) -> Iterator[None]:
    """Hold ``.<name>.lock`` beside ``target`` for the duration; a second holder gets a UserError."""
    lock_path = target.with_name(f".{target.name}.lock")
    fd = _acquire(lock_path, target)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}".encode(), 0)
        yield
    finally:
        with contextlib.suppress(OSError):
            lock_path.unlink()
        os.close(fd)


def _temporary_beside(target: Path) -> Path:
    return target.with_name(f".{target.name}.tmp-{os.getpid()}")


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists() or path.is_symlink():
        path.unlink()


def _check_target_kind(target: Path, directory: bool) -> None:
    if target.is_symlink() and not target.exists():
        raise UserError(f"{target}: a broken symbolic link; remove it or choose another output path")
    if target.exists() and target.is_dir() != directory:
        want, found = ("a folder", "a file") if directory else ("a file", "a folder")
        raise UserError(f"{target}: exists and is {found}, but this output is {want}; remove it or choose "
                        "another output path")
    if not target.parent.is_dir():
        raise UserError(f"{target}: the folder {target.parent} does not exist")
    if directory and _holds_other_files(target):
        raise UserError(f"{target}: the folder holds files that no rollingstar command wrote; the output folder "
                        "is replaced as a whole, so give a new or empty folder")


def _check_replaceable(target: Path, magic: bytes, kind: str) -> None:
    if target.is_file() and target.stat().st_size:
        with open(target, "rb") as f:
            head = f.read(len(magic))
        if head != magic:
            raise UserError(f"{target}: exists and is not {kind}; this command writes {kind} and would replace it: "
                            "remove it or choose another output path")


def _holds_other_files(folder: Path) -> bool:
    return folder.is_dir() and any(folder.iterdir()) and not (folder / FOLDER_MARK).is_file()


def _is_special_file(target: Path) -> bool:
    """A device, pipe or socket (``-o /dev/null``): written to directly, since renaming a file over it
    would replace the device itself."""
    try:
        mode = target.stat().st_mode
    except OSError:
        return False
    return not (stat.S_ISREG(mode) or stat.S_ISDIR(mode))


def _has_content(target: Path) -> bool:
    return target.is_file() or (target.is_dir() and any(target.iterdir()))


def _install(tmp: Path, target: Path, directory: bool) -> None:
    """Rename the finished ``tmp`` over ``target`` (a folder is swapped: old aside, new in, old removed)."""
    if directory and target.exists():
        old = target.with_name(f".{target.name}.old-{os.getpid()}")
        os.replace(target, old)
        os.replace(tmp, target)
        _remove(old)
    else:
        os.replace(tmp, target)


@contextlib.contextmanager
def safe_output(target: str | Path, inputs: Iterable[str | Path] = (), directory: bool = False,
                replaces: tuple[bytes, str] | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``target`` to write to; rename it into place on success.

    On an exception (Ctrl-C included) the target is untouched and the temporary path becomes
    ``<target>.partial`` (replacing an older one); the exception propagates. A ``target`` that is a
    device or pipe is yielded itself: there is nothing to replace atomically or to keep.
    ``replaces``: (the first bytes of, name of) the kind of file written; an existing file of
    another kind (a user's notes given as the output by mistake) is refused, never replaced."""
    target = Path(target)
    check_not_an_input(target, inputs)
    if not directory and _is_special_file(target):
        yield target
        return
    _check_target_kind(target, directory)
    if replaces is not None and not directory:
        _check_replaceable(target, *replaces)
    with output_lock(target):
        if _has_content(target):
            warnings.warn(OverwriteWarning(f"{target} exists: it is replaced when this command completes "
                                           "(and kept as it is if the command fails)"), stacklevel=3)
        tmp = _temporary_beside(target)
        _remove(tmp)
        if directory:
            tmp.mkdir()
            (tmp / FOLDER_MARK).write_text("written by rollingstar; a later run may replace this folder\n")
        try:
            yield tmp
        except BaseException as exc:
            if tmp.exists():
                partial = target.with_name(target.name + PARTIAL_SUFFIX)
                _remove(partial)
                os.replace(tmp, partial)
                if not isinstance(exc, KeyboardInterrupt):  # an interruption's own message says where
                    warnings.warn(PartialOutputWarning(f"what was written before the failure is kept as {partial}; "
                                                       f"{target} is untouched"), stacklevel=3)
            raise
        _install(tmp, target, directory)


def write_text(target: str | Path, text: str, inputs: Iterable[str | Path] = ()) -> Path:
    """Write ``text`` to ``target`` through :func:`safe_output` (a report, a table, a config)."""
    with safe_output(target, inputs) as tmp:
        tmp.write_text(text)
    return Path(target)
