"""What a real arm is commanded with: a Cartesian impedance target on the agent's line.

Python cannot close a 1 kHz torque loop with real-time guarantees, so the line controller's stiffness
and damping run inside the SDK's loop (franky's Cartesian impedance) and Python streams references at
``stream_hz``; the normal force is realised through the spring offset f / k_n along the line, trimmed by
a slow integral on the measured force (:class:`ForceLoop`). The mapping: docs/hardware.md, "The
impedance reference on the agent's line".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from tergodic_cli.config import Config
from tergodic_cli.robot.ga import pose_matrix, tool_rotation
from tergodic_cli.robot.interfaces import ArmState


@dataclass
class ImpedanceTarget:
    """One impedance reference, base frame, SI units.

    pose : (4, 4) target TCP pose.
    stiffness, damping : (6, 6) on (x, y, z, rx, ry, rz) errors, N/m, N m/rad; N s/m, N m s/rad.
    twist : (6,) target TCP twist (v, ω), m/s and rad/s.
    """

    pose: np.ndarray
    stiffness: np.ndarray
    damping: np.ndarray
    twist: np.ndarray = field(default_factory=lambda: np.zeros(6))


@runtime_checkable
class ImpedanceArm(Protocol):
    """An arm whose real-time loop runs in the SDK: references instead of torques (the device behind
    :class:`~tergodic_cli.backends.streamed.StreamedArm`), which the SDK tracks at 1 kHz.
    """

    name: str
    joint_names: list[str]
    #: (dof,) joint limits: rad, rad, rad/s
    q_min: np.ndarray
    q_max: np.ndarray
    dq_max: np.ndarray
    #: (dof,) the picture posture, rad, when the run's config gives none
    home: np.ndarray
    #: rate (Hz) at which the host streams references to the SDK
    stream_hz: float

    def connect(self) -> None:
        """Open the connection (idempotent)."""

    def read_state(self) -> ArmState:
        """The arm's state now.

        Returns
        -------
        ArmState
            Joint positions (rad), velocities (rad/s), the TCP pose and Jacobian (base frame).
        """

    def disconnect(self) -> None:
        """Close the connection, the arm at rest."""

    def move_joints(self, q: np.ndarray, speed: float | None = None) -> None:
        """Blocking joint-space move, planned by the SDK.

        Parameters
        ----------
        q : (7,) float
            Joint positions, rad.
        speed : float, optional
            Share in (0, 1] of the SDK's speed limits; None = its default.
        """

    def command_impedance(self, target: ImpedanceTarget) -> None:
        """Start, or update, the Cartesian impedance controller with a new reference.

        Parameters
        ----------
        target : ImpedanceTarget
            Pose, stiffness, damping and feed-forward twist (base frame, SI units).
        """

    def stop(self) -> None:
        """Bring the arm to rest and end any running controller (blocking)."""

    def fault(self) -> str | None:
        """The SDK's error, if any.

        Returns
        -------
        str or None
            A one-line reason (reflex, lost connection), or None.
        """


@dataclass
class LineImpedanceGains(Config):
    """The line controller's stiffness and damping for an SDK impedance loop (defaults = the simulation's).

    k_lateral, k_normal : N/m across the line and along it (the normal value sets the spring offset
        f / k_normal that realises the force). k_tilt, k_spin : N m/rad about the tool's x/y axes and
        about its own axis (a line leaves the spin free: a weak spring holds it). Damping the same.
    force_ki : 1/s, integral gain of the force trim; force_trim_max : the trim stays within
        ± force_trim_max × F_d.
    """

    k_lateral: float = 1500.0
    k_normal: float = 300.0
    k_tilt: float = 30.0
    k_spin: float = 5.0
    d_lateral: float = 60.0
    d_normal: float = 50.0
    d_tilt: float = 4.0
    d_spin: float = 1.0
    force_ki: float = 2.0
    force_trim_max: float = 1.0


def line_impedance_target(p_tcp: np.ndarray, a: np.ndarray, d: np.ndarray, x_ref: np.ndarray, force: float,
                          gains: LineImpedanceGains, line_velocity: np.ndarray | None = None,
                          axial: float | None = None, axial_speed: float = 0.0) -> ImpedanceTarget:
    """The impedance reference that holds the tool on the line (a, d) and presses with ``force`` N along d.

    Parameters
    ----------
    p_tcp : (3,) present TCP position, m, base frame.
    a, d : (3,) a point of the agent's line and its unit direction into the surface.
    x_ref : (3,) spin reference for the tool's x-axis.
    force : N along d the spring offset realises (0 = just hold the line).
    line_velocity : (3,) velocity of the line point a, m/s (feed-forward twist across the line); None = 0.
    axial : position along the line (m from a, along d) for the target instead of riding with the TCP
        (approach and retreat: a target that advances at ``axial_speed`` m/s finds the surface whatever
        the joint friction, the spring force building up k_n · overshoot); ``force`` is then ignored.

    Returns
    -------
    ImpedanceTarget
        Pose (4, 4), stiffness and damping (6, 6), twist (6,), base frame.
    """
    g = gains
    R = tool_rotation(d, x_ref)
    z = R[:, 2]
    a = np.asarray(a, dtype=float)
    s = float((np.asarray(p_tcp, dtype=float) - a) @ z)
    at = a + (s + force / g.k_normal) * z if axial is None else a + float(axial) * z
    ref = hold_target(pose_matrix(R, at), g)
    if line_velocity is not None:
        v = np.asarray(line_velocity, dtype=float)
        ref.twist[:3] = v - (v @ z) * z  # along the line the target rides with the TCP
    ref.twist[:3] += axial_speed * z
    return ref


def hold_target(pose: np.ndarray, gains: LineImpedanceGains) -> ImpedanceTarget:
    """A reference that holds a pose with the line gains in every direction (k_normal along the tool axis).

    Gains along the tool's x, y, z, in the base frame: blockdiag(R diag(trans) Rᵀ, R diag(rot) Rᵀ).

    Parameters
    ----------
    pose : (4, 4) float
        The TCP pose to hold, base frame, m.
    gains : LineImpedanceGains

    Returns
    -------
    ImpedanceTarget
    """
    R, g = np.asarray(pose, dtype=float)[:3, :3], gains
    K, D = np.zeros((6, 6)), np.zeros((6, 6))
    for G, tr, rot in ((K, (g.k_lateral, g.k_lateral, g.k_normal), (g.k_tilt, g.k_tilt, g.k_spin)),
                       (D, (g.d_lateral, g.d_lateral, g.d_normal), (g.d_tilt, g.d_tilt, g.d_spin))):
        G[:3, :3] = R @ np.diag(tr) @ R.T
        G[3:, 3:] = R @ np.diag(rot) @ R.T
    return ImpedanceTarget(np.array(pose, dtype=float), K, D)


class ForceLoop:
    """The commanded normal force: F_d plus a slow integral trim on the measured force (clamped).

    f_cmd = F_d + ki ∫ (F_d - f_meas) dt, |trim| <= trim_max · F_d.
    """

    def __init__(self, gains: LineImpedanceGains, force_desired: float):
        self.g = gains
        self.F_d = float(force_desired)
        self.trim = 0.0

    def start_from(self, f_now: float) -> None:
        """Bumpless start: the command continues from the force pressed now (e.g. at first contact).

        Without an integrator (force_ki = 0) there is nothing to ramp the trim back: the command is F_d.

        Parameters
        ----------
        f_now : float
            The measured contact force, N.
        """
        lim = self.g.force_trim_max * self.F_d
        self.trim = 0.0 if self.g.force_ki <= 0 else min(max(float(f_now) - self.F_d, -lim), lim)

    def track(self, f_meas: float, dt: float) -> float:
        """One step of the integral trim.

        Parameters
        ----------
        f_meas : float
            Measured contact force along the tool axis, N (NaN: no sample, the trim holds).
        dt : float
            Seconds since the last step.

        Returns
        -------
        float
            The force to command, N (>= 0).
        """
        if math.isfinite(f_meas):
            lim = self.g.force_trim_max * self.F_d
            self.trim = min(max(self.trim + self.g.force_ki * (self.F_d - f_meas) * dt, -lim), lim)
        return max(self.F_d + self.trim, 0.0)
