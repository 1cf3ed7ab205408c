"""The ``tergodic`` command line: one thin module per verb in ``tergodic_cli.commands``.

Every verb module imports only typer and the standard library at import time, so
``tergodic --help`` stays fast; heavy libraries load inside the verb that needs them.
"""

from __future__ import annotations

import sys

import typer

import importlib

from tergodic_cli.errors import TergodicError

#: The verbs, in pipeline order; each is a module in tergodic_cli.commands with a ``register(app)``.
VERBS = ("capture", "precompute", "explore", "replay", "sweep")

app = typer.Typer(
    name="tergodic",
    help=(
        "Tactile ergodic control on coloured point clouds.\n\n"
        "Pipeline: capture -> precompute -> explore -> replay.\n\n"
        "  tergodic capture --synthetic bowl --marking X --out cap/\n\n"
        "  tergodic precompute cap/\n\n"
        "  tergodic explore cap/ --robot kinematic --steps 1000 --out run/\n\n"
        "  tergodic replay run/ --plot run/plots"
    ),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,  # help texts use [robot] and [default: ...] literally, not as Rich markup
    context_settings={"help_option_names": ["-h", "--help"]},
)

for _verb in VERBS:
    try:
        _module = importlib.import_module(f"tergodic_cli.commands.{_verb}")
    except ModuleNotFoundError as _exc:  # a verb not built yet
        if _exc.name != f"tergodic_cli.commands.{_verb}":
            raise
        continue
    _module.register(app)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``tergodic`` console script; returns the exit code."""
    try:
        result = app(args=argv, standalone_mode=False)
        return int(result) if isinstance(result, int) else 0
    except TergodicError as exc:
        print(f"tergodic: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except OSError as exc:  # the operating system's refusals not caught nearer: still one line, no traceback
        from tergodic_cli.errors import os_cause

        where = f" {exc.filename}" if exc.filename else ""
        print(f"tergodic: error: cannot complete:{where} {os_cause(exc)}; check the paths and free space", file=sys.stderr)
        return 2
    except (typer.Abort, KeyboardInterrupt):
        print("tergodic: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        # Usage errors and --help/Exit from typer's (vendored) click carry their own exit code.
        if hasattr(exc, "exit_code"):
            if hasattr(exc, "show"):
                exc.show()
            return int(exc.exit_code)
        raise


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
