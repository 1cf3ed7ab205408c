"""Collision-free set-up moves (issue 24, item 3): the check sees a box on a straight joint move, the
planned path keeps its margins when re-checked at a finer resolution, and a placement whose first move
cannot be planned is refused before the arm moves (exit 2, one line, an earlier run folder untouched).

Independent expectations: the box is placed where the sponge ball is at the middle of the move, read
from the physics scene's own arm (PyBullet's link state, not the checking world's); clearances are
re-measured with PyBullet's closest points at 4× the planner's finest step."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pybullet")
pytest.importorskip("pygafro")
pytest.importorskip("ompl")

from conftest import run_cli  # noqa: E402

from tergodic_cli.backends.pybullet.plan import (DENSE_STEP, LINK_MARGIN, SPONGE_MARGIN, CollisionWorld,  # noqa: E402
                                                 plan_path)
from tergodic_cli.backends.pybullet.scene import PyBulletScene  # noqa: E402
from tergodic_cli.backends.pybullet.arms.panda import HOME as PICTURE_Q
from tergodic_cli.robot.config import SpongeSpec  # noqa: E402
from tergodic_cli.backends.pybullet.arms.panda import Q_MAX, Q_MIN  # noqa: E402

Q_MID = np.array(PICTURE_Q)
Q_A, Q_B = Q_MID.copy(), Q_MID.copy()
Q_A[0], Q_B[0] = 1.2, -1.2  # joint 1 swings the arm across the front: through Q_MID halfway


def _ball_centre(q: np.ndarray) -> np.ndarray:
    """The sponge ball's centre at ``q``, from the physics scene's arm (not the checking world)."""
    sc = PyBulletScene()
    try:
        sc.set_arm(q)
        T = sc.link_pose(sc.sponge_link)
        return T[:3, 3] + T[:3, 2] * SpongeSpec().offset
    finally:
        sc.close()


@pytest.fixture(scope="module")
def boxed():
    """An empty checking world with a 10 cm box around the ball's place at Q_MID."""
    w = CollisionWorld()
    T = np.eye(4)
    T[:3, 3] = _ball_centre(Q_MID)
    w.add_box([0.05, 0.05, 0.05], T)
    yield w
    w.close()


def _min_distance(w: CollisionWorld, path: np.ndarray, step: float):
    """Smallest distance (m) of any arm link and of the ball to the obstacles along ``path`` every ``step`` rad."""
    p, cid, rob = w.p, w.cid, w.robot
    link_min = ball_min = np.inf
    for q0, q1 in zip(path[:-1], path[1:]):
        n = max(1, int(np.ceil(np.max(np.abs(q1 - q0)) / step)))
        for s in np.linspace(0, 1, n + 1):
            w.set_q(q0 + s * (q1 - q0))
            for b in w.bodies():
                for c in p.getClosestPoints(rob, b, 0.2, physicsClientId=cid):
                    if c[3] == w.ball:
                        ball_min = min(ball_min, c[8])
                    elif c[3] >= 0:
                        link_min = min(link_min, c[8])
    return link_min, ball_min


def test_a_straight_move_through_a_box_is_detected(boxed):
    # The ball sits inside the box halfway: the posture and the line through it are refused...
    assert boxed.slack(Q_MID) < -0.02
    assert boxed.segment_slack(Q_A, Q_B) < 0  # certified steps
    assert boxed.segment_slack(Q_A, Q_B, step=DENSE_STEP) < 0  # fixed steps
    # ...while the ends are clear, and so is the same swing in an empty world (the check is not always "no").
    assert boxed.slack(Q_A) >= 0 and boxed.slack(Q_B) >= 0
    empty = CollisionWorld()
    try:
        assert empty.segment_slack(Q_A, Q_B) >= 0
    finally:
        empty.close()


def test_the_planned_path_keeps_the_margins_when_rechecked_finer(boxed):
    plan, err = plan_path(boxed, Q_A, Q_B, Q_MIN + 0.02, Q_MAX - 0.02)
    assert err is None
    assert plan.planner == "RRTConnect"  # the straight line is blocked
    assert np.allclose(plan.path[0], Q_A) and np.allclose(plan.path[-1], Q_B)
    assert np.all(plan.path >= Q_MIN + 0.02 - 1e-9) and np.all(plan.path <= Q_MAX - 0.02 + 1e-9)
    # Re-measured with PyBullet's closest points at a quarter of the finest step the planner used.
    link_min, ball_min = _min_distance(boxed, plan.path, DENSE_STEP / 4)
    assert link_min >= LINK_MARGIN - 1e-4, link_min
    assert ball_min >= SPONGE_MARGIN - 1e-4, ball_min


def test_the_checking_world_copies_every_non_arm_body_of_the_scene():
    """Bodies the scene gains (a table, a stand, anything but the arm) are obstacles without being named."""
    sc = PyBulletScene()
    try:
        p, cid = sc.p, sc.cid
        ball = _ball_centre(Q_MID)
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.04, 0.04, 0.04], physicsClientId=cid)
        box = p.createMultiBody(0.0, col, -1, basePosition=[5.0, 5.0, 0.0], physicsClientId=cid)
        w = CollisionWorld(sc)
        try:
            assert w.slack(Q_MID) >= 0  # the box is far away
            p.resetBasePositionAndOrientation(box, ball.tolist(), [0, 0, 0, 1], physicsClientId=cid)
            w.sync()  # a body moved in the scene moves in the check
            assert w.slack(Q_MID) < -0.02
            sph = p.createMultiBody(0.0, p.createCollisionShape(p.GEOM_SPHERE, radius=0.03, physicsClientId=cid), -1,
                                    basePosition=(ball + [0.0, 0.0, 0.25]).tolist(), physicsClientId=cid)
            w.sync()
            # every body but the arm: the box, the sphere and the scene's own (its table)
            assert len(w.obstacles) == p.getNumBodies(physicsClientId=cid) - 1
            assert (box, -1) in w.obstacles and (sph, -1) in w.obstacles
        finally:
            w.close()
    finally:
        sc.close()


def _bowl_run(pose, **kw):
    from tergodic_cli.basis import compute_basis
    from tergodic_cli.capture import CaptureConfig, capture_cloud
    from tergodic_cli.explore import ExploreConfig, Explorer
    from tergodic_cli.backends.pybullet import RobotRun
    from tergodic_cli.robot import RobotConfig, robot_explore_config

    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic="bowl", voxel=0.006))
    basis = compute_basis(cap.points, 30, 30)
    cfg = RobotConfig(force=5.0, object_pose=pose, **kw)
    ec = robot_explore_config(ExploreConfig(nk=30, seed=0, agent_radius=0.008), cfg.explore_dt)
    ex = Explorer(basis, cap.target, ec, cap.points[np.flatnonzero(cap.target > 0)[0]][None], on_event=lambda m: None)
    return RobotRun(cap, ex, cfg)


def test_a_placement_around_the_picture_pose_is_refused_at_set_up():
    """The bowl high and close to the base wraps the picture pose: no move can start clear of it."""
    from tergodic_cli.errors import TergodicError

    with pytest.raises(TergodicError, match="touches the arm at its picture pose") as exc:
        _bowl_run((0.35, 0.0, 0.6))
    assert "--object-pose" in exc.value.fix


def test_a_start_whose_hover_cannot_be_reached_clear_is_refused_before_motion():
    """Every hover pose over the bowl inside an obstacle (a box added to the check only): refused, nothing moved."""
    from tergodic_cli.errors import TergodicError

    with _bowl_run((0.5, 0.0, 0.2)) as run:
        T = np.eye(4)
        T[:3, 3] = [0.5, 0.0, 0.3]
        run.arm.world.add_box([0.15, 0.15, 0.08], T)  # over the bowl (its top at z = 0.25 m)
        steps0 = run.scene.steps
        q0 = run.arm.dev.read_state().q.copy()
        with pytest.raises(TergodicError, match="without touching anything") as exc:
            run.run(5)
        assert "--object-pose" in exc.value.fix
        assert run.scene.steps == steps0  # not one physics step: nothing moved
        assert np.allclose(run.arm.dev.read_state().q, q0)
        assert not run.sm.history  # never left the picture pose


def test_a_placement_whose_hover_move_needs_a_detour_runs_without_touching(tmp_path):
    """The bowl at z = 0.6 m (issue 24: 103 N on the straight move to hover): planned around, no contact."""
    from tergodic_cli.robot import statemachine as S

    with _bowl_run((0.5, 0.0, 0.6)) as run:
        arm = run.arm
        peak = []
        physics = arm._physics

        def watched():  # every tick of the move to hover: PyBullet's contacts of the robot with anything
            physics()
            if run.sm.state == S.HOVER:
                sc = arm.scene
                peak.append(sum(c[9] for c in sc.p.getContactPoints(sc.robot, physicsClientId=sc.cid)))

        arm._physics = watched
        arm.fast = False  # the protocol-level loop, so every tick passes through _physics here too
        run.begin()
        run.engage()
        assert run.sm.state == S.EXPLORE
        assert len(peak) > 500 and max(peak) == 0.0
        what, plan = arm.plans[0]
        assert what == "hover" and plan.planner == "RRTConnect" and plan.clearance >= 0


def test_the_cli_refuses_it_with_one_line_and_leaves_an_earlier_run(tmp_path):
    cap = tmp_path / "cap"
    assert run_cli("capture", "--synthetic", "bowl", "--marking", "X", "--voxel", "0.006", "--out", cap).code == 0
    out = tmp_path / "run"
    assert run_cli("explore", cap, "--steps", "5", "--nk", "30", "--out", out).code == 0  # an earlier (kinematic) run
    before = {f.name: f.read_bytes() for f in out.iterdir()}
    res = run_cli("explore", cap, "--robot", "pybullet", "--object-pose", "0.35,0,0.6", "--steps", "5", "--nk", "30",
                  "--out", out, "--overwrite")
    # The run's progress lines may come first; the refusal is one line, the last, with its fix.
    errors = [ln for ln in res.err.splitlines() if ln.startswith("tergodic: error:")]
    assert res.code == 2 and len(errors) == 1 and res.err.strip().splitlines()[-1] == errors[0], res.err
    assert "Traceback" not in res.err and "touches the arm" in errors[0] and "--object-pose" in errors[0]
    assert {f.name: f.read_bytes() for f in out.iterdir()} == before


def test_a_retreat_into_a_box_is_cut_short_and_holds_the_line():
    from tergodic_cli.backends.pybullet.scene import kinematic_chain
    from tergodic_cli.backends.pybullet.plan import RETREAT_LEAST, retreat_clear, retreat_postures

    sc = PyBulletScene()
    try:
        chain = kinematic_chain(sc)
        sc.set_arm(Q_MID)
        T0 = sc.tcp_pose()
        d = T0[:3, 2]  # the tool axis (into the surface); the retreat backs off along -d
        Q = retreat_postures(chain, Q_MID, d, 0.05)
        for k, q in enumerate(Q):  # on the line, orientation held: PyBullet's own forward kinematics
            sc.set_arm(q)
            T = sc.tcp_pose()
            assert np.linalg.norm(T[:3, 3] - (T0[:3, 3] - d * 0.05 * k / (len(Q) - 1))) < 5e-4
            assert np.allclose(T[:3, :3], T0[:3, :3], atol=1e-3)
    finally:
        sc.close()
    w = CollisionWorld()
    try:
        assert retreat_clear(w, chain, Q_MID, d, 0.05)[0] == pytest.approx(0.05)  # nothing behind the hand
        # A slab 40 mm behind the hand's top (the flange, 0.142 + 0.107 m back from the TCP), across the axis.
        T = np.eye(4)
        T[:3, :3] = T0[:3, :3]
        T[:3, 3] = T0[:3, 3] - d * (0.142 + 0.107 + 0.04 + 0.005)
        w.add_box([0.2, 0.2, 0.005], T)
        ok, _ = retreat_clear(w, chain, Q_MID, d, 0.05)
        assert RETREAT_LEAST <= ok < 0.05
    finally:
        w.close()


def test_a_table_under_the_arm_is_an_obstacle_but_the_base_standing_on_it_is_not():
    """pybullet_data's plane (the GUI's table) added to the scene: the base (link 0) stands on it and is not
    checked; the picture posture is clear, a posture with the sponge on the floor is not."""
    import os

    import pybullet_data

    sc = PyBulletScene()
    try:
        sc.p.loadURDF(os.path.join(pybullet_data.getDataPath(), "plane.urdf"), physicsClientId=sc.cid)
        w = CollisionWorld(sc)
        try:
            assert w.slack(Q_MID) >= 0
            q = Q_MID.copy()
            q[1], q[3] = 1.5, -0.3  # shoulder forward, elbow open: the tool at the floor
            sc.set_arm(q)
            tip = sc.tcp_pose()[2, 3]
            assert tip < SPONGE_MARGIN  # (the physics scene's own kinematics say it is at the floor)
            assert w.slack(q) < 0
        finally:
            w.close()
    finally:
        sc.close()


def test_a_move_keeps_the_tool_inside_a_box_it_is_given():
    """``inside(q)`` (the guard's workspace box) holds along the whole path, re-checked 4x finer than the
    planner's step; a goal outside it is refused with one reason. The swing's straight line passes the
    front of the arm, which the box here leaves out."""
    from tergodic_cli.backends.pybullet.plan import CHECK_STEP

    sc = PyBulletScene()
    w = CollisionWorld()
    try:
        def ball(q):
            sc.set_arm(q)
            T = sc.link_pose(sc.sponge_link)
            return T[:3, 3] + T[:3, 2] * SpongeSpec().offset

        front = ball(Q_MID)[0]
        limit = front - 0.05  # the straight swing's middle is 5 cm beyond it

        def inside(q):
            return bool(ball(q)[0] <= limit)

        assert inside(Q_A) and inside(Q_B) and not inside(Q_MID)
        plan, err = plan_path(w, Q_A, Q_B, Q_MIN + 0.02, Q_MAX - 0.02, inside=inside)
        if plan is not None:
            assert plan.planner == "RRTConnect"
            for a, b in zip(plan.path[:-1], plan.path[1:]):
                k = max(1, int(np.ceil(np.max(np.abs(b - a)) / (CHECK_STEP / 4))))
                assert max(ball(a + s * (b - a))[0] for s in np.linspace(0, 1, k + 1)) <= limit + 1e-3
        else:
            assert err in ("no collision-free path found in 1.5 s", "the planned path takes the tool outside the workspace box")
        plan, err = plan_path(w, Q_A, Q_MID, Q_MIN + 0.02, Q_MAX - 0.02, inside=inside)
        assert plan is None and err == "the goal posture has the tool outside the workspace box"
    finally:
        w.close()
        sc.close()
