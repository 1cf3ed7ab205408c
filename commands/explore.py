"""``tergodic explore``: HEDAC exploration of a capture (kinematic agent, or the PyBullet robot)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Optional

import typer


def explore(
    ctx: typer.Context,
    capture: Path = typer.Argument(..., help="Capture folder written by 'tergodic capture'."),
    out: Path = typer.Option(..., "--out", "-o", help="Run folder: trajectory.npz, summary.json, run.mcap."),
    robot: str = typer.Option("kinematic", "--robot", help="'kinematic' (virtual agent only), 'pybullet' (a simulated arm, --arm, 1 kHz torque control) or 'franka' (real arm through franky, streamed impedance) or 'franka-torque' (real arm through pylibfranka: the simulation's line impedance and wrench PID in a 1 kHz torque loop; needs --ft bota|netft) or 'ur' (a UR e-Series through ur_rtde: the same wrench in its force mode)."),
    steps: int = typer.Option(1000, "--steps", help="Explorer steps (one step = --dt seconds)."),
    alpha: str = typer.Option("10", "--alpha", help="α of δt = α h₀² (eq. 21, h₀ = 2.5 mm fixed), or a schedule A0:A1@S1, e.g. 50:10@200 (50 for 200 steps, then 10)."),
    nk: int = typer.Option(200, "--nk", help="Eigenpairs used by the spectral diffusion (a larger cached basis is truncated)."),
    agent_radius: float = typer.Option(0.0075, "--agent-radius", help="Footprint radius r_a in METRES (paper: 0.0075 bunny/cup, 0.015 plate)."),
    start: Optional[str] = typer.Option(None, "--start", help="Start: x,y,z in metres, a point index, or 'random' [default: random]."),
    starts: Optional[Path] = typer.Option(None, "--starts", help="Start positions (n, 3) metres: .npz with key x0_arr (the reference starts), x0 or starts; .npy; or .csv rows x,y,z."),
    start_index: Optional[int] = typer.Option(None, "--start-index", help="Row of --starts to use [default: 0]."),
    seed: int = typer.Option(0, "--seed", help="Seed for random starts."),
    agents: int = typer.Option(1, "--agents", help="Agents sharing one coverage field (eq. 3)."),
    diffusion: str = typer.Option("carry", "--diffusion", help="'carry': u <- e^{-δtL}u + s (default, measured best); 'source': eq. 19 on the current source only."),
    integrator: str = typer.Option("resolvent", "--integrator", help="'resolvent' (eq. 4 in the eigenbasis, 1/(1+λδt); default, measured most robust), 'spectral' (eq. 19, e^{-λδt}) or 'implicit' (sparse (M + δt L)^-1 M, the exact baseline)."),
    coverage_norm: str = typer.Option("cloud", "--coverage-norm", help="What the source's coverage is normalised over: 'cloud' (default: the whole cloud, eq. 2 as printed) or 'target' (the marked points only; tuned in wave 1 to the touched share, which the neutral ε does not reward: docs/explore.md)."),
    sheets: str = typer.Option("mixed", "--sheets", help="Sheets of a wall's two sides: 'mixed' (the fit, gradient, footprint and gain use all n_N nearest / 3-D balls, the paper's; default) or 'separate' (only the agent's own sheet: never inside a wall whose two sides are sampled, and nothing deposited or sought through it; within 1.5 mm of the mesh on 97 % of steps against 70 %, but a median ε 1.3x the mixed one on household meshes: docs/explore.md)."),
    v_max: float = typer.Option(0.003, "--v-max", help="Speed limit, m/s (paper: 0.003)."),
    a_max: float = typer.Option(0.003, "--a-max", help="Acceleration limit, m/s² (paper: 0.003)."),
    dt: float = typer.Option(1.0, "--dt", help="Seconds per explorer step (paper: 1)."),
    fit_neighbors: int = typer.Option(20, "--fit-neighbors", help="n_N: neighbours of the tangent-plane and gradient fits (paper Table II: 20)."),
    epsilon: Optional[float] = typer.Option(None, "--epsilon", help="Footprint φ = exp(-ε² r²), ε in 1/m [default: 2/agent-radius: 98% of the Gaussian inside r_a]."),
    neighbors: int = typer.Option(30, "--neighbors", help="Neighbours of the robust Laplacian (must match 'tergodic precompute'; the authors used 40)."),
    cache_dir: Optional[Path] = typer.Option(None, "--cache-dir", help="Basis cache root [default: $TERGODIC_CACHE_DIR or ~/.cache/tergodic]."),
    no_log: bool = typer.Option(False, "--no-log", help="Do not write the per-step MCAP log (for timing)."),
    live: Optional[str] = typer.Option(None, "--live", metavar="[HOST:PORT]", help="Stream the log's channels to Foxglove over WebSocket while the run goes on (Open connection: ws://HOST:PORT); --live alone: 127.0.0.1:8765."),
    live_wait: bool = typer.Option(False, "--live-wait", help="With --live (implied, at 127.0.0.1:8765 unless given): start only once a viewer has connected, and keep serving the final state until Ctrl-C."),
    log_cloud_every: int = typer.Option(50, "--log-cloud-every", help="Log coverage/heat/source per point every N steps (and at the end)."),
    max_start_distance: float = typer.Option(0.02, "--max-start-distance", help="Refuse a start farther than this (metres) from the cloud; closer ones are projected."),
    config: Optional[Path] = typer.Option(None, "--config", help="Repeat a run: its RUN/config.json (explore config, start, seed, robot); options given beside it override it."),
    json_out: bool = typer.Option(False, "--json", help="Print summary.json to stdout."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing run folder at --out (whole, once the new run is complete; a run stopped by Ctrl-C, SIGTERM or a robot fault goes beside it, as RUN.interrupted-TIME or RUN.partial-TIME)."),
    force: Optional[float] = typer.Option(None, "--force", help="[robot] Desired contact force along the tool axis, N [default: 5]."),
    force_limit: Optional[float] = typer.Option(None, "--force-limit", help="[robot] Contact force, low-passed at 10 Hz, that makes the robot retreat and stop, N [default: 3 x --force, at least --force + 5]; one tick over 5 x --force (at least 30 N) is an impact and stops at once."),
    contact_force: Optional[float] = typer.Option(None, "--contact-force", help="[robot] Force that counts as touching (coverage is deposited above it), N [default: 20% of --force]."),
    object_pose: Optional[str] = typer.Option(None, "--object-pose", help="[robot] Capture frame in the robot base frame: x,y,z[,roll,pitch,yaw] (m, deg) or x,y,z,qx,qy,qz,qw [default: the identity for a capture taken in the base frame (--source sim, or a calibrated --camera-pose); otherwise, pybullet only, the cloud's footprint centre 0.5 m in front of the base with its lowest point on a 0.2 m stand, turned 0, 90, -90 or 180 deg about the vertical, then the same at 0.4 m: the first pose where the arm reaches the whole target, else the one reaching most of it (the pose is printed and saved in summary.json); franka refuses to guess]."),
    workspace: Optional[str] = typer.Option(None, "--workspace", help="[robot] Workspace box xmin,ymin,zmin,xmax,ymax,zmax in the base frame, m."),
    explore_dt: Optional[float] = typer.Option(None, "--explore-dt", help="[robot] Simulated seconds per explorer step [default: 0.2; agent limits are rescaled so a step moves the same path]."),
    normal_side: Optional[str] = typer.Option(None, "--normal-side", help="[robot] Side of the sheet the tool works on: auto (= outward: consistent over the sheet, facing the side the cloud is seen from), outward, up or out."),
    gains: Optional[str] = typer.Option(None, "--gains", help="[pybullet] Controller gains: tuned (default) or paper (the paper's K, D and wrench PID on the full wrench, V-A3)."),
    arm: Optional[str] = typer.Option(None, "--arm", help="[pybullet] The simulated arm: panda, xarm6 (UFactory xArm 6, 6 DoF) or iiwa (KUKA LBR iiwa) [default: panda]."),
    gui: bool = typer.Option(False, "--gui", help="[pybullet] Open the PyBullet GUI (needs a display)."),
    realtime: bool = typer.Option(False, "--realtime", help="[pybullet] Pace the simulation to wall-clock time (with --gui)."),
    robot_ip: Optional[str] = typer.Option(None, "--robot-ip", help="[franka, franka-torque, ur] IP address of the robot controller."),
    ft: Optional[str] = typer.Option(None, "--ft", help="[franka] Force source: franka (the arm's own estimate, default with --robot franka), ur (the UR's own, default with --robot ur), bota or netft (franka-torque needs one of these two)."),
    ft_address: Optional[str] = typer.Option(None, "--ft-address", help="[franka] Bota config JSON or Net F/T address."),
    dry_run: bool = typer.Option(False, "--dry-run", help="[franka] Connect read-only (no real-time kernel needed), read the sensors and print the plan without moving."),
    recapture_every: Optional[int] = typer.Option(None, "--recapture-every", help="[pybullet, sim capture] Closed loop: re-capture with the camera every K explorer steps and update the target (basis reused)."),
    until_clean: float = typer.Option(0.05, "--until-clean", help="[closed loop] Stop when the camera sees less than this share of the initial marking."),
    max_steps: Optional[int] = typer.Option(None, "--max-steps", help="[closed loop] Step budget [default: --steps]."),
) -> None:
    """Explore a capture with the paper's HEDAC agent and write the run.

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
    if live_wait and live is None:
        from tergodic_cli.runlog.live import DEFAULT as live
    live_at = _check_live(live, no_log or dry_run) if live is not None else None  # exit 2 before anything is written
    from tergodic_cli.explore import ExploreConfig
    from tergodic_cli.run import (RENAMED, LogSpec, StartSpec, apply_saved, dry_run_report, make_backend, placed_line,
                                  run_explore, went_beside)
    from tergodic_cli.commands._common import given_options, parse_floats
    from tergodic_cli.progress import echo as echo_err

    # the options that set ExploreConfig fields, renamed as for --config's override (run.RENAMED)
    fields = {f: v for opt, v in ctx.params.items() for f in RENAMED.get(opt, (opt,))
              if f in ExploreConfig.__dataclass_fields__}
    box = parse_floats(workspace, 6, "--workspace", "0.15,-0.6,0,0.85,0.6,0.9")  # None: not given
    spec = StartSpec(start=start, starts_file=str(starts) if starts is not None else None, start_index=start_index)
    robot_options = {
        "force": force, "contact_force": contact_force, "explore_dt": explore_dt, "normal_side": normal_side,
        "gains": gains, "gui": gui or None, "realtime": realtime or None, "arm": arm,
        "object_pose": parse_floats(object_pose, None, "--object-pose", "0.5,0,0.2") if object_pose else None,
        "safety": {"force_limit": force_limit,
                   **({"workspace_min": box[:3], "workspace_max": box[3:]} if box else {})},
    }
    if config is not None:  # the saved run, with the options given on this command line on top
        cfg, spec, robot, robot_options, log_cloud_every = apply_saved(
            config, fields, given_options(ctx), spec, robot, robot_options, log_cloud_every)
    else:
        cfg = ExploreConfig(**fields)
    backend = make_backend(robot, robot_options, {"robot_ip": robot_ip, "ft": ft, "ft_address": ft_address},
                           recapture_every, until_clean, max_steps, dry_run)
    if dry_run:
        typer.echo(dry_run_report(capture, cfg, backend, spec))
        return
    placed: dict = {}
    summary = run_explore(capture, cfg, out, backend, spec, None if no_log else LogSpec(log_cloud_every, live_at, live_wait),
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
