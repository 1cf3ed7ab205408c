"""Never trapped (explore/transit.py, docs/explore.md "Never trapped"): the stagnation test, the
transit's goal and path following, and a cloud on which the plain drive is trapped."""

from __future__ import annotations

import math

import numpy as np
import pytest

from reference_geometry import coverage_score
from tergodic_cli.basis import compute_basis
from tergodic_cli.explore import ExploreConfig, Explorer
from tergodic_cli.explore import explorer as explorer_module
from tergodic_cli.explore.transit import (STALL_FALL, STALL_GAIN, Transit, choose_goal, path_to, paths_from,
                                          stalled, surface_graph)


def test_stalled_only_when_the_residual_does_not_fall_and_a_better_place_exists():
    # progress: ∫s fell by more than STALL_FALL, however poor the place
    assert not stalled(100.0, 100.0 * (1 - 2 * STALL_FALL), 0.0, 1.0)
    # no progress, but the agent stands where a deposit still removes much: not stuck
    assert not stalled(100.0, 101.0, 0.5, 1.0)
    assert not stalled(100.0, 101.0, STALL_GAIN * 1.01, 1.0)
    # no progress and little to remove here against the best reachable: stalled
    assert stalled(100.0, 101.0, STALL_GAIN * 0.99, 1.0)
    assert stalled(100.0, 100.0 * (1 - 0.5 * STALL_FALL), 0.0, 1.0)
    # nothing left anywhere (or a first window with no reference): never
    assert not stalled(100.0, 101.0, 0.0, 0.0)
    assert not stalled(math.inf, 101.0, 0.0, 1.0)


def test_the_goal_is_the_nearest_reachable_point_with_at_least_half_the_best_gain():
    dist = np.array([0.01, 0.02, 0.05, np.inf, 0.03])
    gain = np.array([0.1, 0.45, 1.0, 5.0, 0.6])  # the 5.0 is unreachable: the best reachable is 1.0
    assert choose_goal(dist, gain) == 4  # 0.6 >= 0.5 and nearer than the best (0.03 < 0.05)
    assert choose_goal(dist, gain, share=1.0) == 2
    assert choose_goal(np.full(3, np.inf), np.ones(3)) == -1
    assert choose_goal(dist, np.zeros(5)) == -1


def test_the_surface_path_follows_the_sheet_around_a_gap():
    # a U of points at 3 mm: the straight line between the arms' tips crosses 3 cm of nothing
    g = 0.003
    arm = np.arange(0.0, 0.06 + 1e-9, g)
    left = np.column_stack([np.zeros_like(arm), arm, np.zeros_like(arm)])
    base = np.column_stack([np.arange(g, 0.03, g), np.zeros(9), np.zeros(9)])
    right = left + [0.03, 0.0, 0.0]
    pts = np.vstack([left, base, right])
    graph = surface_graph(pts, 2 * 1.5 * g)
    dist, pred = paths_from(graph, len(left) - 1)  # from the left arm's tip
    goal = len(pts) - 1  # the right arm's tip
    path = path_to(pred, len(left) - 1, goal)
    # down, across, up: 15 cm less the corners' diagonal shortcuts (edges reach 4.5 mm), never the 3 cm gap
    assert 0.9 * 0.15 < dist[goal] <= 0.15 + 1e-12
    steps = np.linalg.norm(np.diff(pts[path], axis=0), axis=1)
    assert steps.max() <= 2 * 1.5 * g and path[0] == len(left) - 1 and path[-1] == goal


def test_a_transit_tracks_its_path_and_ends_at_its_goal():
    pts = np.column_stack([np.linspace(0, 0.09, 31), np.zeros(31), np.zeros(31)])
    tr = Transit(pts, 0.003, 0.00375)
    x, n = np.array([0.0, 0.001, 0.0]), np.array([0.0, 0.0, 1.0])
    v = tr.velocity(x, n, 0.003)
    assert np.linalg.norm(v) == pytest.approx(0.003) and v[0] > 0.0 and abs(v[2]) < 1e-15
    for _ in range(40):  # move along it at v_max (the kernel's job): it ends within the arrival radius
        if v is None:
            break
        x = x + v
        v = tr.velocity(x, n, 0.003)
    assert v is None and tr.arrived and np.linalg.norm(x - pts[-1]) <= 0.00375


def _dumbbell():
    """Two 6 x 6 cm squares at 3 mm joined by a 15 cm strip 1.5 cm wide, a target disc of 1.5 cm
    radius on each square; one start in the first square, beside its disc."""
    g, S, L, W = 0.003, 0.06, 0.15, 0.015
    xs, ys = np.arange(0, 2 * S + L + 1e-9, g), np.arange(-S / 2, S / 2 + 1e-9, g)
    u, v = (a.ravel() for a in np.meshgrid(xs, ys))
    keep = (u <= S) | (u >= S + L) | (np.abs(v) <= W / 2)
    pts = np.column_stack([u[keep], v[keep], np.zeros(keep.sum())])
    centres = np.array([[S / 2, 0.0], [S + L + S / 2, 0.0]])
    target = (np.linalg.norm(pts[:, None, :2] - centres[None], axis=2).min(axis=1) < 0.015).astype(float)
    return pts, target, np.array([[0.005, 0.02, 0.0]])


@pytest.mark.slow
def test_the_stagnation_check_frees_an_agent_the_plain_drive_leaves_trapped(monkeypatch):
    pts, target, start = _dumbbell()
    basis = compute_basis(pts, 200, 30)
    # The footprint gain alone (heat weight 0) is cut off 4.5 r_a from the target: once the first disc
    # is covered nothing pulls the agent down the 15 cm strip, and the second disc is never reached.
    cfg = ExploreConfig(nk=200, heat_weight=0.0)

    def run():
        said = []
        ex = Explorer(basis, target, cfg, start, on_event=said.append)
        X = np.empty((1000, 3))
        for k in range(1000):
            ex.step()
            X[k] = ex.positions[0]
        return ex, said, coverage_score(pts, target, X, cfg.agent_radius, basis.h)

    with monkeypatch.context() as m:
        m.setattr(explorer_module, "STALL_WINDOW", 10**9)  # no stagnation check: the plain drive
        ex, said, plain = run()
    assert ex.transits == 0 and plain["touched_fraction"] < 0.6, plain  # trapped on the first square
    ex, said, ref = run()
    assert ref["touched_fraction"] >= 0.98, ref
    assert ex.transits >= 1 and any(m.startswith("transit: ") and "stalled" in m for m in said), said
    assert any("arrived" in m for m in said), said
    assert ref["off_surface_fraction"] == 0.0
    assert ref["step_max_m"] <= cfg.v_max * cfg.dt * (1 + 1e-9)
    assert ref["ergodicity"] < plain["ergodicity"]


def test_the_surface_path_never_crosses_a_thin_wall():
    # a hairpin: two 9 x 3 cm sheets at 3 mm, 7.5 mm apart (closer than the graph's 9 mm reach),
    # joined along x = 0.09 by a half-cylinder; the point straight across the wall is 7.5 mm away
    # through the material and 18 cm + the fold along the surface
    g, gap = 0.003, 0.0075
    x, y = np.meshgrid(np.arange(0.0, 0.09 + 1e-9, g), np.arange(0.0, 0.03 + 1e-9, g))
    x, y = x.ravel(), y.ravel()
    a = np.column_stack([x, y, np.zeros_like(x)])
    b = a + [0.0, 0.0, gap]
    t = np.linspace(0.0, np.pi, 8)[1:-1]
    yy, tt = np.meshgrid(np.arange(0.0, 0.03 + 1e-9, g), t)
    fold = np.column_stack([0.09 + 0.5 * gap * np.sin(tt.ravel()), yy.ravel(), 0.5 * gap * (1 - np.cos(tt.ravel()))])
    pts = np.vstack([a, b, fold])
    graph = surface_graph(pts, 3 * g)
    src = int(np.argmin(np.linalg.norm(a - [0.0, 0.015, 0.0], axis=1)))
    goal = len(a) + src  # the point of the other sheet straight above it
    dist, pred = paths_from(graph, src)
    assert np.isfinite(dist[goal])
    assert dist[goal] >= 2 * 0.09, dist[goal]  # along both sheets and round the fold, never 7.5 mm across
    path = path_to(pred, src, goal)
    assert np.max(pts[path, 0]) >= 0.09  # it went round the fold
