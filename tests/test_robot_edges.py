"""Sharp edges and closed shapes (issue 15, held-out shapes): outward normals, a box edge crossed below the force limit.

Independent expectations: the synthetic generator's own surface normals (the analytic torus and
box), the box's faces in its own frame, and PyBullet's contact forces read at every 1 kHz tick."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from tergodic_cli.capture import CaptureConfig, capture_cloud
from tergodic_cli.capture.synthetic import BOX_SIZE, generate_synthetic
from tergodic_cli.robot.surface import oriented_normals, resolve_side


@pytest.mark.parametrize("obj", ["torus", "box"])
def test_normals_point_out_of_the_object(obj):
    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic=obj, seed=0))
    truth = generate_synthetic(obj, seed=0, spacing=0.0006)  # the analytic outward normals
    gt = truth.normals[cKDTree(truth.points).query(cap.points)[1]]
    n = oriented_normals(cap.points, resolve_side("auto", cap.meta))
    assert np.mean(np.einsum("ij,ij->i", n, gt) > 0.5) > 0.97
    # "+z" cannot orient a torus's underside or a box's walls (the test can fail)
    up = oriented_normals(cap.points, "up")
    assert np.mean(np.einsum("ij,ij->i", up, gt) < 0) > 0.1


def test_torus_hole_blocks_the_tool():
    from tergodic_cli.capture.synthetic import TORUS_MAJOR, TORUS_MINOR
    from tergodic_cli.robot.reach import occluded

    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic="torus", seed=0))
    P = cap.points
    hit = occluded(P, oriented_normals(P, "outward"))
    rho = np.hypot(P[:, 0], P[:, 1])
    inner = (rho < TORUS_MAJOR - 0.9 * TORUS_MINOR) & (np.abs(P[:, 2] - TORUS_MINOR) < 0.004)  # facing the axis
    top = P[:, 2] > 2 * TORUS_MINOR - 0.002
    assert hit[inner].mean() > 0.95 and not hit[top].any()


@pytest.mark.long
def test_box_edge_crossed_below_the_force_limit():
    """Across the box's top edge the tool lifts and moves over (rolling over it held the agent back
    ~30 steps) and touches the wall below the force limit."""
    pytest.importorskip("pybullet")
    pytest.importorskip("pygafro")
    from test_robot_sim import FAST

    from tergodic_cli.basis import compute_basis
    from tergodic_cli.explore import ExploreConfig, Explorer
    from tergodic_cli.backends.pybullet import RobotRun
    from tergodic_cli.robot import RobotConfig, robot_explore_config

    a, _, c = BOX_SIZE
    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic="box", seed=0))
    P = cap.points
    side = (P[:, 0] > a / 2 - 1e-3) & (P[:, 2] < c - 0.015)  # the +x wall, below the edge
    target = side.astype(float)
    start = P[np.argmin(np.linalg.norm(P - [a / 2 - 0.015, 0.0, c], axis=1))][None]  # on the top, 15 mm from the edge
    cfg = RobotConfig(force=5.0, **FAST)
    ec = robot_explore_config(ExploreConfig(nk=40, seed=0, agent_radius=0.008), cfg.explore_dt)
    ex = Explorer(compute_basis(P, 40, 30), target, ec, start, on_event=lambda msg: None)
    with RobotRun(cap, ex, cfg) as run:
        peak = [0.0]

        def watch(contacts, dt):  # PyBullet's contact force at every tick
            peak[0] = max(peak[0], sum(f for _, _, f in contacts))

        run.arm.contact_hook, run.arm.hook_every = watch, 1
        samples = []
        out = run.run(60, lambda k, s: samples.append(s))
        assert out["final_state"] == "done", out["stop_reason"]
        hops = [t for t in out["transitions"] if "crossed a sharp edge" in t["reason"]]
        assert hops and out["move_overs"] >= 1
        # it moved over: in contact at the top edge before the first hop, on the wall just after it
        at = lambda s: run._to_obj(s["contact_point"])  # noqa: E731
        before = [at(s) for s in samples if s["step"] <= hops[0]["step"] and s["in_contact"]]
        after = [at(s) for s in samples if s["step"] > hops[0]["step"] and s["in_contact"]]
        assert before[-1][2] > c - 0.005 and before[-1][0] > a / 2 - 0.005
        # on the wall's plane at once, and going down it (the contact surface rounds the edge by ~1-2 mm)
        assert after[0][0] > a / 2 - 1e-3 and min(x[2] for x in after[:5]) < c - 0.002, (before[-1], after[:5])
        cps = np.array([run._to_obj(s["contact_point"]) for s in samples if s["in_contact"]])
        limit = run.guard.force_limit
    assert (cps[:, 2] > c - 1e-3).any() and (cps[:, 2] < c - 0.008).any()  # on the top, then over the edge
    assert 4.0 < peak[0] < limit
