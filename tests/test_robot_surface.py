"""The contact surface: rebuilt smooth from the cloud, sharp where the object is, checked before any motion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tergodic_cli.capture import CaptureConfig, capture_cloud
from tergodic_cli.capture.filters import mean_spacing
from tergodic_cli.errors import TergodicError
from tergodic_cli.robot.surface import (CRINKLE_DEG, check_surface, curved_edge, dihedral_angles, oriented_normals,
                                        reconstruct_mesh, source_mesh, surface_figures)


def _sphere_cloud(radius: float, n: int, seed: int = 0) -> np.ndarray:
    """``n`` points spread evenly (open3d's Poisson disk, seeded) on a sphere of ``radius`` m about the origin."""
    import open3d as o3d

    o3d.utility.random.seed(seed)
    m = o3d.geometry.TriangleMesh.create_sphere(radius, 60)
    return np.asarray(m.sample_points_poisson_disk(n, init_factor=5).points).copy()


def _rebuilt(points: np.ndarray, side: str = "outward"):
    h = mean_spacing(points)
    n = oriented_normals(points, side)
    mesh = reconstruct_mesh(points, n, h, curved_edge(points, n, 0.01))
    return mesh, surface_figures(mesh, points, h, n)


def test_dihedral_angles_of_known_folds():
    # Two triangles folded by a known angle about their shared edge, either winding: the fold, one
    # interior edge, four border edges.
    for fold in (0.0, 30.0, 90.0, 150.0):
        a = math.radians(fold)
        V = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -math.cos(a), math.sin(a)]], float)
        for T in ([[0, 1, 2], [1, 0, 3]], [[0, 1, 2], [0, 1, 3]]):
            angle, border, nonmanifold = dihedral_angles(V, np.array(T))
            assert angle == pytest.approx([fold], abs=1e-6) and border == 4 and nonmanifold == 0


def test_sphere_surface_is_smooth_and_on_the_sphere():
    R = 0.06
    pts = _sphere_cloud(R, 6000)
    mesh, fig = _rebuilt(pts)
    assert fig["method"] == "poisson"  # a closed cloud
    assert fig["dihedral_p95_deg"] < 15.0
    assert fig["border_edges"] == 0 and fig["coverage"] > 0.99
    # every vertex on the analytic sphere (within a fifth of the 2.3 mm point spacing)
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert np.max(np.abs(r - R)) < 0.5e-3
    # neither shrunk by smoothing nor inflated: the mean radius within 0.2 mm (the facets' chord sag
    # of ~10 mm triangles on 60 mm is ~0.2 mm, inside the sphere)
    assert abs(float(np.mean(r)) - R) < 0.2e-3
    check_surface(fig)  # not refused


def test_torus_surface_meets_the_goal_and_stays_on_the_torus():
    # issue 24's goal on a smooth closed object with two curvatures: dihedral p95 <= 15 deg, and
    # every vertex within 0.25 mm (a tenth of the 2.4 mm spacing) of the analytic torus; its mean
    # signed distance within 0.1 mm (smoothing neither shrinks nor inflates it)
    import open3d as o3d

    R, r = 0.05, 0.02
    o3d.utility.random.seed(0)
    pts = np.asarray(o3d.geometry.TriangleMesh.create_torus(R, r, 120, 60).sample_points_poisson_disk(6000, init_factor=5).points)
    mesh, fig = _rebuilt(pts.copy())
    assert fig["method"] == "poisson" and fig["border_edges"] == 0 and fig["coverage"] > 0.99
    assert fig["dihedral_p95_deg"] <= 15.0 and fig["dihedral_smooth_p95_deg"] <= 15.0
    V = mesh.vertices
    d = np.hypot(np.linalg.norm(V[:, :2], axis=1) - R, V[:, 2]) - r
    assert np.max(np.abs(d)) < 0.25e-3 and abs(float(np.mean(d))) < 0.1e-3
    check_surface(fig)


def test_noisy_sphere_is_smoothed_but_not_moved():
    # A 30 mm sphere sampled with 0.3 mm of noise: the Poisson surface follows part of the noise,
    # the ladder's level misses the 12 deg goal and is Taubin-faired; the result meets the issue's
    # 15 deg and stays on the sphere: every vertex within the noise's 2 sigma plus h/4 (the fairing's
    # limit), the mean radius within 0.1 mm.
    R, sigma = 0.03, 0.0003
    pts = _sphere_cloud(R, 3000) + np.random.default_rng(0).normal(0.0, sigma, (3000, 3))
    mesh, fig = _rebuilt(pts)
    assert fig["method"] == "poisson" and fig["dihedral_p95_deg"] <= 15.0
    rad = np.linalg.norm(mesh.vertices, axis=1)
    assert np.max(np.abs(rad - R)) < 2 * sigma + 0.25 * fig["spacing_mm"] * 1e-3
    assert abs(float(np.mean(rad)) - R) < 0.1e-3
    check_surface(fig)


def test_outward_normals_of_a_union_of_blobs_face_out():
    # A body with a head, arms and ears (a union of spheres, each sampled where it is outside the
    # others): the spanning tree's sign flips across the concave creases where the pieces meet
    # (2.5 % of the points before the ray test); each point's normal must point out of its own
    # sphere, the true outside there.
    import open3d as o3d

    blobs = [((0, 0, 0.04), 0.04), ((0, 0, 0.095), 0.028), ((0.035, 0, 0.06), 0.015), ((-0.035, 0, 0.06), 0.015),
             ((0.02, 0, 0.125), 0.01), ((-0.02, 0, 0.125), 0.01)]
    o3d.utility.random.seed(0)
    pts, out = [], []
    for c, r in blobs:
        p = np.asarray(o3d.geometry.TriangleMesh.create_sphere(r, 60).sample_points_poisson_disk(
            int(1.2e5 * 4 * math.pi * r * r), init_factor=5).points) + c
        keep = np.all([np.linalg.norm(p - c2, axis=1) > r2 for c2, r2 in blobs if c2 != c], axis=0)
        pts.append(p[keep])
        out.append((p[keep] - c) / r)
    pts, out = np.vstack(pts), np.vstack(out)
    n = oriented_normals(pts, "outward")
    assert np.mean(np.einsum("ij,ij->i", n, out) < 0) < 0.005


def test_box_keeps_its_sharp_edges_and_is_not_refused():
    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic="box"))
    a, b, c = 0.10, 0.08, 0.06  # synthetic.BOX_SIZE: the top at z = c, its four edges
    mesh, fig = _rebuilt(cap.points)
    check_surface(fig)  # a box's real edges are not crinkles
    assert fig["method"] == "ball_pivoting"  # five faces: an open sheet
    V, T = mesh.vertices, mesh.triangles
    # each top edge stays one sharp fold: along it the mesh folds by up to ~90 deg (ball pivoting's
    # triangles zig-zag over the samples next to it, so not every edge there takes the whole turn);
    # a Poisson surface smoothed over it folds at most 46-49 deg, spread over several triangles
    E = np.sort(np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]]), axis=1)
    edges, count = np.unique(E, axis=0, return_counts=True)
    inner = edges[count == 2]
    angle, _, _ = dihedral_angles(V, T)  # same order: unique sorted edges shared by two triangles
    mid = 0.5 * (V[inner[:, 0]] + V[inner[:, 1]])
    near_top = np.abs(mid[:, 2] - c) < 0.003
    for axis, half in ((0, a / 2), (0, -a / 2), (1, b / 2), (1, -b / 2)):
        on_edge = near_top & (np.abs(mid[:, axis] - half) < 0.003)
        assert on_edge.sum() >= 5
        assert np.max(angle[on_edge]) > 70.0 and np.percentile(angle[on_edge], 90) > 55.0
    # and the faces between the edges stay flat: triangles 8 mm inside the top face face up
    tc = V[T].mean(axis=1)
    n = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    inside_top = (np.abs(tc[:, 2] - c) < 1e-3) & (np.abs(tc[:, 0]) < a / 2 - 0.008) & (np.abs(tc[:, 1]) < b / 2 - 0.008)
    assert inside_top.sum() > 20 and np.min(np.abs(n[inside_top, 2])) > math.cos(math.radians(5))


def test_surface_that_misses_a_far_cluster_is_refused_in_one_line():
    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic="bowl"))
    far = _sphere_cloud(0.03, 600) + np.array([0.3, 0.0, 0.05])  # a second object 30 cm away: 14 % of the cloud
    pts = np.vstack([cap.points, far])
    _, fig = _rebuilt(pts)
    assert fig["coverage"] < 0.9
    with pytest.raises(TergodicError) as e:
        check_surface(fig)
    msg = str(e.value)
    assert "covers only" in msg and "\n" not in msg and e.value.fix and "crop" in e.value.fix


def test_crinkled_surface_is_refused():
    # A plate whose rebuilt triangles zig-zag (every other vertex row lifted by 2 mm over 3 mm):
    # close to the flat cloud, covering it, but folded ~70 deg at each row where the cloud does not
    # turn at all: refused as crinkled.
    x, y = np.meshgrid(np.linspace(-0.05, 0.05, 34), np.linspace(-0.05, 0.05, 34), indexing="ij")
    z = np.where(np.arange(34)[:, None] % 2 == 0, 0.0, 0.002) * np.ones_like(x)
    V = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    idx = np.arange(34 * 34).reshape(34, 34)
    T = np.concatenate([np.column_stack([idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()]),
                        np.column_stack([idx[:-1, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()])])
    from tergodic_cli.robot.surface import SurfaceMesh

    mesh = SurfaceMesh(V, T, 0.0, "ball_pivoting")
    cloud = V * [1, 1, 0] + [0, 0, 0.001]  # the flat plate the mesh should follow, 1 mm from every vertex
    up = np.tile([0.0, 0.0, 1.0], (len(cloud), 1))
    fig = surface_figures(mesh, cloud, mean_spacing(cloud), up)
    assert fig["fold_excess_p95_deg"] > CRINKLE_DEG and fig["coverage"] == 1.0
    with pytest.raises(TergodicError, match="crinkled"):
        check_surface(fig)
    check_surface(fig, rebuilt=False)  # a source mesh's folds are the object's own


def test_source_mesh_is_used_as_given_and_decimated_like_a_sim_object():
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_sphere(0.05, 80)
    V, T = np.asarray(m.vertices).copy(), np.asarray(m.triangles, dtype=np.int64).copy()
    coarse = source_mesh((V, T), edge=0.0)  # kept as is
    assert coarse.method == "source_mesh"
    np.testing.assert_array_equal(coarse.triangles, T)
    np.testing.assert_allclose(coarse.vertices, V)
    dec = source_mesh((V, T), edge=0.01)  # 12640 triangles of ~3 mm -> about the area / 10 mm triangles
    area = 4 * math.pi * 0.05**2
    assert len(dec.triangles) == pytest.approx(area / (0.433 * 0.01**2), rel=0.05)
    assert np.max(np.abs(np.linalg.norm(dec.vertices, axis=1) - 0.05)) < 1e-3
    with pytest.raises(TergodicError, match="source mesh"):
        source_mesh((V, T + len(V)))


def test_run_presses_on_the_mesh_a_hand_built_capture_carries():
    # A Capture built by hand that carries its source mesh (capture.mesh: vertices (n, 3) m, triangles
    # (k, 3), the points' frame): the run presses on that mesh, not on one rebuilt from the cloud,
    # and reports it in its summary.
    pytest.importorskip("pybullet")
    pytest.importorskip("pygafro")
    from tergodic_cli.backends.pybullet import RobotRun, explore_with_robot
    from tergodic_cli.basis import compute_basis
    from tergodic_cli.capture.artefact import Capture
    from tergodic_cli.explore import ExploreConfig, Explorer
    from tergodic_cli.robot import RobotConfig, robot_explore_config

    # a 12 cm square dish (z = 0.3 (x² + y²), 2 mm deep at the corners: a flat cloud defeats the normals'
    # spanning tree) of 10 mm grid triangles, sampled every 3 mm
    g = np.linspace(-0.06, 0.06, 13)
    x, y = np.meshgrid(g, g, indexing="ij")
    V = np.column_stack([x.ravel(), y.ravel(), 0.3 * (x.ravel() ** 2 + y.ravel() ** 2)])
    idx = np.arange(13 * 13).reshape(13, 13)
    T = np.concatenate([np.column_stack([idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()]),
                        np.column_stack([idx[:-1, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()])]).astype(np.int64)
    rng = np.random.default_rng(0)
    s = np.linspace(-0.057, 0.057, 39)
    px, py = np.meshgrid(s, s, indexing="ij")
    pts = np.column_stack([px.ravel(), py.ravel(), np.zeros(px.size)]) + rng.normal(0, 2e-4, (px.size, 3)) * [1, 1, 0]
    pts[:, 2] = 0.3 * (pts[:, 0] ** 2 + pts[:, 1] ** 2)
    target = (np.linalg.norm(pts[:, :2] - [0.02, 0.0], axis=1) < 0.02).astype(float)
    cap = Capture(pts, None, target, {"spacing_h_m": mean_spacing(pts)})
    cap.mesh = (V, T)
    basis = compute_basis(cap.points, 40, 30)
    cfg = RobotConfig(move_speed=1.6, hover_height=0.02)
    ec = robot_explore_config(ExploreConfig(nk=40, seed=0, agent_radius=0.008), cfg.explore_dt)
    start = pts[np.argmin(np.linalg.norm(pts[:, :2] - [0.02, 0.0], axis=1))][None]

    with RobotRun(cap, Explorer(basis, target, ec, start, on_event=lambda m: None), cfg) as run:
        assert run.mesh_source == "source_mesh" and run.surface["method"] == "source_mesh"
        np.testing.assert_array_equal(run.mesh.triangles, T)  # coarser than mesh_edge: kept as given
        np.testing.assert_allclose(run.mesh.vertices, V)
    out = explore_with_robot(cap, Explorer(basis, target, ec, start, on_event=lambda m: None), cfg, 5)
    assert out["stop_reason"] == "completed" and out["mesh_source"] == "source_mesh"
    cs = out["contact_surface"]
    # the dish's folds: neighbouring facet normals 10 mm apart on a curvature of 0.6 /m: ~0.3 deg
    assert cs["triangles"] == len(T) and cs["border_edges"] == 4 * 12 and cs["dihedral_p95_deg"] < 1.0
    assert cs["coverage"] == 1.0
