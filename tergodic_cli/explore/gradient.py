"""Gradient of a point-sampled field by a weighted least-squares cubic (paper eqs. 32-33).

The neighbours' tangent-plane coordinates (u, v) (metres, origin at the agent's projected
position) and their field values are fitted by

    f(u, v) = c0 + c1 u + c2 v + c3 u² + c4 uv + c5 v² + c6 u³ + c7 u²v + c8 uv² + c9 v³

with weights W = diag(φ(r_i)), and the gradient is the polynomial's analytic derivative
in both directions (:func:`cubic_gradient`). At the origin it is simply (c1, c2).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg.lapack import dposv

N_COEFFS = 10
_DEGREES = np.array([0, 1, 1, 2, 2, 2, 3, 3, 3, 3], dtype=float)


def cubic_design(uv: np.ndarray) -> np.ndarray:
    """Monomials of the cubic above.

    Parameters
    ----------
    uv : (k, 2) float
        Tangent coordinates, metres.

    Returns
    -------
    (k, 10) float
    """
    u, v = uv[:, 0], uv[:, 1]
    uu, vv, uv_ = u * u, v * v, u * v
    return np.column_stack([np.ones_like(u), u, v, uu, uv_, vv, uu * u, uu * v, u * vv, vv * v])


def fit_cubic(uv: np.ndarray, values: np.ndarray, weights: np.ndarray | None = None, degree: int = 3) -> np.ndarray:
    """Weighted least-squares cubic through samples on a tangent patch.

    Coordinates are scaled by the patch radius before solving so the normal equations stay
    well conditioned; the returned coefficients are for unscaled (metre) coordinates. With
    fewer than 10 well-placed samples the minimum-norm solution is returned. ``degree=1``
    fits a plane instead (the higher coefficients are zero): the safe choice when the
    evaluation point lies outside the samples, where a cubic extrapolates wildly.

    Parameters
    ----------
    uv : (k, 2) float
        Tangent coordinates, metres.
    values : (k,) float
        Samples.
    weights : (k,) float, optional
        Least-squares weights; None = 1.
    degree : int
        3 (cubic) or 1 (plane).

    Returns
    -------
    (10,) float
        Coefficients for metre coordinates.
    """
    rho = float(np.sqrt(np.max(np.einsum("ij,ij->i", uv, uv)))) if len(uv) else 0.0
    if rho == 0.0:
        return np.zeros(N_COEFFS)
    X = cubic_design(uv / rho)
    if degree == 1:
        X = X[:, :3]
    XtW = X.T if weights is None else X.T * weights
    # Normal equations by Cholesky (fast); a singular or badly conditioned layout (too few or
    # collinear neighbours) falls back to the SVD minimum-norm least-squares solution.
    chol, coef, info = dposv(XtW @ X, XtW @ values)
    diag = np.abs(np.diagonal(chol)) if info == 0 else None
    # (max/min of the Cholesky diagonal)² is a cheap lower bound of the condition number.
    if info != 0 or not np.all(np.isfinite(coef)) or diag.min() * 1e6 < diag.max():
        sw = np.ones(len(uv)) if weights is None else np.sqrt(weights)
        coef, *_ = np.linalg.lstsq(X * sw[:, None], values * sw, rcond=1e-10)
    if degree == 1:
        coef = np.concatenate([coef, np.zeros(N_COEFFS - 3)])
    # Undo the scaling: a monomial of degree d was evaluated at (u/rho), so divide by rho^d.
    return coef / rho**_DEGREES


def cubic_gradient(coef: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Analytic gradient of a cubic.

    Parameters
    ----------
    coef : (10,) float
    uv : (k, 2) float
        Metres.

    Returns
    -------
    (k, 2) float
        (∂f/∂u, ∂f/∂v), per metre.
    """
    c = coef
    u, v = uv[:, 0], uv[:, 1]
    du = c[1] + 2 * c[3] * u + c[4] * v + 3 * c[6] * u * u + 2 * c[7] * u * v + c[8] * v * v
    dv = c[2] + c[4] * u + 2 * c[5] * v + c[7] * u * u + 2 * c[8] * u * v + 3 * c[9] * v * v
    return np.column_stack([du, dv])


def cubic_value(coef: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Values of a cubic.

    Parameters
    ----------
    coef : (10,) float
    uv : (k, 2) float
        Metres.

    Returns
    -------
    (k,) float
    """
    return cubic_design(uv) @ coef
