"""The capture pipeline: read -> units -> validity -> passthrough -> outliers -> segment -> voxel -> isolated.

Segmentation runs on the raw points, before the voxel grid, so that the default
voxel rule can give p as the share of target-coloured points in each voxel.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tergodic_cli.capture.artefact import Capture
from tergodic_cli.capture.config import MAX_POINTS, CaptureConfig  # noqa: F401  (their home; re-exported here)
from tergodic_cli.capture.filters import (ISOLATED_MIN, VOXEL_RULES, basis_size, count_duplicates, isolated_points, mean_spacing,
                                          remove_statistical_outliers, voxel_downsample)
from tergodic_cli.capture.readers import read_cloud
from tergodic_cli.capture.segment import parse_target, target_weight
from tergodic_cli.capture.synthetic import check_noise, generate_synthetic
from tergodic_cli.config import Config
from tergodic_cli.errors import TergodicError, check_seed, require
from tergodic_cli.progress import echo

MIN_POINTS = 10
#: A tabletop object larger than this many metres was almost surely given in millimetres.
MAX_EXTENT_M = 5.0
#: ... and one smaller than this was almost surely metres read as millimetres.
MIN_EXTENT_M = 0.005
#: Spans beyond these are not a units mistake (x1000 would not make them an object): a corrupt body.
CORRUPT_EXTENT_M = MAX_EXTENT_M * 1e3
DEGENERATE_EXTENT_M = MIN_EXTENT_M * 1e-3
#: The basis' default nK and neighbours, for the capture's size warning (precompute's defaults).
BASIS_NK, BASIS_NEIGHBORS = 200, 30
#: Rough cost of precompute per point (nK = 200), measured at 120k points: 1.6 GB peak, 27 s on 2 cores.
#: Time grows faster than linearly, so the estimate is a lower bound.
BYTES_PER_POINT = 13_000
SECONDS_PER_POINT = 2.3e-4
#: ... and per point of a dense cloud whose basis is on stand-ins (filters.FIELD_VOXEL): its key,
#: spacing and map; measured at 1M points (4507 stand-ins): 297 MB peak, 12 s on 2 loaded cores.
BYTES_PER_DENSE_POINT = 300
SECONDS_PER_DENSE_POINT = 1.2e-5




def capture_cloud(cfg: CaptureConfig, raw: tuple[np.ndarray, np.ndarray | None] | None = None,
                  on_event=None) -> Capture:
    """Run the capture pipeline for ``cfg``.

    Parameters
    ----------
    cfg : CaptureConfig
        A ``source="file"`` whose path is a triangle mesh is sampled by Poisson disk at the voxel
        edge (3 mm when ``voxel`` is 0), seeded by ``cfg.seed``, coloured from the mesh's texture or
        vertex colours; the mesh is kept in the capture (same frame, metres).
    raw : tuple, optional
        (points (n, 3) m, colours (n, 3) in [0, 1] or None), bypassing the source: for sources that
        produce arrays themselves (simulated or real cameras).
    on_event : callable, optional
        ``on_event(str)`` gets warnings (the size guard); default: stderr.

    Returns
    -------
    Capture
        The filtered cloud, its target weight p (n,) in [0, 1], the sidecar ``meta`` and, for a
        mesh input, the mesh.
    """
    _validate_config(cfg)
    on_event = on_event or echo
    t0 = time.perf_counter()
    target_range = parse_target(cfg.target)
    stages: list[tuple[str, int]] = []  # points left after each stage, for the printed summary
    provenance: dict = {"source": cfg.source}
    mesh = None  # (vertices (n, 3) m, triangles (k, 3)) of a mesh input
    units = cfg.units  # of `points` below: a sampled mesh is already in metres
    if raw is not None:
        points, colors = raw
    elif cfg.source == "file" and is_mesh_file(cfg.path):
        points, colors, mesh, provenance["mesh"] = _sample_mesh_file(cfg, target_range)
        provenance["path"] = str(cfg.path)
        units = "m"
    elif cfg.source == "file":
        points, colors = read_cloud(cfg.path, drop_invalid=cfg.drop_invalid, colour_depth=cfg.colour_depth)
        provenance["path"] = str(cfg.path)
    elif cfg.source == "synthetic":
        syn = generate_synthetic(cfg.synthetic, cfg.marking, cfg.seed, noise=cfg.noise)
        points, colors = syn.points, syn.colors
        provenance.update(object=cfg.synthetic, marking=cfg.marking, seed=cfg.seed)
        if float(cfg.noise) > 0:  # validated above
            provenance["noise_m"] = float(cfg.noise)
    else:
        raise TergodicError(f"unknown capture source '{cfg.source}'", "use --from FILE or --synthetic OBJECT")
    stages.append(("input", len(points)))
    require(len(points) > 0, "the cloud is empty", "check the input file or the crop box")

    if units == "mm":
        points = points * 1e-3
    finite = np.all(np.isfinite(points), axis=1)
    if colors is not None:
        finite &= np.all(np.isfinite(colors), axis=1)
    if not finite.all():
        bad = int((~finite).sum())
        require(cfg.drop_invalid, f"the cloud has {bad} points with NaN or inf coordinates or colours",
                "remove them, or pass --drop-invalid to drop them")
        points, colors = points[finite], (colors[finite] if colors is not None else None)
        stages.append(("drop invalid", len(points)))
    require(len(points) >= MIN_POINTS, f"the cloud has only {len(points)} points",
            f"give at least {MIN_POINTS} points (check the file or the filters)")
    _check_extent(points, cfg.units, f"{Path(cfg.path).name}: " if cfg.source == "file" and cfg.path else "")

    keep = np.ones(len(points), bool)
    if cfg.crop is not None:
        box = np.asarray(cfg.crop, dtype=float)
        keep &= np.all((points >= box[:3]) & (points <= box[3:]), axis=1)  # passthrough
        stages.append(("crop", int(keep.sum())))
        require(keep.sum() >= MIN_POINTS, f"only {int(keep.sum())} points are inside the crop box",
                "widen --crop xmin,ymin,zmin,xmax,ymax,zmax (metres)")
    if cfg.outliers is not None:
        idx = np.flatnonzero(keep)
        inl = remove_statistical_outliers(points[idx], int(cfg.outliers[0]), float(cfg.outliers[1]))
        keep[idx[~inl]] = False
        stages.append(("outliers", int(keep.sum())))
    points = points[keep]
    colors = colors[keep] if colors is not None else None

    weight = target_weight(colors, target_range, len(points))
    if cfg.voxel_rule != "intensity":  # the marking only: faint ink (and colour noise on the surface) weighs 0
        weight = (weight >= 1.0).astype(np.float64)
    if cfg.voxel > 0:
        points, colors, p = voxel_downsample(points, colors, weight, cfg.voxel, cfg.voxel_rule)
        stages.append((f"voxel {cfg.voxel * 1e3:g} mm", len(points)))
    if cfg.voxel <= 0:
        p = weight
        n_dup = count_duplicates(points)
        require(n_dup == 0, f"the cloud has {n_dup} duplicate points",
                "merge them with a voxel filter (--voxel 0.003) or remove them from the file")
    if cfg.drop_isolated and len(points) > ISOLATED_MIN:
        lone = isolated_points(points)
        if lone.any():
            points, p = points[~lone], p[~lone]
            colors = colors[~lone] if colors is not None else None
            stages.append(("isolated", len(points)))
    require(len(points) >= MIN_POINTS, f"only {len(points)} points remain after filtering",
            "use a smaller --voxel or a wider --crop")
    n_target = int((p > 0).sum())
    _require_target(n_target, cfg)

    h = mean_spacing(points)
    if len(points) > cfg.max_points:  # the basis' points: a dense cloud's are its 3 mm stand-ins
        n, m = len(points), basis_size(points, h, BASIS_NK, BASIS_NEIGHBORS)
        if m > cfg.max_points:
            on_event(f"warning: {_points_phrase(n, m)} after filtering, above the {cfg.max_points:,}-point "
                     f"limit: precompute would need {_size_estimate(n, m)}; use a coarser --voxel "
                     f"(e.g. 0.003), or --max-points {m} to accept")
    lo, hi = points.min(axis=0), points.max(axis=0)
    from tergodic_cli.provenance import library_versions  # importlib.metadata: only when recorded

    meta = {
        "kind": "tergodic.capture", "format_version": 1, "units": "m", "input_units": cfg.units,
        "provenance": provenance,
        "config": cfg.to_dict(),
        "filters": [{"stage": name, "points": n} for name, n in stages],
        "counts": {"input": stages[0][1], "output": len(points), "target": n_target},
        "target": {"spec": cfg.target, "voxel_rule": cfg.voxel_rule if cfg.voxel > 0 else "per-point",
                   "share": n_target / len(points), "mass": float(p.sum())},
        "spacing_h_m": h, "extent_m": (hi - lo).tolist(), "bbox_m": [lo.tolist(), hi.tolist()],
        "seed": cfg.seed, "seconds": time.perf_counter() - t0, "versions": library_versions(),
    }
    return Capture(points, colors, p, meta, mesh=mesh)


#: Meshes, whatever their content; a .ply is a mesh when its header declares faces.
MESH_ONLY_SUFFIXES = (".obj", ".stl", ".glb", ".gltf", ".off")
#: Spacing of the samples on a mesh when the voxel grid is off, metres.
MESH_SPACING = 0.003


def is_mesh_file(path) -> bool:
    """Whether ``capture --from path`` reads a triangle mesh (and samples it) rather than a cloud.

    Parameters
    ----------
    path : str or Path or None

    Returns
    -------
    bool
        True for .obj, .stl, .glb/.gltf, .off, and a .ply whose header declares faces.
    """
    from tergodic_cli.capture.mesh import ply_has_faces

    if path is None:
        return False
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in MESH_ONLY_SUFFIXES:
        return True
    if suffix != ".ply" or not path.is_file():
        return False
    try:
        return ply_has_faces(path)
    except OSError:
        return False  # the cloud reader says why it cannot read it


#: Uniform samples of a mesh's surface on which its marking is looked for before the real sampling.
PRECHECK_SAMPLES = 20_000


def _require_target(n_target: int, cfg: CaptureConfig) -> None:
    require(n_target > 0 or cfg.allow_empty_target, f"no points match the target colour '{cfg.target}'",
            "check --target (e.g. --target red, hsv:H1-H2,SMIN,VMIN) or use --target all")


def _sample_mesh_file(cfg: CaptureConfig, target_range=None):
    """A mesh file sampled into a cloud: points (n, 3) m, colours or None, (vertices m, triangles), provenance."""
    from tergodic_cli.capture.mesh import read_mesh, sample_mesh, uniform_colors
    from tergodic_cli.progress import Spinner

    mesh = read_mesh(cfg.path, "--from")
    if cfg.units == "mm":
        mesh = mesh.transformed(1e-3)
    # the units are judged before sampling: a millimetre mesh read as metres would need millions of samples
    _check_extent(mesh.vertices, cfg.units, f"{Path(cfg.path).name}: ")
    # ... and the marking, on a quick uniform sample: the Poisson-disk sampling of a large mesh takes
    # minutes, and a wrong --target found after it wasted them (the 1.65 m duck of pybullet_data: 8 min)
    area = mesh.area
    if area > 0:
        colors = uniform_colors(mesh, PRECHECK_SAMPLES, cfg.seed)
        _require_target(int((target_weight(colors, target_range, PRECHECK_SAMPLES) > 0).sum()), cfg)
    spacing = float(cfg.voxel) if cfg.voxel > 0 else MESH_SPACING
    with Spinner(f"sampling the {area:.3g} m² mesh at {spacing * 1e3:.3g} mm"):
        sample = sample_mesh(mesh, spacing, seed=cfg.seed)
    colour = "texture" if mesh.textures and mesh.corner_uvs is not None else ("vertex" if mesh.vertex_colors is not None else "none")
    info = {"vertices": len(mesh.vertices), "triangles": len(mesh.triangles), "area_m2": area,
            "sample_spacing_m": spacing, "samples": len(sample.points), "colour": colour, "seed": cfg.seed}
    return sample.points, sample.colors, (mesh.vertices, mesh.triangles.astype(np.int64)), info


def _validate_config(cfg: CaptureConfig) -> None:
    check_seed(cfg.seed)
    noise = check_noise(cfg.noise)
    require(noise == 0 or cfg.source == "synthetic", f"--noise is for --synthetic objects, not a {cfg.source} cloud",
            "drop --noise (a camera's or a file's cloud has its own noise)")
    require(cfg.units in ("m", "mm"), f"unknown --units '{cfg.units}'", "use m or mm")
    require(cfg.voxel >= 0 and np.isfinite(cfg.voxel), f"--voxel {cfg.voxel} is not a size", "give the voxel edge in metres, e.g. 0.003")
    require(cfg.voxel < 1.0, f"--voxel {cfg.voxel} m is larger than any tabletop object",
            "give the voxel edge in metres, e.g. 0.003 (not millimetres)")
    require(cfg.voxel_rule in VOXEL_RULES, f"unknown --voxel-rule '{cfg.voxel_rule}'", f"use one of {', '.join(VOXEL_RULES)}")
    require(cfg.colour_depth in (None, 8, 16), f"--colour-depth {cfg.colour_depth} is not supported", "use --colour-depth 8 or 16")
    require(cfg.max_points >= 1, f"--max-points {cfg.max_points} is not a point count", "e.g. --max-points 1000000")
    if cfg.crop is not None:
        box = np.asarray(cfg.crop, dtype=float)
        require(box.shape == (6,) and np.all(box[:3] < box[3:]), "--crop needs xmin,ymin,zmin,xmax,ymax,zmax with min < max",
                "e.g. --crop -0.2,-0.2,0,0.2,0.2,0.3 (metres)")
    if cfg.outliers is not None:
        require(cfg.outliers[0] >= 1 and cfg.outliers[1] > 0, "--outliers needs NB,STD with NB >= 1 and STD > 0", "e.g. --outliers 20,2.0")


def _check_extent(points: np.ndarray, units: str, label: str = "") -> None:
    """Refuse a cloud whose span says the units are wrong; only then is the message about units."""
    extent = float(np.ptp(points, axis=0).max())
    require(extent <= CORRUPT_EXTENT_M, f"{label}the cloud spans {extent:.3g} m, too large even for millimetres "
            "(corrupt values in the file?)", "check the file's body, or --crop away the stray points (metres)")
    require(extent <= MAX_EXTENT_M, f"{label}the cloud spans {extent:.3g} m, which looks like millimetres read as metres",
            "pass --units mm" if units == "m" else "check the file's units")
    require(extent != 0.0, f"{label}all {len(points)} points are identical", "check the file: it holds one point repeated")
    require(extent >= DEGENERATE_EXTENT_M, f"{label}the cloud spans only {extent:.3g} m, too small even for metres read as "
            "millimetres (nearly identical or corrupt points)", "check the file's body")
    require(extent >= MIN_EXTENT_M, f"{label}the cloud spans only {extent * 1e3:.3g} mm, which looks like metres read as "
            "millimetres", "pass --units m" if units == "mm" else "check the file's units")


def _points_phrase(n: int, m: int) -> str:
    return f"{n:,} points" if m == n else f"{n:,} points ({m:,} 3 mm stand-ins carry the basis)"


def _size_estimate(n: int, m: int | None = None) -> str:
    """What precompute would roughly need at nK = 200 for ``n`` points whose basis is on ``m`` of them
    (default all), e.g. "~1.6 GB and over 28 s"."""
    m = n if m is None else m
    gb, seconds = m * BYTES_PER_POINT / 1e9, m * SECONDS_PER_POINT
    if m < n:  # a dense cloud on stand-ins: every point costs its key, spacing and map
        gb, seconds = gb + n * BYTES_PER_DENSE_POINT / 1e9, seconds + n * SECONDS_PER_DENSE_POINT
    memory = f"~{gb:.1f} GB" if gb >= 1 else f"~{max(gb * 1e3, 1):.0f} MB"
    return f"{memory} and over {seconds / 60:.0f} min" if seconds >= 60 else f"{memory} and over {max(seconds, 1):.0f} s"


def check_size(where, n: int, limit: int, m: int | None = None) -> None:
    """Refuse a cloud too large to precompute in reasonable memory and time, unless the limit allows it.

    Parameters
    ----------
    where : str or Path
        The capture, for the message.
    n : int
        Its points.
    limit : int
        The ``--max-points`` limit, on the points the basis is computed on.
    m : int, optional
        Those points (``filters.basis_size``): a dense cloud's 3 mm stand-ins; default all ``n``.
    """
    m = n if m is None else m
    require(m <= limit, f"{where} has {_points_phrase(n, m)}, above the {limit:,}-point limit: precompute would need "
            f"{_size_estimate(n, m)}", f"re-capture with a coarser --voxel (e.g. 0.003), or pass --max-points {m}")
