"""The PyBullet backend in DIRECT mode: the F/T sensor, the torque-control traps, the mesh, whole runs, faults."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("pybullet")
pytest.importorskip("pygafro")

from tergodic_cli.basis import compute_basis  # noqa: E402
from tergodic_cli.capture import CaptureConfig, capture_cloud  # noqa: E402
from tergodic_cli.errors import TergodicError  # noqa: E402
from tergodic_cli.explore import ExploreConfig, Explorer  # noqa: E402
from tergodic_cli.backends.pybullet import RobotRun, explore_with_robot  # noqa: E402
from tergodic_cli.robot import RobotConfig, robot_explore_config  # noqa: E402
from tergodic_cli.robot.interfaces import LineTarget  # noqa: E402
from tergodic_cli.backends.franka.gafro import FrankaModel, tool_offset  # noqa: E402
from gafro_matrix import jacobian_base, jacobian_ee  # noqa: E402
from tergodic_cli.backends.pybullet import PyBulletArm, PyBulletScene  # noqa: E402
from tergodic_cli.robot.surface import oriented_normals, reconstruct_mesh  # noqa: E402

#: Quick runs: a faster set-up move and a lower hover than the defaults.
FAST = dict(move_speed=1.6, hover_height=0.02)
SAMPLE_KEYS = ("t_sim", "state", "ee_pose", "q", "dq", "tau", "link_poses", "wrench_measured", "wrench_desired",
               "force_normal", "in_contact", "contact_point", "tilt_deg", "track_mm")


@pytest.fixture(scope="module")
def plate():
    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic="plate", voxel=0.005))
    basis = compute_basis(cap.points, 40, 30)
    return cap, basis


def _explorer(cap, basis, cfg: RobotConfig, seed=0):
    ec = robot_explore_config(ExploreConfig(nk=40, seed=seed, agent_radius=0.008), cfg.explore_dt)
    start = cap.points[np.argmin(np.linalg.norm(cap.points[:, :2] - [0.03, 0.02], axis=1))][None]
    return Explorer(basis, cap.target, ec, start, on_event=lambda msg: None)


def _at_rest(run: RobotRun) -> float:
    st = run.arm.dev.read_state()
    return float(np.max(np.abs(st.dq)))


def mesh_distance(mesh, points: np.ndarray) -> np.ndarray:
    """Unsigned distance (m) from ``points`` (k, 3) to the mesh (open3d raycasting scene)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)), o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(np.asarray(points, dtype=np.float32))).numpy().astype(float)


# ---------------------------------------------------------------------------------- the arm and its models
def test_gafro_kinematics_match_pybullet():
    # Eqs. 14-16, 42-45 (pygafro motors) against PyBullet's own forward kinematics and calculateJacobian.
    sc = PyBulletScene()
    try:
        arm = PyBulletArm(sc)
        arm.connect()
        q0 = np.array([0, -0.785, 0, -2.356, 0, 1.571, 0.785])
        sc.set_arm(q0)
        model = FrankaModel()
        model.tool = tool_offset(model, q0, arm.read_state().ee_pose)
        assert model.tool[2, 3] == pytest.approx(sc.sponge.offset + sc.sponge.radius - 0.1034, abs=1e-6)
        rng = np.random.default_rng(0)
        for _ in range(5):
            q = rng.uniform(model.q_min + 0.2, model.q_max - 0.2)
            sc.set_arm(q)
            st = arm.read_state()
            np.testing.assert_allclose(model.fk(q), st.ee_pose, atol=1e-6)
            np.testing.assert_allclose(jacobian_base(model, q), st.jacobian, atol=1e-6)
            R = st.ee_pose[:3, :3]
            Jee = np.vstack([R.T @ st.jacobian[:3], R.T @ st.jacobian[3:]])
            np.testing.assert_allclose(jacobian_ee(model, q), Jee, atol=1e-6)
            # and the Jacobian is the derivative of the pose (finite differences, independent of both models)
            dq = rng.normal(size=7) * 1e-4
            dx = 0.5 * (model.fk(q + dq)[:3, 3] - model.fk(q - dq)[:3, 3])
            np.testing.assert_allclose(dx, st.jacobian[:3] @ dq, atol=1e-9)
    finally:
        sc.close()


def test_torque_control_traps():
    """Velocity motors off, gravity + Coriolis compensated, TORQUE_CONTROL re-sent each step."""
    sc = PyBulletScene()
    try:
        arm = PyBulletArm(sc)
        arm.connect()
        q0 = np.array([0, -0.5, 0, -2.2, 0, 1.7, 0.785])
        sc.set_arm(q0)
        for _ in range(500):  # gravity compensation alone: the arm floats still
            arm.read_state()
            arm.command(np.zeros(7))
            sc.step()
        assert np.max(np.abs(arm.read_state().q - q0)) < 2e-3
        # 0.5 N m on joint 7 for 0.2 s: it turns as M⁻¹τ predicts (no hidden velocity motor holds it).
        q_start = arm.read_state().q
        M = np.array(sc.p.calculateMassMatrix(sc.robot, q_start.tolist(), physicsClientId=sc.cid))
        tau = np.array([0, 0, 0, 0, 0, 0, 0.5])
        expected = 0.5 * (np.linalg.solve(M, tau)) * 0.2**2
        for _ in range(200):
            arm.read_state()
            arm.command(tau)
            sc.step()
        st = arm.read_state()
        assert st.q[6] - q_start[6] == pytest.approx(expected[6], rel=0.1)
        assert expected[6] > 0.01
        # Without re-sending, PyBullet applies no torque at all: the arm sags under gravity.
        q1 = st.q.copy()
        for _ in range(200):
            sc.step()
        assert np.max(np.abs(arm.read_state().q - q1)) > 0.05
    finally:
        sc.close()


def test_ft_sensor_matches_contact_points_and_applied_force(plate):
    """The wrist F/T reading equals the summed contact normal forces, and an off-axis push gives r × F."""
    cap, basis = plate
    cfg = RobotConfig(**FAST)
    ex = _explorer(cap, basis, cfg)
    with RobotRun(cap, ex, cfg) as run:
        run._t0 = 0.0
        run._move_to_hover()
        # In free space, after the tare, a known external force at an offset point on the sponge:
        sc = run.scene
        T = run.arm.dev.read_state().ee_pose
        F = np.array([2.0, -1.0, 3.0])
        r_ee = np.array([0.03, -0.02, -0.01])  # point of application in the ee frame (on the holder)
        readings = []
        q_hold = run.arm.dev.read_state().q.copy()
        for _ in range(800):
            st = run.arm.dev.read_state()
            T = st.ee_pose
            point = T[:3, :3] @ r_ee + T[:3, 3]
            sc.p.applyExternalForce(sc.robot, sc.sponge_link, F.tolist(), point.tolist(), sc.p.WORLD_FRAME,
                                    physicsClientId=sc.cid)
            run.arm.dev.command(run.arm.joint(st.q, st.dq, q_hold))
            sc.step()
            readings.append(run.arm.contact_wrench(run.arm.sensor.read().wrench, run.arm.dev.read_state().ee_pose))
        w = np.mean(readings[-500:], axis=0)
        R = T[:3, :3]
        f_ee = -(R.T @ F)  # the tool "applies" the reaction of what pushes it
        np.testing.assert_allclose(w[:3], f_ee, atol=0.05)
        np.testing.assert_allclose(w[3:], np.cross(r_ee, f_ee), rtol=0.05, atol=0.006)
        assert np.linalg.norm(np.cross(r_ee, f_ee)) > 0.08
        # In contact: press at 5 N then 8 N on a still target; F/T against getContactPoints.
        run._approach()
        a, d = run._start_line
        for f_d in (5.0, 8.0):
            ft, cp = [], []
            for i in range(1500):
                obs, fault = run._tick(LineTarget(a, d, "press", force=f_d), checks=False)
                st, wee = obs.state, obs.wrench
                if i >= 1000:
                    meas = run._measure(obs)
                    n = meas["normal"]
                    ft.append(float(-(st.ee_pose[:3, :3] @ wee[:3]) @ n))
                    cp.append(meas["force_contact"])
            assert np.mean(ft) == pytest.approx(np.mean(cp), rel=0.02)
            assert np.mean(ft) == pytest.approx(f_d, rel=0.03)


def test_mesh_follows_the_open_sheet():
    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic="bowl"))
    n = oriented_normals(cap.points, "up")
    assert np.mean(n[:, 2] > 0) == 1.0
    # inner surface of a sphere of radius 8 cm centred above the bottom: normals point at the centre
    to_centre = np.array([0, 0, 0.08]) - cap.points
    to_centre /= np.linalg.norm(to_centre, axis=1, keepdims=True)
    assert np.median(np.einsum("ij,ij->i", n, to_centre)) > 0.99
    mesh = reconstruct_mesh(cap.points, n, cap.meta["spacing_h_m"], edge=0.006)
    area = 2 * math.pi * 0.08**2 * (1 - math.cos(math.radians(70)))
    assert mesh.area == pytest.approx(area, rel=0.05)
    dist = mesh_distance(mesh, cap.points)
    assert np.percentile(dist, 99) < 1e-3
    # the mesh's vertices stay on the true sphere (decimation keeps the sag tiny)
    r = np.linalg.norm(mesh.vertices - [0, 0, 0.08], axis=1)
    assert np.max(np.abs(r - 0.08)) < 1e-3


# ---------------------------------------------------------------------------------- whole runs
def test_robot_run_on_plate(plate):
    cap, basis = plate
    cfg = RobotConfig(**FAST)
    ex = _explorer(cap, basis, cfg)
    events, steps = [], []
    out = explore_with_robot(cap, ex, cfg, 12, on_step=lambda k, s: steps.append((k, s)),
                             on_event=lambda k, msg: events.append(msg))
    assert out["final_state"] == "done" and out["stop_reason"] == "completed"
    assert [t["to"] for t in out["transitions"]] == ["hover", "approach", "explore", "retreat", "done"]
    assert sum("->" in e for e in events) == 5
    assert [k for k, _ in steps] == list(range(1, 13)) and ex.step_index == 12
    for _, s in steps:
        for key in SAMPLE_KEYS:
            assert key in s, key
        assert len(s["q"]) == 7 and len(s["ee_pose"]) == 7 and len(s["wrench_measured"]) == 6
    assert out["contact_fraction"] == 1.0
    assert out["force_mean_N"] == pytest.approx(5.0, abs=0.5)
    assert out["track_mm_median"] < 5 and out["tilt_deg_median"] < 5
    assert out["touched_sponge"] > 0 and out["touched_agent"] > 0
    # coverage came from the real contacts: the explorer's coverage sits where the sponge touched
    pts = np.array([s["contact_point"] for _, s in steps if s["in_contact"]])
    assert len(pts) >= 10
    T_obj = np.array(out["object_pose"])
    touched = cap.points[ex.coverage > 0] + T_obj[:3]
    d = np.min(np.linalg.norm(touched[:, None, :] - pts[None, :, :], axis=2), axis=1)
    assert np.max(d) < 0.012  # every covered point lies within a footprint of a contact point
    assert out["realtime_factor"] > 0


class _ExplorerProxy:
    """Wraps the real explorer to inject faults after ``after`` steps (the explorer is not hardware, but its
    output is the robot's input: a bad target or a stalled stream must be survivable)."""

    def __init__(self, ex, after: int, mode: str, run_ref: list):
        self._ex, self._after, self._mode, self._run = ex, after, mode, run_ref

    def __getattr__(self, name):
        return getattr(self._ex, name)

    def step(self, deposit_at=None, agent_at=None):
        k = self._ex.step_index
        if k >= self._after and self._mode == "stall":
            return  # no new step: the target stream stops
        self._ex.step(deposit_at=deposit_at, agent_at=agent_at)
        if k + 1 == self._after and self._mode == "bump":
            sc = self._run[0].scene  # the object is knocked 6 mm towards the tool
            T = sc.object_pose.copy()
            T[2, 3] += 0.006
            sc.move_object(T)

    @property
    def positions(self):
        if self._mode == "outside" and self._ex.step_index >= self._after:
            return self._ex.positions + np.array([0.8, 0.0, 0.0])
        return self._ex.positions


class _FrozenSensor:
    """An F/T driver that stops delivering new samples after ``t_freeze`` (it keeps repeating the last one)."""

    def __init__(self, sensor, t_freeze: float):
        self._s, self._t, self._last = sensor, t_freeze, None
        self.frame_in_ee = sensor.frame_in_ee

    def read(self):
        r = self._s.read()
        if r.t >= self._t and self._last is not None:
            return self._last
        self._last = r
        return r

    def tare(self):
        self._s.tare()


def _faulty_run(plate, mode: str, after: int = 4):
    cap, basis = plate
    cfg = RobotConfig(**FAST)
    ref = []
    ex = _ExplorerProxy(_explorer(cap, basis, cfg), after, mode, ref)
    run = RobotRun(cap, ex, cfg)
    ref.append(run)
    return run


@pytest.mark.parametrize("mode,needle", [("bump", "force"), ("outside", "workspace"), ("stall", "explorer stalled")])
def test_fault_injection_ends_safe(plate, mode, needle):
    run = _faulty_run(plate, mode)
    with run:
        out = run.run(15)
        assert out["final_state"] == "stopped"
        reason = out["stop_reason"]
        assert needle in reason and "\n" not in reason and len(reason) < 200
        assert out["transitions"][-1]["to"] == "stopped"
        assert _at_rest(run) < 0.05  # joints at rest
        # Every fault in contact lifts the tool (issue 15): no force on the sponge at the end.
        assert out["transitions"][-2]["to"] == "retreat"
        assert run.scene.sponge_contacts() == []
        if mode == "bump":
            assert run.fault.data["force"] > run.guard.force_limit
        assert run.samples[-1].get("stop_reason") == reason or mode == "stall"


def test_frozen_sensor_holds_position(plate):
    run = _faulty_run(plate, "none", after=10**6)
    with run:
        run.arm.sensor = _FrozenSensor(run.arm.sensor, t_freeze=math.inf)
        # freeze 1 s into the exploration
        orig = run._explore

        def explore(steps, on_step):
            run.arm.sensor._t = run.scene.t + 1.0
            return orig(steps, on_step)

        run._explore = explore
        out = run.run(15)
        assert out["final_state"] == "stopped"
        assert "sensor stopped updating" in out["stop_reason"]
        assert out["transitions"][-2]["to"] == "retreat"  # lifted first, without the sensor
        assert run.scene.sponge_contacts() == []
        q_end = run.arm.dev.read_state().q
        assert _at_rest(run) < 0.05
        run.arm.hold(0.2)  # the hold keeps the arm where it stopped
        assert np.max(np.abs(run.arm.dev.read_state().q - q_end)) < 2e-3


def test_unreachable_object_is_refused(plate):
    cap, basis = plate
    cfg = RobotConfig(object_pose=(1.5, 0.0, 0.0), **FAST)
    with pytest.raises(TergodicError, match="reach"):
        RobotRun(cap, _explorer(cap, basis, RobotConfig()), cfg)


def test_explorer_with_wrong_timing_is_refused(plate):
    cap, basis = plate
    ex = Explorer(basis, cap.target, ExploreConfig(nk=40, seed=0, agent_radius=0.008), cap.points[:1],
                  on_event=lambda m: None)
    with pytest.raises(TergodicError, match="robot_explore_config"):
        RobotRun(cap, ex, RobotConfig())


def test_robot_explore_config_keeps_the_path_per_step():
    base = ExploreConfig(v_max=0.003, a_max=0.003, dt=1.0)
    scaled = robot_explore_config(base, 0.2)
    assert scaled.dt == 0.2
    assert scaled.v_max * scaled.dt == pytest.approx(base.v_max * base.dt)
    assert scaled.a_max * scaled.dt**2 == pytest.approx(base.a_max * base.dt**2)


@pytest.mark.slow
def test_bowl_run_meets_the_control_goals():
    """The issue's control goals on the built-in bowl (full resolution, nK = 100), 60 explorer steps."""
    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic="bowl"))
    basis = compute_basis(cap.points, 100, 30)
    cfg = RobotConfig(force=5.0)
    ec = robot_explore_config(ExploreConfig(nk=100, seed=0), cfg.explore_dt)
    ex = Explorer(basis, cap.target, ec, cap.points[np.argmax(cap.target)][None], on_event=lambda m: None)
    out = explore_with_robot(cap, ex, cfg, 60)
    assert out["stop_reason"] == "completed"
    assert out["force_rms_error_rel"] <= 0.10
    assert out["tilt_deg_median"] <= 5.0
    assert out["track_mm_median"] <= 5.0
    assert out["contact_fraction"] >= 0.95
    assert out["touched_sponge"] >= 0.9 * out["touched_agent"]


@pytest.fixture(scope="module")
def sim_bowl():
    """The textured bowl on a 20 cm stand, as a small simulated capture, and its basis."""
    from tergodic_cli.backends.pybullet.camera import SimCameraConfig, SimCaptureConfig, capture_sim
    from tergodic_cli.capture.textured import SimObjectConfig

    cap = capture_sim(SimCaptureConfig(object=SimObjectConfig(object="bowl", marking="X", pose=(0.5, 0.0, 0.2),
                                                              texture_size=64),
                                       camera=SimCameraConfig(renderer="tiny", width=240, height=180)))
    return cap, compute_basis(cap.points, 40, 30)


@pytest.mark.parametrize("where", ["bottom", "near wall"])
def test_approach_meets_the_surface_gently(sim_bowl, where):
    # The bottom of the bowl's mesh is a vertex where many triangles meet: at 20 mm/s the first touch
    # there hit 28 N (limit 15 N). On the wall facing the robot the sponge's side touches first, where
    # a 2 mm/s push alone (0.1 N) never registered. The approach must touch gently and register.
    cap, basis = sim_bowl
    c = cap.points[np.argmin(cap.points[:, 2])]
    target = c if where == "bottom" else c + np.array([-0.055, 0.0, 0.0])
    start = cap.points[np.argmin(np.linalg.norm(cap.points[:, :2] - target[:2], axis=1))][None]
    cfg = RobotConfig(**FAST)
    ec = robot_explore_config(ExploreConfig(nk=40, seed=0, agent_radius=0.008), cfg.explore_dt)
    ex = Explorer(basis, cap.target, ec, start, on_event=lambda msg: None)
    with RobotRun(cap, ex, cfg) as run:
        assert run.mesh_source == "sim_object"
        peak = [0.0]
        check = run.guard.check_force

        def watch(t, w):
            if run.sm.state == "approach":
                peak[0] = max(peak[0], float(np.linalg.norm(np.asarray(w)[:3])))
            return check(t, w)

        run.guard.check_force = watch
        out = run.run(2)
    assert out["stop_reason"] == "completed"
    assert [t["to"] for t in out["transitions"]][:3] == ["hover", "approach", "explore"]
    assert 4.0 < peak[0] <= 2.0 * cfg.force  # pressed to F_d, never more than twice it
