"""The simulated arm (``--arm``) with its sponge and wrist F/T sensor behind the contact loop's :class:`Arm`.

The line target becomes joint torques inside the 1 kHz tick: the line-impedance law with the
wrench PID (eq. 47, :class:`~tergodic_cli.robot.controller.LineForceController`), on top of
gravity and Coriolis compensation. Free-space moves are joint-impedance min-jerk moves planned
with inverse kinematics. An explorer interval (200 ticks) runs in one compiled call per tick
(:func:`~tergodic_cli.robot.kernels.pybullet_tick`, the same checks as the loop's), which keeps
the run at tens of times real time.

:func:`explore_with_robot` runs the explorer on it (``tergodic explore --robot pybullet``).
"""

from __future__ import annotations

import math
import time
from typing import Callable

import numpy as np

from tergodic_cli.backends.pybullet.arms import get_arm
from tergodic_cli.backends.pybullet.devices import PyBulletArm, PyBulletWrenchSensor
from tergodic_cli.backends.pybullet.plan import (END_FLOOR, PLAN_SLACK, SPONGE_MARGIN, CollisionWorld, Plan, plan_path,
                                                 retreat_clear)
from tergodic_cli.backends.pybullet.scene import PyBulletScene
from tergodic_cli.errors import TergodicError, require
from tergodic_cli.robot import kernels as Kn
from tergodic_cli.robot.config import RobotConfig, validate_robot_config
from tergodic_cli.robot.controller import JointImpedance, LineForceController, LineTargetLaw, min_jerk
from tergodic_cli.robot.interfaces import ArmState, ContactWrench, LineTarget, Observation
from tergodic_cli.robot.reach import plan_reach, posture, tool_rotations
from tergodic_cli.robot.run import SETTLE_S, ContactRun, object_pose
from tergodic_cli.robot.safety import Fault, fmt_xyz
from tergodic_cli.robot.surface import (SurfaceMesh, check_reachable, check_surface, curved_edge, near_border,
                                         oriented_normals, rebuild_surface, resolve_side, sim_object_mesh, source_mesh,
                                         surface_figures, transform_points)

#: Metres the hand, its fingers and the sponge keep from the object, table and stand, with the tool on the
#: normal, for a point to count as reachable (the tilt's 95th percentile, ~3 deg, moves the hand ~7 mm).
HAND_CLEAR = 0.01
#: Metres a planned set-up move keeps its TCP inside the guard's workspace box (the joint impedance
#: tracks its reference to ~1 mm in free space).
WORKSPACE_MARGIN = 0.01


def arm_gains(gains, spec):
    """The controller gains of a run: ``gains`` as given, or, where the run keeps the default gains, the
    default with the arm's own tuning (its module's ``gains``) on top."""
    from dataclasses import replace

    from tergodic_cli.robot.controller import ControllerGains

    return replace(gains, **spec.gains) if spec.gains and gains == ControllerGains() else gains


def part_label(part: str) -> str:
    """A collision part's name for a message, the robot's prefix dropped: "panda_link3" -> "link 3",
    "panda_hand" -> "hand", "lbr_iiwa_link_3" -> "link 3"."""
    import re

    i = part.find("link")
    part = part[i:] if i > 0 else re.sub(r"^[a-z]+_", "", part)
    return re.sub(r"link_?(\d)", r"link \1", part)


class SimArm:
    """The PyBullet scene's arm, sponge and sensor as one :class:`~tergodic_cli.robot.interfaces.Arm`.

    Parameters
    ----------
    cfg : the RobotConfig (arm, gains, physics_dt, picture_q, sponge, ...). The arm is known through its
        :class:`~tergodic_cli.robot.model.ArmModel` (:attr:`model`: DoF, limits, chain, read from its URDF).
    mesh : the object's collision mesh (vertices (V, 3), triangles (F, 3)) and T_mesh (4, 4), its
        pose in the base frame.
    """

    name = "pybullet"

    def __init__(self, cfg: RobotConfig, mesh, T_mesh: np.ndarray):
        self.cfg = cfg
        self.mesh = mesh
        self.scene = PyBulletScene(cfg.sponge, gui=cfg.gui, dt=cfg.physics_dt, solver_iterations=cfg.solver_iterations,
                                   arm=cfg.arm)
        try:
            self.scene.add_object(mesh.vertices, mesh.triangles, T_mesh)
            self.dev = PyBulletArm(self.scene)
            #: The arm as the robot layer knows it (robot/model.py).
            self.model = model = self.dev.model
            n = model.dof
            #: The picture posture: the run's, else the arm's own.
            self.picture_q = model.home.copy() if cfg.picture_q is None else np.asarray(cfg.picture_q, dtype=float)
            require(len(self.picture_q) == n, f"picture_q needs {n} joint angles for the {model.name}",
                    f"give the {model.name}'s {n} joint angles in rad, or leave picture_q out")
            self.gains = arm_gains(cfg.gains, self.scene.spec)
            self.dev.dynamics_every = int(cfg.dynamics_every)
            self.dev.connect()
            self.scene.set_arm(self.picture_q)
            self.sensor = PyBulletWrenchSensor(self.scene, self.dev)
            if not self.sensor.read().valid:  # PyBullet reads 0 until its first step: hold still for one
                self.dev.command(np.zeros(n))
                self.scene.step()
            # Gravity and inertia of the tool removed: the wrench is the contact's (issue 15, item 3).
            self.contact_wrench = ContactWrench(self.scene.tool_load(), self.sensor.frame_in_ee,
                                                inertial=cfg.inertial_compensation)
            st = self.dev.read_state()
            #: The set-up moves' collision check: the arm and every other body of the scene (plan.py).
            self.world = CollisionWorld(self.scene)
        except BaseException:
            self.scene.close()
            raise
        #: The set-up moves planned so far: [(what, Plan)] (planner, clearance, seconds; the summary's figures).
        self.plans: list[tuple[str, Plan]] = []
        self.start_blocked = False
        self.plan_seconds = 0.0  # wall seconds spent planning, failed plans included
        #: The retreats checked so far: [(m allowed, m wanted, smallest link slack m on the way)].
        self.retreats: list[tuple[float, float, float]] = []
        self._planned: tuple[bytes, Plan] | None = None
        self.joint_names = list(self.dev.joint_names)
        self.dt = float(cfg.physics_dt)
        self.q_min, self.q_max, self.dq_max = self.dev.q_min, self.dev.q_max, self.dev.dq_max
        self.t_origin = 0.0
        self.joint = JointImpedance(*self.scene.spec.joint_gains)
        self.ctrl = LineForceController(self.gains, cfg.physics_dt, q_rest=self.picture_q, x_ref=st.ee_pose[:3, 0],
                                        q_min=self.q_min, q_max=self.q_max)
        #: The compiled 1 kHz loops (:meth:`follow`); False: every tick through get_observation / send_action.
        self.fast = True
        #: Called as contact_hook(contacts, dt) every ``hook_every`` physics steps with the sponge's
        #: contacts [(point on the object (3,) base frame, normal (3,), normal force N)] and the
        #: simulated seconds they stand for (the closed loop's cleaning model). None: no calls.
        self.contact_hook: Callable[[list, float], None] | None = None
        self.hook_every = 20
        self._hook_age = 0
        self.wall0 = time.perf_counter()  # realtime pacing: wall clock at simulated time 0 (the run resets it)
        self._obs = self._meas = None
        #: How a line target becomes the controller's mode each tick (press, approach servo, retreat).
        self.law = LineTargetLaw()
        self._ik: dict = {}
        self.guard = self.ts = None
        #: The first arm contact not yet handed over (:meth:`fault`); ``collision_faults`` False only counts them.
        self.hit: Fault | None = None
        self.collision_faults = True
        self._inject: tuple | None = None
        #: () -> the explorer steps done (the run sets it), for the first contact's record.
        self.step_of: Callable[[], int] = lambda: -1
        #: F_d and the contact threshold, N: given by the run (:meth:`bind`), from its config's one home.
        self.F_d = self.threshold = None

    # ------------------------------------------------------------------ the Arm interface
    @property
    def t(self) -> float:
        return self.scene.t

    @property
    def force(self) -> float:
        return self.ctrl.f_filt

    @property
    def tau(self) -> list:
        return self.dev.last_tau

    @property
    def spin_ref(self) -> np.ndarray:
        return self.ctrl.x_ref

    @spin_ref.setter
    def spin_ref(self, x) -> None:
        self.ctrl.x_ref = x

    def bind(self, guard, tick_stats, force_desired: float, threshold: float) -> None:
        self.guard, self.ts, self.F_d, self.threshold = guard, tick_stats, float(force_desired), float(threshold)
        self.scene.collision.sponge_sink = guard.force_limit / self.cfg.sponge.stiffness

    def get_observation(self, sensor: bool = True) -> Observation:
        st = self.dev.read_state()
        if sensor:
            rd = self.sensor.read()
            w = self.contact_wrench(rd.wrench, st.ee_pose, st)
            if rd.valid and self.ts is not None:
                Kn.tick_stats(st.ee_pose, w, self.ts)
        else:
            rd, w = None, np.zeros(6)
        self._obs = Observation(st, rd, w)
        return self._obs

    def send_action(self, target: LineTarget) -> None:
        """The torque law for one tick towards ``target``, then one physics step."""
        st, w = self._obs.state, self._obs.wrench
        if target.mode != "press":  # the approach and retreat push with the run's F_d in their mode
            target = target._replace(force=self.F_d)
        out = self.law.step(self.ctrl, st, w, target, self.threshold)
        self.dev.command(out.tau)
        self._physics()

    def _physics(self) -> None:
        self.scene.step()
        if self._inject is not None and self.scene.t >= self._inject[0]:
            self.hit, self._inject = self._inject[1], None
        col = self.scene.collision
        col.countdown -= 1
        if col.countdown <= 0:  # paced by the fastest part (collision.py): a contact is found within a few mm
            self._collide()
        if self.contact_hook is not None:
            self._run_hook()
        if self.cfg.realtime:
            lag = self.scene.t - (time.perf_counter() - self.wall0)
            if lag > 0:
                time.sleep(lag)

    def _collide(self) -> None:
        """Check every arm part against the object, table and stand; the first contact becomes :attr:`hit`."""
        found = self.scene.collision.check(self.step_of())
        if found and self.hit is None and self.collision_faults:
            part, body, depth, x = max(found, key=lambda c: c[2])
            what = "sponge" if part == "sponge" else f"arm's {part_label(part)}"
            self.hit = Fault("collision", "retreat", f"the {what} touches the {body} ({1e3 * depth:.0f} mm deep at "
                             f"{fmt_xyz(x)} m); retreating", self.scene.t, {"part": part, "body": body})

    def inject(self, fault, after: float = 0.0) -> None:
        """Fault injection (tests, checks): ``fault`` (a :class:`~tergodic_cli.robot.safety.Fault`) is
        reported by the first control period ``after`` simulated seconds from now, whatever the state:
        a set-up move, an approach, exploring, a retreat or a move-over."""
        self._inject = (self.scene.t + float(after), fault)

    def touching(self) -> bool:
        """Whether anything touches now: the sponge on the object, or any arm part (a check at once)."""
        return bool(self.scene.sponge_contacts()) or bool(self.scene.collision.check(self.step_of()))

    def _run_hook(self) -> None:
        """Every ``hook_every`` physics steps: hand the sponge's contacts to ``contact_hook``."""
        self._hook_age += 1
        if self._hook_age >= self.hook_every:
            self._hook_age = 0
            self.contact_hook(self.scene.sponge_contacts(), self.hook_every * self.cfg.physics_dt)

    def reach(self, T: np.ndarray) -> str | None:
        q_h, pe, oe = self._ik_hover(T)
        if not (pe <= 1e-3 and oe <= 1e-2):
            return f"inverse kinematics off by {pe * 1e3:.1f} mm, {math.degrees(oe):.1f} deg"
        if not self._clear(q_h):
            d, link = self.world.clearance(q_h)
            return f"at the hover pose its {link} is {d * 1e3:.0f} mm from an obstacle"
        return None

    def posture_blocked(self) -> str | None:
        """Why no set-up move can start from the present posture (a link closer to a body than
        plan.END_FLOOR allows: plan.plan_path would refuse every move), or None."""
        self.world.sync()
        q = self.dev.read_state().q
        if self.world.slack(q, PLAN_SLACK) >= END_FLOOR - SPONGE_MARGIN:
            return None
        d, link = self.world.clearance(q)
        return f"its {link} is {d * 1e3:.0f} mm from it" if d >= 0 else f"its {link} is {-d * 1e3:.0f} mm inside it"

    def _clear(self, q: np.ndarray) -> bool:
        """The posture ``q`` (n,) keeps the set-up moves' margins (plan.py) from every non-arm body."""
        self.world.sync()
        return self.world.slack(q) >= 0.0

    def _ik_hover(self, T: np.ndarray):
        """The hover posture (reach.posture: several seeds, no twisted elbow, clear of the object), the
        line controller's rest posture."""
        key = T.tobytes()
        if key not in self._ik:
            self.world.sync()
            self._ik[key] = posture(self.dev._chain, T, self.picture_q, self.q_min, self.q_max,
                                    valid=lambda q: self.world.slack(q) >= 0.0)
        return self._ik[key]

    def set_object_pose(self, T_mesh: np.ndarray) -> None:
        """Move the object (its mesh frame to ``T_mesh`` (4, 4), base frame) before the run."""
        self.scene.move_object(T_mesh)
        self._ik.clear()

    def plan(self, T: np.ndarray) -> str | None:
        """Plan the set-up move from the present joints to the hover posture of ``T`` (4, 4) (plan.py: a
        straight joint-space line when it is clear, else OMPL's RRTConnect; every non-arm body of the scene
        avoided by the margins); :meth:`move_to` follows it. Returns None, or why no move was found."""
        q_h = self._ik_hover(T)[0]
        plan, err = self._plan_to(q_h)
        #: Whether the last plan failed at its start: the present posture is too close to a body.
        self.start_blocked = plan is None and err.startswith("the start")
        if plan is None:
            return err
        self._planned = (T.tobytes(), plan)
        return None

    def _plan_to(self, q_goal: np.ndarray) -> tuple[Plan | None, str | None]:
        t0 = time.perf_counter()
        self.world.sync()
        q0 = self.dev.read_state().q.copy()
        g = self.guard
        lo = np.asarray(g.cfg.workspace_min, float) + WORKSPACE_MARGIN
        hi = np.asarray(g.cfg.workspace_max, float) - WORKSPACE_MARGIN

        def inside(q):  # the guard faults a tool that leaves its box: a set-up move keeps inside it
            x = self.model.fk(q)[:3, 3]
            return bool(np.all(x >= lo) and np.all(x <= hi))

        out = plan_path(self.world, q0, q_goal, g.q_lo, g.q_hi, inside=inside)
        self.plan_seconds += time.perf_counter() - t0
        return out

    def move_to(self, T: np.ndarray, check):
        """The planned move (:meth:`plan`) to the hover posture of ``T``; the posture spring rests there."""
        q_h = self._ik_hover(T)[0]
        if self._planned is not None and self._planned[0] == T.tobytes():
            plan, err = self._planned[1], None
        else:
            plan, err = self._plan_to(q_h)
        self._planned = None
        self._ik.clear()
        if plan is None:
            return Fault("plan", "hold", f"no collision-free move to the hover pose ({err}); holding position", self.t)
        self.plans.append(("hover", plan))
        self.ctrl = LineForceController(self.gains, self.cfg.physics_dt, q_rest=q_h, x_ref=self.ctrl.x_ref.copy(),
                                        q_min=self.q_min, q_max=self.q_max)
        self.law.mode = None
        return self._move_path(plan.path, check)

    def to_picture(self, check):
        """The planned move (plan.py) to the picture pose."""
        plan, err = self._plan_to(self.picture_q)
        if plan is None:
            return Fault("plan", "hold", f"no collision-free move to the picture pose ({err}); holding position", self.t)
        self.plans.append(("picture", plan))
        return self._move_path(plan.path, check)

    def retreat_limit(self, d: np.ndarray, distance: float) -> float:
        """How far (m, up to ``distance``) the tool may back off along the line direction ``d`` (3,) from here,
        checked before it starts (plan.retreat_clear: no arm link comes closer to a body than it is now)."""
        self.world.sync()
        ok, worst = retreat_clear(self.world, self.dev._chain, self.dev.read_state().q, np.asarray(d, float), distance)
        self.retreats.append((ok, distance, worst))
        return ok

    def _move_path(self, path: np.ndarray, check):
        """Joint-impedance min-jerk moves along the planned path's straight joint-space segments (m, n),
        each at rest at its ends (the reference never leaves the checked segments), then settle."""
        cfg = self.cfg
        QD, DQD = [], []
        for q0, q1 in zip(path[:-1], path[1:]):
            # Min-jerk peaks at 1.875 × the mean speed: keep the joints under move_speed and the TCP
            # under half the guard's speed limit.
            dist = float(np.max(np.abs(q1 - q0)))
            tcp = np.array([self.model.fk(q0 + s * (q1 - q0))[:3, 3] for s in np.linspace(0, 1, 21)])
            length = float(np.sum(np.linalg.norm(np.diff(tcp, axis=0), axis=1)))
            duration = max(0.5 if len(path) > 2 else 1.0, 1.875 * dist / cfg.move_speed,
                           1.875 * length / (0.5 * self.guard.cfg.tcp_speed_max))
            n = int(round(duration / self.dt))
            for i in range(n):
                qd, dqd = min_jerk(q0, q1, duration, (i + 1) * self.dt)
                QD.append(qd)
                DQD.append(dqd)
        QD += [np.asarray(path[-1], float)] * int(round(SETTLE_S / self.dt))
        DQD += [np.zeros(self.model.dof)] * int(round(SETTLE_S / self.dt))
        QD, DQD = np.array(QD), np.array(DQD)
        if self.fast:
            return self._joint_fast(QD, DQD)
        for qd, dqd in zip(QD, DQD):
            obs = self.get_observation()
            fault = check(obs)
            if fault is not None:
                return fault
            self.dev.command(self.joint(obs.state.q, obs.state.dq, qd, dqd))
            self._physics()
        return None

    def hold(self, seconds: float) -> None:
        q = self.dev.read_state().q.copy()
        for _ in range(int(round(seconds / self.dt))):
            st = self.dev.read_state()
            self.dev.command(self.joint(st.q, st.dq, q))
            self._physics()

    def tare(self) -> None:
        self.sensor.tare()
        self.contact_wrench.tare_at(self.dev.read_state().ee_pose[:3, :3])

    def contact(self, obs) -> tuple[np.ndarray | None, float, float]:
        """Force-weighted mean of the sponge/object contact points (PyBullet's), their total normal force,
        and the angle (deg) the sponge presses at from the contacts' own normals (a ball's contact normal
        is the surface's there, edges included; the cloud's normal is not at an edge)."""
        key = (id(obs), self.scene.steps)
        if self._meas is None or self._meas[0] != key:  # the sample's, reused at the next step
            contacts = self.scene.sponge_contacts()
            fsum = float(sum(c[2] for c in contacts))
            cp = sum(c[2] * c[0] for c in contacts) / fsum if fsum > 0 else None
            nc = sum(c[2] * c[1] for c in contacts) if fsum > 0 else np.zeros(3)
            nn = float(np.linalg.norm(nc))
            z = obs.state.ee_pose[:3, 2]
            press = math.degrees(math.acos(min(1.0, abs(float(nc @ z)) / nn))) if nn > 0 else 0.0
            self._meas = (key, (cp, fsum, press))
        return self._meas[1]

    def link_poses(self) -> dict:
        return self.scene.link_poses()

    def fault(self) -> Fault | None:
        """The pending whole-arm contact (:meth:`_collide`), handed over once."""
        hit, self.hit = self.hit, None
        return hit

    def stop(self) -> None:
        pass

    def summary(self) -> dict:
        moves = [pl for _, pl in self.plans]
        return {"mesh_triangles": int(len(self.mesh.triangles)), "arm_contacts": self.scene.collision.stats.to_dict(),
                "setup_moves": {"count": len(moves), "planned": sum(pl.planner != "straight" for pl in moves),
                                "slack_min_mm": 1e3 * min(pl.clearance for pl in moves) if moves else None,
                                "planning_seconds": self.plan_seconds},
                "retreats": {"count": len(self.retreats),
                             "shortened": sum(ok < want - 1e-9 for ok, want, _ in self.retreats)}}

    def disconnect(self) -> None:
        try:
            self.dev.disconnect()
        finally:
            self.world.close()
            self.scene.close()

    # ------------------------------------------------------------------ the compiled loops
    def follow(self, A: np.ndarray, D: np.ndarray, v_line=None):
        """The loop's ``_follow`` with the arithmetic in one compiled call per tick
        (:func:`~tergodic_cli.robot.kernels.pybullet_tick`): the same checks in the same order,
        the same arithmetic as get_observation / check / send_action."""
        A, D = np.ascontiguousarray(A, dtype=float), np.ascontiguousarray(D, dtype=float)
        self.law.mode = "press"
        i, t, io, rd, fault = self._compiled(A, D, np.zeros(0), v_line)
        if i < 0:
            return self.get_observation(), None, None, None
        n = self.model.dof
        st = ArmState(t, io[Kn.IO_Q:Kn.IO_Q + n].copy(), io[Kn.IO_DQ:Kn.IO_DQ + n].copy(),
                      io[Kn.IO_T:Kn.IO_T + 16].reshape(4, 4).copy(), io[Kn.IO_J:Kn.IO_J + 6 * n].reshape(6, n).copy())
        return Observation(st, rd, io[Kn.IO_W:Kn.IO_W + 6].copy()), A[i], D[i], fault

    def _joint_fast(self, QD: np.ndarray, DQD: np.ndarray):
        """:meth:`_move_joints` in compiled calls (all checks); the first fault, or None."""
        kd = np.ascontiguousarray(np.concatenate([self.joint.K, self.joint.D]), dtype=float)
        QD, DQD = np.ascontiguousarray(QD, dtype=float), np.ascontiguousarray(DQD, dtype=float)
        return self._compiled(QD, DQD, kd, None)[-1]

    def _compiled(self, A: np.ndarray, D: np.ndarray, kd: np.ndarray, v_line):
        """``len(A)`` ticks, each: one joint read, the sensor read, gravity + Coriolis every
        ``dynamics_every`` ticks, one :func:`~tergodic_cli.robot.kernels.pybullet_tick` (the
        control law: the line controller towards row i of A, D, or with ``kd`` the joint impedance
        towards it; the contact wrench, the guard's limits; a nonzero code names the fault), one
        torque command, the physics step.
        Returns (last tick, its time, io, its reading, fault or None); a faulty tick is not commanded."""
        cst = Kn.pack_constants(self.dev._chain, self.contact_wrench, self.guard, self.dev.tau_max, self.F_d,
                                None if v_line is None else np.asarray(v_line, dtype=float).tolist())
        tick, kpk, mut, ts, dyn = Kn.pybullet_tick, self.ctrl.kpk, self.ctrl.mut, self.ts, self.contact_wrench.dyn
        explorer = len(kd) == 0
        arm, sc, g = self.dev, self.scene, self.guard
        p, cid, rob, idx = sc.p, sc.cid, sc.robot, arm._read_idx
        get_states, send = p.getJointStates, p.setJointMotorControlArray
        gravity, physics = arm.gravity, self._physics
        joints, mode_torque, sread = sc.arm_joints, p.TORQUE_CONTROL, self.sensor.read
        check_sensor, timeout = g.check_sensor, g.cfg.explorer_timeout
        io = np.zeros(Kn.N_IO)
        n = self.model.dof
        OK, F_FORCE, F_IMPACT, tau_sl = Kn.OK, Kn.F_FORCE, Kn.F_IMPACT, slice(Kn.IO_TAU, Kn.IO_TAU + n)
        fg = g.force_state
        i, t, rd, fault = -1, sc.t, None, None
        for i in range(len(A)):
            # Flat tuples: q, q̇ and reactions of the movable joints, then the sensor joint's (last).
            qs, dqs, rs, _ = zip(*get_states(rob, idx, physicsClientId=cid))
            arm.reaction, arm.reaction_step = rs[-1], sc.steps
            rd = sread()
            t = sc.t
            bias = gravity(qs[:-1], dqs[:-1])
            fault = check_sensor(t, rd.t, rd.wrench)
            if fault is None:
                code = tick(i, A, D, qs, dqs, rd.wrench, bias, cst, kpk, mut, kd, io, ts, t, dyn, fg)
                if code == F_FORCE or code == F_IMPACT:
                    fault = g.force_fault(t, code)
                elif code != OK:
                    v = io[Kn.IO_DIAG + Kn.CD_VEE:Kn.IO_DIAG + Kn.CD_VEE + 3]
                    fault = g.check_state(t, io[Kn.IO_Q:Kn.IO_Q + n].copy(), io[Kn.IO_DQ:Kn.IO_DQ + n].copy(),
                                          io[Kn.IO_T:Kn.IO_T + 16].reshape(4, 4)[:3, 3].copy(), float(np.sqrt(v @ v)))
                elif explorer and g._target_t is not None and t - g._target_t > timeout:
                    fault = g.check_explorer(t)
            if fault is not None:
                break
            tot = io[tau_sl].tolist()
            arm.last_tau = tot
            send(rob, joints, mode_torque, forces=tot, physicsClientId=cid)
            physics()
            if self.hit is not None:  # an arm part touches something (checked in physics())
                fault = self.fault()
                break
        arm._q9 = arm._dq9 = None  # stale: the next command() reads the state first
        return i, t, io, rd, fault


def closest_point_fn(mesh, T: np.ndarray):
    """x (3,) -> (the closest point (3,) on ``mesh`` placed by ``T`` (4, 4), its triangle's unit normal
    (3,), either sign), in T's target frame (open3d)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(transform_points(T, mesh.vertices).astype(np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.triangles).astype(np.uint32)))

    def closest(x: np.ndarray) -> np.ndarray:
        out = scene.compute_closest_points(o3d.core.Tensor(np.asarray(x, dtype=np.float32).reshape(1, 3)))
        return out["points"].numpy()[0].astype(float), out["primitive_normals"].numpy()[0].astype(float)

    return closest


class RobotRun(ContactRun):
    """The contact loop on the simulated arm, its scene built from the capture.

    ``scene_mesh`` : (mesh, pose (4, 4) in the capture frame) of the object to press on (the closed
    loop's textured object); None: the simulated capture's own object, or a mesh rebuilt from the cloud.
    Tests reach in through ``run.arm`` (a :class:`SimArm`: ``scene``, ``sensor``, ``fast``).
    """

    def __init__(self, capture, explorer, cfg: RobotConfig, on_event: Callable[[int, str], None] | None = None,
                 scene_mesh=None, on_log: Callable[[str, int, dict], None] | None = None):
        from tergodic_cli.capture.filters import mean_spacing

        validate_robot_config(cfg)
        t_setup = time.perf_counter()
        points = np.asarray(capture.points, dtype=float)
        meta = getattr(capture, "meta", {}) or {}
        pose_given = cfg.object_pose is not None or meta.get("frame") == "robot_base"
        T_obj = object_pose(capture, cfg)
        check_reachable(transform_points(T_obj, points), get_arm(cfg.arm).reach)
        sim = meta.get("sim")
        source = getattr(capture, "mesh", None)
        h = float(meta.get("spacing_h_m") or mean_spacing(points))
        normals = oriented_normals(points, resolve_side(cfg.normal_side, meta))  # the loop's, computed once
        if scene_mesh is not None:
            mesh, T_mesh = scene_mesh
            self.mesh_source = "given"
        elif isinstance(sim, dict) and sim.get("object"):
            # A simulated capture: press on the object the camera rendered (its own surface), not on a
            # mesh rebuilt from the cloud; the cleaning model fades exactly that surface.
            mesh, T_mesh = sim_object_mesh(sim, cfg.mesh_edge)
            self.mesh_source = "sim_object"
        elif source is not None:
            # The capture holds the mesh its cloud was sampled from: the object's own surface.
            mesh, T_mesh = source_mesh(source, cfg.mesh_edge), np.eye(4)
            self.mesh_source = "source_mesh"
        else:
            mesh, T_mesh = rebuild_surface(points, normals, h, curved_edge(points, normals, cfg.mesh_edge)), np.eye(4)
            self.mesh_source = "cloud"
        # The surface's check, before any body or motion exists: refused in one line (exit 2).
        self.surface = surface_figures(SurfaceMesh(transform_points(np.asarray(T_mesh, dtype=float), mesh.vertices),
                                                   mesh.triangles, mesh.seconds, mesh.method or self.mesh_source),
                                       points, h, normals)
        check_surface(self.surface, rebuilt=self.mesh_source == "cloud")
        self.mesh = mesh
        self._T_mesh_obj = np.asarray(T_mesh, dtype=float)
        self.T_mesh = T_obj @ self._T_mesh_obj  # mesh frame -> base frame
        arm = SimArm(cfg, mesh, self.T_mesh)
        try:
            super().__init__(capture, explorer, cfg, arm, T_obj, on_event=on_event, on_log=on_log, normals=normals)
            arm.step_of = self._step
            self.max_tilt_deg = None  # the tool follows the normal; what the arm cannot reach is dropped
            self.closest = closest_point_fn(mesh, self._T_mesh_obj)
            self._plan_reach(capture, pose_given)
        except BaseException:
            arm.disconnect()
            raise
        self.setup_s = time.perf_counter() - t_setup

    def _plan_reach(self, capture, pose_given: bool) -> None:
        """Choose the object pose (when not given), mark where the tool can follow the normal, and drop
        the rest of the target from the explorer (reach.plan_reach), saying so before any contact."""
        arm = self.arm
        target = self.target()
        T, self.reachable = plan_reach(arm.dev._chain, self.points, self.normals, target, self._x_down,
                                       arm.picture_q, arm.q_min, arm.q_max,
                                       self.T_obj if pose_given else None, self.cfg.hover_height,
                                       reach=get_arm(self.cfg.arm).reach)
        # The ball hangs over an open sheet's border (a partial scan's free edge) and rolls off it.
        border = near_border(SurfaceMesh(transform_points(self._T_mesh_obj, self.mesh.vertices), self.mesh.triangles),
                             self.points, self.cfg.sponge.radius)
        if float(target @ (border & self.reachable)) > 1e-3 * float(target.sum()):
            self.on_event(0, f"robot: {100 * float(target @ (border & self.reachable)) / float(target.sum()):.0f} % of "
                             f"the target lies within the sponge's radius of the sheet's open border; dropped")
        self.reachable = self.reachable & ~border
        if not pose_given:
            self.T_obj = T
            self.points_base = transform_points(T, self.points)
            self.T_mesh = T @ self._T_mesh_obj
            arm.set_object_pose(self.T_mesh)
            yaw = math.degrees(math.atan2(T[1, 0], T[0, 0]))
            self.on_event(0, "robot: no --object-pose given; the object stands on a 0.2 m stand, its footprint centre "
                             f"{float(np.hypot(*T[:2, 3])):.2f} m in front of the base, turned {yaw:.0f} deg so the arm "
                             f"reaches its target (object pose {fmt_xyz(T[:3, 3])} m)")
        blocked = arm.posture_blocked()
        if blocked is not None:  # before any motion: no set-up move could start clear of the object
            raise TergodicError(f"the object at {fmt_xyz(self.T_obj[:3, 3])} m touches the arm at its picture pose "
                                f"({blocked})", "place the object lower or farther out, e.g. --object-pose 0.5,0,0.2 "
                                "(without one it stands 0.5 m in front of the base on a 0.2 m stand)")
        # The hand is 0.2 m wide: tilted along a steep wall with the spin reach.tool_rotation gives, it cuts
        # through a bowl's rim (82 % of the bowl's wall). Where the hand, its fingers or the sponge would come
        # within HAND_CLEAR of the object, the table or the stand with the tool on the normal, the tool
        # cannot press: dropped like any unreachable part (the run's checks fault whatever still touches).
        R = tool_rotations(-(self.normals @ self.T_obj[:3, :3].T), self._x_down)
        T_tcp = np.zeros((len(R), 4, 4))
        T_tcp[:, :3, :3], T_tcp[:, :3, 3], T_tcp[:, 3, 3] = R, self.points_base, 1.0
        clear = self.scene.collision.tool_clearance(T_tcp, HAND_CLEAR)
        if float(target @ (~clear & self.reachable)) > 1e-3 * float(target.sum()):
            self.on_event(0, f"robot: {100 * float(target @ (~clear & self.reachable)) / float(target.sum()):.0f} % of the "
                             f"target is where the hand would come within {HAND_CLEAR * 1e3:.0f} mm of the object, table "
                             "or stand with the tool on the normal; dropped")
        self.reachable &= clear
        self.drop_unreachable()

    @property
    def scene(self) -> PyBulletScene:
        return self.arm.scene

    def begin(self) -> None:
        super().begin()
        self.arm.wall0 = self._t0
        f = self.surface
        self.on_event(0, f"robot: contact surface from the {self.mesh_source} ({f['method']}, {f['triangles']} triangles, "
                         f"dihedral p95 {f['dihedral_p95_deg']:.1f} deg, {f['border_edges']} open border edges, "
                         f"covers {100 * f['coverage']:.1f} % of the cloud)")

    def result(self) -> dict:
        return {**super().result(), "setup_seconds": self.setup_s, "mesh_source": self.mesh_source,
                "contact_surface": dict(self.surface)}


def explore_with_robot(capture, explorer, robot_cfg: RobotConfig, steps: int,
                       on_step: Callable[[int, dict], None] | None = None,
                       on_event: Callable[[int, str], None] | None = None,
                       on_log: Callable[[str, int, dict], None] | None = None) -> dict:
    """Run ``steps`` explorer steps on the simulated robot (see :mod:`tergodic_cli.robot.run`).

    Parameters
    ----------
    capture : the :class:`~tergodic_cli.capture.Capture` (its object, or its cloud, becomes the collision mesh).
    explorer : an :class:`~tergodic_cli.explore.Explorer` built with ``robot_explore_config``.
    robot_cfg : :class:`RobotConfig`.
    steps : explorer steps in contact.
    on_step : called as on_step(step, robot_sample_dict) after each explorer step.
    on_event : called as on_event(step, text) at every state transition and warning.
    on_log : called as on_log(kind, step, record): the state transitions and the 1 kHz force windows
        (:class:`~tergodic_cli.robot.run.ContactRun`).

    Returns
    -------
    dict : the robot summary extras (:func:`~tergodic_cli.robot.summary.summarize_robot`) plus
        final_state, stop_reason, transitions, timings and the robot config.
    """
    with RobotRun(capture, explorer, robot_cfg, on_event=on_event, on_log=on_log) as run:
        return run.run(steps, on_step)


__all__ = ["RobotRun", "SimArm", "explore_with_robot"]
