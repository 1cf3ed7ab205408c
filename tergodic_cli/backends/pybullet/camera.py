"""A simulated RGB-D camera: PyBullet renders a textured object, the depth buffer becomes a coloured cloud.

One capture (formulas and measured accuracy in docs/sim_camera.md): ``getCameraImage`` in a private
DIRECT client (EGL plugin when it loads, TinyRenderer otherwise) with our own OpenGL view and
projection matrices; the depth buffer linearised to metres; every object pixel back-projected with
the projection's pinhole intrinsics, shifted by where the renderer samples a pixel (PIXEL_SAMPLE),
into the robot base frame; then the filters and segmentation of
:func:`~tergodic_cli.capture.capture_cloud`.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from tergodic_cli.backends.camera import Intrinsics, deproject
from tergodic_cli.capture.textured import SimObjectConfig, TexturedObject, parse_pose
from tergodic_cli.config import Config
from tergodic_cli.robot.ga import matrix_to_quat, motor_inverse, pose_matrix
from tergodic_cli.errors import require

if TYPE_CHECKING:
    from tergodic_cli.capture import Capture, CaptureConfig

RENDERERS = ("auto", "egl", "tiny")
#: Where each renderer samples pixel (row i, column j) on the image plane, as (o_u, o_v) in
#: u = j + o_u, v = i + o_v (origin at the image's top-left corner). OpenGL (EGL) samples pixel
#: centres; TinyRenderer samples integer corners of its bottom-up raster, which is (j, i + 1)
#: top-down (measured against planes, tests/test_sim_camera.py).
PIXEL_SAMPLE = {"egl": (0.5, 0.5), "tiny": (0.0, 1.0)}
#: Default camera: about the Panda's wrist camera at its "ready" picture pose (flange near
#: x = 0.31 m, z = 0.59 m), looking at the object's centre 0.5 m in front of the base.
DEFAULT_EYE = (0.30, 0.0, 0.60)


@dataclass
class SimCameraConfig(Config):
    """The simulated camera.

    pose : None = look from DEFAULT_EYE at the object's bounding-box centre; 6 numbers = eye x,y,z and
        target x,y,z (look-at, image up towards base +z, or +x when looking straight down);
        7 numbers = x,y,z,qx,qy,qz,qw of the optical frame (x right, y down, z forward) in the base frame.
    width, height : image size, pixels. fov_deg : vertical field of view, degrees (about a D435's colour camera).
    near, far : clipping planes, metres. renderer : "auto" (EGL, else TinyRenderer), "egl" or "tiny".
    depth_noise : std of Gaussian noise added to depth, metres; color_noise : std added to RGB in [0, 1].
    seed : seeds both noises.
    """

    pose: tuple[float, ...] | None = None
    width: int = 640
    height: int = 480
    fov_deg: float = 42.0
    near: float = 0.05
    far: float = 3.0
    renderer: str = "auto"
    depth_noise: float = 0.0
    color_noise: float = 0.0
    seed: int = 0

    def validate(self) -> None:
        require(16 <= self.width <= 4096 and 16 <= self.height <= 4096, f"image size {self.width}x{self.height} is out of range",
                "give --width/--height between 16 and 4096 pixels, e.g. 640 480")
        require(5.0 <= self.fov_deg <= 150.0, f"field of view {self.fov_deg} deg is out of range", "give --fov in degrees, e.g. 42")
        require(0 < self.near < self.far, f"clipping planes near={self.near} far={self.far} are not 0 < near < far", "e.g. 0.05 and 3.0")
        require(self.renderer in RENDERERS, f"unknown renderer '{self.renderer}'", f"use one of {', '.join(RENDERERS)}")
        require(self.depth_noise >= 0 and self.color_noise >= 0, "noise levels must be >= 0", "e.g. --depth-noise 0.001")


@dataclass
class SimCaptureConfig:
    """A full simulated capture: the scene, the camera and the capture pipeline's filters."""

    object: SimObjectConfig = field(default_factory=SimObjectConfig)
    camera: SimCameraConfig = field(default_factory=SimCameraConfig)
    pipeline: CaptureConfig | None = None  # None = CaptureConfig(source="sim") with the file pipeline's defaults


# ----------------------------------------------------------------------------- camera model (pure)
def intrinsics(width: int, height: int, fov_deg: float) -> tuple[float, float, float, float]:
    """Pinhole intrinsics of a vertical field of view, square pixels.

    fy = (height / 2) / tan(fov / 2), fx = fy, cx = width / 2, cy = height / 2 (pixel (0, 0)'s
    top-left corner is the origin, so pixel j's centre is at j + 0.5).

    Parameters
    ----------
    width, height : int
        Image size, pixels.
    fov_deg : float
        Vertical field of view, degrees.

    Returns
    -------
    (fx, fy, cx, cy) : tuple of float
        Pixels.
    """
    fy = 0.5 * height / np.tan(0.5 * np.deg2rad(fov_deg))
    return float(fy), float(fy), 0.5 * width, 0.5 * height


def projection_matrix(width: int, height: int, fov_deg: float, near: float, far: float) -> np.ndarray:
    """The OpenGL perspective projection (what ``computeProjectionMatrixFOV`` builds).

    Parameters
    ----------
    width, height : int
        Image size, pixels.
    fov_deg : float
        Vertical field of view, degrees.
    near, far : float
        Clipping planes, metres.

    Returns
    -------
    (4, 4) float
    """
    f = 1.0 / np.tan(0.5 * np.deg2rad(fov_deg))
    aspect = width / height
    return np.array([[f / aspect, 0, 0, 0],
                     [0, f, 0, 0],
                     [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)],
                     [0, 0, -1, 0]])


def view_matrix(T_base_cam: np.ndarray) -> np.ndarray:
    """OpenGL view matrix: base frame -> OpenGL eye frame (x right, y up, z backwards).

    Parameters
    ----------
    T_base_cam : (4, 4) float
        The optical frame (x right, y down, z forward) in the base frame, metres.

    Returns
    -------
    (4, 4) float
    """
    T_gl = T_base_cam.copy()
    T_gl[:3, 1:3] *= -1.0  # optical -> OpenGL eye axes
    return motor_inverse(T_gl)


def linearize_depth(d: np.ndarray, near: float, far: float) -> np.ndarray:
    """OpenGL depth-buffer values -> distance along the optical axis.

    z = far * near / (far - (far - near) * d)   (d = 0 at the near plane, 1 at the far plane)

    Parameters
    ----------
    d : array of float
        Depth-buffer values in [0, 1].
    near, far : float
        Clipping planes, metres.

    Returns
    -------
    array of float
        z, metres, shaped like ``d``.
    """
    return far * near / (far - (far - near) * np.asarray(d, dtype=np.float64))


def look_at(eye, target) -> np.ndarray:
    """The optical frame at ``eye`` looking at ``target``.

    Image up is towards base +z; when looking (nearly) straight down or up, towards base +x.

    Parameters
    ----------
    eye, target : (3,) float
        Base frame, metres.

    Returns
    -------
    (4, 4) float
        The optical frame's pose in the base frame.
    """
    eye, target = np.asarray(eye, dtype=float), np.asarray(target, dtype=float)
    z = target - eye
    dist = np.linalg.norm(z)
    require(dist > 1e-3, "the camera eye and target coincide", "give --camera-pose eye_x,eye_y,eye_z,target_x,target_y,target_z")
    z /= dist
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.999 else np.array([1.0, 0.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return pose_matrix(np.column_stack([x, y, z]), eye)


def camera_pose(pose, target_default: np.ndarray) -> np.ndarray:
    """The optical frame in the base frame from a :class:`SimCameraConfig` ``pose``.

    Parameters
    ----------
    pose : sequence of 6 or 7 float, or None
        See :class:`SimCameraConfig`.
    target_default : (3,) float
        Where a default camera looks, metres.

    Returns
    -------
    (4, 4) float
    """
    fix = "give --camera-pose ex,ey,ez,tx,ty,tz (eye, target; m) or x,y,z,qx,qy,qz,qw (optical frame z forward)"
    if pose is None:
        return look_at(DEFAULT_EYE, target_default)
    v = [float(x) for x in pose]
    require(len(v) in (6, 7), f"--camera-pose needs 6 or 7 numbers, got {len(v)}", fix)
    T = parse_pose(v, "--camera-pose", fix)  # an object pose's checks; 6 numbers are eye and target here
    return look_at(v[:3], v[3:]) if len(v) == 6 else T


# ----------------------------------------------------------------------------- quiet native output
@contextlib.contextmanager
def quiet_native_output():
    """Silence C-level stdout/stderr (PyBullet's banner, the EGL plugin's GL report) for the block.

    PyBullet prints from C straight to file descriptors 1 and 2, which would break ``--json``
    output and the one-line error contract. C's stdio buffer is flushed before the descriptors return.

    Yields
    ------
    None
    """
    try:
        sys.stdout.flush()
        sys.stderr.flush()
        saved = [os.dup(1), os.dup(2)]
    except (OSError, ValueError, AttributeError):  # no real descriptors (embedded); do nothing
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        yield
    finally:
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None).fflush(None)
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, devnull):
            os.close(fd)


# ----------------------------------------------------------------------------- the camera
@dataclass
class Frame:
    """One rendered frame: rgb (h, w, 3) float in [0, 1], depth (h, w) metres (inf on background),
    seg (h, w) int body id (-1 on background), render_ms."""

    rgb: np.ndarray
    depth: np.ndarray
    seg: np.ndarray
    render_ms: float


class SimCamera:
    """A camera in its own PyBullet DIRECT client, looking at a :class:`TexturedObject`.

    The camera re-renders the object's texture whenever it changed (``obj.version``), so after
    :meth:`TexturedObject.clean` the next :meth:`capture` sees less marking.
    ``client`` is the PyBullet client id (other bodies may be added to it, e.g. in tests).
    """

    def __init__(self, cfg: SimCameraConfig | None = None, obj: TexturedObject | None = None):
        cfg = cfg or SimCameraConfig()
        cfg.validate()
        self.cfg = cfg
        self.obj = obj
        if obj is not None:  # look at the centre of the object's bounding box
            target = obj.pose[:3, 3] + obj.pose[:3, :3] @ (0.5 * (obj.vertices.min(axis=0) + obj.vertices.max(axis=0)))
        else:
            target = np.array([0.5, 0.0, 0.0])
        self.T_base_cam = camera_pose(cfg.pose, target)
        self.K = intrinsics(cfg.width, cfg.height, cfg.fov_deg)
        self._proj = projection_matrix(cfg.width, cfg.height, cfg.fov_deg, cfg.near, cfg.far)
        self._view = view_matrix(self.T_base_cam)
        self._rng = np.random.default_rng(cfg.seed)
        self._assets = tempfile.TemporaryDirectory(prefix="tergodic-sim-")
        self._body: int | None = None
        self._loaded_version = -1
        self.client = -1
        try:
            with quiet_native_output():
                import pybullet as p

                self._p = p
                self.client = p.connect(p.DIRECT)
                require(self.client >= 0, "PyBullet could not start a DIRECT client", "check the pybullet installation")
                self.renderer = self._pick_renderer(cfg.renderer)
        except BaseException:
            self.close()
            raise
        self.last_timing: dict[str, float] = {}
        self.last_frame: Frame | None = None

    def _pick_renderer(self, wanted: str) -> str:
        if wanted in ("auto", "egl"):
            import importlib.util

            spec = importlib.util.find_spec("eglRenderer")  # shipped with the pybullet wheel
            plugin = self._p.loadPlugin(spec.origin, "_eglRendererPlugin", physicsClientId=self.client) if spec and spec.origin else -1
            if plugin >= 0:
                return "egl"
            require(wanted != "egl", "the EGL renderer plugin did not load (no EGL/GPU driver?)", "use --renderer tiny")
        return "tiny"

    def _sync_object(self) -> float:
        """Load the object, or give it its new texture when it changed; returns the milliseconds it took."""
        if self.obj is None or self.obj.version == self._loaded_version:
            return 0.0
        t0 = time.perf_counter()
        with quiet_native_output():
            if self._body is None:
                self._body = self.obj.create_body(self.client, self._assets.name)
            else:
                self.obj.update_texture(self.client, self._body, self._assets.name)
        self._loaded_version = self.obj.version
        return 1e3 * (time.perf_counter() - t0)

    def capture(self) -> tuple[np.ndarray, np.ndarray]:
        """Render the current scene (reloading the object's texture if it changed), then
        back-project every object pixel, with the configured noise.

        Returns
        -------
        points : (n, 3) float
            Base frame, metres.
        colors : (n, 3) float
            In [0, 1].
        """
        texture_ms = self._sync_object()
        cfg, p = self.cfg, self._p
        flag = p.ER_BULLET_HARDWARE_OPENGL if self.renderer == "egl" else p.ER_TINY_RENDERER
        t0 = time.perf_counter()
        with quiet_native_output():
            _, _, rgba, depth, seg = p.getCameraImage(
                cfg.width, cfg.height, viewMatrix=self._view.T.ravel().tolist(),
                projectionMatrix=self._proj.T.ravel().tolist(), renderer=flag,
                physicsClientId=self.client)
        t1 = time.perf_counter()
        rgb = np.asarray(rgba, dtype=np.float64).reshape(cfg.height, cfg.width, 4)[..., :3] / 255.0
        d = np.asarray(depth, dtype=np.float64).reshape(cfg.height, cfg.width)
        seg = np.asarray(seg).reshape(cfg.height, cfg.width).astype(np.int64)
        z = linearize_depth(d, cfg.near, cfg.far)
        z[(seg < 0) | (d >= 1.0)] = np.inf
        self.last_frame = Frame(rgb, z, seg, 1e3 * (t1 - t0))
        rows, cols = np.nonzero(np.isfinite(z))
        z, colors = z[rows, cols], rgb[rows, cols]
        if cfg.depth_noise > 0:
            z = z + self._rng.normal(0.0, cfg.depth_noise, z.shape)
        if cfg.color_noise > 0:
            colors = np.clip(colors + self._rng.normal(0.0, cfg.color_noise, colors.shape), 0.0, 1.0)
        fx, fy, cx, cy = self.K
        o_u, o_v = PIXEL_SAMPLE[self.renderer]  # where a pixel is sampled: shifted principal point
        intr = Intrinsics(cfg.width, cfg.height, fx, fy, cx - o_u, cy - o_v)
        points = deproject(z, intr, self.T_base_cam, rows, cols)
        self.last_timing = {"texture_ms": texture_ms, "render_ms": 1e3 * (t1 - t0),
                            "back_project_ms": 1e3 * (time.perf_counter() - t1)}
        return points, colors

    def describe(self) -> dict:
        """The camera model for the capture sidecar.

        Returns
        -------
        dict
            Intrinsics (pixels), extrinsics (the optical frame in the base frame) and renderer.
        """
        fx, fy, cx, cy = self.K
        return {"renderer": self.renderer, "width": self.cfg.width, "height": self.cfg.height, "fov_deg": self.cfg.fov_deg,
                "near": self.cfg.near, "far": self.cfg.far, "fx": fx, "fy": fy, "cx": cx, "cy": cy,
                "pixel_sample": list(PIXEL_SAMPLE[self.renderer]),
                "T_base_camera": self.T_base_cam.tolist(),
                "pose_xyz_qxyzw": [*self.T_base_cam[:3, 3].tolist(), *matrix_to_quat(self.T_base_cam[:3, :3]).tolist()],
                "frame": "optical (x right, y down, z forward)"}

    def close(self) -> None:
        """Disconnect the client and delete the temporary assets (idempotent)."""
        if self.client >= 0:
            with quiet_native_output():
                self._p.disconnect(physicsClientId=self.client)
            self.client = -1
        self._assets.cleanup()

    def __enter__(self) -> "SimCamera":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ----------------------------------------------------------------------------- capture entry point
def capture_sim(cfg: SimCaptureConfig | None = None, camera: SimCamera | None = None,
                allow_empty_target: bool = False) -> Capture:
    """Render the textured object, back-project, then run the file-capture filters and segmentation.

    Parameters
    ----------
    cfg : SimCaptureConfig, optional
        The scene, camera and pipeline settings (defaults: bowl with an X, default camera).
    camera : SimCamera, optional
        An open camera to reuse (its object, possibly cleaned, is captured; ``cfg.object`` and
        ``cfg.camera`` are then only recorded). Without it a camera is built from ``cfg`` and closed.
    allow_empty_target : bool
        A cloud with no target-coloured point gets p = 0 everywhere instead of the file
        pipeline's "no points match" error (re-captures of a cleaned object).

    Returns
    -------
    Capture
        In the robot base frame; ``meta["sim"]`` holds the object and camera settings, the true
        ``marking_remaining`` and timings.
    """
    from tergodic_cli.capture import CaptureConfig, capture_cloud

    cfg = cfg or SimCaptureConfig()
    pipe = cfg.pipeline or CaptureConfig(source="sim")
    own = camera is None
    if own:
        camera = SimCamera(cfg.camera, TexturedObject(cfg.object))
    try:
        t0 = time.perf_counter()
        points, colors = camera.capture()
        timing = dict(camera.last_timing)
        require(len(points) > 0, "the simulated camera sees nothing of the object",
                "point it at the object with --camera-pose eye_x,eye_y,eye_z,target_x,target_y,target_z")
        t1 = time.perf_counter()
        # A cleaned object has no marking left: keep the cloud with p = 0 instead of refusing it.
        pipe = replace(pipe, source="sim", allow_empty_target=allow_empty_target)
        cap = capture_cloud(pipe, raw=(points, colors))
        timing["pipeline_ms"] = 1e3 * (time.perf_counter() - t1)
        timing["total_ms"] = 1e3 * (time.perf_counter() - t0)
        obj = camera.obj
        obj_cfg = obj.cfg if obj is not None else cfg.object
        cap.meta["frame"] = "robot_base"
        cap.frame = camera.last_frame  # type: ignore[attr-defined]  # the rendered image, not saved by save_capture
        cap.meta["provenance"].update(object=obj_cfg.object, marking=obj_cfg.marking, renderer=camera.renderer)
        cap.meta["sim"] = {
            "object": obj_cfg.to_dict(),
            "object_pose": obj.pose.tolist() if obj is not None else None,
            "camera": {**camera.cfg.to_dict(), **camera.describe()},
            "marking_remaining": obj.marking_remaining() if obj is not None else None,
            "texture_version": obj.version if obj is not None else None,
            "timing_ms": timing,
        }
        return cap
    finally:
        if own:
            camera.close()


def target_on_points(points: np.ndarray, capture: Capture, max_distance: float | None = None) -> np.ndarray:
    """Transfer a capture's target p onto other points (m, 3), e.g. a basis built from an earlier capture.

    Each point takes the p of its nearest capture point; points farther than ``max_distance``
    get 0.

    Parameters
    ----------
    points : (m, 3) float
        Metres, the capture's frame (robot base for sim).
    capture : Capture
    max_distance : float, optional
        Metres; default 3 x the capture's spacing h.

    Returns
    -------
    (m,) float
        p in [0, 1].
    """
    from scipy.spatial import cKDTree

    h = float(capture.meta.get("spacing_h_m", 0.003))
    limit = 3.0 * h if max_distance is None else float(max_distance)
    dist, idx = cKDTree(capture.points).query(np.asarray(points, dtype=float), distance_upper_bound=limit)
    out = np.zeros(len(points))
    hit = np.isfinite(dist)
    out[hit] = capture.target[idx[hit]]
    return out
