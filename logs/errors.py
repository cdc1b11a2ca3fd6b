"""Errors and warnings raised when reading or writing rollingstar MCAP logs."""
from __future__ import annotations


class LogFormatError(ValueError):
    """A log file (or a record in it) does not follow docs/log-format.md.

    The message always names the file and, where it applies, the topic, the log time and what
    was expected.
    """


class TruncatedLogWarning(UserWarning):
    """A log file was cut short or has a damaged part; the complete messages were still read."""


class LogWriteError(OSError):
    """The log could not be written (disk full, device error). The message names the file and how
    much of it is on disk; every chunk finished before the failure stays readable."""
