"""Universal Robots e-Series arms as the robot layer sees them (:class:`~tergodic_cli.robot.model.ArmModel`).

Every UR constant lives here. Kinematics: Universal Robots' published DH parameters of each model
(the "DH parameters for calculations of kinematics and dynamics" table: d1, a2, a3, d4, d5, d6 in m,
α = (π/2, 0, 0, π/2, -π/2, 0)), which is the base and flange frame the controller reports poses in
(``getActualTCPPose``). Limits from the e-Series datasheets: every joint ±360° (±2π rad); joint
speeds and the joints' rated torques by joint size (size 4: 330 N m at 120°/s, size 3: 150 N m at
180°/s, size 2: 56 N m at 180°/s, size 1: 28 N m at 180°/s, size 0: 12 N m at 360°/s).
"""

from __future__ import annotations

import math

import numpy as np

from tergodic_cli.errors import require
from tergodic_cli.robot.model import ArmModel

JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint")
ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
_SIZE = {4: (330.0, math.radians(120)), 3: (150.0, math.radians(180)), 2: (56.0, math.radians(180)),
         1: (28.0, math.radians(180)), 0: (12.0, math.radians(360))}
#: model -> (d1, a2, a3, d4, d5, d6) m, and the joint sizes base to tip.
MODELS = {
    "ur3e": ((0.15185, -0.24355, -0.2132, 0.13105, 0.08535, 0.0921), (2, 2, 1, 0, 0, 0)),
    "ur5e": ((0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996), (3, 3, 3, 1, 1, 1)),
    "ur10e": ((0.1807, -0.6127, -0.57155, 0.17415, 0.11985, 0.11655), (4, 4, 3, 2, 2, 2)),
}
#: The picture posture (rad): the tool points straight down, its TCP ~0.49 m in front of the base (-x) and 0.49 m up (UR5e).
HOME = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)


def dh_parameters(model: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(d (6,), a (6,), α (6,)) of ``model``, m and rad (standard DH: Rz(θ) Tz(d) Tx(a) Rx(α))."""
    require(model in MODELS, f"unknown UR model '{model}'", f"use one of {', '.join(MODELS)}")
    (d1, a2, a3, d4, d5, d6), _ = MODELS[model]
    return np.array([d1, 0, 0, d4, d5, d6]), np.array([0, a2, a3, 0, 0, 0]), np.array(ALPHA)


def _dh_frame(d: float, a: float, alpha: float) -> np.ndarray:
    ca, sa = math.cos(alpha), math.sin(alpha)
    return np.array([[1, 0, 0, a], [0, ca, -sa, 0], [0, sa, ca, d], [0, 0, 0, 1.0]])  # Tz(d) Tx(a) Rx(α)


def ur_model(model: str = "ur5e", tool_length: float = 0.0) -> ArmModel:
    """The :class:`ArmModel` of a UR ``model`` with a tool ``tool_length`` m along the flange's z.

    The chain (:func:`~tergodic_cli.robot.kernels.fk_jacobian`): joint i turns about its frame's z, then
    the fixed DH step Tz(d_i) Tx(a_i) Rx(α_i) leads to the next joint; the TCP sits on the flange's z.
    """
    d, a, al = dh_parameters(model)
    F = np.stack([np.eye(4)] + [_dh_frame(d[i], a[i], al[i]) for i in range(6)])
    axis = np.tile([0.0, 0.0, 1.0], (7, 1))
    qidx = np.array([0, 1, 2, 3, 4, 5, -1])
    sizes = MODELS[model][1]
    tau_max = np.array([_SIZE[s][0] for s in sizes])
    dq_max = np.array([_SIZE[s][1] for s in sizes])
    return ArmModel(name=model, joint_names=JOINTS, q_min=np.full(6, -2 * math.pi), q_max=np.full(6, 2 * math.pi),
                    dq_max=dq_max, tau_max=tau_max, home=np.array(HOME),
                    chain=(np.ascontiguousarray(F), np.ascontiguousarray(axis), qidx, np.array([0.0, 0.0, float(tool_length)])))
