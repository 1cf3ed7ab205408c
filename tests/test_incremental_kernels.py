"""The compiled step kernels against their reference forms: the KD-tree against scipy's
cKDTree, the CGA fit/projection against geometry.py, the cubic slope against gradient.py,
the Jacobi eigensolver against LAPACK, and the heap against sorting."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import fibonacci_sphere, jittered_square
from scipy.spatial import cKDTree

from tergodic_cli.explore import kernels as K
from reference_geometry import fit_primitive, orient, project_onto, tangent_basis
from reference_geometry import fit_cubic


@pytest.fixture(scope="module")
def cloud():
    rng = np.random.default_rng(0)
    return np.vstack([fibonacci_sphere(3000, 0.1), rng.uniform(-0.12, 0.12, (500, 3))])


def test_knn_and_ball_queries_equal_scipy(cloud):
    tree = K.tree_build(cloud)
    ref = cKDTree(cloud)
    rng = np.random.default_rng(1)
    idx = np.empty(20, np.int64)
    d2 = np.empty(20)
    buf = np.empty(len(cloud), np.int64)
    for x in rng.uniform(-0.15, 0.15, (200, 3)):
        K.tree_knn(*tree, x, 20, idx, d2)
        want_d, want_i = ref.query(x, k=20)
        np.testing.assert_allclose(np.sqrt(d2), want_d, rtol=1e-12, atol=1e-15)
        assert set(idx) == set(want_i)
        assert K.nearest_distance(*tree, x) == pytest.approx(want_d[0], rel=1e-12)
        for r in (0.005, 0.02, 0.06):
            cnt = K.tree_ball(*tree, x, r, buf)
            want = set(ref.query_ball_point(x, r))
            got = set(buf[:cnt])
            # Points within 1e-12 of the sphere may go either way.
            border = set(np.flatnonzero(np.abs(np.linalg.norm(cloud - x, axis=1) - r) < 1e-12))
            assert got - border == want - border
            assert cnt == len(got)  # no duplicates


def test_tree_of_a_tiny_and_a_degenerate_cloud():
    pts = np.zeros((5, 3))
    pts[:, 0] = np.arange(5)  # collinear, fewer points than a leaf
    tree = K.tree_build(pts)
    idx, d2 = np.empty(3, np.int64), np.empty(3)
    K.tree_knn(*tree, np.array([2.2, 0.0, 0.0]), 3, idx, d2)
    assert list(idx) == [2, 3, 1]
    np.testing.assert_allclose(d2, [0.04, 0.64, 1.44])


def test_jacobi_eigenvector_equals_lapack():
    rng = np.random.default_rng(2)
    V, W = np.empty((5, 5)), np.empty((5, 5))
    for _ in range(50):
        X = rng.normal(size=(20, 5)) * rng.uniform(0.01, 10, 5)
        A = X.T @ X
        col = K.sym_eig_min(A, 5, V, W)
        w, vecs = np.linalg.eigh(A)
        assert W[col, col] == pytest.approx(w[0], rel=1e-9, abs=1e-12 * w[-1])
        assert abs(abs(V[:, col] @ vecs[:, 0]) - 1) < 1e-9


def _patch(kind, rng, k=20):
    t1, t2 = tangent_basis(np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]))
    if kind == "sphere":
        c = np.array([0.1, 0.2, -0.1])
        d = rng.normal(size=(k, 3)) * [1, 1, 0.2] + [0, 0, 3]
        return c + 0.03 * d / np.linalg.norm(d, axis=1, keepdims=True)
    uv = rng.uniform(-0.006, 0.006, (k, 2))
    n = np.array([1.0, 0, 0]) if kind == "vertical" else np.cross(t1, t2)
    a, b = tangent_basis(n)
    pts = np.array([0.2, 0.1, 0.05]) + uv[:, :1] * a + uv[:, 1:] * b
    if kind == "noisy":
        pts += rng.normal(scale=3e-5, size=pts.shape)
    return pts


@pytest.mark.parametrize("kind", ["sphere", "vertical", "flat", "noisy"])
def test_fit_and_projection_equal_the_geometry_module(kind):
    rng = np.random.default_rng(3)
    xp, nn = np.empty(3), np.empty(3)
    for _ in range(20):
        pts = _patch(kind, rng)
        x = pts.mean(0) + rng.normal(scale=0.002, size=3)
        ref_n = rng.normal(size=3)
        status = K.fit_project(pts, np.arange(len(pts)), len(pts), x, ref_n, xp, nn)
        want_x, want_n = project_onto(fit_primitive(pts), x)
        assert status == 0
        np.testing.assert_allclose(xp, want_x, atol=1e-10)
        np.testing.assert_allclose(nn, orient(want_n, ref_n), atol=1e-8)


def test_fit_falls_back_to_the_nearest_point_on_a_degenerate_patch():
    pts = np.tile([0.1, 0.2, 0.3], (20, 1))
    xp, nn = np.empty(3), np.empty(3)
    ref = np.array([0.0, 0.0, 1.0])
    assert K.fit_project(pts, np.arange(20), 20, np.array([0.0, 0.0, 0.0]), ref, xp, nn) == 1
    np.testing.assert_array_equal(xp, pts[0])
    np.testing.assert_array_equal(nn, ref)


@pytest.mark.parametrize("degree", [3, 1])
def test_cubic_slope_equals_the_gradient_module(degree):
    rng = np.random.default_rng(4)
    for _ in range(30):
        uv = rng.uniform(-0.006, 0.006, (20, 2))
        vals = rng.normal(size=20)
        w = np.exp(-(133.0**2) * (uv**2).sum(1))
        want = fit_cubic(uv, vals, w, degree)[1:3]
        got = K.cubic_slope(uv, vals, w, 20, degree)
        np.testing.assert_allclose(got, want, rtol=1e-7, atol=1e-9 * np.abs(want).max())


def test_cubic_slope_on_collinear_samples_takes_the_least_squares_fallback():
    u = np.linspace(-0.005, 0.005, 20)
    uv = np.column_stack([u, np.zeros_like(u)])
    got = K.cubic_slope(uv, 3.0 * u, np.ones(20), 20, 3)
    assert np.all(np.isfinite(got))
    assert got[0] == pytest.approx(3.0, rel=1e-6)
    np.testing.assert_allclose(got, fit_cubic(uv, 3.0 * u)[1:3], rtol=1e-6, atol=1e-9)


def test_heap_pops_in_key_order():
    rng = np.random.default_rng(5)
    keys = rng.uniform(size=300)
    hk, hi = np.empty(300), np.empty(300, np.int64)
    size = 0
    for j, key in enumerate(keys):
        size = K.heap_push(hk, hi, size, key, j)
    out = []
    while size:
        key, j, size = K.heap_pop(hk, hi, size)
        out.append(j)
    assert out == list(np.argsort(keys, kind="stable"))


def test_the_explorer_tree_on_a_flat_grid_matches_scipy_including_ties():
    # A jittered grid has near-ties at the k-th neighbour; the distances must still agree.
    pts = jittered_square(30, 0.1, seed=3)
    tree = K.tree_build(pts)
    ref = cKDTree(pts)
    idx, d2 = np.empty(20, np.int64), np.empty(20)
    for x in pts[::17]:
        K.tree_knn(*tree, x, 20, idx, d2)
        np.testing.assert_allclose(np.sqrt(d2), ref.query(x, k=20)[0], rtol=1e-12, atol=1e-15)


def test_ball_query_keeps_the_descent_order(cloud):
    # The footprint's order fixes the order of the running sums: the shortcut for boxes wholly
    # inside the ball must give the points a full descent gives, in the same (ascending) order.
    perm, nodes, boxes, tpts = K.tree_build(cloud)
    tree = (np.arange(len(perm)), nodes, boxes, tpts)  # the explorer's internal order
    buf = np.empty(len(cloud), np.int64)
    rng = np.random.default_rng(9)
    for x in rng.uniform(-0.12, 0.12, (100, 3)):
        for r in (0.01, 0.05, 0.3):
            cnt = K.tree_ball(*tree, x, r, buf)
            d = tpts - x
            want = np.flatnonzero((d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]) + d[:, 2] * d[:, 2] <= r * r)
            np.testing.assert_array_equal(buf[:cnt], want)


def test_wide_heap_pops_the_smallest_key_between_pushes():
    rng = np.random.default_rng(6)
    keys = rng.integers(0, 50, 2000).astype(float)  # many ties, several levels of 8 children
    hk, hi = np.empty(2000), np.empty(2000, np.int64)
    size = 0
    waiting = {}
    for j, key in enumerate(keys):
        size = K.heap_push(hk, hi, size, key, j)
        waiting[j] = key
        if j % 3 == 2:  # pops between pushes
            key, i, size = K.heap_pop(hk, hi, size)
            assert key == min(waiting.values()) == waiting.pop(i)
    while size:
        key, i, size = K.heap_pop(hk, hi, size)
        assert key == min(waiting.values()) == waiting.pop(i)
    assert not waiting
