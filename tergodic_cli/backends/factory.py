"""Build hardware backends from CLI-style options; a missing extra fails here with its install hint."""

from __future__ import annotations

import numpy as np

from tergodic_cli.errors import require

from tergodic_cli.backends import registry

#: The real robots, F/T sensors and cameras (names of :data:`~tergodic_cli.backends.registry.BACKENDS`).
ROBOTS = registry.names("robot", hardware=True)
FT_SENSORS = registry.names("ft")
CAMERAS = registry.names("camera")


def make_hardware(robot: str = "franka", robot_ip: str | None = None, ft: str | None = None, ft_address: str | None = None, *,
                  sensor_in_ee=None, read_only: bool = False, gains=None, **options):
    """An (Arm, WrenchSensor) pair from the registry, not yet connected.

    Parameters
    ----------
    robot : a hardware robot of :data:`ROBOTS` ("franka": franky, streamed Cartesian impedance;
        "franka-torque": pylibfranka, the paper's line impedance and wrench PID in a 1 kHz torque loop,
        needs a wrist F/T sensor; "ur": ur_rtde, the same wrench in the UR's force mode).
        robot_ip : the robot's address.
    ft : a sensor of :data:`FT_SENSORS`: "bota" (``ft_address`` = the sensor's JSON configuration, or
        "dummy"), "netft" (``ft_address`` = host[:port]), or an arm's own estimate ("franka", "ur");
        None: the robot's own estimate (franka-torque has none: it needs a wrist sensor).
    sensor_in_ee : (4, 4) pose of the F/T sensor frame in the TCP frame (identity by default).
    read_only : a dry run's devices (no real-time kernel needed: nothing is commanded).
    gains : ControllerGains of the arms that run the line controller (None: each arm's default).
    options : fields of the robot's and the sensor's config dataclasses (model, stream_hz, move_speed,
        ne_t_ee, realtime, isolate, counts_per_force, ...); each config takes its own, None keeps a default.

    The SDKs of both backends are imported here, so a missing extra raises its one-line install hint
    (exit code 2) before anything connects.
    """
    spec = registry.get("robot", robot, "--robot")
    require(spec.hardware, f"--robot {robot} is not a real robot", f"use one of {', '.join(ROBOTS)}")
    require(ft is not None or spec.default_ft is not None, f"--robot {robot} needs a wrist F/T sensor for its 1 kHz wrench PID",
            "add --ft bota or --ft netft with --ft-address")
    fspec = registry.get("ft", ft or spec.default_ft, "--ft")
    ft = fspec.name
    require(not (spec.wrist_ft and fspec.arms is not None), f"--robot {robot} needs a wrist F/T sensor for its 1 kHz wrench PID",
            "add --ft bota or --ft netft with --ft-address")
    require(fspec.arms is None or robot in fspec.arms, f"--ft {ft} is the force estimate of another robot than --robot {robot}",
            f"use --ft bota or netft, or --robot {'|'.join(fspec.arms or ())}")
    if fspec.config is None:
        require(ft_address is None, f"--ft-address does not go with --ft {ft} (the arm's own sensor)",
                "drop --ft-address, or choose --ft bota|netft")
    else:
        require(ft_address is not None, f"--ft {ft} needs --ft-address",
                "give the sensor's JSON configuration file, or 'dummy'" if ft == "bota" else "give the Net F/T box's address, e.g. 192.168.1.1")
    cfg = spec.make_config(ip=str(robot_ip or ""), **options)
    spec.import_sdks()
    fspec.import_sdks()
    frame = None if sensor_in_ee is None else np.asarray(sensor_in_ee, dtype=float)
    sensor = None
    if fspec.config is not None:
        sensor = fspec.factory_fn()(fspec.make_config(address=str(ft_address), frame_in_ee=frame, **options))
    arm = spec.factory_fn()(cfg, sensor, gains, read_only)
    if sensor is None:
        sensor = fspec.factory_fn()(None, arm)
    if not read_only and hasattr(arm, "wrench_sensor"):  # the arm's loop reads the sensor; the run reads it through the loop
        sensor = arm.wrench_sensor
    return arm, sensor


def make_camera(source: str = "realsense", **options):
    """A :class:`~tergodic_cli.backends.camera.Camera` from the registry, not yet connected (the SDK is
    checked now); ``options``: its config's fields (RealSense: serial, width, height, fps, depth_min, ...)."""
    spec = registry.get("camera", source, "camera source")
    spec.import_sdks()
    return spec.factory_fn()(spec.make_config(**options))


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
