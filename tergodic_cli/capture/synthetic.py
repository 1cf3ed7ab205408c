"""Procedurally generated objects with a coloured marking (the project's own test data).

Every object is sized like kitchenware, in metres, resting on z = 0, and sampled as a depth
camera sees it: one sheet, except where a real object has two close together (the thin mug's
inner and outer walls). The marking is drawn in a 2-D chart of the surface (``u, v`` in
metres), so its width is the same on every object.

Objects: ``bowl``, ``plate``, ``mug``, ``sphere``, and the geometry real captures have:
``holed-plate`` (a 3 cm hole beside the marking), ``thin-mug`` (inner and outer walls 4 mm
apart, rim and inside floor), ``torus`` (a closed surface with a hole), ``box`` (sharp edges,
the marking across one) and ``partial`` (a blob seen from one side: its far side is missing).
``noise`` adds seeded Gaussian noise along the surface normal to any of them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from tergodic_cli.errors import TergodicError, require

OBJECTS = ("bowl", "plate", "mug", "sphere", "holed-plate", "thin-mug", "torus", "box", "partial")
MARKINGS = ("X", "ring", "dots", "patches")

SURFACE_RGB = np.array([0.88, 0.86, 0.82])  # glazed ceramic
MARKING_RGB = np.array([0.80, 0.08, 0.08])  # red marker
STROKE_WIDTH = 0.012  # metres
#: Largest accepted ``noise`` σ, metres: anything above is almost surely millimetres typed as metres.
MAX_NOISE = 0.01

# Shapes (metres): bowl = inner spherical cap; plate = flat well + quadratic rim; mug = cylinder wall.
BOWL_RADIUS, BOWL_MAX_POLAR_DEG = 0.08, 70.0
PLATE_FLAT, PLATE_RIM, PLATE_LIFT = 0.08, 0.04, 0.015
MUG_RADIUS, MUG_HEIGHT = 0.04, 0.10
SPHERE_RADIUS = 0.06
# holed-plate: the plate with a hole through its flat well, on one arm of the X 2 cm from its crossing.
HOLE_CENTRE, HOLE_RADIUS = (0.025, 0.025), 0.015
# thin-mug: the mug's outer wall, an inner wall WALL inside it, the rim between them, and the
# inside floor at FLOOR (the base's thickness).
MUG_WALL, MUG_FLOOR = 0.004, 0.006
# torus: major and minor radii; it rests on z = 0 (centre at z = TORUS_MINOR).
TORUS_MAJOR, TORUS_MINOR = 0.06, 0.02
# box: x, y, z edge lengths; the five faces a camera above sees (not the bottom).
BOX_SIZE = (0.10, 0.08, 0.06)
# partial: an ellipsoid blob (semi-axes) seen by an orthographic camera looking along -PARTIAL_VIEW.
PARTIAL_AXES = (0.08, 0.06, 0.05)
PARTIAL_VIEW = (1.0, 0.0, 0.5)  # towards the camera: from +x, 27 deg above the table
PATCH_RADIUS = 0.0125  # patches marking: two discs 2.5 cm across


@dataclass
class SyntheticCloud:
    """A generated cloud.

    points (n, 3) m, colors (n, 3) in [0, 1], mask (n,) bool: the ground-truth marking,
    size: characteristic radius of the object (m), normals (n, 3): unit normals of the
    noise-free surface, towards the side a camera sees (outwards; into the bowl).
    """

    points: np.ndarray
    colors: np.ndarray
    mask: np.ndarray
    size: float  # characteristic radius of the object, metres
    normals: np.ndarray | None = None


class TestObject(NamedTuple):
    """One synthetic cloud of the coverage tests: ``generate_synthetic(object, marking, noise=noise)``."""

    object: str
    marking: str
    noise: float  # metres


TestObject.__test__ = False  # type: ignore[attr-defined]  # a data class, not a pytest test

#: The clouds of issue 13 item 4 (the geometry real captures have), for tests and benchmarks.
COVERAGE_OBJECTS: tuple[TestObject, ...] = (
    TestObject("bowl", "X", 0.0015),  # 1.5 mm Gaussian noise
    TestObject("holed-plate", "X", 0.0),
    TestObject("thin-mug", "X", 0.0),
    TestObject("torus", "patches", 0.0),
    TestObject("box", "X", 0.0),
    TestObject("partial", "X", 0.0),
)


def generate_synthetic(kind: str, marking: str = "X", seed: int = 0, spacing: float = 0.0012,
                       noise: float = 0.0) -> SyntheticCloud:
    """Sample ``kind`` at about one point per ``spacing``² of area and paint ``marking`` on it.

    Parameters
    ----------
    kind : one of :data:`OBJECTS`.
    marking : one of :data:`MARKINGS`.
    seed : seeds the sampling, the colour noise, the dots' placement and the surface noise.
    spacing : metres; the mean distance between samples.
    noise : σ in metres of Gaussian noise along the surface normal (0: none). The samples,
        colours and marking are those of the noise-free cloud with the same seed.

    Returns
    -------
    SyntheticCloud with n points, n ≈ area / spacing².
    """
    require(kind in OBJECTS, f"unknown synthetic object '{kind}'", f"use one of {', '.join(OBJECTS)}")
    require(marking in MARKINGS, f"unknown marking '{marking}'", f"use one of {', '.join(MARKINGS)}")
    noise = check_noise(noise)
    rng = np.random.default_rng(seed)
    sheet = _SHAPES[kind](rng, spacing)
    mask = _MARKS[marking](sheet.chart, sheet.size, np.random.default_rng(seed + 1)) & sheet.visible
    colors = np.where(mask[:, None], MARKING_RGB, SURFACE_RGB)
    colors = np.clip(colors + rng.normal(0.0, 0.025, colors.shape), 0.0, 1.0)
    points = sheet.points
    if noise > 0:  # its own stream, so the noisy cloud is the clean one displaced
        offset = np.random.default_rng([seed, 2]).normal(0.0, noise, len(points))
        points = points + offset[:, None] * sheet.normals
    return SyntheticCloud(points, colors, mask, sheet.size, sheet.normals)


def check_noise(noise: float) -> float:
    """Check a noise level.

    Parameters
    ----------
    noise : float
        σ in metres.

    Returns
    -------
    float
        σ; a one-line :class:`TergodicError` unless 0 ≤ σ < MAX_NOISE.
    """
    try:
        noise = float(noise)
    except (TypeError, ValueError):  # e.g. a string in a sweep grid
        raise TergodicError(f"--noise {noise!r} is not a number", "give σ in metres, e.g. 0.0015") from None
    require(np.isfinite(noise) and noise >= 0, f"--noise {noise} is not a standard deviation",
            "give σ in metres, >= 0, e.g. 0.0015")
    require(noise < MAX_NOISE, f"--noise {noise} m is more than a depth camera's noise",
            "give σ in METRES, e.g. 0.0015 for 1.5 mm")
    return noise


class _Sheet(NamedTuple):
    """A sampled surface: points (n, 3) m, unit normals (n, 3), chart (n, 2) m, visible (n,) bool
    (where the marking may be drawn) and the characteristic radius ``size`` (m)."""

    points: np.ndarray
    normals: np.ndarray
    chart: np.ndarray
    visible: np.ndarray
    size: float


def _count(area: float, spacing: float) -> int:
    return int(area / spacing**2)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _join(*parts: _Sheet, size: float) -> _Sheet:
    return _Sheet(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("points", "normals", "chart", "visible")), size)


def _bowl(rng, spacing):
    # Inner surface of a spherical cap: steep, nearly vertical walls near the rim.
    radius, max_polar = BOWL_RADIUS, np.deg2rad(BOWL_MAX_POLAR_DEG)
    n = _count(2 * np.pi * radius**2 * (1 - np.cos(max_polar)), spacing)
    cos_phi = rng.uniform(np.cos(max_polar), 1.0, n)
    sin_phi = np.sqrt(1 - cos_phi**2)
    theta = rng.uniform(0, 2 * np.pi, n)
    pts = np.column_stack([radius * sin_phi * np.cos(theta), radius * sin_phi * np.sin(theta), radius * (1 - cos_phi)])
    normals = (np.array([0, 0, radius]) - pts) / radius  # towards the sphere's centre: into the bowl
    return _Sheet(pts, normals, pts[:, :2], np.ones(n, bool), radius * np.sin(max_polar))


def _plate_profile(r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Height z(r) and slope dz/dr of the plate: flat well of radius 8 cm, a 4 cm rim rising 1.5 cm."""
    t = np.clip((r - PLATE_FLAT) / PLATE_RIM, 0.0, None)
    return PLATE_LIFT * t**2, 2 * PLATE_LIFT * t / PLATE_RIM


def _plate(rng, spacing):
    outer = PLATE_FLAT + PLATE_RIM
    n = _count(np.pi * outer**2, spacing)
    r = outer * np.sqrt(rng.uniform(0, 1, n))
    theta = rng.uniform(0, 2 * np.pi, n)
    z, slope = _plate_profile(r)
    c, s = np.cos(theta), np.sin(theta)
    pts = np.column_stack([r * c, r * s, z])
    normals = _unit(np.column_stack([-slope * c, -slope * s, np.ones(n)]))
    return _Sheet(pts, normals, pts[:, :2], np.ones(n, bool), outer)


def _holed_plate(rng, spacing):
    # The plate's samples with those over the hole removed: the hole is a true gap in the sheet.
    sheet = _plate(rng, spacing)
    keep = np.hypot(sheet.points[:, 0] - HOLE_CENTRE[0], sheet.points[:, 1] - HOLE_CENTRE[1]) >= HOLE_RADIUS
    return _Sheet(*(a[keep] for a in sheet[:4]), sheet.size)


def _cylinder(rng, spacing, radius, z0, z1, outward, visible):
    n = _count(2 * np.pi * radius * (z1 - z0), spacing)
    theta = rng.uniform(-np.pi, np.pi, n)
    z = rng.uniform(z0, z1, n)
    normals = np.column_stack([np.cos(theta), np.sin(theta), np.zeros(n)]) * (1 if outward else -1)
    pts = np.column_stack([radius * np.cos(theta), radius * np.sin(theta), z])
    chart = np.column_stack([radius * theta, z - MUG_HEIGHT / 2])
    return _Sheet(pts, normals, chart, np.full(n, visible), MUG_HEIGHT / 2)


def _annulus(rng, spacing, r0, r1, z, visible):
    n = _count(np.pi * (r1**2 - r0**2), spacing)
    r = np.sqrt(rng.uniform(r0**2, r1**2, n))
    theta = rng.uniform(-np.pi, np.pi, n)
    pts = np.column_stack([r * np.cos(theta), r * np.sin(theta), np.full(n, z)])
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))
    return _Sheet(pts, normals, pts[:, :2], np.full(n, visible), MUG_HEIGHT / 2)


def _mug(rng, spacing):
    # Outer wall of a cylinder: vertical everywhere, closed around.
    return _cylinder(rng, spacing, MUG_RADIUS, 0.0, MUG_HEIGHT, True, True)


def _thin_mug(rng, spacing):
    # Two sheets 4 mm apart (the hard case for a local surface fit); the marking is on the outside.
    inner = MUG_RADIUS - MUG_WALL
    return _join(_mug(rng, spacing),
                 _cylinder(rng, spacing, inner, MUG_FLOOR, MUG_HEIGHT, False, False),
                 _annulus(rng, spacing, inner, MUG_RADIUS, MUG_HEIGHT, False),
                 _annulus(rng, spacing, 0.0, inner, MUG_FLOOR, False),
                 size=MUG_HEIGHT / 2)


def _sphere(rng, spacing):
    radius = SPHERE_RADIUS
    n = _count(4 * np.pi * radius**2, spacing)
    v = _unit(rng.normal(size=(n, 3)))
    pts = radius * v + np.array([0, 0, radius])
    return _Sheet(pts, v, pts[:, :2], v[:, 2] > 0, radius)  # marking only on the upper half


def _torus(rng, spacing):
    # Uniform in area: the tube angle phi is drawn with density ∝ R + r cos(phi) (rejection).
    big, small = TORUS_MAJOR, TORUS_MINOR
    n = _count(4 * np.pi**2 * big * small, spacing)
    phi = np.empty(0)
    while len(phi) < n:
        draw = rng.uniform(-np.pi, np.pi, n)
        phi = np.concatenate([phi, draw[rng.uniform(0, 1, n) * (big + small) < big + small * np.cos(draw)]])
    phi = phi[:n]
    theta = rng.uniform(-np.pi, np.pi, n)
    normals = np.column_stack([np.cos(phi) * np.cos(theta), np.cos(phi) * np.sin(theta), np.sin(phi)])
    rho = big + small * np.cos(phi)
    pts = np.column_stack([rho * np.cos(theta), rho * np.sin(theta), small + small * np.sin(phi)])
    # Chart: the top view, the marking on the upper half only (as the sphere); the patches'
    # centres (±0.75 size, 0) then fall on the tube's crest, on opposite sides of the hole.
    return _Sheet(pts, normals, pts[:, :2], phi >= 0, big + small)


def _box(rng, spacing):
    # Five faces; the chart is the box unfolded around its top, with its origin on the top's +x
    # edge, so every marking centred on the origin straddles that sharp edge.
    a, b, c = BOX_SIZE
    parts = []
    faces = (("top", 1, a * b), ("x", 1, b * c), ("x", -1, b * c), ("y", 1, a * c), ("y", -1, a * c))
    for face, sign, area in faces:
        n = _count(area, spacing)
        s, t = rng.uniform(-0.5, 0.5, n), rng.uniform(0.0, 1.0, n)  # t: depth below the top, in units of c
        down = c * t
        if face == "top":
            x, y, z, normal = a * s, b * (t - 0.5), np.full(n, c), (0, 0, 1)
            u, v = x - a / 2, y
        elif face == "x":
            x, y, z, normal = np.full(n, sign * a / 2), b * s, c - down, (sign, 0, 0)
            u, v = (down if sign > 0 else -a - down), y
        else:
            x, y, z, normal = a * s, np.full(n, sign * b / 2), c - down, (0, sign, 0)
            u, v = x - a / 2, sign * (b / 2 + down)
        pts = np.column_stack([x, y, z])
        parts.append(_Sheet(pts, np.tile(np.asarray(normal, float), (n, 1)), np.column_stack([u, v]),
                            np.ones(n, bool), b / 2))
    return _join(*parts, size=b / 2)


def _partial(rng, spacing):
    # An ellipsoid blob seen by one camera: samples whose normal faces away from it are the
    # missing side. The X's and the patches' -x ends run into that boundary.
    axes = np.asarray(PARTIAL_AXES)
    a, b, c = axes
    p = 1.6075  # Knud Thomsen's approximation of an ellipsoid's area (within ~1 %)
    area = 4 * np.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)
    n = _count(area, spacing)
    # Uniform in area: a direction on the unit sphere, kept with probability ∝ the area stretch.
    dirs = np.empty((0, 3))
    while len(dirs) < n:
        d = _unit(rng.normal(size=(n, 3)))
        stretch = np.sqrt((b * c * d[:, 0]) ** 2 + (a * c * d[:, 1]) ** 2 + (a * b * d[:, 2]) ** 2)
        dirs = np.concatenate([dirs, d[rng.uniform(0, 1, n) * a * b < stretch]])  # a*b is the largest stretch
    dirs = dirs[:n]
    local = dirs * axes
    normals = _unit(local / axes**2)
    seen = normals @ _unit(np.asarray([PARTIAL_VIEW], float))[0] > 0
    pts = local + np.array([0, 0, c])
    pts, normals, local = pts[seen], normals[seen], local[seen]
    return _Sheet(pts, normals, pts[:, :2], local[:, 2] > 0, a)  # marking on the upper half, as the sphere


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


def _mark_patches(chart, size, rng):
    # Two discs 2.5 cm across at (±0.75 size, 0), the X's arm length: two separate targets.
    u, v = chart[:, 0], chart[:, 1]
    reach = 0.75 * size
    return (np.hypot(u - reach, v) < PATCH_RADIUS) | (np.hypot(u + reach, v) < PATCH_RADIUS)


_SHAPES = {"bowl": _bowl, "plate": _plate, "mug": _mug, "sphere": _sphere, "holed-plate": _holed_plate,
           "thin-mug": _thin_mug, "torus": _torus, "box": _box, "partial": _partial}
_MARKS = {"X": _mark_x, "ring": _mark_ring, "dots": _mark_dots, "patches": _mark_patches}
