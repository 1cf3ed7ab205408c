"""``tergodic capture --source realsense``: one RealSense frame through the file pipeline's filters."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from tergodic_cli.errors import require


def capture_realsense(cfg, serial: str | None = None, width: int = 640, height: int = 480, fps: int = 30,
                      camera_pose=None, frames: int = 1, depth_min: float = 0.1, depth_max: float = 1.5):
    """Capture a coloured cloud with a RealSense camera and segment it like any other capture.

    Parameters
    ----------
    cfg : :class:`~tergodic_cli.capture.CaptureConfig` (filters, target colour; its source becomes "realsense").
    serial : the camera's serial number, or None for the only one connected.
    camera_pose : 7 numbers x,y,z,qx,qy,qz,qw of the optical frame in the robot base frame, or None
        to keep the cloud in the camera's optical frame (then ``--object-pose`` places it for the robot).
    frames : frames merged into the cloud. depth_min, depth_max : metres kept along the optical axis.

    Returns the :class:`~tergodic_cli.capture.Capture`; ``meta["frame"]`` is "robot_base" or
    "camera_optical", ``meta["realsense"]`` the device, its intrinsics and the timings.
    """
    from tergodic_cli.backends.factory import camera_pose_matrix, make_camera
    from tergodic_cli.capture import capture_cloud

    T = camera_pose_matrix(camera_pose) if camera_pose is not None else None
    cam = make_camera("realsense", serial=serial, width=width, height=height, fps=fps, T_base_cam=T,
                      depth_min=depth_min, depth_max=depth_max)
    t0 = time.perf_counter()
    cam.connect()
    try:
        t1 = time.perf_counter()
        require(frames >= 1, f"frames must be >= 1, got {frames}", "e.g. 1")
        clouds = [cam.read() for _ in range(int(frames))]  # merged into one cloud
        points = np.concatenate([p for p, _ in clouds])
        require(len(points) > 0, "the camera returned no valid depth pixels",
                "check the working range (objects closer than ~0.1 m have no depth) and the lighting")
        colors = np.concatenate([c for _, c in clouds])
        cap = capture_cloud(replace(cfg, source="realsense"), raw=(points, colors))
        t2 = time.perf_counter()
        cap.meta["frame"] = "robot_base" if T is not None else "camera_optical"
        cap.meta["provenance"].update(device=cam.name, serial=cam.serial)
        cap.meta["realsense"] = {**cam.describe(), "frames": int(frames),
                                 "timing_ms": {"connect": 1e3 * (t1 - t0), "capture": 1e3 * (t2 - t1)}}
        return cap
    finally:
        cam.disconnect()
