"""Benchmark of ``tergodic explore --robot pybullet``: one table of the issue 15 goals per object.

Usage (a few minutes with the defaults; the full run of docs/robot.md uses --steps 1000):
    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/robot.py [--steps 300]
        [--objects bowl,plate,mug,box,torus,partial,thin-mug] [--force 5] [--seed 0] [--seeds 3]
        [--gains tuned|paper] [--arm panda|xarm6|iiwa] [--json out.json]
    .venv/bin/python benchmarks/robot.py --corpus [tune|check|all] [--objects duck,teddy] [--placements stand,table]
        [--densities 3mm] [--markings patch,band] [--seeds 3] [--steps 1000] [--runs DIR]

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

``--corpus`` runs the household meshes of ``benchmarks/corpus.py`` (objects nobody tuned for) the
way a user would, through ``tergodic explore CAPTURE --robot pybullet`` (exit code and one-line
reason kept), at the default pose ("stand": no ``--object-pose``) and on the table (the mesh's
lowest point on the base plane), and reports per case and in total: the share of runs that
complete, fault stops by reason, the run's own ``arm_contacts`` when its summary has them, an
independent replay of the logged joint states on the stock Panda against the object mesh and the
plane z = 0 (:func:`replay_contacts`: samples with a link more than 1 mm in, the deepest), and ε of
the sponge's logged contact points against the kinematic explorer's from the same start (whole
target). The replay sees what the log holds: today the explorer steps only (set-up moves, approach
and retreat are not logged).
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


def run_one(obj: str, steps: int, seed: int, force: float, nk: int, cache: str, gains: str = "tuned",
            arm: str = "panda") -> dict:
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
    rcfg = RobotConfig(force=force, arm=arm, **({"gains": PAPER_GAINS} if gains == "paper" else {}))
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
        return {"object": obj, "arm": arm, "seed": seed, "steps": steps, "force_N": force, "steps_done": 0,
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
        "object": obj, "arm": arm, "seed": seed, "steps": steps, "force_N": force, "steps_done": len(samples),
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


# ----------------------------------------------------------------------------------- the corpus (issue 24)

#: Links of the stock Panda not checked in the replay: the fingers (the sponge tool replaces the gripper;
#: the simulation keeps them as visuals only). The hand's stock hull is checked: it is arm, not sponge.
REPLAY_SKIP_LINKS = ("panda_leftfinger", "panda_rightfinger", "panda_grasptarget")
#: Contact closer than this (m) counts as a penetration (PyBullet's closest-point margin).
PENETRATION_TOL = 1e-3


def replay_contacts(mcap: str, vertices: np.ndarray, triangles: np.ndarray) -> dict:
    """Replay a run's logged joint states on the stock Panda against the object mesh and the table plane.

    Independent of the run: a separate PyBullet DIRECT client loads pybullet_data's
    ``franka_panda/panda.urdf`` (no sponge), the object as a static concave triangle mesh placed at
    the logged object pose, and a plane at z = 0 (the robot base plane). For every logged sample it
    sets the joints and asks ``getClosestPoints`` for every link except the fingers (link 0 only
    against the object: it stands on the plane).

    Parameters
    ----------
    mcap : path of the run's ``run.mcap``.
    vertices : (n, 3) the object mesh in the capture frame, metres.
    triangles : (k, 3) int.

    Returns
    -------
    dict
        samples, samples_penetrating (any link deeper than PENETRATION_TOL), deepest_mm,
        by_link {link: samples}, deepest_link, table_samples (into the plane), object_samples.
    """
    from tergodic_cli.runlog.reader import read_run_log

    robot = read_run_log(mcap, clouds=False).robot or []  # a run stopped before its first sample has none
    return replay_states([s for s in robot if s.get("q") is not None], vertices, triangles)


def replay_states(rows: list[dict], vertices: np.ndarray, triangles: np.ndarray) -> dict:
    """:func:`replay_contacts` on samples already read: dicts with ``q`` (7,) rad, ``joint_names`` and
    ``object_pose`` (x, y, z, qx, qy, qz, qw) of the capture frame in the robot base frame."""
    import pybullet as p
    import pybullet_data

    from tergodic_cli.rotations import quat_to_matrix

    out = {"samples": len(rows), "samples_penetrating": 0, "deepest_mm": 0.0, "by_link": {}, "deepest_link": None,
           "table_samples": 0, "object_samples": 0}
    if not rows:
        return out
    cid = p.connect(p.DIRECT)
    try:
        arm = p.loadURDF(os.path.join(pybullet_data.getDataPath(), "franka_panda/panda.urdf"), useFixedBase=True,
                         physicsClientId=cid)
        info = [p.getJointInfo(arm, j, physicsClientId=cid) for j in range(p.getNumJoints(arm, physicsClientId=cid))]
        by_name = {i[1].decode(): i[0] for i in info}
        links = {i[12].decode(): i[0] for i in info if i[12].decode() not in REPLAY_SKIP_LINKS}
        links["panda_link0"] = -1  # the base
        pose = np.asarray(rows[0]["object_pose"], dtype=float)
        world = np.asarray(vertices, dtype=float) @ quat_to_matrix(pose[3:]).T + pose[:3]
        shape = p.createCollisionShape(p.GEOM_MESH, vertices=world.tolist(), indices=np.asarray(triangles).ravel().tolist(),
                                       flags=p.GEOM_FORCE_CONCAVE_TRIMESH, physicsClientId=cid)
        obj = p.createMultiBody(0, shape, physicsClientId=cid)
        plane = p.createMultiBody(0, p.createCollisionShape(p.GEOM_PLANE, physicsClientId=cid), physicsClientId=cid)
        names = rows[0].get("joint_names") or [f"panda_joint{i + 1}" for i in range(7)]
        for s in rows:
            for name, q in zip(names, np.asarray(s["q"], dtype=float)):
                p.resetJointState(arm, by_name[name], float(q), physicsClientId=cid)
            hit, hit_obj, hit_table = False, False, False
            for link, index in links.items():
                for body, is_table in ((obj, False), (plane, True)):
                    if is_table and index == -1:
                        continue
                    pts = p.getClosestPoints(arm, body, PENETRATION_TOL, linkIndexA=index, physicsClientId=cid)
                    depth = max((-c[8] for c in pts), default=-np.inf)  # contactDistance < 0: penetration
                    if depth > PENETRATION_TOL:
                        hit = True
                        hit_table |= is_table
                        hit_obj |= not is_table
                        out["by_link"][link] = out["by_link"].get(link, 0) + 1
                        if depth * 1e3 > out["deepest_mm"]:
                            out["deepest_mm"], out["deepest_link"] = depth * 1e3, f"{link} into {'table' if is_table else 'object'}"
            out["samples_penetrating"] += hit
            out["table_samples"] += hit_table
            out["object_samples"] += hit_obj
    finally:
        p.disconnect(cid)
    return out


def _arm_cell(arm: list) -> str:
    """The runs' own ``arm_contacts``: contacts summed over the runs, the deepest one (mm)."""
    if not arm:
        return "not reported"
    count = sum(int(a.get("count", 0)) for a in arm if isinstance(a, dict))
    deepest = max((float(a.get("deepest_mm") or 0.0) for a in arm if isinstance(a, dict)), default=0.0)
    return f"{count} in {len(arm)} runs" + (f", deepest {deepest:.1f} mm" if count else "")


def _reason_key(text: str | None) -> str:
    """A fault reason without its numbers, to count reasons across runs."""
    import re

    if not text:
        return "none"
    return re.sub(r"\s+", " ", re.sub(r"[-+]?\d[\d.,]*(e[-+]?\d+)?", "#", str(text))).strip()[:90]


def corpus_run(case, placement: str, seed: int, steps: int, force: float, out_root: str) -> dict:
    """One corpus case through the CLI as a user runs it, then measured from its files.

    ``tergodic explore CAPTURE --robot pybullet --steps N --seed S --force F [--object-pose TABLE]``;
    the stand placement gives no ``--object-pose`` (the robot stage's default). The row holds the exit
    code and the one-line reason, the run's own summary figures, the replayed contacts
    (:func:`replay_contacts`) and ε of the sponge's logged contact points and of the kinematic explorer
    from the same start with the same config, both scored on the whole target.
    """
    import contextlib
    import io

    from tergodic_cli.capture.filters import mean_spacing
    from tergodic_cli.cli import main as cli
    from tergodic_cli.config import from_dict
    from tergodic_cli.explore import ExploreConfig
    from tergodic_cli.explore.metrics import coverage_score
    from tergodic_cli.run import find_basis
    from tergodic_cli.runlog.reader import read_run_log

    run_dir = os.path.join(out_root, f"{case.name}-{placement}-s{seed}")
    args = ["explore", str(case.capture_dir), "--robot", "pybullet", "--steps", str(steps), "--seed", str(seed),
            "--force", f"{force:g}", "--out", run_dir]
    if placement == "table":
        args += ["--object-pose", case.object_pose("table")]
    err = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = cli(args)
    row = {"case": case.name, "mesh": case.mesh_name, "split": case.split, "placement": placement, "seed": seed,
           "steps": steps, "force_N": force, "exit": code, "wall_s": time.perf_counter() - t0,
           "error": next((ln for ln in err.getvalue().splitlines() if ln.startswith("tergodic:")), None)}
    summary_path = os.path.join(run_dir, "summary.json")
    if not os.path.exists(summary_path):
        return {**row, "completed": False, "stop_reason": row["error"] or f"exit {code}, no run folder",
                "run_folder": False}
    with open(summary_path) as fh:
        sm = json.load(fh)
    row.update(run_folder=True, stop_reason=sm.get("stop_reason"), final_state=sm.get("final_state"),
               steps_done=sm.get("robot_samples"), move_overs=sm.get("move_overs"), object_pose=sm.get("object_pose"),
               force_peak_N=sm.get("force_peak_N"), tilt_deg_p95=sm.get("tilt_deg_p95"),
               arm_contacts_run=sm.get("arm_contacts"), mesh_source=sm.get("mesh_source"))
    row["completed"] = code == 0 and sm.get("stop_reason") == "completed"
    mcap = os.path.join(run_dir, "run.mcap")
    row["replay"] = replay_contacts(mcap, case.vertices, case.triangles) if os.path.exists(mcap) else None
    # ε: the sponge's logged contact points and the kinematic explorer from the same start, same config
    cap = case.capture
    cfg = from_dict(ExploreConfig, sm["config"], "summary config")
    start = np.asarray(sm["starts"]["xyz"], dtype=float)
    basis, _ = find_basis(cap.points, cfg.nk, int(sm["basis"]["neighbors"]))
    data = read_run_log(mcap) if os.path.exists(mcap) else None
    sponge = sponge_path(data.robot) if data is not None and data.robot else np.zeros((0, 3))
    kin = kinematic_path(basis, cap.target, cfg, start, steps)
    h = mean_spacing(cap.points)

    def eps(path, target=cap.target) -> float:
        return coverage_score(cap.points, target, path, cfg.agent_radius, h)["ergodicity"] if len(path) else 1.0

    row.update(eps_sponge=eps(sponge), eps_kinematic=eps(kin), sponge_points=len(sponge))
    row["eps_ratio"] = row["eps_sponge"] / row["eps_kinematic"] if row["eps_kinematic"] > 0 else None
    if data is not None and data.robot and data.clouds:
        row.update(sponge_losses(data, sm, cap, basis, cfg, start, steps, eps))
    return row


def sponge_losses(data, sm: dict, cap, basis, cfg, start: np.ndarray, steps: int, eps) -> dict:
    """Where the sponge loses ε against the kinematic agent, from one run's log (issue 24, item 8).

    - ``target_dropped``: share of the target the robot dropped as out of reach (the kinematic agent
      explores all of it); ``eps_sponge_reach`` / ``eps_kinematic_reach``: both scored on the target the
      robot explored, the kinematic agent run on that target from the same start: ``eps_ratio_reach``.
    - ``eps_agent_reach``: the virtual agent's own logged path (reset to the tool tip every step) on that
      target: sponge → agent is what the tool loses following the agent, agent → kinematic what the
      robot's resets, waits and restarts cost the explorer.
    - per explorer step: ``no_contact_steps`` (samples out of contact), ``lag_mm_median`` / ``lag_mm_p95``
      (the contact point to the agent's logged position), ``wait_steps`` (the contact more than 6 mm from
      the agent: the tool waiting on the reach boundary while the agent moves alone), ``still_steps``
      (the contact point moved less than 0.5 mm over the step: pinned);
    - robot time: ``explore_s`` (in state explore) against ``robot_s`` (all; move-overs are the rest).
    """
    from tergodic_cli.rotations import quat_to_matrix

    target = np.asarray(data.clouds[-1].fields["target"], dtype=float)
    out = {"target_dropped": 1.0 - float(target.sum()) / float(np.sum(cap.target))}
    rows = [s for s in data.robot if s.get("state") == "explore" or s.get("in_contact")]
    pos = np.asarray(data.series["positions"], dtype=float).reshape(len(data.series["positions"]), -1, 3)[:, 0]
    step_of = {int(k): i for i, k in enumerate(data.series["step"])}
    lag, still, prev = [], 0, None
    for s in rows:
        if not s.get("in_contact") or s.get("contact_point") is None:
            prev = None
            continue
        pose = np.asarray(s["object_pose"], dtype=float)
        c = (np.asarray(s["contact_point"], dtype=float) - pose[:3]) @ quat_to_matrix(pose[3:])
        i = step_of.get(int(s.get("step", -1)))
        if i is not None:
            lag.append(float(np.linalg.norm(c - pos[i])))
        if prev is not None and np.linalg.norm(c - prev) < 5e-4:
            still += 1
        prev = c
    lag = np.array(lag)
    out.update(no_contact_steps=int(sum(not s.get("in_contact") for s in data.robot)),
               lag_mm_median=1e3 * float(np.median(lag)) if len(lag) else None,
               lag_mm_p95=1e3 * float(np.percentile(lag, 95)) if len(lag) else None,
               wait_steps=int(np.sum(lag > 6e-3)), still_steps=still)
    sponge = sponge_path(data.robot)
    kin_reach = kinematic_path(basis, target, cfg, start, steps)
    out.update(eps_sponge_reach=eps(sponge, target), eps_kinematic_reach=eps(kin_reach, target),
               eps_agent_reach=eps(pos, target), eps_sponge_run=sm.get("eps_sponge"))
    out["eps_ratio_reach"] = out["eps_sponge_reach"] / out["eps_kinematic_reach"] if out["eps_kinematic_reach"] > 0 else None
    tr = sm.get("transitions") or []
    explore_s = 0.0
    for a, b in zip(tr, tr[1:]):
        if a.get("to") == "explore":
            explore_s += float(b["t"]) - float(a["t"])
    out.update(explore_s=explore_s, robot_s=sm.get("robot_seconds"))
    return out


def corpus_report(rows: list[dict]) -> str:
    """Per case and in total: completed share, fault stops by reason, contacts (the run's and the replay's), ε."""
    lines = ["| case | placement | runs | completed | stops (reason: runs) | arm contacts (run) | replay: samples "
             "penetrating / logged | deepest (mm, link) | ε sponge / ε kinematic |", "|---|---|---|---|---|---|---|---|---|"]
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["case"], r["placement"]), []).append(r)
    for (name, placement), rs in list(groups.items()) + [(("TOTAL", ""), rows)]:
        done = sum(r["completed"] for r in rs)
        stops: dict = {}
        for r in rs:
            if not r["completed"]:
                key = _reason_key(r.get("error") or r.get("stop_reason"))
                stops[key] = stops.get(key, 0) + 1
        rep = [r["replay"] for r in rs if r.get("replay")]
        pen = sum(x["samples_penetrating"] for x in rep)
        logged = sum(x["samples"] for x in rep)
        deep = max(rep, key=lambda x: x["deepest_mm"], default=None)
        arm = [r.get("arm_contacts_run") for r in rs if r.get("arm_contacts_run") is not None]
        ratios = [r["eps_ratio"] for r in rs if r.get("eps_ratio") is not None]
        reach = [r["eps_ratio_reach"] for r in rs if r.get("eps_ratio_reach") is not None]
        eps = (f"{np.median([r['eps_sponge'] for r in rs if 'eps_sponge' in r]):.3f} / "
               f"{np.median([r['eps_kinematic'] for r in rs if 'eps_kinematic' in r]):.3f} "
               f"(ratio median {np.median(ratios):.2f}"
               + (f"; on the reachable target {np.median(reach):.2f}" if reach else "") + ")") if ratios else "n/a"
        deepest = f"{deep['deepest_mm']:.1f} ({deep['deepest_link']})" if deep and deep["deepest_mm"] > 0 else "0"
        lines.append(f"| {name} | {placement} | {len(rs)} | {done} ({100 * done / len(rs):.0f}%) | "
                     f"{'; '.join(f'{k}: {v}' for k, v in stops.items()) or '-'} | "
                     f"{_arm_cell(arm)} | {pen} / {logged} | "
                     f"{deepest} | "
                     f"{eps} |")
    return "\n".join(lines)


def corpus_main(args) -> int:
    corpus = _env.load("corpus")

    placements = args.placements.split(",")
    cases = corpus.cases(args.corpus, densities=tuple(args.densities.split(",")), markings=tuple(args.markings.split(",")),
                         objects=args.objects.split(",") if args.objects else None)
    if args.max_cases:
        cases = cases[: args.max_cases]
    if not cases:
        print(f"no corpus case matches --corpus {args.corpus} --objects {args.objects}: see benchmarks/corpus.py for "
              "which meshes are in TUNE and CHECK", file=sys.stderr)
        return 2
    rows = []
    out_root = args.runs or tempfile.mkdtemp(prefix="tergodic-corpus-runs-")
    print(f"{len(cases)} cases x {len(placements)} placements x {args.seeds} seeds, {args.steps} steps at {args.force:g} N; "
          f"runs in {out_root}", file=sys.stderr, flush=True)
    for case in cases:
        for placement in placements:
            for seed in range(args.seed, args.seed + args.seeds):
                rows.append(corpus_run(case, placement, seed, args.steps, args.force, out_root))
                r = rows[-1]
                print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()}, default=str),
                      file=sys.stderr, flush=True)
    print(f"corpus '{args.corpus}' ({args.densities}, {args.markings}): {args.steps} explorer steps at {args.force:g} N, "
          f"seeds {args.seed}-{args.seed + args.seeds - 1}; replay: stock Panda (fingers excluded) against the mesh "
          f"and the plane z = 0, penetration > {PENETRATION_TOL * 1e3:g} mm\n")
    print(corpus_report(rows))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2, default=str)
    return 0


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
    ap.add_argument("--arm", default="panda", help="the simulated arm (--arm of tergodic explore) [default: panda]")
    ap.add_argument("--corpus", nargs="?", const="all", choices=("tune", "check", "all"), default=None,
                    help="run the household corpus (benchmarks/corpus.py) through the CLI instead of the synthetic "
                         "objects: every case at each placement, seeds --seed.. ; --objects then names corpus meshes")
    ap.add_argument("--placements", default="stand,table", help="corpus: stand (default pose) and/or table")
    ap.add_argument("--densities", default="3mm", help="corpus: 3mm and/or 6mm [default: 3mm]")
    ap.add_argument("--markings", default="patch,band", help="corpus: patch and/or band [default: both]")
    ap.add_argument("--max-cases", type=int, default=0, help="corpus: only the first N cases (0: all)")
    ap.add_argument("--runs", default=None, help="corpus: keep the run folders here [default: a temp folder]")
    args = ap.parse_args(argv)
    if args.corpus:
        if args.objects == ap.get_default("objects"):
            args.objects = None
        return corpus_main(args)
    rows = []
    with tempfile.TemporaryDirectory() as cache:
        for obj in args.objects.split(","):
            for seed in range(args.seed, args.seed + args.seeds):
                rows.append(run_one(obj, args.steps, seed, args.force, args.nk, cache, args.gains, args.arm))
                print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in rows[-1].items()}),
                      file=sys.stderr, flush=True)
    seeds = f"seeds {args.seed}-{args.seed + args.seeds - 1}" if args.seeds > 1 else f"seed {args.seed}"
    print(f"{args.arm}: {args.steps} explorer steps at {args.force:g} N, {seeds} (ε ratios: median; goals: worst seed); "
          f"bare PyBullet now {np.median([r['bare_steps_per_s'] for r in rows]):.0f} steps per CPU second "
          f"(reference {REFERENCE_BARE_STEPS_PER_S:.0f})\n")
    print(table([combine([r for r in rows if r["object"] == o]) for o in dict.fromkeys(r["object"] for r in rows)]))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
