"""The PyBullet world: an arm (``--arm``, arms/) with a sponge tool and a wrist F/T sensor, a table, an object.

Known PyBullet traps handled here:

- every joint starts with a velocity motor that fights torque control: the arm's are turned
  off with ``force=0`` once; TORQUE_CONTROL is then re-sent every step (it is not sticky);
- links get a default linear/angular damping that no model knows about: set to zero;
- ``calculateJacobian`` and ``calculateInverseDynamics`` need numDoF-sized inputs (every
  non-fixed joint, fingers included when a gripper is loaded; here the sponge replaces it);
- joint damping from a URDF's ``<dynamics>`` is applied by PyBullet: set to zero;
- the sensor joint's reaction (the F/T sensor) is reported in the tool link's *inertial* frame,
  moment about the tool's centre of mass, not about the joint.
"""

from __future__ import annotations

import math
import os
import tempfile
from contextlib import suppress

import numpy as np

from tergodic_cli.errors import TergodicError, require
from tergodic_cli.backends.pybullet.arms import ArmSpec, get_arm
from tergodic_cli.robot.config import SpongeSpec
from tergodic_cli.robot.ga import matrix_to_quat, pose_matrix, quat_to_matrix
from tergodic_cli.robot.interfaces import ToolLoad
from tergodic_cli.robot.model import ArmModel

class PyBulletScene:
    """One PyBullet client holding the arm, an optional table and an optional object.

    Parameters
    ----------
    sponge : :class:`SpongeSpec`.
    gui : open the PyBullet GUI instead of DIRECT.
    arm : the arm's name in :data:`~tergodic_cli.backends.pybullet.arms.ARMS` (or its :class:`ArmSpec`).

    The table (top at z = 0, a hole for the base) and, under a lifted object, a stand are bodies of
    every scene; they and the object are checked against every arm part (:attr:`collision`,
    :mod:`~tergodic_cli.backends.pybullet.collision`), while the physics step simulates only the
    sponge on the object.
    dt : physics step, s (1 kHz by default).
    solver_iterations : constraint solver iterations per step.
    """

    def __init__(self, sponge: SpongeSpec | None = None, gui: bool = False, dt: float = 1e-3,
                 solver_iterations: int = 10, arm: str | ArmSpec = "panda"):
        from tergodic_cli.backends.pybullet.camera import quiet_native_output

        with quiet_native_output():  # PyBullet's build banner, printed from C at import
            import pybullet as p
            import pybullet_data

        self.p = p
        self.sponge = sponge or SpongeSpec()
        self.spec = arm if isinstance(arm, ArmSpec) else get_arm(arm)
        self.dt = float(dt)
        self.gui = bool(gui)
        if self.gui:
            try:
                self.cid = p.connect(p.GUI)
            except p.error as exc:
                raise TergodicError(f"cannot open the PyBullet GUI ({exc})",
                                    "run without --gui (DIRECT mode) or set DISPLAY") from None
        else:
            self.cid = p.connect(p.DIRECT)
        require(self.cid >= 0, "cannot start a PyBullet client", "check the pybullet installation")
        cid = self.cid
        p.resetSimulation(physicsClientId=cid)
        p.setGravity(0, 0, -9.81, physicsClientId=cid)
        p.setTimeStep(self.dt, physicsClientId=cid)
        p.setPhysicsEngineParameter(numSolverIterations=int(solver_iterations), physicsClientId=cid)
        data = pybullet_data.getDataPath()
        self.robot = self._load_robot(data)
        p.setPhysicsEngineParameter(contactBreakingThreshold=self._breaking_factor(), physicsClientId=cid)
        from tergodic_cli.backends.pybullet.collision import ArmCollision

        #: The arm's parts against the table, the stand and the object (checked, not simulated: collision.py).
        self.collision = ArmCollision(self, data)
        self.table = self.collision.add_table()
        self.object: int | None = None
        #: {body: (vertices (n, 3), triangles (k, 3))} of every mesh body built from vertices (PyBullet
        #: cannot hand those back): the set-up moves' collision check copies them (plan.CollisionWorld).
        self.mesh_data: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.t = 0.0
        self.steps = 0
        self.teleports = 0  # counts set_arm calls (cached kinematics are stale after one)

    # ------------------------------------------------------------------ robot
    def _load_robot(self, data: str) -> int:
        p, cid = self.p, self.cid
        spec = self.spec
        fd, path = tempfile.mkstemp(suffix=".urdf", prefix=f"tergodic_{spec.name}_")
        try:
            with os.fdopen(fd, "w") as fh:
                fh.write(spec.urdf_text(data, self.sponge, arm_collision=False))
            robot = p.loadURDF(path, useFixedBase=True, flags=p.URDF_USE_INERTIA_FROM_FILE, physicsClientId=cid)
        finally:
            os.unlink(path)
        n = p.getNumJoints(robot, physicsClientId=cid)
        infos = [p.getJointInfo(robot, j, physicsClientId=cid) for j in range(n)]
        for j in range(n):
            p.changeDynamics(robot, j, linearDamping=0.0, angularDamping=0.0, jointDamping=0.0, physicsClientId=cid)
        names = {info[1].decode(): j for j, info in enumerate(infos)}
        self.link_names = [info[12].decode() for info in infos]
        self.link_index = links = {n: j for j, n in enumerate(self.link_names)}
        self.base_link = p.getBodyInfo(robot, physicsClientId=cid)[0].decode()
        self.arm_joints = [names[n] for n in spec.joints]
        # Every non-fixed joint, in index order: the numDoF-sized inputs of calculateJacobian and
        # calculateInverseDynamics (the arm's: the sponge replaces any gripper).
        self.movable = [j for j, info in enumerate(infos) if info[2] != p.JOINT_FIXED]
        require(self.movable == self.arm_joints, f"the {spec.name} URDF's movable joints are not {', '.join(spec.joints)}",
                "list every non-fixed joint of the URDF, base to tip, in the arm's module")
        self.sensor_joint = names[spec.sensor_joint]
        self.sponge_link = links[spec.tool_link]
        #: The TCP is the sponge's tip, a point on the sponge's link (no link of its own: one fewer body).
        self.tcp_link = self.sponge_link
        self.tcp_offset = (0.0, 0.0, float(self.sponge.offset + self.sponge.radius))
        # Torque control: switch the arm's default velocity motors off (force = 0).
        p.setJointMotorControlArray(robot, self.arm_joints, p.VELOCITY_CONTROL, forces=[0.0] * len(self.arm_joints),
                                    physicsClientId=cid)
        p.enableJointForceTorqueSensor(robot, self.sensor_joint, True, physicsClientId=cid)
        s = self.sponge
        # contactProcessingThreshold=0: only touching or penetrating points reach the solver. The
        # sponge/trimesh manifold also holds points still up to the breaking threshold apart (about
        # one of its four in contact); they carry no force but each costs the solver three rows
        # (normal + 2 friction) of multibody Jacobians, ~8 % of a tick (docs/robot.md, "Timing").
        p.changeDynamics(robot, self.sponge_link, contactStiffness=s.stiffness, contactDamping=s.damping,
                         lateralFriction=s.friction, spinningFriction=0.0, rollingFriction=0.0,
                         contactProcessingThreshold=0.0, physicsClientId=cid)
        return robot

    def _breaking_factor(self) -> float:
        """PyBullet's ``contactBreakingThreshold`` that keeps the sponge ball's own contact threshold.

        Bullet scales the threshold (how far apart contact points are still made and kept) with
        each shape's bounding radius about its body's centre of mass: 0.02 × (|c| + √3 r) for a
        ball of radius r whose centre sits at c. As a link of its own the ball had c = 0: 0.42 mm.
        As a child of the hand's shape, 87 mm from the hand's centre of mass, the same default
        would give 2.2 mm, which keeps stale points and measurably changes the contact (median
        track on the bowl 0.7 -> 1.0 mm, force error +20 %). The factor below restores 0.42 mm.
        The setting is process-wide in Bullet (every client), and only the sponge ever touches.
        """
        com = np.array(self.p.getDynamicsInfo(self.robot, self.sponge_link, physicsClientId=self.cid)[3])
        ball = np.array([0.0, 0.0, self.sponge.offset])
        r = math.sqrt(3.0) * self.sponge.radius
        return 0.02 * r / (float(np.linalg.norm(ball - com)) + r)

    def arm_model(self) -> ArmModel:
        """The arm as the robot layer sees it (:class:`~tergodic_cli.robot.model.ArmModel`): DoF and joint
        limits read from the loaded URDF (``getJointInfo``), replaced where the arm's module gives
        datasheet values; the chain base -> TCP (:func:`kinematic_chain`)."""

        p, cid = self.p, self.cid
        info = [p.getJointInfo(self.robot, j, physicsClientId=cid) for j in self.arm_joints]
        urdf = {"q_min": np.array([i[8] for i in info]), "q_max": np.array([i[9] for i in info]),
                "tau_max": np.array([i[10] for i in info]), "dq_max": np.array([i[11] for i in info])}
        lim = {k: np.asarray(self.spec.limits.get(k, v), dtype=float).copy() for k, v in urdf.items()}
        n = len(self.arm_joints)
        require(all(len(v) == n for v in lim.values()) and len(self.spec.home) == n,
                f"the {self.spec.name} module's limits or home posture do not have {n} joints", "fix the arm's module")
        links = tuple([self.base_link] + self.link_names)
        return ArmModel(self.spec.name, tuple(self.spec.joints), lim["q_min"], lim["q_max"], lim["dq_max"],
                        lim["tau_max"], np.array(self.spec.home, dtype=float), kinematic_chain(self), links)

    def set_arm(self, q: np.ndarray) -> None:
        """Teleport the arm to ``q`` (n,) at rest (set-up only, never mid-run)."""
        self.teleports += 1
        for j, qi in zip(self.arm_joints, q):
            self.p.resetJointState(self.robot, j, float(qi), 0.0, physicsClientId=self.cid)

    def link_pose(self, link: int) -> np.ndarray:
        """(4, 4) world pose of a link frame (forward kinematics recomputed)."""
        s = self.p.getLinkState(self.robot, link, computeForwardKinematics=True, physicsClientId=self.cid)
        return pose_matrix(quat_to_matrix(s[5]), np.array(s[4]))

    def tcp_pose(self) -> np.ndarray:
        """(4, 4) world pose of the TCP (the sponge's tip)."""
        T = self.link_pose(self.tcp_link)
        T[:3, 3] += T[:3, :3] @ np.array(self.tcp_offset)
        return T

    def link_poses(self) -> dict[str, np.ndarray]:
        """{link name: (7,) xyz + quaternion xyzw} of every robot link, base frame, for logging."""
        idx = list(range(len(self.link_names)))
        states = self.p.getLinkStates(self.robot, idx, computeForwardKinematics=True, physicsClientId=self.cid)
        return {self.base_link: np.array([0, 0, 0, 0, 0, 0, 1.0]),
                **{name: np.array(tuple(s[4]) + tuple(s[5])) for name, s in zip(self.link_names, states)}}

    def tool_load(self):
        """:class:`ToolLoad` of everything beyond the sensor joint, in the sensor frame."""
        p, cid, rob = self.p, self.cid, self.robot
        T_sensor = self.sensor_frame_world()
        total, mc = 0.0, np.zeros(3)
        for j in range(p.getNumJoints(rob, physicsClientId=cid)):
            if self.sensor_joint in self.chain_to(j):
                m = p.getDynamicsInfo(rob, j, physicsClientId=cid)[0]
                com = np.array(p.getLinkState(rob, j, computeForwardKinematics=True, physicsClientId=cid)[0])
                total += m
                mc += m * com
        com_world = mc / total
        com_sensor = T_sensor[:3, :3].T @ (com_world - T_sensor[:3, 3])
        # The sensor frame is the hand's inertial frame: its principal inertia is along the sensor axes.
        inertia = np.array(p.getDynamicsInfo(rob, self.sponge_link, physicsClientId=cid)[2], dtype=float)
        return ToolLoad(total, com_sensor, inertia)

    def chain_to(self, j: int) -> list[int]:
        """The robot's links from the base to link ``j`` (included), in that order."""
        chain = []
        while j >= 0:
            chain.append(j)
            j = self.p.getJointInfo(self.robot, j, physicsClientId=self.cid)[16]
        return chain[::-1]

    def sensor_frame_world(self) -> np.ndarray:
        """(4, 4) world pose of the F/T frame: the tool link's inertial frame (where PyBullet reports the reaction)."""
        T_hand = self.link_pose(self.sponge_link)
        info = self.p.getDynamicsInfo(self.robot, self.sponge_link, physicsClientId=self.cid)
        return T_hand @ pose_matrix(quat_to_matrix(info[4]), np.array(info[3]))

    # ------------------------------------------------------------------ object
    def add_object(self, vertices: np.ndarray, triangles: np.ndarray, pose: np.ndarray,
                   color=(0.85, 0.83, 0.8, 1.0)) -> int:
        """A static concave triangle mesh (vertices (n, 3) m, triangles (k, 3)) at ``pose`` (4, 4)."""
        p, cid = self.p, self.cid
        kw = dict(vertices=np.asarray(vertices, float).tolist(), indices=np.asarray(triangles, np.int64).ravel().tolist())
        # Internal-edge correction: without it the sponge bumps on every triangle edge it slides over.
        col = p.createCollisionShape(p.GEOM_MESH, flags=p.GEOM_FORCE_CONCAVE_TRIMESH | p.GEOM_CONCAVE_INTERNAL_EDGE,
                                     physicsClientId=cid, **kw)
        vis = p.createVisualShape(p.GEOM_MESH, rgbaColor=list(color), physicsClientId=cid, **kw) if self.gui else -1
        body = p.createMultiBody(0.0, col, vis, basePosition=pose[:3, 3].tolist(),
                                 baseOrientation=matrix_to_quat(pose[:3, :3]).tolist(), physicsClientId=cid)
        p.changeDynamics(body, -1, lateralFriction=self.sponge.friction, physicsClientId=cid)
        self.mesh_data[body] = (np.asarray(vertices, float), np.asarray(triangles, np.int64))
        # Only the sponge touches the object: a hand or finger hull against the concave mesh costs
        # 5-10× a physics step (docs/robot.md). Collision groups: object 2, sponge 1|2, other links 1.
        p.setCollisionFilterGroupMask(body, -1, 2, 2, physicsClientId=cid)
        for link in range(-1, len(self.link_names)):
            bits = 3 if link == self.sponge_link else 1
            p.setCollisionFilterGroupMask(self.robot, link, bits, bits, physicsClientId=cid)
        self.object = body
        self.object_pose = np.array(pose, dtype=float)
        self._object_mesh = (np.asarray(vertices, float), np.asarray(triangles))
        self.collision.set_object(body, self._object_mesh[0] @ self.object_pose[:3, :3].T + self.object_pose[:3, 3],
                                  self._object_mesh[1])
        return body

    def move_object(self, pose: np.ndarray) -> None:
        """Teleport the object (fault injection: the object is bumped)."""
        self.p.resetBasePositionAndOrientation(self.object, pose[:3, 3].tolist(), matrix_to_quat(pose[:3, :3]).tolist(),
                                               physicsClientId=self.cid)
        self.object_pose = np.array(pose, dtype=float)
        V, F = self._object_mesh
        self.collision.set_object(self.object, V @ self.object_pose[:3, :3].T + self.object_pose[:3, 3], F)

    def sponge_contacts(self) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """Contacts between the sponge and the object: [(point on object (3,), normal on the sponge (3,), normal force N)]."""
        if self.object is None:
            return []
        cps = self.p.getContactPoints(self.robot, self.object, self.sponge_link, -1, physicsClientId=self.cid)
        return [(np.array(c[6]), np.array(c[7]), float(c[9])) for c in cps]

    # ------------------------------------------------------------------ time
    def step(self) -> None:
        self.p.stepSimulation(physicsClientId=self.cid)
        self.steps += 1
        self.t = self.steps * self.dt

    def close(self) -> None:
        if self.cid >= 0:
            with suppress(self.p.error):
                self.p.disconnect(physicsClientId=self.cid)
            self.cid = -1


def kinematic_chain(scene: "PyBulletScene") -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The chain base -> TCP link as :func:`fk_jacobian` wants it: (F (m, 4, 4), axis (m, 3), qidx (m,), tcp_off (3,)).

    Calibrated on PyBullet itself: with every movable joint at 0, each link frame in its parent's
    (``getLinkState`` link frames; the base link frame is the world origin, where the robot is loaded)
    is the fixed transform F; the joint rotates the child about ``jointAxis`` (its own frame; PyBullet
    reports it in the child's inertial frame, turned back here). The
    joint states are restored afterwards.
    """
    p, cid, rob = scene.p, scene.cid, scene.robot
    chain = scene.chain_to(scene.tcp_link)
    saved = p.getJointStates(rob, scene.movable, physicsClientId=cid)
    try:
        for jj in scene.movable:
            p.resetJointState(rob, jj, 0.0, 0.0, physicsClientId=cid)
        F, axis, qidx = [], [], []
        T_prev = np.eye(4)
        for link in chain:
            T = scene.link_pose(link)
            F.append(np.linalg.solve(T_prev, T))
            info = p.getJointInfo(rob, link, physicsClientId=cid)
            movable = info[2] != p.JOINT_FIXED
            # PyBullet gives the axis in the link's inertial frame, which it turns to the principal axes of
            # a URDF's full inertia tensor (the xArm's): back into the link frame.
            R_in = quat_to_matrix(p.getDynamicsInfo(rob, link, physicsClientId=cid)[4])
            ax = R_in @ np.array(info[13], dtype=float)
            axis.append(ax / np.linalg.norm(ax) if movable else np.array([0.0, 0.0, 1.0]))
            qidx.append(scene.movable.index(link) if movable else -1)
            T_prev = T
    finally:
        for jj, st in zip(scene.movable, saved):
            p.resetJointState(rob, jj, st[0], st[1], physicsClientId=cid)
    return (np.ascontiguousarray(F, dtype=float), np.ascontiguousarray(axis, dtype=float), np.asarray(qidx, dtype=np.int64),
            np.asarray(scene.tcp_offset, dtype=float))
