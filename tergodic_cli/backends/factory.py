"""Build hardware backends from CLI-style options; a missing extra fails here with its install hint."""

from __future__ import annotations

import numpy as np

from tergodic_cli.errors import require
from tergodic_cli.backends.extras import import_sdk

ROBOTS = ("franka", "franka-torque", "ur")
FT_SENSORS = ("franka", "ur", "bota", "netft")
CAMERAS = ("realsense",)


def make_hardware(robot: str = "franka", robot_ip: str | None = None, ft: str | None = None, ft_address: str | None = None, *,
                  model: str = "panda", stream_hz: float = 100.0, move_speed: float = 0.1, ne_t_ee=None, sensor_in_ee=None,
                  realtime: str = "enforce", counts_per_force: float | None = None, counts_per_torque: float | None = None,
                  read_only: bool = False, gains=None, isolate: str = "process"):
    """An (Arm, WrenchSensor) pair, not yet connected.

    Parameters
    ----------
    robot : "franka" (franky, streamed Cartesian impedance), "franka-torque" (pylibfranka, the paper's
        line impedance and wrench PID in a 1 kHz torque loop; needs --ft bota or netft) or "ur" (ur_rtde:
        the paper's wrench in the UR's force mode). robot_ip : the robot's address.
    model : "panda" or "fr3" (Franka); "ur3e", "ur5e" or "ur10e" (UR; "panda", the default, means ur5e).
    ft : "bota" (bota_driver; ``ft_address`` = the sensor's JSON configuration, or "dummy"), "netft" (ATI
        Net F/T over UDP; ``ft_address`` = host[:port]), "franka" (the Franka's own external wrench
        estimate) or "ur" (the UR's flange sensor); None: the arm's own (bota for franka-torque).
    model, stream_hz, move_speed, ne_t_ee, realtime : see :class:`~tergodic_cli.backends.franka.FrankaConfig`.
    sensor_in_ee : (4, 4) pose of the F/T sensor frame in the TCP frame (identity by default).
    counts_per_force, counts_per_torque : Net F/T scaling (None = read from the box's web page).

    read_only : a dry run's devices (no real-time kernel needed: nothing is commanded).
    gains : ControllerGains of the torque loop (None: the simulation's). isolate : the torque loop's
        "process" (production) or "inline" (tests with a fake SDK).

    The SDK of each chosen backend is imported here, so a missing extra raises its one-line install
    hint (exit code 2) before anything connects.
    """
    require(robot in ROBOTS, f"unknown --robot '{robot}' for hardware", f"use one of {', '.join(ROBOTS)}")
    torque, ur = robot == "franka-torque", robot == "ur"
    ft = ft or ("bota" if torque else "ur" if ur else "franka")
    require(ft in FT_SENSORS, f"unknown --ft '{ft}'", f"use one of {', '.join(FT_SENSORS)}")
    require(not (torque and ft in ("franka", "ur")), "--robot franka-torque needs a wrist F/T sensor for its 1 kHz wrench PID",
            "add --ft bota or --ft netft with --ft-address")
    require((ft == "ur") == ur or ft in ("bota", "netft"), f"--ft {ft} is the force estimate of another robot than --robot {robot}",
            "use --ft bota or netft, or the arm's own (--ft franka with --robot franka, --ft ur with --robot ur)")
    ne = None if ne_t_ee is None else np.asarray(ne_t_ee, dtype=float)
    if ur:
        from tergodic_cli.backends.ur import URArm, URConfig

        import_sdk("rtde_receive")
        if not read_only:
            import_sdk("rtde_control")
        arm = URArm(URConfig(ip=str(robot_ip or ""), model=model if model != "panda" else "ur5e", stream_hz=stream_hz),
                    gains=gains, read_only=read_only)
    elif torque:
        from tergodic_cli.backends.franka.libfranka import LibfrankaConfig

        arm = None
        import_sdk("pylibfranka")
        lcfg = LibfrankaConfig(ip=str(robot_ip or ""), model=model, realtime=realtime, ne_t_ee=ne, stream_hz=stream_hz,
                               isolate=isolate)
        lcfg.validate()
    else:
        from tergodic_cli.backends.franka import FrankaConfig, FrankyArm

        import_sdk("franky")
        arm = FrankyArm(FrankaConfig(ip=str(robot_ip or ""), model=model, stream_hz=stream_hz, move_speed=move_speed,
                                     ne_t_ee=ne, realtime="ignore" if read_only else realtime))
    frame = None if sensor_in_ee is None else np.asarray(sensor_in_ee, dtype=float)
    if ft == "ur":
        from tergodic_cli.backends.ur import URForceSensor

        require(ft_address is None, "--ft-address does not go with the UR's own force sensor", "drop --ft-address, or choose --ft bota|netft")
        sensor = URForceSensor(arm)
    elif ft == "franka":
        from tergodic_cli.backends.franka import FrankaWrenchEstimate

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
    if torque:  # the loop process connects the sensor and reads it at 1 kHz; the run reads it through the loop
        from tergodic_cli.backends.franka.libfranka import make_libfranka_arm

        arm = make_libfranka_arm(lcfg, sensor, gains=gains, read_only=read_only)
        return arm, (sensor if read_only else arm.wrench_sensor)
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
