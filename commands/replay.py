"""``tergodic replay``: numbers and pictures from a run's MCAP log alone."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer


def replay(
    run: Path = typer.Argument(..., help="Run folder written by 'tergodic explore' (holding run.mcap), or the .mcap file."),
    json_out: bool = typer.Option(False, "--json", help="Print the summary as JSON: the keys of summary.json plus 'truncated' and 'status' (complete, interrupted, truncated)."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Write PNG figures into this folder (ε(t), touched(t), force(t), cloud views)."),
    export: Optional[str] = typer.Option(None, "--export", help="Export the time series (npz or csv), or the run as a ROS 2 bag folder (rosbag2: tf, agents, cloud, wrench, joint states)."),
    export_out: Optional[Path] = typer.Option(None, "--export-out", help="Where --export writes (default: series.npz, series.csv or the folder rosbag2 beside run.mcap)."),
    step: Optional[int] = typer.Option(None, "--step", help="Print the state at explorer step N instead of the summary."),
    gui: bool = typer.Option(False, "--gui", help="Replay the logged joint states in the PyBullet GUI (robot runs; needs a display, else exit 2)."),
    speed: float = typer.Option(1.0, "--speed", help="--gui playback speed, times real time."),
    rerun: Optional[Path] = typer.Option(None, "--rerun", help="Write a Rerun recording (.rrd); needs rerun-sdk."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --plot folder, --export, --rerun or --html file (whole, once the new one is complete)."),
    html: Optional[Path] = typer.Option(None, "--html", help="Write an interactive HTML report (cloud with a time slider, trajectory, ε, touched, force); works offline."),
) -> None:
    """Recompute a run's summary from its log, and plot, export or re-drive it.

    The summary is recomputed from the logged series alone and equals summary.json;
    a log cut short by a crash is read up to its last complete chunk and reported
    as truncated; a run stopped by Ctrl-C or SIGTERM is reported as interrupted; a log
    damaged inside (bad CRC, garbage) or with bytes appended after its end is refused
    as corrupt, naming the byte offset.

    Examples:

      tergodic replay run/

      tergodic replay run/run.mcap --json

      tergodic replay run/ --plot run/plots --export csv

      tergodic replay run/ --export rosbag2 --export-out run/rosbag2   (then: ros2 bag play run/rosbag2)

      tergodic replay run/ --step 500

      tergodic replay run/ --html run/report.html
    """
    from tergodic_cli.errors import TergodicError, require
    from tergodic_cli.runlog import resolve_log_path

    require(export in (None, "npz", "csv", "rosbag2"), f"--export '{export}' is not a format",
            "use --export npz, --export csv or --export rosbag2")
    require(rerun is None or rerun.suffix == ".rrd", f"--rerun {rerun} does not end in .rrd", "e.g. --rerun run.rrd")
    if speed <= 0:
        raise TergodicError(f"--speed must be > 0, got {speed}", "e.g. --speed 2")
    from tergodic_cli.atomic import AtomicFolder, check_output_file
    from tergodic_cli.runlog.viewers import require_display, require_rerun

    # every output is checked before the (long) read, and built aside then renamed in; none may be the log itself
    path = resolve_log_path(run)
    if rerun is not None:
        require_rerun()
        check_output_file(rerun, overwrite, "--rerun", inputs=(path,))
    if gui:
        require_display()
    if html is not None:
        check_output_file(html, overwrite, "--html", inputs=(path,))
    dest = None
    bag = None
    if export == "rosbag2":
        from tergodic_cli.runlog.rosbag import require_rosbags

        require_rosbags()
        dest = export_out or path.parent / "rosbag2"
        require(dest.resolve() != path.parent.resolve(), f"--export-out {dest} is the run folder itself",
                "give a new folder for the bag, e.g. --export-out run/rosbag2")
        bag = AtomicFolder(dest, overwrite=overwrite, option="--export-out", what="ROS 2 bag",
                           owned=lambda name: name == "metadata.yaml" or name.endswith((".db3", ".mcap")))
    elif export is not None:
        dest = export_out or path.parent / f"series.{export}"
        check_output_file(dest, overwrite, "--export-out", inputs=(path,))
    plots = AtomicFolder(plot, overwrite=overwrite, option="--plot", what="set of plots",
                         owned=lambda name: name.endswith(".png")) if plot is not None else None
    try:
        for folder in (plots, bag):
            if folder is not None:
                folder.check()
        _replay(path, plots, plot, dest, export, rerun, html, step, gui, speed, json_out, bag)
    finally:
        for folder in (plots, bag):
            if folder is not None:
                folder.release()


def _replay(path, plots, plot, dest, export, rerun, html, step, gui, speed, json_out, bag=None) -> None:
    """The read and every output, once the outputs are checked (``plots`` locked)."""
    from tergodic_cli.progress import Spinner, echo as echo_err
    from tergodic_cli.runlog import read_run_log
    from tergodic_cli.runlog.export import export_series
    from tergodic_cli.runlog.plots import plot_run
    from tergodic_cli.runlog.report import write_html_report
    from tergodic_cli.runlog.summary import (compare_with_file, format_state, format_table, recompute_summary,
                                             state_at, to_json)
    from tergodic_cli.runlog.viewers import replay_gui, write_rerun

    need_clouds = plot is not None or rerun is not None or step is not None or gui or html is not None or bag is not None
    with Spinner(f"reading {path.name}"):
        data = read_run_log(path, clouds=need_clouds)
    # "wrote ..." notes go to stderr when stdout carries JSON
    say = echo_err if json_out else typer.echo
    if data.truncated:
        typer.echo(f"tergodic: warning: {path} is truncated (the run was cut short); "
                   f"read {data.steps} steps up to the last complete chunk", err=True)
    elif data.status == "interrupted":
        typer.echo(f"tergodic: warning: {path} is from an interrupted run (Ctrl-C or SIGTERM); "
                   f"it holds the {data.steps} steps before it", err=True)

    if step is not None:
        state = state_at(data, step)
        typer.echo(to_json(state) if json_out else format_state(state))
    else:
        summary = recompute_summary(data)
        if json_out:
            typer.echo(to_json({**summary, "truncated": data.truncated, "status": data.status}))
        else:
            typer.echo(format_table(summary, data, compare_with_file(summary, path.parent / "summary.json")))

    if bag is not None:
        from tergodic_cli.runlog.rosbag import write_rosbag2_aside

        with bag as tmp:
            write_rosbag2_aside(data, dest, tmp)
        say(f"wrote {dest} (ROS 2 bag: {data.steps} steps, {len(data.clouds)} clouds; ros2 bag play {dest})")
    elif export is not None:
        export_series(data, export, dest)
        say(f"wrote {dest} ({data.steps} rows)")
    if plot is not None:
        with plots as tmp:
            written = plot_run(data, tmp)
        for p in written:
            say(f"wrote {plot / p.name}")
    if rerun is not None:
        say(f"wrote {write_rerun(data, rerun)}")
    if html is not None:
        say(f"wrote {write_html_report(data, html)}")
    if gui:
        replay_gui(data, speed=speed)
    sys.stdout.flush()
