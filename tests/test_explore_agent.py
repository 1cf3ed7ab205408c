"""The explorer as a whole on synthetic clouds: limits, surface tracking, metrics, exploration
behaviour (uniform sphere, two patches), N agents, determinism and the robot-mode API."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import fibonacci_sphere, jittered_square
from reference_geometry import coverage_score, residual_ref

from tergodic_cli.basis import compute_basis
from tergodic_cli.capture.synthetic import generate_synthetic
from tergodic_cli.errors import TergodicError
from tergodic_cli.explore import ExploreConfig, Explorer, metrics as M

SPHERE_C, SPHERE_R = np.array([0.1, 0.0, 0.05]), 0.05


@pytest.fixture(scope="module")
def sphere():
    pts = fibonacci_sphere(1500, SPHERE_R) + SPHERE_C  # h ≈ 4.5 mm
    return pts, compute_basis(pts, 80, 30)


@pytest.fixture(scope="module")
def bowl():
    # Inner spherical cap (radius 8 cm, centre (0, 0, 0.08)) up to 70°: near-vertical walls at the rim.
    cloud = generate_synthetic("bowl", "X", seed=2, spacing=0.004)
    return cloud, compute_basis(cloud.points, 80, 30)


@pytest.fixture(scope="module")
def two_patch():
    pts = jittered_square(50, 0.2, seed=1)
    pts = pts[pts[:, 1] < 0.1]  # a 20 x 10 cm flat sheet, h ≈ 3.9 mm
    a, b = np.array([0.04, 0.05, 0.0]), np.array([0.16, 0.05, 0.0])
    in_a = np.linalg.norm(pts - a, axis=1) < 0.012
    in_b = np.linalg.norm(pts - b, axis=1) < 0.012
    return pts, compute_basis(pts, 120, 30), in_a, in_b, a, b


def _run(ex: Explorer, steps: int) -> dict[str, np.ndarray]:
    out = {k: [] for k in ("x", "v", "a", "n", "erg", "ref", "touched")}
    for _ in range(steps):
        ex.step()
        m = ex.metrics()
        out["x"].append(ex.positions.copy())
        out["v"].append(ex.velocities.copy())
        out["a"].append(ex.accelerations.copy())
        out["n"].append(ex.normals.copy())
        out["erg"].append(m["ergodicity"])
        out["ref"].append(m["residual_ref"])
        out["touched"].append(m["touched_fraction"])
    return {k: np.asarray(v) for k, v in out.items()}


@pytest.mark.parametrize("integrator", ["resolvent", "spectral"])
def test_agent_respects_its_limits_and_stays_on_the_sphere(sphere, integrator):
    pts, basis = sphere
    cfg = ExploreConfig(nk=80, agent_radius=0.012, integrator=integrator)
    ex = Explorer(basis, np.ones(len(pts)), cfg, pts[:1])
    r = _run(ex, 300)
    speed = np.linalg.norm(r["v"], axis=2)
    assert speed.max() <= cfg.v_max * (1 + 1e-12)
    assert np.median(speed[10:]) > 0.5 * cfg.v_max  # it does move (reversals pass through low speeds)
    assert np.linalg.norm(r["a"], axis=2).max() <= cfg.a_max * (1 + 1e-12)
    step = np.linalg.norm(np.diff(r["x"], axis=0), axis=2)
    assert step.max() <= 1.01 * cfg.v_max * cfg.dt  # projection may add a sliver of curvature
    # On the surface: within h (in fact to rounding: the CGA fit of exact sphere samples is the sphere).
    dist = np.abs(np.linalg.norm(r["x"] - SPHERE_C, axis=2) - SPHERE_R)
    assert dist.max() < 1e-3 * basis.h
    # Velocity tangent, normals the sphere's (outward, by the +z hint and continuity).
    radial = (r["x"] - SPHERE_C) / SPHERE_R
    assert np.abs(np.einsum("tij,tij->ti", r["v"], r["n"])).max() < 1e-12
    assert np.abs(np.abs(np.einsum("tij,tij->ti", r["n"], radial)) - 1).max() < 1e-6


def test_agent_tracks_a_bowl_with_steep_walls(bowl):
    cloud, basis = bowl
    cfg = ExploreConfig(nk=80, agent_radius=0.012)
    rim = cloud.points[np.argmax(cloud.points[:, 2])]  # start on the steepest wall
    ex = Explorer(basis, cloud.mask.astype(float), cfg, rim[None])
    r = _run(ex, 300)
    centre = np.array([0.0, 0.0, 0.08])
    dist = np.abs(np.linalg.norm(r["x"] - centre, axis=2) - 0.08)
    assert dist.max() < basis.h  # the sampled sheet is exact; the fit follows it closely
    assert np.linalg.norm(r["v"], axis=2).max() <= cfg.v_max * (1 + 1e-12)
    assert r["touched"][-1] > 0.5


def test_uniform_target_on_a_sphere_ergodicity_falls(sphere):
    pts, basis = sphere
    target = np.ones(len(pts))
    ex = Explorer(basis, target, ExploreConfig(nk=80, agent_radius=0.012), pts[:1])
    r = _run(ex, 500)
    assert 0.9 < r["erg"][0] < 1.0  # 1 is nothing covered: one footprint on a 1500-point sphere
    assert r["erg"][-1] < 0.75 * r["erg"][0]
    assert r["erg"][-1] < r["erg"][250] < r["erg"][10]
    # An agent that cannot move keeps its first value: the decrease is the exploration's doing.
    still = Explorer(basis, target, ExploreConfig(nk=80, agent_radius=0.012, v_max=1e-9), pts[:1])
    r_still = _run(still, 500)
    assert r_still["erg"][-1] > 0.98 * r_still["erg"][0]


@pytest.mark.parametrize("norm", ["target", "cloud"])
def test_incremental_metrics_equal_their_definitions(bowl, norm):
    cloud, basis = bowl
    target = cloud.mask.astype(float)
    # Start on the marking: the first footprint covers target and off-target points, so the
    # two normalisations of the source differ from step 1 on.
    start = cloud.points[np.flatnonzero(cloud.mask)[:1]]
    ex = Explorer(basis, target, ExploreConfig(nk=80, agent_radius=0.012, coverage_norm=norm), start)
    X = []
    for _ in range(120):
        ex.step()
        X.append(ex.positions[0].copy())
    m = ex.metrics()
    # The neutral score, kept step by step, equals its definition on the whole trajectory.
    ref = coverage_score(cloud.points, target, np.array(X), 0.012, basis.h)
    assert m["ergodicity"] == pytest.approx(ref["ergodicity"], rel=1e-9)
    assert m["touched_fraction"] == pytest.approx(ref["touched_fraction"], abs=1e-15)
    assert ex.score()["off_surface_fraction"] == ref["off_surface_fraction"] == 0.0
    assert ex.score()["step_max_m"] == pytest.approx(ref["step_max_m"], rel=1e-12)
    # ... and so does the library's score of a whole trajectory (the benchmarks')
    lib = M.coverage_score(cloud.points, target, np.array(X)[:, None], 0.012, basis.h)
    assert lib == pytest.approx(ref, rel=1e-9, abs=1e-15)
    # p̂ = e^{-δtL} p̄ + s̄₁ after step 1 (the published code's first heat: s̄₁ with the cloud's
    # normalisation), then [c = 0] masks it.
    first = Explorer(basis, target, ExploreConfig(nk=80, agent_radius=0.012, integrator="spectral",
                                                  coverage_norm="cloud"), start)
    first.step()
    assert m["residual_ref"] == pytest.approx(residual_ref(first.heat, ex.coverage), rel=1e-9)
    np.testing.assert_allclose(ex.source, M.source_term(target, ex.coverage, basis.mass, norm=norm), rtol=1e-12,
                               atol=0)
    other = M.source_term(target, ex.coverage, basis.mass, norm="cloud" if norm == "target" else "target")
    assert np.abs(other - ex.source).max() > 0.05 * ex.source.max()  # the two normalisations do differ here


def test_footprint_is_the_gaussian_of_tangent_distance_within_the_radius(sphere):
    pts, basis = sphere
    cfg = ExploreConfig(nk=80, agent_radius=0.012)
    ex = Explorer(basis, np.ones(len(pts)), cfg, pts[:1])
    x, n = ex.positions[0].copy(), ex.normals[0].copy()
    ex.step()
    near = np.linalg.norm(pts - x, axis=1) <= cfg.agent_radius
    d = pts - x
    r_tan = np.sqrt(np.maximum((d * d).sum(1) - (d @ n) ** 2, 0))  # metres, eq. 31
    expected = np.where(near, np.exp(-(2.0 / cfg.agent_radius) ** 2 * r_tan**2), 0.0)  # ε = 2 / r_a
    np.testing.assert_allclose(ex.coverage, expected, rtol=1e-12, atol=0)


def test_a_target_in_two_patches_gets_both_visited(two_patch):
    pts, basis, in_a, in_b, a, _ = two_patch
    target = (in_a | in_b).astype(float)
    # nK = 120 resolves a cleared hole of the footprint's size on this 4 mm sheet; with a basis
    # too coarse for that (nK = 80 here), the truncated heat can peak inside the hole and hold
    # the agent there (measured: 7 of 12 µm-perturbed starts at nK = 80, 12 of 12 at nK = 120).
    ex = Explorer(basis, target, ExploreConfig(nk=120, agent_radius=0.008), (a + [0.002, 0, 0])[None])
    r = _run(ex, 600)
    assert np.mean(ex.coverage[in_a] > 0) > 0.95
    assert np.mean(ex.coverage[in_b] > 0) > 0.95
    assert r["touched"][-1] > 0.95


def test_n_agents_share_one_coverage_field(two_patch):
    pts, basis, in_a, in_b, a, b = two_patch
    target = (in_a | in_b).astype(float)
    starts = np.array([a + [0.002, 0, 0], b + [0.0, 0.01, 0], [0.1, 0.05, 0.0]])
    cfg = ExploreConfig(nk=80, agent_radius=0.008, n_agents=3)
    ex = Explorer(basis, target, cfg, starts)
    ex.step()
    # The first deposits are the three single-agent footprints, summed into one field.
    singles = []
    for s in starts:
        one = Explorer(basis, target, ExploreConfig(nk=80, agent_radius=0.008), s[None])
        one.step()
        singles.append(one.coverage)
    np.testing.assert_allclose(ex.coverage, np.sum(singles, axis=0), rtol=1e-12, atol=0)
    r = _run(ex, 300)
    assert r["x"].shape[1:] == (3, 3)
    assert np.linalg.norm(r["v"], axis=2).max() <= cfg.v_max * (1 + 1e-12)
    assert r["touched"][-1] > 0.99
    # Three agents finish the two patches sooner than one.
    solo = Explorer(basis, target, ExploreConfig(nk=80, agent_radius=0.008), starts[:1])
    solo_touched = _run(solo, 301)["touched"]
    assert r["touched"][:100].sum() > solo_touched[1:101].sum()


def test_seeded_runs_are_bit_identical(bowl):
    cloud, basis = bowl
    target = cloud.mask.astype(float)

    def once():
        ex = Explorer(basis, target, ExploreConfig(nk=80, agent_radius=0.012), cloud.points[[5]])
        r = _run(ex, 80)
        return r, ex.coverage.copy(), ex.heat.copy()

    (r1, c1, u1), (r2, c2, u2) = once(), once()
    for k in r1:
        assert np.array_equal(r1[k], r2[k]), k
    assert np.array_equal(c1, c2) and np.array_equal(u1, u2)


def test_start_off_the_surface_is_projected_with_a_warning_and_far_starts_are_refused(sphere):
    pts, basis = sphere
    msgs = []
    x0 = SPHERE_C + np.array([0.0, 0.0, SPHERE_R + 0.01])  # 1 cm above the north pole
    ex = Explorer(basis, np.ones(len(pts)), ExploreConfig(nk=80, agent_radius=0.012), x0[None], on_event=msgs.append)
    assert abs(np.linalg.norm(ex.positions[0] - SPHERE_C) - SPHERE_R) < 1e-9
    assert any("projected" in m for m in msgs)
    with pytest.raises(TergodicError, match="from the cloud"):
        Explorer(basis, np.ones(len(pts)), ExploreConfig(nk=80, agent_radius=0.012),
                 (SPHERE_C + [0, 0, SPHERE_R + 0.1])[None])


def test_a_target_on_parts_no_agent_starts_on_is_named(sphere):
    # Two copies of the sphere 5 cm apart (a gap no agent crosses), the whole surface the target:
    # one agent leaves half of it untouched, which the run says; one agent on each part does not.
    pts, _ = sphere
    two = np.vstack([pts, pts + [0.15, 0.0, 0.0]])
    basis = compute_basis(two, 40, 30)
    cfg = ExploreConfig(nk=40, agent_radius=0.012)
    north = SPHERE_C + [0.0, 0.0, SPHERE_R]
    msgs = []
    Explorer(basis, np.ones(len(two)), cfg, north[None], on_event=msgs.append)
    said = [m for m in msgs if "parts of the cloud no agent starts on" in m]
    assert len(said) == 1 and said[0].startswith("warning: 50 % of the target")
    msgs.clear()
    Explorer(basis, np.ones(len(two)), ExploreConfig(nk=40, agent_radius=0.012, n_agents=2),
             np.array([north, north + [0.15, 0.0, 0.0]]), on_event=msgs.append)
    assert not any("no agent starts on" in m for m in msgs)


def test_bad_targets_and_configs_are_refused(sphere):
    pts, basis = sphere
    ok = ExploreConfig(nk=80, agent_radius=0.012)
    with pytest.raises(TergodicError, match="empty"):
        Explorer(basis, np.zeros(len(pts)), ok, pts[:1])
    with pytest.raises(TergodicError, match="does not match"):
        Explorer(basis, np.ones(len(pts) - 3), ok, pts[:1])
    with pytest.raises(TergodicError, match="larger than the basis"):
        Explorer(basis, np.ones(len(pts)), ExploreConfig(nk=81, agent_radius=0.012), pts[:1])
    with pytest.raises(TergodicError, match="alpha"):
        Explorer(basis, np.ones(len(pts)), ExploreConfig(nk=80, alpha="0"), pts[:1])
    with pytest.raises(TergodicError, match="alpha"):
        Explorer(basis, np.ones(len(pts)), ExploreConfig(nk=80, alpha="50:10@0"), pts[:1])
    msgs = []
    Explorer(basis, np.ones(len(pts)), ExploreConfig(nk=80, agent_radius=0.001), pts[:1], on_event=msgs.append)
    assert any("below the point spacing" in m for m in msgs)


def test_robot_mode_deposits_at_contacts_and_resets_agents(sphere):
    pts, basis = sphere
    ex = Explorer(basis, np.ones(len(pts)), ExploreConfig(nk=80, agent_radius=0.012), pts[:1])
    ex.step(deposit_at=np.zeros((0, 3)))  # no contact: no coverage
    assert not ex.coverage.any()
    contact = pts[700]
    ex.step(deposit_at=contact[None], agent_at=pts[[300]])
    covered = np.flatnonzero(ex.coverage)
    assert len(covered) and np.linalg.norm(pts[covered] - contact, axis=1).max() <= 0.012
    # The reset happened before the gradient step: the agent is within one step of point 300.
    assert np.linalg.norm(ex.positions[0] - pts[300]) <= 1.01 * ex.cfg.v_max * ex.cfg.dt + 1e-9


def test_set_target_keeps_the_basis_and_restarts_the_reference(sphere):
    pts, basis = sphere
    ex = Explorer(basis, np.ones(len(pts)), ExploreConfig(nk=80, agent_radius=0.012), pts[:1])
    for _ in range(20):
        ex.step()
    upper = (pts[:, 2] > SPHERE_C[2]).astype(float)
    ex.set_target(upper)
    assert math.isnan(ex.metrics()["residual_ref"])
    ex.step()
    m = ex.metrics()
    assert 0 < m["residual_ref"] < 1
    ex.set_target(upper, reset_coverage=True)
    assert not ex.coverage.any()
