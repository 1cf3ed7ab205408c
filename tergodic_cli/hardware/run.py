"""The exploration loop on hardware-shaped devices: an :class:`ImpedanceArm` and a ``WrenchSensor``.

The same state machine as the simulation (:mod:`tergodic_cli.robot.statemachine`) and the same
:class:`~tergodic_cli.robot.safety.SafetyGuard`, but one control tick is one *reference* streamed to
the SDK's 1 kHz impedance loop (:mod:`tergodic_cli.hardware.impedance`), at ``arm.stream_hz``:

    picture -> hover (Cartesian min-jerk in impedance) -> tare -> approach (push d_n·v along the
    normal until the contact threshold) -> explore (line target + force trim, one explorer step
    every explore_dt) -> retreat -> done;  a fault -> retreat or hold -> stopped.

Contact on hardware is what the F/T sensor says: the force along the tool axis at or above the
contact threshold; the contact point is then the TCP (the sponge tip), deposited as coverage and
fed back as the agent's position (paper eq. 22). Ctrl-C during a run is a fault like any other:
the tool retreats, the controller stops, and the summary carries the reason.

Timing comes from ``pace(dt)``, called once per tick: real time by default (sleep to the tick
boundary); a simulated world's ``advance`` in tests.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from tergodic_cli.errors import TergodicError, require
from tergodic_cli.hardware.impedance import ForceLoop, LineImpedanceGains, hold_target, line_impedance_target, tool_rotation
from tergodic_cli.robot import statemachine as S
from tergodic_cli.robot import kernels as Kn
from tergodic_cli.robot.controller import guarded_approach_speed
from tergodic_cli.robot.interfaces import ContactWrench, ToolLoad
from tergodic_cli.robot.run import clamp_tilt
from tergodic_cli.robot.safety import Fault, SafetyGuard, resolve_stop

SETTLE_S = 0.3
HOLD_S = 0.5


@dataclass
class HardwareRunConfig:
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

    def to_dict(self) -> dict:
        return {"gains": self.gains.to_dict(), "tool_load": {"mass": self.tool_load.mass, "com": list(map(float, self.tool_load.com))},
                "move_speed": self.move_speed, "go_to_picture": self.go_to_picture, "force_filter_hz": self.force_filter_hz}


@dataclass
class HardwarePlan:
    """What a run would do, computed without moving (shared by :func:`dry_run` and the run)."""

    T_obj: np.ndarray  # (4, 4) capture frame in the base frame
    start: np.ndarray  # (3,) first line point a, base frame
    direction: np.ndarray  # (3,) unit line direction d (into the surface)
    T_hover: np.ndarray  # (4, 4) hover pose
    first_target: object  # ImpedanceTarget of the first pressing tick
    substeps: int  # references per explorer step
    safety: object  # the SafetyConfig in force
    force_limit: float


def object_pose(capture, robot_cfg) -> np.ndarray:
    """The capture frame's pose in the robot base frame; refuses to guess on hardware."""
    from tergodic_cli.robot.surface import parse_object_pose

    if robot_cfg.object_pose is not None:
        return parse_object_pose(robot_cfg.object_pose)
    meta = getattr(capture, "meta", {}) or {}
    if meta.get("frame") == "robot_base":
        return np.eye(4)
    raise TergodicError("the capture's pose in the robot base frame is unknown (it was not captured in the base frame)",
                        "pass --object-pose x,y,z[,roll,pitch,yaw], or capture with a calibrated --camera-pose")


def hardware_safety(robot_cfg, stream_hz: float):
    """The simulation's limits, with watchdogs no shorter than the hardware's update periods allow."""
    sc = robot_cfg.safety
    return replace(sc, sensor_timeout=max(sc.sensor_timeout, 3.0 / stream_hz),
                   explorer_timeout=max(sc.explorer_timeout, 2.0 * robot_cfg.explore_dt))


def _substeps(robot_cfg, stream_hz: float) -> int:
    ratio = robot_cfg.explore_dt * stream_hz
    require(abs(ratio - round(ratio)) < 1e-6 and round(ratio) >= 1,
            f"the explorer step {robot_cfg.explore_dt} s is not a whole number of {1e3 / stream_hz:g} ms stream periods",
            "use an --explore-dt that is a multiple of the stream period, e.g. 0.2 at 100 Hz")
    return int(round(ratio))


class HardwareRun:
    """One run on hardware-shaped devices (see the module docstring). Tests reach in for fault injection."""

    def __init__(self, capture, explorer, robot_cfg, arm, sensor, hw: HardwareRunConfig | None = None,
                 on_event: Callable[[int, str], None] | None = None, pace: Callable[[float], None] | None = None):
        from scipy.spatial import cKDTree

        from tergodic_cli.robot.config import validate_robot_config
        from tergodic_cli.robot.surface import oriented_normals, resolve_side, transform_points

        validate_robot_config(replace(robot_cfg, backend="pybullet"))  # the shared field checks
        for name in ("connect", "read_state", "command_impedance", "stop", "fault", "move_joints"):
            require(hasattr(arm, name), f"the arm backend {type(arm).__name__} has no {name}()",
                    "use an ImpedanceArm backend (e.g. FrankyArm) for --robot franka")
        self.cfg = robot_cfg
        self.hw = hw or HardwareRunConfig()
        self.arm, self.sensor, self.explorer = arm, sensor, explorer
        self.on_event = on_event or (lambda step, msg: None)
        self.F_d = float(robot_cfg.force)
        self.threshold = robot_cfg.contact_threshold
        self.dt = 1.0 / float(arm.stream_hz)
        self.n_sub = _substeps(robot_cfg, arm.stream_hz)
        edt = float(getattr(getattr(explorer, "cfg", None), "dt", robot_cfg.explore_dt))
        require(abs(edt - robot_cfg.explore_dt) < 1e-9, f"the explorer steps {edt:g} s but the robot expects {robot_cfg.explore_dt:g} s",
                "build the explorer with robot_explore_config(cfg, robot_cfg.explore_dt)")
        self._pace = pace or self._realtime
        self.T_obj = object_pose(capture, robot_cfg)
        points = np.asarray(capture.points, dtype=float)
        self.points_base = transform_points(self.T_obj, points)
        side = resolve_side(robot_cfg.normal_side, getattr(capture, "meta", {}) or {})
        self.normals = oriented_normals(points, side)
        self.kdtree = cKDTree(points)
        self.safety = hardware_safety(robot_cfg, arm.stream_hz)
        self.guard = SafetyGuard(self.safety, arm.q_min, arm.q_max, arm.dq_max, self.F_d)
        from tergodic_cli.robot.summary import SETTLE_S as STEADY_S

        #: Every streamed tick's force peak, steady-contact force error and tilt (kernels.tick_stats).
        self.ts = Kn.new_tick_stats(self.F_d, self.threshold, int(round(STEADY_S / self.dt)))
        self.approach_peak: float | None = None
        self.sm = S.StateMachine(on_event=self.on_event)
        self.force = ForceLoop(self.hw.gains, self.F_d)
        self.samples: list[dict] = []
        self.stop_reason: str | None = None
        self.fault: Fault | None = None
        self._t0 = None
        self._f_filt = 0.0
        self._alpha = 1.0 - math.exp(-2.0 * math.pi * self.hw.force_filter_hz * self.dt)
        self._x_ref = np.array([1.0, 0.0, 0.0])
        self._t_wall0 = time.perf_counter()
        self.t = 0.0

    # ------------------------------------------------------------------ frames and geometry
    def _to_base(self, x):
        return np.asarray(x, dtype=float) @ self.T_obj[:3, :3].T + self.T_obj[:3, 3]

    def _to_obj(self, x):
        return (np.asarray(x, dtype=float) - self.T_obj[:3, 3]) @ self.T_obj[:3, :3]

    def _surface_normal(self, x_base: np.ndarray, k: int = 6) -> np.ndarray:
        _, idx = self.kdtree.query(self._to_obj(x_base), k=k)
        n = self.normals[np.atleast_1d(idx)].mean(axis=0)
        return self.T_obj[:3, :3] @ (n / np.linalg.norm(n))

    def agent_line(self) -> tuple[np.ndarray, np.ndarray]:
        """The explorer's line in the base frame: point a and unit direction d into the surface."""
        a = self._to_base(np.asarray(self.explorer.positions[0], dtype=float))
        n_b = self.T_obj[:3, :3] @ np.asarray(self.explorer.normals[0], dtype=float)
        if n_b @ self._surface_normal(a) < 0:
            n_b = -n_b
        return a, clamp_tilt(-n_b / np.linalg.norm(n_b), self.cfg.max_tool_tilt_deg)

    def plan(self, x_ref: np.ndarray | None = None) -> HardwarePlan:
        """The start line, the hover pose and the first pressing reference, from the present state."""
        a, d = self.agent_line()
        R = tool_rotation(d, self._x_ref if x_ref is None else x_ref)
        T_hover = np.eye(4)
        T_hover[:3, :3], T_hover[:3, 3] = R, a - self.cfg.hover_height * d
        first = line_impedance_target(a, a, d, R[:, 0], self.F_d, self.hw.gains)
        return HardwarePlan(self.T_obj, a, d, T_hover, first, self.n_sub, self.safety, self.guard.force_limit)

    # ------------------------------------------------------------------ one tick
    def _realtime(self, dt: float) -> None:
        now = time.perf_counter()
        if self._t_next is None or now - self._t_next > 0.1:  # first tick, or far behind: re-anchor
            self._t_next = now
        self._t_next += dt
        lag = self._t_next - time.perf_counter()
        if lag > 0:
            time.sleep(lag)

    _t_next = None

    def _read(self):
        st = self.arm.read_state()
        rd = self.sensor.read()
        w = self.contact(rd.wrench, st.rot)
        if getattr(rd, "valid", True):
            Kn.tick_stats(st.ee_pose, w, self.ts)
        if math.isfinite(float(w[2])):
            self._f_filt += self._alpha * (float(w[2]) - self._f_filt)
        self.t = st.t
        return st, rd, w

    def _check(self, st, rd, w, target_pos=None) -> Fault | None:
        reason = self.arm.fault()
        if reason is not None:
            return Fault("robot", "stop", reason, st.t)
        g = self.guard
        v = st.jacobian[:3] @ st.dq
        fault = (g.check_reading(st.t, rd, w)
                 or g.check_state(st.t, st.q, st.dq, st.pos, float(np.linalg.norm(v))))
        if fault is None and target_pos is not None:
            fault = g.check_target(st.t, np.asarray(target_pos))
        if fault is None and self.sm.state == S.EXPLORE:
            fault = g.check_explorer(st.t)
        return fault

    def _tick(self, mode: str, a=None, d=None, speed: float = 0.0, v_line=None, pose=None, axial=None, checks: bool = True):
        """Read, check, stream one reference, pace. Returns (state, ee wrench, fault or None).

        mode: "pose" (hold ``pose``), "move" (target at ``axial`` m along the line, advancing at
        ``speed`` m/s: approach and retreat) or "track" (ride with the TCP, press the commanded force).
        """
        try:
            st, rd, w = self._read()
            if mode == "pose":
                target = hold_target(pose, self.hw.gains)
                if v_line is not None:
                    target.twist[:3] = v_line
            elif mode == "move":
                target = line_impedance_target(st.pos, a, d, self._x_ref, 0.0, self.hw.gains, v_line, axial=axial, axial_speed=speed)
            else:
                f = self.force.track(float(w[2]), self.dt)
                target = line_impedance_target(st.pos, a, d, self._x_ref, f, self.hw.gains, v_line)
            fault = self._check(st, rd, w, target.pose[:3, 3] if speed >= 0 else None) if checks else None
            if fault is None:
                self.arm.command_impedance(target)
                self._pace(self.dt)
            return st, w, fault
        except KeyboardInterrupt:
            st = self.arm.read_state()
            return st, np.zeros(6), Fault("interrupt", "retreat", "interrupted by the user (Ctrl-C); retreating", st.t)

    # ------------------------------------------------------------------ faults
    def _stop(self, fault: Fault, step: int) -> None:
        fault = resolve_stop(fault, self.sm.state)  # in contact every fault lifts the tool first
        self.ts[Kn.TS_COUNT] = 0.0
        self.fault = fault
        self.stop_reason = fault.reason
        try:
            action = fault.action
            if action == "retreat" and self.sm.state != S.RETREAT:
                self.sm.go(S.RETREAT, self.t, step, fault.reason)
                T = self.arm.read_state().ee_pose
                self._retreat(T[:3, 3], T[:3, 2], step, checks=False)
                self.sm.go(S.STOPPED, self.t, step, "retreated after a fault; stopped")
            elif action == "stop":  # the SDK already stopped the robot
                self.sm.go(S.HOLD, self.t, step, fault.reason)
                self.sm.go(S.STOPPED, self.t, step, "the robot stopped itself; stopped")
            else:
                self.sm.go(S.HOLD, self.t, step, fault.reason)
                self._hold(HOLD_S)
                self.sm.go(S.STOPPED, self.t, step, "holding position after a fault; stopped")
        finally:
            self.arm.stop()
        raise _Stop(fault.reason)

    def _hold(self, seconds: float) -> None:
        pose = self.arm.read_state().ee_pose.copy()
        for _ in range(max(1, int(round(seconds / self.dt)))):
            self._tick("pose", pose=pose, checks=False)

    def _retreat(self, a, d, step: int, checks: bool = True) -> None:
        """Back off along the line: the target leaves the TCP's point at retreat_speed, for retreat_distance."""
        cfg = self.cfg
        start = self.arm.read_state().ee_pose[:3, 3].copy()
        s0 = float((start - a) @ d)
        n = int(math.ceil(cfg.retreat_distance / cfg.retreat_speed / self.dt))
        for i in range(n + int(round(SETTLE_S / self.dt))):
            axial = s0 - cfg.retreat_speed * self.dt * min(i + 1, n)
            st, w, fault = self._tick("move", a, d, speed=-cfg.retreat_speed if i < n else 0.0, axial=axial, checks=checks)
            if fault is not None:
                self._stop(fault, step)

    # ------------------------------------------------------------------ phases
    def _move_to_hover(self) -> None:
        from tergodic_cli.robot.ga import matrix_to_rotvec, rotvec_to_matrix
        from tergodic_cli.robot.controller import min_jerk

        hw = self.hw
        if hw.go_to_picture:
            self.on_event(0, "robot: planned joint move to the picture pose")
            self.arm.move_joints(np.asarray(self.cfg.picture_q, dtype=float))
        st = self.arm.read_state()
        self._x_ref = st.ee_pose[:3, 0].copy()
        plan = self.plan()
        self._start_line = (plan.start, plan.direction)
        self._x_ref = plan.T_hover[:3, 0].copy()
        for x in (plan.T_hover[:3, 3], plan.start):
            if not self.guard.inside(x):
                raise TergodicError(f"the start point or its hover pose {_fmt(x)} m is outside the workspace box",
                                    "move the object (--object-pose), or widen the workspace box")
        T0 = st.ee_pose
        dist = float(np.linalg.norm(plan.T_hover[:3, 3] - T0[:3, 3]))
        phi = matrix_to_rotvec(plan.T_hover[:3, :3] @ T0[:3, :3].T)
        duration = max(1.0, 1.875 * max(dist / hw.move_speed, float(np.linalg.norm(phi)) / 0.5))
        self.sm.go(S.HOVER, self.t, 0, f"moving to the hover pose {self.cfg.hover_height * 1e3:.0f} mm above the start {_fmt(plan.start)} m")
        n = int(math.ceil(duration / self.dt))
        p0, p1 = T0[:3, 3], plan.T_hover[:3, 3]
        for i in range(n + int(round(SETTLE_S / self.dt))):
            s, ds = min_jerk(np.zeros(1), np.ones(1), duration, (i + 1) * self.dt)
            pose = np.eye(4)
            pose[:3, :3] = rotvec_to_matrix(phi * float(s[0])) @ T0[:3, :3]
            pose[:3, 3] = p0 + (p1 - p0) * float(s[0])
            st, w, fault = self._tick("pose", pose=pose, v_line=(p1 - p0) * float(ds[0]))
            if fault is not None:
                self._stop(fault, 0)
        self.sensor.tare()
        st = self.arm.read_state()
        self.contact.tare_at(st.ee_pose[:3, :3])
        self._f_filt = 0.0
        err = float(np.linalg.norm(st.ee_pose[:3, 3] - plan.T_hover[:3, 3]))
        self.on_event(0, f"robot: at hover ({err * 1e3:.1f} mm from the planned pose); F/T sensor tared")

    def _approach(self) -> None:
        cfg = self.cfg
        a, d = self._start_line
        v_touch = guarded_approach_speed(0.0, cfg.approach_speed, cfg.contact_speed, self.F_d)
        self.sm.go(S.APPROACH, self.t, 0, f"approaching along the normal at {cfg.approach_speed * 1e3:.0f} mm/s, "
                                          f"touching at {v_touch * 1e3:.1f} mm/s")
        limit = (cfg.hover_height + 0.03) / cfg.approach_speed + 0.03 / v_touch + 0.5
        self.ts[Kn.TS_PEAK_PHASE] = 0.0  # the first touch's peak
        n = int(round(limit / self.dt))
        contact_at = None
        settled = 0
        t0 = self.t
        axial = float((self.arm.read_state().ee_pose[:3, 3] - a) @ d)
        speed = cfg.approach_speed
        for i in range(n + int(round(2.0 / self.dt))):
            if contact_at is None:
                # Guarded: the set-point slows down near the expected surface (the cloud's point a).
                axial += speed * self.dt
                st, w, fault = self._tick("move", a, d, speed=speed, axial=axial)
                speed = guarded_approach_speed(-float((np.asarray(st.pos) - a) @ d), cfg.approach_speed,
                                               cfg.contact_speed, self.F_d)
            else:
                st, w, fault = self._tick("track", a, d)
            if fault is not None:
                self._stop(fault, 0)
            f = self._f_filt
            if contact_at is None:
                if f >= self.threshold:
                    contact_at = self.t
                    self.force.start_from(f)  # bumpless: the press continues from the contact force
                    self.on_event(0, f"robot: contact at {f:.2f} N after {contact_at - t0:.2f} s; pressing to {self.F_d:g} N")
                elif i >= n:
                    self._stop(Fault("approach", "hold", f"no contact within {(cfg.hover_height + 0.03) * 1e3:.0f} mm below the hover pose; "
                                     "check --object-pose; holding position", self.t), 0)
            else:
                settled = settled + 1 if abs(f - self.F_d) <= 0.1 * self.F_d else 0
                if settled >= max(5, int(0.2 / self.dt)):
                    break
        else:
            self.on_event(0, f"robot: the force did not settle within 2 s (now {self._f_filt:.2f} N); exploring anyway")
        self.approach_peak = float(self.ts[Kn.TS_PEAK_PHASE])
        self.sm.go(S.EXPLORE, self.t, 0, f"in contact at {self._f_filt:.2f} N; exploring")

    def _explore(self, steps: int, on_step) -> None:
        from tergodic_cli.progress import track

        ex = self.explorer
        a_cur, d_cur = self._start_line
        st = self.arm.read_state()
        w = np.zeros(6)
        self.guard.feed_target(self.t)
        step = int(getattr(ex, "step_index", 0))
        self.ts[Kn.TS_COUNT], self.ts[Kn.TS_RUN] = 1.0, 0.0  # explore ticks count towards steady contact
        for _ in track(range(steps), total=steps, description=f"explore ({self.arm.name})"):
            in_contact = self._f_filt >= self.threshold
            tcp = st.ee_pose[:3, 3]
            self.ts[Kn.TS_N:Kn.TS_N + 3] = self._surface_normal(tcp)
            deposit = self._to_obj(tcp)[None, :] if in_contact else np.zeros((0, 3))
            before = int(getattr(ex, "step_index", step))
            try:
                ex.step(deposit_at=deposit, agent_at=self._to_obj(tcp)[None, :])
            except TergodicError as exc:
                fault = resolve_stop(Fault("explorer", "hold", f"the explorer failed ({exc}); holding position", self.t),
                                     self.sm.state)
                self._record(before + 1, st, w, a_cur, d_cur, on_step, fault.reason)
                self._stop(fault, before + 1)
            step = int(getattr(ex, "step_index", before + 1))
            a_next, d_next = self.agent_line()
            fault = self.guard.check_target(self.t, a_next)
            if fault is not None:
                fault = resolve_stop(fault, self.sm.state)
                self._record(step, st, w, a_cur, d_cur, on_step, fault.reason)
                self._stop(fault, step)
            self.guard.feed_target(self.t)
            x = self._x_ref - (self._x_ref @ d_next) * d_next
            if np.linalg.norm(x) > 1e-3:
                self._x_ref = x / np.linalg.norm(x)
            v_line = (a_next - a_cur) / self.cfg.explore_dt
            for k in range(1, self.n_sub + 1):
                s = k / self.n_sub
                a = a_cur + s * (a_next - a_cur)
                d = d_cur + s * (d_next - d_cur)
                d = d / np.linalg.norm(d)
                st, w, fault = self._tick("track", a, d, v_line=v_line)
                if fault is not None:
                    fault = resolve_stop(fault, self.sm.state)
                    self._record(step, st, w, a, d, on_step, fault.reason)
                    self._stop(fault, step)
            a_cur, d_cur = a_next, d_next
            self._record(step, st, w, a_cur, d_cur, on_step)
        self.ts[Kn.TS_COUNT] = 0.0
        self._last_line = (a_cur, d_cur)

    # ------------------------------------------------------------------ samples
    def _record(self, step: int, st, w, a, d, on_step, stop_reason: str | None = None) -> None:
        from tergodic_cli.robot.ga import matrix_to_quat, point_line_distance

        T = st.ee_pose
        R = T[:3, :3]
        tcp = T[:3, 3]
        n = self._surface_normal(tcp)
        in_contact = bool(self._f_filt >= self.threshold)
        tilt = math.degrees(math.acos(max(-1.0, min(1.0, float(-R[:, 2] @ n)))))
        f_base = R @ np.asarray(w[:3], dtype=float)
        metrics = self.explorer.metrics() if hasattr(self.explorer, "metrics") else {}
        obj_q = matrix_to_quat(self.T_obj[:3, :3])
        sample = {
            "t_sim": float(st.t - self._t_start),
            "t_wall": time.perf_counter() - self._t_wall0,
            "state": self.sm.state,
            "ee_pose": np.concatenate([tcp, matrix_to_quat(R)]),
            "q": st.q.copy(),
            "dq": st.dq.copy(),
            # measured joint torques when the SDK reports them (franky: tau_J); the commanded ones live inside the SDK
            "tau": np.asarray(getattr(self.arm, "measured_tau", getattr(self.arm, "last_tau", np.zeros(7))), dtype=float).copy(),
            "joint_names": list(self.arm.joint_names),
            "link_poses": {},
            "object_pose": np.concatenate([self.T_obj[:3, 3], obj_q]),
            "wrench_measured": np.nan_to_num(np.asarray(w, dtype=float)).copy(),
            "wrench_desired": np.array([0.0, 0.0, self.F_d, 0.0, 0.0, 0.0]),
            "force_normal": float(-(f_base @ n)) if math.isfinite(float(f_base @ n)) else 0.0,
            "force_contact": float(self._f_filt),
            "in_contact": in_contact,
            "contact_point": tcp.copy() if in_contact else None,
            "tilt_deg": tilt,
            "track_mm": 1e3 * point_line_distance(tcp, np.asarray(a), np.asarray(d)),
            "agent_line_point": np.asarray(a, dtype=float).copy(),
            "agent_line_dir": np.asarray(d, dtype=float).copy(),
            "contact_ergodicity": metrics.get("ergodicity"),
            "contact_touched_fraction": metrics.get("touched_fraction"),
            "step": int(step),
            **Kn.tick_figures(self.ts),
        }
        if stop_reason:
            sample["stop_reason"] = stop_reason
        self.samples.append(sample)
        if on_step is not None:
            on_step(step, sample)

    # ------------------------------------------------------------------ the run
    def run(self, steps: int, on_step=None) -> dict:
        from tergodic_cli.robot.summary import summarize_robot

        require(int(steps) >= 1, f"--steps must be >= 1, got {steps}", "e.g. --steps 300")
        self.arm.connect()
        if hasattr(self.sensor, "connect"):
            self.sensor.connect()
        self.contact = ContactWrench(self.hw.tool_load, self.sensor.frame_in_ee)
        st = self.arm.read_state()
        self._t_start = st.t
        self.t = st.t
        self.on_event(0, f"robot {S.PICTURE}: {self.arm.name}, references at {self.arm.stream_hz:g} Hz "
                         f"({self.n_sub} per explorer step), force limit {self.guard.force_limit:g} N")
        try:
            self._move_to_hover()
            self._approach()
            self._explore(int(steps), on_step)
            step = int(getattr(self.explorer, "step_index", 0))
            self.sm.go(S.RETREAT, self.t, step, f"{steps} explorer steps done; retreating")
            a, d = self._last_line
            self._retreat(a, d, step)
            self.sm.go(S.DONE, self.t, step, "retreated; done")
            self._hold(SETTLE_S)
            self.arm.stop()
        except _Stop:
            pass
        out = summarize_robot(self.samples, stop_reason=self.stop_reason, ticks=Kn.tick_figures(self.ts))
        out.update({
            "force_peak_approach_N": self.approach_peak,
            "backend": self.arm.name,
            "final_state": self.sm.state,
            "robot_seconds": self.t - self._t_start,
            "stream_hz": float(self.arm.stream_hz),
            "explorer_hz": 1.0 / self.cfg.explore_dt,
            "transitions": [{"t": round(tr.t - self._t_start, 4), "step": tr.step, "from": tr.source, "to": tr.target,
                             "reason": tr.reason} for tr in self.sm.history],
            "object_pose": [float(x) for x in self.T_obj[:3, 3]],
            "robot_config": self.cfg.to_dict(),
            "hardware_config": self.hw.to_dict(),
        })
        return out


class _Stop(Exception):
    """A fault ended the run (the robot has been made safe)."""


def explore_with_hardware(capture, explorer, robot_cfg, steps: int, arm, sensor, on_step=None, on_event=None,
                          hw: HardwareRunConfig | None = None, pace=None) -> dict:
    """Run ``steps`` explorer steps on real (or fake-SDK) hardware; same contract as ``explore_with_robot``.

    arm : an ImpedanceArm (e.g. :class:`~tergodic_cli.hardware.franka.FrankyArm`), sensor : a
    WrenchSensor (Bota, Net F/T, or the arm's own estimate); both are connected here and the arm is
    stopped and disconnected at the end, whatever happens. Returns the robot summary extras.
    """
    run = HardwareRun(capture, explorer, robot_cfg, arm, sensor, hw=hw, on_event=on_event, pace=pace)
    try:
        return run.run(steps, on_step)
    finally:
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
    plan : a :class:`DryRunPlan` (capture, explorer, robot config, hardware config).

    Returns the report (several lines). Devices connected here are disconnected again; no
    command, move or reference is ever sent.
    """
    lines = []
    opened = []
    try:
        arm.connect()
        opened.append(arm)
        st = arm.read_state()
        T = st.ee_pose
        lines.append(f"arm {arm.name}: connected; TCP at {_fmt(T[:3, 3])} m, tool axis {_fmt(T[:3, 2])}, "
                     f"q = {_fmt(st.q)} rad")
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
            rate = (len(ts) - 1) / (ts[-1] - ts[0]) if ts[-1] > ts[0] else float("nan")
            ok = np.all(np.isfinite(W))
            rate_text = f"{rate:.0f} samples/s" if math.isfinite(rate) else "WARNING: the sample time did not advance over 20 reads"
            lines.append(f"F/T sensor {type(sensor).__name__}: {'ok' if ok else 'NON-FINITE SAMPLES'}; mean force {_fmt(W[:, :3].mean(0))} N "
                         f"(not tared), noise {W[:, :3].std(0).max():.3f} N, {rate_text}")
        if camera is not None:
            camera.connect()
            opened.append(camera)
            pts, _ = camera.read()
            lines.append(f"camera {type(camera).__name__}: {len(pts)} valid points"
                         + (f", depth {pts[:, 2].min():.3f}..{pts[:, 2].max():.3f} m" if len(pts) else ""))
        if plan is not None:
            explorer = plan.explorer if plan.explorer is not None else _StartAgent(plan.capture, plan.robot_cfg, plan.start)
            run = HardwareRun(plan.capture, explorer, plan.robot_cfg, arm, sensor if sensor is not None else _NoSensor(),
                              hw=plan.hw, pace=lambda dt: None)
            run._x_ref = T[:3, 0].copy()
            p = run.plan()
            tgt = p.first_target
            sc = p.safety
            lines.append(f"plan: object frame at {_fmt(p.T_obj[:3, 3])} m; start {_fmt(p.start)} m, tool axis {_fmt(p.direction)}")
            lines.append(f"  1. {'joint move to the picture pose, then ' if run.hw.go_to_picture else ''}Cartesian move to the hover pose "
                         f"{_fmt(p.T_hover[:3, 3])} m ({np.linalg.norm(p.T_hover[:3, 3] - T[:3, 3]) * 1e3:.0f} mm away, "
                         f"<= {run.hw.move_speed * 1e3:.0f} mm/s)")
            lines.append(f"  2. tare, approach along the normal at {plan.robot_cfg.approach_speed * 1e3:.0f} mm/s until "
                         f"{run.threshold:g} N")
            lines.append(f"  3. press {run.F_d:g} N: first reference {_fmt(tgt.pose[:3, 3])} m "
                         f"({run.F_d / run.hw.gains.k_normal * 1e3:.1f} mm past the surface along the normal, "
                         f"k_normal {run.hw.gains.k_normal:g} N/m, k_lateral {run.hw.gains.k_lateral:g} N/m)")
            lines.append(f"  4. {p.substeps} references per explorer step of {plan.robot_cfg.explore_dt:g} s "
                         f"({arm.stream_hz:g} Hz to the SDK's 1 kHz impedance loop)")
            inside = all(run.guard.inside(x) for x in (p.start, p.T_hover[:3, 3]))
            lines.append(f"limits: force {p.force_limit:g} N (retreat), workspace {_fmt(sc.workspace_min)}..{_fmt(sc.workspace_max)} m "
                         f"({'start inside' if inside else 'START OUTSIDE'}), TCP speed {sc.tcp_speed_max:g} m/s, "
                         f"joint velocity {sc.velocity_factor:g} x limits, sensor watchdog {sc.sensor_timeout * 1e3:.0f} ms, "
                         f"explorer watchdog {sc.explorer_timeout:g} s")
        lines.append("dry run: nothing was moved")
    finally:
        for dev in reversed(opened):
            try:
                dev.disconnect()
            except Exception:  # noqa: BLE001 - a report must not be lost to a failing close
                pass
    return "\n".join(lines)


@dataclass
class DryRunPlan:
    """What :func:`dry_run` plans against.

    capture : the Capture; robot_cfg : the RobotConfig; hw : the HardwareRunConfig (None = defaults).
    explorer : a fresh Explorer (its first agent position and normal), or None to plan from
    ``start`` (x,y,z in the capture frame, m; None = the capture's point nearest its centroid)
    with the capture's own normals, which needs no basis.
    """

    capture: object
    robot_cfg: object
    explorer: object = None
    start: tuple[float, float, float] | None = None
    hw: HardwareRunConfig | None = None


class _NoSensor:
    frame_in_ee = np.eye(4)


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

        class _Cfg:
            dt = robot_cfg.explore_dt

        self.cfg = _Cfg()


def _fmt(x) -> str:
    return "(" + ", ".join(f"{float(v):.3f}" for v in np.ravel(x)) + ")"
