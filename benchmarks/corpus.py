"""The household corpus: meshes nobody tuned for, sampled into marked clouds the way a user would.

Every mesh ships with pybullet_data. Each is turned to stand upright (z up: the up axis its URDF
and its flat base show), scaled to a household size (largest extent 12-18 cm; the shape sorter to
18 cm so that its walls stay 9 mm thick), and placed with its footprint centred on the origin and
its lowest point at z = 0. It is then:

1. Poisson-disk sampled (seeded) at about 3 mm or 6 mm (the shape sorter's coarse case at 6.7 mm,
   the hollow-box case of the coverage issue);
2. painted grey-white with a red marking: "patch" (two or three discs of 2-3 cm radius on the
   surface, seeded per object, on the sheet their centre lies on) or "band" (a horizontal band
   around mid-height, 2 cm tall or 40 % of a flatter object's height);
3. written as a coloured PLY with the project's writer and captured with the project's own
   ``capture_cloud(CaptureConfig(source="file", path=...))`` at the default 3 mm voxel.

The mesh (vertices, triangles) stays in the capture's frame, so ``mesh_distance(case.vertices,
case.triangles, x)`` measures how far any point x of a run is from the true surface.

Split: TUNE (bunny, duck, shape_sorter, torus, mug) may be looked at while tuning; CHECK (the rest)
is for checking only. Placements for the robot: "stand" (the default object pose: footprint centre
0.5 m in front of the base, lowest point on a 0.2 m stand) and "table" (lowest point on the robot
base plane, z = 0), each as an ``--object-pose`` string (:meth:`Case.object_pose`).

Built cases are cached (deterministically: same recipe, same files) under
``$TERGODIC_CORPUS_CACHE`` or the system temp folder, so benchmarks do not rebuild them.

    python benchmarks/corpus.py                     # build and list every case
    python benchmarks/corpus.py --split check --densities 6mm

From another benchmark (``import _env`` first, as every benchmark does)::

    corpus = _env.load("corpus")
    for case in corpus.cases("tune", densities=("6mm",)):
        case.capture, case.vertices, case.triangles, case.object_pose("table")
"""

from __future__ import annotations

if __name__ == "__main__":
    import _env  # noqa: F401,I001  (first: path fix, one BLAS thread; see benchmarks/_env.py)

import os
import shutil
import sys
import tempfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
if str(HERE.parent) not in sys.path:  # run from a checkout without installing
    sys.path.append(str(HERE.parent))

#: Bump when the recipe changes: the cache keys on it (2: the teddy's enclosed faces dropped).
RECIPE = 2
DENSITIES = {"3mm": 0.003, "6mm": 0.006}
MARKINGS = ("patch", "band")
SPLITS = ("tune", "check", "all")
#: The capture's voxel (the CLI's default).
VOXEL = 0.003
#: Band height, metres, at most this share of the object's height (flat objects).
BAND_HEIGHT, BAND_SHARE = 0.02, 0.4
#: Patch radius range (m) and count range.
PATCH_RADIUS, PATCH_COUNT = (0.02, 0.03), (2, 3)
#: y-up files (most of pybullet_data's meshes) turned to z-up: (x, y, z) -> (x, -z, y).
Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


@dataclass(frozen=True)
class MeshSpec:
    """One corpus mesh.

    file : path inside pybullet_data.
    up : the file's up axis, "y" or "z".
    extent : largest extent after scaling, metres.
    split : "tune" or "check".
    units : metres per file unit before the household scale (the differential is in millimetres).
    hulls : the file is a convex decomposition (V-HACD): sample only the union's outer surface.
    coarse : the "6mm" density's spacing, metres.
    """

    file: str
    up: str
    extent: float
    split: str
    units: float = 1.0
    hulls: bool = False
    coarse: float = 0.006


MESHES: dict[str, MeshSpec] = {
    # TUNE: the objects of the issues (bunny trapped, shape sorter's walls, torus, duck, mug)
    "bunny": MeshSpec("bunny.obj", "y", 0.15, "tune"),
    "duck": MeshSpec("duck.obj", "y", 0.15, "tune"),
    "shape_sorter": MeshSpec("toys/shape_sorter.obj", "y", 0.18, "tune", coarse=0.0067),  # 9 mm walls
    "torus": MeshSpec("torus/torus_textured.obj", "y", 0.15, "tune"),
    "mug": MeshSpec("objects/mug.obj", "z", 0.12, "tune"),
    # CHECK: never looked at while tuning
    "teddy": MeshSpec("teddy2_VHACD_CHs.obj", "y", 0.15, "check", hulls=True),
    "sphere": MeshSpec("sphere_smooth.obj", "y", 0.12, "check"),
    "soccerball": MeshSpec("soccerball.obj", "y", 0.14, "check"),
    "tray": MeshSpec("tray/tray_textured.obj", "z", 0.18, "check"),
    "concave_box": MeshSpec("toys/concave_box.obj", "z", 0.15, "check"),
    "cylinder": MeshSpec("toys/cylinder.obj", "z", 0.14, "check"),  # lying on its broad side
    "prism": MeshSpec("toys/prism.obj", "y", 0.14, "check"),
    "diff_carrier": MeshSpec("differential/diff_carrier.stl", "z", 0.12, "check", units=1e-3),
}


@dataclass
class Case:
    """One corpus case: a marked cloud captured from a mesh, and that mesh in the capture's frame.

    Attributes
    ----------
    name : "<mesh>-<density>-<marking>", e.g. "bunny-6mm-band".
    mesh_name, density, marking, split : what it is made of.
    spacing : the sampling spacing, metres.
    cloud_path : the coloured PLY a user would have (before capture).
    capture : the project's Capture of it (3 mm voxel).
    capture_dir : its capture folder (``tergodic explore CAPTURE_DIR ...``).
    vertices : (n, 3) float64, metres, the capture's frame.
    triangles : (k, 3) int64.
    poses : placement -> ``--object-pose`` string ("x,y,z", metres): "stand" is the documented default
        (footprint centre DEFAULT_REACH in front of the base, lowest point DEFAULT_HEIGHT up), "table" the
        same spot with the mesh's lowest point on the base plane. A run given no ``--object-pose`` uses
        whatever pose the robot stage picks (its summary's ``object_pose`` says which).
    """

    name: str
    mesh_name: str
    density: str
    marking: str
    split: str
    spacing: float
    cloud_path: Path
    capture: object
    capture_dir: Path
    vertices: np.ndarray
    triangles: np.ndarray
    poses: dict = field(default_factory=dict)

    def object_pose(self, placement: str = "stand") -> str:
        """The ``--object-pose`` value for ``placement`` ("stand" or "table")."""
        return self.poses[placement]


def cache_dir() -> Path:
    """Where built cases live: ``$TERGODIC_CORPUS_CACHE`` or ``<tmp>/tergodic-corpus``, per recipe."""
    root = os.environ.get("TERGODIC_CORPUS_CACHE") or os.path.join(tempfile.gettempdir(), "tergodic-corpus")
    return Path(root) / f"recipe{RECIPE}"


def mesh_names(split: str = "all") -> list[str]:
    """The corpus meshes of ``split`` ("tune", "check" or "all"), in a fixed order."""
    if split not in SPLITS:
        raise ValueError(f"unknown split '{split}' (use {', '.join(SPLITS)})")
    return [n for n, s in MESHES.items() if split == "all" or s.split == split]


def load_mesh(name: str):
    """The corpus mesh ``name`` upright (z up), scaled, footprint centred on the origin, lowest point at z = 0.

    Returns
    -------
    TriangleMesh
        Vertices in metres.
    """
    import pybullet_data

    from tergodic_cli.capture.mesh import read_mesh

    spec = MESHES[name]
    mesh = read_mesh(Path(pybullet_data.getDataPath()) / spec.file)
    R = Y_UP if spec.up == "y" else np.eye(3)
    v = mesh.vertices * spec.units @ R.T
    scale = spec.extent / float(np.ptp(v, axis=0).max())
    v = v * scale
    lo, hi = v.min(axis=0), v.max(axis=0)
    t = -np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]])
    return mesh.transformed(spec.units * scale, R, t)


def _hull_components(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """Connected pieces of a convex decomposition: each triangle's piece (k,) and each piece's half-spaces."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import ConvexHull

    _, vid = np.unique(np.round(vertices, 9), axis=0, return_inverse=True)
    vid = vid.ravel()
    t = vid[triangles]
    n = int(vid.max()) + 1
    edges = np.concatenate([t[:, [0, 1]], t[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    piece = label[t[:, 0]]
    eqs = [ConvexHull(vertices[triangles[piece == k].ravel()]).equations for k in range(int(piece.max()) + 1)]
    return piece, eqs


def _outer_surface(points: np.ndarray, tri: np.ndarray, vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(n,) bool: the sample lies on the union's outer surface: not inside another convex piece by
    > 0.5 mm, and seen from outside (a ray from 0.5 mm off its face, one of 64 directions within 80 deg
    of its outward normal, leaves the mesh; the teddy's pieces enclose voids whose faces held 32 % of
    its samples, sheets no camera sees)."""
    import open3d as o3d

    piece, eqs = _hull_components(vertices, triangles)
    inside = np.zeros(len(points), bool)
    for k, eq in enumerate(eqs):
        depth = (points @ eq[:, :3].T + eq[:, 3]).max(axis=1)  # < 0 inside piece k
        inside |= (depth < -5e-4) & (piece[tri] != k)
    v = vertices[triangles[tri]]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])  # the pieces are wound outward
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    k = np.arange(64) + 0.5
    z = 1.0 - 2.0 * k / 64
    phi = np.pi * (1.0 + 5.0 ** 0.5) * k
    dirs = np.column_stack([np.sqrt(1.0 - z * z) * np.cos(phi), np.sqrt(1.0 - z * z) * np.sin(phi), z])
    pi, di = np.nonzero(n @ dirs.T > 0.17)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
    rays = np.column_stack([points[pi] + 5e-4 * n[pi], dirs[di]]).astype(np.float32)
    free = np.isinf(scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy())
    seen = np.bincount(pi, weights=free.astype(float), minlength=len(points)) > 0
    return ~inside & seen


def paint(points: np.ndarray, normals: np.ndarray, marking: str, seed: int) -> np.ndarray:
    """(n,) bool: the samples painted red.

    Parameters
    ----------
    points : (n, 3) metres, z up, lowest point at 0.
    normals : (n, 3) unit.
    marking : "patch" (two or three discs of 2-3 cm radius, on the sheet of their centre, not on the
        underside) or "band" (|z - mid-height| below half the band height).
    seed : the patches' draw.
    """
    if marking == "band":
        z = points[:, 2]
        lo, hi = float(z.min()), float(z.max())
        half = 0.5 * min(BAND_HEIGHT, BAND_SHARE * (hi - lo))
        return np.abs(z - 0.5 * (lo + hi)) <= half
    if marking != "patch":
        raise ValueError(f"unknown marking '{marking}' (use {', '.join(MARKINGS)})")
    rng = np.random.default_rng(seed)
    k = int(rng.integers(PATCH_COUNT[0], PATCH_COUNT[1] + 1))
    radii = rng.uniform(*PATCH_RADIUS, size=k)
    candidates = np.flatnonzero(normals[:, 2] > -0.2)  # not the underside (it faces the stand)
    mask = np.zeros(len(points), bool)
    centres: list[int] = []
    for r in radii:
        far = candidates
        if centres:  # apart from the previous discs, when the object leaves room
            d = np.linalg.norm(points[candidates, None] - points[centres][None], axis=2).min(axis=1)
            far = candidates[d > 2.2 * r] if np.any(d > 2.2 * r) else candidates[d >= d.max() - 1e-9]
        c = int(far[rng.integers(len(far))])
        centres.append(c)
        # the disc on the centre's sheet only: a thin wall's far side faces the other way
        near = np.linalg.norm(points - points[c], axis=1) <= r
        mask |= near & (normals @ normals[c] > -0.5)
    return mask


def _build(name: str, density: str, marking: str, folder: Path) -> None:
    """Sample, paint, write and capture one case into ``folder`` (cloud.ply, mesh.npz, capture/)."""
    from tergodic_cli.capture import CaptureConfig, capture_cloud, save_capture
    from tergodic_cli.capture.mesh import sample_mesh
    from tergodic_cli.capture.readers import write_ply
    from tergodic_cli.capture.synthetic import MARKING_RGB, SURFACE_RGB

    spec = MESHES[name]
    spacing = spec.coarse if density == "6mm" else DENSITIES[density]
    mesh = load_mesh(name)
    sample = sample_mesh(mesh, spacing, seed=0)
    points, normals = sample.points, sample.normals
    if spec.hulls:
        keep = _outer_surface(points, sample.triangle, mesh.vertices, mesh.triangles)
        points, normals = points[keep], normals[keep]
    red = paint(points, normals, marking, seed=zlib.crc32(name.encode()))
    colors = np.where(red[:, None], MARKING_RGB, SURFACE_RGB)
    write_ply(folder / "cloud.ply", points, colors)
    np.savez(folder / "mesh.npz", vertices=mesh.vertices.astype(np.float64), triangles=mesh.triangles.astype(np.int64))
    cap = capture_cloud(CaptureConfig(source="file", path=str(folder / "cloud.ply"), voxel=VOXEL), on_event=lambda m: None)
    save_capture(cap, folder / "capture")


def _poses(points: np.ndarray, vertices: np.ndarray) -> dict:
    from tergodic_cli.robot.surface import default_object_pose

    stand = default_object_pose(points)[:3, 3]
    table = np.array([stand[0], stand[1], -float(vertices[:, 2].min())])  # the mesh's lowest point on z = 0
    fmt = lambda t: ",".join(f"{x + 0.0:.4f}" for x in np.round(t, 4))  # noqa: E731  (no "-0.0000")
    return {"stand": fmt(stand), "table": fmt(table)}


def get_case(name: str, density: str = "6mm", marking: str = "patch") -> Case:
    """One corpus case, built on first use and cached (see :func:`cache_dir`)."""
    from tergodic_cli.capture import load_capture

    if name not in MESHES or density not in DENSITIES or marking not in MARKINGS:
        raise ValueError(f"unknown case {name}/{density}/{marking}")
    label = f"{name}-{density}-{marking}"
    folder = cache_dir() / label
    if not (folder / "capture" / "capture.json").exists():
        folder.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{label}-", dir=folder.parent))
        try:
            _build(name, density, marking, tmp)
            try:
                tmp.rename(folder)
            except OSError:  # built meanwhile by another process: keep theirs
                pass
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    cap = load_capture(folder / "capture")
    with np.load(folder / "mesh.npz", allow_pickle=False) as data:
        vertices, triangles = data["vertices"], data["triangles"]
    spec = MESHES[name]
    spacing = spec.coarse if density == "6mm" else DENSITIES[density]
    return Case(label, name, density, marking, spec.split, spacing, folder / "cloud.ply", cap, folder / "capture",
                vertices, triangles, _poses(cap.points, vertices))


def cases(split: str = "all", densities=("3mm", "6mm"), markings=MARKINGS, objects=None) -> list[Case]:
    """The corpus cases of ``split``, every density and marking asked for.

    Parameters
    ----------
    split : "tune", "check" or "all".
    densities : subset of ("3mm", "6mm").
    markings : subset of ("patch", "band").
    objects : mesh names to keep (None: all of the split).
    """
    names = [n for n in mesh_names(split) if objects is None or n in objects]
    return [get_case(n, d, m) for n in names for d in densities for m in markings]


def main() -> int:
    import argparse

    from tergodic_cli.capture.filters import mean_spacing
    from tergodic_cli.capture.mesh import mesh_distance

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--split", default="all", choices=SPLITS)
    ap.add_argument("--densities", default="3mm,6mm")
    ap.add_argument("--markings", default="patch,band")
    ap.add_argument("--objects", default=None, help="comma-separated mesh names")
    args = ap.parse_args()
    print(f"cache: {cache_dir()}")
    print("| case | split | extent (cm) | input pts | capture pts | h (mm) | target | mesh dist p99 (mm) | stand | table |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for c in cases(args.split, args.densities.split(","), args.markings.split(","),
                   args.objects.split(",") if args.objects else None):
        cap = c.capture
        d = mesh_distance(c.vertices, c.triangles, cap.points)
        ext = np.ptp(c.vertices, axis=0) * 100
        print(f"| {c.name} | {c.split} | {ext[0]:.1f}x{ext[1]:.1f}x{ext[2]:.1f} | {cap.meta['counts']['input']} | "
              f"{cap.n_points} | {mean_spacing(cap.points) * 1e3:.2f} | {100 * np.mean(cap.target > 0):.1f}% | "
              f"{np.percentile(d, 99) * 1e3:.3f} | {c.object_pose('stand')} | {c.object_pose('table')} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
