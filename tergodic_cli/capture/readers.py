"""Readers for point-cloud files: PLY, PCD, XYZ/XYZRGB text and NPZ.

Every reader returns ``(points, colors)``: points float64 (n, 3) in the file's
units, colours float64 (n, 3) in [0, 1] or ``None`` when the file has none.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tergodic_cli.errors import TergodicError

SUPPORTED = (".ply", ".pcd", ".xyz", ".xyzrgb", ".txt", ".npz")


def read_cloud(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a coloured point cloud from ``path`` (format from the extension)."""
    path = Path(path)
    if not path.exists():
        raise TergodicError(f"no such file: {path}", "check the path given to --from")
    if not path.is_file():
        raise TergodicError(f"not a file: {path}", "give a PLY, PCD, XYZRGB or NPZ file to --from")
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED:
        raise TergodicError(
            f"unknown point-cloud extension '{suffix}' for {path.name}",
            f"use one of {', '.join(SUPPORTED)}",
        )
    try:
        with open(path, "rb") as fh:
            head = fh.read(64)
    except OSError as exc:
        raise TergodicError(f"cannot read {path}: {exc.strerror}", "check the file's permissions") from None
    if not head:
        raise TergodicError(f"{path.name} is an empty file", "re-export the point cloud")
    if suffix in (".ply", ".pcd"):
        return _read_open3d(path, head)
    if suffix == ".npz":
        return _read_npz(path)
    return _read_text(path)


def _read_open3d(path: Path, head: bytes) -> tuple[np.ndarray, np.ndarray | None]:
    if path.suffix.lower() == ".ply" and not head.startswith(b"ply"):
        raise TergodicError(f"{path.name} is not a valid PLY (no 'ply' header)", "re-export it as PLY")
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    pcd = o3d.io.read_point_cloud(str(path))
    points = np.asarray(pcd.points, dtype=np.float64)
    if len(points) == 0:
        raise TergodicError(
            f"{path.name} holds no readable points (corrupt or truncated file?)",
            "re-export the cloud; PLY needs x, y, z vertex properties",
        )
    _check_truncated_ply(path, head, len(points))
    colors = np.asarray(pcd.colors, dtype=np.float64) if pcd.has_colors() else None
    return points, colors


_PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
              "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def _check_truncated_ply(path: Path, head: bytes, n_read: int) -> None:
    """open3d reads a truncated PLY without failing; compare the header's promise with the file."""
    if path.suffix.lower() != ".ply":
        return
    with open(path, "rb") as fh:
        blob = fh.read(8192)
    end = blob.find(b"end_header")
    if end < 0:
        raise TergodicError(f"{path.name} has no PLY end_header line (corrupt?)", "re-export it as PLY")
    header_len = blob.index(b"\n", end) + 1
    lines = blob[:end].decode("ascii", "replace").splitlines()
    fmt, elements = "", []  # [(count, row_bytes or None when rows vary)]
    for line in lines:
        parts = line.split()
        if parts[:1] == ["format"] and len(parts) > 1:
            fmt = parts[1]
        elif parts[:1] == ["element"] and len(parts) == 3:
            elements.append([int(parts[2]), 0])
        elif parts[:1] == ["property"] and elements:
            size = _PLY_SIZES.get(parts[1]) if parts[1] != "list" else None
            elements[-1][1] = None if size is None or elements[-1][1] is None else elements[-1][1] + size
    declared = elements[0][0] if elements else n_read
    if fmt.startswith("binary") and all(row is not None for _, row in elements):
        expected = header_len + sum(count * row for count, row in elements)
        actual = path.stat().st_size
        if actual < expected:
            raise TergodicError(f"{path.name} is truncated: {actual} of {expected} bytes", "re-export the cloud")
    elif declared != n_read:
        raise TergodicError(f"{path.name} declares {declared} vertices but {n_read} could be read (truncated?)",
                            "re-export the cloud")


def _read_npz(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    try:
        with np.load(path, allow_pickle=False) as data:
            if "points" not in data.files:
                raise TergodicError(f"{path.name} has no 'points' array", "save the cloud with np.savez(points=..., colors=...)")
            points = np.asarray(data["points"], dtype=np.float64)
            colors = np.asarray(data["colors"], dtype=np.float64) if "colors" in data.files else None
    except TergodicError:
        raise
    except Exception as exc:  # zipfile/ValueError: corrupt archive or object arrays
        raise TergodicError(f"{path.name} is not a readable NPZ ({type(exc).__name__})", "re-save it with np.savez") from None
    if points.ndim != 2 or points.shape[1] != 3:
        raise TergodicError(f"'points' in {path.name} has shape {points.shape}, expected (n, 3)", "store points as an (n, 3) array")
    return points, _normalise_colors(colors, len(points), path.name)


def _read_text(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    try:
        table = np.loadtxt(path, dtype=np.float64, ndmin=2, comments=("#", "//"))
    except ValueError as exc:
        raise TergodicError(f"{path.name} is not a numeric XYZ/XYZRGB table ({exc})", "one point per line: x y z [r g b]") from None
    if table.size == 0:
        raise TergodicError(f"{path.name} holds no points", "one point per line: x y z [r g b]")
    if table.shape[1] not in (3, 6):
        raise TergodicError(f"{path.name} has {table.shape[1]} columns", "use 3 (x y z) or 6 (x y z r g b) columns")
    colors = table[:, 3:6] if table.shape[1] == 6 else None
    return table[:, :3].copy(), _normalise_colors(colors, len(table), path.name)


def _normalise_colors(colors: np.ndarray | None, n: int, name: str) -> np.ndarray | None:
    if colors is None:
        return None
    if colors.shape != (n, 3):
        raise TergodicError(f"colours in {name} have shape {colors.shape}, expected ({n}, 3)", "give one RGB triple per point")
    if not np.all(np.isfinite(colors)):
        raise TergodicError(f"colours in {name} contain NaN or inf", "fix the colour channels")
    # 0..255 integers are common in text and NPZ files.
    return colors / 255.0 if colors.max(initial=0.0) > 1.0 else colors


def write_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None) -> None:
    """Write a binary little-endian PLY (double xyz, uchar rgb), the reference clouds' layout."""
    from tergodic_cli.atomic import atomic_path

    n = len(points)
    props = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}",
              "property double x", "property double y", "property double z"]
    if colors is not None:
        props += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header.append("end_header")
    rec = np.empty(n, dtype=props)
    rec["x"], rec["y"], rec["z"] = points[:, 0], points[:, 1], points[:, 2]
    if colors is not None:
        rgb = np.clip(np.rint(colors * 255.0), 0, 255).astype(np.uint8)
        rec["red"], rec["green"], rec["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    with atomic_path(path, suffix=".ply") as tmp:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode("ascii"))
            fh.write(rec.tobytes())
