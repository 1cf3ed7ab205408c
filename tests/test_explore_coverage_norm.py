"""What the source's coverage is normalised over (``ExploreConfig.coverage_norm``).

With eq. 2 as printed (``"cloud"``), c̄ = c̃ / ∫_Ω c̃: when the footprint is wider than the
marking, a share 1 - f of every deposit lands beside it, ∫_T c̄ = f < 1 = ∫ p̄, and the residual
on a covered marking never falls below p̄ (1 - f). The marking then outweighs a small target
spot far from it for ever. Normalised over the target (``"target"``) the residual of a covered
marking vanishes and the far spot keeps its pull. (The heat drive alone is tested here; the default
drive adds the footprint gain, docs/explore.md.)
"""

from __future__ import annotations

import numpy as np
import pytest

from tergodic_cli.basis import compute_basis
from tergodic_cli.capture.synthetic import generate_synthetic
from tergodic_cli.explore import ExploreConfig, Explorer
from tergodic_cli.explore import metrics as M


def test_a_marking_covered_in_proportion_has_no_residual_over_the_target_and_a_floor_over_the_cloud():
    rng = np.random.default_rng(3)
    n = 400
    mass = rng.uniform(0.5, 2.0, n) * 1e-5
    p = np.where(np.arange(n) < 100, rng.uniform(0.2, 1.0, n), 0.0)
    # Coverage in proportion to p on the target, plus three times as much beside it.
    beside = np.where(p == 0, rng.uniform(0.0, 1.0, n), 0.0)
    beside *= 3.0 * (mass @ p) / (mass @ beside)
    cov = 2.5 * p + 2.5 * beside
    pbar = p / (mass @ p)
    assert M.source_term(p, cov, mass, norm="target").max() < 1e-24 * (pbar**2).max()  # 0 up to round-off
    f = (mass @ (2.5 * p)) / (mass @ cov)  # the share of the coverage on the target: 1/4
    assert f == pytest.approx(0.25)
    np.testing.assert_allclose(M.source_term(p, cov, mass, norm="cloud"), (pbar * (1 - f)) ** 2, rtol=1e-12)
    # A point of the target never touched keeps its whole p̄² under either normalisation.
    cov[5] = 0.0
    assert M.source_term(p, cov, mass, norm="target")[5] == pytest.approx(pbar[5] ** 2, rel=1e-12)
    # ε (eq. 48) itself is defined with the cloud's normalisation.
    e = np.maximum(pbar - cov / (mass @ cov), 0.0)
    assert M.ergodicity(p, cov, mass) == pytest.approx(np.sqrt(mass @ e**2), rel=1e-12)


@pytest.fixture(scope="module")
def plate_with_island():
    """A synthetic plate with its X marking (12 mm strokes) and a 9-point spot 5 cm from the X."""
    cloud = generate_synthetic("plate", "X", seed=0, spacing=0.004)
    island = np.hypot(cloud.points[:, 0] - 0.07, cloud.points[:, 1]) < 0.006
    target = (cloud.mask | island).astype(float)
    return cloud, compute_basis(cloud.points, 60, 30), target, island


def _first_touch(basis, target, island, x0, norm, steps):
    ex = Explorer(basis, target, ExploreConfig(nk=60, agent_radius=0.025, coverage_norm=norm, heat_weight=1.0,
                                                   gain_weight=0.0), x0[None])
    for k in range(steps):
        ex.step()
        if (ex.coverage[island] > 0).any():
            return k + 1, ex
    return None, ex


def test_a_small_far_spot_is_reached_when_the_coverage_is_normalised_over_the_target(plate_with_island):
    cloud, basis, target, island = plate_with_island
    assert island.sum() == 9 and not (island & cloud.mask).any()
    # A footprint (r_a = 25 mm) about twice the strokes' width: most of it lands beside them.
    starts = cloud.points[np.flatnonzero(cloud.mask)[[0, 100, 200]]]
    for x0 in starts:
        k, ex = _first_touch(basis, target, island, x0, "target", 600)
        assert k is not None and k <= 400, k
        # ... and the marking was not given up for it: the whole target is touched by step 1000.
        for _ in range(1000 - k):
            ex.step()
        assert ex.metrics()["touched_fraction"] == 1.0
        # Over the cloud (eq. 2 as printed) the X's residual floor outweighs the spot: never reached.
        k_cloud, ex_cloud = _first_touch(basis, target, island, x0, "cloud", 1000)
        assert k_cloud is None
        assert ex_cloud.metrics()["touched_fraction"] == pytest.approx(1 - 9 / target.sum(), abs=0.01)
        assert ex.metrics()["residual_ref"] < 0.5 * ex_cloud.metrics()["residual_ref"]


def test_explorer_refuses_an_unknown_normalisation(plate_with_island):
    from tergodic_cli.errors import TergodicError

    cloud, basis, target, _ = plate_with_island
    with pytest.raises(TergodicError, match="--coverage-norm"):
        Explorer(basis, target, ExploreConfig(nk=60, coverage_norm="marking"), cloud.points[:1])
