"""The closed outer loop in simulation (issue 6 item 3): clean, re-capture, re-target on the same basis.

Small and quick: the built-in plate on a 20 cm stand with one 7 mm ink spot (an image marking),
a 200x150 TinyRenderer camera, nK = 30, ten explorer steps per cycle. Real parts throughout:
PyBullet (robot and camera), the capture pipeline, the basis, the explorer, a real MCAP log.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("pybullet")
pytest.importorskip("pygafro")

from tergodic_cli.basis import BasisConfig, get_basis  # noqa: E402
from tergodic_cli.capture import load_capture, save_capture  # noqa: E402
from tergodic_cli.backends.pybullet.camera import SimCamera, SimCameraConfig, SimCaptureConfig, capture_sim  # noqa: E402
from tergodic_cli.capture.textured import SimObjectConfig, TexturedObject  # noqa: E402
from tergodic_cli.errors import TergodicError  # noqa: E402
from tergodic_cli.explore import ExploreConfig, Explorer  # noqa: E402
from tergodic_cli.backends.pybullet import (CleaningLoopConfig, RobotRun, clean_with_robot, explore_with_robot,  # noqa: E402
                                           log_recapture, sim_scene_configs)
from tergodic_cli.robot import RobotConfig, robot_explore_config  # noqa: E402

FAST = dict(move_speed=1.6, hover_height=0.02)
POSE = (0.5, 0.0, 0.2)  # on a 20 cm stand: every wall direction is reachable with the sponge tilted
SPOT_M = 0.007  # radius of the ink spot, metres: about the sponge footprint (7.5 mm)


def _spot_png(path, radius_m: float = SPOT_M) -> str:
    """A 96x96 marking image with one round spot in the middle. On the plate the image spans the
    chart box (0.24 m), 2.5 mm a pixel."""
    from PIL import Image

    n = 96
    px = 0.24 / n
    yy, xx = np.mgrid[:n, :n]
    inside = np.hypot((xx + 0.5 - n / 2) * px, (yy + 0.5 - n / 2) * px) <= radius_m
    rgba = np.zeros((n, n, 4), np.uint8)
    rgba[..., :3] = (204, 20, 20)
    rgba[..., 3] = np.where(inside, 255, 0)
    Image.fromarray(rgba, "RGBA").save(path)
    return str(path)


@pytest.fixture
def scene(tmp_path):
    """(camera, capture, basis): the plate with one spot, captured at 200x150 by TinyRenderer."""
    obj_cfg = SimObjectConfig(object="plate", marking=_spot_png(tmp_path / "spot.png"), pose=POSE, mesh_edge=0.006)
    cam = SimCamera(SimCameraConfig(renderer="tiny", width=200, height=150), TexturedObject(obj_cfg))
    cap = capture_sim(SimCaptureConfig(object=obj_cfg, camera=cam.cfg), camera=cam)
    basis, hit = get_basis(cap.points, BasisConfig(nk=30, neighbors=30))
    assert not hit
    yield cam, cap, basis
    cam.close()


def _explorer(cap, basis, rcfg: RobotConfig) -> Explorer:
    ec = robot_explore_config(ExploreConfig(nk=30, seed=0, agent_radius=0.008), rcfg.explore_dt)
    centre = (cap.target @ cap.points) / cap.target.sum()  # of the marking
    start = cap.points[np.argmin(np.linalg.norm(cap.points - centre, axis=1))][None]
    return Explorer(basis, cap.target, ec, start, on_event=lambda msg: None)


def _at_rest(run: RobotRun) -> float:
    return float(np.max(np.abs(run.arm.dev.read_state().dq)))


# ---------------------------------------------------------------------------------- the scene record
def test_scene_configs_round_trip_through_the_capture_folder(scene, tmp_path):
    cam, cap, _ = scene
    save_capture(cap, tmp_path / "cap")
    back = load_capture(tmp_path / "cap")
    obj_cfg, cam_cfg, pipe = sim_scene_configs(back.meta)
    assert obj_cfg.object == "plate" and tuple(obj_cfg.pose) == POSE and obj_cfg.marking == cam.obj.cfg.marking
    assert obj_cfg.cleaning == cam.obj.cfg.cleaning
    assert (cam_cfg.width, cam_cfg.height, cam_cfg.renderer, cam_cfg.fov_deg) == (200, 150, "tiny", cam.cfg.fov_deg)
    assert pipe.source == "sim" and pipe.voxel == cap.meta["config"]["voxel"] and pipe.allow_empty_target
    # the rebuilt scene renders the same cloud, point for point
    with SimCamera(cam_cfg, TexturedObject(obj_cfg)) as cam2:
        cap2 = capture_sim(SimCaptureConfig(object=obj_cfg, camera=cam_cfg, pipeline=pipe), camera=cam2)
    np.testing.assert_array_equal(cap2.points, cap.points)
    np.testing.assert_array_equal(cap2.target, cap.target)


def test_closed_loop_refuses_bad_input(scene):
    cam, cap, basis = scene
    rcfg = RobotConfig(**FAST)
    ex = _explorer(cap, basis, rcfg)
    from tergodic_cli.capture import CaptureConfig, capture_cloud

    plain = capture_cloud(CaptureConfig(source="synthetic", synthetic="plate", voxel=0.005))
    cases = [
        (dict(capture=plain), "simulated capture"),
        (dict(robot_cfg=RobotConfig(object_pose=(0.5, 0, 0), **FAST)), "object-pose"),
        (dict(loop_cfg=CleaningLoopConfig(recapture_every=0)), "recapture-every"),
        (dict(loop_cfg=CleaningLoopConfig(until_clean=1.5)), "until-clean"),
        (dict(loop_cfg=CleaningLoopConfig(max_steps=0)), "max-steps"),
    ]
    for change, needle in cases:
        kw = dict(capture=cap, explorer=ex, robot_cfg=rcfg, camera=cam)
        kw.update(change)
        with pytest.raises(TergodicError, match=needle) as info:
            clean_with_robot(**kw)
        assert "\n" not in str(info.value)


def test_a_sim_capture_is_pressed_on_its_own_object(scene):
    # explore_with_robot on a --source sim capture uses the textured object's surface as the collision
    # body (not a mesh rebuilt from the cloud): the sponge presses where the camera saw the plate.
    cam, cap, basis = scene
    rcfg = RobotConfig(**FAST)
    out = explore_with_robot(cap, _explorer(cap, basis, rcfg), rcfg, 8)
    assert out["mesh_source"] == "sim_object" and out["stop_reason"] == "completed"
    assert out["force_mean_N"] == pytest.approx(5.0, abs=0.5)


# ---------------------------------------------------------------------------------- the loop
def test_loop_cleans_the_spot_without_recomputing_the_basis(scene, monkeypatch, tmp_path):
    cam, cap, basis = scene
    rcfg = RobotConfig(**FAST)
    ex = _explorer(cap, basis, rcfg)

    def no_recompute(*a, **k):
        raise AssertionError("the closed loop recomputed a basis")

    import tergodic_cli.basis as basis_pkg
    import tergodic_cli.basis.cache as cache_mod

    monkeypatch.setattr(cache_mod, "compute_basis", no_recompute)
    monkeypatch.setattr(basis_pkg, "compute_basis", no_recompute)
    true0 = cam.obj.marking_remaining()
    samples, recs, events = [], [], []
    from tergodic_cli.provenance import library_versions
    from tergodic_cli.runlog import RunLog, read_run_log

    with RunLog(tmp_path / "run.mcap", config=ex.cfg.to_dict(), seed=0, versions=library_versions(),
                capture_sidecar=cap.meta, points=basis.points, target=cap.target, cloud_every=10) as log:
        def on_step(step, s):
            samples.append((step, s))
            log.log_step(step, step * ex.cfg.dt, positions=ex.positions, velocities=ex.velocities, normals=ex.normals,
                         metrics=ex.metrics(), step_ms=ex.last_step_ms, robot=s)

        def on_recapture(step, rec):
            recs.append(rec)
            log_recapture(log, ex, step, step * ex.cfg.dt, rec)

        out = clean_with_robot(cap, ex, rcfg, camera=cam, on_step=on_step, on_recapture=on_recapture,
                               on_event=lambda k, m: events.append(m),
                               loop_cfg=CleaningLoopConfig(recapture_every=10, until_clean=0.05, max_steps=60))
        log.close(out)

    assert out["clean_reached"] and out["marking_remaining"] <= 0.05, out["recapture_log"]
    # "clean" means clean: the simulator's own ink left is within 3 points of --until-clean (issue 15 item 6)
    assert out["marking_remaining_true"] <= 0.05 + 0.03, out["recapture_log"]
    assert out["loop_stop"].startswith("clean") and f"true ink left {out['marking_remaining_true']:.1%}" in out["loop_stop"]
    assert out["final_state"] == "done" and out["stop_reason"] == "completed" and not out["interrupted"]
    n = out["recaptures"]
    assert 1 <= n <= 6 and len(recs) == n and out["steps_done"] == 10 * n
    # the camera-seen share falls cycle by cycle; the true ink share falls too, and is never below it by much
    seen = [r["marking_remaining"] for r in out["recapture_log"]]
    assert seen[-1] < seen[0] or n == 1
    assert out["marking_remaining_true"] < true0
    # the basis is reused: every re-capture has the basis' geometry (a cache hit), nothing recomputed
    assert out["basis_recomputed"] is False and out["basis_cache_hits"] == n
    assert all(r["basis_cache_hit"] for r in out["recapture_log"]) and out["recapture_initial"]["basis_cache_hit"]
    # re-targeting: every applied re-capture gave the explorer the camera's new p on the basis points
    for r in recs[:-1]:
        assert r["applied"] and r["target"].shape == (len(basis.points),)
    assert not recs[-1]["applied"]
    if n > 1:
        np.testing.assert_array_equal(ex.p, recs[-2]["target"])
    # the cleaning model saw the measured force: impulse = F x time in contact (about F_d x 0.2 s per step)
    contact_s = 0.2 * sum(1 for _, s in samples if s["in_contact"])
    assert out["cleaning_impulse_Ns"] == pytest.approx(5.0 * contact_s, rel=0.25)
    # the ink left is where the sponge did not go: the texels near the contact points are the cleanest
    cps = np.array([s["contact_point"] for _, s in samples if s["in_contact"]])
    obj = cam.obj
    tex = obj.texel_points @ obj.pose[:3, :3].T + obj.pose[:3, 3]
    marked0 = obj.initial.ravel()[obj.texel_index] > 0.5
    from scipy.spatial import cKDTree

    d, _ = cKDTree(cps).query(tex[marked0])
    now = obj.intensity.ravel()[obj.texel_index][marked0]
    assert np.any(d < 0.004) and now[d < 0.004].mean() < 0.2
    # each cycle: explore -> retreat -> picture (re-capture) -> hover -> approach -> explore ...
    path = [t["to"] for t in out["transitions"]]
    assert path[:4] == ["hover", "approach", "explore", "retreat"] and path[-2:] == ["picture", "done"]
    assert path.count("picture") == n
    # the deferred sample of each cycle's last step carries the re-capture's figures
    tagged = [(k, s) for k, s in samples if "marking_remaining" in s]
    assert [k for k, _ in tagged] == [r["step"] for r in out["recapture_log"]]
    assert [s["marking_remaining"] for _, s in tagged] == seen
    assert [k for k, _ in samples] == list(range(1, 10 * n + 1))
    # the log holds every step, a target cloud per re-capture, and the re-capture events
    data = read_run_log(tmp_path / "run.mcap")
    assert data.steps == 10 * n and data.end["status"] == "ok"
    assert sum("recapture: marking_remaining=" in e[2] for e in data.events) == n
    last = data.clouds[-1]
    np.testing.assert_allclose(last.target, recs[-1]["target"].astype(np.float32))
    assert any("re-capture 1 at step 10" in e for e in events)
    # the replay's figures include the remaining share against steps
    from tergodic_cli.runlog.plots import plot_run

    assert tmp_path / "plots" / "cleaning.png" in plot_run(data, tmp_path / "plots")


def test_loop_stops_at_the_step_budget(scene):
    cam, cap, basis = scene
    rcfg = RobotConfig(**FAST)
    out = clean_with_robot(cap, _explorer(cap, basis, rcfg), rcfg, camera=cam,
                           loop_cfg=CleaningLoopConfig(recapture_every=2, until_clean=0.0, max_steps=3))
    assert out["steps_done"] == 3 and out["recaptures"] == 2 and not out["clean_reached"], out
    assert "budget" in out["loop_stop"] and out["final_state"] == "done"


# ---------------------------------------------------------------------------------- stops
@pytest.fixture
def kept_runs(monkeypatch):
    """Keep every RobotRun the loop builds, and its scene open until the test ends (to inspect the arm)."""
    runs = []
    orig_init, orig_close = RobotRun.__init__, RobotRun.close

    def keep(self, *a, **k):
        orig_init(self, *a, **k)
        runs.append(self)

    monkeypatch.setattr(RobotRun, "__init__", keep)
    monkeypatch.setattr(RobotRun, "close", lambda self: None)
    yield runs
    for r in runs:
        orig_close(r)


def test_ctrl_c_in_the_loop_ends_safe_with_a_readable_log(scene, tmp_path, kept_runs):
    cam, cap, basis = scene
    rcfg = RobotConfig(**FAST)
    ex = _explorer(cap, basis, rcfg)
    from tergodic_cli.provenance import library_versions
    from tergodic_cli.runlog import RunLog, read_run_log

    with RunLog(tmp_path / "run.mcap", config=ex.cfg.to_dict(), seed=0, versions=library_versions(),
                capture_sidecar=cap.meta, points=basis.points, target=cap.target) as log:
        def on_step(step, s):
            log.log_step(step, step * ex.cfg.dt, positions=ex.positions, velocities=ex.velocities,
                         normals=ex.normals, metrics=ex.metrics(), step_ms=ex.last_step_ms, robot=s)
            if step == 5:  # in contact, during the second cycle
                raise KeyboardInterrupt

        out = clean_with_robot(cap, ex, rcfg, camera=cam, on_step=on_step,
                               on_event=lambda step, msg: log.log_event(step, step * ex.cfg.dt, msg),
                               loop_cfg=CleaningLoopConfig(recapture_every=3, until_clean=0.0, max_steps=40))
        run = kept_runs[-1]
        assert out["interrupted"] and out["final_state"] == "stopped"
        assert out["stop_reason"].startswith("interrupted by the user (Ctrl-C)") and "\n" not in out["stop_reason"]
        assert [t["to"] for t in out["transitions"]][-2:] == ["retreat", "stopped"]
        assert run.scene.sponge_contacts() == [] and _at_rest(run) < 0.05
        assert out["recaptures"] == 1 and out["steps_done"] == 5
        log.close(out)
    data = read_run_log(tmp_path / "run.mcap")
    assert data.steps == 5 and data.end["status"] == "ok" and not data.truncated
    assert any("interrupted by the user" in e[2] for e in data.events)


def test_ctrl_c_outside_the_loop_still_leaves_a_readable_log(scene, tmp_path):
    # A Ctrl-C the loop does not catch (here: raised by the caller's own hook after the robot stopped)
    # still finishes the MCAP file; the reader sees every step and the "interrupted" status.
    cam, cap, basis = scene
    rcfg = RobotConfig(**FAST)
    ex = _explorer(cap, basis, rcfg)
    from tergodic_cli.provenance import library_versions
    from tergodic_cli.runlog import RunLog, read_run_log

    with pytest.raises(KeyboardInterrupt):
        with RunLog(tmp_path / "run.mcap", config=ex.cfg.to_dict(), seed=0, versions=library_versions(),
                    capture_sidecar=cap.meta, points=basis.points, target=cap.target) as log:
            def on_step(step, s):
                log.log_step(step, step * ex.cfg.dt, positions=ex.positions, velocities=ex.velocities,
                             normals=ex.normals, metrics=ex.metrics(), step_ms=ex.last_step_ms, robot=s)
                if step == 3:
                    raise KeyboardInterrupt

            out = explore_with_robot(cap, ex, rcfg, 8, on_step=on_step)
            assert out["interrupted"] and out["final_state"] == "stopped" and out["robot_samples"] == 3
            raise KeyboardInterrupt  # the command re-raises after writing what it can
    data = read_run_log(tmp_path / "run.mcap")
    assert data.steps == 3 and data.end["status"] == "interrupted"


def test_a_force_fault_in_a_later_cycle_ends_safe(scene, kept_runs):
    cam, cap, basis = scene
    rcfg = RobotConfig(**FAST)
    ex = _explorer(cap, basis, rcfg)

    def on_step(step, s):
        if step == 5:  # the object is knocked 6 mm into the sponge during the second cycle
            sc = kept_runs[-1].scene
            T = sc.object_pose.copy()
            T[2, 3] += 0.006
            sc.move_object(T)

    out = clean_with_robot(cap, ex, rcfg, camera=cam, on_step=on_step,
                           loop_cfg=CleaningLoopConfig(recapture_every=3, until_clean=0.0, max_steps=40))
    run = kept_runs[-1]
    assert out["final_state"] == "stopped" and "force" in out["stop_reason"] and not out["interrupted"]
    assert out["loop_stop"] == out["stop_reason"] and not out["clean_reached"]
    assert [t["to"] for t in out["transitions"]][-2:] == ["retreat", "stopped"]
    assert run.scene.sponge_contacts() == [] and _at_rest(run) < 0.05
    assert out["recaptures"] == 1 and math.isfinite(out["marking_remaining"])
