"""The compiled 1 kHz kernels against independent references: PyBullet's own kinematics, plain-Python
limit checks, and the generic (protocol-level) control loop, which the compiled loop must reproduce
bit for bit."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("pybullet")
pytest.importorskip("pygafro")

from tergodic_cli.basis import compute_basis  # noqa: E402
from tergodic_cli.capture import CaptureConfig, capture_cloud  # noqa: E402
from tergodic_cli.explore import ExploreConfig, Explorer  # noqa: E402
from tergodic_cli.robot import kernels as Kn  # noqa: E402
from tergodic_cli.backends.pybullet import RobotRun  # noqa: E402
from tergodic_cli.robot import RobotConfig, SafetyConfig, SafetyGuard, robot_explore_config  # noqa: E402
from tergodic_cli.backends.pybullet import PyBulletArm, PyBulletScene  # noqa: E402
from tergodic_cli.backends.pybullet.arms.panda import DQ_MAX, Q_MAX, Q_MIN  # noqa: E402


def test_compiled_kinematics_match_pybullet():
    import pybullet as p

    sc = PyBulletScene()
    try:
        arm = PyBulletArm(sc)
        arm.connect()
        rng = np.random.default_rng(4)
        for _ in range(10):
            q = rng.uniform(arm.q_min, arm.q_max)
            sc.set_arm(q)
            st = arm.read_state()
            ls = p.getLinkState(sc.robot, sc.tcp_link, computeForwardKinematics=True, physicsClientId=sc.cid)
            R = np.array(p.getMatrixFromQuaternion(ls[5])).reshape(3, 3)
            lin, ang = p.calculateJacobian(sc.robot, sc.tcp_link, sc.tcp_offset, q.tolist(), [0.0] * 7, [0.0] * 7,
                                           physicsClientId=sc.cid)
            np.testing.assert_allclose(st.ee_pose[:3, :3], R, atol=1e-6)
            np.testing.assert_allclose(st.ee_pose[:3, 3], np.array(ls[4]) + R @ np.array(sc.tcp_offset), atol=1e-6)
            np.testing.assert_allclose(st.jacobian, np.array(lin + ang), atol=1e-6)
            np.testing.assert_allclose(st.ee_pose[3], [0, 0, 0, 1])
        # the chain calibration leaves the arm where it was
        q0 = np.array([0.1, -0.5, 0.2, -2.0, 0.1, 1.6, 0.7])
        sc.set_arm(q0)
        from tergodic_cli.backends.pybullet.scene import kinematic_chain

        kinematic_chain(sc)
        np.testing.assert_allclose([s[0] for s in p.getJointStates(sc.robot, sc.arm_joints, physicsClientId=sc.cid)], q0)
    finally:
        sc.close()


def _plain_state_fault(q, dq, pos, speed, q_lo, q_hi, dq_hi, tcp_max, lo, hi):
    """The limits of SafetyGuard.check_state written out plainly (the reference)."""
    for j in range(7):
        if not q_lo[j] <= q[j] <= q_hi[j]:
            return Kn.F_JOINT_POS, j
    for j in range(7):
        if not abs(dq[j]) <= dq_hi[j]:
            return Kn.F_JOINT_VEL, j
    if not speed <= tcp_max:
        return Kn.F_TCP_SPEED, -1
    for k in range(3):
        if not lo[k] <= pos[k] <= hi[k]:
            return Kn.F_WORKSPACE, k
    return Kn.OK, -1


def test_compiled_limits_agree_with_plain_checks():
    rng = np.random.default_rng(5)
    g = SafetyGuard(SafetyConfig(), Q_MIN, Q_MAX, DQ_MAX, 5.0)
    seen = set()
    for n in range(3000):
        q = rng.uniform(Q_MIN - 0.05, Q_MAX + 0.05) if n % 3 == 0 else rng.uniform(Q_MIN + 0.03, Q_MAX - 0.03)
        dq = rng.normal(0, 1.2, 7)
        pos = rng.uniform([0.1, -0.7, -0.05], [0.9, 0.7, 0.95])
        speed = abs(rng.normal(0, 0.4))
        if n % 97 == 0:
            (q if n % 2 else dq)[rng.integers(7)] = np.nan  # NaN breaks a limit
        want = _plain_state_fault(q, dq, pos, speed, g.q_lo, g.q_hi, g.dq_hi, g.cfg.tcp_speed_max, g.ws_lo, g.ws_hi)
        got = Kn.state_fault(q, dq, pos, speed, g.q_lo, g.q_hi, g.dq_hi, g.cfg.tcp_speed_max, g.ws_lo, g.ws_hi)
        assert tuple(got) == want, (n, got, want)
        fault = g.check_state(0.0, q, dq, pos, speed)
        assert (fault is None) == (want[0] == Kn.OK)
        if fault is not None:
            kind = {Kn.F_JOINT_POS: "joint_position", Kn.F_JOINT_VEL: "joint_velocity", Kn.F_TCP_SPEED: "tcp_speed",
                    Kn.F_WORKSPACE: "workspace"}[want[0]]
            assert fault.kind == kind and "\n" not in fault.reason
            if want[1] >= 0 and kind.startswith("joint"):
                assert f"joint {want[1] + 1} " in fault.reason
        seen.add(want[0])
    assert seen == {Kn.OK, Kn.F_JOINT_POS, Kn.F_JOINT_VEL, Kn.F_TCP_SPEED, Kn.F_WORKSPACE}
    # The force check: 3000 random ticks (|f| of the force part; moments do not count) through the
    # compiled filter and limits against a plain first-order low-pass and the two comparisons.
    a = 1.0 - math.exp(-2.0 * math.pi * g.cfg.force_filter_hz * 0.001)
    filt, codes = 0.0, set()
    for n in range(3000):
        level = (5.0, 5.0, 20.0)[(n // 40) % 3] if rng.random() > 0.01 else 40.0  # pressing, overload, impacts
        w = np.concatenate([rng.normal(0, 1.0, 3) + [0, 0, level], rng.normal(0, 9, 3)])
        if n % 500 == 7:
            w[0] = np.nan
        f = math.sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2)
        if not f <= g.force_impact_limit:
            want = Kn.F_IMPACT
        else:
            filt += a * (f - filt)
            want = Kn.OK if filt <= g.force_limit else Kn.F_FORCE
        fault = g.check_force(0.0, w)
        codes.add(want)
        assert (fault is None) == (want == Kn.OK), n
        if fault is not None:
            assert fault.kind == "force" and fault.action == "retreat" and "\n" not in fault.reason
            assert ("impact" in fault.reason) == (want == Kn.F_IMPACT)
            if want == Kn.F_FORCE:
                assert fault.data["force"] == pytest.approx(filt, rel=1e-12)
        if want != Kn.F_IMPACT:
            assert g.force_filtered == pytest.approx(filt, rel=1e-12)
    assert codes == {Kn.OK, Kn.F_FORCE, Kn.F_IMPACT}


@pytest.fixture(scope="module")
def plate():
    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic="plate", voxel=0.005))
    return cap, compute_basis(cap.points, 40, 30)


def _run(plate, fast: bool, steps: int = 4, **cfg):
    cap, basis = plate
    rcfg = RobotConfig(move_speed=1.6, hover_height=0.02, **cfg)
    ec = robot_explore_config(ExploreConfig(nk=40, seed=0, agent_radius=0.008), rcfg.explore_dt)
    start = cap.points[np.argmin(np.linalg.norm(cap.points[:, :2] - [0.03, 0.02], axis=1))][None]
    ex = Explorer(basis, cap.target, ec, start, on_event=lambda m: None)
    with RobotRun(cap, ex, rcfg) as run:
        run.arm.fast = fast
        out = run.run(steps)
        return out, run.samples


def test_compiled_loop_reproduces_the_generic_loop(plate):
    # The hot loop's one compiled call per tick must be the protocol-level loop (read_state, sensor read,
    # ContactWrench, LineForceController.step, SafetyGuard, Arm.command), not an approximation of it.
    fast, fs = _run(plate, True)
    slow, ss = _run(plate, False)
    assert fast["stop_reason"] == slow["stop_reason"] == "completed" and len(fs) == len(ss) == 4
    for a, b in zip(fs, ss):
        for key in ("q", "dq", "tau", "wrench_measured", "ee_pose"):
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
        assert a["force_filtered"] == b["force_filtered"]


def test_gravity_refresh_rate_does_not_change_the_contact(plate):
    # dynamics_every = 4 (250 Hz gravity + Coriolis) against 1 kHz: the same pressing, to well under 1 %.
    out4, s4 = _run(plate, True, steps=6)
    out1, s1 = _run(plate, True, steps=6, dynamics_every=1)
    f4 = np.array([s["force_filtered"] for s in s4])
    f1 = np.array([s["force_filtered"] for s in s1])
    assert np.max(np.abs(f4 - f1)) < 0.05 * 5.0
    dpos = max(np.linalg.norm(np.asarray(a["ee_pose"][:3]) - np.asarray(b["ee_pose"][:3])) for a, b in zip(s4, s1))
    assert dpos < 0.5e-3


def test_contact_wrench_kernel_is_the_documented_formula():
    # Eq. 39 with the tool weight removed, against a direct evaluation with matrices.
    rng = np.random.default_rng(6)
    from tergodic_cli.robot.ga import pose_matrix, rotvec_to_matrix

    frame = pose_matrix(rotvec_to_matrix(rng.normal(size=3)), rng.normal(size=3) * 0.05)
    R_se, p_se = frame[:3, :3], frame[:3, 3]
    mg, com = 7.5, rng.normal(size=3) * 0.02
    R = rotvec_to_matrix(rng.normal(size=3))
    R_tare = rotvec_to_matrix(rng.normal(size=3))

    def load(Rb):
        f = (Rb @ R_se).T @ np.array([0.0, 0.0, mg])
        return np.concatenate([f, np.cross(com, f)])

    reading = rng.normal(size=6)
    w_s = reading + load(R_tare) - load(R)
    f_ee = R_se @ w_s[:3]
    m_ee = R_se @ w_s[3:] + np.cross(p_se, f_ee)
    out = np.empty(6)
    tare = np.empty(6)
    Kn.tool_load(R_tare, np.ascontiguousarray(R_se), mg, com, tare)
    Kn.contact_wrench(reading, R, np.ascontiguousarray(R_se), np.ascontiguousarray(p_se), mg, com, tare, out)
    np.testing.assert_allclose(out, np.concatenate([f_ee, m_ee]), atol=1e-12)
    assert math.isfinite(out.sum())
