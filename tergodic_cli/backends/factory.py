"""Build hardware backends from CLI-style options; a missing extra fails here with its install hint."""

from __future__ import annotations

import numpy as np

from tergodic_cli.errors import require
from tergodic_cli.backends.extras import import_sdk

ROBOTS = ("franka",)
FT_SENSORS = ("franka", "bota", "netft")
CAMERAS = ("realsense",)


def make_hardware(robot: str = "franka", robot_ip: str | None = None, ft: str | None = None, ft_address: str | None = None, *,
                  model: str = "panda", stream_hz: float = 100.0, move_speed: float = 0.1, ne_t_ee=None, sensor_in_ee=None,
                  realtime: str = "enforce", counts_per_force: float | None = None, counts_per_torque: float | None = None):
    """An (Arm, WrenchSensor) pair, not yet connected.

    Parameters
    ----------
    robot : "franka" (franky). robot_ip : the FCI address.
    ft : "bota" (bota_driver; ``ft_address`` = the sensor's JSON configuration, or "dummy"), "netft" (ATI
        Net F/T over UDP; ``ft_address`` = host[:port]), or "franka"/None (the arm's own external
        wrench estimate: no extra sensor).
    model, stream_hz, move_speed, ne_t_ee, realtime : see :class:`~tergodic_cli.backends.franka.FrankaConfig`.
    sensor_in_ee : (4, 4) pose of the F/T sensor frame in the TCP frame (identity by default).
    counts_per_force, counts_per_torque : Net F/T scaling (None = read from the box's web page).

    The SDK of each chosen backend is imported here, so a missing extra raises its one-line install
    hint (exit code 2) before anything connects.
    """
    require(robot in ROBOTS, f"unknown --robot '{robot}' for hardware", f"use one of {', '.join(ROBOTS)}")
    ft = ft or "franka"
    require(ft in FT_SENSORS, f"unknown --ft '{ft}'", f"use one of {', '.join(FT_SENSORS)}")
    from tergodic_cli.backends.franka import FrankaConfig, FrankaWrenchEstimate, FrankyArm

    import_sdk("franky")
    arm = FrankyArm(FrankaConfig(ip=str(robot_ip or ""), model=model, stream_hz=stream_hz, move_speed=move_speed,
                                 ne_t_ee=None if ne_t_ee is None else np.asarray(ne_t_ee, dtype=float), realtime=realtime))
    frame = None if sensor_in_ee is None else np.asarray(sensor_in_ee, dtype=float)
    if ft == "franka":
        require(ft_address is None, "--ft-address does not go with the arm's own force estimate", "drop --ft-address, or choose --ft bota|netft")
        sensor = FrankaWrenchEstimate(arm)
    elif ft == "bota":
        from tergodic_cli.backends.bota import BotaConfig, BotaSensor

        require(ft_address is not None, "--ft bota needs --ft-address", "give the sensor's JSON configuration file, or 'dummy'")
        import_sdk("bota_driver")
        sensor = BotaSensor(BotaConfig(address=str(ft_address), frame_in_ee=frame))
    else:
        from tergodic_cli.backends.netft import NetFTConfig, NetFTSensor

        require(ft_address is not None, "--ft netft needs --ft-address", "give the Net F/T box's address, e.g. 192.168.1.1")
        sensor = NetFTSensor(NetFTConfig(address=str(ft_address), counts_per_force=counts_per_force,
                                         counts_per_torque=counts_per_torque, frame_in_ee=frame))
    return arm, sensor


def make_camera(source: str = "realsense", **options):
    """A :class:`~tergodic_cli.backends.camera.Camera`, not yet connected (the SDK is checked now); ``options``:
    the :class:`~tergodic_cli.backends.realsense.RealSenseConfig` fields (serial, width, height, fps, depth_min, ...)."""
    require(source in CAMERAS, f"unknown camera source '{source}'", f"use one of {', '.join(CAMERAS)}")
    import_sdk("pyrealsense2")
    from tergodic_cli.backends.realsense import RealSenseCamera, RealSenseConfig

    return RealSenseCamera(RealSenseConfig(**options))


def camera_pose_matrix(values):
    """7 numbers x,y,z,qx,qy,qz,qw (the optical frame in the base frame) -> (4, 4)."""
    from tergodic_cli.robot.ga import pose_matrix, quat_to_matrix

    v = [float(x) for x in values]
    require(len(v) == 7, f"--camera-pose for a real camera needs 7 numbers, got {len(v)}",
            "give the optical frame's pose from your hand-eye calibration: x,y,z,qx,qy,qz,qw (m)")
    q = np.array(v[3:])
    require(bool(np.all(np.isfinite(v))) and abs(np.linalg.norm(q) - 1.0) < 1e-3, "--camera-pose quaternion is not unit length",
            "give x,y,z,qx,qy,qz,qw with a unit quaternion")
    return pose_matrix(quat_to_matrix(q / np.linalg.norm(q)), np.array(v[:3]))
