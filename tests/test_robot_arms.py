"""Any arm through one seam (issue 28, items 1-2): each simulated arm loads, its model is what its URDF says,
and it runs the same contact loop as the Panda."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

pytest.importorskip("pybullet")

from conftest import REPO, assert_one_line_error, run_cli  # noqa: E402

from tergodic_cli.backends.pybullet import PyBulletScene, explore_with_robot  # noqa: E402
from tergodic_cli.backends.pybullet.arms import ARMS, get_arm  # noqa: E402
from tergodic_cli.basis import compute_basis  # noqa: E402
from tergodic_cli.capture import CaptureConfig, capture_cloud  # noqa: E402
from tergodic_cli.errors import TergodicError  # noqa: E402
from tergodic_cli.explore import ExploreConfig, Explorer  # noqa: E402
from tergodic_cli.robot import RobotConfig, robot_explore_config  # noqa: E402

#: (name, URDF in pybullet_data, its movable joints) written out here, independently of the arm modules.
STOCK = {"panda": ("franka_panda/panda.urdf", 7), "xarm6": ("xarm/xarm6_robot.urdf", 6), "iiwa": ("kuka_iiwa/model.urdf", 7)}


def _stock_limits(urdf: str) -> dict:
    """The stock URDF's movable joints and their limits, read with pybullet.getJointInfo in a client of its own."""
    import pybullet as p
    import pybullet_data

    cid = p.connect(p.DIRECT)
    try:
        rob = p.loadURDF(os.path.join(pybullet_data.getDataPath(), urdf), useFixedBase=True, physicsClientId=cid)
        infos = [p.getJointInfo(rob, j, physicsClientId=cid) for j in range(p.getNumJoints(rob, physicsClientId=cid))]
    finally:
        p.disconnect(physicsClientId=cid)
    arm = [i for i in infos if i[2] == p.JOINT_REVOLUTE]
    return {"names": [i[1].decode() for i in arm], "q_min": np.array([i[8] for i in arm]),
            "q_max": np.array([i[9] for i in arm]), "tau_max": np.array([i[10] for i in arm]),
            "dq_max": np.array([i[11] for i in arm])}


def test_the_registry_holds_the_three_arms():
    assert set(ARMS) == set(STOCK)
    with pytest.raises(TergodicError, match="unknown arm 'ur5'.*panda or xarm6 or iiwa"):
        get_arm("ur5")


@pytest.mark.parametrize("name", sorted(STOCK))
def test_arm_model_matches_its_urdf(name):
    urdf, dof = STOCK[name]
    stock = _stock_limits(urdf)
    sc = PyBulletScene(arm=name)
    try:
        m = sc.arm_model()
        assert m.dof == dof and list(m.joint_names) == stock["names"][:dof]
        override = get_arm(name).limits
        for key in ("q_min", "q_max", "dq_max", "tau_max"):
            got, want = getattr(m, key), stock[key][:dof]
            if key in override:  # datasheet limits: never looser than the URDF's
                assert np.all(got >= want - 1e-9) if key == "q_min" else np.all(got <= want + 1e-9), key
            else:
                np.testing.assert_array_equal(got, want, err_msg=key)
        assert np.all(m.q_min < m.home) and np.all(m.home < m.q_max)
        # The model's chain against PyBullet's own forward kinematics and Jacobian (the TCP: the sponge's tip).
        import pybullet as p

        rng = np.random.default_rng(1)
        for _ in range(3):
            q = rng.uniform(np.maximum(m.q_min, -2.5) + 0.1, np.minimum(m.q_max, 2.5) - 0.1)
            sc.set_arm(q)
            np.testing.assert_allclose(m.fk(q), sc.tcp_pose(), atol=1e-6)
            from tergodic_cli.robot.kernels import fk_jacobian

            T, J = np.empty((4, 4)), np.empty((6, dof))
            fk_jacobian(q, *m.chain, T, J)
            lin, ang = p.calculateJacobian(sc.robot, sc.tcp_link, list(sc.tcp_offset), q.tolist(), [0.0] * dof,
                                           [0.0] * dof, physicsClientId=sc.cid)
            np.testing.assert_allclose(J, np.vstack([lin, ang]), atol=1e-6)
        # The TCP: the sponge's tip on the flange's z-axis, tool pointing down at the home posture.
        sc.set_arm(m.home)
        assert sc.tcp_pose()[:3, 2] @ [0, 0, -1.0] > 0.99
        # The reach check's shoulder (datasheet) is the second joint's origin in the URDF, within 1 cm.
        shoulder, reach = get_arm(name).reach
        j2 = p.getLinkState(sc.robot, sc.arm_joints[1], physicsClientId=sc.cid)[4]
        assert np.linalg.norm(np.subtract(j2, shoulder)) < 0.01, (j2, shoulder)
        # ... and its working distance is no more than the farthest the TCP gets from it.
        far = max(np.linalg.norm(m.fk(rng.uniform(m.q_min, m.q_max))[:3, 3] - shoulder) for _ in range(300))
        assert reach < far, (reach, far)
    finally:
        sc.close()


@pytest.fixture(scope="module")
def bowl():
    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic="bowl", voxel=0.005))
    return cap, compute_basis(cap.points, 40, 30)


@pytest.mark.parametrize("name", ["xarm6", "iiwa"])
def test_short_contact_run_on_the_bowl(bowl, name):
    """The same contact loop as the Panda: set-up move, guarded approach, pressing at F_d while exploring,
    retreat; the force at the explorer's samples near F_d, no arm part touching anything."""
    cap, basis = bowl
    cfg = RobotConfig(force=5.0, arm=name, move_speed=1.6, hover_height=0.02)
    ec = robot_explore_config(ExploreConfig(nk=40, seed=0, agent_radius=0.008), cfg.explore_dt)
    start = cap.points[np.argmin(np.linalg.norm(cap.points[:, :2], axis=1))][None]  # the bottom
    ex = Explorer(basis, cap.target, ec, start, on_event=lambda msg: None)
    samples: list[dict] = []
    out = explore_with_robot(cap, ex, cfg, 20, on_step=lambda k, s: samples.append(s))
    assert out["final_state"] == "done", out.get("stop_reason")
    assert len(samples) == 20
    f = np.array([s["force_normal"] for s in samples[5:]])
    # (single 5 Hz samples catch the contact's 1 kHz jitter on the trimesh: up to ~1.5 N, docs/robot.md)
    assert abs(float(np.median(f)) - 5.0) < 0.2 and np.all(np.abs(f - 5.0) < 2.5), f
    assert out["force_rms_error_rel"] < 0.15
    assert (out.get("arm_contacts") or {}).get("count", 0) == 0
    assert out["robot_config"]["arm"] == name


def test_unknown_arm_is_one_line_exit_2(tmp_path):
    res = run_cli("explore", REPO / "data/bowl", "--robot", "pybullet", "--arm", "ur5", "--steps", "2", "--out", tmp_path / "r")
    assert_one_line_error(res, "unknown arm 'ur5'", "panda", "xarm6", "iiwa")
    assert not (tmp_path / "r").exists()
    res = run_cli("explore", REPO / "data/bowl", "--robot", "franka", "--arm", "xarm6", "--steps", "2", "--out", tmp_path / "f")
    assert_one_line_error(res, "--arm xarm6", "simulated")


def test_arm_is_saved_and_repeated_by_config(tmp_path):
    run = tmp_path / "run"
    res = run_cli("explore", REPO / "data/bowl", "--robot", "pybullet", "--arm", "xarm6", "--steps", "2", "--no-log", "--out", run)
    assert res.code == 0, res.err
    saved = json.loads((run / "config.json").read_text())
    assert saved["robot_options"]["arm"] == "xarm6"
    again = tmp_path / "again"
    res = run_cli("explore", REPO / "data/bowl", "--config", run / "config.json", "--no-log", "--out", again)
    assert res.code == 0, res.err
    assert json.loads((again / "config.json").read_text())["robot_options"]["arm"] == "xarm6"
    assert json.loads((again / "summary.json").read_text())["robot_config"]["arm"] == "xarm6"
