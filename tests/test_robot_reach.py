"""Steep walls (issue 15, item 1): the tool follows the normal, unreachable parts are dropped, no press at an angle.

Independent expectations: the mug's analytic normal (radial from its axis) at PyBullet's own contact
points; a normal facing the robot's base cannot be followed (the wrist would sit inside the base),
a sideways one can."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("pybullet")
pytest.importorskip("pygafro")

from test_robot_sim import FAST  # noqa: E402

from tergodic_cli.basis import compute_basis  # noqa: E402
from tergodic_cli.capture import CaptureConfig, capture_cloud  # noqa: E402
from tergodic_cli.errors import TergodicError  # noqa: E402
from tergodic_cli.explore import ExploreConfig, Explorer  # noqa: E402
from tergodic_cli.backends.pybullet import RobotRun  # noqa: E402
from tergodic_cli.robot import RobotConfig, robot_explore_config  # noqa: E402
from tergodic_cli.robot.reach import tool_rotation  # noqa: E402
from tergodic_cli.robot.safety import fault_exit_code  # noqa: E402


@pytest.fixture(scope="module")
def mug():
    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic="mug", voxel=0.005))
    return cap, compute_basis(cap.points, 40, 30)


def _explorer(cap, basis, cfg, target=None, seed=0):
    ec = robot_explore_config(ExploreConfig(nk=40, seed=seed, agent_radius=0.008), cfg.explore_dt)
    p = cap.target if target is None else target
    start = cap.points[np.flatnonzero(p > 0)[0]][None]
    return Explorer(basis, p, ec, start, on_event=lambda msg: None)


def _mug_normal(run, x_base):
    """The mug's true outward normal at a base-frame point: radial from its axis (capture frame z axis)."""
    x = run._to_obj(x_base)
    n = np.array([x[0], x[1], 0.0])
    return run.T_obj[:3, :3] @ (n / np.linalg.norm(n))


def test_tool_rotation_follows_the_axis_and_never_flips():
    x_down = np.array([1.0, 0.0, 0.0])
    # down -> horizontal, then once around the horizon, then back up to 45 deg below it
    dirs = [np.array([math.sin(t), 0.0, -math.cos(t)]) for t in np.linspace(0, math.pi / 2, 90)]
    dirs += [np.array([math.cos(p), math.sin(p), 0.0]) for p in np.linspace(0, 2 * math.pi, 360)]
    dirs += [np.array([math.cos(t), 0.0, -math.sin(t)]) for t in np.linspace(0, math.pi / 4, 45)]
    prev = None
    for d in dirs:
        R = tool_rotation(d, x_down)
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0
        assert np.allclose(R[:, 2], d, atol=1e-12)
        if prev is not None:  # neighbouring axes (1 deg apart) get neighbouring spins: no flip
            assert float(R[:, 0] @ prev) > math.cos(math.radians(5))
        prev = R[:, 0]
    assert np.allclose(tool_rotation(np.array([0.0, 0.0, -1.0]), x_down)[:, 0], x_down)


def test_the_tool_follows_the_normal_on_a_vertical_wall(mug):
    cap, basis = mug
    cfg = RobotConfig(force=5.0, **FAST)
    events = []
    with RobotRun(cap, _explorer(cap, basis, cfg), cfg, on_event=lambda s, m: events.append(m)) as run:
        tilts = []

        def watch(contacts, dt):  # every 10th tick: the angle to the true normal at PyBullet's contact point
            f = sum(c[2] for c in contacts)
            if run.sm.state == "explore" and f > 1.0:
                cp = sum(c[2] * c[0] for c in contacts) / f
                z = run.arm.dev.read_state().ee_pose[:3, 2]
                tilts.append(math.degrees(math.acos(min(1.0, float(-z @ _mug_normal(run, cp))))))

        run.arm.contact_hook, run.arm.hook_every = watch, 10
        out = run.run(15)
    assert out["stop_reason"] == "completed"
    assert len(tilts) > 200
    assert float(np.median(tilts)) <= 5.0
    assert float(np.max(tilts)) <= 15.0
    assert out["tilt_deg_median"] <= 5.0  # the run's own figure agrees


def test_an_unreachable_region_is_reported_and_dropped(mug):
    cap, basis = mug
    cfg = RobotConfig(force=5.0, object_pose=(0.5, 0.0, 0.2), **FAST)  # given pose: no turning the object
    events = []
    ex = _explorer(cap, basis, cfg, target=np.ones(len(cap.points)))
    with RobotRun(cap, ex, cfg, on_event=lambda s, m: events.append(m)) as run:
        nb = np.array([_mug_normal(run, x) for x in run.points_base])
        dropped = [m for m in events if "cannot follow the normal" in m and "dropped from the target" in m]
        assert len(dropped) == 1
        assert np.all(ex.p[~run.reachable] == 0) and np.all(ex.p[run.reachable] > 0)
        facing_base = nb[:, 0] < -0.97  # the wrist would have to sit inside the robot's base
        z = cap.points[:, 2]  # away from the open rim and bottom edge (the sponge's radius from a border is dropped)
        sideways = (np.abs(nb[:, 1]) > 0.97) & (z > z.min() + 0.015) & (z < z.max() - 0.015)
        assert facing_base.any() and not run.reachable[facing_base].any()
        assert run.reachable[sideways].mean() > 0.9
    # a target entirely where the tool cannot follow the normal: refused before any motion (exit 2)
    target = np.where(np.array([_mug_normal(run, x)[0] for x in run.points_base]) < -0.97, 1.0, 0.0)
    with pytest.raises(TergodicError, match="cannot follow the surface normal anywhere"):
        RobotRun(cap, _explorer(cap, basis, cfg, target=target), cfg)


def test_a_start_whose_hover_pose_is_out_of_reach_moves_to_the_next(mug):
    """The reach map is sampled: where the start's hover pose fails the arm's own IK after all, that
    place is marked out of reach and the nearest reachable target point beyond it is tried."""
    import tergodic_cli.robot.run as R

    cap, basis = mug
    cfg = RobotConfig(force=5.0, **FAST)
    events, tried = [], []
    with RobotRun(cap, _explorer(cap, basis, cfg), cfg, on_event=lambda s, m: events.append(m)) as run:
        reach = run.arm.reach

        def failing_twice(T):
            tried.append(T[:3, 3].copy())
            return "inverse kinematics off by 9.0 mm" if len(tried) <= 2 else reach(T)

        run.arm.reach = failing_twice
        out = run.run(3)
    assert out["stop_reason"] == "completed" and len(tried) >= 3
    # each failed hover's place was dropped: the next start lies beyond TRANSIT_M of it
    assert np.linalg.norm(tried[1] - tried[0]) > R.TRANSIT_M and np.linalg.norm(tried[2] - tried[1]) > R.TRANSIT_M
    assert any("starting at the nearest reachable target point" in m for m in events)


@pytest.mark.long
def test_a_joint_near_its_limit_marks_the_place_out_of_reach(mug, monkeypatch):
    """Where the arm's posture nears a joint limit in contact (the torus's far wall drove joint 6 past
    it), the place is marked out of reach: the tool waits there, the agent moves on, the tool moves
    over; the run never stops on the limit. Forced here by counting every posture as near its limit."""
    import tergodic_cli.robot.run as R

    cap, basis = mug
    cfg = RobotConfig(force=5.0, **FAST)
    with RobotRun(cap, _explorer(cap, basis, cfg), cfg) as run:
        run.run(6)
        kept = run.reachable.copy()
    monkeypatch.setattr(R, "JOINT_NEAR", 10.0)
    events = []
    with RobotRun(cap, _explorer(cap, basis, cfg), cfg, on_event=lambda s, m: events.append(m)) as run:
        before = run.reachable.copy()
        out = run.run(12)
        assert out["stop_reason"] == "completed"
        cps = np.array([run._to_obj(s["contact_point"]) for s in run.samples if s["in_contact"]])
        d = np.min(np.linalg.norm(cap.points[:, None] - cps[None], axis=2), axis=1)
        assert not run.reachable[d < 0.005].any() and before[d < 0.005].any()
        assert any("waits on the last reachable point" in m for m in events)
    assert kept[d < 0.005].any()  # without the rule those places stay reachable


def _explore_from_an_unreachable_spot(run, cap, steps):
    """Touch at the start, mark the tool's own 2 mm there out of reach, then explore ``steps``."""
    run.begin()
    with run.guarded():
        run.engage()
        spot = run._to_obj(run._start_line[0])
        run.reachable[np.linalg.norm(cap.points - spot, axis=1) < 0.002] = False
        run.explore(steps)


def test_the_agent_moves_on_when_the_rolled_contact_is_out_of_reach(mug, monkeypatch):
    """Where the turn limit leaves the tool's next line on an unreachable point while the agent's own
    point is reachable, the tool waits and the agent moves on by itself (reset to the standing tool it
    took the same step again and again: the torus stood still for 900 steps); back in reach away from
    the tool, the tool moves over. Forced: no turn at all allowed, the tool's own spot out of reach."""
    import tergodic_cli.robot.run as R

    cap, basis = mug
    cfg = RobotConfig(force=5.0, **FAST)
    monkeypatch.setattr(R, "MAX_TURN_DEG", 0.0)
    monkeypatch.setattr(R, "GENTLE_TURN_DEG", -1.0)
    events = []
    with RobotRun(cap, _explorer(cap, basis, cfg), cfg, on_event=lambda s, m: events.append(m)) as run:
        _explore_from_an_unreachable_spot(run, cap, 15)
        assert run.fault is None and run.sm.state == "explore"
    assert any("moving over" in m for m in events)


def test_no_press_at_a_large_angle(mug):
    cap, basis = mug
    cfg = RobotConfig(force=5.0, **FAST)
    with RobotRun(cap, _explorer(cap, basis, cfg), cfg) as run:
        tilts = []

        def watch(contacts, dt):  # the true tilt (against the mug's normal) whenever the sponge presses
            f = sum(c[2] for c in contacts)
            if f > 0.5:
                cp = sum(c[2] * c[0] for c in contacts) / f
                z = run.arm.dev.read_state().ee_pose[:3, 2]
                tilts.append(math.degrees(math.acos(min(1.0, float(-z @ _mug_normal(run, cp))))))

        run.arm.contact_hook, run.arm.hook_every = watch, 5
        run.begin()
        with run.guarded():
            run.engage()
            line = run._agent_line

            def tilted():  # the commanded axis 30 deg off the normal (a wrong target, a bad normal)
                a, d = line()
                side = np.cross(d, [0.0, 0.0, 1.0])
                side /= np.linalg.norm(side)
                return a, math.cos(math.radians(30)) * d + math.sin(math.radians(30)) * side

            run._agent_line = tilted
            run.explore(20)
        out = run.result()
        assert out["final_state"] == "stopped" and "off the surface normal" in out["stop_reason"]
        assert fault_exit_code(out) == 3
        assert sum(c[2] for c in run.scene.sponge_contacts()) == 0.0  # lifted
    assert len(tilts) > 50 and max(tilts) <= 10.0  # it never pressed tilted: it lifted first


def test_hover_posture_is_not_a_twisted_elbow():
    """The bowl's far wall, 45 deg (seen in a run): from the picture pose alone the inverse kinematics
    settles with joints 1 and 3 counter-rotated and joint 4 near its limit; the multi-seed posture
    finds the untwisted arm."""
    from tergodic_cli.backends.pybullet.arms.panda import HOME as PICTURE_Q
    from tergodic_cli.robot.ga import pose_matrix
    from tergodic_cli.backends.pybullet import PyBulletArm, PyBulletScene
    from tergodic_cli.robot.reach import ik, posture

    scene = PyBulletScene(None)
    try:
        arm = PyBulletArm(scene)
        arm.connect()
        scene.set_arm(np.array(PICTURE_Q))
        x_down = arm.read_state().ee_pose[:3, 0]
        d = np.array([0.5949687, 0.4077826, -0.69262226])
        T = pose_matrix(tool_rotation(d, x_down), np.array([0.54756738, 0.03264705, 0.22460225]) - 0.04 * d)
        q0 = np.array(PICTURE_Q)
        margin = lambda q: float(np.min(np.minimum(q - arm.q_min, arm.q_max - q)))  # noqa: E731
        q1, _, _ = ik(arm._chain, T, q0, arm.q_min, arm.q_max, q_rest=q0)
        q, pe, oe = posture(arm._chain, T, q0, arm.q_min, arm.q_max)
        T_got = np.empty((4, 4))
        from tergodic_cli.robot.kernels import fk_jacobian

        fk_jacobian(q, *arm._chain, T_got, np.empty((6, 7)))
        assert np.linalg.norm(T_got[:3, 3] - T[:3, 3]) < 1e-3 and np.allclose(T_got[:3, :3], T[:3, :3], atol=1e-2)
        assert abs(q1[0] + q1[2]) < 0.2 and abs(q1[0]) > 1.0  # the single seed's twist (the expectation's premise)
        assert abs(q[0]) < 0.3 and abs(q[2]) < 0.3 and margin(q) > margin(q1) + 0.1
    finally:
        scene.close()


@pytest.mark.long
def test_a_press_at_an_angle_lifts_and_touches_again_and_a_repeat_is_a_fault(mug):
    """A soft sponge near a sharp edge wraps it and its contact normals tilt: two steps in a row over
    CONTACT_TILT_MAX_DEG lift the tool, which touches again on the agent's line (RESEATS times within
    RESEAT_WINDOW steps); one more ends the run lifted, exit 3. Injected: the press-angle reading."""
    import tergodic_cli.robot.run as R

    cap, basis = mug
    cfg = RobotConfig(force=5.0, **FAST)
    events = []
    with RobotRun(cap, _explorer(cap, basis, cfg), cfg, on_event=lambda s, m: events.append(m)) as run:
        contact = run.arm.contact
        tilted_steps = {3, 4}  # two steps in a row: one lift, then the run goes on

        def reading(obs):
            cp, f, press = contact(obs)
            return cp, f, (20.0 if run._step() in tilted_steps else press)

        run.arm.contact = reading
        out = run.run(12)
        assert out["stop_reason"] == "completed" and out["move_overs"] == 1
        assert [t["to"] for t in out["transitions"]].count("approach") == 2  # touched again
        assert any("touching again on the agent's line" in m for m in events)

    with RobotRun(cap, _explorer(cap, basis, cfg), cfg) as run:
        contact = run.arm.contact
        run.arm.contact = lambda obs: (*contact(obs)[:2], 20.0)  # always tilted
        out = run.run(30)
        assert out["final_state"] == "stopped" and "off the surface normal" in out["stop_reason"]
        assert fault_exit_code(out) == 3 and out["move_overs"] == R.RESEATS
        assert sum(c[2] for c in run.scene.sponge_contacts()) == 0.0  # lifted


def test_an_agent_left_waiting_restarts_at_the_hottest_reachable_point(mug, monkeypatch):
    """Alone in the dropped part nothing is deposited where the agent goes, so it can settle there for
    good (the torus: 900 steps); after WAIT_STEPS it restarts at the reachable target point with the
    highest heat, away from the reach boundary, and the tool moves over to it. Forced: no turn
    allowed, the tool's spot out of reach."""
    import tergodic_cli.robot.run as R

    cap, basis = mug
    cfg = RobotConfig(force=5.0, **FAST)
    monkeypatch.setattr(R, "MAX_TURN_DEG", 0.0)
    monkeypatch.setattr(R, "GENTLE_TURN_DEG", -1.0)
    monkeypatch.setattr(R, "WAIT_STEPS", 2)
    ex = _explorer(cap, basis, cfg)
    chosen = []
    with RobotRun(cap, ex, cfg) as run:
        hottest = run._hottest_reachable

        def watch():  # expected: the hottest of the reachable target points 12 mm or more from any unreachable one
            ok = np.flatnonzero(run.reachable & (run.target() > 0))
            out = cap.points[~run.reachable]
            gap = np.array([np.min(np.linalg.norm(out - x, axis=1)) for x in cap.points[ok]])
            ok = ok[gap >= R.TRANSIT_M] if (gap >= R.TRANSIT_M).any() else ok
            expect = cap.points[ok[np.argmax(ex.heat[ok])]]
            x = hottest()
            chosen.append((x, expect, ex.step_index))
            return x

        run._hottest_reachable = watch
        _explore_from_an_unreachable_spot(run, cap, 8)
        assert run.fault is None
    assert chosen, "the waiting agent never restarted"
    x, expect, k = chosen[0]
    assert np.allclose(x, expect) and k >= R.WAIT_STEPS


def test_every_placement_tried_is_checked_against_the_arms_reach(monkeypatch):
    """plan_reach tries the next default placement while the arm reaches less than the whole target,
    and checks each against the arm's own shoulder and working distance (a loop variable once hid it)."""
    import tergodic_cli.robot.reach as R
    import tergodic_cli.robot.surface as S

    pts = np.random.default_rng(0).uniform(-0.05, 0.05, (50, 3))
    half = np.arange(50) % 2 == 0
    monkeypatch.setattr(R, "reach_map", lambda *a, **k: half.copy())  # half of the target at every pose
    seen = []
    monkeypatch.setattr(S, "check_reachable", lambda points, reach: seen.append(reach))
    arm_reach = ((0.0, 0.0, 0.3), 0.75)
    R.plan_reach(None, pts, np.tile([0.0, 0.0, 1.0], (50, 1)), np.ones(50), np.array([1.0, 0, 0]), None, None, None,
                 None, reach=arm_reach)
    assert len(seen) == len(R.PLACEMENTS) - 1 and all(r == arm_reach for r in seen)
