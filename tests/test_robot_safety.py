"""The safety guard, the state machine, the robot config and summarize_robot: pure logic, no simulator."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tergodic_cli.errors import TergodicError
from tergodic_cli.robot import RobotConfig, SafetyConfig, SafetyGuard, summarize_robot, validate_robot_config
from tergodic_cli.robot import statemachine as S
from tergodic_cli.backends.pybullet.arms.panda import DQ_MAX, Q_MAX, Q_MIN
from tergodic_cli.robot.surface import default_object_pose, parse_object_pose

Q_OK = np.array([0.0, 0.2, 0.0, -2.2, 0.0, 2.4, 0.785])


def _guard(**kw) -> SafetyGuard:
    return SafetyGuard(SafetyConfig(**kw), Q_MIN, Q_MAX, DQ_MAX, force_desired=5.0)


def test_guard_passes_a_normal_state():
    g = _guard()
    assert g.check_state(0.0, Q_OK, np.zeros(7), (0.5, 0.0, 0.3), 0.01) is None
    assert g.check_force(0.0, np.array([0.5, 0.2, 5.0, 0, 0, 0])) is None
    assert g.check_target(0.0, np.array([0.5, 0.0, 0.2])) is None


def _feed(g: SafetyGuard, forces, t0: float = 0.0, dt: float = 0.001):
    """Each |f| (along the tool axis) as one control tick; the tick and fault of the first fault, else (None, None)."""
    for i, f in enumerate(forces):
        fault = g.check_force(t0 + i * dt, np.array([0.0, 0.0, float(f), 0.3, 0.0, 0.0]))
        if fault is not None:
            return i, fault
    return None, None


def test_force_limit_defaults_to_three_times_desired_and_retreats():
    g = _guard()
    assert g.force_limit == pytest.approx(15.0) and g.force_impact_limit == pytest.approx(30.0)
    i, f = _feed(g, [5.0] * 300 + [40.0])  # one tick over the impact limit
    assert i == 300 and f.kind == "force" and f.action == "retreat" and "40.0 N" in f.reason and "impact" in f.reason
    assert "\n" not in f.reason
    assert _guard().check_force(1.0, np.array([np.nan, 0, 0, 0, 0, 0])).kind == "force"
    assert _feed(_guard(force_limit=30.0, force_impact_limit=50.0), [20.0] * 2000) == (None, None)
    # at low desired forces the default keeps a floor above the contact's jitter: F_d + 5 N
    assert SafetyGuard(SafetyConfig(), np.full(7, -3.0), np.full(7, 3.0), np.full(7, 2.0), 1.0).force_limit == 6.0
    assert SafetyGuard(SafetyConfig(), np.full(7, -3.0), np.full(7, 3.0), np.full(7, 2.0), 2.0).force_limit == 7.0
    assert SafetyGuard(SafetyConfig(), np.full(7, -3.0), np.full(7, 3.0), np.full(7, 2.0), 10.0).force_limit == 30.0
    assert SafetyGuard(SafetyConfig(), np.full(7, -3.0), np.full(7, 3.0), np.full(7, 2.0), 10.0).force_impact_limit == 50.0
    assert SafetyGuard(SafetyConfig(force_limit=2.5), np.full(7, -3.0), np.full(7, 3.0), np.full(7, 2.0), 1.0).force_limit == 2.5
    assert _guard(force_limit=40.0).force_impact_limit == 40.0  # a raised limit raises the impact default with it
    with pytest.raises(TergodicError, match="impact limit"):
        _guard(force_limit=40.0, force_impact_limit=35.0)


def test_a_single_tick_spike_under_the_impact_limit_does_not_stop():
    """The contact's 1 kHz spikes (1-5 ticks, up to 3.3 F_d measured) pass the low-passed limit: a 25 N tick at
    F_d = 5 N (over the 15 N limit, under the 30 N impact limit), and five 14 N ticks in a row."""
    assert _feed(_guard(), [5.0] * 200 + [25.0] + [5.0] * 200) == (None, None)
    assert _feed(_guard(), [5.0] * 200 + [14.0] * 5 + [5.0] * 200 + [29.9] + [5.0] * 50) == (None, None)


@pytest.mark.parametrize("over", [16.0, 20.0, 29.0])
def test_a_sustained_overload_stops_within_the_filter_delay(over):
    """A step from F_d = 5 N to ``over`` stops at the tick the first-order low-pass (10 Hz) reaches the limit:
    n = ceil(ln((over - 15) / (over - 5)) / ln(1 - α)), α = 1 - exp(-2π 10 Hz 1 ms) (< 18 ms for a step to 20 N)."""
    g = _guard()
    alpha = 1.0 - math.exp(-2.0 * math.pi * 10.0 * 0.001)
    i, f = _feed(g, [5.0] * 1000 + [over] * 500)
    assert f is not None and "low-passed at 10 Hz" in f.reason and "over the 15.0 N limit" in f.reason
    # the filter has settled at 5 N within 1e-27 by tick 1000
    n = math.ceil(math.log((over - 15.0) / (over - 5.0)) / math.log(1.0 - alpha))
    assert i - 1000 + 1 == n, (i, n)
    assert f.data["force"] > 15.0 and f.data["force_tick"] == over
    if over == 20.0:
        assert n <= 18


def test_joint_limits_and_speeds_hold():
    g = _guard()
    q = Q_OK.copy()
    q[3] = Q_MAX[3] - 0.01  # inside the 0.02 rad margin
    f = g.check_state(0.0, q, np.zeros(7), (0.5, 0, 0.3), 0.0)
    assert f.kind == "joint_position" and f.action == "hold" and "joint 4" in f.reason
    dq = np.zeros(7)
    dq[5] = -0.95 * DQ_MAX[5]
    f = g.check_state(0.0, Q_OK, dq, (0.5, 0, 0.3), 0.0)
    assert f.kind == "joint_velocity" and "joint 6" in f.reason
    assert g.check_state(0.0, Q_OK, np.zeros(7), (0.5, 0, 0.3), 0.8).kind == "tcp_speed"


def test_workspace_box_for_tool_and_targets():
    g = _guard(workspace_min=(0.2, -0.3, 0.0), workspace_max=(0.7, 0.3, 0.6))
    assert g.check_state(0.0, Q_OK, np.zeros(7), (0.75, 0, 0.3), 0.0).kind == "workspace"
    f = g.check_target(0.0, np.array([0.5, 0.5, 0.2]))
    assert f.kind == "workspace" and f.action == "hold" and "outside the workspace box" in f.reason
    assert g.check_target(0.0, np.array([0.5, np.inf, 0.2])).kind == "target"
    with pytest.raises(TergodicError):
        _guard(workspace_min=(0.5, 0, 0), workspace_max=(0.4, 1, 1))


def test_sensor_watchdog_needs_fresh_samples():
    g = _guard(sensor_timeout=0.02)
    w = np.zeros(6)
    for i in range(30):  # a healthy 1 kHz stream
        assert g.check_sensor(i * 1e-3, i * 1e-3, w) is None
    faults = [g.check_sensor(i * 1e-3, 0.029, w) for i in range(30, 60)]  # the driver repeats the t = 0.029 sample
    assert all(f is None for f in faults[:19])  # up to 20 ms late is tolerated
    f = faults[-1]
    assert f is not None and f.kind == "sensor" and f.action == "hold" and "stopped updating" in f.reason
    assert _guard().check_sensor(0.0, 0.0, np.array([0, 0, np.nan, 0, 0, 0])).kind == "sensor"


def test_explorer_watchdog():
    g = _guard(explorer_timeout=0.5)
    assert g.check_explorer(10.0) is None  # no target yet: nothing to be late
    g.feed_target(1.0)
    assert g.check_explorer(1.4) is None
    f = g.check_explorer(1.6)
    assert f.kind == "explorer" and "stalled" in f.reason


def test_state_machine_logs_and_refuses_illegal_transitions():
    events = []
    sm = S.StateMachine(on_event=lambda step, msg: events.append((step, msg)))
    sm.go(S.HOVER, 0.0, 0, "moving")
    sm.go(S.APPROACH, 1.0, 0, "down")
    with pytest.raises(RuntimeError):
        sm.go(S.DONE, 1.5, 0, "skipping the exploration")
    sm.go(S.EXPLORE, 2.0, 0, "contact")
    sm.go(S.HOLD, 3.0, 7, "fault")
    sm.go(S.STOPPED, 3.5, 7, "held")
    assert sm.finished and [t.target for t in sm.history] == ["hover", "approach", "explore", "hold", "stopped"]
    assert events[-2] == (7, "robot explore -> hold at t=3.000 s: fault")


def test_robot_config_validation():
    validate_robot_config(RobotConfig())
    for bad, needle in [(dict(force=-1.0), "--force"), (dict(force=100.0), "sponge"),
                        (dict(explore_dt=0.0015), "whole number"), (dict(backend="ros"), "backend"),
                        (dict(contact_force=6.0), "contact threshold")]:
        with pytest.raises(TergodicError, match=needle):
            validate_robot_config(RobotConfig(**bad))
    assert round(RobotConfig().explore_dt / RobotConfig().physics_dt) == 200  # control steps per explorer step
    assert RobotConfig(contact_force=None, force=5.0).contact_threshold == pytest.approx(1.0)


def test_object_pose_parsing():
    np.testing.assert_allclose(parse_object_pose([0.5, 0.1, 0.0])[:3, 3], [0.5, 0.1, 0.0])
    T = parse_object_pose([0.5, 0, 0, 0, 0, 90])
    np.testing.assert_allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    T = parse_object_pose([0.5, 0, 0, 0, 0, math.sin(math.pi / 4), math.cos(math.pi / 4)])
    np.testing.assert_allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    for bad in ([0.5, 0], [500, 0, 0], [0.5, 0, 0, 0, 0, 0, 2.0]):
        with pytest.raises(TergodicError):
            parse_object_pose(bad)
    pts = np.array([[-0.1, -0.1, 0.0], [0.1, 0.1, 0.05]])
    moved = pts + default_object_pose(pts)[:3, 3]
    np.testing.assert_allclose(moved.mean(axis=0)[:2], [0.5, 0.0])
    assert moved[:, 2].min() == pytest.approx(0.2)


def _sample(t, f, contact=True, state="explore", tilt=1.0, track=2.0, **extra):
    return {"t_sim": t, "t_wall": t / 4.0, "state": state, "in_contact": contact, "force_normal": f,
            "wrench_desired": [0, 0, 5.0, 0, 0, 0], "tilt_deg": tilt, "track_mm": track, **extra}


def test_summarize_robot_against_hand_computation():
    # 0.2 s per sample; contact from t = 0; the first 0.5 s (samples at 0.0, 0.2, 0.4) are transient.
    forces = [9.0, 9.0, 9.0, 5.5, 4.5, 5.0, 6.0]
    samples = [_sample(0.2 * i, f, tilt=i, track=10 - i) for i, f in enumerate(forces)]
    samples.append(_sample(1.4, 0.0, contact=False, tilt=50.0, track=50.0))
    samples[-1]["touched_sponge"] = 0.4
    samples[-1]["touched_agent"] = 0.5
    out = summarize_robot(samples)
    steady = np.array([5.5, 4.5, 5.0, 6.0])
    assert out["force_rms_error_rel"] == pytest.approx(math.sqrt(np.mean(((steady - 5) / 5) ** 2)))
    assert out["contact_fraction"] == pytest.approx(7 / 8)
    assert out["tilt_deg_median"] == pytest.approx(3.0)  # median of 0..6, the no-contact sample excluded
    assert out["track_mm_median"] == pytest.approx(7.0)
    assert out["realtime_factor"] == pytest.approx(4.0)
    assert out["touched_sponge"] == 0.4 and out["touched_agent"] == 0.5
    assert out["stop_reason"] == "completed" and out["steady_samples"] == 4
    # columns give the same answer (the replay verb may pass columns)
    cols = {k: [s.get(k) for s in samples] for k in samples[0]}
    cols["touched_sponge"] = [s.get("touched_sponge") for s in samples]
    assert summarize_robot(cols)["force_rms_error_rel"] == out["force_rms_error_rel"]


def test_summarize_robot_restarts_settling_after_lost_contact():
    samples = [_sample(0.2 * i, 5.0) for i in range(5)]
    samples.append(_sample(1.0, 0.0, contact=False))
    samples += [_sample(1.2 + 0.2 * i, 9.0 if i < 3 else 5.0) for i in range(5)]  # re-contact transient
    out = summarize_robot(samples)
    assert out["force_rms_error_rel"] == pytest.approx(0.0)
    assert summarize_robot([], stop_reason="x")["stop_reason"] == "x"
    assert summarize_robot(samples + [dict(_sample(3.0, 5.0), stop_reason="boom")])["stop_reason"] == "boom"


def test_the_spin_reference_keeps_the_wrist_inside_its_range():
    """The sponge is round, so its spin is free: a spin reference that would turn the last joint past
    WRIST_MARGIN from its limit is turned back about the tool axis (the corpus bunny's joint 7 hit its
    limit at step 10 otherwise); one inside the range is kept as it is."""
    import math
    from types import SimpleNamespace

    from tergodic_cli.robot.run import WRIST_MARGIN, ContactRun

    R = np.eye(3)  # tool axis z, tool x = base x
    J = np.zeros((6, 7))
    J[3:6, -1] = [0.0, 0.0, 1.0]  # the last joint turns the tool about its axis, + sense
    hi = 2.877
    q = np.zeros(7)
    q[-1] = hi - 0.1  # already inside the margin
    obs = SimpleNamespace(state=SimpleNamespace(ee_pose=np.eye(4), jacobian=J, q=q))
    run = SimpleNamespace(guard=SimpleNamespace(q_lo=-hi * np.ones(7), q_hi=hi * np.ones(7)))

    def spin_of(x):
        return math.atan2(x[1], x[0])

    want = np.array([math.cos(0.5), math.sin(0.5), 0.0])  # asks +0.5 rad more: past the limit
    got = ContactRun._spin_in_wrist(run, want, obs)
    assert spin_of(got) == pytest.approx((hi - WRIST_MARGIN) - q[-1], abs=1e-9)  # turned back to hi - margin
    assert np.linalg.norm(got) == pytest.approx(1.0) and abs(got @ R[:, 2]) < 1e-12
    back = np.array([math.cos(-0.5), math.sin(-0.5), 0.0])  # towards mid-range: kept
    np.testing.assert_array_equal(ContactRun._spin_in_wrist(run, back, obs), back)
    J[3:6, -1] = [0.0, 0.0, -1.0]  # a joint turning the other way: the same reference is now inside
    np.testing.assert_array_equal(ContactRun._spin_in_wrist(run, want, obs), want)
