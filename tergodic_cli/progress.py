"""Progress bars on stderr for anything that takes more than a couple of seconds."""

from __future__ import annotations

import os
import sys
from typing import Iterable, Iterator, TypeVar

T = TypeVar("T")


def progress_enabled() -> bool:
    """Bars are on unless ``TERGODIC_NO_PROGRESS`` is set."""
    return not os.environ.get("TERGODIC_NO_PROGRESS")


def track(iterable: Iterable[T], total: int | None = None, description: str = "") -> Iterator[T]:
    """Iterate with a rich progress bar on stderr (silent when disabled)."""
    if not progress_enabled():
        yield from iterable
        return
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    console = Console(file=sys.stderr)
    columns = (
        TextColumn("[progress.description]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    with Progress(*columns, console=console, transient=not console.is_terminal) as bar:
        yield from bar.track(iterable, total=total, description=description)


class Spinner:
    """A context manager that shows a labelled spinner while a blocking call runs."""

    def __init__(self, description: str):
        self.description = description
        self._status = None

    def __enter__(self) -> "Spinner":
        if progress_enabled():
            from rich.console import Console

            self._status = Console(file=sys.stderr).status(self.description)
            self._status.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self._status is not None:
            self._status.__exit__(*exc)
