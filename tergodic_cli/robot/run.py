"""``tergodic explore --robot pybullet``: the explorer drives a force-controlled arm.

Timing. The control loop (controller, safety checks, physics) runs at 1/physics_dt (1 kHz).
The explorer runs once every ``explore_dt`` simulated seconds (0.2 s: 200 control steps).
Between two explorer steps the line target glides linearly from the previous agent line to
the new one, so the arm follows a continuous path. The explorer is time-scaled for this
(:func:`robot_explore_config`): the paper's 3 mm/s agent with 1 s steps becomes a 15 mm/s
agent with 0.2 s steps, the same 3 mm path per step and the same diffusion per step, five
times faster in simulated time.

Coverage comes from the real contact: at each explorer step the sponge's contact point with
the object (force-weighted mean of PyBullet's contact points) is deposited when the contact
normal force exceeds ``contact_threshold``; the agent is reset to the measured tool tip
(paper eq. 22) before its gradient step.
"""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import replace
from typing import Callable

import numpy as np

from tergodic_cli.capture.filters import mean_spacing

from tergodic_cli.errors import TergodicError
from tergodic_cli.robot import statemachine as S
from tergodic_cli.robot.config import RobotConfig, validate_robot_config
from tergodic_cli.robot.controller import JointImpedance, LineForceController, guarded_approach_speed, min_jerk
from tergodic_cli.robot.ga import matrix_to_quat, point_line_distance, pose_matrix
from tergodic_cli.robot.interfaces import ContactWrench
from tergodic_cli.robot.kernels import TS_COUNT as _TS_COUNT, TS_N as _TS_N, TS_PEAK_PHASE as _TS_PEAK_PHASE, \
    TS_RUN as _TS_RUN, tick_figures, tick_stats as _tick_stats
from tergodic_cli.robot.pybullet_backend import PyBulletArm, PyBulletScene, PyBulletWrenchSensor
from tergodic_cli.robot.safety import Fault, SafetyGuard, resolve_stop
from tergodic_cli.robot.summary import summarize_robot
from tergodic_cli.robot.surface import (check_reachable, default_object_pose, oriented_normals, parse_object_pose,
                                        reconstruct_mesh, resolve_side, sim_object_mesh, transform_points)

#: Seconds of joint-impedance holding after a stop, so the arm ends at rest.
HOLD_S = 0.5
SETTLE_S = 0.3
PRESS_TIMEOUT_S = 2.0
PRESS_RAMP_S = 0.5
#: N/m of the approach's axial position servo: its set-point advances at the guarded speed, so a
#: steady push on the tool (gravity-model error, posture torques) cannot make it touch faster (a
#: pure velocity servo, D_z = 50 N s/m, let 0.17 N push it in at 5.5 mm/s against 2 commanded).
APPROACH_K = 2000.0
#: N s/m added to the approach's axial damping (the controller's D_z, 50) on the speed error.
APPROACH_D = 100.0
RETREAT_TIMEOUT_S = 3.0
#: Degrees between the tool axis and the surface normal in contact above which the run lifts the tool
#: and stops (issue 15: never press at a large angle; following the normal, the median is ~1 deg).
CONTACT_TILT_MAX_DEG = 15.0
#: Metres above the object's highest point the tool passes on its way to and from the picture pose.
CLEARANCE = 0.04


def robot_explore_config(cfg, explore_dt: float):
    """The explorer config time-scaled to ``explore_dt`` s per step, with the same path per step.

    dt -> explore_dt, v_max -> v_max·k, a_max -> a_max·k² with k = dt / explore_dt: each step
    still moves the agent by at most v_max·dt metres and the diffusion per step is unchanged.
    """
    k = cfg.dt / explore_dt
    return replace(cfg, dt=explore_dt, v_max=cfg.v_max * k, a_max=cfg.a_max * k * k)


class _Stop(Exception):
    """Raised inside a phase when a fault ended it (the robot has been made safe)."""


class RobotRun:
    """One robot run: the scene built from the capture, the devices, the controller, the guard.

    Tests and benchmarks reach in for fault injection (``run.sensor``, ``run.scene``); the CLI
    goes through :func:`explore_with_robot`.
    """

    def __init__(self, capture, explorer, cfg: RobotConfig, on_event: Callable[[int, str], None] | None = None,
                 scene_mesh=None):
        from scipy.spatial import cKDTree

        from tergodic_cli.robot.kinematics import FrankaModel, tool_offset
        validate_robot_config(cfg)
        t_setup = time.perf_counter()
        self.cfg = cfg
        self.explorer = explorer
        self.on_event = on_event or (lambda step, msg: None)
        self.F_d = float(cfg.force)
        self.threshold = cfg.contact_threshold
        edt = float(getattr(getattr(explorer, "cfg", None), "dt", cfg.explore_dt))
        if abs(edt - cfg.explore_dt) > 1e-9:
            raise TergodicError(f"the explorer steps {edt:g} s but the robot expects {cfg.explore_dt:g} s per explorer step",
                                "build the explorer with robot_explore_config(cfg, robot_cfg.explore_dt)")
        points = np.asarray(capture.points, dtype=float)
        self.points = points
        meta = getattr(capture, "meta", {}) or {}
        self._pose_given = cfg.object_pose is not None or meta.get("frame") == "robot_base"
        if cfg.object_pose is not None:
            self.T_obj = parse_object_pose(cfg.object_pose)
        elif meta.get("frame") == "robot_base":  # a calibrated (or simulated) camera: the cloud is in the base frame
            self.T_obj = np.eye(4)
        else:
            self.T_obj = default_object_pose(points)
        self.points_base = transform_points(self.T_obj, points)
        check_reachable(self.points_base)
        side = resolve_side(cfg.normal_side, getattr(capture, "meta", {}) or {})
        self.normals = oriented_normals(points, side)
        sim = meta.get("sim") if isinstance(meta.get("sim"), dict) else None
        if scene_mesh is not None:  # given (mesh, pose in the capture frame), e.g. the closed loop's textured object
            self.mesh, T_mesh = scene_mesh
            self.mesh_source = "given"
        elif sim is not None and sim.get("object"):
            # A simulated capture: press on the object the camera rendered (its own surface), not on a
            # mesh rebuilt from the cloud; the cleaning model fades exactly that surface.
            self.mesh, T_mesh = sim_object_mesh(sim, cfg.mesh_edge)
            self.mesh_source = "sim_object"
        else:
            h = float(meta.get("spacing_h_m") or mean_spacing(points))
            self.mesh, T_mesh = reconstruct_mesh(points, self.normals, h, cfg.mesh_edge), np.eye(4)
            self.mesh_source = "cloud"
        self._T_mesh_obj = np.asarray(T_mesh, dtype=float)
        self.T_mesh = self.T_obj @ self._T_mesh_obj  # mesh frame -> base frame
        self._mesh_top = float(transform_points(self.T_mesh, self.mesh.vertices)[:, 2].max())
        self.kdtree = cKDTree(points)
        #: Called as contact_hook(contacts, dt) every ``hook_every`` physics steps with the sponge's
        #: contacts [(point on the object (3,) base frame, normal (3,), normal force N)] and the
        #: simulated seconds they stand for (the closed loop's cleaning model). None: no calls.
        self.contact_hook: Callable[[list, float], None] | None = None
        self.hook_every = 20
        self._hook_age = 0
        self.hook_s = 0.0  # wall seconds spent in contact_hook

        self.scene = PyBulletScene(cfg.sponge, gui=cfg.gui, dt=cfg.physics_dt, solver_iterations=cfg.solver_iterations)
        try:
            self.scene.add_object(self.mesh.vertices, self.mesh.triangles, self.T_mesh)
            self.arm = PyBulletArm(self.scene)
            self.arm.jacobian_every = int(cfg.jacobian_every)
            self.arm.dynamics_every = int(cfg.dynamics_every)
            self.arm.connect()
            self.scene.set_arm(np.array(cfg.picture_q))
            self.sensor = PyBulletWrenchSensor(self.scene, self.arm)
            if not self.sensor.read().valid:  # PyBullet reads 0 until its first step: hold still for one
                self.arm.command(np.zeros(7))
                self.scene.step()
            # Gravity and inertia of the tool removed: the wrench is the contact's (issue 15, item 3).
            self.contact = ContactWrench(self.scene.tool_load(), self.sensor.frame_in_ee, inertial=cfg.inertial_compensation)
            st = self.arm.read_state()
            self.model = FrankaModel()
            self.model.tool = tool_offset(self.model, st.q, st.ee_pose)
            # >>> reach (issue 15, item 1): object pose, reachable mask, unreachable target dropped
            self._x_down = st.ee_pose[:3, 0].copy()  # the tool's spin pointing straight down (reach.tool_rotation)
            self._plan_reach(capture)
            # <<< reach
        except BaseException:
            self.scene.close()
            raise
        self.guard = SafetyGuard(cfg.safety, self.arm.q_min, self.arm.q_max, self.arm.dq_max, self.F_d)
        from tergodic_cli.robot import kernels as Kn
        from tergodic_cli.robot.summary import SETTLE_S as STEADY_S

        #: Every 1 kHz tick's force peak, steady-contact force error and tilt (kernels.tick_stats).
        self.ts = Kn.new_tick_stats(self.F_d, self.threshold, int(round(STEADY_S / cfg.physics_dt)))
        self.approach_peak: float | None = None
        self.sm = S.StateMachine(on_event=self.on_event)
        self.joint = JointImpedance()
        self.samples: list[dict] = []
        self.stop_reason: str | None = None
        self.fault: Fault | None = None
        self.setup_s = time.perf_counter() - t_setup
        self._shadow = _AgentCoverage(explorer)
        self._x_ref = st.ee_pose[:3, 0].copy()
        self._cb_s = 0.0
        self._deferred = None
        self._meas_cache = None
        self.interrupted = False
        self._told_unreachable = False
        #: The compiled 1 kHz loop (PyBullet arm); False: the generic loop through the protocols.
        self.fast_loop = True
        self._t0 = None
        self.paused_s = 0.0

    # ------------------------------------------------------------------ frames
    def _to_base(self, x: np.ndarray) -> np.ndarray:
        return transform_points(self.T_obj, x)

    def _to_obj(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, dtype=float) - self.T_obj[:3, 3]) @ self.T_obj[:3, :3]

    def _surface_normal(self, x_base: np.ndarray, k: int = 6) -> np.ndarray:
        """Oriented unit surface normal (base frame) near ``x_base``: mean of the k nearest cloud normals."""
        _, idx = self.kdtree.query(self._to_obj(x_base), k=k)
        n = self.normals[np.atleast_1d(idx)].mean(axis=0)
        return self.T_obj[:3, :3] @ (n / np.linalg.norm(n))

    # >>> reach (issue 15, item 1)
    def _plan_reach(self, capture) -> None:
        """Choose the object pose (when not given), mark where the tool can follow the normal, and drop
        the rest of the target from the explorer (reach.plan_reach), saying so before any contact."""
        from tergodic_cli.robot.reach import plan_reach

        target = np.asarray(getattr(self.explorer, "p", getattr(capture, "target", np.ones(len(self.points)))), dtype=float)
        T, self.reachable = plan_reach(self.arm._chain, self.points, self.normals, target, self._x_down,
                                       np.array(self.cfg.picture_q), self.arm.q_min, self.arm.q_max,
                                       self.T_obj if self._pose_given else None, self.cfg.hover_height)
        if not self._pose_given:
            self.T_obj = T
            self.points_base = transform_points(T, self.points)
            self.T_mesh = T @ self._T_mesh_obj
            self._mesh_top = float(transform_points(self.T_mesh, self.mesh.vertices)[:, 2].max())
            self.scene.move_object(self.T_mesh)
            yaw = math.degrees(math.atan2(T[1, 0], T[0, 0]))
            self.on_event(0, "robot: no --object-pose given; the object stands on a 0.2 m stand, its footprint centre "
                             f"{float(np.hypot(*T[:2, 3])):.2f} m in front of the base, turned {yaw:.0f} deg so the arm "
                             f"reaches its target (object pose {_fmt(T[:3, 3])} m)")
        total = float(target.sum())
        kept = target * self.reachable
        lost = 1.0 - float(kept.sum()) / total if total > 0 else 0.0
        if lost > 1e-3:
            if float(kept.sum()) <= 0:
                raise TergodicError("the tool cannot follow the surface normal anywhere on the target (the arm's wrist "
                                    "cannot reach those orientations)", "move or turn the object with --object-pose")
            self.on_event(0, f"robot: {100 * lost:.0f} % of the target is where the tool cannot follow the normal "
                             f"({100 * (1 - self.reachable.mean()):.0f} % of the surface); dropped from the target")
            if hasattr(self.explorer, "set_target"):
                self.explorer.set_target(kept)

    def _reachable_at(self, x_base: np.ndarray) -> bool:
        return bool(self.reachable[self.kdtree.query(self._to_obj(x_base))[1]])
    # <<< reach

    def _agent_line(self) -> tuple[np.ndarray, np.ndarray]:
        """The explorer's line L_a⊥ in the base frame: point and unit direction into the surface."""
        x = np.asarray(self.explorer.positions[0], dtype=float)
        n = np.asarray(self.explorer.normals[0], dtype=float)
        a = self._to_base(x)
        n_b = self.T_obj[:3, :3] @ n
        if n_b @ self._surface_normal(a) < 0:  # the explorer's normal sign is arbitrary; ours faces the tool
            n_b = -n_b
        return a, -n_b / np.linalg.norm(n_b)  # reach: the tool follows the normal (unreachable parts are dropped)

    def _update_spin_ref(self, d: np.ndarray) -> None:
        # reach: the spin is a continuous function of the tool axis (no flips, wrist mid-range)
        from tergodic_cli.robot.reach import tool_rotation

        self._x_ref = tool_rotation(d, self._x_down)[:, 0]
        self.ctrl.x_ref = self._x_ref

    # ------------------------------------------------------------------ one control step
    def _tick(self, mode: str, a=None, d=None, q_d=None, dq_d=None, speed: float = 0.0, checks: bool = True,
              force: float | None = None, use_sensor: bool = True):
        """Read, check, command, step. Returns (state, ee wrench, controller output or None, fault or None).
        ``use_sensor`` False: the F/T is not read (w = 0; only for modes that do not use the force)."""
        st = self.arm.read_state()
        if use_sensor:
            rd = self.sensor.read()
            w = self.contact(rd.wrench, st.ee_pose, st)
            if rd.valid:
                _tick_stats(st.ee_pose, w, self.ts)
        else:
            rd, w = None, np.zeros(6)
        fault = None
        out = None
        if mode == "joint":
            tau = self.joint(st.q, st.dq, q_d, dq_d)
        else:
            out = self.ctrl.step(st, a, d, w, mode, self.F_d if force is None else force, speed)
            tau = out.tau
        if checks:
            g = self.guard
            fault = g.check_reading(st.t, rd, w) if rd is not None else None
            if fault is None:
                v = out.v_ee if out is not None else (st.jacobian[:3] @ st.dq).tolist()
                fault = g.check_state(st.t, st.q, st.dq, st.pos, math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]))
            if fault is None and self.sm.state == S.EXPLORE:
                fault = g.check_explorer(st.t)
        if fault is None:
            self.arm.command(tau)
            self.scene.step()
            if self.contact_hook is not None:
                self._run_hook()
            if self.cfg.realtime:
                lag = self.scene.t - (time.perf_counter() - self._t0)
                if lag > 0:
                    time.sleep(lag)
        return st, w, out, fault

    def _track(self, A: np.ndarray, D: np.ndarray, v_ref=None):
        """The 1 kHz loop of one explorer interval (A, D: (n, 3) target line points and directions,
        one per control step). Yields (state, wrench, a, d, fault) after the last step or at the
        first fault (the fault's step is not commanded)."""
        if self.fast_loop and isinstance(self.arm, PyBulletArm):
            return self._track_fast(A, D, v_ref)
        return self._track_generic(A.tolist(), D.tolist(), v_ref)

    def _track_fast(self, A: np.ndarray, D: np.ndarray, v_ref=None):
        """:meth:`_track_generic` for the PyBullet arm with the arithmetic in one compiled call per
        tick (:func:`~tergodic_cli.robot.kernels.pybullet_tick`): per tick one joint read, the
        sensor read, the kernel, one torque command, the physics step, and gravity + Coriolis every
        ``dynamics_every`` ticks. Same checks in the same order, same arithmetic."""
        from tergodic_cli.robot import kernels as Kn
        from tergodic_cli.robot.interfaces import ArmState

        arm, sc, ctrl, g = self.arm, self.scene, self.ctrl, self.guard
        p, cid, rob, idx = sc.p, sc.cid, sc.robot, arm._read_idx
        get_states, inv_dyn, send, physics = p.getJointStates, p.calculateInverseDynamics, p.setJointMotorControlArray, \
            p.stepSimulation
        joints, mode_torque, dt = sc.arm_joints, p.TORQUE_CONTROL, sc.dt
        sread, tick = self.sensor.read, Kn.pybullet_tick
        check_sensor, timeout = g.check_sensor, g.cfg.explorer_timeout
        cst = Kn.pack_constants(arm._chain, self.contact, g, arm.tau_max, self.F_d, v_ref)
        io = np.zeros(Kn.N_IO)
        kpk, mut, ts, dyn = ctrl.kpk, ctrl.mut, self.ts, self.contact.dyn
        A = np.ascontiguousarray(A, dtype=float)
        D = np.ascontiguousarray(D, dtype=float)
        zeros, every, realtime = arm._zeros, arm.dynamics_every, self.cfg.realtime
        hook = self._run_hook if self.contact_hook is not None else None
        OK, F_FORCE, tau_sl = Kn.OK, Kn.F_FORCE, slice(Kn.IO_TAU, Kn.IO_TAU + 7)

        def state():  # the ArmState of the last tick's read (as _track_generic yields it)
            return ArmState(t, io[Kn.IO_Q:Kn.IO_Q + 7].copy(), io[Kn.IO_DQ:Kn.IO_DQ + 7].copy(),
                            io[Kn.IO_T:Kn.IO_T + 16].reshape(4, 4).copy(), io[Kn.IO_J:Kn.IO_J + 42].reshape(6, 7).copy())

        i = -1
        t = sc.t
        for i in range(len(A)):
            # Flat tuples: q, q̇ and reactions of the movable joints, then the sensor joint's (last).
            qs, dqs, rs, _ = zip(*get_states(rob, idx, physicsClientId=cid))
            arm.reaction, arm.reaction_step = rs[-1], sc.steps
            rd = sread()
            t = sc.t
            arm._bias_age += 1
            if arm._bias is None or arm._bias_age >= every or arm._bias_epoch != sc.teleports:
                arm._bias = inv_dyn(rob, qs[:-1], dqs[:-1], zeros, physicsClientId=cid)
                arm._bias_age = 0
                arm._bias_epoch = sc.teleports
            fault = check_sensor(t, rd.t, rd.wrench)
            if fault is None:
                code = tick(i, A, D, qs, dqs, rd.wrench, arm._bias, cst, kpk, mut, io, ts, t, dyn)
                if code != OK:
                    st = state()
                    if code == F_FORCE:
                        fault = g.check_force(t, io[Kn.IO_W:Kn.IO_W + 6])
                    else:
                        v = io[Kn.IO_DIAG + Kn.CD_VEE:Kn.IO_DIAG + Kn.CD_VEE + 3]
                        fault = g.check_state(t, st.q, st.dq, st.ee_pose[:3, 3].copy(), float(np.sqrt(v @ v)))
                elif g._target_t is not None and t - g._target_t > timeout:
                    fault = g.check_explorer(t)
            if fault is not None:
                arm._q9 = arm._dq9 = None  # stale: the next command() reads the state first
                yield state(), io[Kn.IO_W:Kn.IO_W + 6].copy(), A[i], D[i], fault
                return
            tot = io[tau_sl].tolist()
            arm.last_tau = tot
            send(rob, joints, mode_torque, forces=tot, physicsClientId=cid)
            physics(physicsClientId=cid)
            sc.steps += 1
            sc.t = sc.steps * dt
            if hook is not None:
                hook()
            if realtime:
                lag = sc.t - (time.perf_counter() - self._t0)
                if lag > 0:
                    time.sleep(lag)
        arm._q9 = arm._dq9 = None
        if i < 0:
            st = arm.read_state()
            yield st, self.contact(self.sensor.read().wrench, st.ee_pose), None, None, None
            return
        yield state(), io[Kn.IO_W:Kn.IO_W + 6].copy(), A[i], D[i], None

    def _joint_fast(self, QD: np.ndarray, DQD: np.ndarray):
        """:meth:`_tick` ("joint", with every check) along QD, DQD (n, 7) for the PyBullet arm, the
        arithmetic in one compiled call per tick (:func:`~tergodic_cli.robot.kernels.pybullet_joint_tick`),
        as :meth:`_track_fast` does for the line tracking. Returns the first fault (that step is not
        commanded) or None."""
        from tergodic_cli.robot import kernels as Kn

        arm, sc, g = self.arm, self.scene, self.guard
        p, cid, rob, idx = sc.p, sc.cid, sc.robot, arm._read_idx
        get_states, inv_dyn, send, physics = p.getJointStates, p.calculateInverseDynamics, p.setJointMotorControlArray, \
            p.stepSimulation
        joints, mode_torque, dt = sc.arm_joints, p.TORQUE_CONTROL, sc.dt
        sread, tick, check_sensor = self.sensor.read, Kn.pybullet_joint_tick, g.check_sensor
        cst = Kn.pack_constants(arm._chain, self.contact, g, arm.tau_max, self.F_d, None)
        kd = np.ascontiguousarray(np.concatenate([self.joint.K, self.joint.D]), dtype=float)
        io = np.zeros(Kn.N_IO)
        QD = np.ascontiguousarray(QD, dtype=float)
        DQD = np.ascontiguousarray(DQD, dtype=float)
        zeros, every, realtime = arm._zeros, arm.dynamics_every, self.cfg.realtime
        hook = self._run_hook if self.contact_hook is not None else None
        OK, tau_sl = Kn.OK, slice(Kn.IO_TAU, Kn.IO_TAU + 7)
        explore = self.sm.state == S.EXPLORE
        for i in range(len(QD)):
            qs, dqs, rs, _ = zip(*get_states(rob, idx, physicsClientId=cid))
            arm.reaction, arm.reaction_step = rs[-1], sc.steps
            rd = sread()
            t = sc.t
            arm._bias_age += 1
            if arm._bias is None or arm._bias_age >= every or arm._bias_epoch != sc.teleports:
                arm._bias = inv_dyn(rob, qs[:-1], dqs[:-1], zeros, physicsClientId=cid)
                arm._bias_age = 0
                arm._bias_epoch = sc.teleports
            fault = check_sensor(t, rd.t, rd.wrench)
            if fault is None:
                code = tick(i, QD, DQD, qs, dqs, rd.wrench, arm._bias, cst, kd, io, self.ts, t, self.contact.dyn)
                if code == Kn.F_FORCE:
                    fault = g.check_force(t, io[Kn.IO_W:Kn.IO_W + 6])
                elif code != OK:
                    v = io[Kn.IO_DIAG + Kn.CD_VEE:Kn.IO_DIAG + Kn.CD_VEE + 3]
                    fault = g.check_state(t, io[Kn.IO_Q:Kn.IO_Q + 7].copy(), io[Kn.IO_DQ:Kn.IO_DQ + 7].copy(),
                                          io[Kn.IO_T:Kn.IO_T + 16].reshape(4, 4)[:3, 3].copy(), float(np.sqrt(v @ v)))
                elif explore:
                    fault = g.check_explorer(t)
            if fault is not None:
                arm._q9 = arm._dq9 = None  # stale: the next command() reads the state first
                return fault
            tot = io[tau_sl].tolist()
            arm.last_tau = tot
            send(rob, joints, mode_torque, forces=tot, physicsClientId=cid)
            physics(physicsClientId=cid)
            sc.steps += 1
            sc.t = sc.steps * dt
            if hook is not None:
                hook()
            if realtime:
                lag = sc.t - (time.perf_counter() - self._t0)
                if lag > 0:
                    time.sleep(lag)
        arm._q9 = arm._dq9 = None
        return None

    def _track_generic(self, A: list, D: list, v_ref=None):
        """The 1 kHz loop of one explorer interval through the Arm/WrenchSensor protocols:
        :meth:`_tick` ("track", with every check) unrolled with local names."""
        read, sread, contact = self.arm.read_state, self.sensor.read, self.contact
        ctrl, command, physics = self.ctrl.step, self.arm.command, self.scene.step
        g = self.guard
        check_sensor, check_force, check_state, check_explorer = g.check_sensor, g.check_force, g.check_state, g.check_explorer
        F_d, sqrt, realtime, ts = self.F_d, math.sqrt, self.cfg.realtime, self.ts
        hook = self._run_hook if self.contact_hook is not None else None
        st = w = a = d = None
        for a, d in zip(A, D):
            st = read()
            rd = sread()
            t = st.t
            w = contact(rd.wrench, st.ee_pose, st)
            _tick_stats(st.ee_pose, w, ts)
            out = ctrl(st, a, d, w, "track", F_d, 0.0, v_ref)
            v = out.v_ee
            fault = (check_sensor(t, rd.t, rd.wrench) or check_force(t, w)
                     or check_state(t, st.q, st.dq, st.pos, sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]))
                     or check_explorer(t))
            if fault is not None:
                yield st, w, a, d, fault
                return
            command(out.tau)
            physics()
            if hook is not None:
                hook()
            if realtime:
                lag = self.scene.t - (time.perf_counter() - self._t0)
                if lag > 0:
                    time.sleep(lag)
        yield st, w, a, d, None

    def _run_hook(self) -> None:
        """Every ``hook_every`` physics steps: hand the sponge's contacts to ``contact_hook``."""
        self._hook_age += 1
        if self._hook_age >= self.hook_every:
            self._hook_age = 0
            t = time.perf_counter()
            self.contact_hook(self.scene.sponge_contacts(), self.hook_every * self.cfg.physics_dt)
            self.hook_s += time.perf_counter() - t

    # ------------------------------------------------------------------ faults and stops
    def _stop(self, fault: Fault, step: int) -> None:
        """Make the robot safe after ``fault`` and end the run (raises :class:`_Stop`).

        In contact (approach, explore) every fault lifts the tool along its axis without reading
        the sensor (:func:`~tergodic_cli.robot.safety.stop_action`), then holds, lifted."""
        fault = resolve_stop(fault, self.sm.state)
        self.ts[_TS_COUNT] = 0.0
        self.fault = fault
        self.stop_reason = fault.reason
        if fault.action == "retreat" and self.sm.state not in (S.RETREAT,):
            self.sm.go(S.RETREAT, self.scene.t, step, fault.reason)
            T = self.arm.read_state().ee_pose
            self._retreat(T[:3, 3], T[:3, 2], step, checks=False, use_sensor=False)
            self._hold(HOLD_S)
            self.sm.go(S.STOPPED, self.scene.t, step, "retreated after a fault; holding still")
        else:
            self.sm.go(S.HOLD, self.scene.t, step, fault.reason)
            self._hold(HOLD_S)
            self.sm.go(S.STOPPED, self.scene.t, step, "held position after a fault; holding still")
        raise _Stop(fault.reason)

    def _hold(self, seconds: float) -> None:
        q = self.arm.read_state().q.copy()
        for _ in range(int(round(seconds / self.cfg.physics_dt))):
            self._tick("joint", q_d=q, checks=False)

    def _retreat(self, a: np.ndarray, d: np.ndarray, step: int, checks: bool = True, use_sensor: bool = True) -> None:
        """Back the tool off along its axis by ``retreat_distance`` (line fixed on (a, d)): at least
        the hover height, so the tool ends lifted. The retreat mode never uses the force; with
        ``use_sensor`` False it does not even read the sensor (a fault may have come from it)."""
        cfg = self.cfg
        start = self.arm.read_state().ee_pose[:3, 3].copy()
        for _ in range(int(round(RETREAT_TIMEOUT_S / cfg.physics_dt))):
            st, w, out, fault = self._tick("retreat", a, d, speed=cfg.retreat_speed, checks=checks, use_sensor=use_sensor)
            if fault is not None:
                self._stop(fault, step)
            if float((start - st.ee_pose[:3, 3]) @ d) >= max(cfg.retreat_distance, cfg.hover_height):
                break

    # ------------------------------------------------------------------ phases
    def _hover_pose(self, a: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(4, 4) TCP pose ``hover_height`` back from ``a`` along the tool axis ``d``."""
        from tergodic_cli.robot.reach import tool_rotation

        return pose_matrix(tool_rotation(d, self._x_down), a - self.cfg.hover_height * d)

    def _move_to_hover(self) -> None:
        from tergodic_cli.robot.reach import posture as reach_posture

        cfg = self.cfg
        a, d = self._agent_line()
        q0 = self.arm.read_state().q
        # >>> reach: an unreachable start -> the nearest reachable target point (the first step moves the agent there)
        if not self._reachable_at(a):
            ok = np.flatnonzero(self.reachable & (np.asarray(getattr(self.explorer, "p", self.reachable), float) > 0))
            j = ok[np.argmin(np.linalg.norm(self.points_base[ok] - a, axis=1))]
            self.on_event(self._step(), f"robot: the tool cannot follow the normal at the start {_fmt(a)} m; starting at "
                                        f"the nearest reachable target point {_fmt(self.points_base[j])} m")
            a = self.points_base[j]
            d = -self._surface_normal(a)
        # <<< reach
        T_hover = self._hover_pose(a, d)
        if not self.guard.inside(T_hover[:3, 3]) or not self.guard.inside(a):
            self._unreachable(f"the start point {_fmt(a)} m or its hover pose is outside the workspace box",
                              "move the object with --object-pose, or choose another start")
        q_h, pe, oe = reach_posture(self.arm._chain, T_hover, np.array(cfg.picture_q), self.arm.q_min, self.arm.q_max)  # reach
        if pe > 1e-3 or oe > 1e-2:
            self._unreachable(f"the robot cannot reach the hover pose above the agent at {_fmt(a)} m "
                              f"(inverse kinematics off by {pe * 1e3:.1f} mm, {math.degrees(oe):.1f} deg)",
                              "move the object closer with --object-pose, or choose another start")
        self._start_line = (a, d)
        self.q_hover = q_h
        self._x_ref = T_hover[:3, 0].copy()
        self.ctrl = LineForceController(cfg.gains, cfg.physics_dt, q_rest=q_h, x_ref=self._x_ref)
        step = self._step()
        self.sm.go(S.HOVER, self.scene.t, step, f"moving to the hover pose {cfg.hover_height * 1e3:.0f} mm above the start {_fmt(a)} m")
        # Come down from above the object: a joint-space path straight to a hover pose low in a
        # bowl can sweep the sponge through the rim.
        self._move_joints(self._above(T_hover, q_h), step)
        self._move_joints(q_h, step)
        # Tare in free space, at rest: the tool's weight at this orientation becomes the zero.
        self.sensor.tare()
        st = self.arm.read_state()
        self.contact.tare_at(st.ee_pose[:3, :3])
        err = float(np.linalg.norm(st.ee_pose[:3, 3] - T_hover[:3, 3]))
        self.on_event(step, f"robot: at hover ({err * 1e3:.1f} mm from the planned pose); F/T sensor tared")

    def _unreachable(self, problem: str, fix: str) -> None:
        """Before the run: bad input (TergodicError). Mid-run (a later cycle of the closed loop):
        a fault, the arm holds where it is and the run ends with its log and summary."""
        if self.sm.history:
            self._stop(Fault("reach", "hold", f"{problem}; holding position", self.scene.t), self._step())
        raise TergodicError(problem, fix)

    def _above(self, T: np.ndarray, q_near: np.ndarray) -> np.ndarray:
        """Joints that put the TCP at ``T``'s orientation and x, y, lifted to ``CLEARANCE`` above the
        object's top (or ``q_near`` when ``T`` is that high already or the lift is out of reach)."""
        z_top = float(self._mesh_top) + CLEARANCE
        if T[2, 3] >= z_top - 1e-3:
            return q_near
        T_up = T.copy()
        T_up[2, 3] = z_top
        q_up, pe, oe = self.model.ik(T_up, q_near, q_rest=np.asarray(q_near, dtype=float))
        return q_up if pe < 1e-3 and oe < 1e-2 and self.guard.inside(T_up[:3, 3]) else q_near

    def _move_joints(self, q_target: np.ndarray, step: int) -> None:
        """Joint-impedance min-jerk move from the present joints to ``q_target`` (7,), then settle."""
        cfg = self.cfg
        q0 = self.arm.read_state().q.copy()
        # Min-jerk peaks at 1.875 × the mean speed: keep the joints under move_speed and the TCP
        # under half the guard's speed limit.
        dist = float(np.max(np.abs(q_target - q0)))
        path = np.array([self.model.fk(q0 + s * (q_target - q0))[:3, 3] for s in np.linspace(0, 1, 21)])
        length = float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)))
        duration = max(1.0, 1.875 * dist / cfg.move_speed, 1.875 * length / (0.5 * cfg.safety.tcp_speed_max))
        n = int(round(duration / cfg.physics_dt))
        path = [min_jerk(q0, q_target, duration, (i + 1) * cfg.physics_dt)
                for i in range(n + int(round(SETTLE_S / cfg.physics_dt)))]
        QD, DQD = np.array([a for a, _ in path]), np.array([b for _, b in path])
        if self.fast_loop and isinstance(self.arm, PyBulletArm):
            fault = self._joint_fast(QD, DQD)
            if fault is not None:
                self._stop(fault, step)
            return
        for qd, dqd in zip(QD, DQD):
            st, w, out, fault = self._tick("joint", q_d=qd, dq_d=dqd)
            if fault is not None:
                self._stop(fault, step)

    def _approach(self) -> None:
        cfg = self.cfg
        a, d = self._start_line
        step = self._step()
        v_touch = guarded_approach_speed(0.0, cfg.approach_speed, cfg.contact_speed, self.F_d)
        self.sm.go(S.APPROACH, self.scene.t, step, f"approaching along the normal at {cfg.approach_speed * 1e3:.0f} mm/s, "
                                                   f"touching at {v_touch * 1e3:.1f} mm/s")
        self.ctrl.reset()
        self.ts[_TS_PEAK_PHASE] = 0.0  # the first touch's peak (every tick)
        timeout = (cfg.hover_height + 0.03) / cfg.approach_speed + 0.03 / v_touch + 0.5
        n = int(round(timeout / cfg.physics_dt))
        contact_at = None
        settled = 0
        t0 = self.scene.t
        f_ref = self.F_d
        speed = cfg.approach_speed
        push, s_set = 0.0, None
        # Pressing before contact is registered only needs to cross the threshold: the push is capped.
        push_cap = 2.0 * self.threshold
        for i in range(n + int(round(PRESS_TIMEOUT_S / cfg.physics_dt))):
            mode = "approach" if contact_at is None else "track"
            if contact_at is not None:  # ramp the set-point from the contact force to F_d: no overshoot
                f_ref = min(self.F_d, f0 + (self.F_d - f0) * (self.scene.t - contact_at) / PRESS_RAMP_S)
            st, w, out, fault = self._tick(mode, a, d, speed=speed, force=f_ref)
            # Guarded: slow down near the expected surface (the cloud gives the gap), touch at
            # v_touch (the contact's damping and the arm's momentum at 20 mm/s gave 10-28 N impacts on
            # the bowl's trimesh). A position servo along the axis keeps the speed; while the tool is
            # blocked its set-point runs ahead and the push grows (APPROACH_K × v) until the force
            # registers, capped at push_cap.
            p_along = float(st.ee_pose[:3, 3] @ d)
            gap = float(a @ d) - p_along
            v_cmd = guarded_approach_speed(gap, cfg.approach_speed, cfg.contact_speed, self.F_d)
            if contact_at is None:
                s_set = p_along if s_set is None else min(s_set + v_cmd * cfg.physics_dt, p_along + push_cap / APPROACH_K)
                push = APPROACH_K * (s_set - p_along) + APPROACH_D * (v_cmd - out.v_ee[2])
            speed = v_cmd + push / self.ctrl.D[2]
            if fault is not None:
                self._stop(fault, step)
            f = out.force_filtered
            if contact_at is None:
                if f >= self.threshold:
                    contact_at = self.scene.t
                    f0 = f
                    self.ctrl.start_tracking(f0, self.ctrl.D[2] * speed)
                    self.on_event(step, f"robot: contact at {f:.2f} N after {contact_at - t0:.2f} s; pressing to {self.F_d:g} N")
                elif i >= n:
                    self._stop(Fault("approach", "hold", f"no contact within {(cfg.hover_height + 0.03) * 1e3:.0f} mm below the "
                                     "hover pose; check --object-pose; holding position", self.scene.t), step)
            elif f_ref >= self.F_d:
                settled = settled + 1 if abs(f - self.F_d) <= 0.1 * self.F_d else 0
                if settled >= 50:
                    break
        else:
            self.on_event(step, f"robot: the force did not settle within {PRESS_TIMEOUT_S:.0f} s (now {out.force_filtered:.2f} N); exploring anyway")
        self.approach_peak = max(self.approach_peak or 0.0, float(self.ts[_TS_PEAK_PHASE]))
        self.sm.go(S.EXPLORE, self.scene.t, step, f"in contact at {out.force_filtered:.2f} N; exploring")

    def _explore(self, steps: int, on_step, defer_last: bool = False) -> None:
        """``steps`` explorer steps in contact. With ``defer_last`` the last step's sample is recorded
        but not handed to ``on_step`` yet: :meth:`emit_deferred` does it (with the re-capture's figures)."""
        from tergodic_cli.progress import track

        cfg = self.cfg
        ex = self.explorer
        n_sub = cfg.substeps
        a_cur, d_cur = self._start_line
        st = self.arm.read_state()
        w = self.contact(self.sensor.read().wrench, st.ee_pose[:3, :3])
        self.guard.feed_target(self.scene.t)
        step = int(getattr(ex, "step_index", 0))
        ts = self.ts
        ts[_TS_COUNT], ts[_TS_RUN] = 1.0, 0.0  # explore ticks count towards steady contact
        for k in track(range(steps), total=steps, description="explore (pybullet)"):
            meas = self._measure(st)
            ts[_TS_N:_TS_N + 3] = meas["normal"]  # the surface normal at the contact, for this interval's ticks
            deposit = self._to_obj(meas["contact_point"])[None, :] if meas["in_contact"] else np.zeros((0, 3))
            before = int(getattr(ex, "step_index", step))
            try:
                ex.step(deposit_at=deposit, agent_at=self._to_obj(st.ee_pose[:3, 3])[None, :])
            except TergodicError as exc:
                fault = Fault("explorer", "hold", f"the explorer failed ({exc}); holding position", self.scene.t)
                self._fault_sample(fault, before + 1, st, w, a_cur, d_cur, on_step, record=True)
            step = int(getattr(ex, "step_index", before + 1))
            a_next, d_next = a_cur, d_cur
            if step == before + 1:
                a_new = self._to_base(np.asarray(ex.positions[0], dtype=float))
                fault = self.guard.check_target(self.scene.t, a_new)
                if fault is not None:
                    self._fault_sample(fault, step, st, w, a_cur, d_cur, on_step, record=True)
                a_new, d_new = self._agent_line()
                # >>> reach: where the tool cannot follow the normal the line stays on the last reachable one
                if self._reachable_at(a_new):
                    a_next, d_next = a_new, d_new
                elif not self._told_unreachable:
                    self._told_unreachable = True
                    self.on_event(step, f"robot: the agent entered the unreachable part at {_fmt(a_new)} m; the tool "
                                        "waits on the last reachable point")
                off = math.degrees(math.acos(min(1.0, float(-d_next @ self._surface_normal(a_next)))))
                if off > CONTACT_TILT_MAX_DEG:  # never press at a large angle: lift before tilting
                    self._fault_sample(Fault("reach", "retreat", f"the commanded tool axis is {off:.0f} deg off the "
                                             f"surface normal (limit {CONTACT_TILT_MAX_DEG:.0f}); lifting the tool off "
                                             "the surface", self.scene.t), step, st, w, a_cur, d_cur, on_step, record=True)
                # <<< reach
                self.guard.feed_target(self.scene.t)
                self._update_spin_ref(d_next)
            self._shadow.deposit()
            # The line target glides from the previous agent line to the new one over the interval.
            s = (np.arange(1, n_sub + 1) / n_sub)[:, None]
            A = a_cur + s * (a_next - a_cur)
            Dd = d_cur + s * (d_next - d_cur)
            Dd /= np.linalg.norm(Dd, axis=1, keepdims=True)
            v_ref = ((a_next - a_cur) / cfg.explore_dt).tolist() if cfg.velocity_feedforward else None
            for st, w, a, d, fault in self._track(A, Dd, v_ref):
                if fault is not None:
                    # A stalled explorer produced no new step: its last sample is out already.
                    fresh = fault.kind != "explorer" and step > (self.samples[-1]["step"] if self.samples else 0)
                    self._fault_sample(fault, step, st, w, np.array(a), np.array(d), on_step, record=fresh)
            a_cur, d_cur = a_next, d_next
            sample = self._sample(step, st, w, a_cur, d_cur)
            # >>> reach: never press at a large angle to the surface
            press = self._measure(st)["press_angle_deg"]
            if sample["in_contact"] and press > CONTACT_TILT_MAX_DEG:
                self._fault_sample(Fault("reach", "retreat", f"the tool presses {press:.0f} deg off the surface "
                                         f"normal in contact (limit {CONTACT_TILT_MAX_DEG:.0f}); lifting the tool off the "
                                         "surface", self.scene.t), step, st, w, a_cur, d_cur, on_step, record=True)
            # <<< reach
            self.samples.append(sample)
            if defer_last and k == steps - 1:
                self._deferred = (on_step, step)
            else:
                self._emit(on_step, step)
        ts[_TS_COUNT] = 0.0
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

    def _fault_sample(self, fault: Fault, step: int, st, w, a, d, on_step, record: bool) -> None:
        """Record and emit the sample of the step a fault interrupted, then make the robot safe."""
        fault = resolve_stop(fault, self.sm.state)  # the sample names what is done about it
        self.emit_deferred()
        if record:
            self.samples.append(self._sample(step, st, w, a, d, stop_reason=fault.reason))
            self._emit(on_step, step)
        self._stop(fault, step)

    def _emit(self, on_step, step: int) -> None:
        if on_step is not None:
            t = time.perf_counter()
            on_step(step, self.samples[-1])
            self._cb_s += time.perf_counter() - t

    # ------------------------------------------------------------------ measurements
    def _measure(self, st) -> dict:
        """Contact point (force-weighted mean of the sponge/object contacts), contact force, surface normal."""
        key = (id(st), self.scene.steps)
        if self._meas_cache is not None and self._meas_cache[0] == key:  # the sample's, reused at the next step
            return self._meas_cache[1]
        meas = self._measure_now(st)
        self._meas_cache = (key, meas)
        return meas

    def _measure_now(self, st) -> dict:
        contacts = self.scene.sponge_contacts()
        fsum = float(sum(c[2] for c in contacts))
        tcp = st.ee_pose[:3, 3]
        cp = sum(c[2] * c[0] for c in contacts) / fsum if fsum > 0 else None
        x = cp if cp is not None else tcp
        # reach: the angle the sponge presses at, from the contacts' own normals (a ball's contact normal
        # is the surface's there, edges included; the cloud's normal is not at an edge)
        nc = sum(c[2] * c[1] for c in contacts) if fsum > 0 else np.zeros(3)
        nn = float(np.linalg.norm(nc))
        press = math.degrees(math.acos(min(1.0, abs(float(nc @ st.ee_pose[:3, 2])) / nn))) if nn > 0 else 0.0
        return {"contact_point": cp, "force_contact": fsum, "in_contact": bool(cp is not None and fsum >= self.threshold),
                "normal": self._surface_normal(x), "at": x, "press_angle_deg": press}

    def _sample(self, step: int, st, w: np.ndarray, a: np.ndarray, d: np.ndarray, stop_reason: str | None = None) -> dict:
        """The robot_sample_dict of CONTRACTS.md (plus extras) at the end of an explorer interval."""
        meas = self._measure(st)
        T = st.ee_pose
        R = T[:3, :3]
        n = meas["normal"]
        z = R[:, 2]
        tilt = math.degrees(math.acos(max(-1.0, min(1.0, float(-z @ n)))))
        track_mm = 1e3 * point_line_distance(meas["at"], a, d)
        f_base = R @ w[:3]
        metrics = self.explorer.metrics() if hasattr(self.explorer, "metrics") else {}
        shadow = self._shadow.metrics()
        obj_q = matrix_to_quat(self.T_obj[:3, :3])
        sample = {
            "t_sim": float(st.t),
            "t_wall": time.perf_counter() - self._t0 - self._cb_s - self.paused_s,
            "state": self.sm.state,
            "ee_pose": np.concatenate([T[:3, 3], matrix_to_quat(R)]),
            "q": st.q.copy(),
            "dq": st.dq.copy(),
            "tau": np.asarray(self.arm.last_tau, dtype=float).copy(),
            "joint_names": list(self.arm.joint_names),
            "link_poses": self.scene.link_poses(),
            "object_pose": np.concatenate([self.T_obj[:3, 3], obj_q]),
            "wrench_measured": np.asarray(w, dtype=float).copy(),
            "wrench_desired": np.array([0.0, 0.0, self.F_d, 0.0, 0.0, 0.0]),
            "force_normal": float(-(f_base @ n)) if meas["in_contact"] or abs(w[2]) > 0 else 0.0,
            "force_contact": meas["force_contact"],
            "force_filtered": float(self.ctrl.f_filt),
            "in_contact": meas["in_contact"],
            "contact_point": meas["contact_point"],
            "tilt_deg": tilt,
            "track_mm": track_mm,
            "agent_line_point": np.asarray(a, dtype=float).copy(),
            "agent_line_dir": np.asarray(d, dtype=float).copy(),
            "contact_ergodicity": metrics.get("ergodicity"),
            "contact_touched_fraction": metrics.get("touched_fraction"),
            "agent_ergodicity": shadow.get("ergodicity"),
            "agent_touched_fraction": shadow.get("touched_fraction"),
            "step": int(step),
            **tick_figures(self.ts),
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
        self._cb_s = 0.0
        self.paused_s = 0.0  # wall seconds the robot waited for others (the closed loop's re-captures)
        self.on_event(0, f"robot {S.PICTURE}: at the picture pose (cloud of {len(self.points)} points captured; "
                         f"collision mesh {len(self.mesh.triangles)} triangles from the {self.mesh_source})")

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

    def to_picture(self, reason: str) -> None:
        """explore -> retreat along the tool axis -> joint move to the picture pose, state ``picture``."""
        step = self._step()
        self.sm.go(S.RETREAT, self.scene.t, step, reason)
        a, d = self._last_line
        self._retreat(a, d, step)
        self.sm.go(S.PICTURE, self.scene.t, step, "retreated; moving to the picture pose")
        # Straight up to clear the object first: the joint-space path to the picture pose from low
        # in a bowl can sweep the sponge through the rim.
        st = self.arm.read_state()
        self._move_joints(self._above(st.ee_pose, st.q), step)
        self._move_joints(np.array(self.cfg.picture_q, dtype=float), step)

    def finish(self, reason: str) -> None:
        """End normally: retreat if in contact, then ``done``, holding still."""
        step = self._step()
        if self.sm.state == S.EXPLORE:
            self.sm.go(S.RETREAT, self.scene.t, step, reason)
            a, d = self._last_line
            self._retreat(a, d, step)
            reason = "retreated; done"
        self.sm.go(S.DONE, self.scene.t, step, reason)
        self._hold(SETTLE_S)

    def _interrupt(self) -> None:
        """Ctrl-C: retreat if the tool may be in contact, else hold; end ``stopped`` with a one-line reason."""
        self.interrupted = True
        reason = "interrupted by the user (Ctrl-C)"
        state = self.sm.state
        if self.sm.finished or state == S.HOLD:  # already stopping or stopped
            self.stop_reason = self.stop_reason or reason
            return
        contact = state in (S.APPROACH, S.EXPLORE)
        fault = Fault("interrupt", "retreat" if contact else "hold",
                      f"{reason}; {'retreating' if contact else 'holding position'}", self.scene.t)
        try:
            self._stop(fault, self._step())
        except _Stop:
            pass

    def result(self) -> dict:
        """The summary extras of the run so far (call once, at the end)."""
        self.emit_deferred()
        wall = time.perf_counter() - self._t0 - self._cb_s - self.paused_s
        # (the callback's and the pauses' wall time: a fair proxy for their CPU)
        cpu = time.process_time() - self._cpu0 - self._cb_s - self.paused_s
        out = summarize_robot(self.samples, stop_reason=self.stop_reason, ticks=tick_figures(self.ts))
        out.update({
            "force_peak_approach_N": self.approach_peak,
            "final_state": self.sm.state,
            "interrupted": bool(self.interrupted),
            "sim_seconds": self.scene.t,
            "wall_seconds": wall,
            "realtime_factor_run": self.scene.t / wall if wall > 0 else None,
            "cpu_seconds": cpu,
            "setup_seconds": self.setup_s,
            "transitions": [{"t": round(tr.t, 4), "step": tr.step, "from": tr.source, "to": tr.target, "reason": tr.reason}
                            for tr in self.sm.history],
            "object_pose": [float(x) for x in np.concatenate([self.T_obj[:3, 3], matrix_to_quat(self.T_obj[:3, :3])])],
            "mesh_triangles": int(len(self.mesh.triangles)),
            "mesh_source": self.mesh_source,
            "control_hz": 1.0 / self.cfg.physics_dt,
            "explorer_hz": 1.0 / self.cfg.explore_dt,
            "robot_config": self.cfg.to_dict(),
        })
        return out

    def _step(self) -> int:
        return int(getattr(self.explorer, "step_index", 0))

    def close(self) -> None:
        try:
            if getattr(self, "arm", None) is not None:
                self.arm.disconnect()
        finally:
            self.scene.close()

    def __enter__(self) -> "RobotRun":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def explore_with_robot(capture, explorer, robot_cfg: RobotConfig, steps: int,
                       on_step: Callable[[int, dict], None] | None = None,
                       on_event: Callable[[int, str], None] | None = None) -> dict:
    """Run ``steps`` explorer steps on the simulated robot (see the module docstring).

    Parameters
    ----------
    capture : the :class:`~tergodic_cli.capture.Capture` (its cloud becomes the collision mesh).
    explorer : an :class:`~tergodic_cli.explore.Explorer` built with ``robot_explore_config``.
    robot_cfg : :class:`RobotConfig`.
    steps : explorer steps in contact.
    on_step : called as on_step(step, robot_sample_dict) after each explorer step.
    on_event : called as on_event(step, text) at every state transition and warning.

    Returns
    -------
    The robot summary extras (see :func:`~tergodic_cli.robot.summary.summarize_robot`) plus
    final_state, stop_reason, transitions, timings and the robot config.
    """
    with RobotRun(capture, explorer, robot_cfg, on_event=on_event) as run:
        return run.run(steps, on_step)


class _AgentCoverage:
    """Coverage the virtual agent's own path would have left (the kinematic agent's), for comparison."""

    def __init__(self, explorer):
        need = ("points", "mass", "p", "kdtree", "r_a", "eps", "positions", "normals")
        self.ok = all(hasattr(explorer, k) for k in need)
        self.ex = explorer
        if self.ok:
            self.cov = np.zeros(len(explorer.points))

    def deposit(self) -> None:
        if not self.ok:
            return
        ex = self.ex
        for x, n in zip(ex.positions, ex.normals):
            idx = np.asarray(ex.kdtree.query_ball_point(x, ex.r_a), dtype=np.intp)
            if len(idx):
                dd = ex.points[idx] - x
                off = dd @ n
                r2 = np.maximum(np.einsum("ij,ij->i", dd, dd) - off * off, 0.0)
                self.cov[idx] += np.exp(-(ex.eps * ex.eps) * r2)

    def metrics(self) -> dict:
        if not self.ok:
            return {}
        from tergodic_cli.explore.metrics import ergodicity, touched_fraction

        return {"ergodicity": ergodicity(self.ex.p, self.cov, self.ex.mass), "touched_fraction": touched_fraction(self.ex.p, self.cov)}


def clamp_tilt(d: np.ndarray, max_deg: float) -> np.ndarray:
    """``d`` rotated towards straight down (-z) until it is within ``max_deg`` of it."""
    down = np.array([0.0, 0.0, -1.0])
    c = float(d @ down)
    lim = math.cos(math.radians(max_deg))
    if c >= lim:
        return d
    side = d - c * down
    n = float(np.linalg.norm(side))
    if n < 1e-12:
        return down.copy()
    return lim * down + math.sin(math.radians(max_deg)) * side / n


def _fmt(x) -> str:
    return "(" + ", ".join(f"{float(v):.3f}" for v in x) + ")"
