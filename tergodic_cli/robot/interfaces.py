"""Hardware-shaped interfaces: an :class:`Arm` and a :class:`WrenchSensor`.

Small Protocols in the style of lerobot's ``robots/robot.py``: a backend connects, is read,
is commanded, disconnects. The controller, the safety guard and the state machine speak
only these, so a real Franka (libfranka/franky) or a real F/T sensor (Bota) can replace the
PyBullet backend without touching them.

Conventions every backend honours
---------------------------------
- Frames: "base" is the robot base; "ee" is the tool centre point (TCP), z along the tool
  axis pointing out of the flange; the sensor frame is fixed in the ee frame
  (:attr:`WrenchSensor.frame_in_ee`).
- Torques given to :meth:`Arm.command` are *on top of* gravity and Coriolis compensation,
  which the backend adds itself (libfranka compensates gravity in firmware; the PyBullet
  backend adds ``calculateInverseDynamics``).
- :meth:`WrenchSensor.read` returns the wrench the arm applies to the tool through the
  sensor, in the sensor frame, moment about the sensor origin, minus the tare offset. With
  the tool at rest and free it is the tool's weight; pressing on a surface adds the force
  the tool exerts on it. :class:`ToolLoad` removes the weight.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

GRAVITY = 9.81


class ArmState:
    """One sample of the arm.

    Attributes
    ----------
    t : sample time, s (backend clock; simulated time in simulation).
    q, dq : (dof,) joint positions (rad) and velocities (rad/s).
    ee_pose : (4, 4) pose of the TCP in the base frame (the motor M(q) of eq. 14 with the tool).
    jacobian : (6, dof) geometric Jacobian of the TCP in the base frame, rows (v, ω):
        v the TCP velocity, ω the angular velocity (libfranka's "zero Jacobian").
    rot, pos : the same pose as 9 row-major floats and 3 floats, for scalar code at 1 kHz.

    A backend gives either ``ee_pose`` or ``rot`` and ``pos``; the other form is made on first use.
    """

    __slots__ = ("t", "q", "dq", "jacobian", "_T", "_rot", "_pos")

    def __init__(self, t: float, q: np.ndarray, dq: np.ndarray, ee_pose: np.ndarray | None = None,
                 jacobian: np.ndarray | None = None, rot: tuple | None = None, pos: tuple | None = None):
        self.t, self.q, self.dq, self.jacobian = t, q, dq, jacobian
        self._T, self._rot, self._pos = ee_pose, rot, pos

    @property
    def ee_pose(self) -> np.ndarray:
        if self._T is None:
            r, x = self._rot, self._pos
            self._T = np.array(((r[0], r[1], r[2], x[0]), (r[3], r[4], r[5], x[1]), (r[6], r[7], r[8], x[2]),
                                (0.0, 0.0, 0.0, 1.0)))
        return self._T

    @property
    def rot(self) -> tuple:
        if self._rot is None:
            self._rot = tuple(self._T[:3, :3].ravel().tolist())
        return self._rot

    @property
    def pos(self) -> tuple:
        if self._pos is None:
            self._pos = tuple(self._T[:3, 3].tolist())
        return self._pos


@dataclass
class WrenchReading:
    """One F/T sample: time (s) and wrench (6,) ``fx fy fz tx ty tz`` in the sensor frame (N, N m).

    ``wrench`` is array-like: a (6,) array or a 6-tuple (the PyBullet backend's, cheaper at 1 kHz).
    ``valid`` is False for a placeholder that is no measurement (a simulated sensor before its
    first physics step reads 0): such a reading must not count.
    """

    t: float
    wrench: np.ndarray | tuple
    valid: bool = True


@runtime_checkable
class Arm(Protocol):
    """A torque-controlled arm."""

    name: str
    dof: int
    joint_names: list[str]
    #: (dof,) lower/upper joint position limits, rad; (dof,) velocity limits, rad/s; (dof,) torque limits, N m.
    q_min: np.ndarray
    q_max: np.ndarray
    dq_max: np.ndarray
    tau_max: np.ndarray

    @property
    def is_connected(self) -> bool: ...

    def connect(self) -> None:
        """Open the connection (idempotent)."""

    def read_state(self) -> ArmState:
        """The arm's state now.

        Returns
        -------
        ArmState
            Joint positions (rad), velocities (rad/s), the TCP pose and Jacobian.
        """

    def command(self, tau: np.ndarray) -> None:
        """Send joint torques, on top of the backend's gravity/Coriolis compensation.

        Parameters
        ----------
        tau : (dof,) float
            Joint torques, N m.
        """

    def disconnect(self) -> None:
        """Close the connection; the arm is left holding still (brakes, or zero velocity)."""


@runtime_checkable
class WrenchSensor(Protocol):
    """A 6-axis force/torque sensor."""

    #: (4, 4) pose of the sensor frame in the ee (TCP) frame.
    frame_in_ee: np.ndarray

    def read(self) -> WrenchReading:
        """The latest sample, tare offset removed (see the module docstring for the sign).

        Returns
        -------
        WrenchReading
            Force (N) and torque (N m) in the sensor frame, with its timestamp.
        """

    def tare(self) -> None:
        """Zero the reading: subtract the present wrench from every later sample."""


@dataclass
class ToolLoad:
    """Mass (kg) and centre of mass (3,) in the sensor frame of everything beyond the sensor, and
    its principal inertia (3,) about the centre of mass along the sensor axes, kg m² (for the
    inertial compensation; zeros: forces only)."""

    mass: float
    com: np.ndarray
    inertia: np.ndarray | None = None

    def wrench(self, R_base_sensor: np.ndarray) -> np.ndarray:
        """The wrench the arm must apply to hold the tool still against gravity.

        Parameters
        ----------
        R_base_sensor : (3, 3) float
            The sensor frame's rotation in the base frame.

        Returns
        -------
        (6,) float
            Force (N) and torque (N m), sensor frame.
        """
        f = R_base_sensor[2, :] * (self.mass * GRAVITY)  # Rᵀ (0, 0, m g)
        return np.concatenate([f, np.cross(self.com, f)])


class ContactWrench:
    """Turns sensor readings into the wrench the tool exerts on its surroundings, in the ee frame.

    ``tare_at(R)`` records the sensor orientation of the last tare (the tool load then is part
    of the zeroed reading); ``__call__`` removes the change of tool load since, then moves the
    wrench from the sensor frame to the TCP: W'_m of eq. 39. The arithmetic is
    :func:`tergodic_cli.robot.kernels.contact_wrench` (compiled: it runs at 1 kHz).

    With ``inertial`` and the arm's state given, the wrench that accelerates the tool (mass ×
    acceleration of its centre of mass, I α + ω × I ω, from J q̇ differenced between samples) is
    removed too (:func:`~tergodic_cli.robot.kernels.inertial_wrench`): the sensor then measures the
    contact alone while the arm moves (issue 15: uncompensated, the hand's inertial forces read as
    tens of newtons of "contact").
    """

    def __init__(self, load: ToolLoad, frame_in_ee: np.ndarray, inertial: bool = False):
        from tergodic_cli.robot.kernels import contact_wrench

        self.load = load
        self.R_se_m = np.ascontiguousarray(np.asarray(frame_in_ee, dtype=float)[:3, :3])  # sensor -> ee
        self.p_se_v = np.ascontiguousarray(np.asarray(frame_in_ee, dtype=float)[:3, 3])  # sensor origin in the ee frame
        self.R_se = tuple(self.R_se_m.ravel().tolist())
        self.p_se = tuple(self.p_se_v.tolist())
        self.mg = float(load.mass * GRAVITY)
        self.com = np.ascontiguousarray(load.com, dtype=float)
        self.tare_load = np.zeros(6)
        self._kernel = contact_wrench
        self.inertial = bool(inertial)
        self.inertia = np.ascontiguousarray(load.inertia if load.inertia is not None else np.zeros(3), dtype=float)
        from tergodic_cli.robot.kernels import N_DY

        self.dyn = np.zeros(N_DY)  # the last sample's velocities (kernels.inertial_wrench)

    def _load(self, R_base_ee: np.ndarray) -> np.ndarray:
        """The tool load (6,) in the sensor frame at this orientation (the reading of a free, still tool, untared)."""
        from tergodic_cli.robot.kernels import tool_load

        out = np.empty(6)
        tool_load(np.asarray(R_base_ee, dtype=float), self.R_se_m, self.mg, self.com, out)
        return out

    def tare_at(self, R_base_ee: np.ndarray) -> None:
        """Record the tool's orientation at the tare; call right after :meth:`WrenchSensor.tare`, tool at rest and free.

        Parameters
        ----------
        R_base_ee : (3, 3) float
            The end effector's rotation in the base frame.
        """
        self.tare_load = self._load(np.asarray(R_base_ee, dtype=float).reshape(3, 3))

    def __call__(self, reading, R_base_ee, state=None) -> np.ndarray:
        """(6,) wrench (f, m) the tool applies to the environment, ee frame, moment about the TCP.

        ``reading`` is the sensor's (6,) wrench (array or 6-tuple); ``R_base_ee`` the (3, 3) TCP
        rotation (or the (4, 4) pose, or 9 row-major floats); ``state`` the :class:`ArmState` of
        the same tick (t, jacobian, dq), for the inertial compensation (ignored unless ``inertial``).
        """
        R = R_base_ee if isinstance(R_base_ee, np.ndarray) else np.asarray(R_base_ee, dtype=float).reshape(3, 3)
        out = np.empty(6)
        r = np.asarray(reading, dtype=float)
        if self.inertial and state is not None:
            from tergodic_cli.robot.kernels import contact_wrench_dyn

            T = state.ee_pose
            contact_wrench_dyn(r, float(state.t), T, np.ascontiguousarray(state.jacobian, dtype=float),
                               np.ascontiguousarray(state.dq, dtype=float), self.R_se_m, self.p_se_v, self.mg, self.com,
                               self.tare_load, float(self.load.mass), self.inertia, self.dyn, out)
            return out
        self._kernel(r, R, self.R_se_m, self.p_se_v, self.mg, self.com, self.tare_load, out)
        return out
