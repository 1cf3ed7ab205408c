"""The incremental spectral source (docs/speed.md) against a full recompute from the definitions.

Every step the test recomputes, from the explorer's coverage alone, s = max(p̄ - c̄, 0)² on every
point (``metrics.source_term``), its spectral coefficients Φᵀ M s/∫s and the carry-over
recursion, and compares the heat the explorer's agents see at their n_N neighbours, and the
metrics, with it. The explorer never forms s on the whole cloud: it keeps Φᵀ M s up to date
from the footprint's points and the threshold crossings of the active set.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import fibonacci_sphere

from tergodic_cli.basis import compute_basis
from tergodic_cli.capture.synthetic import generate_synthetic
from tergodic_cli.explore import ExploreConfig, Explorer
from tergodic_cli.explore import kernels as K
from tergodic_cli.explore import metrics as M
from tergodic_cli.explore.diffusion import time_step

RTOL = 1e-9


@pytest.fixture(scope="module")
def sphere():
    pts = fibonacci_sphere(1500, 0.05) + np.array([0.1, 0.0, 0.05])
    return pts, compute_basis(pts, 60, 30)


@pytest.fixture(scope="module")
def bowl():
    cloud = generate_synthetic("bowl", "X", seed=2, spacing=0.004)
    return cloud, compute_basis(cloud.points, 60, 30)


class FullRecompute:
    """u_t = Φ f(λδt) Φᵀ M u_{t-1} + s̄_t from u₀ = p̄ (carry) or u_t = Φ f(λδt) Φᵀ M s̄_t (source),
    with s̄ = s/∫s recomputed on all points from the coverage every step (``norm``: what the
    source's coverage is normalised over, as ``ExploreConfig.coverage_norm``)."""

    def __init__(self, basis, target, nk, alpha, integrator, diffusion, norm="cloud"):
        self.norm = norm
        self.phi, self.mass = basis.evecs[:, :nk], basis.mass
        self.p = target
        dt = time_step(alpha)
        lam = basis.evals[:nk]
        self.f = 1.0 / (1.0 + lam * dt) if integrator == "resolvent" else np.exp(-lam * dt)
        self.carry = diffusion == "carry"
        pbar = target / (basis.mass @ target)
        self.a = np.zeros(nk)
        self.b = self.phi.T @ (self.mass * pbar)

    def step(self, coverage):
        s = M.source_term(self.p, coverage, self.mass, norm=self.norm)
        total = float(self.mass @ s)
        self.sbar = s / total if total > 0 else np.zeros_like(s)
        coef = self.phi.T @ (self.mass * self.sbar)
        if self.carry:
            self.a = self.f * (self.a + self.b)
            self.b = coef
        else:
            self.a = self.f * coef

    def heat_at(self, idx):
        u = self.phi[idx] @ self.a
        return u + self.sbar[idx] if self.carry else u


def _heat_at(ex: Explorer, idx) -> np.ndarray:
    """The heat at cloud points ``idx`` exactly as the agents' gradient fits see it."""
    idx = ex._rank[ex._field.rep[np.asarray(idx, dtype=np.int64).ravel()]]
    return np.array([K.heat_at(ex._phi, ex._pf, ex._sp, ex._fs, j, ex._mode, ex._u_full) for j in idx])


def _eq48(ex: Explorer) -> float:
    """√ of the explorer's incrementally kept ∫s (eq. 48, M-weighted, with the source's Z)."""
    return float(np.sqrt(max(ex._fs[K.FS_MASS_S], 0.0)))


def _compare(ex: Explorer, ref: FullRecompute, steps: int, deposit=None, reset=None) -> dict:
    worst = {"heat": 0.0, "ergodicity": 0.0, "reentries": 0, "active_mismatch": 0}
    rng = np.random.default_rng(7)
    T = np.flatnonzero(ref.p > 0)
    for k in range(steps):
        nb = ex.neighbours.copy()  # the patches the coming gradient fits read u on
        before = ex.coverage.copy()
        active_before = ex._pb[K.PB_ACTIVE][ex._rank]  # internal order -> the cloud's
        dep = deposit(k, rng) if deposit else None
        at = reset(k, rng) if reset else None
        ex.step(deposit_at=dep, agent_at=at)
        ref.step(ex.coverage)
        for i in range(len(nb)):
            got, want = _heat_at(ex, nb[i]), ref.heat_at(nb[i])
            scale = np.abs(want).max()
            worst["heat"] = max(worst["heat"], float(np.abs(got - want).max() / scale))
        want_erg = float(np.sqrt(ref.mass @ M.source_term(ref.p, ex.coverage, ref.mass, norm=ref.norm)))
        worst["ergodicity"] = max(worst["ergodicity"], abs(_eq48(ex) - want_erg) / want_erg)
        assert ex._is[K.IS_TOUCHED] / len(T) == M.touched_fraction(ref.p, ex.coverage)
        # The active set {p̄ > c̄} the explorer keeps equals the definition's (up to exact ties);
        # count points that entered it without being touched: only the growth of Z moved them.
        z = ref.mass[T] @ ex.coverage[T] if ref.norm == "target" else ref.mass @ ex.coverage
        e = ref.p[T] / (ref.mass @ ref.p) - (ex.coverage[T] / z if z > 0 else 0.0)
        flags = ex._pb[K.PB_ACTIVE][ex._rank][T] == 1
        clear = np.abs(e) > 1e-12 * np.abs(ref.p[T] / (ref.mass @ ref.p))
        worst["active_mismatch"] += int(np.count_nonzero(flags[clear] != (e[clear] > 0)))
        untouched_now = ex.coverage[T] == before[T]
        worst["reentries"] += int(np.count_nonzero(untouched_now & flags & (active_before[T] == 0)))
    return worst


@pytest.mark.parametrize("resync_every", [300, 0], ids=["resync-every-300", "never-resync"])
def test_incremental_heat_at_the_neighbours_equals_the_full_recompute_over_1000_steps(sphere, resync_every):
    # A uniform target on a sphere: every point is a target, points leave the active set under
    # the footprint and re-enter it as Z = ∫c̃ grows - the threshold crossings are exercised.
    pts, basis = sphere
    target = np.ones(len(pts))
    cfg = ExploreConfig(nk=60, agent_radius=0.012, resync_every=resync_every)
    ex = Explorer(basis, target, cfg, pts[:1])
    ref = FullRecompute(basis, target, 60, 10.0, "resolvent", "carry")
    worst = _compare(ex, ref, 1000)
    assert worst["heat"] < RTOL, worst
    assert worst["ergodicity"] < RTOL, worst
    assert worst["active_mismatch"] == 0, worst
    assert worst["reentries"] > 100, worst  # the heap path did real work
    # The run did explore (the comparison is not between two idle fields).
    assert _eq48(ex) < 0.8 * M.ergodicity(target, np.zeros(len(pts)), basis.mass)


@pytest.mark.parametrize("norm", ["target", "cloud"])
def test_incremental_heat_for_a_marking_equals_the_full_recompute_over_1000_steps(bowl, norm):
    # A marking (the target is a part of the cloud): with the default normalisation over the
    # target the source's Z and ε's (the cloud's) differ, and both are kept incrementally.
    cloud, basis = bowl
    target = cloud.mask.astype(float)
    cfg = ExploreConfig(nk=60, agent_radius=0.012, resync_every=300, coverage_norm=norm)
    ex = Explorer(basis, target, cfg, cloud.points[np.flatnonzero(target)[:1]])
    assert (ex._prm[K.PR_ZTARGET] != 0.0) == (norm == "target")
    ref = FullRecompute(basis, target, 60, 10.0, "resolvent", "carry", norm=norm)
    worst = _compare(ex, ref, 1000)
    assert worst["heat"] < RTOL, worst
    assert worst["ergodicity"] < RTOL, worst
    assert worst["active_mismatch"] == 0, worst
    assert worst["reentries"] > 10, worst  # points re-entered the active set through Z alone
    assert ex.metrics()["touched_fraction"] > 0.9  # the run did explore the marking


@pytest.mark.parametrize("integrator, diffusion", [("spectral", "carry"), ("resolvent", "source")])
def test_incremental_source_for_a_marking_and_the_other_variants(bowl, integrator, diffusion):
    cloud, basis = bowl
    target = cloud.mask.astype(float) * (1.0 + cloud.points[:, 0] * 5)  # non-uniform weights too
    cfg = ExploreConfig(nk=60, agent_radius=0.012, integrator=integrator, diffusion=diffusion, alpha="30:10@150")
    ex = Explorer(basis, target, cfg, cloud.points[np.flatnonzero(target)[:1]])
    ref = FullRecompute(basis, target, 60, 30.0, integrator, diffusion)
    worst = {"heat": 0.0}
    for k in range(300):
        if k == 150:  # the α schedule switches: so does the reference's operator
            ref.f = (1.0 / (1.0 + basis.evals[:60] * time_step(10)) if integrator == "resolvent"
                     else np.exp(-basis.evals[:60] * time_step(10)))
        nb = ex.neighbours[0].copy()
        ex.step()
        ref.step(ex.coverage)
        want = ref.heat_at(nb)
        got = _heat_at(ex, nb)
        worst["heat"] = max(worst["heat"], float(np.abs(got - want).max() / np.abs(want).max()))
    assert worst["heat"] < RTOL, worst
    # The whole reconstructed field agrees too (what the run log's clouds store).
    u_full = ref.phi @ ref.a + (ref.sbar if diffusion == "carry" else 0)
    np.testing.assert_allclose(ex.heat, u_full, rtol=0, atol=RTOL * np.abs(u_full).max())


def test_incremental_source_in_robot_mode_with_several_agents_and_a_new_target(sphere):
    pts, basis = sphere
    target = (pts[:, 2] > 0.04).astype(float)
    cfg = ExploreConfig(nk=60, agent_radius=0.012, n_agents=2)
    ex = Explorer(basis, target, cfg, pts[[0, 700]])
    ref = FullRecompute(basis, target, 60, 10.0, "resolvent", "carry")

    def contacts(k, rng):  # 0-2 contact points near the agents, some off the cloud
        m = k % 3
        pick = ex.positions[rng.integers(0, 2, m)] + rng.normal(scale=0.002, size=(m, 3))
        if k % 7 == 0:
            pick = np.vstack([pick, [[1.0, 1.0, 1.0]]])  # far away: covers nothing
        return pick

    def tips(k, rng):
        return ex.positions + rng.normal(scale=0.001, size=(2, 3)) if k % 5 == 0 else None

    worst = _compare(ex, ref, 200, deposit=contacts, reset=tips)
    assert worst["heat"] < RTOL and worst["ergodicity"] < RTOL and worst["active_mismatch"] == 0, worst
    # A re-capture: new p, coverage kept; the heat restarts from p̄ (eq. 5).
    new = (pts[:, 0] > 0.1).astype(float)
    ex.set_target(new)
    ref = FullRecompute(basis, new, 60, 10.0, "resolvent", "carry")
    worst = _compare(ex, ref, 100)
    assert worst["heat"] < RTOL and worst["ergodicity"] < RTOL and worst["active_mismatch"] == 0, worst


def test_periodic_resync_measures_a_round_off_sized_drift(sphere):
    pts, basis = sphere
    ex = Explorer(basis, np.ones(len(pts)), ExploreConfig(nk=60, agent_radius=0.012, resync_every=100), pts[:1])
    for _ in range(400):
        ex.step()
    assert int(ex._is[K.IS_RESYNCS]) == 1 + 4  # the initial recompute and one every 100 steps
    assert 0.0 < ex.resync_drift < 1e-11


def test_pending_lists_hold_exactly_the_inactive_points_under_this_steps_footprint(bowl):
    # A point the footprint deactivates waits in a pending list, not the heap, while the
    # footprint still covers it. Every step: each inactive target point is in the heap or in a
    # pending list, the lists hold no duplicates and match their flags, and a listed point is
    # one whose coverage grew this step (it leaves the list once the footprint has passed).
    cloud, basis = bowl
    target = cloud.mask.astype(float)
    ex = Explorer(basis, target, ExploreConfig(nk=60, agent_radius=0.012, resync_every=0, coverage_norm="target"),
                  cloud.points[np.flatnonzero(target)[:1]])
    assert ex._prm[K.PR_ZTARGET] != 0.0  # the target's Z: points leave the active set under the footprint
    T = ex._T
    lists = [(K.PB_ACTIVE, K.PB_INHEAP, K.PB_PEND, K.PI_PEND, K.IS_NPEND, K.IS_HEAP, 0)]
    longest = [0]
    for _ in range(600):
        before = ex._cov.copy()
        ex.step()
        grew = ex._cov > before
        for w, (pa, ph, pp, pl, nl, nh, off) in enumerate(lists):
            npend = int(ex._is[nl])
            pend = ex._pi[pl, :npend]
            assert len(np.unique(pend)) == npend
            flagged = np.flatnonzero(ex._pb[pp])
            np.testing.assert_array_equal(np.sort(pend), flagged)
            assert grew[pend].all()
            inheap = set(ex._heap_idx[off:off + int(ex._is[nh])].tolist())
            assert set(np.flatnonzero(ex._pb[ph]).tolist()) <= inheap
            inactive = T[ex._pb[pa, T] == 0]
            waiting = (ex._pb[ph, inactive] == 1) | (ex._pb[pp, inactive] == 1)
            assert waiting.all(), inactive[~waiting]
            longest[w] = max(longest[w], npend)
    assert longest[0] > 0  # the list was used
