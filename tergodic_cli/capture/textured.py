"""Textured objects for the simulated camera, and the cleaning model that fades their marking.

An object is a UV-mapped triangle mesh (metres, object frame) whose texels carry a marking intensity
m in [0, 1], blended from the clean colour towards the ink colour. Built-in objects share the 2-D
chart of :mod:`tergodic_cli.capture.synthetic`, so their markings land where the generator draws
them; a user ``.obj`` keeps its UVs or gets a top-down chart. ``RESERVED_ROWS`` clean rows take the
built-in objects' back faces. Cleaning: m <- m exp(-k F dt) within r_s of a contact pressing with
F > F_min (docs/sim_camera.md).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from tergodic_cli.config import Config
from tergodic_cli.errors import TergodicError, require
from tergodic_cli.rotations import matrix_to_quat, quat_to_matrix

BUILTIN_OBJECTS = ("bowl", "plate", "mug")
PATTERN_MARKINGS = ("X", "ring", "dots", "patches")

# The same surfaces as the synthetic point-cloud generator.
from tergodic_cli.capture.synthetic import (  # noqa: E402
    _MARKS, BOWL_MAX_POLAR_DEG, BOWL_RADIUS, MARKING_RGB, MUG_HEIGHT, MUG_RADIUS, PLATE_FLAT,
    PLATE_LIFT, PLATE_RIM, SURFACE_RGB)

#: Rows of plain clean colour appended below the chart, for the back faces.
RESERVED_ROWS = 8
#: Largest user image accepted as a texture, pixels per side.
MAX_IMAGE_SIDE = 4096
#: An RGB image pixel this close to white (every channel >= it, in [0, 1]) is clean surface.
WHITE_LEVEL = 0.94


@dataclass
class CleaningModel:
    """How a pressing sponge removes the marking.

    rate : k in 1/(N s). The default removes 95% of a spot's marking in 3 s at 5 N
        (exp(-0.2 * 5 * 3) = 0.05); at the default colours the red-marker segmentation stops
        seeing a texel once m < ~0.55, i.e. after ~0.6 s at 5 N.
    force_min : F_min, N. Contacts at or below it do not clean (grazing, noise).
        The default matches the robot's contact threshold at 5 N (20 %).
    radius : r_s, the sponge footprint radius, metres (3-D distance from the contact point);
        the default equals the explorer's agent radius.
    """

    rate: float = 0.2
    force_min: float = 1.0
    radius: float = 0.0075

    def validate(self) -> None:
        require(np.isfinite(self.rate) and self.rate >= 0, f"cleaning rate {self.rate} is not >= 0", "give k in 1/(N s), e.g. 0.2")
        require(np.isfinite(self.force_min) and self.force_min >= 0, f"cleaning force threshold {self.force_min} is not >= 0",
                "give F_min in newtons, e.g. 1.0")
        require(np.isfinite(self.radius) and 0 < self.radius < 0.2, f"sponge footprint radius {self.radius} m is not in (0, 0.2)",
                "give r_s in metres, e.g. 0.0075")


@dataclass
class SimObjectConfig(Config):
    """What the simulated scene holds: an object, its marking and its pose in the robot base frame.

    object : "bowl", "plate", "mug", or a path to a Wavefront .obj (metres unless ``units`` is "mm").
    marking : "X", "ring", "dots", "patches" (drawn in the chart like the synthetic generator) or a path to a
        .png (alpha = marking intensity; without alpha, non-white pixels are marking).
    pose : x,y,z (m) [+ roll,pitch,yaw (deg) | + qx,qy,qz,qw]: the object frame in the robot base frame.
        None: 0.5 m in front of the base, where the robot stage places synthetic objects;
        the mug turned by 180 deg (yaw) so its marking faces the robot and camera.
    texture_size : texels per side of the chart texture (pattern markings).
    mesh_edge : target triangle edge of built-in meshes, metres.
    units : units of a user .obj, "m" or "mm".
    seed : the dots' placement (same draw as ``generate_synthetic(..., seed)``).
    """

    object: str = "bowl"
    marking: str = "X"
    pose: tuple[float, ...] | None = None
    texture_size: int = 512
    mesh_edge: float = 0.003
    units: str = "m"
    seed: int = 0
    cleaning: CleaningModel = field(default_factory=CleaningModel)


# ----------------------------------------------------------------------------- geometry


@dataclass
class ChartMesh:
    """A triangle mesh with a 2-D chart per vertex.

    vertices (n, 3) m, triangles (k, 3) int, chart (n, 2) m (or unit UVs for a user mesh),
    box (2, 2): chart lower/upper corners mapped onto the texture, size: the synthetic
    generator's characteristic radius (sets the marking's extent), two_sided_texture:
    back faces carry the texture too (user meshes, whose winding is unknown).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    chart: np.ndarray
    box: np.ndarray
    size: float
    two_sided_texture: bool = False


def _rings_mesh(radii: np.ndarray, heights: np.ndarray, edge: float) -> tuple[np.ndarray, np.ndarray]:
    """A disk chart triangulated from concentric rings (radius r_i, height z_i; r_0 = 0)."""
    from scipy.spatial import Delaunay

    xy = [np.zeros((1, 2))]
    z = [np.array([heights[0]])]
    for r, h in zip(radii[1:], heights[1:]):
        # Enough points that 3-D edges along the ring are about `edge`; alternate the phase between rings.
        n = max(6, int(np.ceil(2 * np.pi * r / edge)))
        phase = np.pi / n * (len(xy) % 2)
        t = phase + 2 * np.pi * np.arange(n) / n
        xy.append(np.column_stack([r * np.cos(t), r * np.sin(t)]))
        z.append(np.full(n, h))
    xy_all = np.concatenate(xy)
    tri = Delaunay(xy_all).simplices.astype(np.int64)
    return np.column_stack([xy_all, np.concatenate(z)]), tri


def _bowl_mesh(edge: float) -> ChartMesh:
    R, phi_max = BOWL_RADIUS, np.deg2rad(BOWL_MAX_POLAR_DEG)
    phi = np.linspace(0.0, phi_max, max(2, int(np.ceil(R * phi_max / edge))) + 1)  # even 3-D spacing up the wall
    verts, tri = _rings_mesh(R * np.sin(phi), R * (1 - np.cos(phi)), edge)
    size = R * np.sin(phi_max)
    return ChartMesh(verts, tri, verts[:, :2].copy(), np.array([[-size, -size], [size, size]]), size)


def _plate_mesh(edge: float) -> ChartMesh:
    flat, rim, lift = PLATE_FLAT, PLATE_RIM, PLATE_LIFT
    r_flat = np.linspace(0.0, flat, max(2, int(np.ceil(flat / edge))) + 1)  # a ring exactly on the crease
    r_rim = np.linspace(flat, flat + rim, max(2, int(np.ceil(rim / edge))) + 1)[1:]
    radii = np.concatenate([r_flat, r_rim])
    heights = np.where(radii > flat, lift * ((radii - flat) / rim) ** 2, 0.0)
    verts, tri = _rings_mesh(radii, heights, edge)
    outer = flat + rim
    return ChartMesh(verts, tri, verts[:, :2].copy(), np.array([[-outer, -outer], [outer, outer]]), outer)


def _mug_mesh(edge: float) -> ChartMesh:
    r, h = MUG_RADIUS, MUG_HEIGHT
    n_t = max(12, int(np.ceil(2 * np.pi * r / edge)))
    n_z = max(2, int(np.ceil(h / edge)))
    theta = np.linspace(-np.pi, np.pi, n_t + 1)  # the seam vertices are duplicated (u = -pi r and +pi r)
    z = np.linspace(0.0, h, n_z + 1)
    T, Z = np.meshgrid(theta, z)  # (n_z+1, n_t+1)
    verts = np.column_stack([r * np.cos(T.ravel()), r * np.sin(T.ravel()), Z.ravel()])
    chart = np.column_stack([r * T.ravel(), Z.ravel() - h / 2])
    i, j = np.meshgrid(np.arange(n_z), np.arange(n_t), indexing="ij")
    a = (i * (n_t + 1) + j).ravel()
    b, c, d = a + 1, a + n_t + 1, a + n_t + 2
    tri = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
    box = np.array([[-np.pi * r, -h / 2], [np.pi * r, h / 2]])
    return ChartMesh(verts, tri, chart, box, h / 2)


_BUILDERS = {"bowl": _bowl_mesh, "plate": _plate_mesh, "mug": _mug_mesh}


def _front_direction(kind: str, points: np.ndarray) -> np.ndarray:
    """(n, 3) direction the marked side faces: into the bowl, up from the plate, out of the mug."""
    if kind == "bowl":
        return np.array([0.0, 0.0, BOWL_RADIUS]) - points
    if kind == "plate":
        return np.tile([0.0, 0.0, 1.0], (len(points), 1))
    return np.column_stack([points[:, 0], points[:, 1], np.zeros(len(points))])


def builtin_mesh(kind: str, edge: float = 0.003) -> ChartMesh:
    """The built-in object ``kind`` as a chart mesh whose front faces show the marked side."""
    require(kind in _BUILDERS, f"unknown sim object '{kind}'", f"use one of {', '.join(BUILTIN_OBJECTS)} or a path to a .obj file")
    mesh = _BUILDERS[kind](edge)
    # flip the triangles whose counter-clockwise normal disagrees with the front direction
    v = mesh.vertices[mesh.triangles]
    flip = np.einsum("ij,ij->i", np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), _front_direction(kind, v.mean(axis=1))) < 0
    mesh.triangles[flip] = mesh.triangles[flip][:, [0, 2, 1]]
    return mesh


def read_obj(path: str | Path, units: str = "m") -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Read a Wavefront .obj: vertices (n, 3) metres, triangles (k, 3), UVs (n, 2) or None.

    Polygons are fan-triangulated. A vertex used with different texture coordinates is split,
    so every output vertex has one UV.
    """
    from tergodic_cli.capture.mesh import parse_obj

    path = Path(path)
    require(path.is_file(), f"object file {path} does not exist", "check the path given to --object")
    require(path.suffix.lower() == ".obj", f"object file {path} is not a .obj", "give a Wavefront .obj mesh, or bowl, plate or mug")
    vertices, triangles, uvs, _ = parse_obj(path, "--object")
    require(units in ("m", "mm"), f"unknown mesh units '{units}'", "use m or mm")
    if units == "mm":
        vertices = vertices * 1e-3
    require(bool(np.all(np.isfinite(vertices))), f"{path} has non-finite vertex coordinates", "repair the mesh")
    extent = float(np.ptp(vertices, axis=0).max())
    require(0.01 <= extent <= 2.0, f"{path} spans {extent:.3g} m, not a tabletop object in metres",
            "scale the mesh to metres, or pass --units mm for a mesh in millimetres")
    return vertices, triangles.astype(np.int64), uvs


def _file_mesh(path: str, units: str, use_uvs: bool) -> ChartMesh:
    vertices, triangles, uvs = read_obj(path, units)
    if use_uvs and uvs is not None:
        require(bool(np.all((uvs > -1e-6) & (uvs < 1 + 1e-6))), f"{path} has texture coordinates outside [0, 1]",
                "re-export it with UVs in the unit square (no tiling), or use a pattern marking (X, ring, dots)")
        uvs = np.clip(uvs, 0.0, 1.0)
        return ChartMesh(vertices, triangles, uvs, np.array([[0.0, 0.0], [1.0, 1.0]]), 0.0, two_sided_texture=True)
    lo, hi = vertices[:, :2].min(axis=0), vertices[:, :2].max(axis=0)
    centre, half = 0.5 * (lo + hi), 0.5 * float((hi - lo).max())
    chart = vertices[:, :2] - centre
    return ChartMesh(vertices, triangles, chart, np.array([[-half, -half], [half, half]]), half, two_sided_texture=True)


# ----------------------------------------------------------------------------- texture space


def chart_to_uv(chart: np.ndarray, box: np.ndarray, height: int) -> np.ndarray:
    """Chart coordinates (n, 2) -> OBJ texture coordinates (n, 2) for a texture of ``height`` chart rows.

    u spans the chart box left to right; v spans it bottom to top inside the top ``height`` rows
    (OBJ convention: v = 0 is the image's bottom row; the bottom RESERVED_ROWS rows stay clean).
    """
    unit = (chart - box[0]) / (box[1] - box[0])
    total = height + RESERVED_ROWS
    return np.column_stack([unit[:, 0], (RESERVED_ROWS + unit[:, 1] * height) / total])


def rasterize_uv(vertices: np.ndarray, triangles: np.ndarray, uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """3-D surface point under every texel centre: (height, width, 3) metres, NaN where no triangle covers it.

    ``uv`` (n, 2) are OBJ texture coordinates of an image ``width`` x ``height`` (v = 0 at the bottom).
    Each triangle's texels come from barycentric interpolation of its corners.
    """
    px = np.column_stack([uv[:, 0] * width - 0.5, (1.0 - uv[:, 1]) * height - 0.5])  # texel (col, row) coords
    tri_px = px[triangles]  # (k, 3, 2)
    lo = np.maximum(np.ceil(tri_px.min(axis=1) - 1e-9), 0).astype(np.int64)
    hi = np.minimum(np.floor(tri_px.max(axis=1) + 1e-9), [width - 1, height - 1]).astype(np.int64)
    span = np.maximum(hi - lo + 1, 0)
    counts = span[:, 0] * span[:, 1]
    out = np.full((height, width, 3), np.nan)
    keep = counts > 0
    if not keep.any():
        return out
    tid = np.repeat(np.flatnonzero(keep), counts[keep])
    start = np.repeat(np.cumsum(counts[keep]) - counts[keep], counts[keep])
    local = np.arange(len(tid)) - start
    col = lo[tid, 0] + local % span[tid, 0]
    row = lo[tid, 1] + local // span[tid, 0]
    a, b, c = tri_px[tid, 0], tri_px[tid, 1], tri_px[tid, 2]
    e1, e2 = b - a, c - a
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    ok = np.abs(det) > 1e-12
    q = np.column_stack([col, row]) - a
    safe = np.where(ok, det, 1.0)  # degenerate triangles (zero UV area) cover nothing
    l1 = (q[:, 0] * e2[:, 1] - q[:, 1] * e2[:, 0]) / safe
    l2 = (e1[:, 0] * q[:, 1] - e1[:, 1] * q[:, 0]) / safe
    eps = 1e-7
    inside = ok & (l1 >= -eps) & (l2 >= -eps) & (l1 + l2 <= 1 + eps)
    tri_v = vertices[triangles[tid[inside]]]
    l1, l2 = l1[inside, None], l2[inside, None]
    out[row[inside], col[inside]] = (1 - l1 - l2) * tri_v[:, 0] + l1 * tri_v[:, 1] + l2 * tri_v[:, 2]
    return out


def read_marking_image(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """An image marking: ink colour (h, w, 3) in [0, 1] and intensity (h, w) in [0, 1].

    With an alpha channel the alpha is the intensity; without one, pixels whose every channel is
    >= WHITE_LEVEL are clean (intensity 0) and all others are marking (intensity 1).
    """
    path = Path(path)
    require(path.is_file(), f"marking image {path} does not exist", "give X, ring, dots, patches or the path to a .png")
    try:
        from PIL import Image

        with Image.open(path) as im:
            has_alpha = im.mode in ("RGBA", "LA") or (im.mode == "P" and "transparency" in im.info)
            rgba = np.asarray(im.convert("RGBA"), dtype=np.float64) / 255.0
    except Exception as exc:  # PIL raises several types for unreadable files
        raise TergodicError(f"{path} is not a readable image ({type(exc).__name__})", "give a PNG file") from None
    h, w = rgba.shape[:2]
    require(8 <= min(h, w) and max(h, w) <= MAX_IMAGE_SIDE, f"marking image {path} is {w}x{h} pixels",
            f"give an image between 8 and {MAX_IMAGE_SIDE} pixels per side")
    ink = rgba[..., :3]
    intensity = rgba[..., 3] if has_alpha else (~np.all(ink >= WHITE_LEVEL, axis=-1)).astype(np.float64)
    require(float(intensity.max()) > 0, f"marking image {path} has no marking (all white or transparent)",
            "draw the marking in a colour, or give it an alpha channel")
    return ink, intensity


# ----------------------------------------------------------------------------- the object


class TexturedObject:
    """A textured mesh whose marking can be cleaned; everything in metres.

    Attributes
    ----------
    vertices : (n, 3) object frame; triangles : (k, 3) front faces (marked side, counter-clockwise).
    uvs : (n, 2) OBJ texture coordinates of the front faces.
    pose : (4, 4) object frame -> robot base frame.
    intensity : (H, W) marking intensity m per texel of the full texture (reserved rows included).
    initial : (H, W) m at construction.
    texel_points : (t, 3) object-frame surface points of the t texels that lie on the surface.
    texel_index : (t,) their flat indices into ``intensity``.
    version : increments whenever the texture changes (renderers reload on change).
    """

    def __init__(self, cfg: SimObjectConfig | None = None):
        from scipy.spatial import cKDTree

        cfg = cfg or SimObjectConfig()
        cfg.cleaning.validate()
        self.cfg = cfg
        default = (0.5, 0.0, 0.0, 0.0, 0.0, 180.0) if cfg.object == "mug" else (0.5, 0.0, 0.0)
        self.pose = parse_pose(cfg.pose if cfg.pose is not None else default, "--object-pose")
        builtin = cfg.object in BUILTIN_OBJECTS
        image_marking = cfg.marking not in PATTERN_MARKINGS
        if image_marking:
            require(cfg.marking.lower().endswith(".png") or Path(cfg.marking).is_file(), f"unknown marking '{cfg.marking}'",
                    f"use one of {', '.join(PATTERN_MARKINGS)} or the path to a .png image")
            ink, image_m = read_marking_image(cfg.marking)
        if builtin:
            mesh = builtin_mesh(cfg.object, cfg.mesh_edge)
        else:
            require(Path(cfg.object).suffix.lower() == ".obj" or os.sep in cfg.object or Path(cfg.object).exists(),
                    f"unknown sim object '{cfg.object}'", f"use one of {', '.join(BUILTIN_OBJECTS)} or a path to a .obj file")
            mesh = _file_mesh(cfg.object, cfg.units, use_uvs=image_marking)
        self.kind = cfg.object if builtin else "file"
        self.size = mesh.size

        if image_marking:
            height, width = image_m.shape
        else:
            require(16 <= cfg.texture_size <= MAX_IMAGE_SIDE, f"texture size {cfg.texture_size} is out of range",
                    f"give 16 to {MAX_IMAGE_SIDE} texels, e.g. 512")
            height = width = int(cfg.texture_size)
        self.width, self.height = width, height + RESERVED_ROWS
        uv_front = chart_to_uv(mesh.chart, mesh.box, height)

        # Colours: clean surface everywhere; ink and intensity only in the chart rows.
        clean = np.broadcast_to(SURFACE_RGB, (self.height, width, 3))
        ink_rgb = np.broadcast_to(MARKING_RGB, (self.height, width, 3)).copy()
        self.intensity = np.zeros((self.height, width))
        if image_marking:
            ink_rgb[:height] = ink
            self.intensity[:height] = image_m
        else:
            # the chart texels' centres (image row 0 at the chart's top)
            U, V = np.meshgrid((np.arange(width) + 0.5) / width, (height - np.arange(height) - 0.5) / height)
            chart = mesh.box[0] + np.column_stack([U.ravel(), V.ravel()]) * (mesh.box[1] - mesh.box[0])
            # the generator's drawing rules and dots' draw, so both agree exactly
            mark = _MARKS[cfg.marking](chart, mesh.size, np.random.default_rng(cfg.seed + 1))
            self.intensity[:height] = mark.reshape(height, width)

        # Where each texel sits on the surface; texels off the surface carry no marking.
        surf = rasterize_uv(mesh.vertices, mesh.triangles, uv_front, self.width, self.height)
        on_surface = np.all(np.isfinite(surf), axis=-1)
        self.intensity[~on_surface] = 0.0
        require(float(self.intensity.sum()) > 0, "the marking does not fall on the object's surface",
                "check the marking image and the mesh's texture coordinates")
        self.texel_index = np.flatnonzero(on_surface.ravel())
        self.texel_points = surf.reshape(-1, 3)[self.texel_index]
        self._texel_tree = cKDTree(self.texel_points)
        self.initial = self.intensity.copy()
        self._initial_sum = float(self.initial.sum())

        # Render mesh: front faces, plus back faces (plain for built-ins, textured for user meshes).
        self.vertices, self.triangles, self.uvs = mesh.vertices, mesh.triangles, uv_front
        n = len(mesh.vertices)
        back_uv = uv_front if mesh.two_sided_texture else np.tile([0.5, 0.5 * RESERVED_ROWS / self.height], (n, 1))
        self._render_vertices = np.concatenate([mesh.vertices, mesh.vertices])
        self._render_uvs = np.concatenate([uv_front, back_uv])
        normals = _vertex_normals(mesh.vertices, mesh.triangles)
        self._render_normals = np.concatenate([normals, -normals])
        self._render_triangles = np.concatenate([mesh.triangles, mesh.triangles[:, [0, 2, 1]] + n])
        self.version = 0
        # float32 in 0..255, as texture_rgb blends them at every re-capture
        self._blend = ((255.0 * clean).astype(np.float32) + 0.5, (255.0 * (ink_rgb - clean)).astype(np.float32))

    # ------------------------------------------------------------------ marking state
    def marking_remaining(self) -> float:
        """Share of the initial marking intensity still present (1 = untouched, 0 = clean)."""
        return float(self.intensity.sum()) / self._initial_sum

    def to_object(self, points: np.ndarray) -> np.ndarray:
        """Base-frame points (m, 3) -> object frame."""
        R, t = self.pose[:3, :3], self.pose[:3, 3]
        return (np.asarray(points, dtype=float).reshape(-1, 3) - t) @ R

    def clean(self, contact_points: np.ndarray, forces: np.ndarray, dt: float) -> float:
        """Apply the cleaning model for ``dt`` seconds; returns the share of the initial marking removed.

        contact_points : (m, 3) contact points in the robot base frame, metres.
        forces : (m,) normal force at each point, N. Points at or below ``force_min`` do not clean.
        dt : seconds the contacts were held.

        Every texel within ``radius`` of a contact decays by exp(-k F dt); overlapping contacts
        multiply, so the force of a contact split into several points adds up.
        """
        model = self.cfg.cleaning
        pts = np.asarray(contact_points, dtype=float).reshape(-1, 3)
        f = np.asarray(forces, dtype=float).reshape(-1)
        require(len(pts) == len(f), f"{len(pts)} contact points but {len(f)} forces", "give one normal force per contact point")
        require(np.isfinite(dt) and dt >= 0, f"cleaning step dt={dt} is not >= 0", "give the contact duration in seconds")
        active = np.isfinite(f) & (f > model.force_min) & np.all(np.isfinite(pts), axis=1)
        if not active.any() or dt == 0 or model.rate == 0:
            return 0.0
        # Only the texels under a contact are touched (the closed loop calls this every 20 ms).
        balls = self._texel_tree.query_ball_point(self.to_object(pts[active]), model.radius)
        sizes = [len(b) for b in balls]
        if sum(sizes) == 0:
            return 0.0
        idx = np.concatenate([np.asarray(b, dtype=np.intp) for b in balls])
        weight = np.repeat(model.rate * f[active] * dt, sizes)
        if len(balls) > 1:  # overlapping contacts multiply: add their exponents per texel
            idx, inverse = np.unique(idx, return_inverse=True)
            weight = np.bincount(inverse, weights=weight)
        flat = self.intensity.ravel()  # a view: updated in place
        sel = self.texel_index[idx]
        before = flat[sel]
        after = before * np.exp(-weight)
        flat[sel] = after
        self.version += 1
        return float(before.sum() - after.sum()) / self._initial_sum

    # ------------------------------------------------------------------ texture and assets
    def texture_rgb(self) -> np.ndarray:
        """The current texture, (H, W, 3) uint8: clean colour blended to the ink colour by m."""
        base, delta = self._blend
        rgb = base + self.intensity[..., None].astype(np.float32) * delta
        return np.clip(rgb, 0, 255).astype(np.uint8)  # +0.5 above makes the cast round

    @cached_property
    def _obj_body_text(self) -> str:
        v = "\n".join(f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in self._render_vertices)
        vt = "\n".join(f"vt {u:.7f} {w:.7f}" for u, w in self._render_uvs)
        vn = "\n".join(f"vn {x:.6f} {y:.6f} {z:.6f}" for x, y, z in self._render_normals)
        f = "\n".join(f"f {a}/{a}/{a} {b}/{b}/{b} {c}/{c}/{c}" for a, b, c in self._render_triangles + 1)
        return f"o tergodic_object\n{v}\n{vt}\n{vn}\nusemtl marked\ns off\n{f}\n"

    def create_body(self, client: int, folder: str | Path, collision: bool = False) -> int:
        """Add the object to PyBullet ``client`` at ``pose`` with its current texture; returns the body id.

        folder : where the mesh and texture files go (PyBullet loads meshes from files).
        collision : also give it a static concave triangle-mesh collision shape (front faces).

        The mesh file has no material: a texture that came from an .mtl cannot be replaced later
        under the EGL renderer, while one set with ``changeVisualShape`` can (:meth:`update_texture`).
        """
        import pybullet as p

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        mesh_path = folder / "mesh.obj"
        mesh_path.write_text(self._obj_body_text)
        vis = p.createVisualShape(p.GEOM_MESH, fileName=str(mesh_path), physicsClientId=client)
        require(vis >= 0, f"PyBullet could not load {mesh_path}", "check the mesh file")
        col = -1
        if collision:
            col = p.createCollisionShape(p.GEOM_MESH, vertices=self.vertices.tolist(), indices=self.triangles.ravel().tolist(),
                                         flags=p.GEOM_FORCE_CONCAVE_TRIMESH, physicsClientId=client)
        body = p.createMultiBody(0.0, col, vis, basePosition=self.pose[:3, 3].tolist(),
                                 baseOrientation=matrix_to_quat(self.pose[:3, :3]).tolist(), physicsClientId=client)
        self.update_texture(client, body, folder)
        return body

    def update_texture(self, client: int, body: int, folder: str | Path) -> None:
        """Give ``body`` (made by :meth:`create_body`) the current texture.

        ``changeTexture`` has no effect in DIRECT mode, so the texture goes through a new
        versioned file, ``loadTexture`` and ``changeVisualShape``. Each call keeps one texture
        (about 0.8 MB at 512 x 520) in the renderer until the client disconnects.
        """
        import pybullet as p
        from PIL import Image

        # BMP: uncompressed, about 20x faster to write than PNG
        path = Path(folder) / f"texture_v{self.version}.bmp"
        Image.fromarray(self.texture_rgb()).save(path)
        tex = p.loadTexture(str(path), physicsClientId=client)
        require(tex >= 0, f"PyBullet could not load the texture {path}", "check the temporary folder is writable")
        p.changeVisualShape(body, -1, textureUniqueId=tex, rgbaColor=[1, 1, 1, 1], physicsClientId=client)
        path.unlink(missing_ok=True)  # loaded; keep the folder small


def _vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (n, 3) of the counter-clockwise faces."""
    v = vertices[triangles]
    fn = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n = np.zeros_like(vertices)
    np.add.at(n, triangles.T, fn[None])  # every face's normal onto its three corners
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(norm > 0, norm, 1.0)


def parse_pose(values, option: str, fix: str | None = None) -> np.ndarray:
    """A pose as a (4, 4) transform from 3 (x,y,z m), 6 (+ roll,pitch,yaw deg, fixed axes XYZ) or 7 (+ qx,qy,qz,qw) numbers;
    ``fix``: the errors' hint (default: the forms of an ``option`` pose)."""
    v = [float(x) for x in values]
    fix = fix or f"give {option} x,y,z[,roll,pitch,yaw] (m, deg) or x,y,z,qx,qy,qz,qw, e.g. 0.5,0,0"
    require(len(v) in (3, 6, 7), f"{option} needs 3, 6 or 7 numbers, got {len(v)}", fix)
    require(all(np.isfinite(v)), f"{option} has a non-finite number", fix)
    require(max(abs(x) for x in v[:3]) < 5.0, f"{option} position {v[:3]} is not in metres near the robot", fix)
    T = np.eye(4)
    T[:3, 3] = v[:3]
    if len(v) == 6:
        from scipy.spatial.transform import Rotation

        # lower-case "xyz": fixed axes, R = Rz(yaw) Ry(pitch) Rx(roll)
        T[:3, :3] = Rotation.from_euler("xyz", v[3:], degrees=True).as_matrix()
    elif len(v) == 7:
        q = np.array(v[3:])
        require(abs(np.linalg.norm(q) - 1.0) < 1e-3, f"{option} quaternion is not unit length", fix)
        T[:3, :3] = quat_to_matrix(q / np.linalg.norm(q))
    return T


