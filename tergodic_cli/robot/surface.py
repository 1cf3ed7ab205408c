"""The object's collision surface, its normals, and where it stands in front of the robot.

A capture is a single open sheet (what a depth camera sees: the inside of a bowl, a plate,
a mug's wall). Ball pivoting (open3d) turns it into a triangle mesh that follows the sheet
without closing it (Poisson would inflate a sheet into a blob); quadric decimation then
keeps the sag error far below the sampling noise while cutting the triangles the sponge
overlaps, which sets PyBullet's per-step contact cost (docs/robot.md has the measurements).
The mesh becomes one static concave PyBullet body (GEOM_MESH, FORCE_CONCAVE_TRIMESH): on
curved sheets this gives steadier contact than a convex decomposition, which cannot
represent a thin concave shell.
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

    @property
    def area(self) -> float:
        v = self.vertices[self.triangles]
        return float(0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum())


def oriented_normals(points: np.ndarray, side: str, neighbors: int = 20) -> np.ndarray:
    """Unit normals (n, 3) of the cloud, oriented to the side the robot works on.

    side : "outward" (consistent over the whole sheet, propagated along its surface, facing out of
        the object: the side a camera above sees; works on closed shapes, undersides, holes and
        sharp edges), "up" (n·z >= 0) or "out" (away from the cloud's centroid).
    """
    import open3d as o3d

    require(side in ("outward", "up", "out"), f"unknown normal side '{side}'", "use outward, up or out")
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
        return _away_from_close_sheet(points, n)
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


def reconstruct_mesh(points: np.ndarray, normals: np.ndarray, spacing: float, edge: float = 0.006) -> SurfaceMesh:
    """Ball-pivoting mesh of an open sheet, decimated to triangles of about ``edge`` metres.

    Parameters
    ----------
    points : (n, 3) cloud, metres. normals : (n, 3) oriented unit normals.
    spacing : mean point spacing h, metres (ball radii 1.5h, 3h, 6h).
    edge : target mean triangle edge after decimation, metres (0 keeps every triangle).
    """
    import time

    import open3d as o3d

    t0 = time.perf_counter()
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=float)))
    pc.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=float))
    radii = o3d.utility.DoubleVector([1.5 * spacing, 3.0 * spacing, 6.0 * spacing])
    mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(pc, radii)
    mesh.remove_duplicated_triangles()
    mesh.remove_degenerate_triangles()
    mesh.remove_unreferenced_vertices()
    n_tri = len(mesh.triangles)
    require(n_tri >= 10, f"could not build a surface from the cloud ({n_tri} triangles)",
            "check the capture: the robot needs a cloud that samples one connected sheet")
    if edge > 0:
        area = mesh.get_surface_area()
        target = int(area / (0.433 * edge * edge))  # equilateral triangles of side `edge`
        if target < n_tri:
            mesh = mesh.simplify_quadric_decimation(max(target, 50))
            mesh.remove_degenerate_triangles()
            mesh.remove_unreferenced_vertices()
    return SurfaceMesh(np.asarray(mesh.vertices).copy(), np.asarray(mesh.triangles, dtype=np.int64).copy(),
                       time.perf_counter() - t0)


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


def check_reachable(points_base: np.ndarray, reach: float = 0.8) -> None:
    """Refuse objects the Panda cannot reach from its base (distance from the shoulder)."""
    shoulder = np.array([0.0, 0.0, 0.333])
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
        return SurfaceMesh(mesh.vertices.copy(), mesh.triangles.copy(), time.perf_counter() - t0), T
    vertices, triangles, _ = read_obj(kind, str(obj.get("units", "m")))
    if edge > 0:
        import open3d as o3d

        m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles.astype(np.int32)))
        m.remove_duplicated_vertices()
        target = int(m.get_surface_area() / (0.433 * edge * edge))
        if 50 <= target < len(m.triangles):
            m = m.simplify_quadric_decimation(target)
            m.remove_degenerate_triangles()
            m.remove_unreferenced_vertices()
        vertices, triangles = np.asarray(m.vertices).copy(), np.asarray(m.triangles, dtype=np.int64).copy()
    return SurfaceMesh(vertices, triangles, time.perf_counter() - t0), T
