"""Cost of the MCAP run log per explorer step, against the kinematic step itself.

Three measurements, each printed as medians:

A. RunLog alone, on synthetic step data of the reference bunny's size (2996 points after
   the 3 mm voxel grid, 1 agent, a cloud every 50 steps): microseconds per step, for
   both writer backends.
B. The kinematic explorer on the reference bunny (nK = 200, α = 10, 1000 steps): two
   explorers stepped in lockstep in one process, one of them logged (clouds included,
   open and close included); the ratio is the logging overhead the issue bounds at 10 %. Skipped when the reference data or the
   explorer is absent.
C. End to end, ``tergodic explore CAP --robot kinematic`` with and without ``--no-log``:
   CPU time of the child process (robust to other load on a shared machine) and wall time.
   This includes the fixed cost of the logging stack (imports, opening and closing the file).

Run:  OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/logging.py [--quick]
"""

from __future__ import annotations

import _env  # noqa: F401,I001  (first: path fix, one BLAS thread; see benchmarks/_env.py)

import os
import sys


import argparse  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
REFERENCE = REPO.parent / "shared" / "data" / "reference"


def _synthetic_step_data(n_points: int, steps: int, n_agents: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {"points": rng.standard_normal((n_points, 3)) * 0.04, "target": (rng.random(n_points) > 0.93) * 1.0,
            "P": rng.standard_normal((steps, n_agents, 3)) * 0.04, "V": rng.standard_normal((steps, n_agents, 3)) * 3e-3,
            "N": rng.standard_normal((steps, n_agents, 3)), "field": rng.random((3, n_points))}


def bench_runlog(n_points: int = 2996, steps: int = 1000, n_agents: int = 1, repeats: int = 5,
                 backend: str = "auto", cloud_every: int = 50, writer: str = "inline") -> dict:
    """A: RunLog cost per step (µs): the step loop alone, and including open and close.

    ``writer="process"``: the caller's side of BackgroundRunLog (the child started and ready
    beforehand, as explore starts it before loading the basis); "total" then includes waiting
    for the child to finish the file.
    """
    from tergodic_cli.runlog import RunLog
    from tergodic_cli.runlog.background import BackgroundRunLog, LogWriterProcess

    d = _synthetic_step_data(n_points, steps, n_agents)
    caller, total, cpu_loop = [], [], []
    for _ in range(repeats):
        tmp = Path(tempfile.mkdtemp(prefix="tergodic-bench-"))
        try:
            child = None
            if writer == "process":
                child = LogWriterProcess()
                child.wait_ready()
            t0 = time.perf_counter()
            kw = {"writer": child} if child else {}
            log = (BackgroundRunLog if child else RunLog)(
                tmp / "run.mcap", config={"steps": steps}, seed=0, versions={}, points=d["points"], target=d["target"],
                cloud_every=cloud_every, backend=backend, **kw)
            t_open, c_open = time.perf_counter(), time.process_time()
            for k in range(steps):
                log.log_step(k + 1, float(k + 1), positions=d["P"][k], velocities=d["V"][k], normals=d["N"][k],
                             metrics={"ergodicity": 0.1 + k * 1e-5, "residual_ref": 0.2, "touched_fraction": k / steps},
                             step_ms=0.9)
                if (k + 1) % cloud_every == 0:
                    log.log_cloud(k + 1, coverage=d["field"][0], heat=d["field"][1], source=d["field"][2])
            t_loop, c_loop = time.perf_counter(), time.process_time()
            log.close({"steps": steps})
            t_close = time.perf_counter()
            caller.append((t_loop - t_open) / steps * 1e6)
            cpu_loop.append((c_loop - c_open) / steps * 1e6)
            total.append((t_close - t0) / steps * 1e6)
            size = (tmp / "run.mcap").stat().st_size
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    return {"caller_us": float(np.median(caller)), "cpu_us": float(np.median(cpu_loop)), "total_us": float(np.median(total)),
            "file_bytes": size}


def _bunny_explorer_factory(steps: int):
    """Capture, basis and a factory of fresh Explorers on the reference bunny (None when unavailable)."""
    try:
        from tergodic_cli.explore import ExploreConfig, Explorer
    except ImportError:
        return None
    if not (REFERENCE / "bun270_X.ply").exists():
        return None
    from tergodic_cli.basis import BasisConfig, get_basis
    from tergodic_cli.capture import CaptureConfig, capture_cloud

    cap = capture_cloud(CaptureConfig(source="file", path=str(REFERENCE / "bun270_X.ply"), voxel=0.003))
    cache = Path(tempfile.mkdtemp(prefix="tergodic-bench-cache-"))
    basis, _ = get_basis(cap.points, BasisConfig(nk=200, neighbors=40), cache)
    starts = np.load(REFERENCE / "starts" / "bun270_X.npz", allow_pickle=False)["x0_arr"][:1]
    cfg = ExploreConfig(steps=steps, alpha="10", nk=200, agent_radius=0.0075, n_agents=1, seed=0)

    def make():
        return Explorer(basis, cap.target, cfg, starts, on_event=lambda msg: None)

    return cap, basis, cfg, make, cache


def bench_explorer(steps: int = 1000, repeats: int = 3, cloud_every: int = 50,
                   variants: tuple[tuple[str, str], ...] = (("process", "lz4"), ("inline", "lz4"), ("inline", "zstd"))
                   ) -> dict | None:
    """B: two identical explorers stepped in lockstep, one of them logged; ms per step and overhead.

    Lockstep (plain step k, then logged step k, then k + 1 ...) exposes both sides to the
    same machine load at the same moment, which a shared 2-core machine needs.
    """
    made = _bunny_explorer_factory(steps)
    if made is None:
        return None
    cap, basis, cfg, make, cache = made
    out: dict = {"n_points": len(basis.points)}
    warm = make()  # compile / load the explorer's kernels and build the log's schemas before any timing
    for _ in range(5):
        warm.step()
    _lockstep(make, cap, basis, cfg, 20, cloud_every, "lz4", "inline")
    try:
        for writer, comp in variants:
            runs = [_lockstep(make, cap, basis, cfg, steps, cloud_every, comp, writer) for _ in range(repeats)]
            med = {key: float(np.median([r[key] for r in runs])) for key in runs[0]}
            for kind in ("thread", "wall"):  # the median of per-run ratios: each run is one load condition
                med[f"{kind}_overhead"] = float(np.median([r[f"{kind}_logged"] / r[f"{kind}_plain"] for r in runs])) - 1
                med[f"{kind}_steps_overhead"] = float(np.median([r[f"{kind}_steps"] / r[f"{kind}_steps_plain"]
                                                                 for r in runs])) - 1
            out[f"{writer} {comp}"] = med
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    return out


def _lockstep(make, cap, basis, cfg, steps: int, cloud_every: int, compression: str,
              writer: str = "process") -> dict[str, float]:
    """ms per step of the plain and the logged explorer, the logged side as the explore command logs.

    - ``thread_*``: CPU time of the thread that steps the explorers (what the log takes
      from the step itself, whatever else runs on the machine);
    - ``wall_*``: wall time, what a user waits (on a shared machine it also counts the
      time other processes run);
    - ``writer_cpu``: CPU time the log spends outside the stepping thread: the writer child
      (``writer="process"``), which runs beside the step, on another core.
    Opening and closing the log count on the logged side.
    """
    from tergodic_cli.provenance import library_versions
    from tergodic_cli.runlog.background import BackgroundRunLog, LogWriterProcess
    from tergodic_cli.run import LogFeed, RunRecorder
    from tergodic_cli.runlog.writer import RunLog

    def proc_cpu(pid: int) -> float:  # utime + stime of a live process (Linux)
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    child = LogWriterProcess() if writer == "process" else None  # as explore does: started before the set-up
    plain_ex, log_ex = make(), make()
    if child:  # its start-up (imports, ~0.3 s CPU once per run) overlaps explore's own; leave it out
        child.wait_ready()
        child_cpu0 = proc_cpu(child.proc.pid)
    tmp = Path(tempfile.mkdtemp(prefix="tergodic-bench-"))
    tcpu, pcpu, wall = time.thread_time, time.process_time, time.perf_counter
    t_plain = t_log = w_plain = w_log = 0.0
    w_fixed = t_fixed = 0.0  # opening and closing the log, a cost per run rather than per step
    p_start, t_start = pcpu(), tcpu()
    try:
        c0, w0 = tcpu(), wall()
        # as explore opens it: with a writer child, Φ comes from the basis cache file, not down the pipe
        kw = {"writer": child, "field_basis_file": basis.meta.get("evecs_file")} if child else {}
        log = (BackgroundRunLog if child else RunLog)(
            tmp / "run.mcap", config=cfg.to_dict(), seed=cfg.seed, versions=library_versions(), capture_sidecar=cap.meta,
            points=basis.points, target=cap.target, cloud_every=cloud_every, compression=compression,
            field_basis=log_ex.evecs, **kw)
        t_fixed += tcpu() - c0
        w_fixed += wall() - w0
        # both sides keep every step in preallocated arrays, as tergodic explore does for
        # trajectory.npz with or without a log (its RunRecorder); the logged side also hands the
        # log a block of rows every flush_every steps, with the cloud every cloud_every steps,
        # through explore's own LogFeed
        rec_plain, rec_log = RunRecorder(plain_ex, steps), RunRecorder(log_ex, steps)
        feed = LogFeed(log, rec_log)
        for k in range(steps):
            c0, w0 = tcpu(), wall()
            plain_ex.step()
            rec_plain.record(k + 1, None)
            c1, w1 = tcpu(), wall()
            log_ex.step()
            rec_log.record(k + 1, None)
            feed.after_step(cloud=(k + 1) % cloud_every == 0 or k + 1 == steps)
            c2, w2 = tcpu(), wall()
            t_plain += c1 - c0
            t_log += c2 - c1
            w_plain += w1 - w0
            w_log += w2 - w1
        child_cpu = proc_cpu(child.proc.pid) - child_cpu0 if child else 0.0  # (misses the final footer)
        # the end of a run as explore does it: both sides write trajectory.npz; the logged side
        # first sends the end of the log, so that its writer finishes the file meanwhile
        start = np.zeros((1, 3))
        c0, w0 = tcpu(), wall()
        rec_plain.write(tmp / "plain.npz", start)
        c1, w1 = tcpu(), wall()
        feed.flush()
        if hasattr(log, "begin_close"):
            log.begin_close({"steps": steps})
        rec_log.write(tmp / "logged.npz", start)
        log.close({"steps": steps})
        c2, w2 = tcpu(), wall()
        t_end_plain, w_end_plain = c1 - c0, w1 - w0  # both sides pay these; the logged side's include the log's
        t_fixed += c2 - c1
        w_fixed += w2 - w1
        other_threads = (pcpu() - p_start) - (tcpu() - t_start)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    k = 1e3 / steps
    return {"thread_plain": (t_plain + t_end_plain) * k, "thread_logged": (t_log + t_fixed) * k,
            "wall_plain": (w_plain + w_end_plain) * k, "wall_logged": (w_log + w_fixed) * k,
            "thread_steps_plain": t_plain * k, "wall_steps_plain": w_plain * k,
            "thread_steps": t_log * k, "wall_steps": w_log * k,
            "open_close_ms": (w_fixed - w_end_plain) * 1e3, "writer_cpu": (other_threads + child_cpu) * k}


def bench_cli(steps: int = 1000, repeats: int = 3) -> dict | None:
    """C: the explore verb end to end, with and without --no-log: CPU seconds of the child process
    (robust to other load on the machine) and wall seconds, medians."""
    import resource

    if not (REPO / "commands" / "explore.py").exists() or not (REFERENCE / "bun270_X.ply").exists():
        return None
    exe = str(Path(sys.executable).with_name("tergodic"))
    work = Path(tempfile.mkdtemp(prefix="tergodic-bench-cli-"))
    env = {**os.environ, "TERGODIC_CACHE_DIR": str(work / "cache")}

    def child_cpu() -> float:
        ru = resource.getrusage(resource.RUSAGE_CHILDREN)
        return ru.ru_utime + ru.ru_stime

    try:
        cap = work / "cap"
        subprocess.run([exe, "capture", "--from", str(REFERENCE / "bun270_X.ply"), "--voxel", "0.003", "--out", str(cap)],
                       check=True, capture_output=True, env=env)
        subprocess.run([exe, "precompute", str(cap), "--nk", "200", "--neighbors", "40"], check=True,
                       capture_output=True, env=env)
        base = [exe, "explore", str(cap), "--robot", "kinematic", "--steps", str(steps), "--neighbors", "40"]
        cpu: dict[str, list[float]] = {"no_log": [], "log": []}
        wall: dict[str, list[float]] = {"no_log": [], "log": []}
        for r in range(repeats):
            for key, extra in (("no_log", ["--no-log"]), ("log", [])):
                out = work / f"run_{key}_{r}"
                c0, t0 = child_cpu(), time.perf_counter()
                proc = subprocess.run(base + ["--out", str(out)] + extra, capture_output=True, text=True, env=env)
                wall[key].append(time.perf_counter() - t0)
                cpu[key].append(child_cpu() - c0)
                if proc.returncode != 0:
                    return {"error": (proc.stderr or proc.stdout).strip().splitlines()[-1:]}
        m = {k: float(np.median(v)) for k, v in cpu.items()}
        w = {k: float(np.median(v)) for k, v in wall.items()}
        return {"cpu_no_log_s": m["no_log"], "cpu_log_s": m["log"], "cpu_overhead": m["log"] / m["no_log"] - 1.0,
                "wall_no_log_s": w["no_log"], "wall_log_s": w["log"], "wall_overhead": w["log"] / w["no_log"] - 1.0}
    finally:
        shutil.rmtree(work, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats (development)")
    ap.add_argument("--skip-cli", action="store_true", help="skip the end-to-end CLI measurement")
    args = ap.parse_args()
    reps = 2 if args.quick else 5

    print("A. RunLog alone (2996 points, 1 agent, cloud every 50 steps, 1000 steps)")
    for backend in ("foxglove-sdk", "mcap-python"):
        r = bench_runlog(repeats=reps, backend=backend)
        print(f"   {backend:<13}: {r['cpu_us']:6.1f} µs/step CPU, {r['caller_us']:6.1f} µs/step wall in the loop, "
              f"{r['total_us']:6.1f} µs/step wall incl. open+close; "
              f"file {r['file_bytes'] / 1e6:.2f} MB")
    r = bench_runlog(repeats=reps, n_agents=10)
    print(f"   10 agents    : {r['cpu_us']:6.1f} µs/step CPU, {r['caller_us']:6.1f} µs/step wall in the loop")
    r = bench_runlog(repeats=reps, writer="process")
    print(f"   writer child : {r['cpu_us']:6.1f} µs/step CPU, {r['caller_us']:6.1f} µs/step wall in the caller's loop "
          f"(log_step each step), {r['total_us']:6.1f} µs/step wall incl. open + waiting for the child at close")

    r = bench_explorer(repeats=max(1, reps // 2 + 1))
    if r is None:
        print("B. skipped (no reference bunny or no explorer)")
    else:
        print(f"B. kinematic explorer on the reference bunny ({r['n_points']} points, nK 200, 1000 steps, lockstep)")
        for key in (k for k in r if k != "n_points"):
            c = r[key]
            print(f"   {key:<12}: per step {c['wall_steps_plain']:.4f} ms plain, {c['wall_steps']:.4f} logged "
                  f"-> {100 * c['wall_steps_overhead']:+.1f} % wall, {100 * c['thread_steps_overhead']:+.1f} % "
                  f"stepping-thread CPU (budget 10 %)")
            print(f"   {'':<12}  whole run (open, steps, end with trajectory.npz): wall {c['wall_plain']:.4f} / "
                  f"{c['wall_logged']:.4f} ms per step -> {100 * c['wall_overhead']:+.1f} %, thread CPU "
                  f"{100 * c['thread_overhead']:+.1f} %; the log's open + close wait {c['open_close_ms']:.1f} ms; "
                  f"writer CPU beside it {c['writer_cpu']:.4f} ms/step")
    if args.skip_cli:
        return
    r = bench_cli(repeats=max(1, reps // 2 + 1))
    if r is None:
        print("C. skipped (no explore verb yet, or no reference bunny)")
    elif "error" in r:
        print(f"C. explore failed: {r['error']}")
    else:
        print(f"C. tergodic explore on the reference bunny, 1000 steps, whole process (imports, basis load, "
              f"trajectory.npz included):")
        print(f"   CPU : {r['cpu_no_log_s']:.2f} s with --no-log, {r['cpu_log_s']:.2f} s with the log "
              f"-> overhead {100 * r['cpu_overhead']:+.1f} %")
        print(f"   wall: {r['wall_no_log_s']:.2f} s with --no-log, {r['wall_log_s']:.2f} s with the log "
              f"-> overhead {100 * r['wall_overhead']:+.1f} %")


if __name__ == "__main__":
    main()
