"""The Franka Panda's kinematics with pygafro (the Panda's own, so in its folder): motor forward
kinematics (eq. 14); its geometric and ee-frame Jacobians (eqs. 15-16, 42-45) are formed by the tests only (tests/gafro_matrix.py): the loop computes
them compiled (``kernels.fk_jacobian``); inverse kinematics is :func:`~tergodic_cli.robot.reach.ik`.

pygafro's ``FrankaEmikaRobot`` ends at the Franka hand's TCP (flange + 0.1034 m, rotated -45°
about z). Our TCP is the sponge tip, a fixed motor further along the same z-axis; the offset
is measured once against the backend (:func:`tool_offset`) and checked to be a pure z shift.

These run at set-up (the TCP path of a joint move) and in tests, never in the 1 kHz loop: one pygafro
Jacobian costs 57 µs against 1.2 µs compiled (docs/robot.md, "Why matrix form").
"""

from __future__ import annotations

import numpy as np

from tergodic_cli.errors import TergodicError
from tergodic_cli.robot.ga import motor_inverse

class FrankaModel:
    """pygafro's Franka Emika model with a fixed tool motor appended."""

    def __init__(self, tool: np.ndarray | None = None):
        import pygafro

        self.robot = pygafro.FrankaEmikaRobot()
        self.tool = np.eye(4) if tool is None else np.asarray(tool, dtype=float)
        self.q_min = np.asarray(self.robot.getJointLimitsMin(), dtype=float)
        self.q_max = np.asarray(self.robot.getJointLimitsMax(), dtype=float)

    def flange_motor(self, q: np.ndarray) -> np.ndarray:
        """(4, 4) pose of gafro's end-effector (the Franka hand TCP) in the base frame: M(q), eq. 14."""
        M = self.robot.getEEMotor(np.asarray(q, dtype=float))
        return np.asarray(M.toTransformationMatrix(), dtype=float)

    def fk(self, q: np.ndarray) -> np.ndarray:
        """(4, 4) pose of our TCP in the base frame."""
        return self.flange_motor(q) @ self.tool


def tool_offset(model: FrankaModel, q: np.ndarray, T_tcp: np.ndarray) -> np.ndarray:
    """The fixed motor from gafro's end-effector to the backend's TCP, measured at ``q``.

    Refuses anything but a shift along the hand's z-axis: another offset means gafro's Franka
    and the backend's URDF disagree.
    """
    off = motor_inverse(model.flange_motor(q)) @ T_tcp
    if not (np.allclose(off[:3, :3], np.eye(3), atol=1e-4) and np.allclose(off[:2, 3], 0.0, atol=1e-4)):
        raise TergodicError("pygafro's Franka model does not match the simulated Panda's kinematics",
                            "check the pybullet and pygafro versions (pybullet 3.2.7, pygafro 1.3)")
    return off
