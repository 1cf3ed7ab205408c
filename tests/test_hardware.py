"""Real-hardware backends with fake SDKs (franky, bota_driver) installed under their real module names.

The fakes are shaped like the installed SDKs (see tests/fakes/); the physics behind them is a
quasi-static fake world (tests/fakes/world.py). Every backend runs the same exploration loop
(:func:`tergodic_cli.backends.explore_with_hardware`), with the one SafetyGuard.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

pytest.importorskip("pygafro")

from fakes import install, scenario, uninstall  # noqa: E402

from tergodic_cli.errors import TergodicError  # noqa: E402
from tergodic_cli.backends import (DryRunPlan, HardwareRunConfig, LineImpedanceGains, dry_run,  # noqa: E402
                                   explore_with_hardware, line_impedance_target, make_hardware)
from tergodic_cli.backends.extras import import_sdk  # noqa: E402
from tergodic_cli.backends.impedance import ImpedanceArm  # noqa: E402
from tergodic_cli.robot.interfaces import WrenchSensor  # noqa: E402

FAST = HardwareRunConfig(move_speed=0.3)


@pytest.fixture(scope="module")
def plate():
    return scenario.make_plate()


@pytest.fixture
def franky(monkeypatch):
    return install(monkeypatch, "franky")


@pytest.fixture
def bota(monkeypatch):
    return install(monkeypatch, "bota_driver")


def _run(plate, monkeypatch, ft=None, steps=12, world_kw=None, hw=FAST, cfg_kw=None, inject=None, **hw_kw):
    """The shared loop: fake world + backends from make_hardware + explore_with_hardware."""
    world = scenario.world(plate, monkeypatch, **(world_kw or {}))
    if ft == "bota":
        import fakes.bota_driver as fb

        monkeypatch.setattr(fb, "_WORLD", world)
    cfg = scenario.robot_config(plate, **(cfg_kw or {}))
    ex = scenario.explorer(plate, cfg)
    arm, sensor = make_hardware("franka", scenario.ROBOT_IP, ft, "dummy" if ft == "bota" else None, **hw_kw)
    events = []
    samples = []
    pace = world.advance if inject is None else (lambda dt: (world.advance(dt), inject(world, arm, dt)))
    out = explore_with_hardware(plate.capture, ex, cfg, steps, arm, sensor, on_step=lambda s, smp: samples.append(smp),
                                on_event=lambda s, m: events.append(m), hw=hw, pace=pace)
    return out, world, events, samples, arm, ex


# ------------------------------------------------------------------------------------------- extras
@pytest.mark.parametrize("module,extra", [("franky", "franka"), ("bota_driver", "bota"), ("pyrealsense2", "realsense")])
def test_missing_sdk_gives_the_install_hint(monkeypatch, module, extra):
    uninstall(monkeypatch, module)
    with pytest.raises(TergodicError) as e:
        import_sdk(module)
    assert str(e.value).startswith(f"{module} is not installed")
    assert f"pip install 'tergodic[{extra}]'" in str(e.value)


def test_make_hardware_refuses_before_connecting(monkeypatch):
    uninstall(monkeypatch, "franky")
    with pytest.raises(TergodicError, match=r"franky is not installed.*tergodic\[franka\]"):
        make_hardware("franka", "172.16.0.2")
    franky = install(monkeypatch, "franky")
    uninstall(monkeypatch, "bota_driver")
    with pytest.raises(TergodicError, match=r"bota_driver is not installed.*tergodic\[bota\]"):
        make_hardware("franka", "172.16.0.2", "bota", "dummy")
    with pytest.raises(TergodicError, match="needs the robot's address"):
        make_hardware("franka", "", "franka")
    with pytest.raises(TergodicError, match="unknown --ft"):
        make_hardware("franka", "1.2.3.4", "ati")
    with pytest.raises(TergodicError, match="--ft netft needs --ft-address"):
        make_hardware("franka", "1.2.3.4", "netft")
    assert franky._NETWORK == {}  # nothing was contacted


def test_sdk_errors_are_one_line(plate, monkeypatch, franky, bota, tmp_path):
    arm, _ = make_hardware("franka", "10.0.0.99")  # no robot there
    with pytest.raises(TergodicError) as e:
        arm.connect()
    assert "cannot connect to the Franka at 10.0.0.99" in str(e.value) and "activate FCI" in str(e.value)
    assert "\n" not in str(e.value)
    scenario.world(plate, monkeypatch)
    monkeypatch.setattr(franky, "_REALTIME_KERNEL", False)
    arm, _ = make_hardware("franka", scenario.ROBOT_IP)
    with pytest.raises(TergodicError, match="PREEMPT_RT"):
        arm.connect()
    arm, _ = make_hardware("franka", scenario.ROBOT_IP, realtime="ignore")
    arm.connect()  # the bench setting connects without a real-time kernel
    with pytest.raises(TergodicError, match="is not a Bota driver configuration"):
        make_hardware("franka", scenario.ROBOT_IP, "bota", "/dev/ttyUSB0")
    with pytest.raises(TergodicError, match="does not exist"):
        make_hardware("franka", scenario.ROBOT_IP, "bota", str(tmp_path / "missing.json"))


# ------------------------------------------------------------------------------------------- the impedance mapping
def test_line_target_presses_the_force_and_holds_the_line():
    g = LineImpedanceGains()
    rng = np.random.default_rng(3)
    for _ in range(5):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        a = rng.normal(size=3) * 0.1
        off = np.cross(d, rng.normal(size=3))
        off *= 0.004 / np.linalg.norm(off)  # 4 mm across the line
        p = a + 0.03 * d + off
        t = line_impedance_target(p, a, d, np.array([1.0, 0.0, 0.0]), 7.0, g, line_velocity=0.01 * d + np.array([0.02, 0, 0]))
        K = t.stiffness
        assert np.allclose(K, K.T) and np.linalg.eigvalsh(K).min() > 0
        np.testing.assert_allclose(t.pose[:3, 2], d, atol=1e-12)  # tool axis along the line
        spring = K[:3, :3] @ (t.pose[:3, 3] - p)
        assert spring @ d == pytest.approx(7.0, rel=1e-9)  # the force along the line, wherever the surface is
        lateral = spring - (spring @ d) * d
        np.testing.assert_allclose(lateral, -g.k_lateral * off, rtol=1e-9, atol=1e-12)  # pulled back onto the line
        assert abs(t.twist[:3] @ d) < 1e-12  # no velocity feed-forward along the line (the force owns it)


# ------------------------------------------------------------------------------------------- franky backend
def test_franky_arm_state_and_protocols(plate, monkeypatch, franky):
    world = scenario.world(plate, monkeypatch)
    arm, sensor = make_hardware("franka", scenario.ROBOT_IP)
    assert isinstance(arm, ImpedanceArm) and isinstance(sensor, WrenchSensor)
    arm.connect()
    st = arm.read_state()
    np.testing.assert_allclose(st.ee_pose, world.T, atol=1e-12)
    np.testing.assert_allclose(st.q, world.q)
    # the Jacobian franky reports is the derivative of the pose (finite differences through the world model)
    dq = np.array([0.3, -0.2, 0.1, 0.2, -0.1, 0.3, 0.2]) * 1e-4
    dx = 0.5 * (world.model.fk(world.q + dq)[:3, 3] - world.model.fk(world.q - dq)[:3, 3])
    np.testing.assert_allclose(st.jacobian[:3] @ dq, dx, atol=1e-9)
    assert st.t == pytest.approx(world.t)


def test_franky_set_ee_is_column_major(plate, monkeypatch, franky):
    world = scenario.world(plate, monkeypatch)
    T0 = world.T.copy()
    ne = np.eye(4)
    ne[:3, 3] = [0.01, -0.02, 0.05]
    arm, _ = make_hardware("franka", scenario.ROBOT_IP, ne_t_ee=ne)
    arm.connect()
    np.testing.assert_allclose(arm.read_state().ee_pose[:3, 3], T0[:3, 3] + T0[:3, :3] @ ne[:3, 3], atol=1e-12)


def test_franky_refuses_a_list_for_joint_motion(franky):
    # the real binding (franky-control 2.0) rejects a list; the backend always passes an ndarray
    with pytest.raises(TypeError, match="incompatible constructor arguments"):
        franky.JointMotion([0.0] * 7)
    franky.JointMotion(np.zeros(7), relative_dynamics_factor=0.1)


def test_move_joints_then_impedance(plate, monkeypatch, franky):
    world = scenario.world(plate, monkeypatch)
    arm, _ = make_hardware("franka", scenario.ROBOT_IP)
    arm.connect()
    q_goal = world.q + np.array([0.1, -0.05, 0.05, 0.1, 0.0, -0.1, 0.2])
    arm.move_joints(q_goal, 0.5)
    np.testing.assert_allclose(world.q, q_goal, atol=1e-4)
    with pytest.raises(TergodicError, match="outside the joint limits"):
        arm.move_joints(arm.q_max + 0.1)
    # hold a pose 1 cm away: the impedance loop in the "SDK" pulls the TCP there
    from tergodic_cli.backends.impedance import hold_target

    goal = world.T.copy()
    goal[:3, 3] += [0.01, 0.0, -0.01]
    for _ in range(100):
        arm.command_impedance(hold_target(goal, LineImpedanceGains()))
        world.advance(0.01)
    np.testing.assert_allclose(world.T[:3, 3], goal[:3, 3], atol=2e-4)
    assert world.robot.moves == ["JointMotion", "CartesianImpedanceTrackingMotion"]
    arm.move_joints(q_goal)  # ends the torque-mode controller first (TorqueStopMotion), then plans
    assert world.robot.moves[-2:] == ["TorqueStopMotion", "JointMotion"]


# ------------------------------------------------------------------------------------------- bota backend
def test_bota_lifecycle_tare_wrap_and_invalid(plate, monkeypatch, franky, bota):
    world = scenario.world(plate, monkeypatch, noise=0.0)
    monkeypatch.setattr(bota, "_WORLD", world)
    _, sensor = make_hardware("franka", scenario.ROBOT_IP, "bota", "dummy")
    sensor.connect()
    assert sensor.driver.get_driver_state() == bota.DriverState.ACTIVE
    assert sensor.driver.tare() is False  # the driver refuses to tare while streaming: we tare in software
    r0 = sensor.read()
    f, m = world.arm_wrench_on_tool()
    R_s = (world.T @ world.sensor_in_ee)[:3, :3]
    expect = np.concatenate([R_s.T @ f, R_s.T @ m]) + world.bias
    np.testing.assert_allclose(r0.wrench, expect, atol=1e-6)  # float32 in the driver's frames
    assert R_s[2, 2] == pytest.approx(-1.0, abs=1e-6)  # at the picture pose the tool axis points down
    assert r0.wrench[2] == pytest.approx(-world.tool_mass * 9.81 + world.bias[2], abs=1e-6)  # holding the tool up
    sensor.tare()
    np.testing.assert_allclose(sensor.read().wrench, 0.0, atol=1e-6)
    ts = []
    for _ in range(12):  # crosses the uint32 microsecond wrap 0.7 s in
        world.advance(0.1)
        ts.append(sensor.read().t)
    assert np.all(np.diff(ts) > 0.09) and np.all(np.diff(ts) < 0.11)
    world.sensor_fault = "nan"
    assert np.all(np.isnan(sensor.read().wrench))  # an invalid frame never reads as zero force
    sensor.disconnect()
    assert sensor.driver is None


# ------------------------------------------------------------------------------------------- the loop, every backend
@pytest.mark.parametrize("ft", ["franka", "bota"])
def test_exploration_loop_runs_on_each_backend(plate, monkeypatch, franky, bota, ft):
    out, world, events, samples, arm, ex = _run(plate, monkeypatch, ft=ft, world_kw={"normal_force_bias": -1.0})
    assert out["final_state"] == "done" and out["stop_reason"] == "completed", events
    assert len(samples) == 12 and ex.step_index == 12
    # force: the impedance spring plus the integral trim press F_d despite 1 N of joint friction
    assert out["force_mean_N"] == pytest.approx(5.0, rel=0.08)
    assert out["force_rms_error_rel"] < 0.1
    assert world.max_force < out["robot_config"]["safety"]["force_limit_factor"] * 5.0
    # every streamed tick counts (issue 15): the peak against the fake world's own largest contact force
    assert out["tick_steady"] > 0 and out["force_peak_N"] >= out["force_peak_5hz_N"]
    assert out["force_peak_N"] == pytest.approx(world.max_force, rel=0.05)
    # geometry: the tool stays on the agent's line and normal to the plate; contact deposited coverage
    assert out["track_mm_median"] < 1.0
    assert out["tilt_deg_median"] < 2.0
    assert out["contact_fraction"] == 1.0
    assert ex.metrics()["touched_fraction"] > 0
    # after the retreat the tool is off the surface and the controller stopped
    s, _ = world.surface(world.T[:3, 3])
    assert s >= 0.8 * out["robot_config"]["retreat_distance"]
    assert world.robot._active is None
    # samples follow the run-log contract
    for key in ("t_sim", "state", "ee_pose", "q", "dq", "tau", "wrench_measured", "wrench_desired", "force_normal",
                "in_contact", "contact_point", "tilt_deg", "track_mm"):
        assert key in samples[-1]
    json.dumps({k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in samples[-1].items()})


def test_without_the_force_trim_friction_shows(plate, monkeypatch, franky):
    # The same run with the integral trim off presses ~1 N short: the trim is what removes it.
    hw = HardwareRunConfig(move_speed=0.3, gains=LineImpedanceGains(force_ki=0.0))
    out, *_ = _run(plate, monkeypatch, world_kw={"normal_force_bias": -1.0}, hw=hw, steps=6)
    assert out["force_mean_N"] == pytest.approx(4.0, abs=0.2)


# ------------------------------------------------------------------------------------------- safety trips end safe
@pytest.mark.parametrize("bias,reason", [(30.0, "over the 30.0 N impact limit; retreating"),
                                         (15.0, "(low-passed at 10 Hz) over the 15.0 N limit; retreating")])
def test_force_spike_retreats_and_stops(plate, monkeypatch, franky, bota, bias, reason):
    # +30 N at 5 N: over the one-tick impact limit; +15 N: a sustained overload, caught by the low-passed limit
    def spike(world, arm, dt):
        if world.robot is not None and world.f_n > 0 and world.t > 9.0:  # exploring (the guarded touch ends ~7.5 s)
            world.normal_force_bias = bias  # something pushes back hard
    out, world, events, samples, arm, _ = _run(plate, monkeypatch, ft="bota", inject=spike, steps=30)
    assert out["final_state"] == "stopped"
    assert reason in out["stop_reason"]
    assert any("explore -> retreat" in e for e in events) and any("retreat -> stopped" in e for e in events)
    assert world.f_n == 0.0 and world.robot._active is None  # off the surface, controller ended
    assert samples[-1]["stop_reason"] == out["stop_reason"]


def test_stale_sensor_lifts_the_tool(plate, monkeypatch, franky, bota):
    # In contact a fault never ends in a hold while pressed (issue 15): the tool lifts, then stops.
    def freeze(world, arm, dt):
        if world.t > 9.0:
            world.sensor_fault = "freeze"
    out, world, events, *_ = _run(plate, monkeypatch, ft="bota", inject=freeze, steps=30)
    assert out["final_state"] == "stopped"
    assert "stopped updating" in out["stop_reason"] and "lifting the tool" in out["stop_reason"]
    assert any("explore -> retreat" in e for e in events)
    assert world.f_n == 0.0 and world.robot._active is None and np.allclose(world.dq, 0.0)


def test_robot_reflex_is_reported_not_fought(plate, monkeypatch, franky):
    def reflex(world, arm, dt):
        if world.t > 9.0 and world.robot._active is not None:
            world.robot.stop()  # e.g. the user pressed the external activation device
    out, world, events, *_ = _run(plate, monkeypatch, inject=reflex, steps=30)
    assert out["final_state"] == "stopped"
    assert "the Franka stopped" in out["stop_reason"] and "preempted" in out["stop_reason"]


def test_ctrl_c_retreats_and_summarises(plate, monkeypatch, franky):
    def interrupt(world, arm, dt):
        if world.t > 9.0 and not getattr(world, "_interrupted", False):
            world._interrupted = True
            raise KeyboardInterrupt
    out, world, events, samples, *_ = _run(plate, monkeypatch, inject=interrupt, steps=30)
    assert out["final_state"] == "stopped"
    assert out["stop_reason"].startswith("interrupted by the user (Ctrl-C)")
    assert world.f_n == 0.0 and world.robot._active is None
    assert any("retreat -> stopped" in e for e in events)


def test_unknown_object_pose_is_refused(plate, monkeypatch, franky):
    scenario.world(plate, monkeypatch)
    cfg = replace(scenario.robot_config(plate), object_pose=None)
    arm, sensor = make_hardware("franka", scenario.ROBOT_IP)
    with pytest.raises(TergodicError, match="pose in the robot base frame is unknown"):
        explore_with_hardware(plate.capture, scenario.explorer(plate, cfg), cfg, 3, arm, sensor)


@pytest.mark.parametrize("roll_deg, refused", [(50.0, False), (70.0, True)])
def test_hardware_never_presses_beyond_its_tilt_limit(plate, monkeypatch, franky, roll_deg, refused):
    # Without reach planning the tool's axis stays within max_tool_tilt_deg (60) of straight down: a
    # plate turned 70 deg has its whole target beyond that and is refused before anything moves.
    world = scenario.world(plate, monkeypatch)
    cfg = scenario.robot_config(plate)
    cfg = replace(cfg, object_pose=tuple(cfg.object_pose) + (roll_deg, 0.0, 0.0))
    arm, sensor = make_hardware("franka", scenario.ROBOT_IP)
    text = dry_run(arm, sensor, None, DryRunPlan(plate.capture, cfg, start=(0.03, 0.02, 0.0))) if not refused else None
    if refused:
        with pytest.raises(TergodicError, match="cannot follow the surface normal anywhere"):
            explore_with_hardware(plate.capture, scenario.explorer(plate, cfg), cfg, 3, arm, sensor)
        assert world.robot.moves == [] and world.robot._active is None and not arm.is_connected
    else:
        assert "dropped" not in text and "nothing was moved" in text


# ------------------------------------------------------------------------------------------- dry run
def test_dry_run_reads_everything_and_moves_nothing(plate, monkeypatch, franky, bota):
    from tergodic_cli.backends import make_camera

    world = scenario.world(plate, monkeypatch, noise=0.0)
    monkeypatch.setattr(bota, "_WORLD", world)
    rs = install(monkeypatch, "pyrealsense2")
    monkeypatch.setattr(rs, "_DEVICES", [rs.FakeDevice()])
    arm, sensor = make_hardware("franka", scenario.ROBOT_IP, "bota", "dummy")
    camera = make_camera("realsense")
    cfg = scenario.robot_config(plate)
    q0, t0 = world.q.copy(), world.t
    text = dry_run(arm, sensor, camera, DryRunPlan(plate.capture, cfg, start=(0.03, 0.02, 0.0)))
    assert "camera RealSenseCamera: 307200 valid points, depth 0.500..0.500 m" in text
    assert not rs._DEVICES[0].streaming
    assert world.robot.moves == [] and world.t == t0 and np.array_equal(world.q, q0)
    assert "nothing was moved" in text
    assert "force 15 N low-passed at 10 Hz, 30 N in one tick (retreat)" in text and "start inside" in text
    assert "press 5 N" in text and "16.7 mm past the surface" in text  # 5 N / 300 N/m
    assert "20 references per explorer step" in text
    assert f"{-world.tool_mass * 9.81 + world.bias[2]:.3f}" in text  # the untared weight the sensor reads
    assert not arm.is_connected and not sensor.is_connected
    assert "did not advance" in text  # the fake world's clock stood still: a stalled sensor is reported
