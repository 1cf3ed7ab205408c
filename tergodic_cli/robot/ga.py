"""Conformal geometric algebra of the line-tracking controller (paper eqs. 13-17, 35-47), in matrix form.

The paper writes the controller with CGA motors, lines, twists and wrenches. pygafro's line motor
costs 9 µs a call and its Jacobian 57 µs, and numba cannot call it (docs/robot.md, "Why matrix
form"), so the 1 kHz loop evaluates the same products in their matrix form, as the paper itself
notes (V-A3): a motor is a rigid transform (R, t), a line is a Plücker pair (d, m), twists and
wrenches are 6-vectors transformed by 6×6 adjoints. tests/test_robot_ga.py maps each quantity to
pygafro's coefficient vectors (their blade orders are written there) and checks every product.

Conventions (all SI, right-handed)
----------------------------------
- twist   V = (v, ω): v the velocity of the frame origin, ω the angular velocity.
- wrench  W = (f, m): f the force, m the moment about the frame origin
  (``fx fy fz tx ty tz``, the order of CONTRACTS.md).
- power   V·W = v·f + ω·m. In CGA the inner product of a twist and a wrench is -p (III-B).
- motor   M ≅ (R, t): x ↦ R x + t. gafro's exponential and logarithm use the decoupled chart
  M = T(t) R(φ): ``log M = (t, φ)`` with φ the rotation vector of R (this is what
  ``pygafro.MotorLogarithm`` returns; it is not the screw logarithm).
- line    L ≅ (d, m): unit direction d and moment m = a × d for any point a on the line;
  L = P1 ∧ P2 ∧ e∞ is oriented from P1 to P2.
"""

from __future__ import annotations

import math

import numpy as np

from tergodic_cli.rotations import matrix_to_quat, quat_to_matrix  # noqa: F401  (re-exported)

# ---------------------------------------------------------------------------------- rotations


def rotvec_to_matrix(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of the rotation vector ``phi`` (3,) in radians (scipy's Rotation)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(phi, dtype=float)).as_matrix()


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) of the rotation matrix ``R`` (3, 3); angle in [0, π]. (Also compiled: kernels.matrix_to_rotvec.)"""
    R = np.asarray(R, dtype=np.float64)  # np.float64, not float: numba compiles this function too
    c = max(-1.0, min(1.0, 0.5 * (float(np.trace(R)) - 1.0)))
    theta = math.acos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-7:
        return 0.5 * w
    if math.pi - theta < 1e-5:  # near π the antisymmetric part vanishes; use the symmetric part
        B = 0.5 * (R + np.eye(3))
        axis = np.sqrt(np.maximum(np.diag(B), 0.0))
        i = int(np.argmax(axis))
        axis = B[i] / axis[i]
        axis /= np.linalg.norm(axis)
        if w @ axis < 0:
            axis = -axis
        return theta * axis
    return theta / (2.0 * math.sin(theta)) * w


# ---------------------------------------------------------------------------------- motors


def pose_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Homogeneous (4, 4) transform of the motor (R, t)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def motor_inverse(T: np.ndarray) -> np.ndarray:
    """The reverse motor M̃ as a (4, 4) transform: (Rᵀ, -Rᵀ t)."""
    R, t = T[:3, :3], T[:3, 3]
    return pose_matrix(R.T, -R.T @ t)


# ---------------------------------------------------------------------------------- lines


def tool_rotation(d: np.ndarray, x_ref: np.ndarray) -> np.ndarray:
    """The tool's rotation for a line direction.

    Falls back to base +z, then +y, when x_ref is (nearly) parallel to d.

    Parameters
    ----------
    d : (3,) float
        Unit tool axis (into the surface), base frame.
    x_ref : (3,) float
        Reference for the tool's x-axis.

    Returns
    -------
    (3, 3) float
        Rotation [x, y, z] with z = d and x the part of x_ref perpendicular to d.
    """
    z = np.asarray(d, dtype=float)
    z = z / np.linalg.norm(z)
    for c in (np.asarray(x_ref, dtype=float), np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0])):
        x = c - (c @ z) * z
        n = float(np.linalg.norm(x))
        if n > 1e-3:
            x = x / n
            return np.column_stack([x, np.cross(z, x), z])
    raise ValueError("no spin reference perpendicular to the tool axis")


def point_line_distance(x: np.ndarray, a: np.ndarray, d: np.ndarray) -> float:
    """Distance (m) from the point ``x`` to the line through ``a`` with unit direction ``d``."""
    r = np.asarray(x, dtype=float) - a
    return float(np.linalg.norm(r - (r @ d) * d))


#: Lines closer to parallel than this (sin of the angle) are treated as parallel.
PARALLEL_SIN = 1e-9


def line_motor_z(ax: float, ay: float, az: float, dx: float, dy: float, dz: float) -> tuple:
    """The motor M_{L_ee L_a⊥} (eq. 36) in the end-effector frame, where L_ee is the z-axis.

    It is the smallest screw taking the z-axis onto the line through ``a`` with unit direction
    ``d`` (both in the ee frame): a rotation by the angle between the directions about their
    common perpendicular, and a slide along it by the lines' distance, as (1 + L_a L_ee)/C
    of ref. [54] (checked against ``pygafro.Line.getMotor`` in the tests). Plain floats in and
    out: the 1 kHz loop compiles it (``kernels.line_motor_z``).

    Parameters
    ----------
    ax, ay, az : float
        A point on the target line, metres, ee frame.
    dx, dy, dz : float
        Its unit direction, ee frame.

    Returns
    -------
    (tx, ty, tz, φx, φy, φz) : tuple of float
        The motor in gafro's decoupled chart, t metres and the rotation vector φ radians; its
        logarithm is the twist (t, φ) of eq. 37.
    """
    # c = e_z × d; sθ = |c|, cθ = e_z · d.
    cx, cy = -dy, dx
    s = math.sqrt(cx * cx + cy * cy)
    if s < PARALLEL_SIN:
        # Parallel lines: the motor is the translation between them, perpendicular to z.
        # (Anti-parallel lines have no unique smallest motor; the caller keeps d near +z.)
        return ax, ay, 0.0, 0.0, 0.0, 0.0
    ux, uy = cx / s, cy / s  # rotation axis direction, perpendicular to z
    c = dz
    theta = math.atan2(s, c)
    # Closest points: P(σ) = σ e_z on L_ee, Q(τ) = a + τ d on L_a.
    w_d = -(ax * dx + ay * dy + az * dz)  # d · (P(0) - Q(0))
    w_z = -az  # e_z · (P(0) - Q(0))
    denom = s * s
    sigma = (c * w_d - w_z) / denom
    tau = (w_d - c * w_z) / denom
    qx, qy = ax + tau * dx, ay + tau * dy
    delta = qx * ux + qy * uy  # signed distance along u (u has no z component; P(σ) has no x, y)
    # Rotation by θ about u through c1 = σ e_z, then slide δ along u: t = c1 - R c1 + δ u,
    # and R e_z = d (the rotation maps the ee axis onto the target direction), so R c1 = σ d.
    return (-sigma * dx + delta * ux, -sigma * dy + delta * uy, sigma - sigma * dz, theta * ux, theta * uy, 0.0)
