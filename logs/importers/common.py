"""Shared parts of the importers: errors, warnings, strict CSV columns, the import metadata.

CSV files are read with the standard :mod:`csv` module and checked column by column with numpy.
This is hand-written (rather than ``numpy.genfromtxt`` or pandas) because every bad value must be
reported with its file, line and column, which those readers do not give.
"""
from __future__ import annotations

import csv
import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from rollingstar.config import excerpt
from rollingstar.errors import UserError
from rollingstar.logs.reader import LogReader
from rollingstar.sensors.conventions import NS_PER_S, seconds_to_ns


class ImportDataError(UserError):
    """Input to ``rollingstar import`` that cannot be used; names the file, the field or line, and why."""


class ImportDataWarning(UserWarning):
    """Input that was imperfect but recovered unambiguously (the message says what was assumed)."""


def warn(message: str) -> None:
    """Emit an :class:`ImportDataWarning` (the CLI prints it; the log keeps it in ``import.warnings``)."""
    warnings.warn(message, ImportDataWarning, stacklevel=3)


class WarningLog:
    """Collect the import warnings while still emitting them (they go into the log's metadata)."""

    def __init__(self) -> None:
        self.messages: list[str] = []

    def __call__(self, message: str) -> None:
        self.messages.append(message)
        warnings.warn(message, ImportDataWarning, stacklevel=3)


@dataclass(frozen=True)
class CsvTable:
    """A CSV file's columns as strings, with the 1-based file line of every data row."""

    path: Path
    header: tuple[str, ...]
    columns: dict[str, list[str]]
    lines: np.ndarray

    @property
    def n(self) -> int:
        return int(self.lines.size)

    def where(self, row: int, column: str) -> str:
        return f"{self.path}: line {int(self.lines[row])}, column {column!r}"


def read_csv(path: str | Path, required: Iterable[str], optional: Iterable[str] = (),
             one_of: Iterable[tuple[str, ...]] = (), log: WarningLog | None = None) -> CsvTable:
    """Read a headed CSV; missing required columns, ragged rows and empty files raise ImportDataError.

    ``one_of`` lists groups of alternative column names of which exactly one must be present
    (e.g. ``("t_ns", "time_s")``). Columns not named anywhere are ignored with a warning.
    Lines starting with ``#`` and blank lines are skipped.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise ImportDataError(f"{path}: CSV file not found") from None
    except OSError as exc:
        raise ImportDataError(f"{path}: cannot read CSV file ({exc})") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise ImportDataError(f"{path}: line {line}: byte 0x{raw[exc.start]:02x} is not UTF-8 text; a CSV file is "
                              "expected, saved as UTF-8 (or plain ASCII)") from None
    rows: list[tuple[int, list[str]]] = []
    reader = enumerate(csv.reader(text.splitlines()), start=1)
    lineno = 0
    try:
        for lineno, row in reader:
            if not row or all(not c.strip() for c in row) or row[0].lstrip().startswith("#"):
                continue
            rows.append((lineno, [c.strip() for c in row]))
    except csv.Error as exc:  # e.g. a field beyond the csv module's size limit
        raise ImportDataError(f"{path}: line {lineno + 1}: not readable as CSV ({exc})") from None
    if not rows:
        raise ImportDataError(f"{path}: empty CSV file (expected a header line with columns "
                              f"{', '.join(required)})")
    header_line, header = rows[0]
    if all(_is_number(h) for h in header):
        raise ImportDataError(f"{path}: line {header_line}: {excerpt(','.join(header), 60)} holds numbers, not "
                              f"column names; the first line must be a header naming the columns (required: "
                              f"{', '.join(required)})")
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise ImportDataError(f"{path}: line {header_line}: duplicate column(s) {', '.join(dup)}")
    required, optional, groups = list(required), list(optional), [tuple(g) for g in one_of]
    missing = [c for c in required if c not in header]
    if missing:
        sep = next((c for c in (";", "\t", "|") if any(c in h for h in header)), None)
        hint = (f"; the header looks {sep!r}-separated, but the columns must be separated by commas (and decimals "
                "written with '.')" if sep else "")
        raise ImportDataError(f"{path}: line {header_line}: missing column(s) {', '.join(missing)} "
                              f"(found {', '.join(header)}; required: {', '.join(required)}){hint}")
    for group in groups:
        present = [c for c in group if c in header]
        if len(present) != 1:
            what = "none" if not present else " and ".join(present)
            raise ImportDataError(f"{path}: line {header_line}: needs exactly one of the columns "
                                  f"{' or '.join(group)} (found {what})")
    known = set(required) | set(optional) | {c for g in groups for c in g}
    unknown = [h for h in header if h not in known]
    if unknown and log is not None:
        log(f"{path}: column(s) {', '.join(unknown)} not used by rollingstar; ignored")
    data = rows[1:]
    for lineno, row in data:
        if len(row) != len(header):
            raise ImportDataError(f"{path}: line {lineno}: {len(row)} fields, the header has {len(header)}")
    columns = {h: [row[i] for _, row in data] for i, h in enumerate(header) if h in known}
    return CsvTable(path, tuple(header), columns, np.array([ln for ln, _ in data], dtype=np.int64))


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def float_column(table: CsvTable, name: str, *, required: bool = True) -> np.ndarray:
    """A float column; empty cells are NaN (unknown) unless ``required``; NaN/inf text is rejected."""
    cells = table.columns[name]
    out = np.full(len(cells), np.nan)
    for i, cell in enumerate(cells):
        if cell == "":
            if required:
                raise ImportDataError(f"{table.where(i, name)}: empty; a number is required")
            continue
        try:
            value = float(cell)
        except ValueError:
            raise ImportDataError(f"{table.where(i, name)}: {cell!r} is not a number") from None
        if not math.isfinite(value):
            raise ImportDataError(f"{table.where(i, name)}: {cell!r} is not a finite number"
                                  + ("" if required else " (leave the cell empty for 'unknown')"))
        out[i] = value
    return out


INT64_MAX = 2**63 - 1


def int_column(table: CsvTable, name: str, *, default: int | None = None) -> np.ndarray:
    """An integer column (``12`` or ``12.0`` but not ``12.5``); empty cells take ``default`` or fail."""
    cells = table.columns[name]
    out = np.zeros(len(cells), dtype=np.int64)
    for i, cell in enumerate(cells):
        if cell == "":
            if default is None:
                raise ImportDataError(f"{table.where(i, name)}: empty; an integer is required")
            out[i] = default
            continue
        try:
            value = int(cell)
        except ValueError:
            try:
                value = float(cell)
            except ValueError:
                value = math.nan
            if not (math.isfinite(value) and value == int(value)):
                raise ImportDataError(f"{table.where(i, name)}: {cell!r} is not an integer") from None
            value = int(value)
        if not -INT64_MAX <= value <= INT64_MAX:
            raise ImportDataError(f"{table.where(i, name)}: {excerpt(cell, 40)} is beyond a 64-bit integer")
        out[i] = value
    return out


def bool_column(table: CsvTable, name: str) -> np.ndarray:
    """A boolean column: ``1/0``, ``true/false``, ``yes/no`` (any case); empty is False."""
    truthy, falsy = {"1", "true", "yes", "y", "t"}, {"0", "false", "no", "n", "f", ""}
    out = np.zeros(table.n, dtype=bool)
    for i, cell in enumerate(table.columns[name]):
        c = cell.lower()
        if c not in truthy | falsy:
            raise ImportDataError(f"{table.where(i, name)}: {cell!r} is not a boolean (1/0, true/false)")
        out[i] = c in truthy
    return out


TIME_COLUMNS = ("t_ns", "time_s")
"""A time column: integer nanoseconds or seconds, on the recording's own clock."""
UNIX_TIME_COLUMNS = ("t_unix_ns", "time_unix_s")
"""The same stated to be Unix time (UTC, since 1970-01-01T00:00:00Z): frame times that also give the observation time."""


def time_column(table: CsvTable) -> tuple[np.ndarray, str]:
    """Integer ns from whichever time column is present (``*_ns`` integer ns, ``time_*s`` seconds;
    :data:`TIME_COLUMNS`, :data:`UNIX_TIME_COLUMNS`); negative times are rejected."""
    name = next(c for c in (*TIME_COLUMNS, *UNIX_TIME_COLUMNS) if c in table.columns)
    if name.endswith("_ns"):
        try:
            t = int_column(table, name)
        except ImportDataError as exc:
            raise ImportDataError(f"{exc}; {name} holds integer nanoseconds (times in seconds go in a "
                                  f"{'time_unix_s' if 'unix' in name else 'time_s'} column instead)") from None
    else:
        seconds = float_column(table, name)
        beyond = np.flatnonzero(np.abs(seconds) >= INT64_MAX / NS_PER_S)
        if beyond.size:
            i = int(beyond[0])
            hint = (f"; {seconds[i] / 1e3:g} s if it is milliseconds: {name} holds seconds" if "unix" in name
                    and abs(seconds[i]) / 1e3 < 4e9 else ": shift the time origin")
            raise ImportDataError(f"{table.where(i, name)}: {seconds[i]:g} s is beyond the nanosecond clock "
                                  f"(int64 ns reach about 292 years){hint}")
        t = np.asarray(seconds_to_ns(seconds), dtype=np.int64).reshape(-1)
    bad = np.flatnonzero(t < 0)
    if bad.size:
        raise ImportDataError(f"{table.where(int(bad[0]), name)}: negative time; times must be >= 0 "
                              "(shift the time origin)")
    return t, name


def check_non_decreasing(table: CsvTable, values: np.ndarray, column: str, strict: bool = False) -> None:
    """Fail at the first row whose ``column`` goes back in time (or repeats, when ``strict``)."""
    if values.size < 2:
        return
    step = np.diff(values)
    bad = np.flatnonzero(step <= 0 if strict else step < 0)
    if bad.size:
        i = int(bad[0]) + 1
        word = "increase strictly" if strict else "not decrease"
        raise ImportDataError(f"{table.where(i, column)}: {values[i]} after {values[i - 1]} on line "
                              f"{int(table.lines[i - 1])}; {column} must {word}")


def import_metadata(fmt: str, source: Path, details: dict, warnings_log: WarningLog) -> dict[str, str]:
    """The ``import`` metadata record: format, source path, chosen values (JSON) and warnings (JSON)."""
    return {
        "format": fmt,
        "source": str(source),
        "details": json.dumps(details, sort_keys=True),
        "warnings": json.dumps(warnings_log.messages),
    }


def output_path(out: str | Path) -> Path:
    out = Path(out)
    if out.is_dir():
        raise ImportDataError(f"{out}: the output must be a file path (an .mcap file), not a directory")
    if not out.parent.is_dir():
        raise ImportDataError(f"{out}: the output's directory {out.parent} does not exist")
    return out


def import_warnings(recording: str | Path) -> list[str]:
    """The warnings an import emitted, as kept in the log's ``import.warnings`` metadata."""
    meta = LogReader(recording).metadata().get("import")
    if meta is None:
        raise ImportDataError(f"{recording}: not a log written by `rollingstar import` (no 'import' metadata)")
    return list(json.loads(meta.get("warnings", "[]")))


def describe_log(out: Path) -> str:
    """One line about an imported log (for the CLI): messages per topic and the camera's focal length."""
    reader = LogReader(out)
    details = json.loads(reader.metadata().get("import", {}).get("details", "{}"))
    parts = ", ".join(f"{t.message_count} on {t.topic}" for t in reader.summary_info().topics.values())
    focal = f" (camera f = {details['focal_px']:.1f} px)" if "focal_px" in details else ""
    return f"wrote {out}: {parts}{focal}"
