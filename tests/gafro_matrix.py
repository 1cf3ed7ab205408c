"""Test-only matrix forms of the CGA products and pygafro's Franka Jacobians (paper eqs. 15-16, 42-45).

The run never forms them: its 1 kHz loop computes the Jacobian compiled (``kernels.fk_jacobian``) and
applies J^eeᵀ as Jᵀ R (``kernels.line_force_step``). The tests check those against these, and these
against pygafro and PyBullet.
"""

from __future__ import annotations

import numpy as np

from tergodic_cli.robot.ga import motor_inverse


def skew(a: np.ndarray) -> np.ndarray:
    """The (3, 3) matrix [a]× with [a]× b = a × b."""
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def adjoint(T: np.ndarray) -> np.ndarray:
    """6×6 adjoint of the motor T acting on twists (v, ω): the matrix of M V M̃."""
    R, t = T[:3, :3], T[:3, 3]
    return np.block([[R, skew(t) @ R], [np.zeros((3, 3)), R]])


def twist_from_gafro(c: np.ndarray) -> np.ndarray:
    """(v, ω) of pygafro Twist coefficients [e12, e13, e23, e1∞, e2∞, e3∞]."""
    return np.array([c[3], c[4], c[5], c[2], -c[1], c[0]])


def jacobian_spatial(model, q: np.ndarray) -> np.ndarray:
    """(6, 7) geometric Jacobian J_G (eqs. 15-16) of a :class:`~tergodic_cli.backends.franka.gafro.FrankaModel`:
    columns are the joint screws B'_i as base-frame twists (v at the base origin, ω)."""
    cols = model.robot.getEEGeometricJacobian(np.asarray(q, dtype=float))
    return np.column_stack([twist_from_gafro(np.asarray(c.vector())) for c in cols])


def jacobian_ee(model, q: np.ndarray) -> np.ndarray:
    """(6, 7) ee-frame Jacobian J_G^ee = M̃ J_G M (eq. 45) at the model's TCP, rows (v, ω) in the TCP frame."""
    return adjoint(motor_inverse(model.fk(q))) @ jacobian_spatial(model, q)


def jacobian_base(model, q: np.ndarray) -> np.ndarray:
    """(6, 7) base-frame Jacobian at the TCP point (v of the TCP, ω), like PyBullet's calculateJacobian."""
    R = model.fk(q)[:3, :3]
    Je = jacobian_ee(model, q)
    return np.vstack([R @ Je[:3], R @ Je[3:]])
