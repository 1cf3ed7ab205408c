"""PyBullet implementations of :class:`~tergodic_cli.robot.interfaces.Arm` and ``WrenchSensor``.

Both read one ``getJointStates`` call per physics step (every movable joint and the sensor
joint together): the arm caches the sensor joint's reaction for the sensor. The TCP pose and
Jacobian come from compiled forward kinematics of the chain PyBullet loaded
(:func:`~tergodic_cli.robot.kernels.fk_jacobian`, calibrated against PyBullet's own link frames
at connect time; equal to ``getLinkState``/``calculateJacobian`` to 1e-12), so a 1 kHz loop costs
one state query, one torque command and, every ``dynamics_every`` steps, one inverse dynamics.
"""

from __future__ import annotations

import numpy as np

from tergodic_cli.errors import require
from tergodic_cli.robot.ga import motor_inverse
from tergodic_cli.robot.interfaces import ArmState, WrenchReading, WrenchSensor
from tergodic_cli.robot.kernels import fk_jacobian
from tergodic_cli.backends.pybullet.scene import PyBulletScene


class PyBulletArm:
    """The scene's arm behind the :class:`Arm` protocol (its model's n torque-controlled joints)."""

    def __init__(self, scene: PyBulletScene):
        self.scene = scene
        #: The arm as the robot layer knows it (DoF, limits, chain: read from its URDF).
        self.model = model = scene.arm_model()
        self.name = f"{model.name}-pybullet"
        self.joint_names = list(model.joint_names)
        self.q_min, self.q_max, self.dq_max, self.tau_max = (model.q_min.copy(), model.q_max.copy(),
                                                             model.dq_max.copy(), model.tau_max.copy())
        self._connected = False
        self._read_idx = scene.movable + [scene.sensor_joint]
        self._zeros = [0.0] * len(scene.movable)
        self._q9: list[float] | None = None
        self._dq9: list[float] | None = None
        self.reaction: tuple | None = None  # the sensor joint's reaction, cached per step
        self.reaction_step = -1
        self.last_tau = [0.0] * model.dof  # total torque sent (task + compensation)
        self._tau_lim = self.tau_max.tolist()
        #: Gravity + Coriolis (calculateInverseDynamics) every this many commands (1 = every step).
        self.dynamics_every = 1
        self._bias: tuple | None = None
        self._bias_age = 0
        self._bias_epoch = -1
        self._chain = model.chain

    @property
    def is_connected(self) -> bool:
        return self._connected and self.scene.cid >= 0

    def connect(self) -> None:
        require(self.scene.cid >= 0, "the PyBullet scene is closed", "build a new scene")
        self._connected = True

    def read_state(self) -> ArmState:
        require(self.is_connected, "the arm is not connected", "call connect() first")
        sc = self.scene
        p, cid, rob = sc.p, sc.cid, sc.robot
        states = p.getJointStates(rob, self._read_idx, physicsClientId=cid)
        self._q9, self._dq9 = [s[0] for s in states[:-1]], [s[1] for s in states[:-1]]
        self.reaction, self.reaction_step = states[-1][2], sc.steps  # the sensor joint's
        q, T, J = np.array(self._q9), np.empty((4, 4)), np.empty((6, len(self._q9)))
        fk_jacobian(q, *self._chain, T, J)
        return ArmState(sc.t, q, np.array(self._dq9), T, J)

    def command(self, tau: np.ndarray) -> None:
        """Joint torques (n,) on top of gravity + Coriolis from ``calculateInverseDynamics``.

        TORQUE_CONTROL is not sticky in PyBullet: call this every physics step.
        """
        sc = self.scene
        p, cid = sc.p, sc.cid
        if self._q9 is None:  # never read: read first (also checks the connection)
            self.read_state()
        bias, lim = self.gravity(self._q9, self._dq9), self._tau_lim
        total = [min(max(t + b, -m), m) for t, b, m in zip(np.asarray(tau, dtype=float).tolist(), bias, lim)]
        self.last_tau = total
        p.setJointMotorControlArray(sc.robot, sc.arm_joints, p.TORQUE_CONTROL, forces=total, physicsClientId=cid)

    def gravity(self, q, dq) -> tuple:
        """Gravity + Coriolis torques at (q, q̇), movable joints (``calculateInverseDynamics``).

        They change slowly at these speeds (< 0.3 rad/s in contact: 1.2 mrad in 4 ms, ~0.03 N m of
        gravity torque): refreshed every ``dynamics_every`` calls, and after a teleport.
        """
        sc = self.scene
        self._bias_age += 1
        if self._bias is None or self._bias_age >= self.dynamics_every or self._bias_epoch != sc.teleports:
            self._bias = sc.p.calculateInverseDynamics(sc.robot, q, dq, self._zeros,
                                                       physicsClientId=sc.cid)
            self._bias_age = 0
            self._bias_epoch = sc.teleports
        return self._bias

    def disconnect(self) -> None:
        """Leave the joints braked (velocity motors back on) and mark the arm disconnected."""
        if self.is_connected:
            sc = self.scene
            sc.p.setJointMotorControlArray(sc.robot, sc.arm_joints, sc.p.VELOCITY_CONTROL, targetVelocities=[0.0] * len(sc.arm_joints),
                                           forces=self.tau_max.tolist(), physicsClientId=sc.cid)
        self._connected = False


class PyBulletWrenchSensor(WrenchSensor):
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
        # Before the first physics step PyBullet reports a zero reaction, not the tool's weight.
        return WrenchReading(self.scene.t, (r[0] - o[0], r[1] - o[1], r[2] - o[2], r[3] - o[3], r[4] - o[4], r[5] - o[5]),
                             self.scene.steps > 0)

    def tare(self) -> None:
        self._offset = tuple(self._raw())
