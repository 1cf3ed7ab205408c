"""The one contact loop: the explorer drives a force-controlled arm, in simulation or on hardware.

One state machine (:mod:`tergodic_cli.robot.statemachine`) and one
:class:`~tergodic_cli.robot.safety.SafetyGuard` drive every backend through the :class:`Arm`
interface of :mod:`tergodic_cli.robot.interfaces`: the loop reads an observation, checks it, and
sends a line target (:class:`~tergodic_cli.robot.interfaces.LineTarget`); the backend realises the
target at its own rate (the PyBullet arm runs the torque law of eq. 47 inside its 1 kHz tick, a
Franka streams it to the SDK's impedance controller).

    picture -> hover -> tare -> approach (guarded, along the normal, then press to F_d) -> explore
    (one explorer step every explore_dt; the line target glides between agent lines) -> retreat ->
    done;  a fault -> retreat (in contact: the tool is lifted without reading the sensor) or hold
    -> stopped.

Coverage comes from the real contact: at each explorer step the backend's contact point is
deposited when the contact force is at or above ``contact_threshold``; the agent is reset to
the measured tool tip (paper eq. 22) before its gradient step when the tip is more than
:data:`RESET_M` off the agent's line (else it keeps its own path, which the tool follows), never
while the tool rolls over an edge. The run's headline ε is the unit-mass score of the sponge's
logged contact points (``eps_sponge`` in each sample).
"""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import replace
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from tergodic_cli.errors import TergodicError
from tergodic_cli.robot import kernels as Kn
from tergodic_cli.robot import statemachine as S
from tergodic_cli.robot.controller import guarded_approach_speed
from tergodic_cli.robot.ga import matrix_to_quat, point_line_distance, pose_matrix
from tergodic_cli.robot.reach import tool_rotation
from tergodic_cli.robot.interfaces import LineTarget
from tergodic_cli.robot.safety import CONTACT_STATES, Fault, SafetyGuard, fmt_xyz, resolve_stop
from tergodic_cli.robot.summary import SETTLE_S as STEADY_S, summarize_robot
from tergodic_cli.robot.surface import oriented_normals, resolve_side, transform_points

#: Seconds of holding after a stop, so the arm ends at rest.
HOLD_S = 0.5
SETTLE_S = 0.3
PRESS_TIMEOUT_S = 2.0
PRESS_RAMP_S = 0.5
#: Seconds the force must stay within 10 % of F_d before the approach hands over to exploring.
SETTLED_S = 0.05
RETREAT_TIMEOUT_S = 3.0
#: Retreats after a fault at most, while anything still touches (an arm part the first lift did not free).
LIFTS = 3
#: Degrees between the tool axis and the surface normal in contact above which the run lifts the tool
#: and stops (issue 15: never press at a large angle; following the normal, the median is ~1 deg).
CONTACT_TILT_MAX_DEG = 15.0
#: Degrees the line target's direction turns at most per explorer step (edges, tight curves).
MAX_TURN_DEG = 3.0
#: Degrees the surface normal may turn over an explorer step for the line to follow it faster than that.
GENTLE_TURN_DEG = 5.0
#: Start points tried (nearest reachable target first) before a start out of reach is refused.
START_TRIES = 8
#: Metres between the agent, back in reach, and the waiting tool beyond which the tool lifts and moves over.
TRANSIT_M = 0.012
#: Radians from a joint's limit (inside the guard's margin), and the share of its speed limit, at
#: which the tool's place counts as out of reach after all.
JOINT_NEAR, SPEED_NEAR = 0.1, 0.4
#: Radians the last joint (the wrist, about the tool axis) keeps from its limits when the spin
#: reference is chosen: the ball sponge is round, so its spin is free, and the rule of
#: :func:`tool_rotation` alone drove the Panda's joint 7 into its limit at step 10 (corpus bunny, 2 N, seed 2).
WRIST_MARGIN = 0.3
#: Cosine between the last joint's axis and the tool axis above which the wrist turns the tool about it.
WRIST_ALIGNED = 0.9
#: Cosine of the normals' spread beyond which the ball's contact is taken to be at an edge.
EDGE_COS = math.cos(math.radians(10.0))
#: Degrees the agent's line turns over one step above which it crossed a sharp edge: the tool lifts
#: and moves over (rolling over a box's edge at MAX_TURN_DEG held the agent back for ~30 steps).
HOP_TURN_DEG = 30.0
#: Press-angle lifts (the tool touching again on the agent's line) allowed within RESEAT_WINDOW steps;
#: one more is a fault.
RESEATS, RESEAT_WINDOW = 2, 50
#: Metres the tool tip may be off the agent's line before the agent is reset to it (eq. 22). The tool
#: trails its gliding target by ~1 mm (friction, finite stiffness): reset every step, the agent set off
#: from there and lost that much of each 3 mm step (the sponge 2.7 mm a step against the kinematic
#: agent's 3.0, ε 1.09-1.14 x the kinematic agent's on the corpus spheres). Within one step of the tool
#: it keeps its own path, which the tool follows; beyond, the tool is held (a wait, an edge, a tight
#: curve's turn limit) and the agent goes back to it.
RESET_M = 0.003
#: Explorer steps the tool waits on the reach boundary before the agent restarts at the hottest reachable
#: target point: alone in the dropped part (p = 0, nothing deposited) it can settle at a ripple of the
#: truncated spectral heat and stay there (the torus: 900 steps).
WAIT_STEPS = 15


def robot_explore_config(cfg, explore_dt: float):
    """The explorer config time-scaled to ``explore_dt`` s per step, with the same path per step.

    dt -> explore_dt, v_max -> v_max·k, a_max -> a_max·k² with k = dt / explore_dt: each step
    still moves the agent by at most v_max·dt metres and the diffusion per step is unchanged.
    """
    k = cfg.dt / explore_dt
    return replace(cfg, dt=explore_dt, v_max=cfg.v_max * k, a_max=cfg.a_max * k * k)


def loop_safety(robot_cfg, dt: float):
    """The safety limits, with watchdogs no shorter than a control period ``dt`` (s) allows."""
    sc = robot_cfg.safety
    return replace(sc, sensor_timeout=max(sc.sensor_timeout, 3.0 * dt),
                   explorer_timeout=max(sc.explorer_timeout, 2.0 * robot_cfg.explore_dt))


def object_pose(capture, robot_cfg, guess: bool = True, on_event=None) -> np.ndarray:
    """The capture frame's pose (4, 4) in the robot base frame: ``--object-pose``, else the identity
    for a cloud captured in the base frame, else (``guess``, simulation only) the cloud's footprint
    centre 0.5 m in front of the base on a 0.2 m stand; on hardware it refuses to guess."""
    from tergodic_cli.robot.surface import default_object_pose, parse_object_pose

    if robot_cfg.object_pose is not None:
        return parse_object_pose(robot_cfg.object_pose)
    if (getattr(capture, "meta", {}) or {}).get("frame") == "robot_base":  # a calibrated (or simulated) camera
        return np.eye(4)
    if not guess:
        raise TergodicError("the capture's pose in the robot base frame is unknown (it was not captured in the base frame)",
                            "pass --object-pose x,y,z[,roll,pitch,yaw], or capture with a calibrated --camera-pose")
    T = default_object_pose(np.asarray(capture.points, dtype=float))
    if on_event is not None:
        on_event(0, "robot: no --object-pose given; the cloud's footprint centre is placed 0.5 m in front "
                    f"of the base on a 0.2 m stand (object pose {fmt_xyz(T[:3, 3])} m)")
    return T


class _Stop(Exception):
    """Raised inside a phase when a fault ended it (the robot has been made safe)."""


class ContactRun:
    """One run: the state machine and the safety guard over one connected :class:`Arm`.

    Parameters
    ----------
    capture : the Capture (points (N, 3) m in the capture frame, meta).
    explorer : an Explorer built with :func:`robot_explore_config`.
    cfg : the :class:`~tergodic_cli.robot.config.RobotConfig`.
    arm : a connected :class:`~tergodic_cli.robot.interfaces.Arm`.
    T_obj : (4, 4) the capture frame in the robot base frame.
    on_event : called as on_event(step, text) at every state transition and warning.
    on_log : called as on_log(kind, step, record) for the run log: kind "phase" at every state
        transition (record: t, s since the run's start; source, target, reason), kind "force" for
        every window of 1 kHz ticks (record: state, t_start, t_end, ticks, force_max and force_mean
        of |f| over the window's ticks, N, and the run's cumulative tick figures); a window closes at
        each robot sample, each transition and the end, so the windows hold every tick once.
    normals : (N, 3) the cloud's oriented unit normals when the backend has them (else computed).

    Tests and benchmarks reach in for fault injection (``run.arm``, ``run.guard``); the CLI goes
    through the backends' ``explore_with_*``.
    """

    @property
    def F_d(self) -> float:
        """The desired force F_d, N: the robot config's ``force``, its one home (the arm is given it by
        ``bind``, the wrench PID by each press target)."""
        return float(self.cfg.force)

    def __init__(self, capture, explorer, cfg, arm, T_obj: np.ndarray, on_event: Callable[[int, str], None] | None = None,
                 on_log: Callable[[str, int, dict], None] | None = None, normals: np.ndarray | None = None):
        self.cfg = cfg
        self.on_log = on_log
        self.capture = capture
        self.explorer = explorer
        self.arm = arm
        self.on_event = on_event or (lambda step, msg: None)
        self.threshold = cfg.contact_threshold
        self.dt = float(arm.dt)
        ratio = cfg.explore_dt / self.dt
        if abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
            raise TergodicError(f"the explorer step {cfg.explore_dt} s is not a whole number of {self.dt * 1e3:g} ms control periods",
                                "use an --explore-dt that is a multiple of the control period, e.g. 0.2")
        self.n_sub = int(round(ratio))
        edt = float(getattr(getattr(explorer, "cfg", None), "dt", cfg.explore_dt))
        if abs(edt - cfg.explore_dt) > 1e-9:
            raise TergodicError(f"the explorer steps {edt:g} s but the robot expects {cfg.explore_dt:g} s per explorer step",
                                "build the explorer with robot_explore_config(cfg, robot_cfg.explore_dt)")
        self.T_obj = np.asarray(T_obj, dtype=float)
        self.points = np.asarray(capture.points, dtype=float)
        self.points_base = transform_points(self.T_obj, self.points)
        # (a backend that already oriented them, for its contact surface, passes them in: ~1-3 s each)
        self.normals = (np.asarray(normals, dtype=float) if normals is not None else
                        oriented_normals(self.points, resolve_side(cfg.normal_side, getattr(capture, "meta", {}) or {})))
        self.kdtree = cKDTree(self.points)
        self.safety = loop_safety(cfg, self.dt)
        self.guard = SafetyGuard(self.safety, arm.q_min, arm.q_max, arm.dq_max, self.F_d, dt=self.dt)
        #: Every tick's force peak, steady-contact force error and tilt (kernels.tick_stats).
        self.ts = Kn.new_tick_stats(self.F_d, self.threshold, int(round(STEADY_S / self.dt)))
        arm.bind(self.guard, self.ts, self.F_d, self.threshold)
        self.approach_peak: float | None = None
        self.sm = S.StateMachine(on_event=self.on_event, before=self._transition)
        self._win_t0 = 0.0
        self.samples: list[dict] = []
        self.stop_reason: str | None = None
        self.fault: Fault | None = None
        #: The unit-mass score (explore.metrics.CoverageScore) of the sponge's contact points, one per
        #: sample in contact, on the explorer's target: the run's headline ε (made at the first sample).
        self._contacts = None
        self._contacts_p: np.ndarray | None = None
        #: The tool's spin pointing straight down (reach.tool_rotation): the arm's at the start.
        self._x_down = arm.get_observation(sensor=False).state.ee_pose[:3, 0].copy()
        #: (N,) where the tool can follow the normal (a backend that plans its reach narrows it).
        self.reachable = np.ones(len(self.points), dtype=bool)
        #: x (3,) -> (the closest point (3,), its face's unit normal (3,), either sign) of the object's
        #: surface, capture frame, where a backend knows the surface it presses on (a mesh); None: the cloud.
        self.closest: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None
        #: The commanded tool axis is kept within this many degrees of straight down (None: it
        #: follows the normal; the simulation plans its reach instead, robot/reach.py).
        self.max_tilt_deg = cfg.max_tool_tilt_deg
        self._told_unreachable = False
        self.move_overs = 0  # lift-and-move-overs (sharp edges, back in reach, press-angle lifts)
        self._reseats: list[int] = []  # steps of the press-angle lifts
        self._cb_s = 0.0
        self._deferred = None
        self.interrupted = False
        self._t0 = None
        self._t_arm0 = 0.0
        self.paused_s = 0.0
        self._last_line = None
        self._last_agent: tuple[np.ndarray, np.ndarray] | None = None  # the agent's line at its last step
        self._rolling = False

    # ------------------------------------------------------------------ frames
    @property
    def t(self) -> float:
        """The arm's clock, s."""
        return self.arm.t

    def _to_base(self, x: np.ndarray) -> np.ndarray:
        return transform_points(self.T_obj, x)

    def _to_obj(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, dtype=float) - self.T_obj[:3, 3]) @ self.T_obj[:3, :3]

    def _surface_normal(self, x_base: np.ndarray, k: int = 6, smooth: bool = False):
        """Oriented unit surface normal (base frame) near ``x_base``: mean of the k nearest cloud normals.
        With ``smooth``: (normal, whether those normals lie within EDGE_COS of their mean: no edge)."""
        _, idx = self.kdtree.query(self._to_obj(x_base), k=k)
        N = self.normals[np.atleast_1d(idx)]
        m = N.mean(axis=0)
        n = self.T_obj[:3, :3] @ (m / np.linalg.norm(m))
        return (n, bool(np.min(N @ m) >= EDGE_COS * np.linalg.norm(m))) if smooth else n

    def _agent_line(self) -> tuple[np.ndarray, np.ndarray]:
        """The explorer's line L_a⊥ in the base frame: point and unit direction into the surface."""
        a = self._to_base(np.asarray(self.explorer.positions[0], dtype=float))
        n_b = self.T_obj[:3, :3] @ np.asarray(self.explorer.normals[0], dtype=float)
        if n_b @ self._surface_normal(a) < 0:  # the explorer's normal sign is arbitrary; ours faces the tool
            n_b = -n_b
        d = -n_b / np.linalg.norm(n_b)
        if self.max_tilt_deg is not None:
            return a, turn_towards(np.array([0.0, 0.0, -1.0]), d, self.max_tilt_deg)  # the limit off straight down
        if self.closest is not None and not self._surface_normal(a, smooth=True)[1]:
            # Near an edge the cloud's normal is a blend of the faces': the ball would be placed to touch
            # the edge from wherever the agent is; the face's own normal puts it on the agent's face.
            nf = self.T_obj[:3, :3] @ self.closest(self._to_obj(a))[1]
            if abs(float(nf @ d)) < EDGE_COS:
                d = -nf if nf @ d < 0 else nf
        # The line near (a, d) the ball presses along its own contact normal: through the contact, along -normal.
        q, n = self._ball_contact(a, d)
        return q, -n

    def _ball_contact(self, a: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where the sponge's ball on the line (a, d) touches the cloud (base frame) and the unit contact
        normal there, from the nearest surface to the ball's centre: on a smooth part the centre's
        foot on the tangent planes of its 8 nearest cloud points (the surface normal, noise-free);
        at a sharp edge the closest point of the collision surface (:attr:`closest`, where it turns
        the normal by over 10 deg; without it, the points' mean where their normals spread over
        10 deg), so the normal turns about the edge as the ball rolls over it (the cloud's fitted
        normal there is a blend of the faces', its tangent planes miss the edge)."""
        c = a - self.cfg.sponge.radius * d
        co = self._to_obj(c)
        _, idx = self.kdtree.query(co, k=8)
        P, N = self.points[idx], self.normals[idx]
        q = co - np.einsum("ij,ij->i", co - P, N) @ N / len(idx)
        m = N.mean(axis=0)
        if float(np.min(N @ m)) < EDGE_COS * float(np.linalg.norm(m)):  # an edge (not a sheet's border)
            if self.closest is None:
                q = P.mean(axis=0)
            else:  # the collision surface's own closest point: the ball's true contact
                qm = self.closest(co)[0]
                u, v = co - q, co - qm
                if float(u @ v) < EDGE_COS * float(np.linalg.norm(u) * np.linalg.norm(v)):
                    q = qm
        q = self._to_base(q)
        n = c - q
        return q, n / np.linalg.norm(n)

    def target(self) -> np.ndarray:
        """(N,) the target p the explorer works on (the capture's when it has none), capture order."""
        p = getattr(self.explorer, "p", getattr(self.capture, "target", None))
        return np.ones(len(self.points)) if p is None else np.asarray(p, dtype=float)

    def drop_unreachable(self) -> None:
        """Drop the target where the tool cannot follow the normal (:attr:`reachable` False) from the
        explorer, saying so before any contact; refuse when none of the target is left."""
        target = self.target()
        total = float(target.sum())
        kept = target * self.reachable
        lost = 1.0 - float(kept.sum()) / total if total > 0 else 0.0
        if lost <= 1e-3:
            return
        if float(kept.sum()) <= 0:
            sim = "sim" in (getattr(self.capture, "meta", None) or {})  # the pose is the capture's: capture anew
            raise TergodicError("the tool cannot follow the surface normal anywhere on the target (the arm's wrist "
                                "cannot reach those orientations)",
                                "capture a side the arm can reach, e.g. a mug on a stand turned sideways: tergodic "
                                "capture --source sim --object mug --object-pose 0.5,0,0.2,0,0,-90 --camera-pose "
                                "0.5,-0.45,0.6,0.5,0,0.25" if sim else "move or turn the object with --object-pose")
        self.on_event(0, f"robot: {100 * lost:.0f} % of the target is where the tool cannot follow the normal "
                         f"({100 * (1 - self.reachable.mean()):.0f} % of the surface); dropped from the target")
        if hasattr(self.explorer, "set_target"):
            self.explorer.set_target(kept)

    def _hottest_reachable(self) -> np.ndarray | None:
        """(3,) the reachable target point (capture frame) where the explorer's heat u is highest, among
        those TRANSIT_M or more inside the reachable part where there are any; None: none left."""
        ok = np.flatnonzero(self.reachable & (self.target() > 0))
        heat = getattr(self.explorer, "heat", None)
        if len(ok) == 0 or heat is None:
            return None
        if not self.reachable.all():
            # On the boundary the agent's next step leads straight back out of reach (the torus: the
            # same restart every 16 steps for 300 steps, the tool never moving).
            inner = cKDTree(self.points[~self.reachable]).query(self.points[ok])[0] >= TRANSIT_M
            ok = ok[inner] if inner.any() else ok
        return self.points[ok[int(np.argmax(np.asarray(heat)[ok]))]]

    def _agent_reset(self, obs) -> np.ndarray | None:
        """(1, 3) the measured tool tip (capture frame) the agent is reset to before its step (eq. 22),
        or None when the tip is within :data:`RESET_M` of the agent's line or the tool is rolling over an
        edge (the agent keeps its path)."""
        tip = obs.state.ee_pose[:3, 3]
        if self._rolling:
            return None
        if self._last_agent is not None:
            a, d = self._last_agent
            if point_line_distance(tip, a, d) <= RESET_M:
                return None
        return self._to_obj(tip)[None, :]

    def _reachable_at(self, x_base: np.ndarray) -> bool:
        return bool(self.reachable[self.kdtree.query(self._to_obj(x_base))[1]])

    # ------------------------------------------------------------------ one control period
    def check(self, obs) -> Fault | None:
        """The guard's checks on one observation (the backend's own fault first)."""
        reason = self.arm.fault()
        if isinstance(reason, Fault):  # e.g. the simulation's whole-arm contact: the backend's own fault
            return reason
        if reason is not None:
            return Fault("robot", "stop", reason, obs.state.t)
        st, g = obs.state, self.guard
        fault = g.check_reading(st.t, obs.reading, obs.wrench) if obs.reading is not None else None
        if fault is None:
            v = st.jacobian[:3] @ st.dq
            fault = g.check_state(st.t, st.q, st.dq, st.pos, math.sqrt(float(v @ v)))
        if fault is None and self.sm.state == S.EXPLORE:
            fault = g.check_explorer(st.t)
        return fault

    def _tick(self, target: LineTarget, checks: bool = True, sensor: bool = True):
        """Observe, check, act: one control period. Returns (observation, fault or None); a
        faulty period is not acted on. ``sensor`` False: the F/T is not read (wrench 0)."""
        obs = self.arm.get_observation(sensor=sensor)
        fault = self.check(obs) if checks else None
        if fault is None:
            self.arm.send_action(target)
        return obs, fault

    def _follow(self, A: np.ndarray, D: np.ndarray, v_line):
        """One explorer interval of pressing along the lines (A, D: (n, 3) points and directions, one
        per control period). Returns (observation, a, d, fault) of the last period or of the first
        fault. A backend with a compiled interval (``arm.fast``) runs it itself, checks included."""
        if getattr(self.arm, "fast", False):
            return self.arm.follow(A, D, v_line)
        obs = a = d = None
        for a, d in zip(A, D):
            obs, fault = self._tick(LineTarget(a, d, "press", force=self.F_d, v_line=v_line))
            if fault is not None:
                return obs, a, d, fault
        return obs, a, d, None

    def _spin_in_wrist(self, x_ref: np.ndarray, obs) -> np.ndarray:
        """The spin reference ``x_ref`` (3,), turned about the tool axis as far as needed for the last joint
        to stay WRIST_MARGIN inside its limits (the sponge is round: its spin is free). Unchanged where the
        last joint does not turn the tool about its axis."""
        st = obs.state
        R = st.ee_pose[:3, :3]
        z, x = R[:, 2], R[:, 0]
        along = float(np.asarray(st.jacobian)[3:6, -1] @ z)  # the last joint's rate about the tool axis
        if abs(along) < WRIST_ALIGNED:
            return x_ref
        x_t = x_ref - (x_ref @ z) * z
        if float(np.linalg.norm(x_t)) < 1e-6:
            return x_ref
        x_t /= np.linalg.norm(x_t)
        phi = math.atan2(float(np.cross(x, x_t) @ z), float(x @ x_t))  # the turn the spin spring asks for
        q, lo, hi = float(st.q[-1]), float(self.guard.q_lo[-1]) + WRIST_MARGIN, float(self.guard.q_hi[-1]) - WRIST_MARGIN
        if lo >= hi:
            return x_ref
        want = q + phi / along
        ok = min(max(want, lo), hi)
        if ok == want:
            return x_ref
        turn = (ok - q) * along
        c, s_ = math.cos(turn), math.sin(turn)
        return c * x + s_ * np.cross(z, x) + (1.0 - c) * float(z @ x) * z

    # ------------------------------------------------------------------ faults and stops
    def _stop(self, fault: Fault, step: int) -> None:
        """Make the robot safe after ``fault`` and end the run (raises :class:`_Stop`).

        In contact (approach, explore, a retreat) or touching anything (a set-up move that ran into
        something) every fault lifts the tool along its axis without reading the sensor or checking
        (:func:`~tergodic_cli.robot.safety.stop_action`; a fault during a retreat finishes it, from
        where the tool is, along its own axis), until nothing touches, then holds, lifted. In free
        space a fault holds position."""
        fault = resolve_stop(fault, self.sm.state, self._touching())
        self.ts[Kn.TS_COUNT] = 0.0
        self.fault = fault
        self.stop_reason = fault.reason
        try:
            if fault.action == "retreat":
                if self.sm.state != S.RETREAT:
                    self.sm.go(S.RETREAT, self.t, step, fault.reason)
                else:
                    self.on_event(step, f"robot: a fault during the retreat ({fault.reason}); finishing the lift")
                self._lift(step)
                self.arm.hold(HOLD_S)
                self.sm.go(S.STOPPED, self.t, step, "retreated after a fault; holding still")
            elif fault.action == "stop":  # the robot's own controller stopped it
                self.sm.go(S.HOLD, self.t, step, fault.reason)
                self.sm.go(S.STOPPED, self.t, step, "the robot stopped itself; stopped")
            else:
                self.sm.go(S.HOLD, self.t, step, fault.reason)
                self.arm.hold(HOLD_S)
                self.sm.go(S.STOPPED, self.t, step, "held position after a fault; holding still")
        finally:
            self.arm.stop()
        raise _Stop(fault.reason)

    def _touching(self) -> bool:
        """Whether the backend sees anything touching (the simulation: sponge or any arm part); False
        where it cannot tell."""
        touching = getattr(self.arm, "touching", None)
        return bool(touching()) if touching is not None else False

    def _lift(self, step: int) -> None:
        """After a fault: back off along the tool's own axis from where it is, unchecked and without the
        sensor, and again (LIFTS times at most) while anything still touches."""
        for _ in range(LIFTS):
            T = self.arm.get_observation(sensor=False).state.ee_pose
            self._retreat(T[:3, 3].copy(), T[:3, 2].copy(), step, checks=False, sensor=False)
            if not self._touching():
                return
        self.on_event(step, "robot: still touching after lifting the tool "
                            f"{LIFTS * max(self.cfg.retreat_distance, self.cfg.hover_height) * 1e3:.0f} mm")

    def _retreat(self, a: np.ndarray, d: np.ndarray, step: int, checks: bool = True, sensor: bool = True) -> None:
        """Back the tool off along the line (a, d) by ``retreat_distance`` (at least the hover height,
        so the tool ends lifted). The retreat never uses the force; with ``sensor`` False it does not
        even read the sensor (a fault may have come from it)."""
        cfg = self.cfg
        start = self.arm.get_observation(sensor=False).state.ee_pose[:3, 3].copy()
        target = LineTarget(a, d, "move", speed=-cfg.retreat_speed)
        want = max(cfg.retreat_distance, cfg.hover_height)
        if hasattr(self.arm, "retreat_limit"):  # a backend that checks its moves against the object (plan.py)
            ok = self.arm.retreat_limit(d, want)
            if ok < want - 1e-9:
                self.on_event(step, f"robot: the retreat stops after {ok * 1e3:.0f} of {want * 1e3:.0f} mm (further back "
                                    "an arm link would come closer to the object); the next move starts from there")
                want = ok
        gone = 0.0
        for _ in range(int(round(RETREAT_TIMEOUT_S / self.dt))):
            obs, fault = self._tick(target, checks=checks, sensor=sensor)
            if fault is not None:
                self._stop(fault, step)
            gone = float((start - obs.state.ee_pose[:3, 3]) @ d)
            if gone >= want:
                break
        else:  # said, so a move refused next for a tool still near the surface is explained in the log
            self.on_event(step, f"robot: the retreat reached {gone * 1e3:.0f} of {want * 1e3:.0f} mm in its "
                                f"{RETREAT_TIMEOUT_S:g} s")

    def _unreachable(self, problem: str, fix: str) -> None:
        """Before the run: bad input (TergodicError). Mid-run (a later cycle of the closed loop):
        a fault, the arm holds where it is and the run ends with its log and summary."""
        if self.sm.history:
            self._stop(Fault("reach", "hold", f"{problem}; holding position", self.t), self._step())
        raise TergodicError(problem, fix)

    # ------------------------------------------------------------------ phases
    def _hover_pose(self, a: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(4, 4) TCP pose ``hover_height`` back from ``a`` along the tool axis ``d``."""
        return pose_matrix(tool_rotation(d, self._x_down), a - self.cfg.hover_height * d)

    def _move_to_hover(self) -> None:
        cfg = self.cfg
        a, d = self._agent_line()
        start, err = a, None
        for _ in range(START_TRIES):
            if not self._reachable_at(a):  # the nearest reachable target point (the first step moves the agent there)
                ok = np.flatnonzero(self.reachable & (self.target() > 0))
                if len(ok) == 0:
                    err = err or "no reachable target point is left"
                    break
                a = self.points_base[ok[np.argmin(np.linalg.norm(self.points_base[ok] - a, axis=1))]]
                d = -self._surface_normal(a)
            T_hover = self._hover_pose(a, d)
            if not self.guard.inside(T_hover[:3, 3]) or not self.guard.inside(a):
                self._unreachable(f"the start point {fmt_xyz(a)} m or its hover pose is outside the workspace box",
                                  "move the object with --object-pose, or choose another start")
            err = self.arm.reach(T_hover)
            if err is None and hasattr(self.arm, "plan"):  # a backend that plans its set-up moves (plan.py)
                err = self.arm.plan(T_hover)
                if err is not None and getattr(self.arm, "start_blocked", False):
                    break  # the present posture itself is too close: no other start helps
            if err is None:
                break
            # The reach map is sampled: where the hover pose is out of reach after all, mark it so.
            self.reachable[np.asarray(self.kdtree.query_ball_point(self._to_obj(a), TRANSIT_M), dtype=np.intp)] = False
        if err is not None:
            self._unreachable(f"the robot cannot reach the hover pose above the agent at {fmt_xyz(a)} m without "
                              f"touching anything ({err})",
                              "place the object where the arm reaches it from above, e.g. a lower or nearer "
                              "--object-pose (without one it stands 0.5 m in front of the base on a 0.2 m stand)")
        if a is not start:
            self.on_event(self._step(), f"robot: the tool cannot follow the normal at the start {fmt_xyz(start)} m; "
                                        f"starting at the nearest reachable target point {fmt_xyz(a)} m")
        self._start_line = (a, d)
        self.arm.spin_ref = T_hover[:3, 0].copy()
        step = self._step()
        self.sm.go(S.HOVER, self.t, step, f"moving to the hover pose {cfg.hover_height * 1e3:.0f} mm above the start {fmt_xyz(a)} m")
        fault = self.arm.move_to(T_hover, self.check)
        if fault is not None:
            self._stop(fault, step)
        # Tare in free space, at rest: the tool's weight at this orientation becomes the zero.
        self.arm.tare()
        st = self.arm.get_observation(sensor=False).state
        err = float(np.linalg.norm(st.ee_pose[:3, 3] - T_hover[:3, 3]))
        self.on_event(step, f"robot: at hover ({err * 1e3:.1f} mm from the planned pose); F/T sensor tared")

    def _approach(self) -> None:
        cfg = self.cfg
        a, d = self._start_line
        step = self._step()
        v_touch = guarded_approach_speed(0.0, cfg.approach_speed, cfg.contact_speed, self.F_d)
        self.sm.go(S.APPROACH, self.t, step, f"approaching along the normal at {cfg.approach_speed * 1e3:.0f} mm/s, "
                                             f"touching at {v_touch * 1e3:.1f} mm/s")
        self.ts[Kn.TS_PEAK_PHASE] = 0.0  # the first touch's peak (every tick)
        timeout = (cfg.hover_height + 0.03) / cfg.approach_speed + 0.03 / v_touch + 0.5
        n = int(round(timeout / self.dt))
        contact_at = f0 = None
        settled = 0
        t0 = self.t
        speed = cfg.approach_speed
        f = 0.0
        for i in range(n + int(round(PRESS_TIMEOUT_S / self.dt))):
            if contact_at is None:
                target = LineTarget(a, d, "move", speed=speed)
            else:  # ramp the set-point from the contact force to F_d: no overshoot
                f_ref = min(self.F_d, f0 + (self.F_d - f0) * (self.t - contact_at) / PRESS_RAMP_S)
                target = LineTarget(a, d, "press", force=f_ref)
            obs, fault = self._tick(target)
            if fault is not None:
                self._stop(fault, step)
            # Guarded: slow down near the expected surface (the cloud gives the gap) and touch at
            # v_touch; the backend holds the tool to that speed (a set-point advancing along the line).
            gap = float(a @ d) - float(obs.state.ee_pose[:3, 3] @ d)
            speed = guarded_approach_speed(gap, cfg.approach_speed, cfg.contact_speed, self.F_d)
            f = self.arm.force
            if contact_at is None:
                if f >= self.threshold:
                    contact_at, f0 = self.t, f
                    self.on_event(step, f"robot: contact at {f:.2f} N after {contact_at - t0:.2f} s; pressing to {self.F_d:g} N")
                elif i >= n:
                    self._stop(Fault("approach", "hold", f"no contact within {(cfg.hover_height + 0.03) * 1e3:.0f} mm below the "
                                     "hover pose; check --object-pose; holding position", self.t), step)
            elif f_ref >= self.F_d:
                settled = settled + 1 if abs(f - self.F_d) <= 0.1 * self.F_d else 0
                if settled >= max(5, int(round(SETTLED_S / self.dt))):
                    break
        else:
            self.on_event(step, f"robot: the force did not settle within {PRESS_TIMEOUT_S:.0f} s (now {f:.2f} N); exploring anyway")
        self.approach_peak = max(self.approach_peak or 0.0, float(self.ts[Kn.TS_PEAK_PHASE]))
        self.sm.go(S.EXPLORE, self.t, step, f"in contact at {f:.2f} N; exploring")

    def _explore(self, steps: int, on_step, defer_last: bool = False) -> None:
        """``steps`` explorer steps in contact. With ``defer_last`` the last step's sample is recorded
        but not handed to ``on_step`` yet: :meth:`emit_deferred` does it (with the re-capture's figures)."""
        from tergodic_cli.progress import track

        cfg = self.cfg
        ex = self.explorer
        n_sub = self.n_sub
        a_cur, d_cur = self._start_line
        self._tilted = waiting = False
        self._last_agent = None  # the first step starts from the tool
        self._rolling = False  # the tool rolling over an edge at the turn limit (the agent walks on)
        waited = 0
        obs = self.arm.get_observation()
        self.guard.feed_target(self.t)
        step = int(getattr(ex, "step_index", 0))
        ts = self.ts
        ts[Kn.TS_COUNT], ts[Kn.TS_RUN] = 1.0, 0.0  # explore ticks count towards steady contact
        s = (np.arange(1, n_sub + 1) / n_sub)[:, None]
        for k in track(range(steps), total=steps, description=f"explore ({self.arm.name})"):
            meas = self._measure(obs)
            ts[Kn.TS_N:Kn.TS_N + 3] = meas["normal"]  # the surface normal at the contact, for this interval's ticks
            deposit = self._to_obj(meas["contact_point"])[None, :] if meas["in_contact"] else np.zeros((0, 3))
            before = int(getattr(ex, "step_index", step))
            try:
                # While the agent is in the unreachable part the tool waits and the agent moves on its
                # own (reset to the waiting tool it would be sent straight back: a deadlock).
                at = None if waiting else self._agent_reset(obs)
                waited = waited + 1 if waiting else 0
                if self.max_tilt_deg is None and waited > WAIT_STEPS and (hot := self._hottest_reachable()) is not None:
                    at, waited = hot[None, :], 0
                ex.step(deposit_at=deposit, agent_at=at)
            except TergodicError as exc:
                fault = Fault("explorer", "hold", f"the explorer failed ({exc}); holding position", self.t)
                self._fault_sample(fault, before + 1, obs, a_cur, d_cur, on_step, record=True)
            step = int(getattr(ex, "step_index", before + 1))
            a_next, d_next = a_cur, d_cur
            if step == before + 1:
                a_new = self._to_base(np.asarray(ex.positions[0], dtype=float))
                fault = self.guard.check_target(self.t, a_new)
                if fault is not None:
                    self._fault_sample(fault, step, obs, a_cur, d_cur, on_step, record=True)
                a_new, d_new = self._agent_line()
                self._last_agent = (a_new, d_new)
                # Where the tool cannot follow the normal it waits on the last reachable line.
                waiting = not self._reachable_at(a_new)
                # The agent's line against the surface normal where the surface has one (not at an edge,
                # where the ball's normal turns about it; the measured press angle is checked below).
                n_a, smooth = self._surface_normal(a_new, smooth=True)
                off = math.degrees(math.acos(min(1.0, float(-d_new @ n_a))))
                if self.max_tilt_deg is None and not waiting and smooth and off > CONTACT_TILT_MAX_DEG:
                    self._fault_sample(Fault("reach", "retreat", f"the commanded tool axis is {off:.0f} deg off the "
                                             f"surface normal (limit {CONTACT_TILT_MAX_DEG:.0f}); lifting the tool off "
                                             "the surface", self.t), step, obs, a_cur, d_cur, on_step, record=True)
                if self.max_tilt_deg is None and not waiting and float(np.linalg.norm(a_new - a_cur)) > TRANSIT_M \
                        and self.arm.reach(self._hover_pose(a_new, d_new)) is not None:
                    # The reach map is sampled: where the hover pose is out of reach after all, mark it so.
                    near = self.kdtree.query_ball_point(self._to_obj(a_new), TRANSIT_M)
                    self.reachable[np.asarray(near, dtype=np.intp)] = False
                    waiting = True
                turn = math.degrees(math.acos(min(1.0, float(d_new @ d_cur))))
                n_c, smooth_c = self._surface_normal(a_cur, smooth=True)
                far = float(np.linalg.norm(a_new - a_cur))
                sharp = turn > HOP_TURN_DEG and not (smooth and smooth_c)
                if self.max_tilt_deg is None and not waiting and (far > TRANSIT_M or sharp):
                    # Back in reach away from the waiting tool, or across a sharp edge: lift, move over, touch again.
                    # (Away from a tool rolling over an edge the move is local: the tool is not in a dropped part.)
                    why = (f"the agent is {1e3 * far:.0f} mm from the tool rolling over an edge" if far > TRANSIT_M and self._rolling
                           else f"the agent is back in reach {1e3 * far:.0f} mm from the waiting tool" if far > TRANSIT_M
                           else f"the agent crossed a sharp edge ({turn:.0f} deg)")
                    a_cur, d_cur, obs = self._move_over(f"{why}; moving over", (a_cur, d_cur),
                                                        far=far > TRANSIT_M and not self._rolling)
                    a_new, d_new = a_cur, d_cur
                    turn = 0.0
                    n_c, smooth_c = self._surface_normal(a_cur, smooth=True)
                # On a gentle curve the line may turn as fast as the surface's own normal over the step
                # (+1 deg): at a flat MAX_TURN_DEG the bowl's 3.4 deg per 3 mm held the agent back
                # (--gains paper: eps 1.30 x the kinematic agent's). At an edge (the cloud's normals
                # spread) or on a tight curve (the torus's tube, 8.6 deg per step) it stays MAX_TURN_DEG.
                geo = math.degrees(math.acos(min(1.0, float(n_a @ n_c))))
                limit = max(MAX_TURN_DEG, geo + 1.0) if smooth and smooth_c and geo <= GENTLE_TURN_DEG else MAX_TURN_DEG
                self._rolling = False
                if self.max_tilt_deg is None and turn > limit:
                    # The normal turns fast (an edge, a tight curve): the ball rolls MAX_TURN_DEG about
                    # its contact, the line through where it then touches. On a tight curve the agent,
                    # reset to the tool tip, is held back with it; over an edge it walks on (not reset):
                    # held, it stood ~30 steps per edge (the corpus's concave box: 114 of 300 steps held,
                    # 42 with the contact still), and once it is past the edge the tool moves over to it.
                    d_new = turn_towards(d_cur, d_new, limit)
                    a_new = self._ball_contact(a_cur, d_new)[0]
                    self._rolling = not (smooth and smooth_c)
                # Where the line (rolled by the turn limit) lands out of reach the tool stays and the agent
                # moves on its own: reset to the tool tip it took the same step again and again (torus).
                waiting = waiting or not self._reachable_at(a_new)
                if not waiting:
                    a_next, d_next = a_new, d_new
                elif not self._told_unreachable:
                    self._told_unreachable = True
                    self.on_event(step, f"robot: the agent entered the unreachable part at {fmt_xyz(a_new)} m; the tool "
                                        "waits on the last reachable point")
                self.guard.feed_target(self.t)
                # The spin is a continuous function of the tool axis (no flips), held inside the wrist's range.
                self.arm.spin_ref = self._spin_in_wrist(tool_rotation(d_next, self._x_down)[:, 0], obs)
            # The line target glides from the previous agent line to the new one over the interval.
            A = a_cur + s * (a_next - a_cur)
            Dd = d_cur + s * (d_next - d_cur)
            Dd /= np.linalg.norm(Dd, axis=1, keepdims=True)
            v_line = (a_next - a_cur) / cfg.explore_dt if cfg.velocity_feedforward else None
            obs, a, d, fault = self._follow(A, Dd, v_line)
            if fault is not None:
                # A stalled explorer produced no new step: its last sample is out already.
                fresh = fault.kind != "explorer" and step > (self.samples[-1]["step"] if self.samples else 0)
                self._fault_sample(fault, step, obs, np.array(a), np.array(d), on_step, record=fresh)
            a_cur, d_cur = a_next, d_next
            st, g = obs.state, self.guard
            near_limit = min(np.min(st.q - g.q_lo), np.min(g.q_hi - st.q)) < JOINT_NEAR
            spinning = max(abs(st.dq) / self.arm.dq_max) > SPEED_NEAR
            if self.max_tilt_deg is None and (near_limit or spinning):
                # A joint nears its limit, or the wrist spins up (near a singularity): the posture
                # drifted from the planned one and this part is out of reach after all; the tool
                # waits here and moves over when the agent is back in reach.
                near = self.kdtree.query_ball_point(self._to_obj(a_cur), TRANSIT_M)
                self.reachable[np.asarray(near, dtype=np.intp)] = False
            sample = self._sample(step, obs, a_cur, d_cur)
            # Never press at a large angle: two explorer steps in a row (a ball rolling over an edge
            # sees single-sample transients when it touches both faces; a wrong axis stays wrong).
            press = self._measure(obs)["press_angle_deg"] if sample["in_contact"] else 0.0
            tilted, self._tilted = self._tilted, press > CONTACT_TILT_MAX_DEG
            self._reseats = [j for j in self._reseats if j > step - RESEAT_WINDOW]
            if tilted and self._tilted and (len(self._reseats) >= RESEATS or self.max_tilt_deg is not None):
                self._fault_sample(Fault("reach", "retreat", f"the tool presses {press:.0f} deg off the surface "
                                         f"normal in contact (limit {CONTACT_TILT_MAX_DEG:.0f}); lifting the tool off the "
                                         "surface", self.t), step, obs, a_cur, d_cur, on_step, record=True)
            self._record(sample)
            if defer_last and k == steps - 1:
                self._deferred = (on_step, step)
            else:
                self._emit(on_step, step)
            if tilted and self._tilted and k < steps - 1:
                # A soft sponge near a sharp edge wraps it (its contact normals tilt) and slides over
                # it: lift and touch again on the agent's own line; only a repeat is a fault.
                self._reseats.append(step)
                self._tilted = False
                a_cur, d_cur, obs = self._move_over(f"the tool pressed {press:.0f} deg off the surface normal (limit "
                                                    f"{CONTACT_TILT_MAX_DEG:.0f}); lifting and touching again on the "
                                                    "agent's line", (a_cur, d_cur))
        ts[Kn.TS_COUNT] = 0.0
        self._last_line = (a_cur, d_cur)
        self._start_line = self._last_line  # a further explore() continues from here
        self._told_unreachable = False

    def emit_deferred(self, extra: dict | None = None) -> None:
        """Hand the deferred last sample (see :meth:`_explore`) to its ``on_step``, updated with ``extra``."""
        if self._deferred is None:
            return
        on_step, step = self._deferred
        self._deferred = None
        if extra:
            self.samples[-1].update(extra)
        self._emit(on_step, step)

    def _fault_sample(self, fault: Fault, step: int, obs, a, d, on_step, record: bool) -> None:
        """Record and emit the sample of the step a fault interrupted, then make the robot safe."""
        fault = resolve_stop(fault, self.sm.state, self._touching())  # the sample names what is done about it
        self.emit_deferred()
        if record:
            self._record(self._sample(step, obs, a, d, stop_reason=fault.reason))
            self._emit(on_step, step)
        self._stop(fault, step)

    def _emit(self, on_step, step: int) -> None:
        if on_step is not None:
            t = time.perf_counter()
            on_step(step, self.samples[-1])
            self._cb_s += time.perf_counter() - t

    # ------------------------------------------------------------------ the run log
    def _transition(self, tr) -> None:
        """Before each state transition: the window of the state being left, then the transition."""
        self._log_window(tr.step)
        if self.on_log is not None:
            self.on_log("phase", tr.step, {"t": tr.t - self._t_arm0, "source": tr.source, "target": tr.target,
                                           "reason": tr.reason})

    def _log_window(self, step: int) -> None:
        """Hand the ticks since the last window (their |f| max and mean, the state they ran in) to
        ``on_log`` and start a new window."""
        ts = self.ts
        n = int(ts[Kn.TS_WIN_N])
        if n == 0:
            return
        t = self.t - self._t_arm0
        if self.on_log is not None:
            self.on_log("force", step, {"state": self.sm.state, "t_start": self._win_t0, "t_end": t, "ticks": n,
                                        "force_max": float(ts[Kn.TS_WIN_MAX]), "force_mean": float(ts[Kn.TS_WIN_SUM]) / n,
                                        **Kn.tick_figures(ts)})
        ts[Kn.TS_WIN_MAX] = ts[Kn.TS_WIN_SUM] = ts[Kn.TS_WIN_N] = 0.0
        self._win_t0 = t

    # ------------------------------------------------------------------ samples
    def _measure(self, obs) -> dict:
        """The backend's contact point, force and press angle, and the surface normal there."""
        cp, fsum, press = self.arm.contact(obs)
        T = obs.state.ee_pose
        x = cp if cp is not None else T[:3, 3]
        # The surface normal where the tool's ball touches: the cloud's fit on smooth parts; at an
        # edge (no normal of its own) the ball's contact normal, from its centre (ee pose) to the surface.
        n = self._surface_normal(x) if self.max_tilt_deg is not None else self._ball_contact(T[:3, 3], T[:3, 2])[1]
        return {"contact_point": cp, "force_contact": fsum, "in_contact": bool(cp is not None and fsum >= self.threshold),
                "normal": n, "at": x, "press_angle_deg": press}

    def _record(self, sample: dict) -> None:
        """Keep ``sample`` (it goes to the log): its contact point scored first, ``eps_sponge`` and
        ``touched_sponge`` set to the sponge's score so far (so every logged contact point, and only
        those, counts)."""
        sponge = self._score_contact(sample)
        sample["eps_sponge"], sample["touched_sponge"] = sponge.get("ergodicity"), sponge.get("touched_fraction")
        self.samples.append(sample)

    def _score_contact(self, sample: dict) -> dict:
        """Add the sample's contact point (when in contact) to the sponge's coverage score and return
        the score so far ({} when the explorer has no agent radius or spacing to score with).

        The score is :class:`~tergodic_cli.explore.metrics.CoverageScore`, the explorer's own neutral
        score, fed the contact points (capture frame) instead of the agent's positions, on the target
        the explorer works on (re-targeted, coverage kept, when that changes: the closed loop)."""
        ex = self.explorer
        if not (hasattr(ex, "r_a") and hasattr(ex, "h")):
            return {}
        p = getattr(ex, "score_target", None)  # what the explorer's own ε scores (a dense cloud: at 3 mm)
        p = self.target() if p is None else np.asarray(p, dtype=float)
        if self._contacts is None:
            from tergodic_cli.explore.index import cloud_index
            from tergodic_cli.explore.metrics import CoverageScore

            self._contacts = CoverageScore(cloud_index(self.points), p, float(ex.r_a), float(ex.h), 1)
            self._contacts_p = p.copy()
        elif not np.array_equal(p, self._contacts_p):
            from tergodic_cli.explore.index import cloud_index

            self._contacts.set_target(p, cloud_index(self.points))
            self._contacts_p = p.copy()
        if sample["in_contact"]:
            self._contacts.add(self._to_obj(sample["contact_point"])[None, :])
        return self._contacts.metrics()

    def _sample(self, step: int, obs, a: np.ndarray, d: np.ndarray, stop_reason: str | None = None) -> dict:
        """The robot_sample_dict of CONTRACTS.md (plus extras) at the end of an explorer interval."""
        self._log_window(step)
        st, w = obs.state, np.nan_to_num(np.asarray(obs.wrench, dtype=float))
        meas = self._measure(obs)
        T = st.ee_pose
        R = T[:3, :3]
        n = meas["normal"]
        tilt = math.degrees(math.acos(max(-1.0, min(1.0, float(-R[:, 2] @ n)))))
        f_base = R @ w[:3]
        agent = self.explorer.metrics() if hasattr(self.explorer, "metrics") else {}
        sample = {
            "t_sim": float(st.t - self._t_arm0),
            "t_wall": time.perf_counter() - self._t0 - self._cb_s - self.paused_s,
            "state": self.sm.state,
            "ee_pose": np.concatenate([T[:3, 3], matrix_to_quat(R)]),
            "q": st.q.copy(),
            "dq": st.dq.copy(),
            "tau": np.asarray(self.arm.tau, dtype=float).copy(),
            "joint_names": list(self.arm.joint_names),
            "link_poses": self.arm.link_poses(),
            "object_pose": np.concatenate([self.T_obj[:3, 3], matrix_to_quat(self.T_obj[:3, :3])]),
            "wrench_measured": w.copy(),
            "wrench_desired": np.array([0.0, 0.0, self.F_d, 0.0, 0.0, 0.0]),
            "force_normal": float(-(f_base @ n)) if meas["in_contact"] or abs(w[2]) > 0 else 0.0,
            "force_contact": meas["force_contact"],
            "force_filtered": float(self.arm.force),
            "in_contact": meas["in_contact"],
            "contact_point": meas["contact_point"],
            "tilt_deg": tilt,
            "track_mm": 1e3 * point_line_distance(meas["at"], a, d),
            "agent_line_point": np.asarray(a, dtype=float).copy(),
            "agent_line_dir": np.asarray(d, dtype=float).copy(),
            # ε so far (unit-mass, explore.metrics.coverage_score) of the sponge's contact points, and of
            # the virtual agent's own path (the explorer's neutral score), on the same target
            # (eps_sponge and touched_sponge are added when the sample is recorded: _record)
            "eps_agent": agent.get("ergodicity"),
            "touched_agent": agent.get("touched_fraction"),
            "step": int(step),
            **Kn.tick_figures(self.ts),
        }
        if stop_reason:
            sample["stop_reason"] = stop_reason
        return sample

    # ------------------------------------------------------------------ the run
    def run(self, steps: int, on_step: Callable[[int, dict], None] | None = None) -> dict:
        """Picture -> hover -> approach -> explore ``steps`` explorer steps -> retreat. Returns the summary extras.

        A fault ends the run safe (retreat or hold, then ``stopped``); so does Ctrl-C
        (KeyboardInterrupt anywhere inside, ``on_step`` included): the tool retreats if it was
        in contact, the arm holds still, and the summary says ``interrupted``.
        """
        if int(steps) < 1:
            raise TergodicError(f"--steps must be >= 1, got {steps}", "e.g. --steps 300")
        self.begin()
        with self.guarded():
            self.engage()
            self._explore(int(steps), on_step)
            self.finish(f"{steps} explorer steps done; retreating")
        return self.result()

    def begin(self) -> None:
        """Start the run's clocks, at the picture pose (once per run)."""
        self._t0 = time.perf_counter()
        self._cpu0 = time.process_time()
        self._t_arm0 = self.arm.t_origin
        self._win_t0 = self.t - self._t_arm0
        self._cb_s = 0.0
        self.paused_s = 0.0  # wall seconds the robot waited for others (the closed loop's re-captures)
        self.on_event(0, f"robot {S.PICTURE}: {self.arm.name} at the picture pose, {1 / self.dt:g} Hz control "
                         f"({self.n_sub} periods per explorer step); cloud of {len(self.points)} points, "
                         f"force limit {self.guard.force_limit:g} N (low-passed at {self.safety.force_filter_hz:g} Hz), "
                         f"impact limit {self.guard.force_impact_limit:g} N (one tick)")

    @contextlib.contextmanager
    def guarded(self):
        """Run phases inside: a fault (already made safe) ends them; Ctrl-C makes the robot safe and ends them."""
        try:
            yield
        except _Stop:
            pass
        except KeyboardInterrupt:
            self._interrupt()

    def engage(self) -> None:
        """(picture) -> hover above the agent -> approach -> pressing at F_d, state ``explore``."""
        from tergodic_cli.progress import Spinner

        with Spinner("robot: moving to the start and approaching"):
            self._move_to_hover()
            self._approach()

    def explore(self, steps: int, on_step: Callable[[int, dict], None] | None = None, defer_last: bool = False) -> None:
        """``steps`` explorer steps in contact (state ``explore``); see :meth:`_explore`."""
        self._explore(int(steps), on_step, defer_last)

    def _move_over(self, reason: str, line: tuple[np.ndarray, np.ndarray], far: bool = False):
        """explore -> retreat along the tool's ``line`` (a, d) -> hover above the agent -> approach -> explore.
        ``far``: through the picture pose (a joint-space move across the object could sweep through it).
        Returns the new line's point and direction and the observation there."""
        self._last_line = line
        if far:
            self.to_picture(reason)
        else:
            step = self._step()
            self.sm.go(S.RETREAT, self.t, step, reason)
            self._retreat(*self._last_line, step)
        self.move_overs += 1
        self.engage()
        self.ts[Kn.TS_COUNT], self.ts[Kn.TS_RUN] = 1.0, 0.0
        self.guard.feed_target(self.t)
        return (*self._start_line, self.arm.get_observation())

    def to_picture(self, reason: str) -> None:
        """explore -> retreat along the tool axis -> move to the picture pose, state ``picture``."""
        step = self._step()
        self.sm.go(S.RETREAT, self.t, step, reason)
        self._retreat(*self._last_line, step)
        self.sm.go(S.PICTURE, self.t, step, "retreated; moving to the picture pose")
        fault = self.arm.to_picture(self.check)
        if fault is not None:
            self._stop(fault, step)

    def finish(self, reason: str) -> None:
        """End normally: retreat if in contact, then ``done``, holding still."""
        step = self._step()
        if self.sm.state == S.EXPLORE:
            self.sm.go(S.RETREAT, self.t, step, reason)
            self._retreat(*self._last_line, step)
            reason = "retreated; done"
        self.sm.go(S.DONE, self.t, step, reason)
        self.arm.hold(SETTLE_S)
        self.arm.stop()

    def _interrupt(self) -> None:
        """Ctrl-C: retreat if the tool may be in contact, else hold; end ``stopped`` with a one-line reason."""
        self.interrupted = True
        reason = "interrupted by the user (Ctrl-C)"
        state = self.sm.state
        if self.sm.finished or state == S.HOLD:  # already stopping or stopped
            self.stop_reason = self.stop_reason or reason
            return
        contact = state in CONTACT_STATES or self._touching()
        fault = Fault("interrupt", "retreat" if contact else "hold",
                      f"{reason}; {'retreating' if contact else 'holding position'}", self.t)
        try:
            self._stop(fault, self._step())
        except _Stop:
            pass

    def result(self) -> dict:
        """The summary extras of the run so far (call once, at the end)."""
        self.emit_deferred()
        self._log_window(self._step())  # the ticks after the last sample (a retreat, a fault's)
        wall = time.perf_counter() - self._t0 - self._cb_s - self.paused_s
        # (the callback's and the pauses' wall time: a fair proxy for their CPU)
        cpu = time.process_time() - self._cpu0 - self._cb_s - self.paused_s
        robot_s = self.t - self._t_arm0
        out = summarize_robot(self.samples, stop_reason=self.stop_reason, ticks=Kn.tick_figures(self.ts))
        out.update({
            "force_peak_approach_N": self.approach_peak,
            "backend": self.arm.name,
            "final_state": self.sm.state,
            "interrupted": bool(self.interrupted),
            "move_overs": self.move_overs,
            "sim_seconds": robot_s,
            "robot_seconds": robot_s,
            "wall_seconds": wall,
            "realtime_factor_run": robot_s / wall if wall > 0 else None,
            "cpu_seconds": cpu,
            "transitions": [{"t": round(tr.t - self._t_arm0, 4), "step": tr.step, "from": tr.source, "to": tr.target,
                             "reason": tr.reason} for tr in self.sm.history],
            "object_pose": [float(x) for x in np.concatenate([self.T_obj[:3, 3], matrix_to_quat(self.T_obj[:3, :3])])],
            "control_hz": 1.0 / self.dt,
            "explorer_hz": 1.0 / self.cfg.explore_dt,
            "robot_config": self.cfg.to_dict(),
            **self.arm.summary(),
        })
        return out

    def _step(self) -> int:
        return int(getattr(self.explorer, "step_index", 0))

    def close(self) -> None:
        self.arm.disconnect()

    def __enter__(self) -> "ContactRun":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def turn_towards(d0: np.ndarray, d1: np.ndarray, max_deg: float) -> np.ndarray:
    """Unit (3,): ``d0`` rotated towards ``d1`` (both unit) by at most ``max_deg`` degrees; ``d0``
    when ``d1`` is its opposite (no direction to turn in)."""
    ang = math.acos(max(-1.0, min(1.0, float(d0 @ d1))))
    if ang <= math.radians(max_deg):
        return d1
    side = d1 - (d0 @ d1) * d0
    n = float(np.linalg.norm(side))
    if n < 1e-12:
        return d0.copy()
    return math.cos(math.radians(max_deg)) * d0 + math.sin(math.radians(max_deg)) * side / n
