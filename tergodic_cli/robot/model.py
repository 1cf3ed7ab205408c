"""The arm as the robot layer sees it: :class:`ArmModel`, read from the arm's URDF by its backend.

The state machine, the safety guard, the line-force controller, the reach planner and the surface
code know an arm only through this model: its degrees of freedom, joint limits (position, velocity,
effort), the kinematic chain from the base to the TCP, the posture it starts from, and the links the
collision checks watch. No arm's constants live in the robot layer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ArmModel:
    """One serial arm with its tool.

    name : the arm's registry name (``--arm``).
    joint_names : (n,) the movable joints, base to tip.
    q_min, q_max : (n,) joint position limits, rad. dq_max : (n,) joint speed limits, rad/s.
    tau_max : (n,) joint torque limits, N m.
    home : (n,) the picture ("ready") posture, rad: a wrist camera sees the table in front of the robot.
    chain : (F (m, 4, 4), axis (m, 3), qidx (m,), tcp_off (3,)): the chain base -> TCP as
        :func:`~tergodic_cli.robot.kernels.fk_jacobian` wants it (link frames at zero joint angles,
        joint axes, index of each link's joint into q or -1 for a fixed joint, the TCP in the last link).
    links : names of the links whose collision shapes the whole-arm checks watch, base to tool.
    """

    name: str
    joint_names: tuple[str, ...]
    q_min: np.ndarray
    q_max: np.ndarray
    dq_max: np.ndarray
    tau_max: np.ndarray
    home: np.ndarray
    chain: tuple
    links: tuple[str, ...] = ()

    @property
    def dof(self) -> int:
        """The number of movable joints n."""
        return len(self.joint_names)

    def fk(self, q: np.ndarray) -> np.ndarray:
        """(4, 4) the TCP's pose in the base frame at joints ``q`` (n,) (compiled chain)."""
        from tergodic_cli.robot.kernels import fk_jacobian

        T, J = np.empty((4, 4)), np.empty((6, self.dof))
        fk_jacobian(np.asarray(q, dtype=float), *self.chain, T, J)
        return T


__all__ = ["ArmModel"]
