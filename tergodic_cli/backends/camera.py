"""The :class:`Camera` protocol, RGB-D frames, and back-projection into a coloured cloud.

A camera backend connects, is read, disconnects. ``read()`` returns the coloured cloud
(points (n, 3) in metres, in the robot base frame when the camera's pose is known, colours
(n, 3) in [0, 1]); ``read_frame()`` returns the aligned RGB-D image with its intrinsics, for
tools that want the pixels; a capture runs the same filters and segmentation as every other
capture source (:func:`~tergodic_cli.backends.realsense.capture.capture_realsense`).

Back-projection (pixel (u, v) = (column, row), pixel centres at integer coordinates, the
convention of librealsense's ``rs2_deproject_pixel_to_point``):

    x = (u - cx) / fx,  y = (v - cy) / fy                      (normalised image coordinates)
    "brown_conrady": undo x_d = x f(r²) + δ(x) with f = 1 + k1 r² + k2 r⁴ + k3 r⁶ and the tangential
        term δ_x = 2 p1 x y + p2 (r² + 2x²), δ_y = 2 p2 x y + p1 (r² + 2y²), by fixed-point iteration
        x <- (x_d - δ(x)) / f(r²), 10 rounds from x = x_d;
    "inverse_brown_conrady": the same iteration with δ evaluated at x f(r²) instead of x
        (librealsense >= 2.50 treats both models this way; checked against its
        rs2_deproject_pixel_to_point to 1e-8, tests/test_hardware_realsense.py)
    P_cam = z (x', y', 1)  (optical frame: x right, y down, z forward), P_base = R P_cam + t

with coefficients (k1, k2, p1, p2, k3) in librealsense's order.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from tergodic_cli.config import Config
from tergodic_cli.errors import require

DISTORTIONS = ("none", "inverse_brown_conrady", "brown_conrady")


@dataclass
class Intrinsics(Config):
    """Pinhole intrinsics in pixels, with a distortion model and its 5 coefficients (k1, k2, p1, p2, k3)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    model: str = "none"
    coeffs: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass
class RGBDFrame:
    """An aligned RGB-D image.

    depth : (h, w) metres along the optical axis, 0 where the sensor has no value.
    rgb : (h, w, 3) in [0, 1]. intrinsics : of the (common) image.
    T_base_cam : (4, 4) pose of the optical frame in the robot base frame (identity = camera frame).
    t : capture time, s (device clock).
    """

    depth: np.ndarray
    rgb: np.ndarray
    intrinsics: Intrinsics
    T_base_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    t: float = 0.0


@runtime_checkable
class Camera(Protocol):
    """An RGB-D camera that yields coloured clouds."""

    def connect(self) -> None:
        """Open the device and start streaming (idempotent)."""

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """(points (n, 3) m, colours (n, 3) in [0, 1]) of the valid pixels, in the frame of ``T_base_cam``."""

    def read_frame(self) -> RGBDFrame:
        """The next aligned RGB-D frame with its intrinsics."""

    def disconnect(self) -> None:
        """Stop streaming and release the device."""


def deproject(depth: np.ndarray, intr: Intrinsics, T_base_cam: np.ndarray | None = None,
              rows: np.ndarray | None = None, cols: np.ndarray | None = None) -> np.ndarray:
    """Pixels with depth (metres) -> points (n, 3), base frame (see the module docstring).

    depth : (h, w) image (then every pixel, row-major) or (n,) depths of the pixels ``rows``, ``cols``.
    The simulated camera's pinhole (no distortion) is the same, its pixel sampling offset in cx, cy.
    """
    require(intr.model in DISTORTIONS,
            f"the camera reports the distortion model '{intr.model}', which tergodic cannot undo",
            f"stream a profile with one of {', '.join(DISTORTIONS)} (the colour stream of D400 cameras)")
    z = np.asarray(depth, dtype=np.float64)
    if rows is None or cols is None:
        rows, cols = np.indices(z.shape)
        rows, cols, z = rows.ravel(), cols.ravel(), z.ravel()
    u = np.asarray(cols, dtype=np.float64) - intr.cx
    v = np.asarray(rows, dtype=np.float64) - intr.cy
    k1, k2, p1, p2, k3 = (float(c) for c in (tuple(intr.coeffs) + (0.0,) * 5)[:5])
    if intr.model == "none" or not any((k1, k2, p1, p2, k3)):
        cam = np.column_stack([u * z / intr.fx, v * z / intr.fy, z])
    else:  # undo the distortion by fixed-point iteration on the normalised coordinates
        x, y = u / intr.fx, v / intr.fy
        inverse = intr.model == "inverse_brown_conrady"
        xu, yu = x.copy(), y.copy()
        for _ in range(10):
            r2 = xu * xu + yu * yu
            f = 1.0 + ((k3 * r2 + k2) * r2 + k1) * r2
            tx, ty = (xu * f, yu * f) if inverse else (xu, yu)
            dx = 2 * p1 * tx * ty + p2 * (r2 + 2 * tx * tx)
            dy = 2 * p2 * tx * ty + p1 * (r2 + 2 * ty * ty)
            xu, yu = (x - dx) / f, (y - dy) / f
        cam = np.column_stack([xu * z, yu * z, z])
    if T_base_cam is None:
        return cam
    T = np.asarray(T_base_cam, dtype=float)
    return cam @ T[:3, :3].T + T[:3, 3]


def frame_to_cloud(frame: RGBDFrame, depth_min: float = 0.0, depth_max: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """The valid pixels of an RGB-D frame (depth_min < z <= depth_max, finite) as (points, colours)."""
    z = np.asarray(frame.depth, dtype=np.float64)
    rgb = np.asarray(frame.rgb, dtype=np.float64)
    require(z.ndim == 2 and rgb.shape == z.shape + (3,),
            f"depth {z.shape} and colour {rgb.shape} images are not aligned", "align depth to colour before back-projection")
    ok = np.isfinite(z) & (z > max(depth_min, 0.0)) & (z <= depth_max)
    rows, cols = np.nonzero(ok)
    pts = deproject(z[rows, cols], frame.intrinsics, frame.T_base_cam, rows, cols)
    return pts, rgb[rows, cols]

