"""A whole ``tergodic explore`` run: capture -> basis -> starts -> explorer loop -> artefacts.

The artefacts in RUN_DIR (``trajectory.npz``, ``summary.json``, ``config.json``, ``run.mcap``) are
described in docs/explore.md; they are built in a temporary folder and renamed into place.
"""

from __future__ import annotations

import json
from contextlib import nullcontext, suppress
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np

from tergodic_cli.capture.readers import check_npz_size
from tergodic_cli.errors import TergodicError, require
from tergodic_cli.resources import free_disk, free_memory
from tergodic_cli.explore.config import ExploreConfig, parse_alpha, validate_config
from tergodic_cli.explore.explorer import Explorer
from tergodic_cli.explore.summary import summarize_run
from tergodic_cli.config import options_of
from tergodic_cli.runspec import ClosedLoopSpec, HardwareSpec, LogSpec, StartSpec
from tergodic_cli.backends import registry

__all__ = ["ClosedLoopSpec", "HardwareSpec", "LogSpec", "StartSpec", "apply_saved", "make_backend", "run_explore"]

#: The robots a run drives (``--robot``) and the real ones among them: the backend registry's.
ROBOTS = registry.names("robot")
HARDWARE = registry.names("robot", hardware=True)
#: What a run folder may hold: explore's files and replay's default outputs (--overwrite replaces only these).
RUN_FILES = frozenset({"run.mcap", "summary.json", "config.json", "trajectory.npz", "series.npz", "series.csv", "plots",
                       "run.rrd", "report.html"})


#: ``config.json``: what repeats a run (``tergodic explore CAPTURE --config RUN/config.json``).
RUN_CONFIG_KIND = "tergodic.run_config"
#: Its sections (:func:`_run_config`).
RUN_CONFIG_SECTIONS = ("capture", "explore", "starts", "robot", "robot_options", "log_cloud_every", "closed_loop",
                       "hardware")


def _run_config(capture_dir, user_cfg: ExploreConfig, backend, starts: StartSpec | None, log_cloud_every: int,
                dry_run: bool = False) -> dict:
    """The sections of a run's ``config.json``: the config as given (before a robot's time scaling),
    the starts (the seed in ``cfg`` makes a random start the same), the robot's config without the GUI,
    the closed loop (a simulated robot) and the real robot's connection (a hardware run, and whether
    it was a dry run): everything :func:`apply_saved` needs to repeat the run."""
    spec = starts or StartSpec()
    rc = backend.robot_cfg
    loop = getattr(backend, "loop", None)
    hardware = getattr(backend, "hardware", None)
    return {"capture": str(Path(capture_dir).resolve()), "explore": user_cfg.to_dict(),
            "starts": {"start": spec.start, "start_index": spec.start_index,
                       "starts_file": str(Path(spec.starts_file).resolve()) if spec.starts_file else None},
            "robot": backend.name,
            "robot_options": replace(rc, gui=False, realtime=False).to_dict() if rc is not None else {},
            "log_cloud_every": int(log_cloud_every),
            "closed_loop": loop.to_dict() if loop is not None else None,
            "hardware": replace(hardware, dry_run=dry_run).to_dict() if hardware is not None else None}


def save_dry_run(out_dir, capture_dir, cfg: ExploreConfig, backend, starts: StartSpec | None, log_cloud_every: int,
                 overwrite: bool = False) -> Path:
    """Write the ``config.json`` of a hardware dry run into ``out_dir`` (nothing else): ``--config`` repeats the
    dry run, and with ``--no-dry-run`` makes the run it planned.

    Parameters
    ----------
    out_dir : str or Path
        The run folder: created; one that holds files is refused unless ``overwrite``.
    capture_dir, cfg, backend, starts, log_cloud_every
        As for :func:`run_explore`.
    overwrite : bool
        Replace the folder's ``config.json``.

    Returns
    -------
    Path
        The file written.
    """
    from tergodic_cli.config import CONFIG_FILE, write_config

    out = Path(out_dir)
    require(overwrite or not out.exists() or not any(out.iterdir()), f"--out {out} exists and is not empty",
            "choose another --out, or add --overwrite")
    out.mkdir(parents=True, exist_ok=True)
    write_config(out / CONFIG_FILE, RUN_CONFIG_KIND, **_run_config(capture_dir, cfg, backend, starts, log_cloud_every,
                                                                   dry_run=True))
    return out / CONFIG_FILE


#: The ExploreConfig field each ``tergodic explore`` option sets, where they differ (from the fields' options).
RENAMED = {o.name: (f,) for f, o in options_of(ExploreConfig) if o.name != f}


def apply_saved(path, fields: dict, given: set, starts: StartSpec, robot: str, robot_options: dict,
                log_cloud_every: int, loop: ClosedLoopSpec | None = None, hardware: HardwareSpec | None = None) -> tuple:
    """A saved run's ``config.json`` with the options given on the command line on top.

    Parameters
    ----------
    path : str or Path
        ``RUN/config.json``; a missing, corrupt or foreign file, or an unknown key, raises
        :class:`TergodicError` (exit 2).
    fields : dict
        :class:`ExploreConfig` fields from the command line.
    given : set of str
        The verb's option names given on the command line (they win over the saved ones).
    starts, robot, robot_options, log_cloud_every
        The command line's starts, backend name, robot options (None: not given) and cloud interval.
    loop, hardware : ClosedLoopSpec, HardwareSpec, optional
        The command line's closed loop and robot connection (their options in ``given`` win).

    Returns
    -------
    tuple
        (ExploreConfig, StartSpec, robot, robot_options, log_cloud_every, ClosedLoopSpec, HardwareSpec).
    """
    from tergodic_cli.config import from_dict, override, read_config

    d = read_config(path, RUN_CONFIG_KIND, "give the config.json that 'tergodic explore' wrote beside a run",
                    sections=RUN_CONFIG_SECTIONS)
    where, fix = f"--config {path}", "use a config.json written by 'tergodic explore'"
    require(isinstance(d.get("robot_options") or {}, dict), f"{where}: robot_options is not a JSON object", fix)
    require(isinstance(d.get("log_cloud_every", 50), int), f"{where}: log_cloud_every is not an int", fix)
    saved_starts = from_dict(StartSpec, d.get("starts") or {}, f"{where}: starts")
    cfg = override(ExploreConfig.from_dict(d.get("explore"), f"{where}: explore"), ExploreConfig(**fields), given, RENAMED)
    options = dict(d.get("robot_options") or {})
    for key, value in robot_options.items():
        if key == "safety":
            options["safety"] = {**(options.get("safety") or {}), **{k: v for k, v in (value or {}).items() if v is not None}}
        elif value is not None:
            options[key] = value
    # the closed loop and the connection: as saved (a run without them: none), the options given on top
    loop = override(from_dict(ClosedLoopSpec, d.get("closed_loop") or {}, f"{where}: closed_loop"),
                    loop or ClosedLoopSpec(), given)
    hardware = override(from_dict(HardwareSpec, d.get("hardware") or {}, f"{where}: hardware"),
                        hardware or HardwareSpec(), given)
    return (cfg, starts if given & {"start", "starts", "start_index"} else saved_starts,
            robot if "robot" in given else d.get("robot", "kinematic"), options,
            log_cloud_every if "log_cloud_every" in given else d.get("log_cloud_every", 50), loop, hardware)


#: The keys a starts file may hold its (n, 3) start positions under, in order of preference (x0_arr: the
#: paper's reference starts).
STARTS_KEYS = ("x0_arr", "x0", "starts")


def read_starts(path: Path) -> np.ndarray:
    """Start positions (n, 3), metres: an .npz with key x0_arr, x0 or starts, an .npy, or a text
    file (.csv/.txt) of rows x, y, z.

    A one-line :class:`TergodicError` for a missing or unreadable file, no known key, or a shape other
    than (n, 3) with n >= 1.
    """
    fix = ("give an .npz with key x0_arr, x0 or starts (n, 3) in metres, an .npy of shape (n, 3), "
           "or a .csv of rows x,y,z")
    require(path.is_file(), f"--starts {path} does not exist", fix)
    try:
        if path.suffix.lower() in (".csv", ".txt"):
            x0, where = np.atleast_2d(np.loadtxt(path, delimiter="," if path.suffix.lower() == ".csv" else None,
                                                 dtype=np.float64, ndmin=2)), "the rows"
        else:
            if path.suffix.lower() == ".npz":
                check_npz_size(path, f"--starts {path}", fix)
            data = np.load(path, allow_pickle=False)
            if isinstance(data, np.ndarray):  # an .npy
                x0, where = np.asarray(data, dtype=np.float64), "the array"
            else:
                with data:
                    keys = list(data.files)
                    key = next((k for k in STARTS_KEYS if k in keys), None)
                    require(key is not None, f"--starts {path} has no key {', '.join(STARTS_KEYS)} "
                            f"(keys: {', '.join(keys) or 'none'})", fix)
                    x0, where = np.asarray(data[key], dtype=np.float64), f"key {key}"
    except TergodicError:
        raise
    except Exception as exc:
        raise TergodicError(f"--starts {path} is unreadable ({type(exc).__name__})", fix) from None
    require(x0.ndim == 2 and x0.shape[1] == 3 and len(x0) > 0, f"--starts {path}: {where} has shape {x0.shape}, "
            "not (n, 3)", "give start positions as rows x, y, z in metres")
    require(bool(np.isfinite(x0).all()), f"--starts {path}: {where} holds NaN or infinite values",
            "give finite start positions in metres")
    return x0


def resolve_starts(spec: StartSpec, points: np.ndarray, n_agents: int, seed: int) -> np.ndarray:
    """Start positions (n_agents, 3), metres.

    Agent 0 starts where ``spec`` says; further agents take the next rows of the starts file
    (wrapping), or, for other specs, distinct cloud points drawn with ``seed``.
    """
    n = len(points)
    rng = np.random.default_rng(seed)
    if spec.starts_file is not None:
        require(spec.start is None, "--start and --starts are both given", "use one of them")
        path = Path(spec.starts_file)
        x0 = read_starts(path)
        i = 0 if spec.start_index is None else int(spec.start_index)
        require(0 <= i < len(x0), f"--start-index {i} is outside 0..{len(x0) - 1}", f"use 0 <= i < {len(x0)}")
        return x0[(i + np.arange(n_agents)) % len(x0)]
    require(spec.start_index is None, "--start-index needs --starts FILE.npz", "add --starts, or use --start INDEX")
    text = (spec.start or "random").strip()
    if text == "random":
        require(n_agents <= n, f"{n_agents} agents but only {n} points", "use fewer agents")
        return points[rng.choice(n, size=n_agents, replace=False)]
    if "," in text:
        try:
            first = np.array([float(v) for v in text.split(",")])
        except ValueError:
            first = np.zeros(0)
        require(first.shape == (3,) and bool(np.all(np.isfinite(first))), f"--start '{text}' is not x,y,z",
                "e.g. --start 0.01,0.02,0.05 (metres)")
    else:
        try:
            idx = int(text)
        except ValueError:
            raise TergodicError(f"--start '{text}' is not x,y,z, a point index or 'random'",
                                "e.g. --start 0.01,0.02,0.05 (metres), --start 120, or --start random") from None
        require(0 <= idx < n, f"--start index {idx} is outside 0..{n - 1}", f"use an index below {n}")
        first = points[idx]
    return np.vstack([first[None, :], points[rng.choice(n, size=n_agents - 1, replace=False)]])


def find_basis(points: np.ndarray, nk: int, neighbors: int, cache_dir=None,
               on_event: Callable[[str], None] | None = None):
    """The cached basis of ``points`` with at least ``nk`` eigenpairs (truncated to ``nk``), or a
    freshly computed (and cached) one with ``nk``. Returns (basis, cache_hit)."""
    from tergodic_cli.basis import BasisConfig, get_basis
    from tergodic_cli.basis.cache import SOLVERS, default_cache_dir, geometry_key

    root = Path(cache_dir or default_cache_dir()) / "basis"
    candidates: set[tuple[int, str, str]] = set()
    for meta_path in root.glob("*/basis.json"):  # none when the folder is missing
        with suppress(OSError, ValueError, KeyError, TypeError):  # unreadable entries are get_basis' business
            meta = json.loads(meta_path.read_text())
            bcfg = meta["config"]
            if (int(meta["n_points"]) == len(points) and int(bcfg["neighbors"]) == neighbors
                    and int(bcfg["nk"]) >= nk and bcfg.get("solver", BasisConfig.solver) in SOLVERS):
                candidates.add((int(bcfg["nk"]), str(bcfg.get("solver", BasisConfig.solver)),
                                meta_path.parent.name))
    for cand_nk, solver, key in sorted(candidates):
        bcfg = BasisConfig(nk=cand_nk, neighbors=neighbors, solver=solver)
        if geometry_key(points, bcfg)[0] == key:
            basis, hit = get_basis(points, bcfg, cache_dir, on_event=on_event)
            return (basis.truncated(nk) if basis.nk > nk else basis), hit
    return get_basis(points, BasisConfig(nk=nk, neighbors=neighbors), cache_dir, on_event=on_event)


#: Bytes a run holds in memory per explorer step and agent (positions, velocities, normals,
#: accelerations: 4 x 3 float64) and per step (time, ε, residual, touched, step time); a robot run adds
#: its per-step sample. Measured from trajectory.npz and the robot's samples.
STEP_BYTES, AGENT_STEP_BYTES, ROBOT_STEP_BYTES = 40, 96, 4096
#: Log bytes per explorer step (agent poses, scalars, events) and per logged cloud point (position and
#: four float32 fields), measured on the demo run's MCAP before compression.
LOG_STEP_BYTES, LOG_POINT_BYTES = 400, 28
#: Above this many steps, or this many log bytes, a run says up front what it will hold and write.
BIG_STEPS, BIG_LOG = 100_000, 1 << 30


def estimate_run_size(steps: int, n_agents: int, n_points: int, cloud_every: int | None,
                      robot: bool) -> tuple[int, int]:
    """What a run of ``steps`` explorer steps holds in memory and writes to its log, bytes.

    Returns
    -------
    (memory, log) : tuple of int
        The per-step series kept until the run ends, and the MCAP's size (0 without a log).
    """
    memory = steps * (STEP_BYTES + n_agents * AGENT_STEP_BYTES + (ROBOT_STEP_BYTES if robot else 0))
    log = 0 if cloud_every is None else steps * LOG_STEP_BYTES * n_agents + \
        (steps // cloud_every + 2) * n_points * LOG_POINT_BYTES + (steps * ROBOT_STEP_BYTES if robot else 0)
    return memory, log


def _check_run_size(run: "_Run", out_dir: Path) -> None:
    """Refuse a run whose series would not fit in the free memory; say up front what a huge run will
    hold and write (a disk that fills during the run is met by the writer: the old run stays whole)."""
    steps = int(run.cfg.steps)
    memory, log = estimate_run_size(steps, int(run.cfg.n_agents), len(run.capture.points),
                                    None if run.log is None else run.log.cloud_every,
                                    run.backend.robot_cfg is not None)
    gb = lambda b: f"{b / 1e9:.1f} GB" if b >= 1e8 else f"{b / 1e6:.0f} MB"  # noqa: E731
    free_mem = free_memory()
    require(free_mem is None or memory < free_mem, f"--steps {steps} would hold {gb(memory)} of series in memory, "
            f"more than the {gb(free_mem or 0)} free", "use fewer --steps")
    if steps >= BIG_STEPS or log >= BIG_LOG:
        disk = free_disk(out_dir)
        run.say(f"note: {steps} steps hold about {gb(memory)} in memory"
                + (f" and write about {gb(log)} of log" if run.log is not None else "")
                + (f" ({gb(disk)} free on the disk of --out)" if run.log is not None and disk is not None else "")
                + " until the run ends")


def run_explore(capture_dir: str | Path, cfg: ExploreConfig, out_dir: str | Path, backend=None,
                starts: StartSpec | None = None, log: LogSpec | None = LogSpec(), cache_dir=None,
                on_event: Callable[[str], None] | None = None, overwrite: bool = False,
                placed: dict | None = None) -> dict:
    """Run one exploration through ``backend`` and write its artefacts.

    Parameters
    ----------
    capture_dir : str or Path
        The capture to explore.
    cfg : ExploreConfig
        The explore config (a robot backend rescales its time, :meth:`PyBullet.explore_config`).
    out_dir : str or Path
        The run folder: built in a temporary sibling and renamed into place when complete; an
        existing one holding files is refused up front unless ``overwrite`` (then replaced whole).
    backend : Kinematic, PyBullet or Hardware, optional
        What moves (:func:`make_backend`); default :class:`Kinematic`.
    starts : StartSpec, optional
        Where the agents start (default: random, with ``cfg.seed``).
    log : LogSpec or None
        The per-step MCAP log; None: none.
    cache_dir : str or Path, optional
        The basis cache root.
    on_event : callable, optional
        ``on_event(text)`` for each event line.
    overwrite : bool
        Replace an existing run folder (only with a complete run: a run stopped by a robot fault
        or an interrupt goes beside it, ``RUN.partial-TIME`` or ``RUN.interrupted-TIME``).
    placed : dict, optional
        Filled with ``placed["dir"]``: the folder the run went to.

    Returns
    -------
    dict
        The summary (``summary.json``). On Ctrl-C/SIGTERM the partial run (log marked interrupted)
        is renamed into place (beside an earlier run) and :class:`~tergodic_cli.errors.Interrupted` is raised.
    """
    from tergodic_cli.atomic import AtomicFolder
    from tergodic_cli.explore.warm import compile_explorer
    from tergodic_cli.robot.warm import robot_kernels_line

    run = _Run(capture_dir, cfg, backend or Kinematic(), starts, log, on_event or (lambda msg: None))
    require(log is None or log.cloud_every >= 1, f"--log-cloud-every must be >= 1, got {log and log.cloud_every}", "e.g. 50")
    folder = AtomicFolder(Path(out_dir), overwrite=overwrite, what="run", keep_partial=True, owned=RUN_FILES.__contains__)
    check_backend_options(cfg, run.backend)
    folder.check()  # before any work: a refused --out costs nothing and touches nothing; locks --out
    try:
        for left in folder.leftovers():
            run.say(f"note: {left} is left from a run that was killed; 'tergodic replay {left}' reads it, "
                    f"'mv {left} NEWNAME' keeps it, or delete it")
        run.capture, run.start_xyz = load_for_run(capture_dir, cfg, starts)
        run.backend.check(run.capture, run.start_xyz)
        run.cfg = run.backend.explore_config(cfg)
        _check_run_size(run, Path(out_dir))
        run.basis, run.hit = find_basis(run.capture.points, cfg.nk, cfg.basis_neighbors, cache_dir, on_event=run.event)
        require(np.array_equal(run.basis.points, run.capture.points),
                "the basis does not match the capture's points", "recompute it: tergodic precompute CAPTURE --force")
        compile_explorer(run.say)  # numba compiles on first call: here, so no compile lands in a timed step
        if run.backend.robot_cfg is not None and (line := robot_kernels_line()):
            run.say(line)
        run.explorer = Explorer(run.basis, run.capture.target, run.cfg, run.start_xyz, on_event=run.event)
        with folder as tmp:
            summary = _write_run(tmp, run)
            # a run the robot stopped (fault, or an interrupt it absorbed) never replaces a complete one
            folder.partial = "interrupted" if summary.get("interrupted") else "partial" if _faulted(summary) else None
    except KeyboardInterrupt as exc:
        if folder.kept:
            from tergodic_cli.errors import Interrupted

            word = "terminated" if getattr(exc, "exit_code", 130) == 143 else "interrupted"
            raise Interrupted(f"{word}; {placed_line(folder.placed, Path(out_dir), 'partial run')} "
                              f"(its log is marked interrupted)", exc) from None
        raise
    finally:
        folder.release()
    if placed is not None:
        placed["dir"] = folder.placed
    return summary


def placed_line(placed: Path | None, out_dir: Path, what: str = "run") -> str:
    """Where a run went, as words for its message.

    Parameters
    ----------
    placed : Path or None
        The folder the run went to (``run_explore``'s ``placed["dir"]``).
    out_dir : Path
        The ``--out`` given.
    what : str
        What the run is called ("run", "partial run").

    Returns
    -------
    str
        "the partial run is in RUN/", or, when it was put beside an earlier complete run it
        must not replace, "RUN/ still holds the earlier run; this partial run is in RUN.partial-TIME/".
    """
    if not went_beside(placed, out_dir):
        return f"the {what} is in {out_dir}/"
    return f"{out_dir}/ still holds the earlier run; this {what} is in {Path(out_dir).parent / Path(placed).name}/"


def went_beside(placed: Path | None, out_dir) -> bool:
    """Whether the run was put beside ``out_dir`` (an earlier complete run there was kept).

    Parameters
    ----------
    placed : Path or None
        Where the run went.
    out_dir : path-like
        The ``--out`` given.

    Returns
    -------
    bool
    """
    import os

    return placed is not None and Path(placed) != Path(os.path.abspath(out_dir))


def _faulted(summary: dict) -> bool:
    from tergodic_cli.robot.safety import fault_exit_code

    return bool(fault_exit_code(summary))


def dry_run_report(capture_dir: str | Path, cfg: ExploreConfig, backend, starts: StartSpec | None = None) -> str:
    """What a run on the hardware ``backend`` (:class:`Hardware`) would do: the devices are connected
    and read, nothing moves and nothing is written. Returns the report (several lines)."""
    check_backend_options(cfg, backend)
    capture, start_xyz = load_for_run(capture_dir, cfg, starts)
    backend.check(capture, start_xyz)
    return backend.dry_run(capture, start_xyz[0])


def check_backend_options(cfg: ExploreConfig, backend) -> None:
    """Refuse explore options the backend cannot honour: one arm follows one agent.

    Parameters
    ----------
    cfg : ExploreConfig
    backend : Kinematic, PyBullet or Hardware
    """
    require(backend.robot_cfg is None or cfg.n_agents == 1,
            f"--agents {cfg.n_agents} with --robot {backend.name}: the arm follows one agent",
            "drop --agents (or --agents 1), or use --robot kinematic for several agents")


def load_for_run(capture_dir, cfg: ExploreConfig, starts: StartSpec | None):
    """The checked capture and the start positions (n_agents, 3) m of a run."""
    from tergodic_cli.capture import load_capture

    validate_config(cfg)
    capture = load_capture(capture_dir)
    require(bool(np.any(capture.target > 0)), f"the target of {capture_dir} is empty (no point has p > 0)",
            "re-capture with the right --target colour, or --target all for uniform coverage")
    require(cfg.nk < capture.n_points, f"--nk {cfg.nk} is not below the number of points ({capture.n_points})",
            f"use --nk < {capture.n_points}")
    return capture, resolve_starts(starts or StartSpec(), capture.points, cfg.n_agents, cfg.seed)


class _Run:
    """What one run carries from its set-up to its artefacts."""

    def __init__(self, capture_dir, cfg, backend, starts, log, say):
        self.capture_dir, self.user_cfg, self.cfg, self.backend, self.starts = capture_dir, cfg, cfg, backend, starts
        self.log, self.say, self.events = log, say, []
        self.capture = self.start_xyz = self.basis = self.hit = self.explorer = None

    def event(self, msg: str) -> None:
        self.events.append(msg)
        self.say(msg)


def _write_run(out: Path, run: _Run) -> dict:
    """The explorer loop and the artefacts, written into ``out`` (the temporary run folder)."""
    cfg, explorer, say, spec = run.cfg, run.explorer, run.say, run.log or LogSpec()
    from tergodic_cli.provenance import library_versions
    from tergodic_cli.runlog import RunLog

    recorder = RunRecorder(explorer)
    runlog = None if run.log is None else RunLog(
        out / "run.mcap", config=cfg.to_dict(), seed=cfg.seed, versions=library_versions(),
        capture_sidecar=run.capture.meta, points=run.basis.points, target=run.capture.target,
        cloud_every=spec.cloud_every, live=spec.live)
    # leaving the block on an error closes the log "interrupted" (Ctrl-C) or "error: ..."
    with runlog if runlog is not None else nullcontext():
        if runlog is not None:
            if runlog.live is not None:
                say(f"live: {runlog.live.url} (Foxglove: Open connection)")
                if spec.live_wait:
                    say("live: waiting for a viewer to connect (Ctrl-C stops)")
                    runlog.live.wait_for_viewer()
            for msg in run.events:
                runlog.log_event(0, 0.0, msg)

        def event_hook(step: int, msg: str) -> None:
            say(msg)
            if runlog is not None:
                runlog.log_event(step, step * cfg.dt, msg)

        explorer.on_event = lambda msg: event_hook(explorer.step_index, msg)

        def after_step(step: int, robot_sample: dict | None) -> None:
            metrics = step_metrics(explorer, robot_sample)
            recorder.record(step, metrics)
            if runlog is not None:
                runlog.log_step(step, step * cfg.dt, positions=explorer.positions, velocities=explorer.velocities,
                                normals=explorer.normals, metrics=metrics, step_ms=explorer.last_step_ms,
                                robot=robot_sample)
                if step % spec.cloud_every == 0 or step == cfg.steps:
                    _log_cloud(runlog, explorer, step)

        robot_extra = run.backend.drive(run.capture, explorer, cfg.steps, after_step, event_hook, runlog) or {}
        if recorder.count == 0 and robot_extra.get("final_state") != "stopped":
            from tergodic_cli.errors import RobotStopped

            raise RobotStopped(f"the run made no explorer step (robot stopped: {robot_extra.get('stop_reason') or 'unknown reason'})",
                               "see the robot's events above; adjust --force, --object-pose or --workspace")
        # A robot fault before the first step is written like one after it (its events, summary and
        # log; the command exits 3 with the reason): the run folder says what happened and replays.
        if runlog is not None and recorder.count % spec.cloud_every and recorder.count != cfg.steps:
            _log_cloud(runlog, explorer, recorder.count)  # a robot run that stopped early

        extra = _provenance(run, robot_extra, logged=runlog is not None)
        if cfg is not run.user_cfg:
            extra["requested_config"] = run.user_cfg.to_dict()  # before the robot's time scaling
        summary = summarize_run(recorder.series(), cfg.to_dict(), extra)
        recorder.write(out / "trajectory.npz", run.start_xyz)
        from tergodic_cli.atomic import write_json
        from tergodic_cli.config import CONFIG_FILE, write_config

        write_json(out / "summary.json", summary)
        write_config(out / CONFIG_FILE, RUN_CONFIG_KIND,
                     **_run_config(run.capture_dir, run.user_cfg, run.backend, run.starts, spec.cloud_every))
        if runlog is not None:
            hold = (lambda: runlog.live.hold(say)) if spec.live_wait and runlog.live is not None else None
            runlog.close(summary, status="interrupted" if summary.get("interrupted") else "ok",  # robot made safe
                         hold=hold)
        return summary


def make_robot_config(robot_config_cls, options: dict | None):
    """A RobotConfig from options: its fields (None keeps the default; ``safety``, ``gains`` and
    ``sponge`` as dicts of their fields), from the command line or a saved run."""
    options = {k: v for k, v in (options or {}).items() if v is not None}
    if isinstance(options.get("safety"), dict):
        options["safety"] = {k: v for k, v in options["safety"].items() if v is not None}
    if isinstance(options.get("gains"), str):  # --gains tuned | paper
        from tergodic_cli.robot.controller import gains_preset

        options["gains"] = gains_preset(options["gains"])
    return robot_config_cls.from_dict(options, "robot_options")


# ----------------------------------------------------------------------------- backends
class Kinematic:
    """The virtual agent alone (``--robot kinematic``). Every backend has a ``name``, a ``robot_cfg``
    (None here), ``check(capture, start_xyz)`` (its preconditions, before anything is written),
    ``explore_config(cfg)`` (the explorer config it runs) and ``drive(...)`` (the run)."""

    name = "kinematic"
    robot_cfg = None

    def check(self, capture, start_xyz) -> None:
        pass

    def explore_config(self, cfg: ExploreConfig) -> ExploreConfig:
        return cfg

    def drive(self, capture, explorer, steps: int, on_step, on_event, runlog=None) -> dict:
        """Run ``steps`` explorer steps, calling ``on_step(step, robot_sample or None)`` after each and
        ``on_event(step, text)``; returns the robot's summary extras."""
        from tergodic_cli.progress import track

        for k in track(range(steps), total=steps, description="exploring"):
            explorer.step()
            on_step(k + 1, None)
        return {}


def _robot_log(runlog, explorer):
    """The robot run's ``on_log`` (its state transitions and 1 kHz force windows) into ``runlog``, at
    the explorer's time base like the events; None without a log."""
    if runlog is None:
        return None
    dt = float(explorer.cfg.dt)
    return lambda kind, step, record: runlog.log_robot_record(kind, step, step * dt, record)


class PyBullet(Kinematic):
    """The simulated arm (``--robot pybullet``, ``--arm``) with ``robot_cfg`` (a RobotConfig); with
    ``recapture_every`` the closed loop (a ``--source sim`` capture): re-capture every K steps and stop
    once the camera sees less than ``until_clean`` of the marking or ``max_steps`` (default: the run's) are spent."""

    name = "pybullet"

    def __init__(self, robot_cfg, recapture_every: int | None = None, until_clean: float = 0.05,
                 max_steps: int | None = None):
        self.robot_cfg = robot_cfg
        self.recapture_every, self.until_clean, self.max_steps = recapture_every, until_clean, max_steps

    @property
    def loop(self) -> ClosedLoopSpec:
        """The closed loop as the run's ``config.json`` saves it (``recapture_every`` None: no loop)."""
        return ClosedLoopSpec(self.recapture_every, self.until_clean, self.max_steps)

    def check(self, capture, start_xyz) -> None:
        guard = _check_robot(self.robot_cfg)
        from tergodic_cli.robot.run import object_pose
        from tergodic_cli.backends.pybullet.arms import get_arm
        from tergodic_cli.robot.surface import check_reachable, transform_points

        # the same placement as the run, so an unreachable pose is refused before the run folder
        T_obj = object_pose(capture, self.robot_cfg)
        check_reachable(transform_points(T_obj, capture.points), get_arm(self.robot_cfg.arm).reach)
        for a in transform_points(T_obj, np.atleast_2d(start_xyz)):
            require(guard.inside(a), f"the start point ({', '.join(f'{v:.3f}' for v in a)}) m is outside the workspace box",
                    "move the object with --object-pose, widen --workspace, or choose another start")

    def explore_config(self, cfg: ExploreConfig) -> ExploreConfig:
        """The robot runs the explorer at its own step period with the same path per step."""
        from tergodic_cli.robot.run import robot_explore_config

        return robot_explore_config(cfg, self.robot_cfg.explore_dt)

    def drive(self, capture, explorer, steps: int, on_step, on_event, runlog=None) -> dict:
        if self.recapture_every is None:
            from tergodic_cli.backends.pybullet import explore_with_robot

            return explore_with_robot(capture, explorer, self.robot_cfg, steps, on_step=on_step, on_event=on_event,
                                      on_log=_robot_log(runlog, explorer))
        from tergodic_cli.backends.pybullet.closed_loop import clean_with_robot, log_recapture

        dt = explorer.cfg.dt
        on_recapture = (lambda step, rec: log_recapture(runlog, explorer, step, step * dt, rec)) if runlog else None
        return clean_with_robot(capture, explorer, self.robot_cfg, loop_cfg=self._loop(steps), on_step=on_step,
                                on_event=on_event, on_recapture=on_recapture, on_log=_robot_log(runlog, explorer))

    def _loop(self, steps: int):
        from tergodic_cli.backends.pybullet.closed_loop import CleaningLoopConfig

        return CleaningLoopConfig(recapture_every=self.recapture_every, until_clean=self.until_clean,
                                  max_steps=self.max_steps or steps)


class Hardware(PyBullet):
    """A real arm with a force source (``--robot`` one of :data:`HARDWARE`: franky's streamed impedance,
    pylibfranka's 1 kHz torque loop, a UR's force mode); ``hardware`` holds the
    :func:`~tergodic_cli.backends.factory.make_hardware` arguments, whose SDKs are imported now;
    ``dry_run``: the devices connect read-only (no real-time kernel needed)."""

    name = "franka"

    def __init__(self, robot_cfg, hardware: dict | None = None, robot: str = "franka", dry_run: bool = False):
        from tergodic_cli.backends.factory import make_hardware

        self.robot_cfg, self.name = robot_cfg, robot
        #: The connection, as the run's ``config.json`` saves it.
        self.hardware = HardwareSpec(**(hardware or {}))
        self.recapture_every, self.until_clean, self.max_steps = None, ClosedLoopSpec.until_clean, None  # no loop
        self.arm, self.sensor = make_hardware(robot=robot, read_only=dry_run, **(hardware or {}))

    def check(self, capture, start_xyz) -> None:
        _check_robot(self.robot_cfg)  # the hardware plans its own reach

    def drive(self, capture, explorer, steps: int, on_step, on_event, runlog=None) -> dict:
        from tergodic_cli.backends.streamed import explore_with_hardware

        return explore_with_hardware(capture, explorer, self.robot_cfg, steps, self.arm, self.sensor,
                                     on_step=on_step, on_event=on_event, on_log=_robot_log(runlog, explorer))

    def dry_run(self, capture, start_xyz) -> str:
        """Connect, read the devices and say what a run from ``start_xyz`` (3,) m would do; nothing moves."""
        from tergodic_cli.backends.streamed import DryRunPlan, dry_run

        return dry_run(self.arm, self.sensor, None, DryRunPlan(capture, self.robot_cfg, start=tuple(start_xyz)))


#: The former name of :class:`Hardware` (a Franka was the only real robot).
Franka = Hardware


def make_backend(robot: str = "kinematic", robot_options: dict | None = None, hardware: dict | None = None,
                 recapture_every: int | None = None, until_clean: float = 0.05, max_steps: int | None = None,
                 dry_run: bool = False):
    """The backend a run drives, from the verb's options; bad options raise :class:`TergodicError` (exit 2).

    Parameters
    ----------
    robot : str
        One of :data:`ROBOTS`.
    robot_options : dict or None
        :class:`~tergodic_cli.robot.RobotConfig` fields (see :func:`make_robot_config`).
    hardware : dict or None
        ``robot="franka"``: the :func:`~tergodic_cli.backends.factory.make_hardware` arguments.
    recapture_every, until_clean, max_steps : int or None, float, int or None
        ``robot="pybullet"``: the closed re-capture loop (see :class:`PyBullet`).
    dry_run : bool
        Only to plan (``robot="franka"``).

    Returns
    -------
    Kinematic, PyBullet or Hardware
    """
    require(robot in ROBOTS, f"--robot '{robot}' is unknown", f"use one of {', '.join(ROBOTS)}")
    require(recapture_every is None or robot == "pybullet", "--recapture-every needs the simulated robot",
            "add --robot pybullet (with a 'tergodic capture --source sim' capture)")
    require(0.0 <= until_clean < 1.0, f"--until-clean must be in [0, 1), got {until_clean}", "e.g. 0.05 (5% of the marking left)")
    require(not dry_run or robot in HARDWARE, "--dry-run needs a real robot", f"use it with --robot {'|'.join(HARDWARE)}")
    if robot == "kinematic":
        return Kinematic()
    from tergodic_cli.robot import RobotConfig

    robot_cfg = make_robot_config(RobotConfig, robot_options)
    if robot in HARDWARE:
        require(robot_cfg.arm == "panda", f"--arm {robot_cfg.arm} is a simulated arm, not --robot {robot}",
                f"leave --arm out with --robot {robot}, or use --robot pybullet")
        return Hardware(robot_cfg, hardware, robot, dry_run)
    from tergodic_cli.backends.pybullet.arms import get_arm

    get_arm(robot_cfg.arm)  # an unknown arm: one line naming the choices, before anything runs
    backend = PyBullet(robot_cfg, recapture_every, until_clean, max_steps)
    if recapture_every is not None:
        from tergodic_cli.backends.pybullet.closed_loop import validate_loop_config

        validate_loop_config(backend._loop(max_steps or 1))
    return backend


def _check_robot(robot_cfg):
    """The robot config's checks and its :class:`SafetyGuard` (workspace box, force limit above --force)."""
    from tergodic_cli.robot.config import validate_robot_config
    from tergodic_cli.robot.safety import SafetyGuard
    from tergodic_cli.runlog.viewers import require_display

    validate_robot_config(robot_cfg)
    guard = SafetyGuard(robot_cfg.safety, np.zeros(7), np.ones(7), np.ones(7), float(robot_cfg.force))  # joint limits unused
    if robot_cfg.gui:
        require_display()
    return guard


def _log_cloud(runlog, explorer: Explorer, step: int) -> None:
    runlog.log_cloud(step, coverage=explorer.coverage, heat=explorer.heat, source=explorer.source, target=explorer.p)


#: trajectory.npz's per-step arrays, in the file's order: (T, N, 3) vectors, then (T,) scalars.
VEC_FIELDS = ("positions", "velocities", "normals", "accelerations")
SCALAR_FIELDS = ("time", "ergodicity", "residual_ref", "touched_fraction", "step_ms")


def step_metrics(explorer: Explorer, robot_sample: dict | None) -> dict:
    """The step's metrics for the series and the log: the explorer's (its agent's path), but on a robot
    run ε and the touched share are the sponge's real contact points (the sample's ``eps_sponge``,
    ``touched_sponge``), with the agent's beside them as ``ergodicity_agent``, ``touched_fraction_agent``."""
    m = dict(explorer.metrics())
    if robot_sample is not None and robot_sample.get("eps_sponge") is not None:
        m["ergodicity_agent"], m["touched_fraction_agent"] = m["ergodicity"], m["touched_fraction"]
        m["ergodicity"], m["touched_fraction"] = robot_sample["eps_sponge"], robot_sample["touched_sponge"]
    return m


class RunRecorder:
    """The explorer's state after every step: trajectory.npz and the summary's series."""

    def __init__(self, explorer: Explorer):
        self.ex, self.vecs, self.rows = explorer, [], []

    @property
    def count(self) -> int:
        return len(self.rows)

    def record(self, step: int, metrics: dict | None = None) -> None:
        """Keep the explorer's state after ``step``; ``metrics`` (default ``explorer.metrics()``) gives
        the step's ergodicity, residual_ref and touched_fraction (:func:`step_metrics`)."""
        ex = self.ex
        m = ex.metrics() if metrics is None else metrics
        # np.stack copies: the explorer updates its arrays in place
        self.vecs.append(np.stack([getattr(ex, k) for k in VEC_FIELDS]))
        self.rows.append((step * ex.cfg.dt, m["ergodicity"], m["residual_ref"],
                          m["touched_fraction"], ex.last_step_ms))

    def arrays(self) -> dict[str, np.ndarray]:
        """The per-step arrays by name (empty, of the same shapes, before the first step)."""
        if not self.rows:  # a robot stopped before the first step: empty series of the right shapes
            shape = (0, len(VEC_FIELDS), *np.shape(self.ex.positions))
            vecs, rows = np.zeros(shape), np.zeros((0, len(SCALAR_FIELDS)))
        else:
            vecs, rows = np.array(self.vecs, dtype=np.float64), np.array(self.rows, dtype=np.float64)
        return {**{k: vecs[:, i] for i, k in enumerate(VEC_FIELDS)},
                **{k: rows[:, i] for i, k in enumerate(SCALAR_FIELDS)}}

    def series(self) -> dict[str, np.ndarray]:
        return {k: v for k, v in self.arrays().items() if k in SCALAR_FIELDS[1:]}

    def write(self, path: Path, start: np.ndarray) -> None:
        from tergodic_cli.atomic import write_npz

        ex = self.ex
        write_npz(path, **self.arrays(), start=np.asarray(start, dtype=np.float64),
                  coverage=ex.coverage, heat=ex.heat, source=ex.source, target=ex.p,
                  points=ex.points)


def _provenance(run: _Run, robot_extra: dict, logged: bool) -> dict:
    from tergodic_cli.provenance import library_versions

    starts, capture, basis, explorer, cfg = run.starts or StartSpec(), run.capture, run.basis, run.explorer, run.cfg
    score = explorer.score()
    extra = {
        "robot": run.backend.name,
        # what the headline ε (ergodicity, its series and milestones) scores: the real contacts on a robot run
        "eps_source": "agent path" if run.backend.name == "kinematic" else "sponge contacts",
        "capture": {"path": str(Path(run.capture_dir)), "n_points": int(capture.n_points),
                    "n_target": int(np.count_nonzero(capture.target > 0)),
                    "sha256": capture.meta.get("arrays", {}).get("sha256")},
        "basis": {"key": basis.meta.get("key"), "path": basis.meta.get("path"), "cache_hit": bool(run.hit),
                  "nk_used": int(cfg.nk), "neighbors": int(cfg.basis_neighbors), "h_m": float(basis.h)},
        "explorer": {"alpha_schedule": [[s, a] for s, a in parse_alpha(cfg.alpha)],
                     "epsilon_per_m": cfg.footprint_epsilon, "edge_events": int(explorer.edge_events),
                     "transits": int(explorer.transits),
                     "diffusion": cfg.diffusion, "integrator": cfg.integrator},
        # the neutral score's surface checks (issue 13): positions > 2h off the cloud, longest step
        "off_surface_fraction": score["off_surface_fraction"], "step_max_m": score["step_max_m"],
        # a cloud much denser than 3 mm: ε above scores its target at the fields' 3 mm; this, per point
        **({"ergodicity_point_target": score["ergodicity_point_target"]} if "ergodicity_point_target" in score else {}),
        "starts": {"start": starts.start, "starts_file": starts.starts_file, "start_index": starts.start_index,
                   "xyz": np.asarray(run.start_xyz).tolist()},
        "files": ["trajectory.npz", "summary.json", "config.json"] + (["run.mcap"] if logged else []),
        "versions": library_versions(),
    }
    # the robot's summary extras, merged in (CONTRACTS.md)
    return {**extra, **{k: v for k, v in robot_extra.items() if k not in extra}}
