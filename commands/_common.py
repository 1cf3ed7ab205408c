"""Small option parsers shared by the verb modules (standard library only)."""

from __future__ import annotations

from tergodic_cli.errors import TergodicError


def parse_floats(text: str | None, n: int | None, option: str, example: str) -> tuple[float, ...] | None:
    """Parse ``"a,b,c"`` into ``n`` floats (any count when ``n`` is None: the stage checks it), None into None,
    or raise a one-line error naming ``option``."""
    if text is None:
        return None
    try:
        values = tuple(float(x) for x in text.split(","))
    except ValueError:
        count = f"{n} " if n is not None else ""
        raise TergodicError(f"{option} '{text}' is not {count}comma-separated numbers", f"e.g. {option} {example}") from None
    if n is not None and len(values) != n:
        raise TergodicError(f"{option} needs {n} numbers, got {len(values)}", f"e.g. {option} {example}")
    return values


def given_options(ctx) -> set[str]:
    """The parameters given on the command line (not defaults): they override a ``--config``."""
    return {n for n in ctx.params if (src := ctx.get_parameter_source(n)) is not None and src.name == "COMMANDLINE"}


#: The ``--help`` epilog of every verb ("\b": click prints the lines as they are).
EXIT_CODES = ("Exit codes:\n\n\b\n  0    complete\n  2    bad input, or an output that cannot be written\n"
              "  3    the robot stopped on a fault and reached a safe state\n  130  interrupted (Ctrl-C)\n"
              "  143  terminated (SIGTERM)")
