"""Run logs: every explorer step into one self-describing MCAP file, and back.

Write with :class:`RunLog` (Foxglove protobuf schemas for viewers, exact float64
records for replay); read with :func:`read_run_log`, which also recovers a log cut
short by a crash. ``tergodic replay`` builds on both. The MCAP and Foxglove libraries
load on first use, so ``--no-log`` runs never import them.
"""

from tergodic_cli.runlog.reader import CloudFrame, RunLogData, read_run_log, resolve_log_path
from tergodic_cli.runlog.schema import LOG_SCHEMA_VERSION
from tergodic_cli.runlog.writer import RunLog

__all__ = ["CloudFrame", "LOG_SCHEMA_VERSION", "RunLog", "RunLogData", "read_run_log", "resolve_log_path"]
