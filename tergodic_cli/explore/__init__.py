"""Exploration: paper-faithful HEDAC on point clouds (section IV-A) and its metrics.

The pure core: it imports nothing from the robot, hardware, log or sweep stages and runs
without a simulator. Entry points: :class:`ExploreConfig`, :class:`Explorer` (one object per run;
``step()`` per explorer step), :func:`metrics.coverage_score` (the neutral score of a trajectory),
:func:`summarize_run` (summary.json from the per-step series, pure). A whole ``tergodic explore``
run (capture, basis, starts, a backend, the log) is :func:`tergodic_cli.run.run_explore`.
"""

from tergodic_cli.explore.config import ExploreConfig, parse_alpha, validate_config


def __getattr__(name):  # the explorer pulls in numba: load it on first use (the CLI reads the config at start-up)
    if name == "Explorer":
        from tergodic_cli.explore.explorer import Explorer

        return Explorer
    if name == "summarize_run":
        from tergodic_cli.explore.summary import summarize_run

        return summarize_run
    raise AttributeError(name)


__all__ = ["ExploreConfig", "Explorer", "parse_alpha", "summarize_run", "validate_config"]
