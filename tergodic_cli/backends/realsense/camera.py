"""Intel RealSense depth cameras through pyrealsense2 (``pip install 'tergodic[realsense]'``).

API used (pyrealsense2 2.59, checked against the installed package): ``context().query_devices()``
and ``device.get_info(camera_info.serial_number)``; ``config.enable_device(serial)``,
``config.enable_stream(stream, width, height, format, framerate)``; ``pipeline.start(config)``
returning a ``pipeline_profile`` (``get_device().first_depth_sensor().get_depth_scale()``,
``get_stream(stream.color).as_video_stream_profile().get_intrinsics()``);
``pipeline.wait_for_frames(timeout_ms)``; ``align(stream.color).process(frames)`` then
``get_depth_frame()`` / ``get_color_frame()`` and ``np.asanyarray(frame.get_data())``;
``pipeline.stop()``.

Depth is aligned to the colour image, so one set of intrinsics (the colour stream's, with its
distortion model) back-projects every pixel (:func:`~tergodic_cli.backends.camera.deproject`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tergodic_cli.config import Config
from tergodic_cli.errors import TergodicError, require
from tergodic_cli.backends.camera import Intrinsics, RGBDFrame, frame_to_cloud
from tergodic_cli.backends.extras import import_sdk


@dataclass
class RealSenseConfig(Config):
    """serial : the camera's serial number (None = the only one connected).
    width, height, fps : stream profile of both streams (D400: 640x480 or 1280x720 at 6-30 fps).
    depth_min, depth_max : metres kept along the optical axis (D435 sees from ~0.1 m).
    warmup_frames : frames dropped after start while auto-exposure settles.
    timeout_ms : wait for a frame set. T_base_cam : (4, 4) optical frame in the robot base frame
        (hand-eye calibration); None = clouds in the camera's optical frame.
    """

    serial: str | None = None
    width: int = 640
    height: int = 480
    fps: int = 30
    depth_min: float = 0.1
    depth_max: float = 1.5
    warmup_frames: int = 15
    timeout_ms: int = 5000
    T_base_cam: np.ndarray | None = None

    def validate(self) -> None:
        require(16 <= self.width <= 4096 and 16 <= self.height <= 4096, f"image size {self.width}x{self.height} is out of range",
                "use a profile the camera offers, e.g. --width 640 --height 480")
        require(1 <= self.fps <= 300, f"frame rate {self.fps} is out of range", "e.g. 30")
        require(0 <= self.depth_min < self.depth_max, f"depth range {self.depth_min}..{self.depth_max} m is empty", "e.g. 0.1 to 1.5 m")
        require(self.warmup_frames >= 0, "warmup_frames must be >= 0", "e.g. 15")
        if self.T_base_cam is not None:
            T = np.asarray(self.T_base_cam, dtype=float)
            require(T.shape == (4, 4) and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6),
                    "the camera pose is not a rigid (4, 4) transform", "give --camera-pose x,y,z,qx,qy,qz,qw of the optical frame")


class RealSenseCamera:
    """A RealSense camera behind :class:`~tergodic_cli.backends.camera.Camera`."""

    def __init__(self, cfg: RealSenseConfig | None = None):
        self.cfg = cfg or RealSenseConfig()
        self.cfg.validate()
        # set by connect(): the stream, its intrinsics and depth scale (m per unit), the device
        self.pipeline = self.intrinsics = self.depth_scale = None
        self.serial = self.name = self._align = None

    def connect(self) -> None:
        if self.pipeline is not None:
            return
        rs = import_sdk("pyrealsense2")
        cfg = self.cfg
        devices = list(rs.context().query_devices())
        serials = [d.get_info(rs.camera_info.serial_number) for d in devices]
        require(len(serials) > 0, "no RealSense camera is connected", "plug it into a USB 3 port and check it shows in realsense-viewer")
        if cfg.serial is None:
            require(len(serials) == 1, f"{len(serials)} RealSense cameras are connected ({', '.join(serials)})", "choose one with --serial")
            serial = serials[0]
        else:
            require(cfg.serial in serials, f"no RealSense camera with serial {cfg.serial} (connected: {', '.join(serials)})",
                    "check --serial")
            serial = cfg.serial
        dev = devices[serials.index(serial)]
        self.name = dev.get_info(rs.camera_info.name)
        config = rs.config()
        config.enable_device(serial)
        config.enable_stream(rs.stream.depth, cfg.width, cfg.height, rs.format.z16, cfg.fps)
        config.enable_stream(rs.stream.color, cfg.width, cfg.height, rs.format.rgb8, cfg.fps)
        pipeline = rs.pipeline()
        try:
            profile = pipeline.start(config)
        except RuntimeError as exc:
            raise TergodicError(f"the RealSense {serial} cannot stream {cfg.width}x{cfg.height} at {cfg.fps} fps: {' '.join(str(exc).split())[:160]}",
                                "choose a profile it supports (e.g. 640x480 at 30 fps) with --width/--height") from None
        self.pipeline = pipeline
        self.serial = serial
        try:
            self.depth_scale = float(profile.get_device().first_depth_sensor().get_depth_scale())
            intr = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
            model = getattr(intr.model, "name", str(intr.model).rsplit(".", 1)[-1])
            self.intrinsics = Intrinsics(int(intr.width), int(intr.height), float(intr.fx), float(intr.fy), float(intr.ppx),
                                         float(intr.ppy), str(model), tuple(float(c) for c in intr.coeffs))
            self._align = rs.align(rs.stream.color)
            for _ in range(int(cfg.warmup_frames)):
                pipeline.wait_for_frames(int(cfg.timeout_ms))
        except BaseException:
            self.disconnect()
            raise

    def read_frame(self) -> RGBDFrame:
        require(self.pipeline is not None, "the RealSense camera is not connected", "call connect() first")
        try:
            frames = self.pipeline.wait_for_frames(int(self.cfg.timeout_ms))
        except RuntimeError as exc:
            raise TergodicError(f"the RealSense {self.serial} delivered no frames: {' '.join(str(exc).split())[:160]}",
                                "check the USB 3 connection and that no other program holds the camera") from None
        aligned = self._align.process(frames)
        depth, color = aligned.get_depth_frame(), aligned.get_color_frame()
        require(depth and color, "the RealSense frame set lacks depth or colour", "retry; if it persists, replug the camera")
        z = np.asanyarray(depth.get_data()).astype(np.float64) * self.depth_scale
        rgb = np.asanyarray(color.get_data()).astype(np.float64) / 255.0
        T = np.eye(4) if self.cfg.T_base_cam is None else np.asarray(self.cfg.T_base_cam, dtype=float)
        return RGBDFrame(z, rgb, self.intrinsics, T, 1e-3 * float(depth.get_timestamp()))

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        return frame_to_cloud(self.read_frame(), self.cfg.depth_min, self.cfg.depth_max)

    def describe(self) -> dict:
        return {**self.cfg.to_dict(), "serial": self.serial, "name": self.name, "depth_scale": self.depth_scale,
                "intrinsics": self.intrinsics.to_dict() if self.intrinsics else None}

    def disconnect(self) -> None:
        if self.pipeline is None:
            return
        try:
            self.pipeline.stop()
        finally:
            self.pipeline = None
