"""Small option parsers shared by the verb modules (standard library only)."""

from __future__ import annotations

from tergodic_cli.config import parse_floats  # noqa: F401  (its home is config.py; the verbs import it from here)


def given_options(ctx) -> set[str]:
    """The parameters given on the command line (not defaults): they override a ``--config``."""
    return {n for n in ctx.params if (src := ctx.get_parameter_source(n)) is not None and src.name == "COMMANDLINE"}


#: The ``--help`` epilog of every verb ("\b": click prints the lines as they are); the verbs that
#: never drive a robot (capture, precompute) leave out code 3.
_CODES = (("0", "complete"), ("2", "bad input, or an output that cannot be written"),
          ("3", "the robot stopped on a fault and reached a safe state"), ("130", "interrupted (Ctrl-C)"),
          ("143", "terminated (SIGTERM)"))


def exit_codes(robot: bool = True) -> str:
    """The exit-code table of a verb's ``--help``; ``robot`` adds code 3 (a fault ended in a safe state)."""
    rows = [f"  {c:<5}{what}" for c, what in _CODES if robot or c != "3"]
    return "Exit codes:\n\n\b\n" + "\n".join(rows)


