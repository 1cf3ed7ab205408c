"""The paper's controller on a real Franka: pylibfranka's 1 kHz torque loop (``--robot franka-torque``),
against a fake ``pylibfranka`` shaped like its 0.21.3 stubs (tests/fakes/pylibfranka.py) and the fake
world's physics; the F/T sensor is the Bota (fake bota_driver) read inside the loop.
"""

from __future__ import annotations

import gc
import threading

import numpy as np
import pytest

pytest.importorskip("pygafro")

from fakes import install, scenario, uninstall  # noqa: E402

from tergodic_cli.backends import HardwareRunConfig, explore_with_hardware, make_hardware  # noqa: E402
from tergodic_cli.errors import TergodicError  # noqa: E402
from tergodic_cli.robot.interfaces import ContactWrench, ToolLoad, WrenchSensor  # noqa: E402

FAST = HardwareRunConfig(move_speed=0.3)


@pytest.fixture(scope="module")
def plate():
    return scenario.make_plate()


@pytest.fixture
def fr(monkeypatch):
    return install(monkeypatch, "pylibfranka")


@pytest.fixture
def bota(monkeypatch):
    return install(monkeypatch, "bota_driver")


def _world(plate, monkeypatch, fr, **kw):
    w = scenario.world(plate, monkeypatch, **kw)
    monkeypatch.setattr(fr, "_NETWORK", {scenario.ROBOT_IP: w})
    return w


class FixedSensor(WrenchSensor):
    """A sensor that always reads ``w`` (sensor frame = TCP frame)."""

    def __init__(self, w):
        super().__init__(np.eye(4), tare_samples=1)
        self.w, self.t = np.asarray(w, dtype=float), 0.0

    def _sample(self):
        self.t += 0.001
        return self.t, self.w.copy()


def _fixed_arm(world_sensor, gains, isolate="inline"):
    from tergodic_cli.backends.franka.libfranka import LibfrankaConfig, make_libfranka_arm

    return make_libfranka_arm(LibfrankaConfig(ip=scenario.ROBOT_IP, isolate=isolate), world_sensor, gains=gains)


# ------------------------------------------------------------------------------------------- the torque of one tick
def test_the_torque_sent_is_the_line_impedance_plus_the_wrench_pid(plate, monkeypatch, fr):
    from tergodic_cli.robot.controller import ControllerGains
    from tergodic_cli.robot.interfaces import LineTarget

    world = _world(plate, monkeypatch, fr)
    # PID: P only on the axial force, no filters, no null-space terms: the law is J^T (K t + W_C) exactly
    g = ControllerGains(kp=2.0, ki=0.0, kd=0.0, force_filter_hz=0.0, nullspace_stiffness=0.0, nullspace_damping=0.0,
                        limit_stiffness=0.0)
    arm = _fixed_arm(FixedSensor([0.0, 0.0, 3.0, 0.0, 0.0, 0.0]), g)
    arm.connect()
    try:
        arm.bind(ContactWrench(ToolLoad(0.0, np.zeros(3)), np.eye(4)), None)
        T, J = world.T.copy(), world.J.copy()
        R, p = T[:3, :3], T[:3, 3]
        delta = np.array([0.004, -0.002, 0.0])  # the line 4 mm along the tool's x, -2 mm along its y
        a = p + R @ delta
        d = R[:, 2]
        arm.command_line(LineTarget(a, d, "press", force=5.0), x_ref=R[:, 0])  # no spin error
        arm.h.run_for(0.001)
        sent = world.robot.tau
        # independent: ee-frame wrench (k_x dx, k_y dy, kp (F_d - f)), moment 0, into the base frame
        f_ee = np.array([g.k_trans[0] * delta[0], g.k_trans[1] * delta[1], g.kp * (5.0 - 3.0)])
        expected = J.T @ np.concatenate([R @ f_ee, np.zeros(3)]) + fr.CORIOLIS * world.dq
        assert np.allclose(sent, expected, atol=1e-6), (sent, expected)
        assert np.allclose(arm.last_tau, sent)
    finally:
        arm.disconnect()
    assert world.robot._active is None  # the control was ended


# ------------------------------------------------------------------------------------------- isolation
def test_the_loop_process_ticks_while_the_run_process_is_busy(plate, monkeypatch, fr):
    """The loop runs in its own process: the run process holding the GIL and collecting garbage
    (a busy explorer, a log flush) does not hold it up; every tick reads one 1 ms state and writes."""
    from tergodic_cli.robot.controller import ControllerGains
    from tergodic_cli.robot.interfaces import LineTarget

    world = _world(plate, monkeypatch, fr)
    arm = _fixed_arm(FixedSensor(np.zeros(6)), ControllerGains(), isolate="process")
    arm.connect()
    try:
        assert arm.h.proc is not None and arm.h.proc.pid != threading.get_native_id()
        arm.bind(ContactWrench(ToolLoad(0.0, np.zeros(3)), np.eye(4)), None)
        T = arm.read_state().ee_pose
        arm.command_line(LineTarget(T[:3, 3], T[:3, 2], "move", speed=0.0))  # hold the line
        s0 = arm.h.state()
        n = 300
        junk = [[i] for i in range(200_000)]  # a heap for the collector to walk
        busy = 0
        while int(arm.h.link["tick"]) < int(s0["tick"]) + n:  # never yields the GIL on purpose
            busy += sum(range(500))
            gc.collect(0)
            assert busy < 10**13  # (a bound, so a broken loop fails instead of hanging)
            if not arm.h.alive():
                break
        del junk
        s1 = arm.h.state()
        ticks = int(s1["tick"]) - int(s0["tick"])
        assert ticks >= n, arm.h.message()
        # one tick = one 1 ms read of the arm: the loop's clock advanced by exactly its ticks
        assert float(s1["t"]) - float(s0["t"]) == pytest.approx(ticks * 1e-3, abs=1e-9)
        assert int(s1["fault"]) == 0
        assert np.any(s1["tau"] != 0.0)  # the line law ran (gravity is the SDK's; the null space pulls)
    finally:
        arm.disconnect()
    assert arm.h is None


# ------------------------------------------------------------------------------------------- the contact loop
def _run(plate, monkeypatch, fr, bota, steps=12, inject=None, world_kw=None):
    import fakes.bota_driver as fb

    world = _world(plate, monkeypatch, fr, **(world_kw or {}))
    monkeypatch.setattr(fb, "_WORLD", world)
    cfg = scenario.robot_config(plate)
    ex = scenario.explorer(plate, cfg)
    arm, sensor = make_hardware("franka-torque", scenario.ROBOT_IP, "bota", "dummy", isolate="inline")

    def pace(dt):
        arm.h.run_for(dt)
        if inject is not None:
            inject(world)

    events, samples = [], []
    out = explore_with_hardware(plate.capture, ex, cfg, steps, arm, sensor, on_step=lambda s, smp: samples.append(smp),
                                on_event=lambda s, m: events.append(m), hw=FAST, pace=pace)
    return out, world, events, samples, arm, ex


def test_exploration_presses_the_force_with_the_torque_loop(plate, monkeypatch, fr, bota):
    out, world, events, samples, arm, ex = _run(plate, monkeypatch, fr, bota, world_kw={"normal_force_bias": -1.0})
    assert out["final_state"] == "done" and out["stop_reason"] == "completed", events
    assert len(samples) == 12 and ex.step_index == 12
    assert out["controller"].startswith("line impedance + wrench PID")
    # the wrench PID's integral presses F_d despite 1 N of "joint friction" the fake world takes off
    assert out["force_mean_N"] == pytest.approx(5.0, rel=0.03)
    assert out["force_rms_error_rel"] < 0.25  # (the fake plate is a point cloud: a tick at a normal jump spikes)
    assert out["track_mm_median"] < 1.0 and out["tilt_deg_median"] < 2.0
    assert ex.metrics()["touched_fraction"] > 0
    s, _ = world.surface(world.T[:3, 3])
    assert s >= 0.8 * out["robot_config"]["retreat_distance"]  # lifted after the run
    assert world.robot._active is None and arm.h is None


def test_a_force_over_the_limit_ends_lifted_with_exit_3(plate, monkeypatch, fr, bota):
    from tergodic_cli.robot.safety import fault_exit_code

    def spike(world):
        if world.f_n > 0 and world.t > 9.0:  # exploring
            world.normal_force_bias = 20.0  # something pushes back: over the 15 N limit, below the arm's 40 N reflex
    out, world, events, *_ = _run(plate, monkeypatch, fr, bota, steps=30, inject=spike)
    assert out["final_state"] == "stopped" and fault_exit_code(out) == 3
    assert out["stop_reason"].startswith("the 1 kHz loop saw a contact force")  # caught inside the loop, within a tick
    assert "retreating" in out["stop_reason"]
    assert any("retreat -> stopped" in e for e in events)
    assert world.f_n == 0.0 and world.robot._active is None
    s, _ = world.surface(world.T[:3, 3])
    assert s > 0.005  # lifted off the surface


# ------------------------------------------------------------------------------------------- set-up and refusals
def test_dry_run_needs_no_realtime_kernel_and_sends_nothing(plate, monkeypatch, fr, bota):
    import fakes.bota_driver as fb

    from tergodic_cli.backends import DryRunPlan, dry_run

    world = _world(plate, monkeypatch, fr, noise=0.0)
    monkeypatch.setattr(fb, "_WORLD", world)
    monkeypatch.setattr(fr, "_REALTIME_KERNEL", False)
    arm, sensor = make_hardware("franka-torque", scenario.ROBOT_IP, "bota", "dummy", read_only=True)
    q0 = world.q.copy()
    text = dry_run(arm, sensor, None, DryRunPlan(plate.capture, scenario.robot_config(plate), start=(0.03, 0.02, 0.0)))
    assert "arm franka-libfranka: connected" in text and "nothing was moved" in text
    assert world.robot.n_writes == 0 and world.robot._active is None and np.array_equal(world.q, q0)
    # the same arm for a run needs the real-time kernel: libfranka's refusal, one line
    arm, _ = make_hardware("franka-torque", scenario.ROBOT_IP, "bota", "dummy", isolate="inline")
    with pytest.raises(TergodicError, match="PREEMPT_RT"):
        arm.connect()


def test_refusals_are_one_line(monkeypatch, fr):
    with pytest.raises(TergodicError, match="needs a wrist F/T sensor"):
        make_hardware("franka-torque", scenario.ROBOT_IP, "franka")
    uninstall(monkeypatch, "pylibfranka")
    with pytest.raises(TergodicError, match=r"pylibfranka is not installed.*tergodic\[libfranka\]"):
        make_hardware("franka-torque", scenario.ROBOT_IP, "bota", "dummy")
