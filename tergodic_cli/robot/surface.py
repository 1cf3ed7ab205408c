"""The object's contact surface, its normals, and where it stands in front of the robot.

The surface the sponge presses on is the capture's own mesh when it has one, else it is rebuilt
from the cloud (:func:`reconstruct_mesh`): screened Poisson cropped to the data for a closed or
nearly closed object, ball pivoting for an open sheet (what a depth camera sees: the inside of a
bowl, a plate; Poisson would close it with a made-up lid), then a decimation ladder that keeps the
angle between neighbouring triangles small where the object is smooth, since the sponge
feels every fold as a jump of the contact normal (a Poisson level Taubin-faired within h/4 of the
Poisson surface when it misses that; ball pivoting when Poisson crinkles a thin object's rims).
:func:`surface_figures` and :func:`check_surface` measure it and refuse one that does not cover
the cloud, floats off it or is crinkled. The mesh becomes one static concave PyBullet body
(GEOM_MESH, FORCE_CONCAVE_TRIMESH): on curved sheets this gives steadier contact than a convex
decomposition, which cannot represent a thin concave shell. docs/robot.md ("The contact surface") has the measurements.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tergodic_cli.errors import TergodicError, require
from tergodic_cli.robot.ga import pose_matrix, rotvec_to_matrix

#: Default object placement for clouds that do not say where they were captured: the cloud's
#: footprint centre DEFAULT_REACH in front of the robot base, its lowest point DEFAULT_HEIGHT
#: above the base (a 20 cm stand). There the Panda can tilt the sponge 45° in every direction
#: (on the base plane, tilting it away from the robot runs joint 6 into its limit at ~30°).
DEFAULT_REACH = 0.5
DEFAULT_HEIGHT = 0.2
NORMAL_SIDES = ("auto", "outward", "up", "out")


@dataclass
class SurfaceMesh:
    """A triangle mesh of the captured sheet: vertices (n, 3) m and triangles (k, 3), object frame."""

    vertices: np.ndarray
    triangles: np.ndarray
    seconds: float = 0.0
    #: How it was made: "poisson", "ball_pivoting" (rebuilt from the cloud), "source_mesh",
    #: "sim_object" or "given".
    method: str = ""

    @property
    def area(self) -> float:
        v = self.vertices[self.triangles]
        return float(0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum())


def oriented_normals(points: np.ndarray, side: str, neighbors: int = 20) -> np.ndarray:
    """Unit normals (n, 3) of the cloud, oriented to the side the robot works on.

    side : "outward" (consistent over the whole sheet, propagated along its surface, facing out of
        the object: the side a camera above sees; works on closed shapes, undersides, holes and
        sharp edges; then each point turned to the side rays from it escape to, :func:`_toward_views`),
        "up" (n·z >= 0) or "out" (away from the cloud's centroid).

    From :data:`FORK_POINTS` points the work runs in a forked child (:func:`tergodic_cli.native.in_fork`):
    open3d holds the GIL through it (3 s at 26k points on a loaded 2-core machine), and the child,
    unlike the main thread, can be killed at once on Ctrl-C or SIGTERM.
    """
    require(side in ("outward", "up", "out"), f"unknown normal side '{side}'", "use outward, up or out")
    if len(points) >= FORK_POINTS:
        from tergodic_cli.native import in_fork

        return in_fork(lambda: {"normals": _oriented_normals(points, side, neighbors)}, "the cloud's normals")["normals"]
    return _oriented_normals(points, side, neighbors)


#: From this many points :func:`oriented_normals` runs in a forked child (about 0.5 s of open3d below it).
FORK_POINTS = 5000


def _oriented_normals(points: np.ndarray, side: str, neighbors: int) -> np.ndarray:
    """:func:`oriented_normals` in this process."""
    import open3d as o3d

    points = np.asarray(points, dtype=float)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(min(neighbors, len(points) - 1)))
    if side == "outward":
        # One sign for the whole sheet (a minimum spanning tree over the tangent planes), then the
        # sign that makes the surface seen from above face up: a per-point rule ("+z", "from the
        # centroid") points normals into a torus's tube or a box's walls wherever it is ambiguous.
        pc.orient_normals_consistent_tangent_plane(min(neighbors, len(points) - 1))
        n = np.asarray(pc.normals).copy()
        n = n if _seen_from_above(points, n) >= 0 else -n
        return _toward_views(points, _away_from_close_sheet(points, n))
    n = np.asarray(pc.normals).copy()
    ref = np.array([0.0, 0.0, 1.0])[None, :] if side == "up" else points - points.mean(axis=0)
    flip = np.einsum("ij,ij->i", n, np.broadcast_to(ref, n.shape)) < 0
    n[flip] *= -1.0
    return n


def _away_from_close_sheet(points: np.ndarray, normals: np.ndarray, reach: float = 0.01) -> np.ndarray:
    """Normals (n, 3) turned away from another sheet closer than ``reach`` m along them, where the other
    side is free: a thin wall's two sheets (the thin mug's, 4 mm apart) defeat the spanning tree's
    propagation (52 % wrong), but each sheet faces away from its neighbour (the outer one out, the
    inner one into the mug, where :func:`~tergodic_cli.robot.reach.occluded` marks it unreachable)."""
    from scipy.spatial import cKDTree

    from tergodic_cli.capture.filters import mean_spacing

    h = mean_spacing(points)
    tree = cKDTree(points)

    def blocked(n):
        hit = np.zeros(len(points), dtype=bool)
        for s in np.arange(1.5 * h, reach, 0.5 * h):
            hit |= np.isfinite(tree.query(points + s * n, distance_upper_bound=h)[0])
        return hit

    flip = blocked(normals) & ~blocked(-normals)
    out = normals.copy()
    out[flip] *= -1.0
    return out


def _toward_views(points: np.ndarray, normals: np.ndarray, views: int = 64, neighbors: int = 10) -> np.ndarray:
    """Normals (n, 3) turned to the side the cloud is seen from, where it says which side that is.

    Each point becomes a small disc (radius 1.5 h, across its unsigned normal: no side assumed) and
    from each point rays go out over ``views`` directions (a Fibonacci sphere; those within 60 deg of
    either side of the normal, starting h off the point) through open3d's raycasting. A point whose
    escaping rays (hitting no disc) all leave on one side, at least two of them, faces that side.
    The points of one open sheet (a plate, a bowl's wall) are seen from both sides and keep their
    sign; a point seen from nowhere takes, from the placed points inward, the side its ``neighbors``
    nearest placed points along the sheet agree on (weighted by |n·n'|). A closed object's point is
    seen only from outside, so this undoes the spanning tree's flips across creases and thin parts
    (corpus, TUNE split, normals pointing in: bunny 3.4 -> 1.0 %, shape sorter 3.4 -> 0.1 %, mug
    2.0 -> 0.6 %).
    """
    import open3d as o3d
    from scipy.spatial import cKDTree

    from tergodic_cli.capture.filters import mean_spacing

    P = np.asarray(points, dtype=float)
    n = np.asarray(normals, dtype=float).copy()
    if len(P) < 20:
        return n
    h = mean_spacing(P)
    # the discs: hexagons (6 triangles about the point) across the normal
    a = np.cross(n, np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]]))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(n, a)
    t = np.linspace(0.0, 2.0 * np.pi, 7)[:-1]
    rim = P[:, None] + 1.5 * h * (np.cos(t)[None, :, None] * a[:, None] + np.sin(t)[None, :, None] * b[:, None])
    V = np.concatenate([P, rim.reshape(-1, 3)]).astype(np.float32)
    c = np.repeat(np.arange(len(P)), 6)
    r0 = len(P) + np.arange(len(P) * 6)
    r1 = len(P) + (np.arange(len(P))[:, None] * 6 + (np.arange(6)[None] + 1) % 6).ravel()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V), o3d.core.Tensor(np.column_stack([c, r0, r1]).astype(np.uint32)))
    k = np.arange(views) + 0.5
    z = 1.0 - 2.0 * k / views
    phi = np.pi * (1.0 + 5.0 ** 0.5) * k
    dirs = np.column_stack([np.sqrt(1.0 - z * z) * np.cos(phi), np.sqrt(1.0 - z * z) * np.sin(phi), z])
    cos = n @ dirs.T  # (n, views)
    pi, di = np.nonzero(np.abs(cos) > 0.5)
    rays = np.column_stack([P[pi] + h * dirs[di], dirs[di]]).astype(np.float32)
    free = np.isinf(scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy())
    plus = np.bincount(pi, weights=(free & (cos[pi, di] > 0)).astype(float), minlength=len(P))
    minus = np.bincount(pi, weights=(free & (cos[pi, di] < 0)).astype(float), minlength=len(P))
    decided = ((plus >= 2) & (minus == 0)) | ((minus >= 2) & (plus == 0))
    n[decided & (minus > 0)] *= -1.0
    # points seen from both sides (an open sheet) keep their sign; the unseen ones, from the placed
    # points inward, take the side their placed neighbours along the sheet agree on (across a thin
    # wall the other sheet faces the other way)
    _, nb = cKDTree(P).query(P, k=min(neighbors + 1, len(P)))
    nb = nb[:, 1:]
    dx = P[nb] - P[:, None]
    along = np.abs(np.einsum("ijk,ik->ij", dx, n)) < 0.5 * np.linalg.norm(dx, axis=2)
    known = decided | ((plus > 0) & (minus > 0))
    while not known.all():
        rest = np.flatnonzero(~known)
        c = np.einsum("ijk,ik->ij", n[nb[rest]], n[rest])
        w = np.abs(c) * along[rest] * known[nb[rest]]
        total = w.sum(axis=1)
        step = total > 0
        if not step.any():
            break
        agree = (w * np.sign(c)).sum(axis=1) / np.maximum(total, 1e-12)
        n[rest[step & (agree < 0)]] *= -1.0
        known[rest[step]] = True
    return n


def _seen_from_above(points: np.ndarray, normals: np.ndarray, cells: int = 32) -> float:
    """Sum of n_z over the topmost point of each cell of a ``cells``² grid over the footprint."""
    lo, hi = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    ij = np.minimum(((points[:, :2] - lo) / np.maximum(hi - lo, 1e-9) * cells).astype(int), cells - 1)
    cell = ij[:, 0] * cells + ij[:, 1]
    order = np.lexsort((-points[:, 2], cell))  # by cell, highest first
    first = order[np.r_[True, cell[order][1:] != cell[order][:-1]]]
    return float(normals[first, 2].sum())


def resolve_side(side: str, capture_meta: dict | None = None) -> str:
    """"auto" -> "outward" (consistent, out of the object); "outward", "up" and "out" as given."""
    require(side in NORMAL_SIDES, f"unknown --normal-side '{side}'", f"use one of {', '.join(NORMAL_SIDES)}")
    return "outward" if side == "auto" else side


def curved_edge(points: np.ndarray, normals: np.ndarray, edge: float, floor: float = 0.004) -> float:
    """Triangle edge (m) for the collision mesh: ``edge`` on gentle shapes, finer on tightly curved ones.

    A fifth of the surface's radius of curvature (75th percentile over the cloud, from the turn of
    the unit ``normals`` (n, 3) between the 10 nearest ``points`` (n, 3)) keeps neighbouring facets
    within ~12 deg, so a ball pressing on them does not tilt by a facet's angle (the torus's 20 mm
    tube at 10 mm facets made the sponge press 15 deg off its normal); never below ``floor``.
    """
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(points).query(points, k=11)
    kappa = np.median(np.linalg.norm(normals[idx[:, 1:]] - normals[:, None], axis=2) / np.maximum(dist[:, 1:], 1e-9), axis=1)
    radius = 1.0 / max(float(np.percentile(kappa, 75)), 1e-9)
    return float(min(edge, max(floor, 0.2 * radius))) if edge > 0 else edge


#: The contact surface's check (docs/robot.md, "The contact surface"). Figures go to summary.json's
#: ``contact_surface``; a surface rebuilt from the cloud that fails them is refused before any motion.
#: SMOOTH_GOAL_DEG: the decimation stops at the coarsest mesh whose dihedral p95 over the smooth part
#: is at most this (issue goal 15 deg on smooth objects, 3 deg kept as margin). SHARP_DEG: an edge
#: whose two triangles' nearest cloud normals differ by more is on a real edge of the object (a
#: box's), not part of the smooth part. CRINKLE_DEG: a rebuilt surface whose folds exceed the
#: cloud's own (95th percentile) by more is refused: it folds where the object does not.
SMOOTH_GOAL_DEG = 12.0
#: The ladder's finest triangle edge, m (and never below 0.9 h): the ball's contact tests every
#: triangle in its box, so the cost grows with their number (same run, a 12 mm ball pressed on the
#: duck: 16 800 triangles of 2.8 mm cost 2.5x the 3 300 of the former 6.3 mm mesh per step).
MIN_EDGE = 0.003
SHARP_DEG = 30.0
CRINKLE_DEG = 30.0
#: Coverage: the share of cloud points within COVER_H·h of the surface must reach MIN_COVERAGE.
COVER_H, MIN_COVERAGE = 1.5, 0.95
#: The surface must not float off the data: the 95th percentile of its distance from the cloud at
#: most OFFSET_H·h (measured 0.6-1.0 h on every built-in and corpus object).
OFFSET_H = 2.0
#: Poisson's cropped area share above which the cloud is an open sheet (Poisson closed it with a
#: made-up lid: 30-72 % on the built-in sheets, box included; at most 1.5 % on the closed corpus
#: objects and the built-in sphere and torus).
OPEN_SHARE = 0.1
#: Fairing of a Poisson surface (:func:`_fair`): Taubin iterations, and how far (FAIR_H·h) a vertex
#: may leave the Poisson surface. Tuned on the corpus's TUNE objects (3 mm; with the seen-side
#: normals): the smooth part's p95 from 26.1/13.3/25.8 deg (bunny/duck/mug) to 21.8/12.0/17.9, the
#: vertices' 95th-percentile distance to the source mesh from 1.05/0.63/1.07 mm to 1.30/0.87/1.07;
#: 100-300 iterations did no better (the limit then kinks the surface).
FAIR_ITERATIONS = 50
FAIR_H = 0.25


def _o3d_mesh(vertices: np.ndarray, triangles: np.ndarray):
    import open3d as o3d

    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(vertices, dtype=float)),
                                     o3d.utility.Vector3iVector(np.asarray(triangles, dtype=np.int32)))


def _clean(m):
    m.remove_duplicated_vertices()
    m.remove_duplicated_triangles()
    m.remove_degenerate_triangles()
    m.remove_non_manifold_edges()
    m.remove_unreferenced_vertices()
    return m


def decimate_to_edge(m, edge: float):
    """An open3d mesh quadric-decimated to about ``edge`` m per triangle side (equilateral count by
    area); returned as is when it is already coarser or ``edge`` <= 0. The one decimation rule of the
    collision meshes (rebuilt, source and simulated objects)."""
    if edge <= 0:
        return m
    target = int(m.get_surface_area() / (0.433 * edge * edge))  # equilateral triangles of side `edge`
    if 50 <= target < len(m.triangles):
        m = m.simplify_quadric_decimation(target)
        m.remove_degenerate_triangles()
        m.remove_unreferenced_vertices()
    return m


def _largest_piece(m):
    """The connected piece of largest area (the robot presses one object; stray pieces would let a
    far cluster pass the coverage check)."""
    labels, _, areas = m.cluster_connected_triangles()
    labels = np.asarray(labels)
    if len(areas) > 1:
        m.remove_triangles_by_mask(labels != int(np.argmax(np.asarray(areas))))
        m.remove_unreferenced_vertices()
    return m


def _folds(vertices: np.ndarray, triangles: np.ndarray):
    """(fold angles (m,) degrees, the two triangles of each (m, 2), border edge count, non-manifold edge count)."""
    V = np.asarray(vertices, dtype=float)
    T = np.asarray(triangles, dtype=np.int64)
    if len(T) == 0:
        return np.zeros(0), np.zeros((0, 2), dtype=np.int64), 0, 0
    E = np.sort(np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]]), axis=1)
    opposite = np.concatenate([T[:, 2], T[:, 0], T[:, 1]])
    tri = np.tile(np.arange(len(T)), 3)
    key = E[:, 0] * (len(V) + 1) + E[:, 1]
    order = np.argsort(key, kind="stable")
    _, start, count = np.unique(key[order], return_index=True, return_counts=True)
    pair = start[count == 2]
    i0, i1 = order[pair], order[pair + 1]
    a, e = V[E[i0, 0]], V[E[i0, 1]] - V[E[i0, 0]]
    n1 = np.cross(e, V[opposite[i0]] - a)
    n2 = np.cross(V[opposite[i1]] - a, e)
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True) + 1e-30
    n2 /= np.linalg.norm(n2, axis=1, keepdims=True) + 1e-30
    angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n1, n2), -1.0, 1.0)))
    return angle, np.column_stack([tri[i0], tri[i1]]), int((count == 1).sum()), int((count > 2).sum())


def dihedral_angles(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, int, int]:
    """Fold angles (degrees, (m,)) across the edges shared by exactly two triangles (in the order of
    the sorted vertex pairs), and the counts of open border edges (one triangle) and non-manifold
    edges (three or more).

    The angle is between the two triangles' normals taken about the shared edge (0 on a flat
    sheet, 90 at a box's edge), so it does not depend on the triangles' winding.
    """
    angle, _, border, nonmanifold = _folds(vertices, triangles)
    return angle, border, nonmanifold


def _cloud_folds(vertices: np.ndarray, triangles: np.ndarray, pairs: np.ndarray, tree, normals: np.ndarray) -> np.ndarray:
    """(m,) degrees: the angle between the cloud's normals nearest to the two triangles of each fold
    (either sign): how much the object itself turns there."""
    V = np.asarray(vertices, dtype=float)
    centre = V[np.asarray(triangles, dtype=np.int64)].mean(axis=1)
    n = normals[tree.query(centre)[1]]
    c = np.abs(np.einsum("ij,ij->i", n[pairs[:, 0]], n[pairs[:, 1]]))
    return np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))


def _smooth_p95(angle: np.ndarray, cloud_fold: np.ndarray | None) -> float:
    """95th percentile of the folds where the cloud is smooth (its own turn below SHARP_DEG)."""
    a = angle if cloud_fold is None else angle[cloud_fold < SHARP_DEG]
    return float(np.percentile(a, 95)) if len(a) else 0.0


def surface_figures(mesh: "SurfaceMesh", points: np.ndarray, spacing: float, normals: np.ndarray | None = None,
                    samples: int = 20000, seed: int = 0) -> dict:
    """The contact surface's check figures (summary.json ``contact_surface``).

    Parameters
    ----------
    mesh : the surface, in the frame of ``points``. points : (n, 3) cloud, m. spacing : h, m.
    normals : (n, 3) the cloud's unit normals (either sign); given, the folds are compared with the
        cloud's own turn (dihedral_smooth_p95_deg, fold_excess_p95_deg; else those are None).

    Returns
    -------
    dict : method, triangles, vertices, dihedral_p50_deg / dihedral_p95_deg (between neighbouring
        triangles), dihedral_smooth_p95_deg (over the edges where the cloud turns less than
        SHARP_DEG: a box's edges left out), fold_excess_p95_deg (fold minus the cloud's own turn:
        crinkle), border_edges (open, one triangle), nonmanifold_edges, coverage (share of cloud
        points within COVER_H·h of the surface), cover_radius_mm, cloud_to_surface_p95_mm,
        surface_to_cloud_p95_mm / _max_mm (``samples`` points spread evenly over the surface,
        distance to the nearest cloud point: it does not float off), spacing_mm, build_seconds.
    """
    import open3d as o3d
    from scipy.spatial import cKDTree

    V = np.asarray(mesh.vertices, dtype=float)
    T = np.asarray(mesh.triangles, dtype=np.int64)
    pts = np.asarray(points, dtype=float)
    angle, pairs, border, nonmanifold = _folds(V, T)
    tree = cKDTree(pts)
    smooth = excess = None
    if normals is not None and len(angle):
        cloud_fold = _cloud_folds(V, T, pairs, tree, np.asarray(normals, dtype=float))
        smooth = _smooth_p95(angle, cloud_fold)
        excess = float(np.percentile(np.maximum(angle - cloud_fold, 0.0), 95))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(T.astype(np.uint32)))
    d_cloud = scene.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy().astype(float)
    o3d.utility.random.seed(int(seed))
    s = np.asarray(_o3d_mesh(V, T).sample_points_uniformly(int(samples)).points)
    d_surf = tree.query(s)[0]
    pct = (lambda x, q: float(np.percentile(x, q))) if len(angle) else (lambda x, q: float("nan"))
    return {
        "method": mesh.method,
        "triangles": int(len(T)),
        "vertices": int(len(V)),
        "dihedral_p50_deg": pct(angle, 50),
        "dihedral_p95_deg": pct(angle, 95),
        "dihedral_smooth_p95_deg": smooth,
        "fold_excess_p95_deg": excess,
        "border_edges": border,
        "nonmanifold_edges": nonmanifold,
        "coverage": float(np.mean(d_cloud < COVER_H * spacing)),
        "cover_radius_mm": 1e3 * COVER_H * spacing,
        "cloud_to_surface_p95_mm": 1e3 * float(np.percentile(d_cloud, 95)),
        "surface_to_cloud_p95_mm": 1e3 * float(np.percentile(d_surf, 95)),
        "surface_to_cloud_max_mm": 1e3 * float(d_surf.max()),
        "spacing_mm": 1e3 * float(spacing),
        "build_seconds": float(mesh.seconds),
    }


def check_surface(fig: dict, rebuilt: bool = True) -> None:
    """Refuse a contact surface whose figures (:func:`surface_figures`) fail, in one line with the fix.

    Coverage applies to every surface. The distance from the cloud and the crinkle limit apply only
    to one rebuilt from the cloud (``rebuilt``): a source or simulated object's mesh is the object,
    its side the camera did not see lies far from the cloud and its folds are its own edges.
    """
    h = fig["spacing_mm"]
    if fig["coverage"] < MIN_COVERAGE:
        raise TergodicError(f"the contact surface covers only {100 * fig['coverage']:.0f} % of the cloud (points within "
                            f"{fig['cover_radius_mm']:.1f} mm; {100 * MIN_COVERAGE:.0f} % needed): the cloud holds parts "
                            "that do not join one surface",
                            "capture one object: crop the cloud to it (capture --crop) or drop stray clusters (--outliers)")
    if rebuilt and fig["surface_to_cloud_p95_mm"] > OFFSET_H * h:
        raise TergodicError(f"the contact surface floats off the cloud ({fig['surface_to_cloud_p95_mm']:.1f} mm at the 95th "
                            f"percentile, limit {OFFSET_H * h:.1f} mm = {OFFSET_H:g} x the point spacing)",
                            "capture the object more densely and evenly (a smaller --voxel, no large holes)")
    if rebuilt and (fig.get("fold_excess_p95_deg") or 0.0) > CRINKLE_DEG:
        raise TergodicError(f"the contact surface rebuilt from the cloud is crinkled (its neighbouring triangles fold "
                            f"{fig['fold_excess_p95_deg']:.0f} deg more than the cloud turns there, 95th percentile; "
                            f"limit {CRINKLE_DEG:.0f} deg)",
                            "capture the object more densely with less noise (a smaller --voxel, --outliers), "
                            "or give its mesh (capture --from FILE.obj)")


def _poisson(points: np.ndarray, normals: np.ndarray, spacing: float):
    """Screened Poisson surface on cells of the point spacing, cropped to within 2 h of the cloud.

    Returns (mesh, share of its area the crop removed)."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pc.normals = o3d.utility.Vector3dVector(normals)
    # Finest cells of one spacing h: finer ones follow each sample's bump (duck: dihedral p95 25 deg
    # at depth 8 against 11 at h, decimated alike) and cost more.
    m, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pc, depth=0, width=float(spacing), n_threads=1)
    area = m.get_surface_area()
    far = cKDTree(points).query(np.asarray(m.vertices))[0] >= 2.0 * spacing
    m.remove_vertices_by_mask(far)
    m = _largest_piece(_clean(m))
    return m, 1.0 - m.get_surface_area() / max(area, 1e-12)


def _ball_pivoting(points: np.ndarray, normals: np.ndarray, spacing: float):
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pc.normals = o3d.utility.Vector3dVector(normals)
    radii = o3d.utility.DoubleVector([1.5 * spacing, 3.0 * spacing, 6.0 * spacing])
    return _largest_piece(_clean(o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(pc, radii)))


def _closest(scene, x: np.ndarray) -> np.ndarray:
    """(n, 3) the closest points on the open3d raycasting ``scene``'s triangles to ``x`` (n, 3)."""
    import open3d as o3d

    q = scene.compute_closest_points(o3d.core.Tensor(np.asarray(x, dtype=np.float32)))["points"].numpy()
    return q.astype(float)


def _scene(m):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(m.vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.asarray(m.triangles).astype(np.uint32)))
    return scene


def _onto(d, m, scene=None):
    """The open3d mesh ``d`` with each vertex moved to its closest point on the open3d mesh ``m``."""
    import open3d as o3d

    d.vertices = o3d.utility.Vector3dVector(_closest(scene if scene is not None else _scene(m), np.asarray(d.vertices)))
    return d


def _fair(d, scene, limit: float, iterations: int = FAIR_ITERATIONS):
    """The open3d mesh ``d`` (its vertices on the surface of ``scene``) Taubin-smoothed (open3d's
    ``filter_smooth_taubin``, a low-pass filter; λ 0.5, μ -0.51: the default μ -0.53 inflated a
    60 mm sphere by 0.6 mm, -0.50 shrank it by 0.3), then each vertex pulled back to within
    ``limit`` m of that surface: the folds the Poisson grid and the sampling leave are smoothed,
    the surface stays where the cloud is."""
    import open3d as o3d

    s = d.filter_smooth_taubin(number_of_iterations=int(iterations), lambda_filter=0.5, mu=-0.51)
    x = np.asarray(s.vertices)
    q = _closest(scene, x)
    off = x - q
    dist = np.linalg.norm(off, axis=1, keepdims=True)
    s.vertices = o3d.utility.Vector3dVector(q + off * np.minimum(1.0, limit / np.maximum(dist, 1e-12)))
    return s


def _level_p95(d, tree, normals) -> float:
    """Dihedral p95 (degrees) over the smooth part of the open3d mesh ``d`` (all edges without a cloud)."""
    V, T = np.asarray(d.vertices), np.asarray(d.triangles)
    angle, pairs, _, _ = _folds(V, T)
    return _smooth_p95(angle, _cloud_folds(V, T, pairs, tree, normals) if tree is not None else None)


def smooth_decimation(m, edge: float, floor: float, points: np.ndarray | None = None, normals: np.ndarray | None = None,
                      goal_deg: float = SMOOTH_GOAL_DEG, subdivide: bool = False, fair: float = 0.0):
    """Decimate ``m`` to the coarsest of edge, edge/1.5, edge/1.5², ... (not below ``floor`` m) whose
    dihedral p95 over the smooth part (where the cloud ``points``/``normals`` turn less than
    SHARP_DEG; all edges without them) is at most ``goal_deg``, else to the smoothest of them. A
    coarser mesh of a curved surface folds more at each edge (about edge / radius); a box's real
    edges fold 90 deg at any size and do not count.

    ``subdivide`` (smooth surfaces only: it rounds sharp edges): each level decimates to twice its
    edge, splits once by Loop subdivision and puts the vertices back on ``m`` (Loop's surface lies
    inside a convex one: 1.7 mm on a 60 mm sphere at 10 mm triangles; 0.04 mm once put back): the
    same triangle count with smaller folds (duck, ~3300 triangles: 20 deg against 24 decimated
    alone, ~7500: 14.5 against 17). ``fair`` > 0 (m): a level that misses ``goal_deg`` is also
    Taubin-faired within ``fair`` of ``m`` (:func:`_fair`) and kept faired when that folds less.
    Returns (mesh, that p95)."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    tree = cKDTree(points) if points is not None and normals is not None else None
    scene = _scene(m) if subdivide else None
    best = None
    e = float(edge)
    while True:
        if e <= 0:
            d = m
        elif subdivide:
            d = _onto(decimate_to_edge(m, 2.0 * e).subdivide_loop(1), m, scene)
        else:
            d = decimate_to_edge(m, e)
        p95 = _level_p95(d, tree, normals)
        if fair > 0 and e > 0 and p95 > goal_deg:
            f = _fair(o3d.geometry.TriangleMesh(d), scene if scene is not None else _scene(m), fair)
            fp95 = _level_p95(f, tree, normals)
            if fp95 < p95:
                d, p95 = f, fp95
        if best is None or p95 < best[1]:
            best = (d, p95)
        if p95 <= goal_deg or e <= 0 or e / 1.5 < floor:
            return best
        e /= 1.5


def _fold_excess(m, points: np.ndarray, normals: np.ndarray) -> float:
    """surface_figures' fold_excess_p95_deg of the open3d mesh ``m`` (degrees)."""
    from scipy.spatial import cKDTree

    V, T = np.asarray(m.vertices), np.asarray(m.triangles)
    angle, pairs, _, _ = _folds(V, T)
    if len(angle) == 0:
        return 0.0
    return float(np.percentile(np.maximum(angle - _cloud_folds(V, T, pairs, cKDTree(points), normals), 0.0), 95))


def reconstruct_mesh(points: np.ndarray, normals: np.ndarray, spacing: float, edge: float = 0.006,
                     method: str = "auto", goal_deg: float = SMOOTH_GOAL_DEG) -> SurfaceMesh:
    """The collision surface rebuilt from the cloud, smooth where the object is.

    ``auto``: screened Poisson (open3d) on cells of one spacing h, cropped to within 2 h of the cloud;
    if the crop removed more than OPEN_SHARE of its area the cloud is an open sheet (Poisson closed
    it with a made-up lid) and ball pivoting (radii 1.5h, 3h, 6h) builds it instead, following the
    sheet and keeping its sharp edges. Either is then quadric-decimated to the coarsest of ``edge``,
    edge/1.5, ... (not below 0.9 h nor MIN_EDGE) whose dihedral p95 over its smooth part is at most
    SMOOTH_GOAL_DEG (:func:`smooth_decimation`); the Poisson surface to twice that edge, then split
    once by Loop subdivision and put back on the Poisson surface (the same triangle count, smaller
    folds), and a level that still misses the goal Taubin-faired within FAIR_H·h of the Poisson
    surface (:func:`_fair`). The corpus duck (15 cm, 4968 points) went from a dihedral p95 of 46 deg
    (ball pivoting decimated once) to 14.5, then 13.1 faired. ``auto`` builds ball pivoting too when
    the Poisson surface folds more than CRINKLE_DEG beyond the cloud (a thin tray's rims rounded
    into creases) and keeps the one that folds less.

    Parameters
    ----------
    points : (n, 3) cloud, metres. normals : (n, 3) oriented unit normals.
    spacing : mean point spacing h, metres.
    edge : the coarsest mean triangle edge after decimation, metres (0 keeps every triangle).
    method : "auto", "poisson" or "ball_pivoting".
    goal_deg : the decimation ladder's goal (inf: one decimation to ``edge``, the former rule).
    """
    import time

    require(method in ("auto", "poisson", "ball_pivoting"), f"unknown surface method '{method}'",
            "use auto, poisson or ball_pivoting")
    t0 = time.perf_counter()
    points = np.ascontiguousarray(points, dtype=float)
    normals = np.ascontiguousarray(normals, dtype=float)
    m, used = None, method
    if method in ("auto", "poisson"):
        m, open_share = _poisson(points, normals, spacing)
        used = "poisson"
        if method == "auto" and open_share > OPEN_SHARE:
            m = None
    if m is None:
        m, used = _ball_pivoting(points, normals, spacing), "ball_pivoting"
    n_tri = len(m.triangles)
    require(n_tri >= 10, f"could not build a surface from the cloud ({n_tri} triangles)",
            "check the capture: the robot needs a cloud that samples one connected sheet")
    floor = max(0.9 * spacing, MIN_EDGE)
    poisson = used == "poisson"
    m, _ = smooth_decimation(m, edge, floor, points, normals, goal_deg, subdivide=poisson,
                             fair=FAIR_H * spacing if poisson else 0.0)
    if method == "auto" and poisson and _fold_excess(m, points, normals) > CRINKLE_DEG:
        # Poisson rounds a thin object's sharp rims into folds the cloud does not have (the check
        # would refuse it as crinkled); ball pivoting follows the sheet and keeps the rims
        b = _ball_pivoting(points, normals, spacing)
        if len(b.triangles) >= 10:
            b, _ = smooth_decimation(b, edge, floor, points, normals, goal_deg)
            if _fold_excess(b, points, normals) < _fold_excess(m, points, normals):
                m, used = b, "ball_pivoting"
    return SurfaceMesh(np.asarray(m.vertices).copy(), np.asarray(m.triangles, dtype=np.int64).copy(),
                       time.perf_counter() - t0, used)


def rebuild_surface(points: np.ndarray, normals: np.ndarray, spacing: float, edge: float = 0.006) -> SurfaceMesh:
    """:func:`reconstruct_mesh` (method ``auto``) in a forked child process.

    open3d holds the GIL through its Poisson reconstruction and decimation (10 s at 50k points on a
    loaded 2-core machine), so in-process the run could not answer Ctrl-C or SIGTERM until it
    returned; the child is killed instead (:func:`tergodic_cli.native.in_fork`).

    Parameters
    ----------
    points : (n, 3) cloud, metres. normals : (n, 3) oriented unit normals.
    spacing : mean point spacing h, metres.
    edge : the coarsest mean triangle edge after decimation, metres.

    Returns
    -------
    SurfaceMesh
        Equal to :func:`reconstruct_mesh`'s (vertices (m, 3) m, triangles (k, 3), seconds, method).
    """
    from tergodic_cli.native import in_fork

    def build() -> dict[str, np.ndarray]:
        m = reconstruct_mesh(points, normals, spacing, edge)
        return {"vertices": m.vertices, "triangles": m.triangles, "seconds": np.float64(m.seconds),
                "method": np.array(m.method)}

    out = in_fork(build, "the contact surface's reconstruction")
    return SurfaceMesh(out["vertices"], out["triangles"], float(out["seconds"]), str(out["method"]))


def source_mesh(mesh, edge: float = 0.01) -> SurfaceMesh:
    """The capture's own source mesh as the collision surface: (vertices (n, 3) m, triangles (k, 3))
    in the points' frame, decimated to about ``edge`` m like a simulated object's mesh."""
    import time

    t0 = time.perf_counter()
    vertices, triangles = mesh
    V = np.asarray(vertices, dtype=float)
    T = np.asarray(triangles, dtype=np.int64)
    require(V.ndim == 2 and V.shape[1] == 3 and T.ndim == 2 and T.shape[1] == 3 and len(T) >= 1
            and bool(np.all(np.isfinite(V))) and int(T.min()) >= 0 and int(T.max()) < len(V),
            "the capture's source mesh is not (vertices (n, 3), triangles (k, 3)) with valid indices",
            "re-capture from the mesh file (capture --from FILE.obj)")
    m = decimate_to_edge(_clean(_o3d_mesh(V, T)), edge)
    return SurfaceMesh(np.asarray(m.vertices).copy(), np.asarray(m.triangles, dtype=np.int64).copy(),
                       time.perf_counter() - t0, "source_mesh")


def near_border(mesh: SurfaceMesh, points: np.ndarray, width: float) -> np.ndarray:
    """(n,) bool: ``points`` (n, 3) within ``width`` m of the mesh's open border (edges of one triangle).

    A sponge ball pressing there hangs over the sheet's edge; a ball-pivoting border is ragged, so
    the ball rolls off it (the partial scan's free border: 28 deg off the normal)."""
    from scipy.spatial import cKDTree

    T = np.asarray(mesh.triangles)
    E = np.sort(np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]]), axis=1)
    edges, count = np.unique(E, axis=0, return_counts=True)
    border = edges[count == 1]
    if len(border) == 0:
        return np.zeros(len(points), dtype=bool)
    V = np.asarray(mesh.vertices, dtype=float)
    s = np.linspace(0.0, 1.0, 6)[:, None, None]  # points along each border edge (edges ~10 mm)
    samples = (V[border[:, 0]][None] * (1 - s) + V[border[:, 1]][None] * s).reshape(-1, 3)
    return cKDTree(samples).query(np.asarray(points, dtype=float), distance_upper_bound=width)[0] < width


def parse_object_pose(values) -> np.ndarray:
    """The capture frame's pose in the robot base frame as a (4, 4) transform.

    values : 3 numbers x,y,z (m); 6 numbers x,y,z,roll,pitch,yaw (m, degrees, fixed-axis XYZ);
        or 7 numbers x,y,z,qx,qy,qz,qw (the simulated scene's object pose, one parser).
    """
    from tergodic_cli.capture.textured import parse_pose

    return parse_pose(values, "--object-pose")


def default_object_pose(points: np.ndarray, reach: float = DEFAULT_REACH, yaw_deg: float = 0.0) -> np.ndarray:
    """Pose putting the cloud's footprint centre at (reach, 0) and its lowest point at DEFAULT_HEIGHT,
    turned ``yaw_deg`` about the vertical through that centre."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre = 0.5 * (lo + hi)
    R = rotvec_to_matrix(np.array([0.0, 0.0, math.radians(yaw_deg)]))
    return pose_matrix(R, np.array([reach, 0.0, DEFAULT_HEIGHT]) - R @ np.array([centre[0], centre[1], lo[2]]))


def transform_points(T: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Points (..., 3) mapped by the (4, 4) transform T."""
    return np.asarray(x, dtype=float) @ T[:3, :3].T + T[:3, 3]


def check_reachable(points_base: np.ndarray, reach: tuple | None) -> None:
    """Refuse objects the arm cannot reach from its base: a rough check before the reach map.

    Parameters
    ----------
    points_base : (n, 3) float
        The cloud in the robot base frame, m.
    reach : ((3,) float, float) or None
        The arm's shoulder (the point its reach is measured from, base frame, m) and the distance
        from it the tool can work at, m (``ArmSpec.reach``); None: no check.
    """
    if reach is None:
        return
    shoulder, reach = np.asarray(reach[0], dtype=float), float(reach[1])
    d = np.linalg.norm(points_base - shoulder, axis=1)
    far = float(d.max())
    if far > reach:
        raise TergodicError(f"part of the object is {far:.2f} m from the robot's shoulder, beyond the {reach:.2f} m the tool can reach",
                            "move it closer with --object-pose x,y,z (e.g. 0.5,0,0)")
    if float(points_base[:, 0].min()) < 0.2 and float(np.abs(points_base[:, 1]).min()) < 0.15:
        raise TergodicError("the object overlaps the robot's base", "move it in front of the robot with --object-pose (e.g. 0.5,0,0)")


def sim_object_mesh(sim_meta: dict, edge: float = 0.01) -> tuple[SurfaceMesh, np.ndarray]:
    """The collision mesh of a simulated capture's object: the textured object's own surface.

    A ``--source sim`` capture records its object (``meta["sim"]["object"]``, a
    :class:`~tergodic_cli.capture.textured.SimObjectConfig` as a dict) and its pose in the base
    frame (``meta["sim"]["object_pose"]``). The robot presses on that surface, not on a mesh
    rebuilt from the cloud, so the sponge touches exactly what the camera renders and the
    cleaning model fades. Built-in objects are re-triangulated at ``edge`` (their analytic
    surface, so no decimation error beyond the chord sag); a user ``.obj`` is decimated to
    about ``edge``.

    Returns the mesh (object frame, metres) and its (4, 4) pose in the robot base frame.
    """
    import time

    from tergodic_cli.capture.textured import BUILTIN_OBJECTS, builtin_mesh, read_obj

    t0 = time.perf_counter()
    obj = dict(sim_meta.get("object") or {})
    kind = str(obj.get("object", ""))
    pose = sim_meta.get("object_pose")
    require(bool(kind) and pose is not None, "the capture's sim record has no object or object pose",
            "re-capture with 'tergodic capture --source sim'")
    T = np.asarray(pose, dtype=float)
    require(T.shape == (4, 4) and bool(np.all(np.isfinite(T))), "the capture's sim object pose is not a 4x4 transform",
            "re-capture with 'tergodic capture --source sim'")
    if kind in BUILTIN_OBJECTS:
        mesh = builtin_mesh(kind, float(edge) if edge > 0 else float(obj.get("mesh_edge") or 0.003))
        return SurfaceMesh(mesh.vertices.copy(), mesh.triangles.copy(), time.perf_counter() - t0, "sim_object"), T
    vertices, triangles, _ = read_obj(kind, str(obj.get("units", "m")))
    if edge > 0:
        m = _o3d_mesh(vertices, triangles)
        m.remove_duplicated_vertices()
        m = decimate_to_edge(m, edge)
        vertices, triangles = np.asarray(m.vertices).copy(), np.asarray(m.triangles, dtype=np.int64).copy()
    return SurfaceMesh(vertices, triangles, time.perf_counter() - t0, "sim_object"), T
