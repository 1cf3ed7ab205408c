"""The NumPy references of the explorer's numba kernels (tests only): the CGA fit, the cubic
gradient, the neutral coverage score and the authors' residual from full arrays.

Local surface geometry by the paper's conformal-geometric-algebra fit (eqs. 23-29).

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

Gradient of a point-sampled field by a weighted least-squares cubic (paper eqs. 32-33).

The neighbours' tangent-plane coordinates (u, v) (metres, origin at the agent's projected
position) and their field values are fitted by

    f(u, v) = c0 + c1 u + c2 v + c3 u² + c4 uv + c5 v² + c6 u³ + c7 u²v + c8 uv² + c9 v³

with weights W = diag(φ(r_i)), and the gradient is the polynomial's analytic derivative
in both directions (:func:`cubic_gradient`). At the origin it is simply (c1, c2).
"""

from __future__ import annotations

from dataclasses import dataclass

import math

import numpy as np
from scipy.linalg.lapack import dposv, dsyevd

from tergodic_cli.explore import metrics as M

#: A sphere whose radius exceeds this many rms patch radii is treated as its tangent plane
#: (its sagitta over the patch is below 1e-4 of the patch size, far below the sampling noise).
PLANE_RADIUS_RATIO = 1e4
#: A sphere smaller than this many rms patch radii is not a plausible surface through the
#: patch: the fit has latched onto noise, and the least-squares plane is used instead.
MIN_RADIUS_RATIO = 1.5
#: Two sheets (a wall's sides) are split where the neighbours' offsets along a normal line leave a
#: gap wider than this many mean spacings h (the explorer's sheet separation).
SHEET_GAP = 0.5
#: ... and a neighbour whose normal line is turned more than 60° from the nearest point's is on another face.
SHEET_COS = 0.5
#: ... or than this many times the cloud's noise, if wider.
SHEET_NOISE = 3.0


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


# ---------------------------------------------------------------------------------- metrics
def residual_ref(first_heat: np.ndarray, coverage: np.ndarray) -> float:
    """The authors' residual: ‖p̂ · [c̃ = 0]‖₂ / ‖p̂‖₂ with p̂ = u₁ / Σu₁ (plain sums and norms).

    [c̃ = 0] marks points the footprint never reached. Raw, unnormalised coverage makes any
    touched point count as done.

    Parameters
    ----------
    first_heat : (n,) float
        The heat u after the first step.
    coverage : (n,) float
        Raw coverage c̃.

    Returns
    -------
    float
        Dimensionless, in [0, 1].
    """
    p_hat = first_heat / first_heat.sum()
    untouched = coverage == 0
    return float(np.linalg.norm(p_hat[untouched]) / np.linalg.norm(p_hat))


def coverage_score(points: np.ndarray, target: np.ndarray, positions: np.ndarray,
                   agent_radius: float, h: float) -> dict:
    """The neutral coverage score of a trajectory, from full arrays (the definition of
    :class:`tergodic_cli.explore.metrics.CoverageScore`).

    Parameters
    ----------
    points : (n, 3) cloud points P, metres.
    target : (n,) target weight p >= 0.
    positions : (T, 3) or (T, N, 3) agent positions X_t, metres (all agents' count).
    agent_radius : r_a, metres; the footprint is exp(-(2/r_a)² d²), d the 3-D distance.
    h : mean point spacing, metres.

    Returns
    -------
    dict: ``ergodicity`` ε = ‖max(p̄ - c̄, 0)‖₂ / ‖p̄‖₂ with c_i = Σ_t exp(-(2/r_a)² |P_i - X_t|²)
    and p̄ = p/Σp, c̄ = c/Σc (dimensionless, 0 is perfect, 1 untouched); ``touched_fraction``
    (share of target points within r_a of some X_t); ``off_surface_fraction`` (share of positions
    more than 2h from every point or, when their neighbours hold more than one sheet, more than h/2
    from the local surface of the one sheet they are
    nearest to (or the sheet gap, if wider), :func:`sheet_distance`); ``step_max_m`` (largest |X_{t+1} - X_t| of one agent).
    """
    from scipy.spatial import cKDTree

    P = np.asarray(points, dtype=np.float64)
    X = np.asarray(positions, dtype=np.float64)
    steps = np.linalg.norm(np.diff(X, axis=0), axis=-1) if len(X) > 1 else np.zeros(1)
    X = X.reshape(-1, 3)
    k = (2.0 / agent_radius) ** 2
    c = np.zeros(len(P))
    for a in range(0, len(X), 256):
        d2 = ((P[:, None, :] - X[None, a:a + 256, :]) ** 2).sum(-1)
        c += np.exp(-k * d2).sum(1)
    p = np.asarray(target, dtype=np.float64)
    pbar = p / p.sum()
    cbar = c / c.sum() if c.sum() > 0 else c
    tree = cKDTree(P)
    near, _ = tree.query(X)
    hit = np.zeros(len(P), dtype=bool)
    for idx in tree.query_ball_point(X, agent_radius):
        hit[idx] = True
    T = p > 0
    eps = float(np.linalg.norm(np.maximum(pbar - cbar, 0.0)) / np.linalg.norm(pbar))
    normals, gap = sheet_gap(P, h)
    off = [d > M.OFF_SURFACE_H * h or sheet_distance(P, normals, x, gap, tree) > max(M.OFF_SHEET_H * h, gap)
           for x, d in zip(X, near)]
    return {"ergodicity": eps, "touched_fraction": float(hit[T].mean()),
            "off_surface_fraction": float(np.mean(off)),
            "step_max_m": float(steps.max())}


# ---------------------------------------------------------------------------------------- sheets
def split_sheet(points: np.ndarray, normals: np.ndarray, idx: np.ndarray, gap: float) -> np.ndarray:
    """The points of ``idx`` (nearest first) on the sheet of the first, in their order: those whose
    normal lines lie within 60° of its line, with offsets along its line in the run holding its
    own (0) after cutting the sorted offsets at every gap wider than ``gap`` (metres). Fewer than 3
    in it: all of ``idx``.
    """
    j0 = idx[0]
    par = np.abs(normals[idx] @ normals[j0]) >= SHEET_COS
    d = (points[idx] - points[j0]) @ normals[j0]
    srt = np.sort(d[par])
    cuts = np.flatnonzero(np.diff(srt) > gap)  # a cut between srt[c] and srt[c + 1]
    i0 = int(np.searchsorted(srt, 0.0))
    lo = srt[cuts[cuts < i0][-1] + 1] if np.any(cuts < i0) else srt[0]
    hi = srt[cuts[cuts >= i0][0]] if np.any(cuts >= i0) else srt[-1]
    keep = par & (d >= lo) & (d <= hi)
    return idx[keep] if 3 <= keep.sum() < len(idx) else idx


def _least_variance(y: np.ndarray) -> np.ndarray:
    return np.linalg.svd(y - y.mean(axis=0), full_matrices=False)[2][-1]


def sheet_gap(points: np.ndarray, h: float, k: int = 20, seed: int = 7) -> tuple[np.ndarray, float]:
    """The normal lines (:func:`sheet_normals`) and the sheet gap: h/2, or 3 times the cloud's noise
    when wider (a robust σ: the median over the points of the median absolute offset of their
    ``seed`` - 1 nearest from their plane, / 0.6745), with the lines fitted again for that gap."""
    gap = SHEET_GAP * h
    normals, mad = sheet_normals(points, gap, k, seed)
    if SHEET_NOISE * np.median(mad) / 0.6745 > gap:
        gap = SHEET_NOISE * float(np.median(mad)) / 0.6745
        normals, _ = sheet_normals(points, gap, k, seed)
    return normals, gap


def sheet_normals(points: np.ndarray, gap: float, k: int = 20, seed: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """Each point's normal line (unit, unoriented), fitted to its own sheet: of the planes through
    the point and two of its ``seed`` - 1 nearest, the one holding the most of its ``k`` nearest
    within gap/2; then twice the least-squares plane of those within gap/2 of the plane so far.
    And the median absolute offset of its ``seed`` - 1 nearest from its plane (metres)."""
    from scipy.spatial import cKDTree

    tol = 0.5 * gap
    mad = np.empty(len(points))
    _, nbs = cKDTree(points).query(points, k=min(k, len(points)))
    out = np.empty((len(points), 3))
    for j, nb in enumerate(nbs):
        nb = np.concatenate([[j], nb[nb != j]])[: len(nb)]
        rel = points[nb] - points[j]
        best, normal = -1, None
        for a in range(1, seed):
            for b in range(a + 1, seed):
                c = np.cross(rel[a], rel[b])
                if not np.linalg.norm(c) > 0.25 * np.linalg.norm(rel[a]) * np.linalg.norm(rel[b]):
                    continue
                c /= np.linalg.norm(c)
                count = int(np.count_nonzero(np.abs(rel @ c) <= tol))
                if count > best:
                    best, normal = count, c
        if normal is None:
            normal = _least_variance(points[nb[:seed]])
        for _ in range(2):
            near = np.abs(rel @ normal) <= tol
            if near.sum() < 3:
                break
            normal = _least_variance(points[nb[near]])
        out[j] = normal
        mad[j] = np.median(np.abs(rel[1:seed] @ normal))
    return out, mad


def sheet_distance(points: np.ndarray, normals: np.ndarray, x: np.ndarray, gap: float, tree, k: int = 20) -> float:
    """Distance (metres) from ``x`` (3,) to the CGA surface (:func:`fit_primitive`; a plane when
    fewer than 6 points) fitted to its ``k`` nearest points that lie on the nearest one's sheet
    (:func:`split_sheet`, ``gap`` metres)."""
    _, nb = tree.query(x, k=min(k, len(points)))
    kept = split_sheet(points, normals, nb, gap)
    if len(kept) == len(nb):  # one sheet only: how far x is from the data is the 2h test's
        return 0.0
    pts = points[kept]
    if len(kept) < 6:
        centroid = pts.mean(axis=0)
        prim = _pca_plane(pts - centroid, centroid, 1.0)
    else:
        prim = fit_primitive(pts)
    xp, _ = project_onto(prim, x)
    return float(np.linalg.norm(x - xp))
