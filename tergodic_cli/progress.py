"""Progress bars on stderr for anything that takes more than a couple of seconds."""

from __future__ import annotations

import contextlib
import os
import sys
from typing import Iterable, Iterator, TypeVar

T = TypeVar("T")


def _console():
    """The stderr console of bars and spinners; None when off or not a terminal (a file, a pipe)."""
    if os.environ.get("TERGODIC_NO_PROGRESS"):
        return None
    from rich.console import Console

    console = Console(file=sys.stderr)
    return console if console.is_terminal else None


#: The rich consoles of the bars and spinners on screen now, innermost last (see :func:`echo`).
_LIVE: list = []


def echo(message: str) -> None:
    """One line on stderr. With a bar or spinner on screen it goes through that display's console,
    which ends the animated line first: a plain write would run into it ("...approachingrobot: at hover")."""
    if _LIVE:
        _LIVE[-1].print(message, markup=False, highlight=False, emoji=False, soft_wrap=True)
    else:
        print(message, file=sys.stderr, flush=True)


def track(iterable: Iterable[T], total: int | None = None, description: str = "",
          weight=None) -> Iterator[T]:
    """Iterate with a rich progress bar on stderr (silent when disabled).

    ``weight(item)``: how many units an item completes (default 1), e.g. the runs in a batch, so the
    bar counts what the user was told about. It is applied after the item's loop body.
    """
    console = _console()
    if console is None:
        yield from iterable
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    columns = (TextColumn("[progress.description]{task.description}"), BarColumn(), MofNCompleteColumn(),
               TimeElapsedColumn(), TimeRemainingColumn())
    with Progress(*columns, console=console) as bar:
        _LIVE.append(console)
        try:
            task = bar.add_task(description, total=total)
            for item in iterable:
                yield item
                bar.advance(task, 1 if weight is None else weight(item))
        finally:
            _LIVE.remove(console)


@contextlib.contextmanager
def Spinner(description: str) -> Iterator[None]:  # noqa: N802  (used like a class: ``with Spinner(...)``)
    """Show a labelled spinner while a blocking call runs."""
    console = _console()
    if console is None:
        yield
        return
    with console.status(description):
        _LIVE.append(console)
        try:
            yield
        finally:
            _LIVE.remove(console)
