"""The synthetic objects of the coverage tests (issue 13 item 4), checked against their geometry.

Every expectation is written from the object's description (its sizes in metres), not from
the generator's code: a 3 cm hole at (25, 25) mm, a torus R 6 cm r 2 cm resting on the table,
a 10 x 8 x 6 cm box, walls 4 mm apart, an ellipsoid 8 x 6 x 5 cm seen from +x, 27 deg up.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from tergodic_cli.capture import CaptureConfig, capture_cloud, load_capture
from tergodic_cli.capture.synthetic import COVERAGE_OBJECTS, OBJECTS, generate_synthetic
from tergodic_cli.errors import TergodicError


def _components(points: np.ndarray, radius: float) -> int:
    """Connected components of the graph joining points closer than ``radius`` (m)."""
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray")
    n = len(points)
    from scipy.sparse import coo_matrix

    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[0]


def test_coverage_objects_list_the_issues_geometry():
    objs = list(COVERAGE_OBJECTS)
    kinds = {o.object for o in objs}
    assert {"holed-plate", "thin-mug", "torus", "box", "partial"} <= kinds
    assert any(o.object == "bowl" and 0.001 <= o.noise <= 0.002 for o in objs)  # "1-2 mm Gaussian noise"
    assert any(o.object == "torus" and o.marking == "patches" for o in objs)
    assert all(o.object in OBJECTS for o in objs)


@pytest.mark.parametrize("obj", COVERAGE_OBJECTS, ids=lambda o: f"{o.object}-{o.marking}-{o.noise}")
def test_coverage_objects_have_a_few_thousand_points_and_a_target_at_3mm(obj):
    cap = capture_cloud(CaptureConfig(synthetic=obj.object, marking=obj.marking, noise=obj.noise, voxel=0.003))
    n_target = int((cap.target > 0).sum())
    assert 2500 <= cap.n_points <= 10_000
    assert 50 <= n_target <= 0.2 * cap.n_points
    assert cap.meta["config"]["noise"] == obj.noise


def test_holed_plate_has_no_point_in_the_hole_and_target_at_its_edge():
    cloud = generate_synthetic("holed-plate", "X", seed=0)
    d = np.hypot(cloud.points[:, 0] - 0.025, cloud.points[:, 1] - 0.025)
    assert d.min() >= 0.015
    assert np.all(np.abs(cloud.points[d < 0.03, 2]) < 1e-12)  # the hole is in the flat well
    # A sheet all around the hole (no cut to the rim), and the marking at its edge on both sides.
    ring = d < 0.018
    angles = np.arctan2(cloud.points[ring, 1] - 0.025, cloud.points[ring, 0] - 0.025)
    assert np.histogram(angles, bins=12, range=(-np.pi, np.pi))[0].min() > 0
    edge_target = cloud.points[ring & cloud.mask]
    assert len(edge_target) > 0
    side = edge_target[:, :2].sum(axis=1) - 0.05  # along the X's arm through the hole: before and beyond it
    assert side.min() < -0.01 and side.max() > 0.01


def test_torus_points_satisfy_its_equation():
    for seed in (0, 1):
        p = generate_synthetic("torus", "patches", seed=seed).points
        rho = np.hypot(p[:, 0], p[:, 1])
        np.testing.assert_allclose(np.hypot(rho - 0.06, p[:, 2] - 0.02), 0.02, rtol=0, atol=1e-9)
        assert p[:, 2].min() == pytest.approx(0.0, abs=2e-4) and p[:, 2].max() == pytest.approx(0.04, abs=2e-4)


def test_torus_is_sampled_uniformly_in_area():
    # Area on the outer half (rho > R) over the inner half is (pi R + 2 r) / (pi R - 2 r).
    p = generate_synthetic("torus", "X", seed=0).points
    outer = (np.hypot(p[:, 0], p[:, 1]) > 0.06).sum()
    assert outer / (len(p) - outer) == pytest.approx((np.pi * 0.06 + 0.04) / (np.pi * 0.06 - 0.04), rel=0.05)


def test_torus_patches_are_two_separate_targets_after_the_voxel():
    cap = capture_cloud(CaptureConfig(synthetic="torus", marking="patches", voxel=0.003))
    target = cap.points[cap.target > 0]
    assert _components(target, 0.0075) == 2
    # On opposite sides of the hole, each about a 2.5 cm disc.
    left, right = target[target[:, 0] < 0], target[target[:, 0] > 0]
    assert len(left) > 20 and len(right) > 20
    for half in (left, right):
        assert np.ptp(half[:, 1]) == pytest.approx(0.025, abs=0.006)
    assert np.linalg.norm(left.mean(axis=0) - right.mean(axis=0)) > 0.1


@pytest.mark.parametrize("kind, centre, radius", [("bowl", (0, 0, 0.08), 0.08), ("sphere", (0, 0, 0.06), 0.06)])
def test_noise_has_the_requested_std_along_the_normal(kind, centre, radius):
    sigma = 0.0015
    noisy = generate_synthetic(kind, "X", seed=4, noise=sigma)
    residual = np.linalg.norm(noisy.points - np.asarray(centre), axis=1) - radius  # along the normal of a sphere
    assert residual.std() == pytest.approx(sigma, rel=0.2)
    assert abs(residual.mean()) < 0.1 * sigma
    # Only along the normal: the same seed without noise differs by a purely normal offset.
    clean = generate_synthetic(kind, "X", seed=4)
    delta = noisy.points - clean.points
    radial = (clean.points - np.asarray(centre)) / radius
    tangential = delta - np.sum(delta * radial, axis=1, keepdims=True) * radial
    assert np.abs(tangential).max() < 1e-12
    np.testing.assert_array_equal(noisy.colors, clean.colors)
    np.testing.assert_array_equal(noisy.mask, clean.mask)


def test_noise_on_flat_faces_is_along_their_normals():
    sigma = 0.001
    p = generate_synthetic("box", "X", seed=2, noise=sigma).points
    top = (np.abs(p[:, 0]) < 0.045) & (np.abs(p[:, 1]) < 0.035) & (p[:, 2] > 0.055)
    assert (p[top, 2] - 0.06).std() == pytest.approx(sigma, rel=0.2)


def test_box_points_lie_on_its_five_faces_and_the_x_straddles_an_edge():
    cloud = generate_synthetic("box", "X", seed=0)
    x, y, z = cloud.points.T
    eps = 1e-12
    assert np.all((np.abs(x) <= 0.05 + eps) & (np.abs(y) <= 0.04 + eps) & (z >= -eps) & (z <= 0.06 + eps))
    on_face = (np.abs(z - 0.06) < eps) | (np.abs(np.abs(x) - 0.05) < eps) | (np.abs(np.abs(y) - 0.04) < eps)
    assert on_face.all()
    for face in (np.abs(z - 0.06) < eps, np.abs(x - 0.05) < eps, np.abs(x + 0.05) < eps,
                 np.abs(y - 0.04) < eps, np.abs(y + 0.04) < eps):
        assert face.sum() > 1000
    # The marking is on both faces of one sharp edge, and reaches it.
    top, side = cloud.mask & (np.abs(z - 0.06) < eps), cloud.mask & (np.abs(x - 0.05) < eps)
    assert top.sum() > 100 and side.sum() > 100
    assert (0.05 - x[top]).min() < 0.002 and (0.06 - z[side]).min() < 0.002


def test_thin_mug_has_two_walls_4mm_apart_rim_and_floor():
    cloud = generate_synthetic("thin-mug", "X", seed=0)
    r, z = np.hypot(cloud.points[:, 0], cloud.points[:, 1]), cloud.points[:, 2]
    eps = 1e-12
    outer, inner = np.abs(r - 0.04) < eps, np.abs(r - 0.036) < eps
    rim = (np.abs(z - 0.10) < eps) & (r >= 0.036 - eps) & (r <= 0.04 + eps)
    floor = (np.abs(z - 0.006) < eps) & (r <= 0.036 + eps)
    assert (outer | inner | rim | floor).all()
    assert outer.sum() > inner.sum() > 1000 and rim.sum() > 50 and floor.sum() > 500
    assert z[outer].min() < 0.002 and z[inner].min() >= 0.006 - eps
    assert cloud.mask.any() and np.all(outer[cloud.mask])  # the marking is on the outside


def test_partial_scan_keeps_only_the_side_facing_its_camera():
    cloud = generate_synthetic("partial", "X", seed=0)
    a, b, c = 0.08, 0.06, 0.05
    x, y, z = cloud.points.T
    np.testing.assert_allclose((x / a) ** 2 + (y / b) ** 2 + ((z - c) / c) ** 2, 1.0, atol=1e-9)
    grad = np.column_stack([x / a**2, y / b**2, (z - c) / c**2])
    facing = grad @ np.array([1.0, 0.0, 0.5])
    assert facing.min() > 0  # no point whose normal faces away from the camera
    assert not np.any((x < 0) & (z < c))  # the far side, lower half, is missing ...
    assert np.linalg.norm(cloud.points - [-a, 0, c], axis=1).min() > 0.02  # ... and its far end
    assert 0.35 < len(x) / (4 * np.pi * 0.0595**2 / 0.0012**2) < 0.65  # ... about half of the blob
    # The marking reaches the boundary: some target points are nearly edge-on to the camera.
    cos = facing / np.linalg.norm(grad, axis=1) / np.linalg.norm([1.0, 0.0, 0.5])
    assert cos[cloud.mask].min() < 0.1


@pytest.mark.parametrize("kind", OBJECTS)
def test_same_seed_same_cloud(kind):
    a = generate_synthetic(kind, "dots", seed=7, spacing=0.003, noise=0.001)
    b = generate_synthetic(kind, "dots", seed=7, spacing=0.003, noise=0.001)
    c = generate_synthetic(kind, "dots", seed=8, spacing=0.003, noise=0.001)
    for f in ("points", "colors", "mask", "normals"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    assert a.points.shape != c.points.shape or not np.array_equal(a.points, c.points)


@pytest.mark.parametrize("kind", OBJECTS)
def test_normals_are_unit_and_noise_free_cloud_unchanged_by_the_option(kind):
    cloud = generate_synthetic(kind, "X", seed=1, spacing=0.003)
    np.testing.assert_allclose(np.linalg.norm(cloud.normals, axis=1), 1.0, atol=1e-12)
    assert cloud.points[:, 2].min() >= -1e-12  # resting on the table
    np.testing.assert_array_equal(generate_synthetic(kind, "X", seed=1, spacing=0.003, noise=0.0).points, cloud.points)


def test_capture_cli_noise_writes_provenance(tmp_path):
    res = run_cli("capture", "--synthetic", "bowl", "--noise", "0.0015", "--out", tmp_path / "cap")
    assert res.code == 0, res.err
    cap = load_capture(tmp_path / "cap")
    assert cap.meta["config"]["noise"] == 0.0015 and cap.meta["provenance"]["noise_m"] == 0.0015


@pytest.mark.parametrize("value, needle", [("-0.001", "not a standard deviation"), ("nan", "not a standard deviation"),
                                           ("inf", "not a standard deviation"), ("1.5", "METRES")])
def test_capture_cli_rejects_bad_noise(tmp_path, value, needle):
    res = run_cli("capture", "--synthetic", "bowl", "--noise", value, "--out", tmp_path / "out")
    assert_one_line_error(res, "--noise", needle)
    assert not (tmp_path / "out" / "capture.json").exists()


def test_capture_cli_noise_is_for_synthetic_objects_only(tmp_path):
    cloud = generate_synthetic("bowl", "X", seed=0, spacing=0.003)
    np.savez(tmp_path / "c.npz", points=cloud.points, colors=cloud.colors)
    assert_one_line_error(run_cli("capture", "--from", tmp_path / "c.npz", "--noise", "0.001", "--out", tmp_path / "out"),
                          "--noise", "synthetic")


def test_generator_rejects_bad_noise_in_one_line():
    with pytest.raises(TergodicError, match="not a standard deviation"):
        generate_synthetic("torus", "X", noise=-1.0)


@pytest.mark.parametrize("obj", COVERAGE_OBJECTS, ids=lambda o: f"{o.object}-{o.marking}")
def test_coverage_objects_precompute_and_explore(obj, tmp_path):
    cap = tmp_path / "cap"
    assert run_cli("capture", "--synthetic", obj.object, "--marking", obj.marking, "--noise", obj.noise,
                   "--out", cap).code == 0
    res = run_cli("precompute", cap, "--nk", "60")
    assert res.code == 0, res.err
    res = run_cli("explore", cap, "--robot", "kinematic", "--nk", "60", "--steps", "200", "--no-log", "--out", tmp_path / "run")
    assert res.code == 0, res.err
    traj = np.load(tmp_path / "run" / "trajectory.npz")
    assert all(np.isfinite(traj[k]).all() for k in traj.files if np.issubdtype(traj[k].dtype, np.floating))
