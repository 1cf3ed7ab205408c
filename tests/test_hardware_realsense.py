"""RealSense capture with a fake ``pyrealsense2`` (tests/fakes/pyrealsense2.py) and the back-projection maths."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import assert_one_line_error, run_cli
from fakes import install, uninstall

from tergodic_cli.capture import CaptureConfig
from tergodic_cli.errors import TergodicError
from tergodic_cli.backends import Camera, Intrinsics, deproject, make_camera
from tergodic_cli.backends.realsense.capture import capture_realsense

# librealsense 2.59.1's own rs2_deproject_pixel_to_point (pyrealsense2 wheel), for
# 640x480, fx 600, fy 610, ppx 320.5, ppy 240.25, coeffs (0.1, -0.05, 0.001, 0.002, 0.01):
# (u, v, depth) -> point, float32 results. Recorded once from the real SDK.
SDK_PIXELS = [(0.0, 0.0, 0.7), (639.0, 479.0, 1.2), (100.0, 50.0, 0.5), (320.5, 240.25, 0.45), (500.0, 100.0, 0.9)]
SDK_POINTS = {
    "none": [[-0.373916686, -0.275696725, 0.7], [0.636999965, 0.469672173, 1.2], [-0.183750004, -0.155942619, 0.5],
             [0.0, 0.0, 0.45], [0.269250005, -0.206926227, 0.9]],
    "inverse_brown_conrady": [[-0.363372535, -0.267788291, 0.7], [0.613985479, 0.452925414, 1.2],
                              [-0.180736855, -0.153308496, 0.5], [0.0, 0.0, 0.45], [0.265376329, -0.204261065, 0.9]],
    "brown_conrady": [[-0.363306999, -0.267740011, 0.7], [0.614090681, 0.453003138, 1.2], [-0.18072249, -0.153296307, 0.5],
                      [0.0, 0.0, 0.45], [0.265381157, -0.20426479, 0.9]],
}


@pytest.fixture
def rs(monkeypatch):
    mod = install(monkeypatch, "pyrealsense2")
    monkeypatch.setattr(mod, "_DEVICES", [mod.FakeDevice()])
    return mod


@pytest.mark.parametrize("model", list(SDK_POINTS))
def test_deprojection_matches_librealsense(model):
    intr = Intrinsics(640, 480, 600.0, 610.0, 320.5, 240.25, model, (0.1, -0.05, 0.001, 0.002, 0.01))
    u, v, z = np.array(SDK_PIXELS).T
    pts = deproject(z, intr, None, rows=v, cols=u)
    np.testing.assert_allclose(pts, SDK_POINTS[model], atol=1e-6)  # the SDK computes in float32


def test_unsupported_distortion_is_refused():
    intr = Intrinsics(640, 480, 600.0, 600.0, 320.0, 240.0, "kannala_brandt4", (0.1, 0, 0, 0, 0))
    with pytest.raises(TergodicError, match="cannot undo"):
        deproject(np.ones((2, 2)), intr)


def test_plane_at_half_a_metre_within_a_millimetre(rs):
    # A tilted plane n·X = c seen by the camera: every back-projected point must lie on it (z16 depth,
    # 1 mm steps, so the error is the quantisation: <= 0.5 mm along the optical axis).
    n = np.array([0.15, -0.1, 1.0])
    n /= np.linalg.norm(n)
    rs._DEVICES[0].scene = rs.Scene(normal=n, c=0.5 * n[2])
    cam = make_camera("realsense")
    assert isinstance(cam, Camera)
    cam.connect()
    try:
        pts, cols = cam.read()
    finally:
        cam.disconnect()
    assert len(pts) == 640 * 480
    dist = pts @ n - 0.5 * n[2]
    assert np.abs(dist).max() <= 1e-3
    assert np.abs(dist).mean() < 3e-4
    assert cols.min() >= 0 and cols.max() <= 1


def test_depth_is_aligned_to_colour(rs):
    # The fake's depth camera sits 15 mm beside the colour camera: without align.process the red disc
    # (a colour feature) would land 15 mm off in the cloud. Its centroid must be where the scene put it.
    n = np.array([0.3, 0.0, 1.0]) / np.hypot(0.3, 1.0)  # tilted: a sideways shift changes the depth
    centre = np.array([0.03, -0.02, 0.5])
    rs._DEVICES[0].scene = rs.Scene(normal=n, c=float(n @ centre), centre=centre, radius=0.04)
    cap = capture_realsense(CaptureConfig(source="realsense", voxel=0.0))
    red = cap.points[cap.target > 0]
    np.testing.assert_allclose(red.mean(axis=0), [0.03, -0.02, 0.5], atol=1e-3)
    assert cap.meta["frame"] == "camera_optical"
    assert cap.meta["realsense"]["serial"] == "123456789012"
    assert cap.meta["realsense"]["intrinsics"]["model"] == "none"


def test_camera_pose_puts_the_cloud_in_the_base_frame(rs):
    # Camera 0.6 m above the base origin looking straight down (optical z = -base z): qx = 1 (180° about x).
    cap = capture_realsense(CaptureConfig(source="realsense", voxel=0.0), camera_pose=(0.4, 0.0, 0.6, 1.0, 0.0, 0.0, 0.0))
    assert cap.meta["frame"] == "robot_base"
    np.testing.assert_allclose(cap.points[:, 2], 0.1, atol=1e-3)  # the plane 0.5 m in front of the lens
    red = cap.points[cap.target > 0].mean(axis=0)
    np.testing.assert_allclose(red, [0.4, 0.0, 0.1], atol=1e-3)


def test_cli_capture_realsense_writes_a_segmented_cloud(rs, tmp_path):
    res = run_cli("capture", "--source", "realsense", "--out", tmp_path / "cap", "--voxel", "0.003")
    assert res.code == 0, res.err
    meta = json.loads((tmp_path / "cap" / "capture.json").read_text())
    assert meta["config"]["source"] == "realsense"
    share = meta["target"]["share"]
    # red disc of radius 5 cm on a plane 0.5 m away, in a 0.95 w focal-length view: analytic share of the image
    fx = 0.95 * 640
    area_image = (640 * 0.5 / fx) * (480 * 0.5 / fx)
    assert share == pytest.approx(np.pi * 0.05**2 / area_image, rel=0.05)
    assert "realsense Intel RealSense D435 (123456789012)" in res.out


def test_cli_errors_are_one_line(rs, monkeypatch, tmp_path):
    res = run_cli("capture", "--source", "realsense", "--serial", "999", "--out", tmp_path / "a")
    assert_one_line_error(res, "no RealSense camera with serial 999", "123456789012")
    res = run_cli("capture", "--source", "realsense", "--width", "1000", "--height", "700", "--out", tmp_path / "b")
    assert_one_line_error(res, "cannot stream 1000x700")
    res = run_cli("capture", "--source", "realsense", "--camera-pose", "0.4,0,0.6", "--out", tmp_path / "c")
    assert_one_line_error(res, "needs 7 numbers")
    monkeypatch.setattr(rs, "_DEVICES", [])
    res = run_cli("capture", "--source", "realsense", "--out", tmp_path / "d")
    assert_one_line_error(res, "no RealSense camera is connected")
    assert not any((tmp_path / x).exists() for x in "abcd")


def test_cli_without_the_sdk_prints_the_install_hint(monkeypatch, tmp_path):
    uninstall(monkeypatch, "pyrealsense2")
    res = run_cli("capture", "--source", "realsense", "--out", tmp_path / "cap")
    assert_one_line_error(res, "pyrealsense2 is not installed", "pip install 'tergodic[realsense]'")
    assert not (tmp_path / "cap").exists()


def test_disconnect_releases_the_device(rs):
    cam = make_camera("realsense")
    cam.connect()
    assert rs._DEVICES[0].streaming and rs._DEVICES[0].frames_delivered == 15  # warm-up frames dropped
    cam.disconnect()
    assert not rs._DEVICES[0].streaming
    cam.disconnect()  # idempotent
