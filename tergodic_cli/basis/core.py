"""Computing the basis: robust Laplacian and generalised eigenpairs."""

from __future__ import annotations

import signal
import time
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from tergodic_cli.capture.filters import FIELD_VOXEL, count_duplicates, enough_standins, mean_spacing, thins, voxel_standins
from tergodic_cli.errors import TergodicError, require

@dataclass
class Basis:
    """Spectral basis of a point cloud.

    On a cloud much denser than a 3 mm capture (:func:`thins`), L, mass and the eigenvectors live
    on its m stand-ins (one per :data:`FIELD_VOXEL` voxel, ``sel``), and ``rep`` maps every cloud
    point to its stand-in; otherwise m = n, ``sel`` and ``rep`` are None.

    Attributes
    ----------
    points : (n, 3) float64, metres, in the capture's order and frame.
    L : (m, m) sparse CSR, the weak (stiffness) Laplacian, symmetric positive semi-definite.
    mass : (m,) float64, the diagonal of the lumped mass matrix M (areas, m²).
    evals : (nK,) float64, ascending eigenvalues λ of L φ = λ M φ (1/m²).
    evecs : (m, nK) float64, M-orthonormal eigenvectors Φ (Φᵀ M Φ = I).
    h : mean spacing of ``points`` (metres), mean distance to the 3 nearest neighbours.
    sel : (m,) int64 or None, the stand-ins' indices into ``points`` (row j of L, mass, evecs is
        point ``sel[j]``).
    rep : (n,) int64 or None, each point's stand-in as a row of L, mass and evecs.
    """

    points: np.ndarray
    L: sp.csr_matrix
    mass: np.ndarray
    evals: np.ndarray
    evecs: np.ndarray
    h: float
    meta: dict = field(default_factory=dict)
    sel: np.ndarray | None = None
    rep: np.ndarray | None = None

    @property
    def nk(self) -> int:
        return len(self.evals)

    @property
    def thinned(self) -> bool:
        """True when L, mass and evecs are on stand-ins (``sel``, ``rep``), not on every point."""
        return self.rep is not None

    @cached_property
    def point_mass(self) -> np.ndarray:
        """(n,) each cloud point's share of the lumped mass, m²: ``mass`` itself, or on stand-ins each
        stand-in's mass split evenly between the points it stands for (so a voxel's points sum to it)."""
        if self.rep is None:
            return self.mass
        counts = np.bincount(self.rep, minlength=len(self.mass))
        return self.mass[self.rep] / counts[self.rep]

    @cached_property
    def kdtree(self):
        """A scipy cKDTree over ``points`` (built on first use)."""
        from scipy.spatial import cKDTree

        return cKDTree(self.points)

    def truncated(self, nk: int) -> "Basis":
        """The first eigenpairs of this basis (a view, no copy of L).

        Parameters
        ----------
        nk : int
            Eigenpairs kept, <= ``self.nk``.

        Returns
        -------
        Basis
        """
        require(nk <= self.nk, f"nK = {nk} is larger than the basis ({self.nk} eigenpairs)",
                f"run 'tergodic precompute CAPTURE --nk {nk}' or use --nk <= {self.nk}")
        return Basis(self.points, self.L, self.mass, self.evals[:nk], self.evecs[:, :nk], self.h, dict(self.meta),
                     self.sel, self.rep)


def check_geometry(points: np.ndarray) -> None:
    """Refuse clouds robust_laplacian cannot handle: collinear/coplanar-degenerate or duplicate points.

    Parameters
    ----------
    points : (n, 3) float
        Metres.
    """
    centred = points - points.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    require(sv[0] > 0, "all points are identical", "give a cloud that spans a surface")
    require(sv[1] > 1e-6 * sv[0], "the points are (nearly) collinear, so they span no surface",
            "give a cloud that samples a 2-D surface")
    n_dup = count_duplicates(points)
    require(n_dup == 0, f"the cloud has {n_dup} duplicate points", "re-capture with a voxel filter (--voxel 0.003)")


#: From this many points the Laplacian is built in a child process: robust_laplacian holds the GIL for
#: the whole call (about 1 s at 20k points, 70 s at 150k on a loaded 2-core machine), so only a child,
#: killed on Ctrl-C or SIGTERM, lets the run answer within a second. Below it the ~0.5 s start of a
#: child would cost more than it saves.
CHILD_POINTS = 20_000
#: Signals held (blocked) while the Laplacian's child is started: the child unblocks them.
HELD_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _laplacian_in_child(points: np.ndarray, n_neighbors: int, fix: str) -> tuple[sp.csr_matrix, np.ndarray]:
    """:func:`robust_laplacian.point_cloud_laplacian` in ``python -m tergodic_cli.basis._laplacian_child``,
    arrays passed as ``.npy`` files; the child is killed when the wait is interrupted."""
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory(prefix="tergodic-laplacian-") as tmp:
        d = Path(tmp)
        np.save(d / "points.npy", np.ascontiguousarray(points, dtype=np.float64))
        np.save(d / "k.npy", np.int64(n_neighbors))
        # Ctrl-C/SIGTERM held over the fork and exec: arriving inside Popen, they would end this process
        # before the code below that kills the child (the child unblocks them itself)
        hold = getattr(signal, "pthread_sigmask", None)
        held = hold(signal.SIG_BLOCK, HELD_SIGNALS) if hold else None
        try:
            proc = subprocess.Popen([sys.executable, "-m", "tergodic_cli.basis._laplacian_child", tmp],
                                    stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        except BaseException:
            if hold:
                hold(signal.SIG_SETMASK, held)
            raise
        try:
            if hold:
                hold(signal.SIG_SETMASK, held)  # a signal that came meanwhile is handled here, inside the try
            while True:  # short waits: the signal handlers run between them
                try:
                    _, err = proc.communicate(timeout=0.1)
                    break
                except subprocess.TimeoutExpired:
                    continue
        except BaseException:
            proc.kill()
            proc.wait()
            raise
        if (d / "error.txt").exists():
            raise TergodicError(f"robust_laplacian failed on this cloud ({(d / 'error.txt').read_text()})", fix)
        if proc.returncode != 0:
            last = (err.decode(errors="replace").strip().splitlines() or ["no message"])[-1][:120]
            raise TergodicError(f"the Laplacian's process failed (exit {proc.returncode}: {last})",
                                "check free memory, or voxel the capture more coarsely") from None
        n = len(points)
        arrays = {k: np.load(d / f"{k}.npy", allow_pickle=False) for k in ("data", "indices", "indptr", "mass")}
    L = sp.csr_matrix((arrays["data"], arrays["indices"], arrays["indptr"]), shape=(n, n))
    return L, arrays["mass"]


def compute_laplacian(points: np.ndarray, n_neighbors: int, validate: bool = True) -> tuple[sp.csr_matrix, np.ndarray]:
    """Robust point-cloud Laplacian (Sharp & Crane 2020) by ``robust_laplacian.point_cloud_laplacian``.

    Parameters
    ----------
    points : (n, 3) float64, metres.
    n_neighbors : neighbours of each point's local triangulation (3 <= k < n).
    validate : run :func:`check_geometry` first (False when the caller already did).

    Returns
    -------
    L : (n, n) CSR float64, the weak (stiffness) Laplacian: cotangent weights, symmetric, rows sum to 0.
    mass : (n,) float64, the lumped mass M's diagonal (areas, m²).
    """
    if validate:
        check_geometry(points)
    require(n_neighbors >= 3, f"--neighbors {n_neighbors} is too small", "use at least 3 (default 30)")
    require(n_neighbors < len(points), f"--neighbors {n_neighbors} is not below the {len(points)} points", "use fewer neighbours")
    fix = "the points may be degenerate; check the capture or change --neighbors"
    if len(points) >= CHILD_POINTS:
        L, mass = _laplacian_in_child(points, n_neighbors, fix)
    else:
        import robust_laplacian

        try:
            L, M = robust_laplacian.point_cloud_laplacian(points, n_neighbors=n_neighbors)
        except (RuntimeError, ValueError, AssertionError) as exc:
            raise TergodicError(f"robust_laplacian failed on this cloud ({str(exc).splitlines()[0][:80]})",
                                fix) from None
        mass = np.asarray(M.diagonal(), dtype=np.float64)
    require(np.all(np.isfinite(mass)) and np.all(mass > 0), "the Laplacian has zero-area points (degenerate sampling)",
            "re-capture with a voxel filter, or change --neighbors")
    return sp.csr_matrix(L, dtype=np.float64), mass


def solve_eigenpairs(L: sp.csr_matrix, mass: np.ndarray, nk: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``nk`` smallest eigenpairs of L φ = λ M φ, ascending and M-orthonormal, certified
    (:func:`~tergodic_cli.basis.eigensolvers.smallest_eigenpairs`).

    Parameters
    ----------
    L : (n, n) sparse
        The Laplacian in stiffness form (dimensionless cotangent weights).
    mass : (n,) float
        Lumped mass M, m².
    nk : int
        Eigenpairs wanted.

    Returns
    -------
    evals : (nk,) ascending, exactly 0 for each connected component.
    evecs : (n, nk) with Φᵀ M Φ = I; each column's largest-magnitude entry is positive.
    """
    from tergodic_cli.basis.eigensolvers import smallest_eigenpairs

    n = L.shape[0]
    require(nk >= 1, f"--nk {nk} must be positive", "e.g. --nk 200")
    require(nk < n, f"--nk {nk} is not below the number of points ({n})", f"use --nk < {n}, or a finer --voxel")
    evals, evecs = smallest_eigenpairs(L, mass, nk, seed=0)
    # Fix each eigenvector's sign (largest-magnitude entry positive) so caches are reproducible.
    flip = np.sign(evecs[np.abs(evecs).argmax(axis=0), np.arange(nk)])
    evecs *= np.where(flip == 0, 1.0, flip)
    return evals, evecs


def compute_basis(points: np.ndarray, nk: int, n_neighbors: int, timings: dict | None = None) -> Basis:
    """Laplacian, eigenpairs and spacing of a cloud; on a dense cloud (:func:`thins`), of its stand-ins.

    Parameters
    ----------
    points : (n, 3) float
        Metres.
    nk : int
        Eigenpairs.
    n_neighbors : int
        Neighbours of the robust Laplacian.
    timings : dict, optional
        Filled with the stages' times, ms.

    Returns
    -------
    Basis
        L (m, m), mass (m,) m², evals (nk,) 1/m², evecs (m, nk), spacing h in metres; m = n, or the
        stand-ins (``sel`` (m,), ``rep`` (n,)) when the cloud is much denser than :data:`FIELD_VOXEL`.
        A dense cloud too small to carry nK eigenpairs and the neighbours on its stand-ins keeps every point.
    """
    timings = {} if timings is None else timings
    check_geometry(points)
    require(nk < len(points), f"--nk {nk} is not below the number of points ({len(points)})", f"use --nk < {len(points)}")
    t = time.perf_counter()
    h = mean_spacing(points)
    timings["spacing_ms"] = 1e3 * (time.perf_counter() - t)
    sel = rep = None
    carrier = points
    if thins(h):
        t = time.perf_counter()
        sel, rep = voxel_standins(points, FIELD_VOXEL)
        timings["standins_ms"] = 1e3 * (time.perf_counter() - t)
        carrier = points[sel]
        try:  # a strip one voxel wide has collinear stand-ins
            check_geometry(carrier)
            enough = enough_standins(len(sel), nk, n_neighbors)
        except TergodicError:
            enough = False
        if not enough:  # stand-ins cannot carry the basis asked for: the whole cloud (slow, but what was asked)
            carrier, sel, rep = points, None, None
    t = time.perf_counter()
    L, mass = compute_laplacian(carrier, n_neighbors, validate=False)
    timings["laplacian_ms"] = 1e3 * (time.perf_counter() - t)
    t = time.perf_counter()
    evals, evecs = solve_eigenpairs(L, mass, nk)
    timings["eigensolver_ms"] = 1e3 * (time.perf_counter() - t)
    return Basis(points, L, mass, evals, evecs, h, sel=sel, rep=rep)
