"""The capture artefact on disk.

A capture folder holds:

- ``cloud.npz``: ``points`` (n, 3) float64 metres, ``colors`` (n, 3) float32 in [0, 1]
  (absent for colourless clouds), ``target`` (n,) float64, the per-point target weight p in [0, 1];
- ``cloud.ply``: the same points and colours, for any point-cloud viewer;
- ``mesh.npz`` (a capture sampled from a triangle mesh only): ``vertices`` (n, 3) float64 metres in
  the frame of ``points`` and ``triangles`` (k, 3) int64, checksummed in the sidecar like ``cloud.npz``;
- ``capture.json``: the sidecar: provenance, units, filters with counts, target rule,
  target share, spacing h, extent, seed, library versions, and the sha256 of ``cloud.npz``;
- ``config.json``: the configs that made it (``tergodic capture --config CAP/config.json`` repeats it).

The folder is built beside its target and renamed into place when complete.
``capture.json`` carries ``sidecar_sha256``, a checksum of its own content, so a stub or
an edited sidecar is refused by :func:`load_capture`, like a changed ``cloud.npz``.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tergodic_cli.atomic import AtomicFolder, _json_default, file_sha256
from tergodic_cli.capture.readers import write_ply
from tergodic_cli.config import CONFIG_FILE, write_config
from tergodic_cli.errors import TergodicError, os_error, require

SIDECAR = "capture.json"
ARRAYS = "cloud.npz"
MESH = "mesh.npz"
#: The sidecar's own checksum: a stub or an edited capture.json is refused on load.
SIDECAR_SHA = "sidecar_sha256"


@dataclass
class Capture:
    """A captured cloud: points (n, 3) metres, colours (n, 3) or None, target weight p (n,).

    ``mesh``: the triangle mesh the cloud was sampled from, (vertices (m, 3) float64 metres in the
    frame of ``points``, triangles (k, 3) int64), or None for a cloud read or seen by a camera.
    """

    points: np.ndarray
    colors: np.ndarray | None
    target: np.ndarray
    meta: dict = field(default_factory=dict)
    mesh: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def n_points(self) -> int:
        return len(self.points)


#: The files a capture folder may hold; --overwrite replaces only a folder of these.
CAPTURE_FILES = frozenset({ARRAYS, MESH, "cloud.ply", SIDECAR, "camera_rgb.png", "config.json"})
#: The kind of a capture's ``config.json``.
CAPTURE_CONFIG_KIND = "tergodic.capture_config"


def _folder(out: str | Path, overwrite: bool) -> AtomicFolder:
    return AtomicFolder(out, overwrite, "--out", what="capture", owned=CAPTURE_FILES.__contains__)


def check_out_folder(out: str | Path, overwrite: bool) -> None:
    """Refuse an ``--out`` that cannot take a capture, before any work: a file, a folder of
    other files, an existing capture without ``overwrite``, or an unwritable parent.

    Parameters
    ----------
    out : str or Path
        The capture folder to be.
    overwrite : bool
        An existing capture there may be replaced.
    """
    _folder(out, overwrite).check()


def save_capture(capture: Capture, out_dir: str | Path, overwrite: bool = True, extra=None,
                 config: dict | None = None) -> Path:
    """Write ``capture`` into ``out_dir``.

    The folder is built in a temporary sibling and renamed into place when complete, so an
    error leaves no partial folder and an existing capture untouched (replaced only with
    ``overwrite``).

    Parameters
    ----------
    capture : Capture
        The cloud, its target and its sidecar ``meta``.
    out_dir : str or Path
        The capture folder.
    overwrite : bool
        Replace an existing capture folder.
    extra : callable, optional
        ``extra(folder)`` adds files (e.g. the camera image) before the rename.
    config : dict, optional
        Sections of a loadable ``config.json`` (section name -> config dataclass), written with
        :data:`CAPTURE_CONFIG_KIND`.

    Returns
    -------
    Path
        The sidecar ``out_dir/capture.json``.
    """
    arrays = {"points": capture.points.astype(np.float64), "target": capture.target.astype(np.float64)}
    if capture.colors is not None:
        arrays["colors"] = capture.colors.astype(np.float32)
    with _folder(out_dir, overwrite) as tmp:
        np.savez(tmp / ARRAYS, **arrays)  # the name ends in .npz: numpy adds no suffix
        write_ply(tmp / "cloud.ply", capture.points, capture.colors)
        if extra is not None:
            extra(tmp)
        if config is not None:
            write_config(tmp / CONFIG_FILE, CAPTURE_CONFIG_KIND, **config)
        meta = dict(capture.meta)
        meta.pop(SIDECAR_SHA, None)
        meta.pop("mesh", None)
        meta["arrays"] = {"file": ARRAYS, "sha256": file_sha256(tmp / ARRAYS)}
        if capture.mesh is not None:
            vertices, triangles = capture.mesh
            np.savez(tmp / MESH, vertices=np.asarray(vertices, dtype=np.float64), triangles=np.asarray(triangles, dtype=np.int64))
            meta["mesh"] = {"file": MESH, "sha256": file_sha256(tmp / MESH), "vertices": len(vertices), "triangles": len(triangles)}
        meta = json.loads(json.dumps(meta, default=_json_default))  # what a reader will see
        meta[SIDECAR_SHA] = sidecar_checksum(meta)
        (tmp / SIDECAR).write_text(json.dumps(meta, indent=2) + "\n")
    capture.meta = meta
    return Path(out_dir) / SIDECAR


def load_capture(path: str | Path) -> Capture:
    """Load a capture folder, verifying the sidecar and its arrays.

    Parameters
    ----------
    path : str or Path
        The capture folder, or its ``capture.json``.

    Returns
    -------
    Capture
        Points (n, 3) m, colours (n, 3) in [0, 1] or None, target p (n,) in [0, 1], and the sidecar.
    """
    path = Path(path)
    folder = path.parent if path.name == SIDECAR else path
    sidecar = folder / SIDECAR
    rerun = "re-run 'tergodic capture ... --out DIR --overwrite'"
    require(sidecar.exists(), f"{folder} is not a capture (no {SIDECAR})", "run 'tergodic capture ... --out DIR' first and pass DIR")
    try:
        meta = json.loads(sidecar.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise TergodicError(f"{sidecar} is not valid JSON", rerun) from None
    except OSError as exc:
        raise os_error(exc, sidecar, "read", "check the capture folder's permissions") from None
    if not isinstance(meta, dict) or SIDECAR_SHA not in meta or not isinstance(meta.get("arrays"), dict):
        raise TergodicError(f"{sidecar} is a stub or from an older tergodic (no checksum)", rerun)
    require(meta[SIDECAR_SHA] == sidecar_checksum(meta), f"{sidecar} was edited (its checksum does not match its content)", rerun)
    arrays = folder / ARRAYS
    require(arrays.exists(), f"{folder} has no {ARRAYS}", rerun)
    try:
        actual = file_sha256(arrays)
    except OSError as exc:
        raise os_error(exc, arrays, "read", "check the capture folder's permissions") from None
    require(meta["arrays"].get("sha256") == actual, f"{arrays} does not match the checksum in {SIDECAR} (modified?)", rerun)
    try:
        with np.load(arrays, allow_pickle=False) as data:
            points = np.asarray(data["points"], dtype=np.float64)
            target = np.asarray(data["target"], dtype=np.float64)
            colors = np.asarray(data["colors"], dtype=np.float64) if "colors" in data.files else None
    except Exception as exc:
        raise TergodicError(f"{arrays} is unreadable ({type(exc).__name__})", rerun) from None
    require(points.ndim == 2 and points.shape[1] == 3 and target.shape == (len(points),),
            f"{arrays} has inconsistent shapes", rerun)
    mesh = _load_mesh(folder, meta, rerun) if "mesh" in meta else None
    return Capture(points, colors, target, meta, mesh=mesh)


def _load_mesh(folder: Path, meta: dict, rerun: str) -> tuple[np.ndarray, np.ndarray]:
    """The capture's ``mesh.npz``, checked against the sidecar: (vertices (n, 3) m, triangles (k, 3) int64)."""
    entry = meta["mesh"]
    path = folder / MESH
    require(isinstance(entry, dict), f"{folder / SIDECAR} has a malformed 'mesh' entry", rerun)
    require(path.exists(), f"{folder} has no {MESH} (its {SIDECAR} lists one)", rerun)
    try:
        actual = file_sha256(path)
    except OSError as exc:
        raise os_error(exc, path, "read", "check the capture folder's permissions") from None
    require(entry.get("sha256") == actual, f"{path} does not match the checksum in {SIDECAR} (modified?)", rerun)
    try:
        with np.load(path, allow_pickle=False) as data:
            vertices, triangles = data["vertices"], data["triangles"]
    except Exception as exc:
        raise TergodicError(f"{path} is unreadable ({type(exc).__name__})", rerun) from None
    require(vertices.ndim == 2 and vertices.shape[1] == 3 and vertices.dtype.kind == "f"
            and triangles.ndim == 2 and triangles.shape[1] == 3 and triangles.dtype.kind in "iu" and len(triangles) > 0
            and (len(vertices), len(triangles)) == (entry.get("vertices"), entry.get("triangles")),
            f"{path} has inconsistent shapes or types", rerun)
    vertices, triangles = vertices.astype(np.float64), triangles.astype(np.int64)
    require(bool(np.all(np.isfinite(vertices))) and triangles.min() >= 0 and triangles.max() < len(vertices),
            f"{path} has non-finite vertices or face indices outside its vertex list", rerun)
    return vertices, triangles


def sidecar_checksum(meta: dict) -> str:
    """The sidecar's checksum.

    Parameters
    ----------
    meta : dict
        The sidecar's content.

    Returns
    -------
    str
        sha256 (hex) of the content without its own checksum field, as canonical JSON.
    """
    body = {k: v for k, v in meta.items() if k != SIDECAR_SHA}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode()).hexdigest()

