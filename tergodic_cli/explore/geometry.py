"""Local surface geometry by the paper's conformal-geometric-algebra fit (eqs. 23-29).

A conformal point is P = e0 + x + ½|x|² e∞ (eq. 8), with e0·e∞ = -1. A dual sphere or
plane is X* = v1 e1 + v2 e2 + v3 e3 + v∞ e∞ + v0 e0 (eq. 26), so that

    P · X* = x·(v1, v2, v3) - v∞ - ½|x|² v0 = w(x) · v,   w(x) = (x, -1, -½|x|²)   (eq. 25)

is an algebraic distance of x to the primitive. Minimising Σ (P_i · X*)² over |v| = 1 (eq. 23)
gives the eigenvector of the smallest eigenvalue of the 5×5 matrix B = Σ w_i w_iᵀ (eq. 24).
v0 = 0 is a plane (normal (v1, v2, v3), offset v∞); otherwise a sphere with centre
c = (v1, v2, v3)/v0 and radius² = |c|² - 2 v∞/v0.

The fit treats every orientation alike (no height field), so vertical walls work, and an
exactly flat patch gives v0 = 0 exactly. For conditioning the points are centred on their
centroid and scaled by their rms radius before the fit, and the result is mapped back.

The projection of eq. 27 (the point pair of the line through P and the primitive, split
into its nearer point) is evaluated in closed form: along the normal for a plane, radially
for a sphere. The normal line (eq. 28) is {x' + s n} and the tangent plane (eq. 29) is the
plane through x' with normal n.
"""

from __future__ import annotations

from dataclasses import dataclass

import math

import numpy as np
from scipy.linalg.lapack import dsyevd

#: A sphere whose radius exceeds this many rms patch radii is treated as its tangent plane
#: (its sagitta over the patch is below 1e-4 of the patch size, far below the sampling noise).
PLANE_RADIUS_RATIO = 1e4
#: A sphere smaller than this many rms patch radii is not a plausible surface through the
#: patch: the fit has latched onto noise, and the least-squares plane is used instead.
MIN_RADIUS_RATIO = 1.5


@dataclass(frozen=True)
class Primitive:
    """A fitted plane or sphere (metres).

    Attributes
    ----------
    kind : "plane" or "sphere".
    normal : (3,) unit normal of the plane (planes only).
    offset : plane offset d, the plane is {x : normal·x = d} (planes only).
    centre : (3,) sphere centre (spheres only).
    radius : sphere radius (spheres only).
    """

    kind: str
    normal: np.ndarray | None = None
    offset: float = 0.0
    centre: np.ndarray | None = None
    radius: float = 0.0


def conformal_rows(points: np.ndarray) -> np.ndarray:
    """The conformal rows of eq. 25.

    Parameters
    ----------
    points : (k, 3) float
        Metres.

    Returns
    -------
    (k, 5) float
        Rows w_i = (x, y, z, -1, -½|x|²).
    """
    w = np.empty((len(points), 5))
    w[:, :3] = points
    w[:, 3] = -1.0
    w[:, 4] = -0.5 * np.einsum("ij,ij->i", points, points)
    return w


def fit_primitive(points: np.ndarray) -> Primitive:
    """Least-squares plane or sphere through points (eqs. 23-26).

    Parameters
    ----------
    points : (k, 3) float
        Metres, k >= 4.

    Returns
    -------
    Primitive
        In the input frame (metres).
    """
    centroid = points.sum(axis=0) / len(points)
    y = points - centroid
    scale = math.sqrt(float(np.einsum("ij,ij->", y, y)) / len(y))
    if scale == 0.0:
        raise ValueError("all points of the patch coincide")
    y /= scale
    w = conformal_rows(y)
    _, vecs, info = dsyevd(w.T @ w)  # LAPACK directly: ascending eigenvalues, 5x faster than eigh's wrapper
    if info != 0:
        raise ValueError("the 5x5 eigenproblem did not converge")
    v = vecs[:, 0]
    n_raw, v_inf, v0 = v[:3], float(v[3]), float(v[4])
    n_norm = math.sqrt(float(n_raw @ n_raw))
    # Sphere radius in units of the patch scale; |v0| tiny means a plane (v0 = 0 exactly when flat).
    if abs(v0) * PLANE_RADIUS_RATIO > n_norm:
        c = n_raw / v0
        r2 = float(c @ c - 2.0 * v_inf / v0)
        if r2 > (MIN_RADIUS_RATIO) ** 2:
            return Primitive("sphere", centre=centroid + scale * c, radius=scale * float(np.sqrt(r2)))
        return _pca_plane(y, centroid, scale)
    if n_norm == 0.0:
        return _pca_plane(y, centroid, scale)
    n = n_raw / n_norm
    return Primitive("plane", normal=n, offset=float(n @ centroid + scale * v_inf / n_norm))


def _pca_plane(y: np.ndarray, centroid: np.ndarray, scale: float) -> Primitive:
    # The v0 = 0 restriction of eq. 23: minimise Σ (n·y_i - d)² with |n| = 1, i.e. the
    # direction of least variance; used when the sphere branch is degenerate.
    _, _, vt = np.linalg.svd(y, full_matrices=False)
    n = vt[-1]
    return Primitive("plane", normal=n, offset=float(n @ centroid))


def project_onto(prim: Primitive, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest point x' on the primitive to ``x`` (3,) (eq. 27) and the unit normal there.

    For a sphere the normal points away from the centre; for a plane it is the fitted
    normal. Orientation is the caller's business (see :func:`orient`).

    Parameters
    ----------
    prim : Primitive
    x : (3,) float
        Metres.

    Returns
    -------
    x_proj : (3,) float
        Metres.
    normal : (3,) float
        Unit.
    """
    if prim.kind == "plane":
        n = prim.normal
        return x - (n @ x - prim.offset) * n, n.copy()
    r = x - prim.centre
    dist = math.sqrt(float(r @ r))
    if dist < 1e-12 * max(prim.radius, 1e-300):
        raise ValueError("the point is at the centre of the fitted sphere; its projection is undefined")
    n = r / dist
    return prim.centre + prim.radius * n, n


def orient(normal: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``normal`` flipped, if needed, to have a non-negative dot product with ``reference``.

    Parameters
    ----------
    normal, reference : (3,) float

    Returns
    -------
    (3,) float
    """
    return -normal if normal @ reference < 0 else normal


def tangent_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A tangent frame.

    Parameters
    ----------
    normal : (3,) float
        Unit.

    Returns
    -------
    t1, t2 : (3,) float
        Unit vectors with (t1, t2, normal) a right-handed orthonormal frame.
    """
    # Cross with the world axis least aligned with the normal: never degenerate.
    # (Written out: np.cross costs ~30 µs per call, a real share of an explorer step.)
    nx, ny, nz = float(normal[0]), float(normal[1]), float(normal[2])
    ax, ay, az = abs(nx), abs(ny), abs(nz)
    if ax <= ay and ax <= az:  # n × e_x
        t1 = (0.0, nz, -ny)
    elif ay <= az:  # n × e_y
        t1 = (-nz, 0.0, nx)
    else:  # n × e_z
        t1 = (ny, -nx, 0.0)
    inv = 1.0 / math.sqrt(t1[0] * t1[0] + t1[1] * t1[1] + t1[2] * t1[2])
    a, b, c = t1[0] * inv, t1[1] * inv, t1[2] * inv
    t2 = (ny * c - nz * b, nz * a - nx * c, nx * b - ny * a)
    return np.array((a, b, c)), np.array(t2)


def normal_line(point: np.ndarray, normal: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Points of the normal line L_a⊥ (eq. 28).

    Parameters
    ----------
    point : (3,) float
        Metres.
    normal : (3,) float
        Unit.
    s : (m,) float
        Line parameters, metres.

    Returns
    -------
    (m, 3) float
        point + s·normal.
    """
    return point[None, :] + np.asarray(s, dtype=float)[:, None] * normal[None, :]


def tangent_distances(points: np.ndarray, origin: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Distances in the tangent plane (eqs. 29 and 31).

    Parameters
    ----------
    points : (k, 3) float
        Metres.
    origin : (3,) float
        Metres.
    normal : (3,) float
        Unit normal of the plane through ``origin``.

    Returns
    -------
    (k,) float
        Distances from ``origin`` to the projected points, metres.
    """
    d = points - origin
    off = d @ normal
    r2 = np.einsum("ij,ij->i", d, d) - off * off
    return np.sqrt(np.maximum(r2, 0.0))
