"""One exception type for every user-facing problem.

The CLI turns a :class:`TergodicError` into one line on stderr and exit code 2,
so bad input never ends in a traceback. The message names the problem and the
fix: ``"<problem>: <fix>"``.
"""

from __future__ import annotations


class TergodicError(Exception):
    """A problem the user can fix (bad input, bad config, missing extra)."""

    exit_code = 2

    def __init__(self, problem: str, fix: str | None = None):
        self.problem = problem
        self.fix = fix
        super().__init__(f"{problem}; {fix}" if fix else problem)


def require(condition: bool, problem: str, fix: str | None = None) -> None:
    """Raise :class:`TergodicError` unless ``condition`` holds."""
    if not condition:
        raise TergodicError(problem, fix)
