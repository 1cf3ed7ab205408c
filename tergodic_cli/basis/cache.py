"""The on-disk basis cache, keyed by geometry content.

Key: sha256 over the format version, every basis parameter, and the cloud's points
in a *canonical frame* (centroid at the origin, principal axes as x, y, z, each axis
signed by its third moment), quantised to 1 µm and sorted. A rigid motion of the same
points, or a new target on them, gives the same key, so the basis is reused; the
cached arrays are stored in canonical order and mapped back to the caller's order.

When the canonical frame is ambiguous (an exactly symmetric point set: equal
principal variances or zero third moments), the key falls back to the points as
given, which still hits for a changed target but not across a rigid motion.

Files: ``<cache>/basis/<key>/<array>.npy`` (plain ``.npy``, never pickles, loaded
with ``allow_pickle=False``) and ``basis.json`` (config, timings, versions and a
CRC-32 of every array). A missing, corrupt or edited entry is reported, discarded
and recomputed. (CRC-32 detects corruption and edits; it is not a cryptographic seal,
and it keeps a warm load within a few tens of milliseconds.)
"""

from __future__ import annotations

import hashlib
import json
import zlib
import os
import shutil
import tempfile
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from tergodic_cli import FORMAT_VERSION
from tergodic_cli.basis.core import Basis, compute_basis

QUANTUM_M = 1e-6
_DEGENERATE = 1e-7


@dataclass(frozen=True)
class BasisConfig:
    """Parameters of a basis; all of them are part of the cache key."""

    nk: int = 200
    neighbors: int = 30
    solver: str = "lanczos-interior-shift"


def default_cache_dir() -> Path:
    """``$TERGODIC_CACHE_DIR``, else ``$XDG_CACHE_HOME/tergodic``, else ``~/.cache/tergodic``."""
    if os.environ.get("TERGODIC_CACHE_DIR"):
        return Path(os.environ["TERGODIC_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "tergodic"


def canonical_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """Centroid (3,), rotation R (3, 3) whose rows are the canonical axes, and whether
    the frame is well defined (rigid-motion invariant)."""
    centroid = points.mean(axis=0)
    centred = points - centroid
    cov = centred.T @ centred / len(points)
    w, v = np.linalg.eigh(cov)
    w, v = w[::-1], v[:, ::-1]  # largest variance first
    proj = centred @ v
    third = (proj**3).mean(axis=0)
    sigma = np.sqrt(np.maximum(w, 1e-300))
    gaps_ok = (w[0] - w[1]) > _DEGENERATE * w[0] and (w[1] - w[2]) > _DEGENERATE * w[0]
    skew_ok = bool(np.all(np.abs(third) > _DEGENERATE * sigma**3))
    signs = np.where(third < 0, -1.0, 1.0)
    R = (v * signs).T
    if np.linalg.det(R) < 0:  # keep a proper rotation; the third axis follows the other two
        R[2] *= -1
    return centroid, R, bool(gaps_ok and skew_ok)


def geometry_key(points: np.ndarray, cfg: BasisConfig) -> tuple[str, np.ndarray, bool]:
    """Cache key, the permutation that puts ``points`` into canonical order, and rigid invariance."""
    key, order, invariant, _ = _geometry(points, cfg)
    return key, order, invariant


def _geometry(points: np.ndarray, cfg: BasisConfig) -> tuple[str, np.ndarray, bool, np.ndarray]:
    """Key, canonical order, invariance and the canonical coordinates (n, 3) in canonical order."""
    centroid, R, invariant = canonical_frame(points)
    canon = (points - centroid) @ R.T if invariant else points
    q = np.rint(canon / QUANTUM_M).astype(np.int64)
    order = np.lexsort((q[:, 2], q[:, 1], q[:, 0]))
    h = hashlib.sha256()
    h.update(json.dumps({"format": FORMAT_VERSION, "invariant": invariant, **asdict(cfg)}, sort_keys=True).encode())
    h.update(np.ascontiguousarray(q[order]).tobytes())
    return h.hexdigest()[:32], order, invariant, canon[order]


def _checksums(arrays: dict[str, np.ndarray]) -> dict[str, str]:
    """CRC-32 of each array's dtype, shape and bytes (read through a memoryview: no copy)."""
    out = {}
    for name, a in arrays.items():
        a = np.require(a, requirements="C")  # (ascontiguousarray would turn 0-d into 1-d)
        crc = zlib.crc32(f"{a.dtype.str}{a.shape}".encode())
        out[name] = f"{zlib.crc32(memoryview(a).cast('B'), crc):08x}"
    return out


def _to_arrays(basis: Basis, order: np.ndarray, canon: np.ndarray) -> dict[str, np.ndarray]:
    L = basis.L[order][:, order].tocsr()
    return {
        "canonical_points": canon,
        "evals": basis.evals,
        "evecs": basis.evecs[order],
        "mass": basis.mass[order],
        "L_data": L.data,
        "L_indices": L.indices,
        "L_indptr": L.indptr,
        "h": np.array(basis.h),
    }


def _from_arrays(arrays: dict[str, np.ndarray], points: np.ndarray, order: np.ndarray, meta: dict) -> Basis:
    n = len(points)
    L = sp.csr_matrix((arrays["L_data"], arrays["L_indices"], arrays["L_indptr"]), shape=(n, n))
    if np.array_equal(order, np.arange(n)):  # the caller's order is the canonical one: no copies
        return Basis(points, L, arrays["mass"], arrays["evals"], arrays["evecs"], float(arrays["h"]), meta)
    inv = np.empty_like(order)
    inv[order] = np.arange(n)
    return Basis(points, L[inv][:, inv].tocsr(), arrays["mass"][inv], arrays["evals"], arrays["evecs"][inv],
                 float(arrays["h"]), meta)


class CacheMiss(Exception):
    """The entry is absent; the message says why when it was present but unusable."""


_ARRAY_NAMES = ("canonical_points", "evals", "evecs", "mass", "L_data", "L_indices", "L_indptr", "h")


def _load_entry(entry: Path, points: np.ndarray, order: np.ndarray, canon: np.ndarray) -> Basis:
    meta_path = entry / "basis.json"
    if not meta_path.exists():
        raise CacheMiss("")
    try:
        meta = json.loads(meta_path.read_text())
        arrays = {name: np.load(entry / f"{name}.npy", allow_pickle=False) for name in _ARRAY_NAMES}
    except Exception as exc:
        raise CacheMiss(f"unreadable ({type(exc).__name__})") from None
    if _checksums(arrays) != meta.get("checksums"):
        raise CacheMiss("checksum mismatch (corrupt or modified)")
    # Guard against key collisions: the cached geometry must be this geometry.
    cached = arrays["canonical_points"]
    if cached.shape != canon.shape or np.abs(cached - canon).max() > 10 * QUANTUM_M:
        raise CacheMiss("geometry does not match its key")
    return _from_arrays(arrays, points, order, meta)


def get_basis(points: np.ndarray, cfg: BasisConfig, cache_dir: str | Path | None = None, force: bool = False,
              on_event=None) -> tuple[Basis, bool]:
    """Load the basis for ``points`` from the cache, or compute and store it.

    Parameters
    ----------
    points : (n, 3) float64, metres.
    cfg : basis parameters.
    cache_dir : cache root (default :func:`default_cache_dir`).
    force : recompute even when a valid entry exists.
    on_event : optional callable(str) for warnings and progress messages.

    Returns
    -------
    (basis, hit) where ``hit`` is True when nothing was recomputed.
    """
    say = on_event or (lambda msg: warnings.warn(msg, stacklevel=2))
    t0 = time.perf_counter()
    key, order, invariant, canon = _geometry(points, cfg)
    entry = Path(cache_dir or default_cache_dir()) / "basis" / key
    timings = {"key_ms": 1e3 * (time.perf_counter() - t0)}
    if not force:
        try:
            t = time.perf_counter()
            basis = _load_entry(entry, points, order, canon)
            basis.meta["timings_load"] = {**timings, "load_ms": 1e3 * (time.perf_counter() - t)}
            basis.meta["path"] = str(entry)
            return basis, True
        except CacheMiss as miss:
            if str(miss):
                say(f"warning: cached basis {entry} is unusable: {miss}; recomputing")
    from tergodic_cli.progress import Spinner

    with Spinner(f"computing basis: Laplacian + {cfg.nk} eigenpairs of {len(points)} points"):
        basis = compute_basis(points, cfg.nk, cfg.neighbors, timings)
    from tergodic_cli.provenance import library_versions

    t = time.perf_counter()
    arrays = _to_arrays(basis, order, canon)
    meta = {
        "kind": "tergodic.basis",
        "format_version": FORMAT_VERSION,
        "key": key,
        "config": asdict(cfg),
        "n_points": len(points),
        "rigid_invariant": invariant,
        "h_m": basis.h,
        "lambda_range": [float(basis.evals[0]), float(basis.evals[-1])],
        "timings": timings,
        "versions": library_versions(),
        "checksums": _checksums(arrays),
    }
    _write_entry(entry, arrays, meta)
    timings["write_ms"] = 1e3 * (time.perf_counter() - t)
    meta["path"] = str(entry)
    basis.meta = meta
    return basis, False


def _write_entry(entry: Path, arrays: dict[str, np.ndarray], meta: dict) -> None:
    """Write into a temporary sibling folder, then rename it into place (atomic)."""
    entry.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{entry.name}.", dir=entry.parent))
    try:
        for name, array in arrays.items():
            np.save(tmp / f"{name}.npy", np.require(array, requirements="C"), allow_pickle=False)
        (tmp / "basis.json").write_text(json.dumps(meta, indent=2) + "\n")
        if entry.exists():
            shutil.rmtree(entry)
        os.replace(tmp, entry)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
