"""Exploration: paper-faithful HEDAC on point clouds (section IV-A) and its metrics.

Entry points: :class:`ExploreConfig`, :class:`Explorer` (one object per run; ``step()`` per
explorer step), :func:`summarize_run` (summary.json from the per-step series, pure), and
:func:`run_explore` (the whole ``tergodic explore`` run: basis, starts, loop, artefacts).
"""

from tergodic_cli.explore.config import ExploreConfig, parse_alpha, validate_config
from tergodic_cli.explore.explorer import Explorer
from tergodic_cli.explore.summary import summarize_run

__all__ = ["ExploreConfig", "Explorer", "parse_alpha", "summarize_run", "validate_config"]


def __getattr__(name):  # run_explore pulls in the capture/basis stack; load it on first use
    if name in ("run_explore", "resolve_starts", "find_basis"):
        from tergodic_cli.explore import run

        return getattr(run, name)
    raise AttributeError(name)
