"""A cloud much denser than a 3 mm capture has its basis on one stand-in per 3 mm voxel (issue 27,
item 5): the spectrum still is the surface's, every point maps to a stand-in in its own voxel, the
cache keeps the map through a rigid motion and a reordering, and the explorer keeps its target,
coverage and heat per cloud point."""

from __future__ import annotations

import numpy as np
import pytest

from tergodic_cli.basis import BasisConfig, compute_basis, get_basis
from tergodic_cli.capture.filters import FIELD_VOXEL
from tergodic_cli.capture.synthetic import SPHERE_RADIUS, generate_synthetic
from tergodic_cli.explore import ExploreConfig, Explorer

N_DENSE = 32_000
NK = 16  # l = 0 .. 3 of the sphere: 1 + 3 + 5 + 7
DIAGONAL = np.sqrt(3.0) * FIELD_VOXEL


@pytest.fixture(scope="module")
def sphere():
    """The built-in sphere (radius 6 cm) with ~32k uniform random points (spacing ~0.6 mm), and its basis."""
    spacing = float(np.sqrt(4 * np.pi * SPHERE_RADIUS**2 / N_DENSE))
    cloud = generate_synthetic("sphere", "X", seed=4, spacing=spacing)
    return cloud, compute_basis(cloud.points, NK, 30)


def test_dense_sphere_spectrum_is_the_sphere(sphere):
    """Eigenvalues of the stand-ins' basis against the sphere's l(l+1)/R², each l's 2l+1 copies."""
    cloud, basis = sphere
    n = len(cloud.points)
    assert basis.thinned
    m = len(basis.sel)
    # about the 3 mm capture's size (the sphere's area over 9 mm², less the voxels a curved sheet cuts)
    assert 4000 < m < 9000 and m < n / 3
    assert basis.evecs.shape == (m, NK) and basis.mass.shape == (m,) and basis.L.shape == (m, m)
    exact = np.array([l * (l + 1) for l in range(4) for _ in range(2 * l + 1)]) / SPHERE_RADIUS**2
    assert basis.evals[0] == 0.0
    # the robust Laplacian on a ~3 mm random sampling is a few per cent low; 6 % bounds it
    np.testing.assert_allclose(basis.evals[1:], exact[1:], rtol=0.06)
    # the mass is the sphere's area, and every point's share sums back to it
    assert basis.mass.sum() == pytest.approx(4 * np.pi * SPHERE_RADIUS**2, rel=0.01)
    assert basis.point_mass.shape == (n,)
    assert basis.point_mass.sum() == pytest.approx(basis.mass.sum(), rel=1e-12)


def test_every_point_maps_to_a_stand_in_of_its_voxel(sphere):
    cloud, basis = sphere
    pts, sel, rep = cloud.points, basis.sel, basis.rep
    assert rep.shape == (len(pts),) and len(np.unique(sel)) == len(sel)
    assert np.array_equal(rep[sel], np.arange(len(sel)))  # a stand-in stands for itself
    assert np.linalg.norm(pts - pts[sel[rep]], axis=1).max() <= DIAGONAL
    # one stand-in per occupied voxel: the voxels of the stand-ins are those of the cloud, each once
    cell = np.floor((pts - pts.min(axis=0)) / FIELD_VOXEL).astype(np.int64)
    assert len(np.unique(cell, axis=0)) == len(sel)
    assert np.array_equal(cell[sel[rep]], cell)


def test_cache_keeps_the_map_through_a_rigid_motion_and_a_reordering(sphere, tmp_path):
    cloud, _ = sphere
    cfg = BasisConfig(nk=NK)
    first, hit = get_basis(cloud.points, cfg, cache_dir=tmp_path)
    assert not hit and first.meta["n_standins"] == len(first.sel) < first.meta["n_points"]
    rng = np.random.default_rng(1)
    perm = rng.permutation(len(cloud.points))
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    moved = cloud.points[perm] @ R.T + [0.1, -0.2, 0.3]
    again, hit = get_basis(moved, cfg, cache_dir=tmp_path)
    assert hit
    np.testing.assert_array_equal(again.evals, first.evals)
    # point i of the moved cloud is point perm[i]: same stand-in row, and the stand-in is the same point
    np.testing.assert_array_equal(again.rep, first.rep[perm])
    np.testing.assert_array_equal(perm[again.sel], first.sel)
    assert np.linalg.norm(moved - moved[again.sel[again.rep]], axis=1).max() <= DIAGONAL * (1 + 1e-9)


def test_a_dense_cloud_too_small_for_stand_ins_keeps_every_point():
    """A 2.4 cm patch at 0.5 mm: 64 stand-ins cannot carry 80 eigenpairs, so the whole cloud does."""
    g = np.arange(48) * 0.0005
    x, y = np.meshgrid(g, g)
    pts = np.column_stack([x.ravel(), y.ravel(), 0.5 * (x.ravel() ** 2 + 2 * y.ravel() ** 2)])
    basis = compute_basis(pts, 80, 30)
    assert not basis.thinned and basis.evecs.shape == (len(pts), 80)


@pytest.mark.parametrize("integrator", ["spectral", "implicit"])
def test_explorer_keeps_target_coverage_and_heat_per_point(sphere, integrator):
    cloud, basis = sphere
    n = len(cloud.points)
    target = cloud.mask.astype(float)
    cfg = ExploreConfig(steps=20, nk=NK, seed=0, integrator=integrator)
    start = cloud.points[np.argmax(cloud.points[:, 2])][None, :]
    ex = Explorer(basis, target, cfg, start)
    for _ in range(cfg.steps):
        ex.step()
    cov, heat = ex.coverage, ex.heat
    assert cov.shape == (n,) and heat.shape == (n,) and np.all(np.isfinite(heat))
    # a point's coverage is its stand-in's: equal within each voxel, and deposited where the agent went
    np.testing.assert_array_equal(cov, cov[basis.sel[basis.rep]])
    near = np.linalg.norm(cloud.points - ex.positions[0], axis=1) < cfg.agent_radius / 2
    assert near.any() and np.all(cov[near] > 0)
    # the heat is a field on the stand-ins too; its start was p̄, positive on the target
    np.testing.assert_array_equal(heat, heat[basis.sel[basis.rep]])
    score = ex.score()
    assert 0.0 < score["touched_fraction"] < 1.0 and 0.0 < score["ergodicity"] < 1.0


def test_size_guard_counts_the_points_the_basis_is_on(sphere):
    """--max-points bounds the basis' points: a dense cloud's stand-ins, not its raw points."""
    from tergodic_cli.capture.filters import basis_size, mean_spacing
    from tergodic_cli.capture.pipeline import check_size
    from tergodic_cli.errors import TergodicError

    cloud, basis = sphere
    n = len(cloud.points)
    m = basis_size(cloud.points, mean_spacing(cloud.points), NK, 30)
    assert m == len(basis.sel) < n
    check_size("cap", n, n - 1, m)  # more raw points than the limit: accepted, the basis is on m
    with pytest.raises(TergodicError) as err:
        check_size("cap", n, m - 1, m)
    assert f"{m:,} 3 mm stand-ins" in str(err.value) and f"--max-points {m}" in err.value.fix


def test_stray_points_and_duplicates_by_their_definitions():
    """The dense-capture filters (one k-nearest query, one sort) against their definitions: fewer than
    ISOLATED_MIN others within ISOLATED_RADIUS median spacings (ball counts), and np.unique."""
    from scipy.spatial import cKDTree

    from tergodic_cli.capture.filters import ISOLATED_MIN, ISOLATED_RADIUS, count_duplicates, isolated_points

    rng = np.random.default_rng(7)
    sheet = rng.random((20_000, 3)) * [0.1, 0.1, 0.001]
    pair = np.array([[0.3, 0.3, 0.3], [0.3, 0.3, 0.3001]])  # two strays next to each other: one other each
    pts = np.vstack([sheet, rng.random((40, 3)) * 0.3 + 0.15, pair])
    tree = cKDTree(pts)
    r = ISOLATED_RADIUS * float(np.median(tree.query(pts, k=2)[0][:, 1]))
    expected = tree.query_ball_point(pts, r, return_length=True) - 1 < ISOLATED_MIN
    assert expected[-2:].all() and expected.sum() >= 42
    np.testing.assert_array_equal(isolated_points(pts), expected)
    dup = np.vstack([pts, pts[[5, 9, 9]]])
    assert count_duplicates(dup) == len(dup) - len(np.unique(dup, axis=0)) == 3


def test_a_dense_clouds_score_uses_its_target_at_the_fields_resolution(sphere):
    """On stand-ins the explorer seeks each voxel's mean p (a 3 mm capture's own rule); its ε scores that
    target, and the captured per-point p is scored too: both against metrics.coverage_score of the path."""
    from tergodic_cli.explore.metrics import coverage_score

    cloud, basis = sphere
    target = cloud.mask.astype(float)
    cfg = ExploreConfig(steps=40, nk=NK, seed=0)
    start = cloud.points[np.argmax(cloud.points[:, 2])][None, :]
    ex = Explorer(basis, target, cfg, start)
    path = [ex.positions.copy()]
    for _ in range(cfg.steps):
        ex.step()
        path.append(ex.positions.copy())
    X = np.array(path)[1:]
    # the voxel means, group by group (the basis' map; the points' lumped masses as weights)
    w = basis.point_mass
    p_field = np.empty_like(target)
    for g in np.unique(basis.rep):
        members = basis.rep == g
        p_field[members] = (w[members] @ target[members]) / w[members].sum()
    assert np.any((p_field > 0) & (p_field < 1))  # the marking's edges are soft at 3 mm
    score = ex.score()
    want = coverage_score(cloud.points, p_field, X, cfg.agent_radius, basis.h)["ergodicity"]
    raw = coverage_score(cloud.points, target, X, cfg.agent_radius, basis.h)["ergodicity"]
    assert score["ergodicity"] == pytest.approx(want, rel=1e-9)
    assert score["ergodicity_point_target"] == pytest.approx(raw, rel=1e-9)
    assert abs(want - raw) > 1e-3  # the two targets do differ
