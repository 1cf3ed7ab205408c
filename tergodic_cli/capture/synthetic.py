"""Procedurally generated objects with a coloured marking (the project's own test data).

Every object is a single sheet, as a depth camera sees it, sized like kitchenware,
in metres, resting on z = 0. The marking is drawn in a 2-D chart of the surface
(``u, v`` in metres), so its width is the same on every object.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tergodic_cli.errors import TergodicError

OBJECTS = ("bowl", "plate", "mug", "sphere")
MARKINGS = ("X", "ring", "dots")

SURFACE_RGB = np.array([0.88, 0.86, 0.82])  # glazed ceramic
MARKING_RGB = np.array([0.80, 0.08, 0.08])  # red marker
STROKE_WIDTH = 0.012  # metres

# Shapes (metres): bowl = inner spherical cap; plate = flat well + quadratic rim; mug = cylinder wall.
BOWL_RADIUS, BOWL_MAX_POLAR_DEG = 0.08, 70.0
PLATE_FLAT, PLATE_RIM, PLATE_LIFT = 0.08, 0.04, 0.015
MUG_RADIUS, MUG_HEIGHT = 0.04, 0.10
SPHERE_RADIUS = 0.06


@dataclass
class SyntheticCloud:
    """A generated cloud: points (n, 3) m, colours (n, 3) in [0, 1], ground-truth marking mask (n,)."""

    points: np.ndarray
    colors: np.ndarray
    mask: np.ndarray
    size: float  # characteristic radius of the object, metres


def generate_synthetic(kind: str, marking: str = "X", seed: int = 0, spacing: float = 0.0012) -> SyntheticCloud:
    """Sample ``kind`` at about one point per ``spacing``² of area and paint ``marking`` on it."""
    if kind not in OBJECTS:
        raise TergodicError(f"unknown synthetic object '{kind}'", f"use one of {', '.join(OBJECTS)}")
    if marking not in MARKINGS:
        raise TergodicError(f"unknown marking '{marking}'", f"use one of {', '.join(MARKINGS)}")
    rng = np.random.default_rng(seed)
    points, chart, visible, size = _SHAPES[kind](rng, spacing)
    mask = _MARKS[marking](chart, size, np.random.default_rng(seed + 1)) & visible
    colors = np.where(mask[:, None], MARKING_RGB, SURFACE_RGB)
    colors = np.clip(colors + rng.normal(0.0, 0.025, colors.shape), 0.0, 1.0)
    return SyntheticCloud(points, colors, mask, size)


def _count(area: float, spacing: float) -> int:
    return int(area / spacing**2)


def _bowl(rng, spacing):
    # Inner surface of a spherical cap: steep, nearly vertical walls near the rim.
    radius, max_polar = BOWL_RADIUS, np.deg2rad(BOWL_MAX_POLAR_DEG)
    n = _count(2 * np.pi * radius**2 * (1 - np.cos(max_polar)), spacing)
    cos_phi = rng.uniform(np.cos(max_polar), 1.0, n)
    sin_phi = np.sqrt(1 - cos_phi**2)
    theta = rng.uniform(0, 2 * np.pi, n)
    pts = np.column_stack([radius * sin_phi * np.cos(theta), radius * sin_phi * np.sin(theta), radius * (1 - cos_phi)])
    return pts, pts[:, :2], np.ones(n, bool), radius * np.sin(max_polar)


def _plate(rng, spacing):
    # Flat well of radius 8 cm and a 4 cm rim rising 1.5 cm.
    flat, rim, lift = PLATE_FLAT, PLATE_RIM, PLATE_LIFT
    outer = flat + rim
    n = _count(np.pi * outer**2, spacing)
    r = outer * np.sqrt(rng.uniform(0, 1, n))
    theta = rng.uniform(0, 2 * np.pi, n)
    z = np.where(r > flat, lift * ((r - flat) / rim) ** 2, 0.0)
    pts = np.column_stack([r * np.cos(theta), r * np.sin(theta), z])
    return pts, pts[:, :2], np.ones(n, bool), outer


def _mug(rng, spacing):
    # Outer wall of a cylinder: vertical everywhere, closed around.
    radius, height = MUG_RADIUS, MUG_HEIGHT
    n = _count(2 * np.pi * radius * height, spacing)
    theta = rng.uniform(-np.pi, np.pi, n)
    z = rng.uniform(0, height, n)
    pts = np.column_stack([radius * np.cos(theta), radius * np.sin(theta), z])
    chart = np.column_stack([radius * theta, z - height / 2])
    return pts, chart, np.ones(n, bool), height / 2


def _sphere(rng, spacing):
    radius = SPHERE_RADIUS
    n = _count(4 * np.pi * radius**2, spacing)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    pts = radius * v + np.array([0, 0, radius])
    return pts, pts[:, :2], v[:, 2] > 0, radius  # marking only on the upper half


def _mark_x(chart, size, rng):
    u, v = chart[:, 0], chart[:, 1]
    arm = 0.75 * size
    on_a = np.abs(u - v) / np.sqrt(2) < STROKE_WIDTH / 2
    on_b = np.abs(u + v) / np.sqrt(2) < STROKE_WIDTH / 2
    return (on_a | on_b) & (np.hypot(u, v) < arm)


def _mark_ring(chart, size, rng):
    return np.abs(np.hypot(chart[:, 0], chart[:, 1]) - 0.5 * size) < STROKE_WIDTH / 2


def _mark_dots(chart, size, rng):
    # Five dots of radius 10 mm, centres at least 2.5 radii apart (best of a bounded number of draws).
    radius, reach = 0.010, 0.65 * size
    centres: list[np.ndarray] = []
    for _ in range(10_000):
        if len(centres) == 5:
            break
        c = rng.uniform(-reach, reach, 2)
        if np.hypot(*c) < reach and all(np.hypot(*(c - d)) > 2.5 * radius for d in centres):
            centres.append(c)
    d = np.min([np.hypot(chart[:, 0] - c[0], chart[:, 1] - c[1]) for c in centres], axis=0)
    return d < radius


_SHAPES = {"bowl": _bowl, "plate": _plate, "mug": _mug, "sphere": _sphere}
_MARKS = {"X": _mark_x, "ring": _mark_ring, "dots": _mark_dots}
