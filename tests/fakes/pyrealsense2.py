"""A fake ``pyrealsense2`` module (librealsense 2.59 Python API), with a camera looking at an analytic scene.

Shapes follow the real binding: ``context().query_devices()``, ``device.get_info(camera_info.X)``,
``config.enable_device / enable_stream`` (the overloads (stream, width, height, format, framerate) and
(stream, index, width, height, format, framerate)), ``pipeline.start(config) -> pipeline_profile``,
``wait_for_frames(timeout_ms=5000)``, ``align(stream.color).process(frames)``, frames that are falsy
when empty, ``get_data()`` arrays, ``first_depth_sensor().get_depth_scale()``, and
``pipeline.stop()`` refusing when never started (RuntimeError, as documented).

The scene (``_SCENE``) is a plane n·X = c in the colour camera's optical frame with a red disc on it.
The depth camera sits ``baseline`` metres along x from the colour camera, so depth frames that are not
aligned to colour are shifted, and ``align.process`` re-renders depth in the colour geometry.
Depth is quantised to ``depth_scale`` (1 mm), like a z16 stream.
"""

from __future__ import annotations

import enum

import numpy as np

_DEVICES: list = []  # FakeDevice objects "plugged in"


class stream(enum.Enum):  # noqa: N801 - the real names
    any = 0
    depth = 1
    color = 2
    infrared = 3


class format(enum.Enum):  # noqa: N801,A001
    any = 0
    z16 = 1
    rgb8 = 5
    bgr8 = 6


class camera_info(enum.Enum):  # noqa: N801
    name = 0
    serial_number = 1
    firmware_version = 3


class distortion(enum.Enum):  # noqa: N801
    none = 0
    modified_brown_conrady = 1
    inverse_brown_conrady = 2
    ftheta = 3
    brown_conrady = 4
    kannala_brandt4 = 5


class intrinsics:  # noqa: N801
    def __init__(self):
        self.width = 0
        self.height = 0
        self.ppx = 0.0
        self.ppy = 0.0
        self.fx = 0.0
        self.fy = 0.0
        self.model = distortion.none
        self.coeffs = [0.0] * 5


class Scene:
    """plane n·X = c (colour optical frame, m), grey, with a red disc of ``radius`` around ``centre``."""

    def __init__(self, normal=(0.0, 0.0, 1.0), c: float = 0.5, centre=(0.0, 0.0, 0.5), radius: float = 0.05):
        self.n = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
        self.c = float(c)
        self.centre = np.asarray(centre, dtype=float)
        self.radius = float(radius)

    def depth(self, intr: intrinsics, shift_x: float = 0.0) -> np.ndarray:
        """Depth along the optical axis of a camera displaced by shift_x along x (same orientation)."""
        v, u = np.indices((intr.height, intr.width), dtype=float)
        x, y = (u - intr.ppx) / intr.fx, (v - intr.ppy) / intr.fy
        # a point of the camera ray: O + z (x, y, 1) with O = (shift_x, 0, 0) in the colour frame
        denom = self.n[0] * x + self.n[1] * y + self.n[2]
        return (self.c - self.n[0] * shift_x) / denom

    def colour(self, intr: intrinsics) -> np.ndarray:
        z = self.depth(intr)
        v, u = np.indices((intr.height, intr.width), dtype=float)
        X = np.stack([(u - intr.ppx) / intr.fx * z, (v - intr.ppy) / intr.fy * z, z], axis=-1)
        red = np.linalg.norm(X - self.centre, axis=-1) <= self.radius
        img = np.full(z.shape + (3,), 180, dtype=np.uint8)
        img[red] = (220, 20, 30)
        return img


class FakeDevice:
    def __init__(self, serial: str = "123456789012", name: str = "Intel RealSense D435", scene: Scene | None = None,
                 depth_scale: float = 0.001, baseline: float = 0.015,
                 profiles=((640, 480, 30), (1280, 720, 30), (848, 480, 30))):
        self.serial, self.name, self.scene = serial, name, scene or Scene()
        self.depth_scale, self.baseline, self.profiles = depth_scale, baseline, tuple(profiles)
        self.streaming = False
        self.frames_delivered = 0

    def intrinsics(self, width: int, height: int) -> intrinsics:
        i = intrinsics()
        i.width, i.height = width, height
        i.fx = i.fy = 0.95 * width  # about a D435's colour camera (69 deg horizontal)
        i.ppx, i.ppy = width / 2 - 0.5 + 1.25, height / 2 - 0.5 - 0.75
        return i


class device:  # noqa: N801
    def __init__(self, dev: FakeDevice):
        self._dev = dev

    def get_info(self, info: camera_info) -> str:
        if info == camera_info.serial_number:
            return self._dev.serial
        if info == camera_info.name:
            return self._dev.name
        return "5.15.0.2"

    def first_depth_sensor(self) -> "depth_sensor":
        return depth_sensor(self._dev)


class depth_sensor:  # noqa: N801
    def __init__(self, dev: FakeDevice):
        self._dev = dev

    def get_depth_scale(self) -> float:
        return self._dev.depth_scale


class context:  # noqa: N801
    def query_devices(self) -> list:
        return [device(d) for d in _DEVICES]


class config:  # noqa: N801
    def __init__(self):
        self.serial = None
        self.streams: dict = {}

    def enable_device(self, serial: str) -> None:
        self.serial = str(serial)

    def enable_stream(self, stream_type: stream, *args) -> None:
        if len(args) == 4:
            width, height, fmt, fps = args
        elif len(args) == 5:
            _, width, height, fmt, fps = args
        else:
            raise TypeError("enable_stream(): incompatible function arguments")
        if not isinstance(stream_type, stream) or not isinstance(fmt, format):
            raise TypeError("enable_stream(): incompatible function arguments")
        self.streams[stream_type] = (int(width), int(height), fmt, int(fps))


class video_stream_profile:  # noqa: N801
    def __init__(self, intr: intrinsics):
        self._intr = intr

    def as_video_stream_profile(self) -> "video_stream_profile":
        return self

    def get_intrinsics(self) -> intrinsics:
        return self._intr


class pipeline_profile:  # noqa: N801
    def __init__(self, dev: FakeDevice, intr_color: intrinsics, intr_depth: intrinsics):
        self._dev, self._color, self._depth = dev, intr_color, intr_depth

    def get_device(self) -> device:
        return device(self._dev)

    def get_stream(self, stream_type: stream, stream_index: int = -1) -> video_stream_profile:
        return video_stream_profile(self._color if stream_type == stream.color else self._depth)


class frame:  # noqa: N801
    def __init__(self, data: np.ndarray | None, timestamp_ms: float = 0.0):
        self._data = data
        self._ts = timestamp_ms

    def __bool__(self) -> bool:
        return self._data is not None

    def get_data(self) -> np.ndarray:
        return self._data

    def get_timestamp(self) -> float:
        return self._ts

    def get_width(self) -> int:
        return self._data.shape[1]

    def get_height(self) -> int:
        return self._data.shape[0]


class depth_frame(frame):  # noqa: N801
    def __init__(self, data, timestamp_ms, units):
        super().__init__(data, timestamp_ms)
        self._units = units

    def get_units(self) -> float:
        return self._units


class video_frame(frame):  # noqa: N801
    pass


class composite_frame:  # noqa: N801
    def __init__(self, dev: FakeDevice, intr: intrinsics, t_ms: float, aligned: bool):
        self._dev, self._intr, self._t, self._aligned = dev, intr, t_ms, aligned

    def get_depth_frame(self) -> depth_frame:
        d = self._dev
        z = d.scene.depth(self._intr, 0.0 if self._aligned else d.baseline)
        raw = np.where(np.isfinite(z) & (z > 0), np.round(z / d.depth_scale), 0).astype(np.uint16)
        return depth_frame(raw, self._t, d.depth_scale)

    def get_color_frame(self) -> video_frame:
        return video_frame(self._dev.scene.colour(self._intr), self._t)


class align:  # noqa: N801
    def __init__(self, align_to: stream):
        if not isinstance(align_to, stream):
            raise TypeError("__init__(): incompatible constructor arguments")
        self.align_to = align_to

    def process(self, frames: composite_frame) -> composite_frame:
        if self.align_to != stream.color:
            raise NotImplementedError("the fake aligns depth to colour only")
        return composite_frame(frames._dev, frames._intr, frames._t, aligned=True)


class pipeline:  # noqa: N801
    def __init__(self, ctx: context | None = None):
        self._dev = None
        self._intr = None
        self._t = 0.0

    def start(self, cfg: config | None = None) -> pipeline_profile:
        cfg = cfg or config()
        devs = [d for d in _DEVICES if cfg.serial is None or d.serial == cfg.serial]
        if not devs:
            raise RuntimeError("No device connected")
        dev = devs[0]
        if dev.streaming:
            raise RuntimeError("Device or resource busy")
        want = cfg.streams or {stream.depth: (640, 480, format.z16, 30), stream.color: (640, 480, format.rgb8, 30)}
        for s, (w, h, fmt, fps) in want.items():
            ok_fmt = (s == stream.depth and fmt == format.z16) or (s == stream.color and fmt in (format.rgb8, format.bgr8))
            if (w, h, fps) not in dev.profiles or not ok_fmt:
                raise RuntimeError("Couldn't resolve requests")
        w, h, _, _ = want.get(stream.color, (640, 480, format.rgb8, 30))
        self._dev, self._intr = dev, dev.intrinsics(w, h)
        dev.streaming = True
        return pipeline_profile(dev, self._intr, self._intr)

    def wait_for_frames(self, timeout_ms: int = 5000) -> composite_frame:
        if self._dev is None:
            raise RuntimeError("wait_for_frames cannot be called before start()")
        self._t += 1000.0 / 30.0
        self._dev.frames_delivered += 1
        return composite_frame(self._dev, self._intr, self._t, aligned=False)

    def stop(self) -> None:
        if self._dev is None:
            raise RuntimeError("stop() cannot be called before start()")
        self._dev.streaming = False
        self._dev = None
