"""Run logs: every explorer step into one self-describing MCAP file, and back.

Write with :class:`RunLog` (Foxglove protobuf schemas for viewers, exact float64
records for replay); read with :func:`read_run_log`, which also recovers a log cut
short by a crash. ``tergodic replay`` builds on both. Names load on first use, so
``--no-log`` runs never import the logging stack.
"""

from tergodic_cli.runlog.schema import LOG_SCHEMA_VERSION

_LAZY = {"RunLog": "writer", "CloudFrame": "reader", "RunLogData": "reader", "read_run_log": "reader",
         "resolve_log_path": "reader"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"tergodic_cli.runlog.{_LAZY[name]}"), name)
    raise AttributeError(name)


__all__ = ["CloudFrame", "LOG_SCHEMA_VERSION", "RunLog", "RunLogData", "read_run_log", "resolve_log_path"]
