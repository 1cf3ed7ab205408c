"""The contact force's 1 kHz jitter, and how often ordinary runs stop on the force limit.

Usage (one process per call; a few minutes per object and force at 300 steps):
    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/force_jitter.py \
        [--objects bowl,plate,mug,thin-mug,torus] [--forces 2,5,10] [--seeds 3] [--steps 300] \
        [--traces DIR] [--json out.json]

For each built-in synthetic object, desired force and seed it runs the simulated robot
(``explore_with_robot``, the CLI's path) and records the contact force |f| the safety guard sees at
every 1 kHz tick of the explore phase (a wrapper around the compiled tick). It prints, per run,
whether the run completed its steps or why it stopped, and per object and force:

- the raw tick peak over F_d and the ticks above 2 F_d;
- how long the excursions above 1.5 F_d last (ticks in a row: single-tick spikes or sustained);
- the jitter's spectrum (Welch, detrended |f| in steady contact): the share of its power above
  5, 10, 20 and 50 Hz;
- the peak of |f| low-passed (first order, the guard's filter) at 5, 10, 20 and 30 Hz, over F_d;
- where the limit this replaced (raw ticks over 3 F_d, at least 5 N) would have stopped the run: the
  first explore tick over it (its explorer step). The guard does not act on the control until it
  faults, so up to that tick the run is the one the old limit ran.

docs/robot.md ("Force limits") gives the figures this measured and the cutoff chosen from them.
``--traces DIR`` keeps each run's explore-phase force trace as ``OBJ_F_SEED.npz`` (f, N; dt, s).
"""

from __future__ import annotations

import _env  # noqa: F401,I001  (first: path fix, one BLAS thread; see benchmarks/_env.py)

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

CUTOFFS_HZ = (5.0, 10.0, 20.0, 30.0)


def old_limit(force: float) -> float:
    """The force limit before the low-pass: raw ticks over 3 F_d, at least 5 N."""
    return max(3.0 * force, 5.0)
BANDS_HZ = (5.0, 10.0, 20.0, 50.0)


def lowpass_peak(f: np.ndarray, fc: float, dt: float) -> float:
    """Peak of ``f`` through the guard's first-order low-pass at ``fc`` Hz (from the first sample)."""
    from scipy.signal import lfilter

    a = 1.0 - np.exp(-2.0 * np.pi * fc * dt)
    y = lfilter([a], [1.0, a - 1.0], f - f[0]) + f[0]
    return float(y.max()) if len(y) else 0.0


def runs_above(f: np.ndarray, level: float) -> np.ndarray:
    """Lengths (ticks) of the runs of ``f`` above ``level``."""
    above = np.concatenate([[False], f > level, [False]]).astype(np.int8)
    d = np.diff(above)
    return np.flatnonzero(d == -1) - np.flatnonzero(d == 1)


def run_one(obj: str, force: float, seed: int, steps: int, cache: str, nk: int = 200) -> dict:
    from tergodic_cli.backends.pybullet import explore_with_robot
    from tergodic_cli.basis import BasisConfig, get_basis
    from tergodic_cli.capture import CaptureConfig, capture_cloud
    from tergodic_cli.errors import TergodicError
    from tergodic_cli.explore import ExploreConfig, Explorer
    from tergodic_cli.robot import RobotConfig, robot_explore_config
    from tergodic_cli.robot import kernels as Kn
    from tergodic_cli.robot import run as R

    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic=obj, seed=0), on_event=lambda m: None)
    basis, _ = get_basis(cap.points, BasisConfig(nk=nk, neighbors=30), cache_dir=cache)
    start = cap.points[np.random.default_rng(seed).integers(len(cap.points))][None]
    rcfg = RobotConfig(force=force)
    cfg = robot_explore_config(ExploreConfig(nk=nk, seed=seed), rcfg.explore_dt)
    ex = Explorer(basis, cap.target, cfg, start, on_event=lambda m: None)
    trace: list[float] = []
    tick = Kn.pybullet_tick
    runs: list = []
    orig_init = R.ContactRun.__init__

    def init(self, *a, **k):  # the run, to know its state at each tick
        orig_init(self, *a, **k)
        runs.append(self)

    def watched(i, A, D, qs, dqs, reading, bias, *rest):
        code = tick(i, A, D, qs, dqs, reading, bias, *rest)
        if runs and runs[-1].sm.state == "explore":
            w = rest[4][Kn.IO_W:Kn.IO_W + 3]  # io
            trace.append(float(np.sqrt(w @ w)))
        return code

    Kn.pybullet_tick, R.ContactRun.__init__ = watched, init
    n = [0]
    t0 = time.perf_counter()
    try:
        out = explore_with_robot(cap, ex, rcfg, steps, on_step=lambda k, s: n.__setitem__(0, n[0] + 1))
    except TergodicError as exc:
        out = {"stop_reason": f"refused: {exc}"}
    finally:
        Kn.pybullet_tick, R.ContactRun.__init__ = tick, orig_init
    trace = np.asarray(trace)
    over = np.flatnonzero(trace > old_limit(force))
    return {"object": obj, "force_N": force, "seed": seed, "steps": steps, "steps_done": n[0],
            # explore ticks come 200 to an explorer step (explore_dt / physics_dt)
            "old_limit_stop_step": int(over[0] // round(rcfg.explore_dt / rcfg.physics_dt)) + 1 if len(over) else None,
            "completed": out.get("stop_reason") == "completed", "stop_reason": out.get("stop_reason"),
            "force_peak_N": out.get("force_peak_N"), "wall_s": time.perf_counter() - t0,
            "trace": trace, "dt": rcfg.physics_dt}


def jitter(rows: list[dict]) -> dict:
    """Figures of the explore-phase traces of ``rows`` (one object, one force)."""
    from scipy.signal import welch

    fd, dt = rows[0]["force_N"], rows[0]["dt"]
    fs = [r["trace"] for r in rows if len(r["trace"]) > 2000]
    if not fs:
        return {}
    allf = np.concatenate(fs)
    lens = np.concatenate([runs_above(f, 1.5 * fd) for f in fs])
    out = {"ticks": int(len(allf)), "raw_peak_rel": float(allf.max() / fd),
           "ticks_over_2fd": int((allf > 2 * fd).sum()), "ticks_over_3fd": int((allf > 3 * fd).sum()),
           "excursions_over_1p5fd": int(len(lens)), "excursion_ticks_median": float(np.median(lens)) if len(lens) else 0,
           "excursion_ticks_max": int(lens.max()) if len(lens) else 0,
           "excursion_ticks_p99": float(np.percentile(lens, 99)) if len(lens) else 0}
    # Spectrum of the jitter in steady contact (the force within 0.5..2 F_d: contact held).
    P = None
    for f in fs:
        x = f[(f > 0.2 * fd)]
        if len(x) < 4096:
            continue
        freq, p = welch(x - x.mean(), fs=1.0 / dt, nperseg=2048)
        P = p if P is None else P + p
    if P is not None:
        tot = float(P.sum())
        for b in BANDS_HZ:
            out[f"power_above_{b:g}Hz"] = float(P[freq > b].sum() / tot)
    for fc in CUTOFFS_HZ:
        out[f"lp{fc:g}_peak_rel"] = max(lowpass_peak(f, fc, dt) for f in fs) / fd
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", default="bowl,plate,mug,thin-mug,torus")
    ap.add_argument("--forces", default="2,5,10")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--traces", default=None, help="folder for each run's force trace (npz)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as cache:
        for obj in args.objects.split(","):
            for force in (float(x) for x in args.forces.split(",")):
                group = []
                for seed in range(args.seed, args.seed + args.seeds):
                    r = run_one(obj, force, seed, args.steps, cache)
                    group.append(r)
                    if args.traces:
                        os.makedirs(args.traces, exist_ok=True)
                        np.savez(os.path.join(args.traces, f"{obj}_{force:g}_{seed}.npz"), f=r["trace"], dt=r["dt"])
                    print(json.dumps({k: v for k, v in r.items() if k != "trace"}, default=str), flush=True)
                j = jitter(group)
                print(json.dumps({"object": obj, "force_N": force, "jitter": j}), flush=True)
                rows += [{**{k: v for k, v in r.items() if k != "trace"}, "jitter": j} for r in group]
    done = sum(r["completed"] for r in rows)
    print(f"completed {done} of {len(rows)} runs ({100.0 * done / max(len(rows), 1):.0f} %) at {args.steps} steps")
    old = sum(r["completed"] and r["old_limit_stop_step"] is None for r in rows)
    print(f"with the raw 3 F_d limit (before): {old} of {len(rows)} ({100.0 * old / max(len(rows), 1):.0f} %)")
    for r in rows:
        if not r["completed"]:
            print(f"  {r['object']} {r['force_N']:g} N seed {r['seed']}: step {r['steps_done']}: {r['stop_reason']}")
        elif r["old_limit_stop_step"] is not None:
            print(f"  {r['object']} {r['force_N']:g} N seed {r['seed']}: before: stopped at step {r['old_limit_stop_step']}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
