"""PyBullet implementations of :class:`~tergodic_cli.robot.interfaces.Arm` and ``WrenchSensor``.

Both read one ``getJointStates`` call per physics step (every movable joint and the sensor
joint together): the arm caches the sensor joint's reaction for the sensor, so a
1 kHz loop costs one state query, one forward-kinematics query, one Jacobian, one inverse
dynamics and one torque command.
"""

from __future__ import annotations

import numpy as np

from tergodic_cli.errors import TergodicError
from tergodic_cli.robot.ga import motor_inverse
from tergodic_cli.robot.interfaces import ArmState, WrenchReading
from tergodic_cli.robot.pybullet_backend.scene import ARM_JOINTS, DQ_MAX, Q_MAX, Q_MIN, TAU_MAX, PyBulletScene


class PyBulletArm:
    """The simulated Panda behind the :class:`Arm` protocol (7 torque-controlled joints)."""

    name = "panda-pybullet"
    dof = 7

    def __init__(self, scene: PyBulletScene):
        self.scene = scene
        self.joint_names = list(ARM_JOINTS)
        self.q_min, self.q_max, self.dq_max, self.tau_max = Q_MIN.copy(), Q_MAX.copy(), DQ_MAX.copy(), TAU_MAX.copy()
        self._connected = False
        self._read_idx = scene.movable + [scene.sensor_joint]
        self._zeros = [0.0] * len(scene.movable)
        self._q9: list[float] | None = None
        self._dq9: list[float] | None = None
        self.reaction: tuple | None = None  # the sensor joint's reaction, cached per step
        self.reaction_step = -1
        self.last_tau = [0.0] * 7  # total torque sent (task + compensation)
        self._tau_lim = self.tau_max.tolist()
        #: Refresh the Jacobian every this many reads (1 = every control step).
        self.jacobian_every = 1
        self._J = None
        self._J_epoch = -1
        assert scene.tcp_offset[:2] == (0.0, 0.0)
        self._tcp_z = float(scene.tcp_offset[2])
        self._age = 0

    @property
    def is_connected(self) -> bool:
        return self._connected and self.scene.cid >= 0

    def connect(self) -> None:
        if self.scene.cid < 0:
            raise TergodicError("the PyBullet scene is closed", "build a new scene")
        self._connected = True

    def _require(self) -> None:
        if not self.is_connected:
            raise TergodicError("the arm is not connected", "call connect() first")

    def read_state(self) -> ArmState:
        self._require()
        sc = self.scene
        p, cid, rob = sc.p, sc.cid, sc.robot
        states = p.getJointStates(rob, self._read_idx, physicsClientId=cid)
        q9 = [s[0] for s in states[:-1]]
        dq9 = [s[1] for s in states[:-1]]
        self._q9, self._dq9 = q9, dq9
        self.reaction = states[-1][2]
        self.reaction_step = sc.steps
        ls = p.getLinkState(rob, sc.tcp_link, computeForwardKinematics=True, physicsClientId=cid)
        r = p.getMatrixFromQuaternion(ls[5], physicsClientId=cid)
        x, o = ls[4], self._tcp_z  # TCP = link origin + offset along the link's z
        pos = (x[0] + r[2] * o, x[1] + r[5] * o, x[2] + r[8] * o)
        self._age += 1
        if self._J is None or self._age >= self.jacobian_every or self._J_epoch != sc.teleports:
            lin, ang = p.calculateJacobian(rob, sc.tcp_link, sc.tcp_offset, q9, self._zeros, self._zeros,
                                           physicsClientId=cid)
            self._J = np.array(lin + ang)[:, :7]
            self._age = 0
            self._J_epoch = sc.teleports
        return ArmState(sc.t, np.array(q9[:7]), np.array(dq9[:7]), None, self._J, r, pos)

    def command(self, tau: np.ndarray) -> None:
        """Joint torques (7,) on top of gravity + Coriolis from ``calculateInverseDynamics``.

        TORQUE_CONTROL is not sticky in PyBullet: call this every physics step.
        """
        sc = self.scene
        p, cid = sc.p, sc.cid
        if self._q9 is None:  # never read: read first (also checks the connection)
            self.read_state()
        bias = p.calculateInverseDynamics(sc.robot, self._q9, self._dq9, self._zeros, physicsClientId=cid)
        lim = self._tau_lim
        total = [min(max(t + b, -m), m) for t, b, m in zip(np.asarray(tau, dtype=float).tolist(), bias, lim)]
        self.last_tau = total
        p.setJointMotorControlArray(sc.robot, sc.arm_joints, p.TORQUE_CONTROL, forces=total, physicsClientId=cid)

    def disconnect(self) -> None:
        """Leave the joints braked (velocity motors back on) and mark the arm disconnected."""
        if self.is_connected:
            sc = self.scene
            sc.p.setJointMotorControlArray(sc.robot, sc.arm_joints, sc.p.VELOCITY_CONTROL, targetVelocities=[0.0] * 7,
                                           forces=self.tau_max.tolist(), physicsClientId=sc.cid)
        self._connected = False


class PyBulletWrenchSensor:
    """The wrist F/T sensor: the reaction of the fixed joint between flange and hand.

    Reports the wrench the arm applies to the hand (and everything beyond it) in the hand's
    inertial frame, moment about its origin, minus the tare offset.
    """

    def __init__(self, scene: PyBulletScene, arm: PyBulletArm | None = None):
        self.scene = scene
        self.arm = arm
        self._offset = (0.0,) * 6
        self.frame_in_ee = motor_inverse(scene.tcp_pose()) @ scene.sensor_frame_world()

    def _raw(self) -> tuple:
        sc = self.scene
        arm = self.arm
        if arm is not None and arm.reaction_step == sc.steps and arm.reaction is not None:
            return arm.reaction
        return sc.p.getJointState(sc.robot, sc.sensor_joint, physicsClientId=sc.cid)[2]

    def read(self) -> WrenchReading:
        """The latest sample; ``wrench`` is a 6-tuple (array-like), tare offset removed."""
        r, o = self._raw(), self._offset
        return WrenchReading(self.scene.t, (r[0] - o[0], r[1] - o[1], r[2] - o[2], r[3] - o[3], r[4] - o[4], r[5] - o[5]))

    def tare(self) -> None:
        self._offset = tuple(self._raw())

    @property
    def offset(self) -> np.ndarray:
        return np.array(self._offset)
