"""The ``tergodic`` command line: one thin module per verb in ``tergodic_cli.commands``.

Every verb module imports only typer and the standard library at import time, so
``tergodic --help`` stays fast; heavy libraries load inside the verb that needs them.
"""

from __future__ import annotations

import os
import platform
import signal
import sys

import typer

from tergodic_cli import native
from tergodic_cli.errors import Terminated, TergodicError, os_cause
from tergodic_cli.progress import echo


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

#: The libraries whose versions ``--version`` prints (an alias distribution is named: open3d-cpu).
LIBRARIES = ("numpy", "scipy", "open3d", "robust_laplacian", "pybullet", "numba", "mcap")


def version_text() -> str:
    """``tergodic --version``: this package's version, then the key libraries' (from their metadata, no imports)."""
    from tergodic_cli import __version__
    from tergodic_cli.provenance import installed

    lines = [f"tergodic {__version__} (Python {platform.python_version()}, {platform.system()} {platform.machine()})"]
    for name in LIBRARIES:
        found = installed(name)
        text = "not installed" if found is None else found[0] + (f" ({found[1]})" if found[1] != name else "")
        lines.append(f"  {name} {text}")
    return "\n".join(lines)


def _print_version(value: bool) -> None:
    if value:
        typer.echo(version_text())
        raise typer.Exit(0)


@app.callback()
def _root(version: bool = typer.Option(False, "--version", "-V", callback=_print_version, is_eager=True,
                                       help="Print the version of tergodic and of its key libraries, and exit.")) -> None:
    pass


class _Command(typer.core.TyperCommand):
    """Usage lines in the usual form, ``tergodic sweep [OPTIONS] GRID``; typer writes ``{grid}``."""

    def collect_usage_pieces(self, ctx) -> list[str]:
        pieces = super().collect_usage_pieces(ctx)
        return [piece.replace("{", "").replace("}", "").upper() for piece in pieces]

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt as exc:  # typer would turn it into a silent exit 130
            raise typer.Exit(_interrupted(exc)) from None


from tergodic_cli.commands import capture, explore, precompute, replay, sweep  # noqa: E402  (after app)
from tergodic_cli.commands._common import exit_codes  # noqa: E402

for _verb in (capture.capture, precompute.precompute, explore.explore, replay.replay, sweep.sweep):
    # every verb lists its exit codes under --help; only the robot's verbs can end on a fault (3)
    _epilog = exit_codes(robot=_verb not in (capture.capture, precompute.precompute))
    app.command(_verb.__name__, no_args_is_help=True, epilog=_epilog, cls=_Command)(_verb)


def _on_sigterm(signum, frame) -> None:
    Terminated.received = True
    raise Terminated()


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``tergodic`` console script; returns the exit code (130 on Ctrl-C, 143 on SIGTERM)."""
    code = _main(argv)
    if argv is None and code in (130, 143) and native.may_exit_now():
        # the console script, interrupted: every artefact is closed or set aside by now (the one line said
        # where), and the interpreter's teardown with open3d, PyBullet and numba loaded takes ~1 s more
        # (and waits on a native worker an interrupt left computing: tergodic_cli.native)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


def _main(argv: list[str] | None) -> int:
    try:
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    except ValueError:  # not the main thread (an embedding caller): leave SIGTERM alone
        previous = None
    argv = explore.expand_live(sys.argv[1:] if argv is None else argv)  # --live [HOST:PORT]: an optional value
    try:
        result = app(args=argv, prog_name="tergodic", standalone_mode=False)
        return int(result) if isinstance(result, int) else 0
    except TergodicError as exc:
        print(f"tergodic: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except OSError as exc:  # the operating system's refusals not caught nearer: still one line, no traceback
        where = f" {exc.filename}" if exc.filename else ""
        print(f"tergodic: error: cannot complete:{where} {os_cause(exc)}; check the paths and free space", file=sys.stderr)
        return 2
    except (typer.Abort, KeyboardInterrupt) as exc:
        return _interrupted(exc)
    except Exception as exc:
        # Usage errors and --help/Exit from typer's (vendored) click carry their own exit code.
        if hasattr(exc, "exit_code"):
            fmt = getattr(exc, "format_message", None)
            if fmt is not None and int(exc.exit_code) == 2 and type(exc).__name__ != "NoArgsIsHelpError":
                ctx = getattr(exc, "ctx", None)  # a usage error: one line, like every other bad input
                where = ctx.command_path if ctx is not None else "tergodic"
                print(f"tergodic: error: {' '.join(fmt().split()).rstrip('.')}; see '{where} --help'", file=sys.stderr)
            elif hasattr(exc, "show"):
                exc.show()
            return int(exc.exit_code)
        raise
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _interrupted(exc: BaseException) -> int:
    """Ctrl-C or SIGTERM: one line (a verb's own, e.g. how to resume), no traceback; the exit code."""
    code = getattr(exc, "exit_code", 130)
    echo(f"tergodic: {getattr(exc, 'message', None) or ('terminated' if code == 143 else 'interrupted')}")
    return code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
