"""Benchmark of the closed outer loop in simulation (issue 6 item 3): clean the built-in bowl's X.

Usage:
    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/cleaning.py
        [--recapture-every 50,200] [--until-clean 0.05] [--max-steps 1000] [--seeds 1]
        [--renderer tiny] [--width 640 --height 480] [--object-pose 0.5,0,0.2] [--png cleaning.png] [--json out.json]

The scene: ``tergodic capture --source sim --object bowl --marking X`` (512² texture, the default
640x480 camera, TinyRenderer), the bowl on a 20 cm stand (``--object-pose 0.5,0,0.2``; on the table,
z = 0, the far wall of the bowl is out of the Panda's wrist range, docs/closed_loop.md). nK = 200,
5 N, the robot's default time scaling (0.2 s per explorer step), a random start on the cloud (seed).
For each K in ``--recapture-every`` it runs :func:`clean_with_robot` until the camera sees at most
``--until-clean`` of the initial marking or ``--max-steps`` are spent, and checks the goals:

    marking removed (camera) >= 95 % within the budget     each re-capture <= 200 ms (median and max)
    the basis is never recomputed (every re-capture is a cache hit)
    "clean" means clean: the true ink left <= --until-clean + 3 points (the texture's own accounting)

It prints one row per re-capture (the remaining share against steps) and writes a PNG of it
(camera-seen and true ink share). Times are wall clock on a shared machine; CPU times beside them.
"""

from __future__ import annotations

import _env  # noqa: F401,I001  (first: path fix, one BLAS thread; see benchmarks/_env.py)

import os
import sys

import argparse  # noqa: E402
import json  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

RECAPTURE_MS_GOAL = 200.0
TRUE_INK_MARGIN = 0.03  # issue 15: when the loop says clean, the true ink left is within 3 points of --until-clean
REMOVED_GOAL = 0.95


def run_one(k: int, until: float, budget: int, seed: int, nk: int, cache: str, renderer: str, width: int, height: int,
            pose: tuple) -> dict:
    from tergodic_cli.basis import BasisConfig, get_basis
    from tergodic_cli.backends.pybullet.camera import SimCamera, SimCameraConfig, SimCaptureConfig, capture_sim
    from tergodic_cli.capture.textured import SimObjectConfig, TexturedObject
    from tergodic_cli.explore import ExploreConfig, Explorer
    from tergodic_cli.backends.pybullet import CleaningLoopConfig, clean_with_robot
    from tergodic_cli.robot import RobotConfig, robot_explore_config

    obj_cfg = SimObjectConfig(object="bowl", marking="X", pose=pose)
    cam = SimCamera(SimCameraConfig(renderer=renderer, width=width, height=height), TexturedObject(obj_cfg))
    try:
        t0 = time.perf_counter()
        cap = capture_sim(SimCaptureConfig(object=obj_cfg, camera=cam.cfg), camera=cam)
        capture_s = time.perf_counter() - t0
        basis, hit = get_basis(cap.points, BasisConfig(nk=nk, neighbors=30), cache_dir=cache)
        rcfg = RobotConfig(force=5.0)
        ec = robot_explore_config(ExploreConfig(nk=nk, seed=seed), rcfg.explore_dt)
        start = cap.points[np.random.default_rng(seed).integers(len(cap.points))][None]
        ex = Explorer(basis, cap.target, ec, start, on_event=lambda m: None)
        t0 = time.perf_counter()
        cpu0 = time.process_time()
        out = clean_with_robot(cap, ex, rcfg, camera=cam,
                               loop_cfg=CleaningLoopConfig(recapture_every=k, until_clean=until, max_steps=budget))
        wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    finally:
        cam.close()
    log = out["recapture_log"]
    return {
        "recapture_every": k, "seed": seed, "points": int(cap.n_points), "target_points": int(np.count_nonzero(cap.target)),
        "renderer": cam.renderer, "image": f"{width}x{height}", "capture_s": capture_s, "basis_cached_before": hit,
        "clean_reached": out["clean_reached"], "steps_done": out["steps_done"],
        "marking_remaining": out["marking_remaining"], "marking_removed": 1.0 - out["marking_remaining"],
        "marking_remaining_true": out["marking_remaining_true"], "recaptures": out["recaptures"],
        "recapture_ms_median": out["recapture_ms_median"], "recapture_ms_max": out["recapture_ms_max"],
        "recapture_cpu_ms_median": out["recapture_cpu_ms_median"],
        "recapture_parts_ms_median": {part: float(np.median([r[part] for r in log]))
                                      for part in ("texture_ms", "render_ms", "pipeline_ms", "transfer_ms", "key_ms")},
        "basis_cache_hits": out["basis_cache_hits"], "basis_recomputed": out["basis_recomputed"],
        "force_rms_error_rel": out["force_rms_error_rel"], "tilt_deg_median": out["tilt_deg_median"],
        "track_mm_median": out["track_mm_median"], "contact_fraction": out["contact_fraction"],
        "realtime_factor": out["realtime_factor"], "realtime_factor_overall": out["realtime_factor_overall"],
        "sim_s": out["sim_seconds"], "wall_s": wall, "cpu_s": cpu, "cleaning_ms_total": out["cleaning_ms_total"],
        "stop_reason": out["stop_reason"], "loop_stop": out["loop_stop"],
        "curve": [[0, 1.0, 1.0]] + [[r["step"], r["marking_remaining"], r["marking_remaining_true"]] for r in log],
    }


def plot(rows: list[dict], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for i, r in enumerate(rows):
        c = np.array(r["curve"])
        lab = f"K = {r['recapture_every']}, seed {r['seed']}"
        ax.plot(c[:, 0], 100 * c[:, 1], "o-", color=f"C{i}", label=f"{lab}: camera")
        ax.plot(c[:, 0], 100 * c[:, 2], "s--", color=f"C{i}", ms=3, alpha=0.6, label=f"{lab}: ink (true)")
    ax.axhline(100 * (1 - REMOVED_GOAL), color="k", lw=0.8, ls=":", label="goal: 5 % left")
    ax.set_xlabel("explorer step (0.2 s each)")
    ax.set_ylabel("marking left (% of the initial)")
    ax.set_title("Closed-loop cleaning of the bowl's X (PyBullet, 5 N)")
    ax.set_ylim(0, 105)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recapture-every", default="50,200")
    ap.add_argument("--until-clean", type=float, default=0.05)
    ap.add_argument("--max-steps", type=int, default=1000)
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--nk", type=int, default=200)
    ap.add_argument("--renderer", default="tiny")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--object-pose", default="0.5,0,0.2")
    ap.add_argument("--png", default="cleaning.png")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    pose = tuple(float(v) for v in args.object_pose.split(","))
    rows = []
    with tempfile.TemporaryDirectory() as cache:
        for k in (int(v) for v in args.recapture_every.split(",")):
            for seed in range(args.seeds):
                r = run_one(k, args.until_clean, args.max_steps, seed, args.nk, cache, args.renderer, args.width,
                            args.height, pose)
                rows.append(r)
                print(json.dumps({kk: (round(v, 4) if isinstance(v, float) else v) for kk, v in r.items() if kk != "curve"}),
                      flush=True)
    print("\nremaining share against steps (camera | true ink)")
    for r in rows:
        print(f"K = {r['recapture_every']}, seed {r['seed']}: "
              + "  ".join(f"{s}: {100 * a:.1f}|{100 * b:.1f}%" for s, a, b in r["curve"]))
    ok_all = True
    print(f"\n{'K':>4} {'seed':>4} {'goal':<34} {'value':>10} {'target':>12}  verdict")
    for r in rows:
        checks = [
            (f"marking removed within {args.max_steps} steps", r["marking_removed"], f">= {REMOVED_GOAL}",
             r["marking_removed"] >= REMOVED_GOAL),
            ("steps used", r["steps_done"], f"<= {args.max_steps}", r["clean_reached"]),
            ("true ink left", r["marking_remaining_true"], f"<= {args.until_clean + TRUE_INK_MARGIN:.3f}",
             r["marking_remaining_true"] <= args.until_clean + TRUE_INK_MARGIN),
            ("recapture_ms_median (wall)", r["recapture_ms_median"], f"<= {RECAPTURE_MS_GOAL:g}",
             r["recapture_ms_median"] <= RECAPTURE_MS_GOAL),
            ("recapture_ms_max (wall)", r["recapture_ms_max"], f"<= {RECAPTURE_MS_GOAL:g}",
             r["recapture_ms_max"] <= RECAPTURE_MS_GOAL),
            ("basis cache hits / recaptures", f"{r['basis_cache_hits']}/{r['recaptures']}", "all",
             r["basis_cache_hits"] == r["recaptures"] and not r["basis_recomputed"]),
        ]
        for name, value, target, ok in checks:
            ok_all &= bool(ok)
            v = f"{value:.3f}" if isinstance(value, float) else str(value)
            print(f"{r['recapture_every']:>4} {r['seed']:>4} {name:<34} {v:>10} {target:>12}  {'PASS' if ok else 'FAIL'}")
        print(f"{'':>9} recapture cpu ms median {r['recapture_cpu_ms_median']:.0f}; parts (ms) "
              + ", ".join(f"{k[:-3]} {v:.0f}" for k, v in r["recapture_parts_ms_median"].items())
              + f"; true ink left {100 * r['marking_remaining_true']:.1f} %; RTF {r['realtime_factor']:.2f}")
    if args.png:
        plot(rows, args.png)
        print(f"\nwrote {args.png}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2)
    return 0 if ok_all else 1


if __name__ == "__main__":
    sys.exit(main())
