"""Benchmark of ``tergodic explore --robot pybullet``: one table of the issue 15 goals per object.

Usage (a few minutes with the defaults; the full run of docs/robot.md uses --steps 1000):
    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/robot.py [--steps 300]
        [--objects bowl,plate,mug,box,torus,partial,thin-mug] [--force 5] [--seed 0] [--seeds 3]
        [--gains tuned|paper] [--json out.json]

For each built-in synthetic object (the box is the shape with sharp edges and vertical walls) it
runs the robot (PyBullet, DIRECT, 1 kHz torque control) for ``--steps`` explorer steps at
``--force`` newtons from ``--seeds`` seeded starts, and the kinematic explorer with the same
(time-scaled) config from the same start for the same number of steps, on the target the robot
explored (the part the tool cannot follow dropped, as the robot run does) and on the whole target.
Figures per object (goals checked on the worst seed, the ε ratio on the median over the seeds):

- force RMS error (1 kHz ticks in steady contact) and the 1 kHz peak (goal on the approach peak,
  <= 1.5 x F_d);
- tilt (tool axis to the surface normal) median and 95th percentile; tracking median (contact
  point to the agent line); contact share of the explore samples;
- ε of the sponge path / ε of the kinematic agent: the unit-mass score of issue 13
  (:func:`tergodic_cli.explore.metrics.coverage_score`) of the sponge's contact points at every
  explorer step in contact against the kinematic agent's positions, same r_a, both scored on the
  target the robot explored; beside it the same ratio against the kinematic agent on the whole
  target, both scored on the whole target (nothing hidden: the dropped part counts as missed);
- real-time factor, normalised to the reference machine: the goal is checked on simulated seconds
  per CPU second of the run × 36 000 / the bare PyBullet torque-stepping rate measured in this
  process just before (which removes most of the load other processes put on shared cores). The
  measured wall-clock figure is printed beside it.
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

#: Bare PyBullet torque stepping of the stock Panda on the reference 2-core machine, idle (issue 4).
REFERENCE_BARE_STEPS_PER_S = 36000.0
#: (figure, label, format, goal (op, value) or None). "F_d" in a goal scales by the desired force.
ROWS = (
    ("steps_done", "explorer steps done", "{:d}", ("==", "steps")),
    ("force_rms_error_rel", "force RMS error", "{:.1%}", ("<=", 0.10)),
    ("force_peak_N", "force peak, 1 kHz (N)", "{:.1f}", None),
    ("force_peak_approach_N", "  during approach (N)", "{:.1f}", ("<=", "1.5 F_d")),
    ("tilt_deg_median", "tilt median (deg)", "{:.1f}", ("<=", 5.0)),
    ("tilt_deg_p95", "tilt 95th pct (deg)", "{:.1f}", None),
    ("track_mm_median", "tracking median (mm)", "{:.1f}", ("<=", 2.0)),
    ("contact_fraction", "contact share", "{:.1%}", (">=", 0.95)),
    ("eps_ratio", "ε sponge / ε kinematic", "{:.2f}", ("<=", 1.1)),
    ("eps_ratio_whole", "  kinematic on the whole target", "{:.2f}", None),
    ("arm_contacts", "arm contacts (whole-arm checks)", "{:d}", ("<=", 0)),
    ("realtime_factor_normalised", "real-time factor (normalised)", "{:.0f}x", (">=", 10.0)),
    ("realtime_factor", "  measured, wall clock", "{:.0f}x", None),
)


def bare_pybullet_rate(n: int = 3000) -> float:
    """Steps per CPU second of the reference loop: stock Panda, gravity-compensating torque control, no contact."""
    import pybullet as p
    import pybullet_data

    cid = p.connect(p.DIRECT)
    try:
        p.setGravity(0, 0, -9.81, physicsClientId=cid)
        r = p.loadURDF(os.path.join(pybullet_data.getDataPath(), "franka_panda/panda.urdf"), useFixedBase=True,
                       physicsClientId=cid)
        arm = list(range(7))
        for j, q in zip(arm, (0, -0.785, 0, -2.356, 0, 1.571, 0.785)):
            p.resetJointState(r, j, q, physicsClientId=cid)
        p.setJointMotorControlArray(r, arm, p.VELOCITY_CONTROL, forces=[0] * 7, physicsClientId=cid)
        movable = [0, 1, 2, 3, 4, 5, 6, 9, 10]
        zero = [0.0] * 9
        t0 = time.process_time()
        for _ in range(n):
            s = p.getJointStates(r, movable, physicsClientId=cid)
            tau = p.calculateInverseDynamics(r, [x[0] for x in s], [x[1] for x in s], zero, physicsClientId=cid)
            p.setJointMotorControlArray(r, arm, p.TORQUE_CONTROL, forces=tau[:7], physicsClientId=cid)
            p.stepSimulation(physicsClientId=cid)
        return n / (time.process_time() - t0)
    finally:
        p.disconnect(cid)


def sponge_path(samples: list[dict]) -> np.ndarray:
    """The sponge's contact points (m, 3) in the object (capture) frame, one per explorer step in contact."""
    from tergodic_cli.rotations import quat_to_matrix

    out = []
    for s in samples:
        if s.get("in_contact") and s.get("contact_point") is not None:
            pose = np.asarray(s["object_pose"], dtype=float)
            out.append((np.asarray(s["contact_point"], dtype=float) - pose[:3]) @ quat_to_matrix(pose[3:]))
    return np.array(out).reshape(-1, 3)


def kinematic_path(basis, target: np.ndarray, cfg, start: np.ndarray, steps: int) -> np.ndarray:
    """The kinematic explorer's own path (steps, 3) on ``target`` from ``start``."""
    from tergodic_cli.explore import Explorer

    kin = Explorer(basis, target, cfg, start, on_event=lambda m: None)
    path = []
    for _ in range(steps):
        kin.step()
        path.append(np.array(kin.positions[0], dtype=float))
    return np.array(path)


def run_one(obj: str, steps: int, seed: int, force: float, nk: int, cache: str, gains: str = "tuned") -> dict:
    from tergodic_cli.basis import BasisConfig, get_basis
    from tergodic_cli.capture import CaptureConfig, capture_cloud
    from tergodic_cli.capture.filters import mean_spacing
    from tergodic_cli.errors import TergodicError
    from tergodic_cli.explore import ExploreConfig, Explorer
    from tergodic_cli.explore.metrics import coverage_score
    from tergodic_cli.backends.pybullet import explore_with_robot
    from tergodic_cli.robot import PAPER_GAINS, RobotConfig, robot_explore_config

    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic=obj, seed=0), on_event=lambda m: None)
    basis, _ = get_basis(cap.points, BasisConfig(nk=nk, neighbors=30), cache_dir=cache)
    start = cap.points[np.random.default_rng(seed).integers(len(cap.points))][None]
    rcfg = RobotConfig(force=force, **({"gains": PAPER_GAINS} if gains == "paper" else {}))
    cfg = robot_explore_config(ExploreConfig(nk=nk, seed=seed), rcfg.explore_dt)
    bare = bare_pybullet_rate()
    ex = Explorer(basis, cap.target, cfg, start, on_event=lambda m: None)
    samples: list[dict] = []
    agent: list[np.ndarray] = []  # the virtual agent's own path (before each reset to the tool tip)
    on_step = lambda k, s: (samples.append(s), agent.append(np.array(ex.positions[0], dtype=float)))  # noqa: E731
    t0 = time.perf_counter()
    try:
        out = explore_with_robot(cap, ex, rcfg, steps, on_step=on_step)
    except TergodicError as exc:  # refused before any motion (bad input, nothing reachable): a row that says so
        return {"object": obj, "seed": seed, "steps": steps, "force_N": force, "steps_done": 0,
                "stop_reason": f"refused: {exc}", "bare_steps_per_s": bare,
                **dict.fromkeys(("eps_sponge", "eps_kinematic", "eps_sponge_whole", "eps_kinematic_whole"), float("nan"))}
    wall = time.perf_counter() - t0
    h = mean_spacing(cap.points)
    reach = np.asarray(ex.p, dtype=float)  # the target the robot explored: the unreachable part dropped

    def eps(path, target) -> float:
        return coverage_score(cap.points, target, path, ex.r_a, h)["ergodicity"] if len(path) else 1.0

    # Kinematic references from the same start, on the target the robot explored and on the whole one.
    kin, kin_whole = (kinematic_path(basis, t, cfg, start, steps) for t in (reach, cap.target))
    sponge, agent_path = sponge_path(samples), np.array(agent).reshape(-1, 3)
    e = {"eps_sponge": eps(sponge, reach), "eps_kinematic": eps(kin, reach), "eps_agent": eps(agent_path, reach),
         "eps_sponge_whole": eps(sponge, cap.target), "eps_kinematic_whole": eps(kin_whole, cap.target),
         "eps_kinematic_reach_whole": eps(kin, cap.target), "eps_agent_whole": eps(agent_path, cap.target)}
    return {
        "object": obj, "seed": seed, "steps": steps, "force_N": force, "steps_done": len(samples),
        **{k: out.get(k) for k in ("force_rms_error_rel", "force_peak_N", "force_peak_approach_N", "tilt_deg_median",
                                    "tilt_deg_p95", "track_mm_median", "contact_fraction", "realtime_factor",
                                    "stop_reason", "force_rms_error_rel_5hz", "force_peak_5hz_N", "move_overs")},
        **e, "target_dropped": 1.0 - float(reach.sum()) / float(np.sum(cap.target)),
        "arm_contacts": int((out.get("arm_contacts") or {}).get("count", 0)),
        "eps_ratio": e["eps_sponge"] / e["eps_kinematic"] if e["eps_kinematic"] > 0 else None,
        "eps_ratio_whole": e["eps_sponge_whole"] / e["eps_kinematic_whole"] if e["eps_kinematic_whole"] > 0 else None,
        "realtime_factor_normalised": out["sim_seconds"] / out["cpu_seconds"] * REFERENCE_BARE_STEPS_PER_S / bare,
        "bare_steps_per_s": bare, "sim_s": out["sim_seconds"], "wall_s_run": wall,
    }


def combine(rows: list[dict]) -> dict:
    """One object's seeds in one row: the ε ratios as their median, every figure with a goal at its worst
    seed (the goals must hold on every start), the rest as their median."""
    out = dict(rows[0], seeds=[r["seed"] for r in rows])
    for key, _, _, goal in ROWS + (("eps_sponge", 0, 0, None), ("eps_kinematic", 0, 0, None),
                                   ("eps_sponge_whole", 0, 0, None), ("eps_kinematic_whole", 0, 0, None)):
        v = [r[key] for r in rows if r.get(key) is not None]
        if not v:
            continue
        worst = (max if goal[0] == "<=" else min) if goal and not key.startswith("eps") else None
        out[key] = worst(v) if worst else type(v[0])(np.median(v))
    out["stop_reason"] = "; ".join(sorted({str(r["stop_reason"]) for r in rows}))
    return out


def table(rows: list[dict]) -> str:
    """The markdown table: one column per object, the goal and met/missed beside each figure."""
    objs = [r["object"] for r in rows]
    lines = ["| figure | goal | " + " | ".join(objs) + " |", "|---|---|" + "---|" * len(objs)]
    for key, label, fmt, goal in ROWS:
        cells = []
        for r in rows:
            v = r.get(key)
            if v is None:
                cells.append("n/a")
                continue
            cell = fmt.format(v)
            if goal is not None:
                op, target = goal
                target = {"1.5 F_d": 1.5 * r["force_N"], "steps": r["steps"]}.get(target, target)
                ok = v <= target if op == "<=" else (v >= target if op == ">=" else v == target)
                cell += " met" if ok else " MISSED"
            cells.append(cell)
        g = f"{goal[0]} {goal[1]:.0%}" if goal and key in ("force_rms_error_rel", "contact_fraction") else \
            (f"{goal[0]} {goal[1]}" if goal else "")
        g = g.replace("== steps", f"= {rows[0]['steps']}") if rows else g
        lines.append(f"| {label} | {g} | " + " | ".join(cells) + " |")
    lines.append("| ε sponge, ε kinematic | | " + " | ".join(f"{r['eps_sponge']:.3f}, {r['eps_kinematic']:.3f}"
                                                         for r in rows) + " |")
    lines.append("| same, whole target | | " + " | ".join(
        f"{r['eps_sponge_whole']:.3f}, {r['eps_kinematic_whole']:.3f}" for r in rows) + " |")
    lines.append("| stop | | " + " | ".join(str(r["stop_reason"]) for r in rows) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=300, help="explorer steps per object (0.2 s each) [default: 300]")
    ap.add_argument("--objects", default="bowl,plate,mug,box,torus,partial,thin-mug",
                    help="synthetic objects [default: bowl,plate,mug,box,torus,partial,thin-mug]")
    ap.add_argument("--force", type=float, default=5.0, help="desired force, N [default: 5]")
    ap.add_argument("--seed", type=int, default=0, help="the first start's seed [default: 0]")
    ap.add_argument("--seeds", type=int, default=3, help="random starts per object, seeds --seed.. [default: 3]")
    ap.add_argument("--nk", type=int, default=200)
    ap.add_argument("--json", default=None, help="write every row to this JSON file")
    ap.add_argument("--gains", choices=("tuned", "paper"), default="tuned", help="the tuned gains or the paper's (V-A3)")
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as cache:
        for obj in args.objects.split(","):
            for seed in range(args.seed, args.seed + args.seeds):
                rows.append(run_one(obj, args.steps, seed, args.force, args.nk, cache, args.gains))
                print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in rows[-1].items()}),
                      file=sys.stderr, flush=True)
    seeds = f"seeds {args.seed}-{args.seed + args.seeds - 1}" if args.seeds > 1 else f"seed {args.seed}"
    print(f"{args.steps} explorer steps at {args.force:g} N, {seeds} (ε ratios: median; goals: worst seed); "
          f"bare PyBullet now {np.median([r['bare_steps_per_s'] for r in rows]):.0f} steps per CPU second "
          f"(reference {REFERENCE_BARE_STEPS_PER_S:.0f})\n")
    print(table([combine([r for r in rows if r["object"] == o]) for o in dict.fromkeys(r["object"] for r in rows)]))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
