"""The contact loop on hardware: an :class:`ImpedanceArm` (franky) and a ``WrenchSensor`` behind
the loop's :class:`~tergodic_cli.robot.interfaces.Arm` (docs/hardware.md).

One control period streams one impedance *reference* to the SDK's 1 kHz loop, at ``arm.stream_hz``
(:mod:`tergodic_cli.backends.impedance`): the line target, its force a spring offset trimmed by a
slow integrator on the measured force. Free-space moves: the SDK's planned joint move to the picture
pose, then a Cartesian min-jerk in impedance to the hover pose. Contact is what the F/T sensor says
(the axial force at or above the threshold; the contact point is the TCP). ``pace(dt)`` times each
period: real time by default (sleep to the period's end), a simulated world's ``advance`` in tests.
"""

from __future__ import annotations

import math
import time
from contextlib import suppress
from dataclasses import dataclass, field, replace
from types import SimpleNamespace
from typing import Callable

import numpy as np

from tergodic_cli.config import Config
from tergodic_cli.backends.impedance import ForceLoop, LineImpedanceGains, hold_target, line_impedance_target
from tergodic_cli.errors import require
from tergodic_cli.robot import kernels as Kn
from tergodic_cli.robot.controller import min_jerk
from tergodic_cli.robot.ga import matrix_to_rotvec, pose_matrix, rotvec_to_matrix
from tergodic_cli.robot.interfaces import ContactWrench, LineTarget, Observation, ToolLoad
from tergodic_cli.robot.run import SETTLE_S, ContactRun, object_pose
from tergodic_cli.robot.safety import fmt_xyz


@dataclass
class HardwareRunConfig(Config):
    """Settings of a run on hardware that the simulation does not have.

    gains : the impedance line controller (:class:`LineImpedanceGains`).
    tool_load : mass (kg) and centre of mass (sensor frame, m) of everything beyond the F/T sensor;
        the tare at the hover pose removes the weight at that orientation, this the change since.
    move_speed : m/s peak TCP speed of the Cartesian move to the hover pose.
    go_to_picture : start with a planned joint move to the robot config's picture pose.
    force_filter_hz : cut-off of the first-order filter on the measured force (contact detection).
    """

    gains: LineImpedanceGains = field(default_factory=LineImpedanceGains)
    tool_load: ToolLoad = field(default_factory=lambda: ToolLoad(0.0, np.zeros(3)))
    move_speed: float = 0.1
    go_to_picture: bool = True
    force_filter_hz: float = 10.0


class _PlanArm:
    """A connected ImpedanceArm as far as planning needs it: its limits, period and present state."""

    def __init__(self, arm):
        self.dev, self.name, self.dt = arm, arm.name, 1.0 / float(arm.stream_hz)
        self.q_min, self.q_max, self.dq_max = arm.q_min, arm.q_max, arm.dq_max

    def bind(self, *args) -> None:
        pass

    def get_observation(self, sensor: bool = False) -> Observation:
        return Observation(self.dev.read_state(), None, np.zeros(6))


class StreamedArm(_PlanArm):
    """An :class:`~tergodic_cli.backends.impedance.ImpedanceArm` and its F/T sensor as the loop's Arm.

    Parameters
    ----------
    arm : an ImpedanceArm (e.g. :class:`~tergodic_cli.backends.franka.FrankyArm`); sensor : a
        WrenchSensor (Bota, Net F/T, or the arm's own estimate). Both are connected here.
    robot_cfg : the RobotConfig (picture_q); hw : the :class:`HardwareRunConfig`.
    pace : called as pace(dt) once per period (None: real time).
    """

    def __init__(self, arm, sensor, robot_cfg, hw: HardwareRunConfig | None = None, pace: Callable[[float], None] | None = None):
        for name in ("connect", "read_state", "command_impedance", "stop", "fault", "move_joints"):
            require(hasattr(arm, name), f"the arm backend {type(arm).__name__} has no {name}()",
                    "use an ImpedanceArm backend (e.g. FrankyArm) for --robot franka")
        super().__init__(arm)
        self.sensor, self.cfg, self.hw = sensor, robot_cfg, hw or HardwareRunConfig()
        self.joint_names = list(arm.joint_names)
        self._pace = pace or self._realtime
        self._t_next = None
        arm.connect()
        if hasattr(sensor, "connect"):
            sensor.connect()
        self.contact_wrench = ContactWrench(self.hw.tool_load, sensor.frame_in_ee)
        self.t = self.t_origin = float(arm.read_state().t)
        self.force = 0.0
        self._alpha = 1.0 - math.exp(-2.0 * math.pi * self.hw.force_filter_hz * self.dt)
        self.force_loop = ForceLoop(self.hw.gains, float(robot_cfg.force))
        self.spin_ref = np.array([1.0, 0.0, 0.0])
        self.threshold = float(robot_cfg.contact_threshold)
        self.ts = self._obs = self._mode = self._guard = None
        self._axial = 0.0
        #: The device runs the paper's line controller itself (a torque loop, :mod:`~tergodic_cli.backends.torque`):
        #: it takes the line targets as they are, not impedance references.
        self.lines = hasattr(arm, "command_line")
        if self.lines:
            arm.bind(self.contact_wrench, None)

    @property
    def tau(self) -> np.ndarray:
        """Measured joint torques when the SDK reports them (franky: tau_J); the commanded ones live inside the SDK."""
        return getattr(self.dev, "measured_tau", getattr(self.dev, "last_tau", np.zeros(7)))

    def bind(self, guard, tick_stats, force_desired: float, threshold: float) -> None:
        self.ts, self.threshold, self._guard = tick_stats, float(threshold), guard
        self.force_loop.F_d = float(force_desired)
        if self.lines:
            self.dev.bind(self.contact_wrench, guard)

    def get_observation(self, sensor: bool = True) -> Observation:
        st = self.dev.read_state()
        self.t = float(st.t)
        if not sensor:
            self._obs = Observation(st, None, np.zeros(6))
            return self._obs
        rd = self.sensor.read()
        w = self.contact_wrench(rd.wrench, st.ee_pose)
        if getattr(rd, "valid", True) and self.ts is not None:
            Kn.tick_stats(st.ee_pose, w, self.ts)
        if math.isfinite(float(w[2])):
            self.force += self._alpha * (float(w[2]) - self.force)
        self._obs = Observation(st, rd, w)
        return self._obs

    def send_action(self, target: LineTarget) -> None:
        """Stream the impedance reference of ``target`` for one period."""
        if self.lines:  # the device's 1 kHz loop runs the line controller and its wrench PID
            self.dev.command_line(target, self.spin_ref, self.threshold,
                                  wrench=self._obs.wrench if self._obs is not None else None)
            self._mode = target.mode
            self._pace(self.dt)
            return
        obs = self._obs
        st = obs.state
        a, d = np.asarray(target.a, dtype=float), np.asarray(target.d, dtype=float)
        if target.mode == "press":
            if self._mode == "move":  # bumpless: the press continues from the contact force
                self.force_loop.start_from(self.force)
            self.force_loop.F_d = float(target.force)
            f = self.force_loop.track(float(obs.wrench[2]), self.dt)
            ref = line_impedance_target(st.pos, a, d, self.spin_ref, f, self.hw.gains, target.v_line)
        else:  # the set-point advances along the line at the commanded speed, from the TCP's own point
            if self._mode != "move":
                self._axial = float((np.asarray(st.pos) - a) @ d)
            self._axial += target.speed * self.dt
            ref = line_impedance_target(st.pos, a, d, self.spin_ref, 0.0, self.hw.gains, target.v_line,
                                        axial=self._axial, axial_speed=target.speed)
        self._mode = target.mode
        self._send(ref)

    def _send(self, ref) -> None:
        self.dev.command_impedance(ref)
        self._pace(self.dt)

    def _realtime(self, dt: float) -> None:
        now = time.perf_counter()
        if self._t_next is None or now - self._t_next > 0.1:  # first period, or far behind: re-anchor
            self._t_next = now
        self._t_next += dt
        lag = self._t_next - time.perf_counter()
        if lag > 0:
            time.sleep(lag)

    def reach(self, T: np.ndarray) -> str | None:
        return None  # the SDK's impedance loop finds its own joints; its reflexes report the rest

    def move_to(self, T: np.ndarray, check):
        """The planned joint move to the picture pose (``go_to_picture``), then a Cartesian min-jerk
        in impedance to ``T``, every period checked."""
        if self.hw.go_to_picture:
            self.dev.move_joints(self._picture_q())
        self._mode = None
        T0 = self.dev.read_state().ee_pose
        dist = float(np.linalg.norm(T[:3, 3] - T0[:3, 3]))
        phi = matrix_to_rotvec(T[:3, :3] @ T0[:3, :3].T)
        duration = max(1.0, 1.875 * max(dist / self.hw.move_speed, float(np.linalg.norm(phi)) / 0.5))
        p0, p1 = T0[:3, 3], T[:3, 3]
        for i in range(int(math.ceil(duration / self.dt)) + int(round(SETTLE_S / self.dt))):
            s, ds = min_jerk(np.zeros(1), np.ones(1), duration, (i + 1) * self.dt)
            s = float(s[0])
            pose = pose_matrix(rotvec_to_matrix(phi * s) @ T0[:3, :3], p0 + (p1 - p0) * s)
            fault = check(self.get_observation())
            if fault is not None:
                return fault
            ref = hold_target(pose, self.hw.gains)
            ref.twist[:3] = (p1 - p0) * float(ds[0])
            self._send(ref)
        return None

    def _picture_q(self) -> np.ndarray:
        """The run's picture posture, else the arm's own."""
        q = self.cfg.picture_q if self.cfg.picture_q is not None else self.dev.home
        return np.asarray(q, dtype=float)

    def to_picture(self, check):
        self.dev.stop()
        self.dev.move_joints(self._picture_q())
        self._mode = None
        return None

    def hold(self, seconds: float) -> None:
        pose = self.dev.read_state().ee_pose.copy()
        for _ in range(max(1, int(round(seconds / self.dt)))):
            self.t = float(self.dev.read_state().t)
            self._send(hold_target(pose, self.hw.gains))
        self._mode = None

    def tare(self) -> None:
        self.sensor.tare()
        self.contact_wrench.tare_at(self.dev.read_state().ee_pose[:3, :3])
        self.force = 0.0
        if self.lines:  # the loop computes the contact wrench too
            self.dev.bind(self.contact_wrench, self._guard)

    def contact(self, obs) -> tuple[np.ndarray | None, float, float]:
        """The TCP when the filtered axial force is at or above the contact threshold, that force, and
        the press angle (0: the F/T sensor cannot tell it)."""
        tcp = obs.state.ee_pose[:3, 3]
        return (tcp.copy() if self.force >= self.threshold else None), float(self.force), 0.0

    def link_poses(self) -> dict:
        return {}

    def fault(self) -> str | None:
        return self.dev.fault()

    def stop(self) -> None:
        self.dev.stop()
        self._mode = None

    def summary(self) -> dict:
        out = {"stream_hz": 1.0 / self.dt, "hardware_config": self.hw.to_dict()}
        if self.lines:
            out["controller"] = self.dev.controller
        return out

    def disconnect(self) -> None:
        _disconnect(self.dev, self.sensor)


def explore_with_hardware(capture, explorer, robot_cfg, steps: int, arm, sensor, on_step=None, on_event=None,
                          hw: HardwareRunConfig | None = None, pace=None, on_log=None) -> dict:
    """Run ``steps`` explorer steps on real (or fake-SDK) hardware; same contract as ``explore_with_robot``.

    arm : an ImpedanceArm (e.g. :class:`~tergodic_cli.backends.franka.FrankyArm`), sensor : a
    WrenchSensor (Bota, Net F/T, or the arm's own estimate); both are connected here and the arm is
    stopped and disconnected at the end, whatever happens. Returns the robot summary extras.
    """
    from tergodic_cli.robot.config import validate_robot_config

    validate_robot_config(replace(robot_cfg, backend="pybullet"))  # the shared field checks
    T_obj = object_pose(capture, robot_cfg, guess=False)
    driver = None
    try:
        driver = StreamedArm(arm, sensor, robot_cfg, hw, pace)
        with ContactRun(capture, explorer, robot_cfg, driver, T_obj, on_event=on_event, on_log=on_log) as run:
            _keep_within_tilt(run)
            return run.run(steps, on_step)
    finally:
        if driver is None:
            _disconnect(arm, sensor)


def _keep_within_tilt(run: ContactRun) -> None:
    """Without a reach planner here (it needs the simulator's chain and scene) the tool's axis stays
    within ``max_tool_tilt_deg`` of straight down: where the normal lies beyond that the target is
    dropped before contact, so the tool never presses at an angle (issue 15)."""
    up = run.normals @ run.T_obj[:3, :3].T[:, 2]  # the normals' vertical component, base frame
    run.reachable = up >= math.cos(math.radians(run.max_tilt_deg)) - 1e-9
    run.drop_unreachable()


def _disconnect(arm, sensor) -> None:
    try:
        arm.disconnect()
    finally:
        if hasattr(sensor, "disconnect"):
            sensor.disconnect()


def dry_run(arm, sensor, camera, plan) -> str:
    """Connect, read every device, and say what a run would do, without moving anything.

    Parameters
    ----------
    arm : an ImpedanceArm; sensor : a WrenchSensor or None; camera : a Camera or None.
    plan : a :class:`DryRunPlan` (capture, robot config, start, hardware config).

    Returns the report (several lines). Devices connected here are disconnected again; no
    command, move or reference is ever sent.
    """
    lines, opened = [], []
    try:
        arm.connect()
        opened.append(arm)
        st = arm.read_state()
        T = st.ee_pose
        lines.append(f"arm {arm.name}: connected; TCP at {fmt_xyz(T[:3, 3])} m, tool axis {fmt_xyz(T[:3, 2])}, "
                     f"q = {fmt_xyz(st.q)} rad")
        reason = arm.fault() if hasattr(arm, "fault") else None
        lines.append(f"  robot status: {reason or 'no error'}")
        margin = np.minimum(st.q - arm.q_min, arm.q_max - st.q)
        lines.append(f"  smallest joint-limit margin {np.degrees(margin.min()):.1f} deg (joint {int(np.argmin(margin)) + 1})")
        if sensor is not None:
            if hasattr(sensor, "connect"):
                sensor.connect()
                opened.append(sensor)
            reads = [sensor.read() for _ in range(20)]
            W = np.array([r.wrench for r in reads])
            ts = np.array([r.t for r in reads])
            rate_text = (f"{(len(ts) - 1) / (ts[-1] - ts[0]):.0f} samples/s" if ts[-1] > ts[0]
                         else "WARNING: the sample time did not advance over 20 reads")
            ok = np.all(np.isfinite(W))
            lines.append(f"F/T sensor {type(sensor).__name__}: {'ok' if ok else 'NON-FINITE SAMPLES'}; "
                         f"mean force {fmt_xyz(W[:, :3].mean(0))} N "
                         f"(not tared), noise {W[:, :3].std(0).max():.3f} N, {rate_text}")
        if camera is not None:
            camera.connect()
            opened.append(camera)
            pts, _ = camera.read()
            lines.append(f"camera {type(camera).__name__}: {len(pts)} valid points"
                         + (f", depth {pts[:, 2].min():.3f}..{pts[:, 2].max():.3f} m" if len(pts) else ""))
        if plan is not None:
            explorer = _StartAgent(plan.capture, plan.robot_cfg, plan.start)
            hw = plan.hw or HardwareRunConfig()
            run = ContactRun(plan.capture, explorer, plan.robot_cfg, _PlanArm(arm),
                             object_pose(plan.capture, plan.robot_cfg, guess=False),
                             on_event=lambda step, text: lines.append(f"plan: {text}"))
            _keep_within_tilt(run)
            a, d = run._agent_line()
            T_hover = run._hover_pose(a, d)
            tgt = line_impedance_target(a, a, d, T_hover[:3, 0], run.F_d, hw.gains)
            sc = run.safety
            lines.append(f"plan: object frame at {fmt_xyz(run.T_obj[:3, 3])} m; start {fmt_xyz(a)} m, tool axis {fmt_xyz(d)}")
            lines.append(f"  1. {'joint move to the picture pose, then ' if hw.go_to_picture else ''}Cartesian move to the hover pose "
                         f"{fmt_xyz(T_hover[:3, 3])} m ({np.linalg.norm(T_hover[:3, 3] - T[:3, 3]) * 1e3:.0f} mm away, "
                         f"<= {hw.move_speed * 1e3:.0f} mm/s)")
            lines.append(f"  2. tare, approach along the normal at {plan.robot_cfg.approach_speed * 1e3:.0f} mm/s until "
                         f"{run.threshold:g} N")
            lines.append(f"  3. press {run.F_d:g} N: first reference {fmt_xyz(tgt.pose[:3, 3])} m "
                         f"({run.F_d / hw.gains.k_normal * 1e3:.1f} mm past the surface along the normal, "
                         f"k_normal {hw.gains.k_normal:g} N/m, k_lateral {hw.gains.k_lateral:g} N/m)")
            lines.append(f"  4. {run.n_sub} references per explorer step of {plan.robot_cfg.explore_dt:g} s "
                         f"({arm.stream_hz:g} Hz to the SDK's 1 kHz impedance loop)")
            inside = all(run.guard.inside(x) for x in (a, T_hover[:3, 3]))
            lines.append(f"limits: force {run.guard.force_limit:g} N low-passed at {sc.force_filter_hz:g} Hz, "
                         f"{run.guard.force_impact_limit:g} N in one tick (retreat), workspace "
                         f"{fmt_xyz(sc.workspace_min)}..{fmt_xyz(sc.workspace_max)} m "
                         f"({'start inside' if inside else 'START OUTSIDE'}), TCP speed {sc.tcp_speed_max:g} m/s, "
                         f"joint velocity {sc.velocity_factor:g} x limits, sensor watchdog {sc.sensor_timeout * 1e3:.0f} ms, "
                         f"explorer watchdog {sc.explorer_timeout:g} s")
        lines.append("dry run: nothing was moved")
    finally:
        for dev in reversed(opened):
            with suppress(Exception):  # a report must not be lost to a failing close
                dev.disconnect()
    return "\n".join(lines)


@dataclass
class DryRunPlan:
    """What :func:`dry_run` plans against.

    capture : the Capture; robot_cfg : the RobotConfig; hw : the HardwareRunConfig (None = defaults).
    start : x,y,z in the capture frame, m (None = the capture's point nearest its centroid), planned
    with the capture's own normals, which needs no basis.
    """

    capture: object
    robot_cfg: object
    start: tuple[float, float, float] | None = None
    hw: HardwareRunConfig | None = None


class _StartAgent:
    """The first agent of a run, without an explorer: the start point and the capture's normal there."""

    def __init__(self, capture, robot_cfg, start):
        from tergodic_cli.robot.surface import oriented_normals, resolve_side

        pts = np.asarray(capture.points, dtype=float)
        x = pts.mean(axis=0) if start is None else np.asarray(start, dtype=float)
        i = int(np.argmin(np.linalg.norm(pts - x, axis=1)))
        n = oriented_normals(pts, resolve_side(robot_cfg.normal_side, getattr(capture, "meta", {}) or {}))[i]
        self.positions = pts[i][None, :]
        self.normals = n[None, :]
        self.cfg = SimpleNamespace(dt=robot_cfg.explore_dt)
