"""Triangle meshes: read one, sample it into a coloured cloud, measure distances to it.

Everything is in metres. A mesh is read from Wavefront .obj (parsed here: polygons are
fan-triangulated, a vertex used with two texture coordinates is split, the ``map_Kd`` texture of
its .mtl is loaded) or from .stl, .ply, .glb/.gltf and .off (open3d). It is sampled by Poisson
disk (open3d, seeded) at a given spacing; each sample takes the colour of the surface under it,
interpolated from the vertex colours or looked up in the texture. Distances to the surface come
from open3d's ray-casting scene.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tergodic_cli.errors import TergodicError, require

MESH_SUFFIXES = (".obj", ".stl", ".ply", ".glb", ".gltf", ".off")
#: A Poisson-disk sample of N points on area A has its nearest neighbours about sqrt(A / (N sqrt(3)/2))
#: apart when packed hexagonally; the sampler does not pack that tightly, so ask for this share of it.
_PACKING = 0.75
#: More samples than this is a mistake (a spacing in millimetres given as metres, or a huge mesh).
MAX_SAMPLES = 2_000_000


@dataclass
class TriangleMesh:
    """A triangle mesh with what colours its surface.

    Attributes
    ----------
    vertices : (n, 3) float64
        Metres (or the file's units until scaled).
    triangles : (k, 3) int64
        Vertex indices, counter-clockwise as in the file.
    vertex_colors : (n, 3) float64 or None
        In [0, 1].
    corner_uvs : (k, 3, 2) float64 or None
        Texture coordinates of each triangle's corners (v = 0 is the image's bottom row).
    textures : list of (h, w, 3) float64
        Images in [0, 1]; ``material`` picks one per triangle.
    material : (k,) int64 or None
        Index into ``textures`` per triangle; None: texture 0 everywhere.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    vertex_colors: np.ndarray | None = None
    corner_uvs: np.ndarray | None = None
    textures: list | None = None
    material: np.ndarray | None = None

    @property
    def triangle_areas(self) -> np.ndarray:
        """(k,) each triangle's area, square metres (of the vertices' units)."""
        v = self.vertices[self.triangles]
        return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)

    @property
    def area(self) -> float:
        """Total surface area, square metres (of the vertices' units)."""
        return float(self.triangle_areas.sum())

    @property
    def has_colour(self) -> bool:
        return self.vertex_colors is not None or bool(self.textures and self.corner_uvs is not None)

    def transformed(self, scale: float = 1.0, R: np.ndarray | None = None, t: np.ndarray | None = None) -> TriangleMesh:
        """The same mesh with vertices mapped x -> R (scale x) + t; colours and UVs kept.

        Parameters
        ----------
        scale : float
            Uniform scale (e.g. 1e-3 for millimetres to metres).
        R : (3, 3) rotation, optional
        t : (3,) translation in the output units, optional

        Returns
        -------
        TriangleMesh
            A new mesh sharing the triangles, colours and UVs.
        """
        v = self.vertices * float(scale)
        if R is not None:
            v = v @ np.asarray(R, dtype=float).T
        if t is not None:
            v = v + np.asarray(t, dtype=float)
        return TriangleMesh(v, self.triangles, self.vertex_colors, self.corner_uvs, self.textures, self.material)


@dataclass
class MeshSample:
    """Points sampled on a mesh.

    Attributes
    ----------
    points : (n, 3) float64, metres, on the surface.
    normals : (n, 3) float64, unit, the normal of the triangle each point lies on (its winding).
    colors : (n, 3) float64 in [0, 1], or None when the mesh has no colour.
    triangle : (n,) int64, the triangle each point lies on.
    """

    points: np.ndarray
    normals: np.ndarray
    colors: np.ndarray | None
    triangle: np.ndarray


# ----------------------------------------------------------------------------- reading


def parse_obj(path: str | Path, option: str = "--from") -> tuple[np.ndarray, np.ndarray, np.ndarray | None, Path | None]:
    """Parse a Wavefront .obj without judging its units.

    Polygons are fan-triangulated. A vertex used with different texture coordinates is split,
    so every output vertex has one UV.

    Parameters
    ----------
    path : str or Path
    option : str
        The command-line option that named the file, for messages.

    Returns
    -------
    vertices : (n, 3) float64
        In the file's units.
    triangles : (k, 3) int64
    uvs : (n, 2) float64 or None
        One texture coordinate per vertex, when every face corner has one.
    texture : Path or None
        The image the first ``map_Kd`` of its material library names, when that file exists.
    """
    path = Path(path)
    require(path.is_file(), f"mesh file {path} does not exist", f"check the path given to {option}")
    pos, tex, corners, mtllibs = [], [], [], []
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            for line in fh:
                parts = line.split()
                if not parts:
                    continue
                if parts[0] == "v":
                    pos.append([float(x) for x in parts[1:4]])
                elif parts[0] == "vt":
                    tex.append([float(x) for x in parts[1:3]])
                elif parts[0] == "f":
                    face = []
                    for item in parts[1:]:
                        idx = item.split("/")
                        vi = int(idx[0])
                        ti = int(idx[1]) if len(idx) > 1 and idx[1] else 0
                        # OBJ indices are 1-based; negative ones count back from the last element.
                        face.append((vi - 1 if vi > 0 else len(pos) + vi, (ti - 1 if ti > 0 else len(tex) + ti) if ti else -1))
                    corners += [(face[0], face[k], face[k + 1]) for k in range(1, len(face) - 1)]
                elif parts[0] == "mtllib" and len(parts) > 1:
                    mtllibs.append(line.split(None, 1)[1].strip())
    except (ValueError, IndexError):
        raise TergodicError(f"{path} is not a readable .obj (bad v/vt/f line)", "re-export the mesh as a Wavefront .obj") from None
    require(len(pos) >= 3 and len(corners) > 0, f"{path} has no triangles", "give a mesh with faces (f lines)")
    V = np.asarray(pos, dtype=float)
    flat = np.array([c for tri in corners for c in tri], dtype=np.int64)  # (3k, 2): vertex, uv index
    require(flat[:, 0].min() >= 0 and flat[:, 0].max() < len(V), f"{path} has face indices outside its vertex list",
            "re-export the mesh")
    has_uv = len(tex) > 0 and bool(np.all(flat[:, 1] >= 0))
    require(not has_uv or flat[:, 1].max() < len(tex), f"{path} has texture indices outside its vt list",
            "re-export the mesh")
    # one output vertex per (vertex, uv) pair used, or per vertex used
    pairs, inverse = np.unique(flat if has_uv else flat[:, :1], axis=0, return_inverse=True)
    vertices, triangles = V[pairs[:, 0]], inverse.reshape(-1, 3).astype(np.int64)
    uvs = np.asarray(tex, dtype=float)[pairs[:, 1]] if has_uv else None
    return vertices, triangles, uvs, _mtl_texture(path, mtllibs) if has_uv else None


def _mtl_texture(obj: Path, mtllibs: list[str]) -> Path | None:
    """The first existing ``map_Kd`` image of the .obj's material libraries (its last token is the file)."""
    for lib in mtllibs:
        mtl = obj.parent / lib
        if not mtl.is_file():
            continue
        for line in mtl.read_text(encoding="utf-8", errors="replace").splitlines():
            parts = line.split()
            if len(parts) >= 2 and parts[0] == "map_Kd":
                image = (mtl.parent / parts[-1].replace("\\", "/"))
                if image.is_file():
                    return image
    return None


def _read_image(path: Path) -> np.ndarray:
    """(h, w, 3) float64 in [0, 1]."""
    try:
        from PIL import Image

        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"), dtype=np.float64) / 255.0
    except Exception as exc:  # PIL raises several types for unreadable files
        raise TergodicError(f"texture {path} is not a readable image ({type(exc).__name__})",
                            "fix or remove the map_Kd line of the mesh's .mtl") from None


def ply_has_faces(path: str | Path) -> bool:
    """Whether a PLY file's header declares a non-empty ``element face`` (a mesh, not a cloud).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    bool
    """
    with open(path, "rb") as fh:
        head = fh.read(65536)
    end = head.find(b"end_header")
    for line in head[: end if end >= 0 else len(head)].decode("ascii", "replace").splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[0] == "element" and parts[1] == "face":
            return parts[2].isdigit() and int(parts[2]) > 0
    return False


def read_mesh(path: str | Path, option: str = "--from") -> TriangleMesh:
    """Read a triangle mesh (format from the extension), in the file's units.

    Parameters
    ----------
    path : str or Path
        .obj (its .mtl's ``map_Kd`` texture is loaded), .stl, .ply (with faces), .glb/.gltf or .off.
    option : str
        The command-line option that named the file, for messages.

    Returns
    -------
    TriangleMesh
        Checked: at least one triangle, finite vertices, indices in range, non-zero area.
    """
    path = Path(path)
    require(path.exists(), f"no such file: {path}", f"check the path given to {option}")
    require(path.is_file(), f"not a file: {path}", f"give a mesh file ({', '.join(MESH_SUFFIXES)}) to {option}")
    suffix = path.suffix.lower()
    require(suffix in MESH_SUFFIXES, f"unknown mesh extension '{suffix}' for {path.name}", f"use one of {', '.join(MESH_SUFFIXES)}")
    require(path.stat().st_size > 0, f"{path.name} is an empty file", "re-export the mesh")
    if suffix == ".obj":
        vertices, triangles, uvs, image = parse_obj(path, option)
        mesh = TriangleMesh(vertices, triangles)
        if uvs is not None and image is not None:
            mesh.corner_uvs, mesh.textures = uvs[triangles], [_read_image(image)]
    else:
        mesh = _read_open3d(path)
    v, t = mesh.vertices, mesh.triangles
    require(len(t) > 0 and len(v) >= 3, f"{path.name} has no triangles",
            "give a mesh with faces (a cloud goes to capture --from as .ply/.pcd/.xyz without faces)")
    require(bool(np.all(np.isfinite(v))), f"{path.name} has non-finite (NaN or inf) vertex coordinates", "repair the mesh")
    require(t.min() >= 0 and t.max() < len(v), f"{path.name} has face indices outside its vertex list", "re-export the mesh")
    require(mesh.area > 0, f"{path.name} has only degenerate (zero-area) triangles", "re-export the mesh")
    return mesh


def _read_open3d(path: Path) -> TriangleMesh:
    import open3d as o3d

    # open3d prints its own warnings (and reads a broken file as empty): silence them, check the result
    level = o3d.utility.get_verbosity_level()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    try:
        m = o3d.io.read_triangle_mesh(str(path), enable_post_processing=False)
    except Exception as exc:  # open3d raises RuntimeError on some malformed files
        raise TergodicError(f"{path.name} is not a readable mesh ({type(exc).__name__})", "re-export the mesh") from None
    finally:
        o3d.utility.set_verbosity_level(level)
    vertices = np.asarray(m.vertices, dtype=np.float64).copy()
    triangles = np.asarray(m.triangles, dtype=np.int64).copy()
    mesh = TriangleMesh(vertices, triangles)
    if m.has_vertex_colors() and len(m.vertex_colors) == len(vertices):
        mesh.vertex_colors = np.clip(np.asarray(m.vertex_colors, dtype=np.float64), 0.0, 1.0)
    textures = [np.asarray(im, dtype=np.float64) for im in m.textures if not im.is_empty()]
    if textures and m.has_triangle_uvs() and len(m.triangle_uvs) == 3 * len(triangles):
        mesh.textures = [_as_rgb(im) for im in textures]
        # open3d gives OBJ-convention UVs (also for glTF, whose v runs down) but stores the image
        # bottom row first; flipping v makes surface_colors' lookup (row = (1 - v) h) read it right
        uv = np.asarray(m.triangle_uvs, dtype=np.float64).reshape(-1, 3, 2)
        mesh.corner_uvs = np.stack([uv[..., 0], 1.0 - uv[..., 1]], axis=-1)
        if m.has_triangle_material_ids():
            mesh.material = np.clip(np.asarray(m.triangle_material_ids, dtype=np.int64), 0, len(textures) - 1)
    return mesh


def _as_rgb(image: np.ndarray) -> np.ndarray:
    """An open3d image as (h, w, 3) in [0, 1]."""
    im = image if image.ndim == 3 else image[..., None]
    im = im[..., :3] if im.shape[2] >= 3 else np.repeat(im[..., :1], 3, axis=2)
    return im / 255.0 if im.max() > 1.0 else im


# ----------------------------------------------------------------------------- sampling and distance


def _scene(vertices: np.ndarray, triangles: np.ndarray):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.asarray(triangles, dtype=np.uint32)))
    return scene


def closest_on_mesh(vertices: np.ndarray, triangles: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The closest surface point of a mesh to each query point.

    Parameters
    ----------
    vertices : (n, 3) float, metres
    triangles : (k, 3) int
    points : (m, 3) float, metres

    Returns
    -------
    closest : (m, 3) float64, metres
    triangle : (m, 3) int64, the triangle it lies on
    barycentric : (m, 3) float64, its weights on that triangle's corners (summing to 1)
    """
    import open3d as o3d

    q = o3d.core.Tensor(np.asarray(points, dtype=np.float32).reshape(-1, 3))
    ans = _scene(vertices, triangles).compute_closest_points(q)
    uv = ans["primitive_uvs"].numpy().astype(np.float64)  # weights of corners 1 and 2
    bary = np.column_stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]])
    return ans["points"].numpy().astype(np.float64), ans["primitive_ids"].numpy().astype(np.int64), bary


def mesh_distance(vertices: np.ndarray, triangles: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Unsigned distance from each point to a triangle mesh's surface.

    Parameters
    ----------
    vertices : (n, 3) float, metres
    triangles : (k, 3) int
    points : (m, 3) float, metres, in the mesh's frame

    Returns
    -------
    (m,) float64
        Metres (computed in single precision: ~1e-8 m at tabletop sizes).
    """
    import open3d as o3d

    q = o3d.core.Tensor(np.asarray(points, dtype=np.float32).reshape(-1, 3))
    return _scene(vertices, triangles).compute_distance(q).numpy().astype(np.float64)


def surface_colors(mesh: TriangleMesh, triangle: np.ndarray, barycentric: np.ndarray) -> np.ndarray | None:
    """The mesh's colour at surface points given by triangle and barycentric weights.

    Parameters
    ----------
    mesh : TriangleMesh
    triangle : (m,) int
    barycentric : (m, 3) float

    Returns
    -------
    (m, 3) float64 in [0, 1], or None when the mesh has neither texture nor vertex colours.
        The texture wins over vertex colours; texels are looked up nearest, UVs wrap (tiling).
    """
    if mesh.textures and mesh.corner_uvs is not None:
        uv = np.einsum("mc,mcd->md", barycentric, mesh.corner_uvs[triangle])
        mat = mesh.material[triangle] if mesh.material is not None else np.zeros(len(triangle), np.int64)
        out = np.empty((len(triangle), 3))
        for i, image in enumerate(mesh.textures):
            sel = mat == i
            h, w = image.shape[:2]
            u, v = np.mod(uv[sel, 0], 1.0), np.mod(uv[sel, 1], 1.0)
            col = np.minimum((u * w).astype(np.int64), w - 1)
            row = np.minimum(((1.0 - v) * h).astype(np.int64), h - 1)  # v = 0 is the bottom row
            out[sel] = image[row, col, :3]
        return np.clip(out, 0.0, 1.0)
    if mesh.vertex_colors is not None:
        return np.clip(np.einsum("mc,mcd->md", barycentric, mesh.vertex_colors[mesh.triangles[triangle]]), 0.0, 1.0)
    return None


def uniform_colors(mesh: TriangleMesh, n: int, seed: int = 0) -> np.ndarray | None:
    """The surface colour at ``n`` points drawn uniformly over the mesh's area: a quick look at its
    colours (its marking) before :func:`sample_mesh`'s slower Poisson-disk sampling.

    Parameters
    ----------
    mesh : TriangleMesh
    n : int
        Number of points.
    seed : int
        Seeds the draw.

    Returns
    -------
    (n, 3) float64 in [0, 1], or None when the mesh has no colour (or no area).
    """
    area = mesh.triangle_areas
    if not area.sum() > 0:
        return None
    rng = np.random.default_rng(seed)
    tri = rng.choice(len(area), size=n, p=area / area.sum())
    return surface_colors(mesh, tri, rng.dirichlet(np.ones(3), size=n))


def sample_mesh(mesh: TriangleMesh, spacing: float, seed: int = 0) -> MeshSample:
    """Poisson-disk sample a mesh at about ``spacing`` between neighbouring points.

    Parameters
    ----------
    mesh : TriangleMesh
        In metres.
    spacing : float
        Target distance to the nearest neighbour, metres (e.g. 0.003).
    seed : int
        Seeds open3d's sampler: the same mesh, spacing and seed give the same points.

    Returns
    -------
    MeshSample
        Points on the surface with their triangle's normal and the surface colour there.
    """
    import open3d as o3d

    require(np.isfinite(spacing) and spacing > 0, f"sampling spacing {spacing} is not a length > 0", "give it in metres, e.g. 0.003")
    area = mesh.area
    n = int(np.ceil(_PACKING * area / (spacing ** 2 * np.sqrt(3) / 2)))
    require(n <= MAX_SAMPLES, f"sampling a {area:.3g} m² mesh at {spacing * 1e3:.3g} mm needs {n:,} points",
            "use a larger spacing (--voxel, in metres), or check the mesh's --units")
    n = max(n, 10)
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                  o3d.utility.Vector3iVector(mesh.triangles.astype(np.int32)))
    o3d.utility.random.seed(int(seed))
    cloud = m.sample_points_poisson_disk(number_of_points=n, init_factor=5)
    points = np.asarray(cloud.points, dtype=np.float64)
    # the sampler does not say where each point came from: find its triangle (it lies on it)
    closest, tri, bary = closest_on_mesh(mesh.vertices, mesh.triangles, points)
    v = mesh.vertices[mesh.triangles[tri]]
    nrm = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    return MeshSample(points, nrm, surface_colors(mesh, tri, bary), tri)
