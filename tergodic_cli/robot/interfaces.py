"""The backends' interfaces: an :class:`Arm` driven by line targets, and a :class:`WrenchSensor`.

In the style of lerobot's ``robots/robot.py`` (the arm a Protocol, the sensor a base class): a
backend connects, is read, is commanded, disconnects. The state machine and the safety guard speak
only these, so a real Franka (franky) with a real F/T sensor (Bota, Net F/T) replaces the PyBullet
backend without touching them.

Conventions every backend honours
---------------------------------
- Frames: "base" is the robot base; "ee" is the tool centre point (TCP), z along the tool
  axis pointing out of the flange; the sensor frame is fixed in the ee frame
  (:attr:`WrenchSensor.frame_in_ee`).
- :meth:`WrenchSensor.read` returns the wrench the arm applies to the tool through the
  sensor, in the sensor frame, moment about the sensor origin, minus the tare offset. With
  the tool at rest and free it is the tool's weight; pressing on a surface adds the force
  the tool exerts on it. :class:`ToolLoad` removes the weight.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple, Protocol, runtime_checkable

import numpy as np

from tergodic_cli.errors import TergodicError, require

if TYPE_CHECKING:
    from tergodic_cli.robot.safety import Fault

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
    pos : the TCP position as 3 floats (m), made on first use, for scalar code at 1 kHz.
    """

    __slots__ = ("t", "q", "dq", "ee_pose", "jacobian", "_pos")

    def __init__(self, t: float, q: np.ndarray, dq: np.ndarray, ee_pose: np.ndarray,
                 jacobian: np.ndarray | None = None):
        self.t, self.q, self.dq, self.ee_pose, self.jacobian = t, q, dq, ee_pose, jacobian
        self._pos = None

    @property
    def pos(self) -> tuple:
        if self._pos is None:
            self._pos = tuple(self.ee_pose[:3, 3].tolist())
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


class LineTarget(NamedTuple):
    """The action the contact loop sends an :class:`Arm`: a line-impedance target (paper eq. 47).

    a, d : (3,) a point of the agent's line L_a⊥ and its unit direction into the surface, base frame.
    mode : "press" holds the tool on the line and presses ``force`` N along d (the wrench PID);
        "move" holds it on the line and moves it along d at ``speed`` m/s (negative: back off), a
        set-point advancing at that speed, so a steady push cannot make it touch faster.
    force : N, desired force along d ("press").
    speed : m/s along d ("move").
    v_line : (3,) velocity of the line point a, m/s (feed-forward), or None.
    """

    a: np.ndarray
    d: np.ndarray
    mode: str
    force: float = 0.0
    speed: float = 0.0
    v_line: np.ndarray | None = None


class Observation(NamedTuple):
    """One control period's reading: the arm's state, the F/T reading (None: not read) and the
    contact wrench (6,) the tool applies, ee frame, moment about the TCP (N, N m)."""

    state: ArmState
    reading: WrenchReading | None
    wrench: np.ndarray


@runtime_checkable
class Arm(Protocol):
    """An arm with its F/T sensor, driven by the contact loop (:mod:`tergodic_cli.robot.run`).

    In the style of lerobot's ``Robot``: connected on construction, read with
    :meth:`get_observation`, commanded with :meth:`send_action` (one control period of ``dt``
    seconds), closed with :meth:`disconnect`. The free-space moves and holds are the backend's
    own (joint impedance in simulation, the SDK's planner on hardware); every period they run is
    checked by the loop's ``check`` (the one :class:`~tergodic_cli.robot.safety.SafetyGuard`).
    A backend with ``fast`` True runs a whole explorer interval of "press" targets itself,
    ``follow(A, D, v_line)`` (the simulation's compiled 1 kHz loop, the same checks), returning
    as the loop's own ``_follow``.
    """

    name: str
    joint_names: list[str]
    #: s, one control period; (dof,) joint limits (rad, rad/s) for the guard.
    dt: float
    q_min: np.ndarray
    q_max: np.ndarray
    dq_max: np.ndarray
    #: s, the arm's clock now and at the start; N, the filtered force along the tool axis;
    #: (dof,) the last joint torques (commanded or measured), N m; (3,) the spin reference
    #: (base frame) the tool's x-axis is held near.
    t: float
    t_origin: float
    force: float
    tau: np.ndarray
    spin_ref: np.ndarray

    def bind(self, guard, tick_stats: np.ndarray, force_desired: float, threshold: float) -> None:
        """Share the loop's guard and per-tick statistics.

        Parameters
        ----------
        guard : SafetyGuard
            The loop's one guard (its limits also run inside a compiled interval).
        tick_stats : (N_TS,) float
            The loop's per-tick statistics (``kernels.tick_stats``), updated at every valid reading.
        force_desired, threshold : float
            F_d and the contact threshold, N.
        """

    def get_observation(self, sensor: bool = True) -> Observation:
        """Read the arm, and the F/T sensor.

        Parameters
        ----------
        sensor : bool
            False: the sensor is not read (``reading`` None, wrench 0; after a sensor fault).

        Returns
        -------
        Observation
            State, reading and contact wrench (ee frame, N and N m) of this period.
        """

    def send_action(self, target: LineTarget) -> None:
        """Realise ``target`` for one control period, from the last observation.

        Parameters
        ----------
        target : LineTarget
            The line (base frame, m), "press" with a force (N) or "move" at a speed (m/s).
        """

    def reach(self, T: np.ndarray) -> str | None:
        """Whether the TCP can reach a pose.

        Parameters
        ----------
        T : (4, 4) float
            TCP pose, base frame (m).

        Returns
        -------
        str or None
            None if reachable, else why not (one line).
        """

    def move_to(self, T: np.ndarray, check) -> Fault | None:
        """Move the TCP to a pose through free space, every period checked.

        Parameters
        ----------
        T : (4, 4) float
            TCP pose, base frame (m).
        check : callable
            ``check(observation) -> Fault | None``, the loop's guard.

        Returns
        -------
        Fault or None
            The first fault (the move stops there), or None.
        """

    def to_picture(self, check) -> Fault | None:
        """Move to the picture pose through free space.

        Parameters
        ----------
        check : callable
            ``check(observation) -> Fault | None``, the loop's guard.

        Returns
        -------
        Fault or None
            The first fault, or None.
        """

    def hold(self, seconds: float) -> None:
        """Hold the present pose, without checks and without the force.

        Parameters
        ----------
        seconds : float
            How long, s.
        """

    def tare(self) -> None:
        """Tare the F/T sensor (tool at rest, free): its load at this orientation becomes the zero."""

    def contact(self, obs: Observation) -> tuple[np.ndarray | None, float, float]:
        """Where, how hard and at what angle the tool touches.

        Parameters
        ----------
        obs : Observation
            This period's observation.

        Returns
        -------
        point : (3,) float or None
            Contact point, base frame (m); None: no contact.
        force : float
            Contact force, N.
        press_angle : float
            Degrees between the tool axis and the contact normal (0 when the backend cannot tell).
        """

    def link_poses(self) -> dict:
        """Poses of the arm's links for the log.

        Returns
        -------
        dict
            Link name -> (7,) position (m) and quaternion (x, y, z, w); {} when unknown.
        """

    def fault(self) -> str | None:
        """The arm's own error.

        Returns
        -------
        str or None
            A one-line reason if the arm reports an error (a reflex, a lost connection), else None.
        """

    def stop(self) -> None:
        """End any running controller, the arm at rest."""

    def summary(self) -> dict:
        """The backend's own summary extras.

        Returns
        -------
        dict
            Name -> JSON-able value.
        """

    def disconnect(self) -> None:
        """Close the connection; the arm is left holding still."""


class WrenchSensor:
    """A 6-axis force/torque sensor (the sign of its reading: see the module docstring).

    The base of every backend's sensor, in the style of lerobot's base classes. A backend gives
    ``frame_in_ee`` and overrides :meth:`read` and :meth:`tare`, or gives ``_sample() -> (t s,
    (6,) wrench)`` and is tared in software here: :meth:`tare` averages ``tare_samples`` samples
    into the offset :meth:`read` removes; ``bad_tare`` (problem, fix) refuses a tare over a
    non-finite sample (None: not checked).
    """

    #: (4, 4) pose of the sensor frame in the ee (TCP) frame.
    frame_in_ee: np.ndarray
    bad_tare: tuple[str, str] | None = None

    def __init__(self, frame_in_ee: np.ndarray | None = None, tare_samples: int = 50):
        self.frame_in_ee = np.asarray(np.eye(4) if frame_in_ee is None else frame_in_ee, float)
        require(self.frame_in_ee.shape == (4, 4), "frame_in_ee must be a (4, 4) transform",
                "give the sensor pose in the TCP frame")
        self.offset = np.zeros(6)
        self.tare_samples = int(tare_samples)

    def read(self) -> WrenchReading:
        """The latest sample, tare offset removed.

        Returns
        -------
        WrenchReading
            Force (N) and torque (N m) in the sensor frame, with its timestamp (s).
        """
        t, w = self._sample()
        return WrenchReading(t, w - self.offset)

    def tare(self) -> None:
        """Zero the reading (tool at rest, free): the wrench now is taken off every later one."""
        ws = np.array([self._sample()[1] for _ in range(self.tare_samples)])
        if self.bad_tare is not None and not np.all(np.isfinite(ws)):
            raise TergodicError(*self.bad_tare)
        self.offset = ws.mean(axis=0)


@dataclass
class ToolLoad:
    """Mass (kg) and centre of mass (3,) in the sensor frame of everything beyond the sensor, and
    its principal inertia (3,) about the centre of mass along the sensor axes, kg m² (for the
    inertial compensation; zeros: forces only)."""

    mass: float
    com: np.ndarray
    inertia: np.ndarray | None = None


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
        from tergodic_cli.robot import kernels  # lazily: numba is not loaded at CLI start-up

        self._kn = kernels
        self.load = load
        self.R_se_m = np.ascontiguousarray(np.asarray(frame_in_ee, dtype=float)[:3, :3])  # sensor -> ee
        self.p_se_v = np.ascontiguousarray(np.asarray(frame_in_ee, dtype=float)[:3, 3])  # sensor origin in the ee frame
        self.mg = float(load.mass * GRAVITY)
        self.com = np.ascontiguousarray(load.com, dtype=float)
        self.tare_load = np.zeros(6)
        self.inertial = bool(inertial)
        self.inertia = np.ascontiguousarray(load.inertia if load.inertia is not None else np.zeros(3), dtype=float)
        self.dyn = np.zeros(kernels.N_DY)  # the last sample's velocities (kernels.inertial_wrench)

    def tare_at(self, R_base_ee: np.ndarray) -> None:
        """Record the tool's orientation at the tare; call right after :meth:`WrenchSensor.tare`, tool at rest and free.

        Parameters
        ----------
        R_base_ee : (3, 3) float
            The end effector's rotation in the base frame.
        """
        R = np.asarray(R_base_ee, dtype=float).reshape(3, 3)
        self._kn.tool_load(R, self.R_se_m, self.mg, self.com, self.tare_load)

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
            J = np.ascontiguousarray(state.jacobian, dtype=float)
            dq = np.ascontiguousarray(state.dq, dtype=float)
            self._kn.contact_wrench_dyn(r, float(state.t), state.ee_pose, J, dq, self.R_se_m,
                                        self.p_se_v, self.mg, self.com, self.tare_load,
                                        float(self.load.mass), self.inertia, self.dyn, out)
        else:
            self._kn.contact_wrench(r, R, self.R_se_m, self.p_se_v, self.mg, self.com,
                                    self.tare_load, out)
        return out
