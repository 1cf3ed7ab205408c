"""Cost of the MCAP run log, per step and on a whole ``tergodic explore`` process.

A. RunLog alone, on synthetic step data of the reference bunny's size (2996 points, a cloud
   every 50 steps, 1000 steps): CPU and wall microseconds per step, and the file's size.
B. ``tergodic explore data/bowl --steps 1000 --out RUN`` (kinematic) end to end, logged and with
   ``--no-log``, in interleaved rounds: wall and CPU seconds of the whole process, medians and
   their ratio. ``--baseline DIR`` adds the same command run from another checkout (``DIR``, e.g. a
   ``git worktree`` of an older commit with ``DIR/tergodic_cli/commands`` linked to ``../commands``),
   and ``--baseline-env K=V`` a second baseline variant with that environment (e.g.
   ``TERGODIC_LOG_WRITER=inline``), so writers are compared in the same run.

Run:  OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/logging.py [--rounds 7]
"""

from __future__ import annotations

import _env  # noqa: F401,I001  (first: path fix, one BLAS thread; see benchmarks/_env.py)

import argparse  # noqa: E402
import os  # noqa: E402
import resource  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def bench_runlog(n_points: int = 2996, steps: int = 1000, n_agents: int = 1, repeats: int = 5,
                 cloud_every: int = 50) -> dict:
    """A: RunLog per step (µs, medians over ``repeats``): CPU and wall of the loop, wall incl. open and close."""
    from tergodic_cli.runlog import RunLog

    rng = np.random.default_rng(0)
    pts = rng.standard_normal((n_points, 3)) * 0.04
    P, V, N = (rng.standard_normal((steps, n_agents, 3)) * s for s in (0.04, 3e-3, 1.0))
    field = rng.random((3, n_points))
    cpu, loop, total, size = [], [], [], 0
    for _ in range(repeats):
        tmp = Path(tempfile.mkdtemp(prefix="tergodic-bench-"))
        try:
            t0 = time.perf_counter()
            log = RunLog(tmp / "run.mcap", config={"steps": steps}, seed=0, versions={}, points=pts,
                         target=(field[0] > 0.9) * 1.0, cloud_every=cloud_every)
            t1, c1 = time.perf_counter(), time.process_time()
            for k in range(steps):
                log.log_step(k + 1, float(k + 1), positions=P[k], velocities=V[k], normals=N[k],
                             metrics={"ergodicity": 0.1 + k * 1e-5, "residual_ref": 0.2, "touched_fraction": k / steps},
                             step_ms=0.9)
                if (k + 1) % cloud_every == 0:
                    log.log_cloud(k + 1, coverage=field[0], heat=field[1], source=field[2])
            t2, c2 = time.perf_counter(), time.process_time()
            log.close({"steps": steps})
            t3 = time.perf_counter()
            size = (tmp / "run.mcap").stat().st_size
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        cpu.append((c2 - c1) / steps * 1e6)
        loop.append((t2 - t1) / steps * 1e6)
        total.append((t3 - t0) / steps * 1e6)
    return {"cpu_us": float(np.median(cpu)), "loop_us": float(np.median(loop)), "total_us": float(np.median(total)),
            "file_bytes": size}


def bench_cli(variants: dict[str, tuple[Path, list[str], dict[str, str]]], rounds: int, steps: int = 1000) -> dict:
    """B: each variant ``name: (checkout, extra args, extra env)`` run ``rounds`` times, interleaved.

    Returns ``{name: {"wall": [s...], "cpu": [s...]}}``: wall and CPU (user + system, of the process and
    its children) seconds of each whole ``tergodic explore data/bowl --steps N`` process.
    """
    work = Path(tempfile.mkdtemp(prefix="tergodic-bench-cli-"))
    env0 = {**os.environ, "TERGODIC_NO_PROGRESS": "1", "TERGODIC_CACHE_DIR": str(work / "cache")}
    res = {name: {"wall": [], "cpu": []} for name in variants}
    try:
        for r in range(-1, rounds):  # round -1 warms the basis cache (and numba's, per checkout)
            for name, (checkout, args, env) in variants.items():
                out = work / f"run-{name}"
                shutil.rmtree(out, ignore_errors=True)
                e = {**env0, **env}
                if checkout != REPO:
                    e["PYTHONPATH"] = str(checkout)  # found before the editable install of this one
                before = resource.getrusage(resource.RUSAGE_CHILDREN)
                t0 = time.perf_counter()
                subprocess.run([sys.executable, "-m", "tergodic_cli", "explore", str(REPO / "data" / "bowl"), "--steps",
                                str(steps), "--out", str(out), *args], cwd=checkout, env=e, check=True,
                               capture_output=True)
                wall = time.perf_counter() - t0
                after = resource.getrusage(resource.RUSAGE_CHILDREN)
                if r >= 0:
                    res[name]["wall"].append(wall)
                    res[name]["cpu"].append(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=7, help="interleaved rounds of B (medians over them)")
    ap.add_argument("--baseline", type=Path, help="another checkout to time beside this one in B")
    ap.add_argument("--baseline-env", action="append", default=[], metavar="K=V",
                    help="also time the baseline with this environment variable (repeatable)")
    ap.add_argument("--skip-cli", action="store_true", help="skip B")
    args = ap.parse_args()

    print("A. RunLog alone (2996 points, cloud every 50 steps, 1000 steps), medians of 5")
    for n_agents in (1, 10):
        r = bench_runlog(n_agents=n_agents)
        print(f"   {n_agents:2d} agent(s): {r['cpu_us']:6.1f} µs/step CPU, {r['loop_us']:6.1f} µs/step wall in the loop, "
              f"{r['total_us']:6.1f} µs/step wall incl. open + close; file {r['file_bytes'] / 1e6:.2f} MB")
    if args.skip_cli:
        return
    variants = {"log": (REPO, [], {}), "no-log": (REPO, ["--no-log"], {})}
    if args.baseline is not None:
        variants["baseline"] = (args.baseline.resolve(), [], {})
        if args.baseline_env:
            variants["baseline+env"] = (args.baseline.resolve(), [], dict(kv.split("=", 1) for kv in args.baseline_env))
    res = bench_cli(variants, args.rounds)
    med = {name: {k: float(np.median(v)) for k, v in d.items()} for name, d in res.items()}
    print(f"B. tergodic explore data/bowl --steps 1000, whole process, medians of {args.rounds} interleaved rounds")
    for name, m in med.items():
        print(f"   {name:<13} wall {m['wall']:.3f} s   CPU {m['cpu']:.3f} s   "
              f"(walls {' '.join(f'{x:.2f}' for x in res[name]['wall'])})")
    for name in med:
        if name != "no-log":
            print(f"   {name} / no-log: wall {med[name]['wall'] / med['no-log']['wall']:.3f}x, "
                  f"CPU {med[name]['cpu'] / med['no-log']['cpu']:.3f}x")
    for name in ("baseline", "baseline+env"):
        if name in med:
            print(f"   log / {name}: wall {med['log']['wall'] / med[name]['wall']:.3f}x, "
                  f"CPU {med['log']['cpu'] / med[name]['cpu']:.3f}x")


if __name__ == "__main__":
    main()
