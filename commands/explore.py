"""``tergodic explore``: HEDAC exploration of a capture (kinematic agent, or the PyBullet robot)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Optional

import typer

from tergodic_cli.commands._options import with_options
from tergodic_cli.explore.config import ExploreConfig
from tergodic_cli.robot.config import RobotConfig, SafetyConfig
from tergodic_cli.runspec import ClosedLoopSpec, HardwareSpec, LogSpec, StartSpec


@with_options(ExploreConfig, StartSpec, LogSpec, RobotConfig, SafetyConfig, ClosedLoopSpec, HardwareSpec)
def explore(
    ctx: typer.Context,
    capture: Path = typer.Argument(..., help="Capture folder written by 'tergodic capture'."),
    out: Path = typer.Option(..., "--out", "-o", help="Run folder: trajectory.npz, summary.json, run.mcap."),
    robot: str = typer.Option("kinematic", "--robot", help="'kinematic' (virtual agent only), 'pybullet' (a simulated arm, --arm, 1 kHz torque control), 'franka' (real arm through franky, streamed impedance), 'franka-torque' (real arm through pylibfranka: the simulation's line impedance and wrench PID in a 1 kHz torque loop; needs --ft bota|netft) or 'ur' (a UR e-Series through ur_rtde: the same wrench in its force mode)."),
    cache_dir: Optional[Path] = typer.Option(None, "--cache-dir", help="Basis cache root [default: $TERGODIC_CACHE_DIR or ~/.cache/tergodic]."),
    no_log: bool = typer.Option(False, "--no-log", help="Do not write the per-step MCAP log (for timing)."),
    config: Optional[Path] = typer.Option(None, "--config", help="Repeat a run: its RUN/config.json (explore config, start, seed, robot, closed loop, robot connection); options given beside it override it."),
    json_out: bool = typer.Option(False, "--json", help="Print summary.json to stdout."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing run folder at --out (whole, once the new run is complete; a run stopped by Ctrl-C, SIGTERM or a robot fault goes beside it, as RUN.interrupted-TIME or RUN.partial-TIME)."),
    **opts,
) -> None:
    """Explore a capture with the paper's HEDAC agent and write the run.

    Its options come from the configs they set (explore, starts, log, robot, safety, closed loop,
    robot connection), and a run's config.json holds all of them: --config repeats any run.

    The basis is looked up in the cache (any cached basis with >= nK eigenpairs and the same
    --neighbors) or computed, so this works straight from a fresh capture.

    With --robot pybullet the sponge presses on a contact surface: a --source sim capture's own
    object, else the mesh the capture was sampled from when it holds one, else a surface rebuilt
    from the cloud (screened Poisson cropped to within 2 point spacings of the cloud; ball
    pivoting when the cloud is an open sheet, which Poisson would close), decimated to the
    coarsest triangles whose 95th-percentile angle between neighbours is at most 12 deg where the
    object is smooth (a Poisson surface decimated to twice that, split once by Loop subdivision
    and, where that still folds more, Taubin-smoothed with each vertex kept within a quarter point
    spacing of the Poisson surface; ball pivoting instead when Poisson folds a thin object's rims).
    The outward normals it is built from face the side rays from each point escape to. It is
    checked before any motion (it must cover the cloud, and a rebuilt one must stay near it and
    not fold where the cloud does not) and its figures are written to summary.json under
    contact_surface.

    Examples:

      tergodic explore data/bowl --robot kinematic --steps 1000 --out run/

      tergodic explore data/bowl --starts starts.csv --start-index 0 --out run/   (starts.csv: rows x,y,z in metres)

      tergodic explore data/bowl --alpha 50:10@200 --agents 3 --seed 1 --no-log --json --out run/

      tergodic explore data/bowl --config run/config.json --steps 2000 --out run2/

      tergodic explore data/bowl --robot pybullet --force 5 --steps 300 --out run/

      tergodic explore data/bowl --live-wait --out run/   (then in Foxglove: Open connection ws://127.0.0.1:8765)

      tergodic explore simcap/ --robot pybullet --recapture-every 200 --until-clean 0.05 --max-steps 1000 --out run/

      tergodic explore cap/ --robot franka --robot-ip 172.16.0.2 --ft bota --ft-address bota.json --dry-run --out run/
    """
    from tergodic_cli.commands._common import given_options
    from tergodic_cli.commands._options import values
    from tergodic_cli.progress import echo as echo_err
    from tergodic_cli.run import apply_saved, dry_run_report, make_backend, placed_line, run_explore, save_dry_run, went_beside

    given = given_options(ctx)
    log = LogSpec(**values(LogSpec, opts))
    if log.live_wait and log.live is None:
        from tergodic_cli.runlog.live import DEFAULT

        log.live = DEFAULT
    hardware = HardwareSpec(**values(HardwareSpec, opts))
    live_at = _check_live(log.live, no_log or hardware.dry_run) if log.live is not None else None  # exit 2 before anything is written
    fields = values(ExploreConfig, opts)
    spec = StartSpec(**values(StartSpec, opts))
    loop = ClosedLoopSpec(**values(ClosedLoopSpec, opts))
    # the robot's options given on this command line (the rest: RobotConfig's defaults, or the saved run's)
    robot_options = {**values(RobotConfig, opts, given), "safety": values(SafetyConfig, opts, given)}
    log_cloud_every = log.cloud_every
    if config is not None:  # the saved run, with the options given on this command line on top
        cfg, spec, robot, robot_options, log_cloud_every, loop, hardware = apply_saved(
            config, fields, given, spec, robot, robot_options, log_cloud_every, loop, hardware)
    else:
        cfg = ExploreConfig(**fields)
    backend = make_backend(robot, robot_options, hardware.connection(), loop.recapture_every, loop.until_clean,
                           loop.max_steps, hardware.dry_run)
    if hardware.dry_run:
        typer.echo(dry_run_report(capture, cfg, backend, spec))
        saved = save_dry_run(out, capture, cfg, backend, spec, log_cloud_every, overwrite)
        typer.echo(f"wrote {saved} (repeat this dry run with --config {saved}; add --no-dry-run to make the run)")
        return
    placed: dict = {}
    summary = run_explore(capture, cfg, out, backend, spec, None if no_log else LogSpec(log_cloud_every, live_at, log.live_wait),
                          cache_dir, on_event=echo_err, overwrite=overwrite, placed=placed)
    where = placed_line(placed.get("dir"), out, "partial run")
    if summary.get("interrupted"):
        from tergodic_cli.errors import Terminated

        echo_err(f"interrupted: the robot was made safe; {where}")
        raise typer.Exit(143 if Terminated.received else 130)
    from tergodic_cli.robot.safety import fault_exit_code

    code = fault_exit_code(summary)  # a robot stopped on a fault, made safe: exit 3 with its reason
    if json_out:
        typer.echo(json.dumps(summary, indent=2))
    if code:
        echo_err(f"robot stopped: {summary.get('stop_reason')}"
                 + (f"; {where}" if went_beside(placed.get("dir"), out) else ""))
        raise typer.Exit(code)
    if json_out:
        return
    typer.echo(f"explored {summary['steps']} steps ({robot}): ε {summary['ergodicity']:.3f} (unit-mass, 0 best), "
               f"touched {100 * summary['touched_fraction']:.1f}%, "
               f"off-surface {100 * (summary.get('off_surface_fraction') or 0.0):.1f}%, "
               f"step max {1e3 * (summary.get('step_max_m') or 0.0):.2f} mm, "
               f"explorer step {summary['step_ms_median']:.3f} ms (median)"
               + (f"; {'clean' if summary.get('clean_reached') else 'not clean'}: the camera sees "
                  f"{100 * summary['marking_remaining']:.1f}% of the marking, true ink left "
                  f"{100 * summary['marking_remaining_true']:.1f}%" if summary.get("marking_remaining") is not None else ""))
    typer.echo(f"wrote {out}/ ({', '.join(summary['files'])})")


_HOST_PORT = re.compile(r"^(\[[0-9A-Fa-f:.]*\]|[^\s/]*):\d+$|^\d+$")


def expand_live(argv: list[str]) -> list[str]:
    """``--live`` takes an optional value (typer has no such option): ``--live`` followed by nothing,
    an option or an existing path (the capture) becomes ``--live=127.0.0.1:8765``; anything else is
    its value (HOST:PORT, checked later)."""
    out = list(argv)
    for i, arg in enumerate(out):
        if arg == "--":
            break
        if arg != "--live":
            continue
        nxt = out[i + 1] if i + 1 < len(out) else None
        if nxt is None or (not _HOST_PORT.match(nxt) and (nxt.startswith("-") or Path(nxt).exists())):
            out[i] = "--live=127.0.0.1:8765"
    return out


def _check_live(live: str, no_log: bool) -> str:
    """--live's HOST:PORT, checked now: a bad address or a port in use stops the run before it writes."""
    from tergodic_cli.errors import require
    from tergodic_cli.runlog.live import check_bindable, parse_live

    host, port = parse_live(live)
    require(not no_log, "--live streams the run log", "drop --no-log / --dry-run, or drop --live")
    check_bindable(host, port)
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
