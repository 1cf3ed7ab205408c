"""Whole-arm collision (issue 24, item 2) and faults that end lifted in every state (item 6).

Geometry is checked against analytic values (the table's plane and hole, the stand's box, a finger hull's
depth from its own vertices); faults are injected through ``SimArm.inject`` in each state and the end is
read from PyBullet itself: no sponge contact, no arm part touching anything.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

pytest.importorskip("pybullet")
pytest.importorskip("pygafro")

from conftest import run_cli  # noqa: E402
from test_robot_sim import FAST, _explorer, plate  # noqa: E402,F401

from tergodic_cli.backends.pybullet import PyBulletScene, RobotRun  # noqa: E402
from tergodic_cli.backends.pybullet.collision import BASE_MARGIN, _obj_vertices, replay_contacts, stand_box  # noqa: E402
from tergodic_cli.backends.pybullet.arms.panda import HOME as PANDA_HOME  # noqa: E402
from tergodic_cli.robot import RobotConfig  # noqa: E402
from tergodic_cli.robot.safety import FAULT_EXIT_CODE, Fault, fault_exit_code  # noqa: E402


def _sheet(side: float = 0.1, n: int = 11):
    """A flat square sheet (vertices (n², 3), triangles) of ``side`` m centred on the origin at z = 0."""
    u = np.linspace(-side / 2, side / 2, n)
    X, Y = np.meshgrid(u, u)
    V = np.column_stack([X.ravel(), Y.ravel(), np.zeros(n * n)])
    F = [(i * n + j, i * n + j + 1, (i + 1) * n + j) for i in range(n - 1) for j in range(n - 1)]
    F += [(i * n + j + 1, (i + 1) * n + j + 1, (i + 1) * n + j) for i in range(n - 1) for j in range(n - 1)]
    return V, np.array(F)


def _ball_gap(sc, body, x, r=0.01) -> float:
    """Signed distance (m) of a ball of radius ``r`` at ``x`` to ``body`` (inf when over 0.05 m)."""
    p = sc.p
    shape = p.createCollisionShape(p.GEOM_SPHERE, radius=r, physicsClientId=sc.cid)
    res = p.getClosestPoints(-1, body, 0.05, collisionShapeA=shape, collisionShapePositionA=list(x), physicsClientId=sc.cid)
    return min((c[8] for c in res), default=np.inf)


def test_table_at_the_base_plane_with_a_hole_and_a_stand_under_a_lifted_object():
    sc = PyBulletScene()
    try:
        V, F = _sheet()
        T = np.eye(4)
        T[:3, 3] = (0.5, 0.1, 0.2)
        sc.add_object(V, F, T)
        col = sc.collision
        table, stand = col.bodies["table"], col.bodies["stand"]
        # The table's top is z = 0 away from the base: a ball 1 mm above is clear, 3 mm into it is 3 mm deep.
        for x, y in ((0.5, -0.4), (-0.4, 0.3), (0.9, 0.9)):
            assert _ball_gap(sc, table, (x, y, 0.011)) == pytest.approx(0.001, abs=2e-4)
            assert _ball_gap(sc, table, (x, y, 0.007)) == pytest.approx(-0.003, abs=2e-4)
        # ... and there is a hole around the base: link0's footprint + the margin.
        base = _obj_vertices(os.path.join(__import__("pybullet_data").getDataPath(), "franka_panda/meshes/collision/link0.obj"))
        lo, hi = base[:, :2].min(axis=0) - BASE_MARGIN, base[:, :2].max(axis=0) + BASE_MARGIN
        np.testing.assert_allclose(col.hole[0], lo)
        np.testing.assert_allclose(col.hole[1], hi)
        assert _ball_gap(sc, table, (0.5 * (lo[0] + hi[0]), 0.0, 0.005)) > 0.005  # inside the hole: nothing
        # The stand: a box from the table to the sheet, the sheet's own footprint (0.1 m square about (0.5, 0.1)).
        data = sc.p.getCollisionShapeData(stand, -1, physicsClientId=sc.cid)[0]
        half = np.array(data[3]) / 2
        pos = np.array(sc.p.getBasePositionAndOrientation(stand, physicsClientId=sc.cid)[0])
        np.testing.assert_allclose(pos - half, (0.45, 0.05, 0.0), atol=1e-6)
        np.testing.assert_allclose(pos + half, (0.55, 0.15, 0.2), atol=1e-6)
        # The object moved onto the table: no stand any more.
        T[2, 3] = 0.0
        sc.move_object(T)
        assert "stand" not in col.bodies and col.stand_box is None
    finally:
        sc.close()
    # a small foot gets the minimum footprint, centred on it
    lo, hi = stand_box(np.array([[0.5, 0.0, 0.3], [0.51, 0.0, 0.3], [0.5, 0.0, 0.5]]))
    np.testing.assert_allclose(lo, (0.485, -0.02, 0.0))
    np.testing.assert_allclose(hi, (0.525, 0.02, 0.3))


def test_a_finger_driven_into_the_table_is_found_at_its_depth():
    sc = PyBulletScene()
    try:
        col = sc.collision
        sc.set_arm(np.array(PANDA_HOME))
        assert col.check() == []  # the picture pose touches nothing
        sc.set_arm(np.array([0.0, 1.5, 0.0, -0.5, 0.0, 2.0, 0.785]))  # the hand low over the table
        found = col.check(step=7)
        # The depth, independently: the finger hull's lowest vertex at the hand's pose (+ Bullet's 1 mm margin).
        fv = _obj_vertices(os.path.join(__import__("pybullet_data").getDataPath(), "franka_panda/meshes/collision/finger.obj"))
        T = sc.link_pose(sc.link_index["panda_hand"])
        z_low = float(np.min((fv + [0, 0, 0.0584]) @ T[:3, :3].T + T[:3, 3], axis=0)[2])
        assert z_low < -0.01
        depth = {part: d for part, body, d, _ in found if body == "table"}
        assert set(depth) >= {"panda_leftfinger", "panda_rightfinger"}
        assert max(depth["panda_leftfinger"], depth["panda_rightfinger"]) == pytest.approx(-z_low + 0.001, abs=1.5e-3)
        st = col.stats
        assert st.count >= 2 and st.first["body"] == "table" and st.first["step"] == 7
        assert st.deepest_mm == pytest.approx(1e3 * max(depth.values()), abs=1e-6)
        # Replayed joint states count the same (a logged run's check).
        again = replay_contacts(sc, np.array([PANDA_HOME, [0.0, 1.5, 0.0, -0.5, 0.0, 2.0, 0.785]]))
        assert again.count == len(found) and again.first["step"] == 1
    finally:
        sc.close()


def _watch(run):
    """PyBullet's summed sponge contact force at the injection and its largest value after it."""
    rec = {"at": None, "peak_after": 0.0}
    step = run.scene.step

    def _step():
        step()
        if run.arm._inject is None and rec["at"] is None and run.arm.hit is not None:
            rec["at"] = float(sum(c[2] for c in run.scene.sponge_contacts()))
        if rec["at"] is not None:
            rec["peak_after"] = max(rec["peak_after"], float(sum(c[2] for c in run.scene.sponge_contacts())))

    run.scene.step = _step
    return rec


@pytest.mark.parametrize("state", ["hover", "approach", "explore", "retreat"])
@pytest.mark.parametrize("action", ["hold", "retreat"])
def test_a_fault_in_every_state_ends_lifted(plate, state, action):
    cap, basis = plate
    cfg = RobotConfig(**FAST)
    with RobotRun(cap, _explorer(cap, basis, cfg), cfg) as run:
        go = run.sm.go
        fault = Fault("injected", action, f"injected fault in {state}; " + ("holding position" if action == "hold" else "retreating"))

        def watch_go(target, t, step, reason):
            go(target, t, step, reason)
            if target == state and run.stop_reason is None and run.arm._inject is None:
                run.arm.inject(fault, after=0.3 if state != "explore" else 0.5)

        run.sm.go = watch_go
        rec = _watch(run)
        out = run.run(4)
        assert out["final_state"] == "stopped" and fault_exit_code(out) == FAULT_EXIT_CODE
        assert out["stop_reason"].startswith(f"injected fault in {state}") and "\n" not in out["stop_reason"]
        assert any(t["from"] == state for t in out["transitions"])  # it happened in that state
        # Lifted, at rest, nothing touching: no sponge contact and no arm part on anything.
        assert run.scene.sponge_contacts() == []
        assert run.scene.collision.check() == []
        assert float(np.max(np.abs(run.arm.dev.read_state().dq))) < 0.05
        if state in ("approach", "explore", "retreat"):  # where the tool may be pressed: it lifted
            assert out["transitions"][-1]["from"] == "retreat"
            assert rec["peak_after"] <= max(rec["at"] or 0.0, 1.5 * run.F_d) + 0.5, rec
        assert out["arm_contacts"]["count"] == 0


def test_an_arm_contact_faults_lifted_and_the_run_folder_replays(tmp_path, monkeypatch):
    """Through the CLI: a plate 50 mm under the table's top (the workspace let down to allow it), with the
    hand-clearance filter and the set-up planning switched off (they refuse this pose before motion, exit 2): the move to hover
    drives the sponge and fingers into the table. A contact fault before the first explorer step: exit 3
    with one line, lifted, and the run folder (events, summary, log) is written and replays."""
    from tergodic_cli.backends.pybullet.collision import ArmCollision

    from tergodic_cli.backends.pybullet import plan as plan_mod

    monkeypatch.setattr(ArmCollision, "tool_clearance", lambda self, T, clear=0.0: np.ones(len(T), dtype=bool))
    # ... and the set-up moves' checking world blinded (it refuses the hover before motion, exit 2): the
    # contact has to happen for its fault path to be tested
    for name in ("slack", "segment_slack", "path_slack"):
        monkeypatch.setattr(plan_mod.CollisionWorld, name, lambda self, *a, **k: 1.0)
    monkeypatch.setattr(plan_mod.CollisionWorld, "clearance", lambda self, *a, **k: (1.0, "none"))
    plate_cap = tmp_path / "cap"
    assert run_cli("capture", "--synthetic", "plate", "--out", plate_cap).code == 0
    res = run_cli("explore", plate_cap, "--robot", "pybullet", "--steps", "20", "--nk", "40", "--object-pose", "0.5,0,-0.05",
                  "--workspace", "0.15,-0.6,-0.2,0.85,0.6,0.9", "--out", tmp_path / "run")
    assert res.code == 3, res.err[-3000:]
    lines = [ln for ln in res.err.splitlines() if ln.startswith("robot stopped:")]
    assert len(lines) == 1 and "touches the table" in lines[0], res.err[-2000:]
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["final_state"] == "stopped" and summary["steps"] == 0
    ac = summary["arm_contacts"]
    assert ac["count"] >= 1 and ac["first"]["body"] == "table" and ac["deepest_mm"] > 0
    assert [t["to"] for t in summary["transitions"]][-2:] == ["retreat", "stopped"]
    rep = run_cli("replay", tmp_path / "run", "--json")
    assert rep.code == 0, rep.err[-2000:]
    replayed = json.loads(rep.out)
    assert replayed["steps"] == 0 and replayed["stop_reason"] == summary["stop_reason"]
    assert replayed["arm_contacts"] == ac
    assert run_cli("replay", tmp_path / "run").code == 0


def test_the_sponge_may_sink_into_a_support_only_where_the_pressed_point_lies_on_it(monkeypatch):
    from tergodic_cli.backends.pybullet import collision
    from tergodic_cli.robot.reach import tool_rotation

    sc = PyBulletScene()
    try:
        V, F = _sheet()
        T = np.eye(4)
        T[:3, 3] = (0.5, 0.1, 0.2)  # a sheet on a stand: x, y in [0.45, 0.55] x [0.05, 0.15], top z = 0.2
        sc.add_object(V, F, T)
        col = sc.collision
        r = sc.sponge.radius
        x_down = np.array([1.0, 0.0, 0.0])

        def pose(p, d):
            M = np.eye(4)
            M[:3, :3], M[:3, 3] = tool_rotation(np.asarray(d, float), x_down), p
            return M

        # Pressing the sheet's top (on the stand): the ball sinks into the stand as into the sheet.
        on_top = pose((0.5, 0.1, 0.2), (0.0, 0.0, -1.0))
        # Pressing sideways (tool along -x) over the stand, the ball's bottom 3 mm above its top: clear of
        # it now, but within the 10 mm a tilted, pressed ball needs (a prism's side by its stand touched it
        # mid-run when only the sink was kept). Far above the stand the same pose is fine.
        side = pose((0.54, 0.1, 0.2 + r + 0.003), (-1.0, 0.0, 0.0))
        assert _ball_gap(sc, col.bodies["stand"], side[:3, 3] + [r, 0.0, 0.0], r) == pytest.approx(0.003, abs=3e-4)
        high = pose((0.54, 0.1, 0.2 + r + 0.03), (-1.0, 0.0, 0.0))
        # A face sloped 30 degrees (the tool 60 degrees from straight down) pressed 4.5 mm above the stand's
        # top: by the support, not on it. The ball's lowest point is r - r sin 30 - 4.5 mm = 1.5 mm into the
        # stand, within the foam's sink (3 mm), which a pressed, tilted ball exceeds (the corpus prism: 3 mm).
        d = np.array([-np.cos(np.radians(30)), 0.0, -np.sin(np.radians(30))])
        sloped = pose((0.52, 0.1, 0.2045), d)
        assert col.sponge_sink > 0.0015
        assert _ball_gap(sc, col.bodies["stand"], sloped[:3, 3] - r * d, r) == pytest.approx(0.0045 - r / 2, abs=3e-4)
        ok = col.tool_clearance(np.stack([on_top, side, high, sloped]), 0.01)
        assert ok[0] and not ok[1] and ok[2] and not ok[3]
        # Counted as on the support whatever the tool's direction (the former rule), the sloped pose passed:
        # nothing but the sponge's sink into the stand refuses it.
        monkeypatch.setattr(collision, "SUPPORT_COS", -2.0)
        assert col.tool_clearance(sloped[None], 0.01)[0]
    finally:
        sc.close()
