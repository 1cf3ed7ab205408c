"""A UR e-Series through ur_rtde (``--robot ur``), against fake ``rtde_control`` / ``rtde_receive`` modules
shaped like ur_rtde 1.6.5's (tests/fakes/) and a fake UR5e over a table (tests/fakes/ur_world.py, its own
DH kinematics): the paper's wrench in the UR's force mode, the UR's own TCP force as the sensor.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from fakes import install, uninstall
from fakes.ur_world import URWorld

from tergodic_cli.backends import HardwareRunConfig, explore_with_hardware, make_hardware
from tergodic_cli.errors import TergodicError

IP = "192.168.1.50"


@pytest.fixture
def rtde(monkeypatch):
    rr = install(monkeypatch, "rtde_receive")
    rc = install(monkeypatch, "rtde_control")
    return rr, rc


@pytest.fixture(scope="module")
def plate():
    from tergodic_cli.basis import compute_basis
    from tergodic_cli.capture import CaptureConfig, capture_cloud

    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic="plate", voxel=0.005))
    return cap, compute_basis(cap.points, 40, 30)


def _setup(plate, monkeypatch, rtde, **world_kw):
    from tergodic_cli.backends.ur.model import HOME
    from tergodic_cli.robot import RobotConfig
    from tergodic_cli.robot.safety import SafetyConfig

    cap, _ = plate
    pts = cap.points
    # the plate's top in front of the UR (its picture pose looks down at x ~ -0.49 m)
    pose = (-0.45, -0.13, 0.10 - float(pts[:, 2].max()))
    world = URWorld(HOME, plane_z=0.10, **world_kw)
    monkeypatch.setattr(rtde[0], "_NETWORK", {IP: world})
    monkeypatch.setattr(rtde[1], "_NETWORK", rtde[0]._NETWORK)
    cfg = RobotConfig(force=5.0, object_pose=pose, hover_height=0.02,
                      safety=SafetyConfig(workspace_min=(-0.85, -0.6, -0.01), workspace_max=(-0.15, 0.6, 0.9)))
    return world, cfg


def _explorer(plate, cfg):
    from tergodic_cli.explore import ExploreConfig, Explorer
    from tergodic_cli.robot import robot_explore_config

    cap, basis = plate
    ec = robot_explore_config(ExploreConfig(nk=40, seed=0, agent_radius=0.008), cfg.explore_dt)
    start = cap.points[np.argmin(np.linalg.norm(cap.points[:, :2] - [0.03, 0.02], axis=1))][None]
    return Explorer(basis, cap.target, ec, start, on_event=lambda msg: None)


# ------------------------------------------------------------------------------------------- the model
def test_ur5e_model_matches_the_datasheet_and_the_fake_kinematics():
    from tergodic_cli.backends.ur.model import ur_model
    from tergodic_cli.robot.kernels import fk_jacobian

    m = ur_model("ur5e", tool_length=0.05)
    assert m.dof == 6 and np.allclose(m.q_max, 2 * math.pi) and np.allclose(m.dq_max, math.pi)
    assert m.tau_max.tolist() == [150.0, 150.0, 150.0, 28.0, 28.0, 28.0]
    # the zero pose UR publishes: x = a2 + a3, y = -(d4 + d6 + tool), z = d1 - d5
    assert np.allclose(m.fk(np.zeros(6))[:3, 3], [-0.8172, -0.2329 - 0.05, 0.0628], atol=1e-4)
    world = URWorld(np.zeros(6), plane_z=-1.0, tool_length=0.05)
    q = np.random.default_rng(1).uniform(-2.0, 2.0, 6)
    T, J = np.empty((4, 4)), np.empty((6, 6))
    fk_jacobian(q, *m.chain, T, J)
    assert np.allclose(T, world.fk(q), atol=1e-9)
    assert np.allclose(J, world.jacobian(q), atol=1e-5)  # finite differences vs the compiled chain


# ------------------------------------------------------------------------------------------- the contact loop
def test_exploration_in_force_mode_presses_the_force(plate, monkeypatch, rtde):
    world, cfg = _setup(plate, monkeypatch, rtde, noise=0.02)
    arm, sensor = make_hardware("ur", IP)
    ex = _explorer(plate, cfg)
    events = []
    out = explore_with_hardware(plate[0], ex, cfg, 12, arm, sensor, on_event=lambda s, m: events.append(m),
                                hw=HardwareRunConfig(move_speed=0.3), pace=world.advance)
    assert out["final_state"] == "done" and out["stop_reason"] == "completed", events
    assert out["controller"] == "line impedance + wrench PID, as the UR's force mode"
    assert out["force_mean_N"] == pytest.approx(5.0, rel=0.05)  # the wrench PID through the UR's admittance
    assert out["force_rms_error_rel"] < 0.05
    assert out["force_max_N"] < 1.5 * 5.0
    assert out["track_mm_median"] < 1.0 and out["tilt_deg_median"] < 2.0
    assert ex.metrics()["touched_fraction"] > 0
    assert world.T[2, 3] - world.plane_z >= 0.8 * cfg.retreat_distance  # lifted at the end
    assert world.mode is None and "forceMode" in world.calls and "servoL" in world.calls and "moveJ" in world.calls
    assert "stopScript" in world.calls


def test_a_protective_stop_is_reported_with_exit_3(plate, monkeypatch, rtde):
    from tergodic_cli.robot.safety import fault_exit_code

    world, cfg = _setup(plate, monkeypatch, rtde)

    def pace(dt):
        world.advance(dt)
        if world.f_n > 0 and world.t > 5.0:  # exploring (the touch ends at ~3.8 s)
            world.protective = True  # e.g. someone leans on the arm
    arm, sensor = make_hardware("ur", IP)
    out = explore_with_hardware(plate[0], _explorer(plate, cfg), cfg, 40, arm, sensor, hw=HardwareRunConfig(move_speed=0.3),
                                pace=pace)
    assert out["final_state"] == "stopped" and fault_exit_code(out) == 3
    assert "protective stop" in out["stop_reason"]


# ------------------------------------------------------------------------------------------- set-up and refusals
def test_dry_run_only_reads(plate, monkeypatch, rtde):
    from tergodic_cli.backends import DryRunPlan, dry_run

    world, cfg = _setup(plate, monkeypatch, rtde)
    arm, sensor = make_hardware("ur", IP, read_only=True)
    q0 = world.q.copy()
    text = dry_run(arm, sensor, None, DryRunPlan(plate[0], cfg, start=(0.03, 0.02, 0.0)))
    assert "arm ur-rtde: connected" in text and "nothing was moved" in text
    assert world.control_created == 0 and world.calls == [] and np.array_equal(world.q, q0)


def test_refusals_are_one_line(monkeypatch, rtde):
    with pytest.raises(TergodicError, match="cannot connect to the UR at 10.0.0.9"):
        make_hardware("ur", "10.0.0.9")[0].connect()
    with pytest.raises(TergodicError, match="force estimate of another robot"):
        make_hardware("ur", IP, "franka")
    with pytest.raises(TergodicError, match="needs the robot's address"):
        make_hardware("ur", "")
    uninstall(monkeypatch, "rtde_control")
    with pytest.raises(TergodicError, match=r"rtde_control is not installed.*tergodic\[ur\]"):
        make_hardware("ur", IP)
