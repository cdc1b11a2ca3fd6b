"""One progress bar style for long work (rich), silent when not on a terminal or disabled."""
from __future__ import annotations

from contextlib import contextmanager

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

console = Console(stderr=True)
_silenced = False


def silence() -> None:
    """No progress bars from now on in this process (a command's ``-q`` for work that does not take
    an ``enabled`` flag through every layer, such as the paper reproductions)."""
    global _silenced
    _silenced = True


@contextmanager
def progress_bar(description: str, total: int | None, enabled: bool = True):
    """Yields ``advance(n=1)``; draws a bar on stderr when enabled and stderr is a terminal."""
    if not enabled or _silenced or not console.is_terminal:
        yield lambda n=1: None
        return
    with Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn(),
        console=console, transient=True,
    ) as progress:
        task = progress.add_task(description, total=total)
        yield lambda n=1: progress.advance(task, n)
