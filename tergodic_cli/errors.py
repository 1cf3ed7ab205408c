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


class RobotStopped(TergodicError):
    """The robot stopped on a fault and was made safe (tool lifted, arm still): exit code 3."""

    exit_code = 3


def require(condition: bool, problem: str, fix: str | None = None) -> None:
    """Raise :class:`TergodicError` unless ``condition`` holds."""
    if not condition:
        raise TergodicError(problem, fix)


def check_seed(seed, option: str = "--seed") -> int:
    """A seed as the random generators take it: a whole number >= 0 (numpy refuses a negative one
    with a traceback).

    Parameters
    ----------
    seed : int
        The seed; anything else (negative, a float, a bool) raises :class:`TergodicError`.
    option : str
        How the seed is named in the one-line error.

    Returns
    -------
    int
        The seed.
    """
    ok = isinstance(seed, int) and not isinstance(seed, bool) and 0 <= seed < 2**63
    require(ok, f"{option} must be a whole number >= 0, got {seed!r}", f"e.g. {option} 0")
    return int(seed)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised by the CLI's handler where the program is, so verbs clean up as on Ctrl-C."""

    exit_code = 143
    received = False  # set by the handler: verbs that absorb the interrupt (a robot made safe) still exit 143


class Interrupted(KeyboardInterrupt):
    """Ctrl-C (or SIGTERM) with the verb's own one-line ``message``, e.g. how to resume."""

    def __init__(self, message: str, cause: BaseException | None = None):
        super().__init__(message)
        self.message = message
        self.exit_code = getattr(cause, "exit_code", 130)


#: The operating system's causes in the words of the one-line message, where they differ from
#: its own (lower-cased) text; ENOSPC for numpy's short writes, which carry no errno.
_CAUSES = {
    "ENOSPC": "no space left on device",
    "EROFS": "read-only filesystem",
    "EPERM": "permission denied",
    "ENOTDIR": "a part of the path is a file, not a folder",
    "EISDIR": "it is a folder",
    "EEXIST": "it already exists",
    "ENAMETOOLONG": "the name is too long",
}


def os_cause(exc: OSError) -> str:
    """A short lower-case cause for ``exc`` (no errno number, no library text)."""
    import errno

    name = errno.errorcode.get(exc.errno or -1, "")
    text = str(exc).lower()
    if not name and ("space" in text or "written" in text):  # numpy's short write ("N requested and M written"): no errno
        name = "ENOSPC"
    return _CAUSES.get(name) or (exc.strerror or str(exc) or type(exc).__name__).lower()


def os_error(exc: OSError, path, action: str, fix: str) -> TergodicError:
    """One line for an operating-system failure: ``cannot ACTION PATH: CAUSE; FIX``."""
    return TergodicError(f"cannot {action} {path}: {os_cause(exc)}", fix)

