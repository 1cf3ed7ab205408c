"""Running a sweep: objects -> bases (once per object) -> runs in parallel -> one table and plots.

docs/speed.md describes the engines, resuming and the outputs. One executor (:func:`_execute`)
runs :func:`run_batch` on batches of one (object, nK) in joblib's process pool or as Ray tasks,
and yields each batch's results as soon as it is done (joblib's own Ray backend cannot stream
results back, which resuming needs). A run counts as done when its record verifies
(:func:`load_record`). Results do not depend on the engine or the number of workers: a run is a
pure function of its inputs, single-threaded, with no BLAS call (explore.kernels).
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import multiprocessing
import os
import shutil
import signal
import statistics
import tempfile
import time
from contextlib import suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from tergodic_cli.atomic import _json_default, file_sha256
from tergodic_cli.errors import TergodicError, os_cause, require
from tergodic_cli.sweep.grid import Grid, ObjectSpec, alpha_key, load_grid, run_config, run_id

ENGINES = ("joblib", "ray")
SERIES = ("ergodicity", "residual_ref", "touched_fraction")
#: Columns of results.csv before the grid's own option columns.
LEAD_COLUMNS = ("run_id", "object", "n_points", "n_target", "start", "start_x", "start_y", "start_z", "nk", "alpha")
#: Metric columns after them.
METRIC_COLUMNS = ("steps", "ergodicity", "residual_ref", "touched_fraction", "ergodicity_at_200",
                  "ergodicity_at_500", "residual_ref_at_200", "residual_ref_at_500", "touched_fraction_at_200",
                  "touched_fraction_at_500", "off_surface_fraction", "step_max_m", "edge_events", "step_ms_median",
                  "wall_s")
#: Columns that measure time, and so differ between otherwise identical sweeps.
TIMING_COLUMNS = ("step_ms_median", "wall_s")


@dataclass
class SweepResult:
    """What a sweep did; ``files`` are paths relative to ``out``."""

    out: Path
    n_runs: int
    computed: int
    skipped: int
    failed: list[dict] = field(default_factory=list)
    wall_s: float = 0.0
    files: list[str] = field(default_factory=list)
    table: list[dict] = field(default_factory=list)

    def summary(self) -> dict:
        """The counts, wall time (s) and files: what ``tergodic sweep --json`` prints."""
        return {"out": str(self.out), "runs": self.n_runs, "computed": self.computed, "skipped": self.skipped,
                "failed": len(self.failed), "wall_s": round(self.wall_s, 2), "files": self.files}

    def ergodicity_tables(self) -> str:
        """Mean final ε (the neutral unit-mass ergodicity) over starts and other options, per object:
        one Markdown table each, nK down and α across."""
        out = []
        for obj in sorted({r["object"] for r in self.table}):
            sel = [r for r in self.table if r["object"] == obj and r["ergodicity"] is not None]
            alphas = sorted({str(r["alpha"]) for r in sel}, key=lambda a: (len(a), a))
            out += [f"\n{obj}: mean ε at the last step (over starts and other options)",
                    "| nK \\ α | " + " | ".join(alphas) + " |", "|---|" + "---|" * len(alphas)]
            for nk in sorted({r["nk"] for r in sel}):
                cells = [[r["ergodicity"] for r in sel if r["nk"] == nk and str(r["alpha"]) == a] for a in alphas]
                out.append(f"| {nk} | " + " | ".join(f"{statistics.fmean(v):.3f}" if v else "" for v in cells) + " |")
        return "\n".join(out)


@dataclass
class _Object:
    spec: ObjectSpec
    key: str
    points: np.ndarray
    target: np.ndarray
    starts: dict[int, np.ndarray]

    @property
    def n_target(self) -> int:
        return int(np.count_nonzero(self.target > 0))


# ---------------------------------------------------------------------------------- objects
def materialise(spec: ObjectSpec, starts: list[int], seed: int, out: Path) -> _Object:
    """Capture (or load) one object, save it under ``out/objects/NAME`` and resolve its starts."""
    from tergodic_cli.capture import CaptureConfig, capture_cloud, load_capture, save_capture
    from tergodic_cli.run import StartSpec, resolve_starts

    if spec.source == "capture":
        cap = load_capture(spec.location)
    else:
        where = {"path": spec.location} if spec.source == "file" else {"synthetic": spec.location}
        try:
            cap = capture_cloud(CaptureConfig(source=spec.source, **where, **spec.capture_options))
        except TypeError as exc:
            raise TergodicError(f"object {spec.name}: bad capture option ({exc})", "see 'tergodic capture --help'") from None
    require(bool(np.any(cap.target > 0)), f"object {spec.name}: the target is empty (no point has p > 0)",
            "check its target/marking options")
    save_capture(cap, out / "objects" / spec.name)
    arrays = (np.ascontiguousarray(a, dtype=np.float64).tobytes() for a in (cap.points, cap.target))
    h = hashlib.sha1(b"".join(arrays) + str(spec.neighbors).encode())  # the object's content key
    xyz = {}
    for i in starts:
        if spec.starts_file is not None:
            xyz[i] = resolve_starts(StartSpec(starts_file=spec.starts_file, start_index=i), cap.points, 1, seed)[0]
        else:  # a seeded random cloud point per start index
            xyz[i] = resolve_starts(StartSpec(start="random"), cap.points, 1, seed * 100003 + i)[0]
    return _Object(spec, h.hexdigest()[:16], np.asarray(cap.points, dtype=np.float64),
                   np.asarray(cap.target, dtype=np.float64), xyz)


# ---------------------------------------------------------------------------------- workers
_BASES: dict[tuple, object] = {}


def _basis_for(key: str, points, neighbors: int, max_nk: int, nk: int, cache_dir):
    """The (object, nK) basis in this process: loaded once from the cache (largest nK), then truncated."""
    if (key, max_nk) not in _BASES:
        from tergodic_cli.run import find_basis

        _BASES[(key, max_nk)] = find_basis(points, max_nk, neighbors, cache_dir)[0]
    if (key, max_nk, nk) not in _BASES:
        full = _BASES[(key, max_nk)]
        _BASES[(key, max_nk, nk)] = full if nk == full.nk else full.truncated(nk)
    return _BASES[(key, max_nk, nk)]


def run_batch(task: dict) -> list[dict]:
    """Run the explorer for every run of ``task`` (one object and nK); never raises for one run.

    Returns one record per run: the summary, the per-step series (float32) and the wall time,
    or an ``error`` message.
    """
    os.environ.setdefault("TERGODIC_NO_PROGRESS", "1")
    if multiprocessing.current_process().name != "MainProcess":
        # A pool worker: Ctrl-C reaches the whole process group, and the driver stops the pool
        # itself; a worker interrupted inside numba's compiler printed llvmlite's traceback. (Kept
        # for a worker the pool respawns later: the first ones start ignoring it, see _execute.)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    from tergodic_cli.explore import ExploreConfig, Explorer, summarize_run
    from tergodic_cli.explore.warm import compile_explorer
    from tergodic_cli.run import RunRecorder

    compile_explorer()  # a worker's first step would otherwise load the kernels inside its timing
    out = []
    for run in task["runs"]:
        t0 = time.perf_counter()
        try:
            cfg = ExploreConfig(**{**run["config"], "normal_hint": tuple(run["config"]["normal_hint"])})
            basis = _basis_for(task["key"], task["points"], task["neighbors"], task["max_nk"], cfg.nk,
                               task["cache_dir"])
            warnings: list[str] = []
            ex = Explorer(basis, task["target"], cfg, np.asarray(run["start_xyz"], dtype=np.float64)[None],
                          on_event=warnings.append)
            recorder = RunRecorder(ex)
            for k in range(cfg.steps):
                ex.step()
                recorder.record(k + 1)
            series = recorder.series()
            summary = summarize_run(series, cfg.to_dict(), {"edge_events": ex.edge_events, "transits": ex.transits, "warnings": warnings,
                                                                  "off_surface_fraction": ex.score()["off_surface_fraction"],
                                                                  "step_max_m": ex.score()["step_max_m"]})
            out.append({"run_id": run["run_id"], "summary": summary, "wall_s": time.perf_counter() - t0,
                        "series": {k: series[k].astype(np.float32) for k in SERIES}})
        except Exception as exc:  # one bad run must not lose the batch's other results
            msg = exc.problem if isinstance(exc, TergodicError) else f"{type(exc).__name__}: {exc}"
            out.append({"run_id": run["run_id"], "error": str(msg).splitlines()[0][:300]})
    return out


# ---------------------------------------------------------------------------------- engines
def _execute(batches: list[dict], engine: str, jobs: int, address: str | None, on_event):
    """Yield each batch's records as soon as it finishes (any order): the one executor of both
    engines, running :func:`run_batch` in joblib's process pool or as Ray tasks."""
    if engine == "joblib":  # --jobs 1: joblib runs the batches in this process, no pool
        import joblib

        # The pool starts its workers in this call. They inherit an ignored SIGINT through fork and
        # exec, so a Ctrl-C while one still imports prints no traceback (a blocked mask is not
        # enough: the resource tracker's start unblocks it). One pressed in this short window is lost.
        # (With --jobs 1 the call runs nothing: the batches run as the results are read.)
        handler = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            results = joblib.Parallel(n_jobs=jobs, backend="loky", return_as="generator_unordered")(
                joblib.delayed(run_batch)(b) for b in batches)
        finally:
            signal.signal(signal.SIGINT, handler)
        yield from results
        return
    import ray  # imported by run_sweep already

    started = not ray.is_initialized()  # a cluster we start, we also shut down
    if started:
        try:
            ray.init(address=address, include_dashboard=False, log_to_driver=False, configure_logging=False)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            where = address or "a new local cluster"
            raise TergodicError(f"cannot start or reach Ray at {where} ({str(exc).splitlines()[0][:80]})",
                                "start a cluster with 'ray start --head' and pass --address HOST:PORT") from None
    on_event(f"ray: {int(ray.cluster_resources().get('CPU', 0))} CPUs "
             f"({'started locally' if started else 'existing cluster'})")
    try:
        remote = ray.remote(num_cpus=1, max_retries=2)(run_batch)
        cpus = max(int(ray.cluster_resources().get("CPU", 1)), 1)
        limit = cpus if jobs == -1 else min(jobs, cpus)
        todo = list(batches)
        running = []
        # Keep a bounded number of tasks in flight (2 per worker slot): the driver writes results
        # while the cluster works, and a crash loses at most the batches in flight.
        while todo or running:
            while todo and len(running) < 2 * limit:
                running.append(remote.remote(todo.pop(0)))
            done, running = ray.wait(running, num_returns=1)
            yield ray.get(done[0])
    finally:
        if started:
            ray.shutdown()


# ---------------------------------------------------------------------------------- the sweep
#: The sweep's mark in its folder: the grid it runs (a folder of another grid, or of files it did
#: not write, is refused unless --overwrite).
MARKER = ".tergodic-sweep.json"
#: What a sweep folder may hold; --overwrite replaces only a folder of these.
SWEEP_NAMES = frozenset({MARKER, "results.csv", "results.parquet", "series.npz", "sweep.json", "runs", "objects"})


def _owned(name: str) -> bool:
    return name in SWEEP_NAMES or name.endswith(".png") or name.startswith(".results.tmp-")


def grid_fingerprint(grid: Grid) -> str:
    """What a grid runs, as a fingerprint.

    Parameters
    ----------
    grid : Grid

    Returns
    -------
    str
        sha256 of its objects, options, starts, steps and seed (not its file's path or comments).
    """
    from dataclasses import asdict

    body = {k: v for k, v in asdict(grid).items() if k != "path"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, default=str).encode()).hexdigest()


def cap_jobs(jobs: int, on_event) -> int:
    """``--jobs`` for local processes: at most the CPUs (more only queue and take memory).

    Parameters
    ----------
    jobs : int
        The workers asked for (>= 1).
    on_event : callable
        ``on_event(text)`` gets the note when they are capped.

    Returns
    -------
    int
        The workers to start.
    """
    cpus = os.cpu_count() or 1
    if jobs > cpus:
        on_event(f"note: --jobs {jobs} is more than the {cpus} CPUs; using {cpus}")
        return cpus
    return jobs


def _claim(out: Path, fingerprint: str, grid: Grid, overwrite: bool) -> bool:
    """Whether the sweep runs in ``out`` itself (new, empty, or this grid's sweep: resumed) or, with
    ``overwrite``, is built aside and swapped in (another grid's sweep, or files it did not write)."""
    try:
        names = sorted(p.name for p in out.iterdir()) if out.is_dir() else []
    except OSError as exc:
        raise TergodicError(f"cannot read --out {out}: {os_cause(exc)}", "choose another --out") from None
    if not names:
        return False
    mark = None
    with suppress(OSError, ValueError):
        mark = json.loads((out / MARKER).read_text())
    if isinstance(mark, dict) and mark.get("grid_sha256") == fingerprint:
        return False  # the same grid: resumed
    if overwrite:
        return True
    if isinstance(mark, dict):
        raise TergodicError(f"--out {out} holds the sweep of another grid ({mark.get('grid', '?')}); a sweep never "
                            "mixes two grids", "choose another --out, or pass --overwrite to replace it")
    raise TergodicError(f"--out {out} holds files this sweep did not write ({names[0]}{', ...' if len(names) > 1 else ''})",
                        "choose another --out (a new or empty folder), or pass --overwrite to replace them")


def run_sweep(grid_path: str | Path, out: str | Path, jobs: int | None = None, engine: str = "joblib",
              address: str | None = None, cache_dir=None, plots: bool = True, parquet: bool = False,
              on_event: Callable[[str], None] | None = None, overwrite: bool = False) -> SweepResult:
    """Run (or resume) the sweep of ``grid_path`` into ``out``; see the module docstring.

    ``out`` is locked for the sweep (a second sweep into it is refused). A folder holding another
    grid's sweep, or files the sweep did not write, is refused unless ``overwrite``: the new sweep
    is then built in a temporary sibling and replaces it whole once complete.
    """
    from tergodic_cli.atomic import AtomicFolder

    say = on_event or (lambda msg: None)
    require(engine in ENGINES, f"--engine '{engine}' is unknown", f"use one of {', '.join(ENGINES)}")
    if jobs is None:
        jobs = -1 if engine == "ray" else (os.cpu_count() or 1)
    require(jobs == -1 or jobs >= 1, f"--jobs must be >= 1 (or -1: all CPUs), got {jobs}", "e.g. --jobs 2")
    if engine == "joblib":
        jobs = cap_jobs(jobs, say)
    grid = load_grid(grid_path)
    out = Path(out)
    # before any work: a file, a path under a file, a folder we cannot write; the lock is held to the end
    folder = AtomicFolder(out, overwrite=True, what="sweep", owned=_owned)
    folder.check(renamed=False)
    try:
        fingerprint = grid_fingerprint(grid)
        replace = _claim(out, fingerprint, grid, overwrite)
        if engine == "ray":  # refuse early, before any work, when Ray is missing
            try:
                import ray  # noqa: F401
            except ImportError:
                raise TergodicError("--engine ray needs Ray, which is not installed",
                                    "pip install 'ray>=2.9' (or use --engine joblib)") from None
        args = (grid, fingerprint, jobs, engine, address, cache_dir, plots, parquet, say)
        if not replace:
            return _sweep_into(out, *args)
        folder.check()  # only a sweep's files are replaced (never, say, a home folder given as --out)
        say(f"sweep: building the new sweep beside {out} and replacing it once complete")
        with folder as stage:
            result = _sweep_into(stage, *args)
        result.out = out
        return result
    finally:
        folder.release()


def _sweep_into(out: Path, grid: Grid, fingerprint: str, jobs: int, engine: str, address, cache_dir, plots: bool,
                parquet: bool, say) -> SweepResult:
    """The sweep, in ``out`` (claimed: new, or this grid's)."""
    from tergodic_cli.atomic import write_json, write_npz
    from tergodic_cli.progress import track
    from tergodic_cli.provenance import library_versions
    from tergodic_cli.run import find_basis

    t_start = time.perf_counter()
    if not (out / MARKER).exists():
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / MARKER, {"grid": str(grid.path), "grid_sha256": fingerprint})

    objects = []
    for spec in grid.objects:
        obj = materialise(spec, grid.starts, grid.seed, out)
        require(grid.max_nk < len(obj.points), f"object {spec.name}: nK = {grid.max_nk} is not below its "
                f"{len(obj.points)} points", f"use nk values below {len(obj.points)}")
        t0 = time.perf_counter()
        _, hit = find_basis(obj.points, grid.max_nk, spec.neighbors, cache_dir, on_event=say)
        say(f"object {spec.name}: {len(obj.points)} points, {obj.n_target} target; basis "
            f"nK = {grid.max_nk} {'from the cache' if hit else f'computed in {time.perf_counter() - t0:.1f} s'}")
        objects.append(obj)

    runs_dir = out / "runs"
    runs_dir.mkdir(parents=True, exist_ok=True)
    plan: list[tuple[_Object, int, dict, str, object]] = [
        (obj, start, combo, run_id(obj.key, start, cfg.to_dict()), cfg)
        for obj in objects for combo in grid.combos()
        for cfg in [run_config(grid, obj.spec, combo)] for start in grid.starts]
    # resuming: a run whose record verifies is done; one that does not is run again
    checked = {p[3]: load_record(runs_dir, p[3]) for p in plan
               if (runs_dir / f"{p[3]}.json").exists()}
    finished = {rid: rec for rid, rec in checked.items() if not isinstance(rec, str)}
    bad = [rec for rec in checked.values() if isinstance(rec, str)]
    if bad:
        say(f"sweep: {len(bad)} finished run record(s) do not verify (e.g. {bad[0]}); running them again")
    pending = [p for p in plan if p[3] not in finished]
    say(f"{len(plan)} runs: {len(plan) - len(pending)} done already, {len(pending)} to run "
        f"({engine}, {'all CPUs' if jobs == -1 else f'{jobs} job(s)'})")

    by_id = {p[3]: p for p in pending}
    batches = _batches(pending, grid, jobs, cache_dir)
    failed: list[dict] = []
    if batches:
        from tergodic_cli.explore.warm import compile_explorer

        compile_explorer(say)  # once here, so the workers load the cached code instead of each compiling it
        # the bar counts runs, as announced above, not batches
        for records in track(_execute(batches, engine, jobs, address, say), total=len(pending), description="sweep",
                             weight=len):
            for rec in records:
                if "error" in rec:
                    failed.append(rec)
                    continue
                obj, start, combo, rid, cfg = by_id[rec["run_id"]]
                write_npz(runs_dir / f"{rid}.npz", **rec["series"])
                record = {"run_id": rid, "object": obj.spec.name, "object_key": obj.key,
                          "n_points": len(obj.points), "n_target": obj.n_target, "start": start,
                          "start_xyz": obj.starts[start].tolist(), "grid": dict(combo),
                          "wall_s": rec["wall_s"], "summary": rec["summary"],
                          "series_sha256": file_sha256(runs_dir / f"{rid}.npz")}
                record[RECORD_SHA] = record_checksum(record)
                write_json(runs_dir / f"{rid}.json", record)
                finished[rid] = (json.loads(json.dumps(record, default=_json_default)), rec["series"])
    table, series = _collect(plan, finished)
    # every pending run gives one record: its result or its error
    result = SweepResult(out=out, n_runs=len(plan), computed=len(pending) - len(failed),
                         skipped=len(plan) - len(pending), failed=failed, table=table)

    def build(stage: Path) -> list[str]:
        files = _write_outputs(stage, grid, table, series, parquet)
        if plots and table:
            from tergodic_cli.sweep.plots import plot_sweep

            files += plot_sweep(stage, grid, table, series)
        result.wall_s = time.perf_counter() - t_start
        objs = {o.spec.name: {"source": o.spec.source, "location": o.spec.location, "key": o.key,
                              "n_points": len(o.points), "n_target": o.n_target,
                              "neighbors": o.spec.neighbors} for o in objects}
        write_json(stage / "sweep.json", {
            "grid": str(grid.path), "steps": grid.steps, "seed": grid.seed, "starts": grid.starts,
            "options": grid.options, "objects": objs, "engine": engine, "jobs": jobs,
            "runs": len(plan), "computed": result.computed, "skipped": result.skipped, "failed": failed,
            "wall_s": result.wall_s, "files": files, "versions": library_versions()})
        return files + ["sweep.json"]

    result.files = _publish(out, build)
    return result


def _publish(out: Path, build: Callable[[Path], list[str]]) -> list[str]:
    """``build(stage)`` writes the outputs into a temporary folder inside ``out`` (same filesystem);
    the files it names are then renamed into ``out`` together. On an error the folder is removed
    and the old outputs stay as they were. Returns the names."""
    try:
        stage = Path(tempfile.mkdtemp(prefix=".results.tmp-", dir=out))
        try:
            files = build(stage)
            for name in files:
                os.replace(stage / name, out / name)
        finally:
            shutil.rmtree(stage, ignore_errors=True)
    except OSError as exc:
        raise TergodicError(f"cannot write the sweep's results in {out}: {os_cause(exc)}",
                            "free space or fix the folder's permissions, then run the same command "
                            "again: finished runs are kept") from None
    return files


#: The record's checksum of its own content (canonical JSON without this key).
RECORD_SHA = "record_sha256"
#: What a finished-run record must hold to be counted as done.
RECORD_KEYS = ("run_id", "object", "n_points", "n_target", "start", "start_xyz", "wall_s", "summary", "series_sha256")
SUMMARY_KEYS = ("steps", "ergodicity", "residual_ref", "touched_fraction", "ergodicity_at", "residual_ref_at",
                "touched_fraction_at", "step_ms_median")


def record_checksum(record: dict) -> str:
    body = {k: v for k, v in record.items() if k != RECORD_SHA}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True,
                      default=_json_default)
    return hashlib.sha256(text.encode()).hexdigest()


def load_record(runs_dir: Path, rid: str):
    """The finished run ``rid`` as (record, series), or a one-phrase reason it does not verify:
    unreadable or not JSON, a missing key, an edited record, a missing or changed series file."""
    jpath, npath = runs_dir / f"{rid}.json", runs_dir / f"{rid}.npz"
    name = f"runs/{rid}.json"
    try:
        rec = json.loads(jpath.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return f"{name}: not readable JSON"
    if not isinstance(rec, dict) or not isinstance(rec.get("summary"), dict):
        return f"{name}: not a run record"
    missing = [k for k in RECORD_KEYS if k not in rec] + [k for k in SUMMARY_KEYS if k not in rec["summary"]]
    if missing:
        return f"{name}: no '{missing[0]}'"
    if rec.get(RECORD_SHA) != record_checksum(rec) or rec["run_id"] != rid:
        return f"{name}: edited (its checksum does not match)"
    try:
        if file_sha256(npath) != rec["series_sha256"]:
            return f"runs/{rid}.npz: changed (its checksum does not match the record)"
        with np.load(npath, allow_pickle=False) as z:
            series = {k: np.asarray(z[k]) for k in SERIES}
    except (OSError, ValueError, KeyError):
        return f"runs/{rid}.npz: missing or unreadable"
    return rec, series


def _batches(pending, grid: Grid, jobs: int, cache_dir) -> list[dict]:
    """Runs grouped by (object, nK), cut into batches small enough to keep every worker busy."""
    workers = max(jobs, 1) if jobs != -1 else (os.cpu_count() or 2)
    size = max(1, min(25, math.ceil(len(pending) / (4 * workers))))
    groups: dict[tuple, list] = {}
    for obj, start, combo, rid, cfg in pending:
        groups.setdefault((obj.spec.name, cfg.nk), []).append((obj, start, rid, cfg))
    batches = []
    for (_, _), items in sorted(groups.items()):
        obj = items[0][0]
        for i in range(0, len(items), size):
            batches.append({"key": obj.key, "points": obj.points, "target": obj.target,
                            "neighbors": obj.spec.neighbors, "max_nk": grid.max_nk,
                            "cache_dir": None if cache_dir is None else str(cache_dir),
                            "runs": [{"run_id": rid, "config": cfg.to_dict(), "start_xyz": obj.starts[start].tolist()}
                                     for obj, start, rid, cfg in items[i:i + size]]})
    return batches


def _collect(plan, finished: dict) -> tuple[list[dict], dict]:
    """The table rows and series of this grid's finished runs (sorted), from the verified records."""
    rows, series = [], []
    for obj, start, combo, rid, cfg in plan:
        if rid not in finished:
            continue
        rec, run_series = finished[rid]
        s = rec["summary"]
        x, y, z = rec["start_xyz"]
        rows.append({"run_id": rid, "object": rec["object"], "n_points": rec["n_points"],
                     "n_target": rec["n_target"], "start": start, "start_x": x, "start_y": y,
                     "start_z": z, "nk": cfg.nk, "alpha": cfg.alpha,
                     **{k: v for k, v in combo.items() if k not in ("nk", "alpha")},
                     **{k: s[k] for k in ("steps", *SERIES)},
                     **{f"{k}_at_{m}": s[f"{k}_at"][m] for k in SERIES for m in ("200", "500")},
                     **{k: s.get(k) for k in ("off_surface_fraction", "step_max_m", "edge_events")},
                     "step_ms_median": s["step_ms_median"], "wall_s": rec["wall_s"]})
        series.append(run_series)

    def sort_key(i: int) -> tuple:
        r = rows[i]
        others = [str(r.get(k)) for k in r if k not in LEAD_COLUMNS and k not in METRIC_COLUMNS]
        return r["object"], r["nk"], alpha_key(r["alpha"]), others, r["start"]

    order = sorted(range(len(rows)), key=sort_key)
    merged = {"run_id": np.array([rows[i]["run_id"] for i in order], dtype="U16")}
    for k in SERIES:
        merged[k] = np.stack([series[i][k] for i in order]) if order else np.zeros((0, 0), np.float32)
    return [rows[i] for i in order], merged


def _write_outputs(out: Path, grid: Grid, rows: list[dict], series: dict, parquet: bool) -> list[str]:
    """The table and series into ``out``, the staging folder (renamed into place whole)."""
    from tergodic_cli.atomic import write_npz

    columns = list(LEAD_COLUMNS) + [k for k in grid.options if k not in ("nk", "alpha")] + list(METRIC_COLUMNS)
    with open(out / "results.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=columns, extrasaction="ignore")
        w.writeheader()
        w.writerows({k: "" if r.get(k) is None else repr(r[k]) if isinstance(r[k], float) else r[k]
                     for k in columns} for r in rows)
    write_npz(out / "series.npz", **series)
    files = ["results.csv", "series.npz"]
    if parquet:
        try:
            import pyarrow as pa
            import pyarrow.parquet as pq
        except ImportError:
            raise TergodicError("--parquet needs pyarrow, which is not installed",
                                "pip install pyarrow, or use results.csv") from None
        table = pa.table({k: [r.get(k) for r in rows] for k in columns if any(r.get(k) is not None for r in rows)})
        pq.write_table(table, out / "results.parquet")
        files.append("results.parquet")
    return files


def read_table(path: str | Path) -> list[dict]:
    """results.csv as a list of dicts (numbers parsed), for tests and scripts."""
    with open(path, newline="") as fh:
        return [{k: _parse(v) for k, v in r.items()} for r in csv.DictReader(fh)]


def _parse(v: str):
    for cast in (int, float):
        with suppress(ValueError):
            return cast(v)
    return v or None  # an empty cell (neither cast takes "")
