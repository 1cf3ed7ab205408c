"""The capture artefact on disk.

A capture folder holds:

- ``cloud.npz``: ``points`` (n, 3) float64 metres, ``colors`` (n, 3) float32 in [0, 1]
  (absent for colourless clouds), ``target`` (n,) float64, the per-point target weight p in [0, 1];
- ``cloud.ply``: the same points and colours, for any point-cloud viewer;
- ``capture.json``: the sidecar: provenance, units, filters with counts, target rule,
  target share, spacing h, extent, seed, library versions, and the sha256 of ``cloud.npz``.

``capture.json`` is written last, so a folder without it is not a capture.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tergodic_cli.atomic import write_json, write_npz
from tergodic_cli.errors import TergodicError

SIDECAR = "capture.json"
ARRAYS = "cloud.npz"


@dataclass
class Capture:
    """A captured cloud: points (n, 3) metres, colours (n, 3) or None, target weight p (n,)."""

    points: np.ndarray
    colors: np.ndarray | None
    target: np.ndarray
    meta: dict = field(default_factory=dict)

    @property
    def n_points(self) -> int:
        return len(self.points)


def save_capture(capture: Capture, out_dir: str | Path) -> Path:
    """Write ``capture`` into ``out_dir`` (created if needed); returns the sidecar path."""
    from tergodic_cli.capture.readers import write_ply

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise TergodicError(f"--out {out} exists and is not a folder", "give a folder path for the capture")
    arrays = {"points": capture.points.astype(np.float64), "target": capture.target.astype(np.float64)}
    if capture.colors is not None:
        arrays["colors"] = capture.colors.astype(np.float32)
    write_npz(out / ARRAYS, **arrays)
    write_ply(out / "cloud.ply", capture.points, capture.colors)
    meta = dict(capture.meta)
    meta["arrays"] = {"file": ARRAYS, "sha256": _sha256(out / ARRAYS)}
    write_json(out / SIDECAR, meta)
    capture.meta = meta
    return out / SIDECAR


def load_capture(path: str | Path) -> Capture:
    """Load a capture folder (or its ``capture.json``), verifying its arrays."""
    path = Path(path)
    folder = path.parent if path.name == SIDECAR else path
    sidecar = folder / SIDECAR
    if not sidecar.exists():
        raise TergodicError(f"{folder} is not a capture (no {SIDECAR})", "run 'tergodic capture ... --out DIR' first and pass DIR")
    try:
        meta = json.loads(sidecar.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise TergodicError(f"{sidecar} is not valid JSON", "re-run 'tergodic capture'") from None
    arrays = folder / ARRAYS
    if not arrays.exists():
        raise TergodicError(f"{folder} has no {ARRAYS}", "re-run 'tergodic capture'")
    expected = meta.get("arrays", {}).get("sha256")
    if expected and expected != _sha256(arrays):
        raise TergodicError(f"{arrays} does not match the checksum in {SIDECAR} (modified?)", "re-run 'tergodic capture'")
    try:
        with np.load(arrays, allow_pickle=False) as data:
            points = np.asarray(data["points"], dtype=np.float64)
            target = np.asarray(data["target"], dtype=np.float64)
            colors = np.asarray(data["colors"], dtype=np.float64) if "colors" in data.files else None
    except Exception as exc:
        raise TergodicError(f"{arrays} is unreadable ({type(exc).__name__})", "re-run 'tergodic capture'") from None
    if points.ndim != 2 or points.shape[1] != 3 or target.shape != (len(points),):
        raise TergodicError(f"{arrays} has inconsistent shapes", "re-run 'tergodic capture'")
    return Capture(points, colors, target, meta)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
