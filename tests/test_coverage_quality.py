"""Coverage quality under the neutral score (issue 13): the agent stays on the data, never steps
farther than v_max dt, and reaches the target, on the geometry real captures have.

The clouds are the project's own (``capture.synthetic.COVERAGE_OBJECTS``: a bowl with 1.5 mm
noise, a plate with a hole, a thin-walled mug, a torus with two target patches, a box with sharp
edges, a one-sided partial scan), captured at the default 3 mm voxel; the paper's bunny and plate
are used when ../shared/data/reference is present. The score is recomputed from the trajectory
with ``reference_geometry.coverage_score`` (full arrays), independent of the explorer's
incremental one.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tergodic_cli.basis import BasisConfig, get_basis
from tergodic_cli.capture import CaptureConfig, capture_cloud
from tergodic_cli.capture.synthetic import COVERAGE_OBJECTS
from tergodic_cli.explore import ExploreConfig, Explorer
from reference_geometry import coverage_score

REFERENCE = Path(__file__).resolve().parents[2] / "shared" / "data" / "reference"
STEPS = 1000


def _run(basis, target, x0, radius, steps=STEPS, sheets="mixed"):
    cfg = ExploreConfig(steps=steps, agent_radius=radius, sheets=sheets)
    ex = Explorer(basis, target, cfg, np.atleast_2d(x0), on_event=lambda msg: None)
    X = np.empty((steps, 3))
    for k in range(steps):
        ex.step()
        X[k] = ex.positions[0]
    return ex, X, cfg


#: Objects where the default ("mixed", the paper's) fit leaves the surface of one sheet, as the
#: one-sheet off-surface figure shows (issue 25, item 2, left): the thin mug's 4 mm wall (the agent
#: runs between its sheets), the box's edges (the fit crosses an edge by up to a step).
#: ``--sheets separate`` keeps the agent on one sheet (below), at a higher ε on household meshes
#: (docs/explore.md, "Sheet separation").
INSIDE_KNOWN = {"thin-mug", "box"}


def _inside_case(name: str, tmp_path):
    """The capture, basis and seeded start of one of the INSIDE_KNOWN objects."""
    obj = next(o for o in COVERAGE_OBJECTS if o.object == name)
    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic=obj.object, marking=obj.marking, noise=obj.noise))
    basis, _ = get_basis(cap.points, BasisConfig(nk=200, neighbors=30), str(tmp_path))
    return cap, basis, cap.points[np.random.default_rng(1).choice(cap.n_points, 1, replace=False)]


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="issue 25 item 2 left: the default fit runs inside the thin mug's wall and past the box's edges")
@pytest.mark.parametrize("name", sorted(INSIDE_KNOWN))
def test_the_agent_never_leaves_one_sheet_on_thin_walls_and_edges(name, tmp_path):
    cap, basis, x0 = _inside_case(name, tmp_path)
    _, X, _ = _run(basis, cap.target, x0, 0.0075)
    assert coverage_score(cap.points, cap.target, X, 0.0075, basis.h)["off_surface_fraction"] == 0.0


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(INSIDE_KNOWN))
def test_with_separate_sheets_the_agent_never_leaves_one_sheet_on_thin_walls_and_edges(name, tmp_path):
    # the same runs with the fit, the footprint and the gain on the agent's sheet: the one-sheet
    # off-surface figure (recomputed from the trajectory) is 0, and the target is still reached
    # (mixed: 0.91 on the thin mug, 0.035 on the box)
    cap, basis, x0 = _inside_case(name, tmp_path)
    _, X, cfg = _run(basis, cap.target, x0, 0.0075, sheets="separate")
    ref = coverage_score(cap.points, cap.target, X, 0.0075, basis.h)
    assert ref["off_surface_fraction"] == 0.0
    assert ref["touched_fraction"] >= 0.98
    assert ref["step_max_m"] <= cfg.v_max * cfg.dt * (1 + 1e-9)


@pytest.mark.long
@pytest.mark.slow
@pytest.mark.parametrize("obj", COVERAGE_OBJECTS, ids=lambda o: f"{o.object}-{o.marking}-{o.noise * 1e3:g}mm")
def test_the_agent_stays_on_the_data_and_reaches_the_target(obj, tmp_path):
    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic=obj.object, marking=obj.marking, noise=obj.noise))
    basis, _ = get_basis(cap.points, BasisConfig(nk=200, neighbors=30), str(tmp_path))
    starts = cap.points[np.random.default_rng(1).choice(cap.n_points, 3, replace=False)]
    for x0 in starts:
        ex, X, cfg = _run(basis, cap.target, x0, 0.0075)
        ref = coverage_score(cap.points, cap.target, X, 0.0075, basis.h)
        if obj.object not in INSIDE_KNOWN:
            assert ref["off_surface_fraction"] == 0.0, (obj, x0)
        assert ref["step_max_m"] <= cfg.v_max * cfg.dt * (1 + 1e-9), (obj, x0)
        assert ref["touched_fraction"] >= 0.98, (obj, x0, ref)
        assert 0.0 < ref["ergodicity"] < 0.7, (obj, x0, ref)  # 1 is nothing covered
        assert ex.metrics()["ergodicity"] == pytest.approx(ref["ergodicity"], rel=1e-9)


#: The authors' code under the same score (issue 13): median ε over the starts.
AUTHORS = {"bun270_X": (0.0075, 5, 0.468), "plate_shapes": (0.015, 3, 0.398)}


@pytest.mark.long
@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(AUTHORS))
def test_the_reference_clouds_are_covered_better_than_by_the_authors_code(name, tmp_path):
    if not (REFERENCE / f"{name}.ply").exists():
        pytest.skip(f"reference data absent ({REFERENCE})")
    radius, n_starts, authors = AUTHORS[name]
    cap = capture_cloud(CaptureConfig(source="file", path=str(REFERENCE / f"{name}.ply"), voxel=0.003, voxel_rule="all"))
    basis, _ = get_basis(cap.points, BasisConfig(nk=200, neighbors=40), str(tmp_path))
    with np.load(REFERENCE / "starts" / f"{name}.npz", allow_pickle=False) as data:
        starts = data["x0_arr"][:n_starts]
    eps = []
    for x0 in starts:
        ex, X, cfg = _run(basis, cap.target, x0, radius)
        ref = coverage_score(cap.points, cap.target, X, radius, basis.h)
        # the one-sheet test flags at most one step in 1000 on the reference clouds (the bunny: 1, at a crease)
        assert ref["off_surface_fraction"] <= 0.001
        assert ref["step_max_m"] <= cfg.v_max * cfg.dt * (1 + 1e-9)
        assert ref["touched_fraction"] >= 0.98
        eps.append(ref["ergodicity"])
    # The goal (0.85x) is measured by benchmarks/coverage.py; here: better than the authors' code.
    assert np.median(eps) < authors, eps


def test_a_start_on_a_part_without_target_moves_to_the_targets_part_with_a_warning():
    from tergodic_cli.basis import compute_basis

    # Two 6 x 6 cm sheets at 3 mm spacing, 2 cm apart (a gap no agent on the data can cross);
    # the target is a disc on the second one.
    g = np.arange(0.0, 0.06, 0.003)
    u, v = np.meshgrid(g, g)
    a = np.column_stack([u.ravel(), v.ravel(), np.zeros(u.size)])
    b = a + [0.08, 0.0, 0.0]
    pts = np.vstack([a, b])
    target = (np.linalg.norm(pts[:, :2] - [0.11, 0.03], axis=1) < 0.012).astype(float)
    basis = compute_basis(pts, 60, 30)
    said = []
    ex = Explorer(basis, target, ExploreConfig(nk=60, agent_radius=0.0075), a[:1], on_event=said.append)
    assert len(said) == 1 and "part of the cloud the target is not on" in said[0]
    assert ex.positions[0, 0] >= 0.08 - 1e-9  # on the second sheet
    X = []
    for _ in range(300):
        ex.step()
        X.append(ex.positions[0].copy())
    ref = coverage_score(pts, target, np.array(X), 0.0075, basis.h)
    assert ref["touched_fraction"] >= 0.98 and ref["off_surface_fraction"] == 0.0
