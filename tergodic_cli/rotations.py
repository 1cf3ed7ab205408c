"""Rotation conversions shared by every stage (quaternions in pybullet's (x, y, z, w) order)."""

from __future__ import annotations

import math

import numpy as np


def quat_to_matrix(q) -> np.ndarray:
    """Rotation matrix (3, 3) of the unit quaternion ``q`` = (x, y, z, w) (pybullet order)."""
    x, y, z, w = (float(c) for c in q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of the rotation matrix ``R`` (3, 3), w >= 0."""
    R = np.asarray(R, dtype=float)
    tr = float(np.trace(R))
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = np.array([(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s])
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 1e-300))
        q = np.zeros(4)
        q[i] = 0.25 * s
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
        q[3] = (R[k, j] - R[j, k]) / s
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def quat_from_axis(axis: int, v) -> tuple[float, float, float, float]:
    """Shortest-arc quaternion (x, y, z, w) turning the unit ``axis`` (0: +x, 2: +z) onto ``v`` (3,).

    A zero ``v`` gives the identity; ``v`` opposite the axis a half turn (about z for +x, about x for +z).
    """
    x, y, z = (float(c) for c in v)
    n = math.sqrt(x * x + y * y + z * z)
    q = (0.0, -z, y, n + x) if axis == 0 else (-y, x, 0.0, n + z)  # [axis × v, |v| + axis·v]
    qn = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if qn < 1e-12 * max(n, 1e-300):
        if n == 0.0:
            return 0.0, 0.0, 0.0, 1.0
        return (0.0, 0.0, 1.0, 0.0) if axis == 0 else (1.0, 0.0, 0.0, 0.0)
    return q[0] / qn, q[1] / qn, q[2] / qn, q[3] / qn
