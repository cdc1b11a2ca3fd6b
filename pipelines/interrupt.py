"""Stop long work cleanly on SIGINT (Ctrl-C): finish the frame in hand, finalise the log, exit 130.

:func:`stop_on_sigint` replaces the SIGINT handler (main thread only) by one that only sets a flag
the frame loop checks between frames, so the log ends at a frame boundary with its summary and
footer written. A second SIGINT raises :class:`KeyboardInterrupt` at once (the writer still closes
the file; the reader recovers every complete chunk). The loop then raises :class:`Interrupted`,
which the CLI turns into its message and exit code 130 (128 + SIGINT).
"""
from __future__ import annotations

import signal
import threading
from contextlib import contextmanager


class Interrupted(KeyboardInterrupt):
    """Work stopped by SIGINT after finalising its output; the message says what was kept."""


class StopFlag:
    requested: bool = False


@contextmanager
def stop_on_sigint():
    """Yields a :class:`StopFlag` whose ``requested`` turns True on the first SIGINT."""
    flag = StopFlag()
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return

    def handler(signum, frame):
        if flag.requested:
            raise KeyboardInterrupt
        flag.requested = True

    old = signal.signal(signal.SIGINT, handler)
    try:
        yield flag
    finally:
        signal.signal(signal.SIGINT, old)
