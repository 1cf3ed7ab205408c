"""The on-disk basis cache, keyed by geometry content.

Key: BLAKE2b over the format, every basis parameter and the points in a canonical frame (centroid,
principal axes signed by their third moment, quantised to 1 µm, sorted), so a rigid motion or a new
target reuses the basis; an ambiguous frame falls back to the points as given. Files:
``<cache>/basis/<key>/<array>.npy`` (never pickles) and ``basis.json`` with a checksum of every
array, checked on every read; a missing, corrupt or edited entry is reported, discarded and
recomputed. Details: docs/precompute.md, "Warm cache".

The arrays' checksum is BLAKE2b over the array's dtype and shape, the wrapping 64-bit sums of each
run of 4096 words (the "rows"), the 4096 per-position sums across those runs (the "lanes"), and the
few trailing bytes: one pass at memory speed (a warm hit must take under 30 ms). Any change inside
one 8-byte word (a flipped bit or byte) changes its row's sum, so it is always detected; two
swapped words differ in their row or in their lane, so a swap is detected too. It detects
corruption and edits; it is not a cryptographic seal against a deliberate forgery.
"""

from __future__ import annotations

import errno
import hashlib
import json
import math
import os
import shutil
import tempfile
import time
import warnings
from dataclasses import asdict
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from tergodic_cli import FORMAT_VERSION
from tergodic_cli.atomic import check_parent_writable
from tergodic_cli.basis.core import Basis, compute_basis
from tergodic_cli.capture.artefact import SIDECAR_SHA, sidecar_checksum
from tergodic_cli.config import CONFIG_FILE, write_config
from tergodic_cli.errors import os_error, require
from tergodic_cli.progress import Spinner

__all__ = ["BasisConfig", "CacheMiss", "array_checksum", "default_cache_dir", "geometry_key",
           "get_basis"]

QUANTUM_M = 1e-6
_DEGENERATE = 1e-7
#: Layout of a cache entry (files, row order, checksum); part of the key, so entries of an
#: older layout are never read: they are recomputed under their new key.
CACHE_LAYOUT = 4  # 4: the stand-ins of a dense cloud (standin_sel, standin_rep)
_CACHE_OPTION = "--cache-dir (or $TERGODIC_CACHE_DIR)"
#: The kind of a basis entry's ``config.json`` (``tergodic precompute CAPTURE --config`` repeats it).
BASIS_CONFIG_KIND = "tergodic.basis_config"
_BITS = 21  # per axis in the packed sort key: 2**21 µm = 2.1 m of extent


from tergodic_cli.basis.config import SOLVERS, BasisConfig  # noqa: E402  (their home; re-exported here)


def validate_basis_config(cfg: BasisConfig) -> None:
    """Refuse, in one line, a basis config no solver can honour (a name that would only change the key).

    Parameters
    ----------
    cfg : BasisConfig
        nK >= 1, at least 3 neighbours, a solver in :data:`SOLVERS`; else :class:`TergodicError` (exit 2).
    """
    require(cfg.solver in SOLVERS, f"unknown basis solver '{cfg.solver}'", f"use {' or '.join(SOLVERS)}")
    require(isinstance(cfg.nk, int) and cfg.nk >= 1, f"--nk {cfg.nk} must be positive", "e.g. --nk 200")
    require(isinstance(cfg.neighbors, int) and cfg.neighbors >= 3, f"--neighbors {cfg.neighbors} is too small",
            "use at least 3 (default 30)")


def default_cache_dir() -> Path:
    """The cache root.

    Returns
    -------
    Path
        ``$TERGODIC_CACHE_DIR``, else ``$XDG_CACHE_HOME/tergodic``, else ``~/.cache/tergodic``.
    """
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(os.environ.get("TERGODIC_CACHE_DIR") or Path(base) / "tergodic")


def _canonical_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """Centroid, rotation R whose rows are the principal axes each signed by its third moment,
    and whether that frame is well defined (rigid-motion invariant)."""
    centroid = points.mean(axis=0)
    centred = points - centroid
    cov = centred.T @ centred / len(points)
    w, v = np.linalg.eigh(cov)
    w, v = w[::-1], np.ascontiguousarray(v[:, ::-1])  # largest variance first
    proj = centred @ v
    third = np.einsum("ij,ij,ij->j", proj, proj, proj) / len(points)  # (x**3 calls pow: 30x slower)
    sigma = np.sqrt(np.maximum(w, 1e-300))
    gaps_ok = (w[0] - w[1]) > _DEGENERATE * w[0] and (w[1] - w[2]) > _DEGENERATE * w[0]
    skew_ok = bool(np.all(np.abs(third) > _DEGENERATE * sigma**3))
    signs = np.where(third < 0, -1.0, 1.0)
    R = (v * signs).T
    if np.linalg.det(R) < 0:  # keep a proper rotation; the third axis follows the other two
        R[2] *= -1
    return centroid, R, bool(gaps_ok and skew_ok)


def _canonical_order(q: np.ndarray) -> tuple[np.ndarray, bytes]:
    """An order sorting the integer coordinates q (n, 3) by x, y then z, and bytes identifying
    the sorted coordinates. Spans under 2**21 quanta pack into one int64 and sort once (10x
    faster than ``np.lexsort``); points in the same µm cell keep the sort's (deterministic) order."""
    lo = q.min(axis=0)
    span = q.max(axis=0) - lo
    if len(q) and np.all(span < (1 << _BITS)):
        r = q - lo
        packed = (r[:, 0] << (2 * _BITS)) | (r[:, 1] << _BITS) | r[:, 2]
        order = np.argsort(packed)
        return order, b"packed" + lo.tobytes() + packed[order].tobytes()
    order = np.lexsort((q[:, 2], q[:, 1], q[:, 0]))
    return order, b"lexsort" + np.ascontiguousarray(q[order]).tobytes()


def geometry_key(points: np.ndarray, cfg: BasisConfig) -> tuple[str, np.ndarray, bool, np.ndarray]:
    """The cache key of a cloud and basis parameters.

    Parameters
    ----------
    points : (n, 3) float
        Metres.
    cfg : BasisConfig

    Returns
    -------
    key : str
        Hex digest.
    order : (n,) int
        The permutation that puts ``points`` into canonical order.
    invariant : bool
        Whether the key is invariant to rigid motions.
    canon : (n, 3) float
        The canonical coordinates, metres, in canonical order.
    """
    centroid, R, invariant = _canonical_frame(points)
    canon = (points - centroid) @ R.T if invariant else points
    q = np.rint(canon / QUANTUM_M).astype(np.int64)
    order, identity = _canonical_order(q)
    h = hashlib.blake2b(digest_size=16)
    h.update(json.dumps({"format": FORMAT_VERSION, "layout": CACHE_LAYOUT, "invariant": invariant, **asdict(cfg)},
                        sort_keys=True).encode())
    h.update(identity)
    return h.hexdigest(), order, invariant, canon[order]


# ---------------------------------------------------------------------------------------
# Entries

#: Checksum geometry: 64-bit words per "row" (the lanes).
_LANES = 4096


class CacheMiss(Exception):
    """The entry is absent; the message says why when it was present but unusable."""


def array_checksum(a: np.ndarray) -> str:
    """Checksum (32 hex digits) of an array as :func:`np.save` writes it (C order).

    Parameters
    ----------
    a : ndarray
        Any shape and numeric dtype.

    Returns
    -------
    str
        See the module docstring.
    """
    a = np.require(a, requirements="C")  # (ascontiguousarray would turn 0-d into 1-d)
    raw = memoryview(a).cast("B") if a.nbytes else memoryview(b"")
    body = a.nbytes // (8 * _LANES) * (8 * _LANES)  # whole rows; the rest is the tail
    words = np.frombuffer(raw[:body], dtype=np.uint64).reshape(-1, _LANES)
    h = hashlib.blake2b(f"{a.dtype.str}{a.shape}False".encode(), digest_size=16)
    h.update(words.sum(axis=1, dtype=np.uint64).tobytes())  # sums wrap modulo 2**64
    h.update(raw[body:])
    h.update(words.sum(axis=0, dtype=np.uint64).tobytes())
    return h.hexdigest()


def _read_checked(path: Path, expected: str | None) -> np.ndarray:
    """A ``.npy`` of an entry, never unpickled; CacheMiss when unreadable or its checksum differs."""
    _check_npy_size(path)
    try:
        a = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, TypeError, MemoryError) as exc:
        raise CacheMiss(f"unreadable ({type(exc).__name__})") from None
    if array_checksum(a) != expected:
        raise CacheMiss("checksum mismatch (corrupt or modified)")
    return a


def _check_npy_size(path: Path) -> None:
    """CacheMiss, before anything is allocated, when the ``.npy`` header's shape and dtype do not
    account for exactly the bytes after it (a damaged header can claim terabytes)."""
    from numpy.lib import format as npy

    try:
        with open(path, "rb") as fh:
            version = npy.read_magic(fh)
            read_header = npy.read_array_header_1_0 if version == (1, 0) else npy.read_array_header_2_0
            shape, _, dtype = read_header(fh, max_header_size=10_000)
            body = os.fstat(fh.fileno()).st_size - fh.tell()
    except (OSError, ValueError, EOFError, TypeError) as exc:
        raise CacheMiss(f"unreadable header ({type(exc).__name__})") from None
    if dtype.hasobject:
        raise CacheMiss("unreadable (it holds Python objects, never unpickled)")
    need = math.prod(shape) * dtype.itemsize
    if need != body:
        raise CacheMiss(f"unreadable (its header claims {need} bytes of data, {dtype} of shape {shape}; the file holds {body})")


_ARRAY_NAMES = ("points_order", "canonical_points", "evals", "evecs", "mass", "L_data", "L_indices", "L_indptr", "h",
                "standin_sel", "standin_rep")
_NO_STANDINS = np.zeros(0, dtype=np.int64)  # a basis on every point stores both stand-in arrays empty


def _to_arrays(basis: Basis, order: np.ndarray, canon: np.ndarray) -> dict[str, np.ndarray]:
    """The arrays of an entry, in the computing cloud's point order (plus its canonical order)."""
    L = sp.csr_matrix(basis.L)
    sel = _NO_STANDINS if basis.sel is None else np.asarray(basis.sel, dtype=np.int64)
    rep = _NO_STANDINS if basis.rep is None else np.asarray(basis.rep, dtype=np.int64)
    return dict(zip(_ARRAY_NAMES, (np.asarray(order, dtype=np.int64), canon, basis.evals, basis.evecs, basis.mass,
                                   L.data, L.indices, L.indptr, np.array(basis.h), sel, rep)))


def _from_arrays(arrays: dict[str, np.ndarray], points: np.ndarray, order: np.ndarray, meta: dict) -> Basis:
    """The basis in the caller's point order; ``order`` is the caller's canonical order."""
    n = len(points)
    stored_order = arrays["points_order"]
    nk = int(meta["config"]["nk"])
    sel, rep = arrays["standin_sel"], arrays["standin_rep"]
    thinned = len(rep) > 0
    m = len(sel) if thinned else n
    shapes_ok = (stored_order.shape == (n,) and arrays["evecs"].shape == (m, nk) and arrays["evals"].shape == (nk,)
                 and arrays["mass"].shape == (m,) and arrays["L_indptr"].shape == (m + 1,) and arrays["h"].shape == ())
    if thinned:  # every point has a stand-in, every stand-in is a point
        shapes_ok = (shapes_ok and rep.shape == (n,) and sel.ndim == 1 and 0 < m <= n and int(rep.min()) >= 0
                     and int(rep.max()) < m and int(sel.min()) >= 0 and int(sel.max()) < n)
    elif len(sel):
        shapes_ok = False
    if not shapes_ok:
        raise CacheMiss("its arrays do not fit this cloud")
    L = sp.csr_matrix((arrays["L_data"], arrays["L_indices"], arrays["L_indptr"]), shape=(m, m))
    h = float(arrays["h"])
    same = np.array_equal(order, stored_order)
    if thinned:
        # L, mass and evecs are per stand-in: kept as stored; the maps follow the caller's point order.
        if not same:
            rows = stored_order[np.argsort(order)]  # caller's point i is stored point rows[i] (see below)
            where = np.empty(n, dtype=np.int64)
            where[rows] = np.arange(n)
            sel, rep = where[sel], rep[rows]
        return Basis(points, L, arrays["mass"], arrays["evals"], arrays["evecs"], h, meta, sel, rep)
    if same:  # the caller's order is the stored one: no copies
        return Basis(points, L, arrays["mass"], arrays["evals"], arrays["evecs"], h, meta)
    # Caller's row i is canonical point k = argsort(order)[i] (order inverted), stored as row stored_order[k].
    rows = stored_order[np.argsort(order)]
    return Basis(points, L[rows][:, rows].tocsr(), arrays["mass"][rows], arrays["evals"], arrays["evecs"][rows],
                 h, meta)


def _load_entry(entry: Path, points: np.ndarray, order: np.ndarray, canon: np.ndarray) -> Basis:
    meta_path = entry / "basis.json"
    if not meta_path.exists():
        raise CacheMiss("")
    try:
        meta = json.loads(meta_path.read_text())
        checksums = meta["checksums"]
        if not isinstance(checksums, dict):
            raise TypeError("checksums")
    except Exception as exc:
        raise CacheMiss(f"unreadable ({type(exc).__name__})") from None
    if meta.get(SIDECAR_SHA) != sidecar_checksum(meta):  # an edited h_m or n_points must not load
        raise CacheMiss("basis.json was edited or is from an older tergodic (its checksum does not match)")
    if set(checksums) != set(_ARRAY_NAMES):
        raise CacheMiss("checksum mismatch (corrupt or modified)")
    arrays = {name: _read_checked(entry / f"{name}.npy", checksums[name]) for name in _ARRAY_NAMES}
    # Guard against key collisions: the cached geometry must be this geometry.
    cached = arrays["canonical_points"]
    if cached.shape != canon.shape or np.abs(cached - canon).max() > 10 * QUANTUM_M:
        raise CacheMiss("geometry does not match its key")
    try:
        return _from_arrays(arrays, points, order, meta)
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise CacheMiss(f"inconsistent ({type(exc).__name__})") from None


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
    validate_basis_config(cfg)
    say = on_event or (lambda msg: warnings.warn(msg, stacklevel=2))
    t0 = time.perf_counter()
    key, order, invariant, canon = geometry_key(points, cfg)
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
    # before minutes of work, not after
    check_parent_writable(entry, entry.parent.parent, _CACHE_OPTION)
    with Spinner(f"computing basis: Laplacian + {cfg.nk} eigenpairs of {len(points)} points"):
        basis = compute_basis(points, cfg.nk, cfg.neighbors, timings)
    from tergodic_cli.provenance import library_versions  # importlib.metadata: only when recorded

    t = time.perf_counter()
    arrays = _to_arrays(basis, order, canon)
    meta = {
        "kind": "tergodic.basis", "format_version": FORMAT_VERSION, "layout": CACHE_LAYOUT, "key": key,
        "config": cfg.to_dict(), "n_points": len(points), "n_standins": len(basis.mass),
        "rigid_invariant": invariant, "h_m": basis.h,
        "lambda_range": [float(basis.evals[0]), float(basis.evals[-1])],
        "timings": timings,
        "versions": library_versions(),
        "checksums": {name: array_checksum(a) for name, a in arrays.items()},
    }
    meta = json.loads(json.dumps(meta))  # what a reader will see
    meta[SIDECAR_SHA] = sidecar_checksum(meta)
    try:
        _write_entry(entry, arrays, meta, cfg)
    except OSError as exc:  # a full disk or a vanished permission: one line, nothing partial (see _write_entry)
        raise os_error(exc, entry.parent.parent, "write the basis cache",
                       f"free space or choose another {_CACHE_OPTION}") from None
    meta["timings"]["write_ms"] = 1e3 * (time.perf_counter() - t)  # in memory only (after the write)
    meta["path"] = str(entry)
    basis.meta = meta
    return basis, False


def _write_entry(entry: Path, arrays: dict[str, np.ndarray], meta: dict, cfg: BasisConfig) -> None:
    """Write into a temporary sibling folder, then rename it into place (atomic)."""
    entry.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{entry.name}.", dir=entry.parent))
    try:
        for name, array in arrays.items():
            np.save(tmp / f"{name}.npy", np.require(array, requirements="C"), allow_pickle=False)
        (tmp / "basis.json").write_text(json.dumps(meta, indent=2) + "\n")
        write_config(tmp / CONFIG_FILE, BASIS_CONFIG_KIND, basis=cfg)
        if entry.exists():
            shutil.rmtree(entry, ignore_errors=True)
        try:
            os.replace(tmp, entry)
        except OSError as exc:
            # Another process (a sweep's workers) put the same entry in place meanwhile: same key,
            # same content, so theirs stands and ours goes.
            if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST) or not (entry / "basis.json").exists():
                raise
            shutil.rmtree(tmp, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
