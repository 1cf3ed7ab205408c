"""Computing the basis: robust Laplacian and generalised eigenpairs."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from contextlib import contextmanager
from functools import cached_property, lru_cache

import numpy as np
import scipy.sparse as sp

from tergodic_cli.errors import TergodicError, require


@dataclass
class Basis:
    """Spectral basis of a point cloud.

    Attributes
    ----------
    points : (n, 3) float64, metres, in the capture's order and frame.
    L : (n, n) sparse CSR, the weak (stiffness) Laplacian, symmetric positive semi-definite.
    mass : (n,) float64, the diagonal of the lumped mass matrix M (areas, m²).
    evals : (nK,) float64, ascending eigenvalues λ of L φ = λ M φ (1/m²).
    evecs : (n, nK) float64, M-orthonormal eigenvectors Φ (Φᵀ M Φ = I).
    h : mean spacing (metres), mean distance to the 3 nearest neighbours.
    """

    points: np.ndarray
    L: sp.csr_matrix
    mass: np.ndarray
    evals: np.ndarray
    evecs: np.ndarray
    h: float
    meta: dict = field(default_factory=dict)

    @property
    def nk(self) -> int:
        return len(self.evals)

    @cached_property
    def kdtree(self):
        """A scipy cKDTree over ``points`` (built on first use)."""
        from scipy.spatial import cKDTree

        return cKDTree(self.points)

    def truncated(self, nk: int) -> "Basis":
        """The first ``nk`` eigenpairs of this basis (a view, no copy of L)."""
        require(nk <= self.nk, f"nK = {nk} is larger than the basis ({self.nk} eigenpairs)",
                f"run 'tergodic precompute CAPTURE --nk {nk}' or use --nk <= {self.nk}")
        return Basis(self.points, self.L, self.mass, self.evals[:nk], self.evecs[:, :nk], self.h, dict(self.meta))


def check_geometry(points: np.ndarray) -> None:
    """Refuse clouds robust_laplacian cannot handle: collinear/coplanar-degenerate or duplicate points."""
    centred = points - points.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    require(sv[0] > 0, "all points are identical", "give a cloud that spans a surface")
    require(sv[1] > 1e-6 * sv[0], "the points are (nearly) collinear, so they span no surface",
            "give a cloud that samples a 2-D surface")
    # Duplicates by one lexicographic sort (np.unique(axis=0) sorts a structured copy: 5x slower).
    ordered = points[np.lexsort((points[:, 2], points[:, 1], points[:, 0]))]
    n_dup = int(np.count_nonzero(np.all(ordered[1:] == ordered[:-1], axis=1)))
    require(n_dup == 0, f"the cloud has {n_dup} duplicate points", "re-capture with a voxel filter (--voxel 0.003)")


#: Environment switch for which implementation makes L and M (see compute_laplacian).
ENV_LAPLACIAN = "TERGODIC_LAPLACIAN"
LAPLACIAN_METHODS = ("auto", "fast", "robust_laplacian")
#: The robust_laplacian release whose algorithm tergodic.basis.fast_laplacian reproduces.
FAST_LAPLACIAN_MATCHES = "1.1.0"


def laplacian_method() -> str:
    """``auto`` (default), ``fast`` or ``robust_laplacian``, from ``$TERGODIC_LAPLACIAN``; see :func:`compute_laplacian`."""
    import os

    method = os.environ.get(ENV_LAPLACIAN, "auto").strip().lower() or "auto"
    require(method in LAPLACIAN_METHODS, f"{ENV_LAPLACIAN}={method} is not a Laplacian method",
            f"set {ENV_LAPLACIAN} to {', '.join(LAPLACIAN_METHODS)}")
    return method


@contextmanager
def using_laplacian(method: str | None, flag: str = "--laplacian"):
    """Within the block, :func:`compute_laplacian` uses ``method`` (None: leave the choice as it is).

    A bad value is a one-line error naming ``flag``; the previous ``$TERGODIC_LAPLACIAN`` comes back after.
    """
    import os

    if method is None:
        yield
        return
    require(method in LAPLACIAN_METHODS, f"{flag} {method} is not a Laplacian method",
            f"use one of {', '.join(LAPLACIAN_METHODS)}")
    previous = os.environ.get(ENV_LAPLACIAN)
    os.environ[ENV_LAPLACIAN] = method
    try:
        yield
    finally:
        if previous is None:
            os.environ.pop(ENV_LAPLACIAN, None)
        else:
            os.environ[ENV_LAPLACIAN] = previous


@lru_cache(maxsize=1)
def _robust_laplacian_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("robust_laplacian")
    except PackageNotFoundError:
        return "unknown"


def compute_laplacian(points: np.ndarray, n_neighbors: int, validate: bool = True,
                      info: dict | None = None) -> tuple[sp.csr_matrix, np.ndarray]:
    """Robust point-cloud Laplacian (Sharp & Crane 2020): L (n, n) CSR and lumped mass (n,).

    Two implementations give the same L and M to round-off (about 1e-14 of max|L|):
    ``robust_laplacian.point_cloud_laplacian`` (the C++ library) and
    :mod:`tergodic_cli.basis.fast_laplacian`, our compiled re-implementation of release 1.1.0,
    2-2.5x faster. ``$TERGODIC_LAPLACIAN`` (``tergodic precompute --laplacian``) chooses:

    - ``auto`` (default): the re-implementation when its ahead-of-time build is present and
      current (``make`` builds it; it loads in under a millisecond), else the library;
    - ``fast``: the re-implementation, from numba just in time when there is no build (0.6-0.8 s
      to load per process, ~30 s to compile once);
    - ``robust_laplacian``: always the library.

    Whatever is asked, the library is called where the re-implementation declines (a decision of
    the library's algorithm too close to call for round-off to agree: near-ties, regular grids),
    where another robust_laplacian release is installed, or where its matrices fail a check.

    ``validate=False`` skips :func:`check_geometry` when the caller already ran it. ``info``
    (a dict) receives ``"laplacian"``: which implementation made the matrices, and why.
    """
    if validate:
        check_geometry(points)
    require(n_neighbors >= 3, f"--neighbors {n_neighbors} is too small", "use at least 3 (default 30)")
    require(n_neighbors < len(points), f"--neighbors {n_neighbors} is not below the {len(points)} points", "use fewer neighbours")
    info = {} if info is None else info
    info["laplacian"] = "robust_laplacian"
    L = None
    method = laplacian_method()
    if method != "robust_laplacian":
        from tergodic_cli.basis.fast_laplacian import FastLaplacianNotBuilt, LaplacianMismatchRisk
        from tergodic_cli.basis.fast_laplacian import point_cloud_laplacian as fast_laplacian

        lib = _robust_laplacian_version()
        if lib != FAST_LAPLACIAN_MATCHES:
            info["laplacian"] = (f"robust_laplacian (the re-implementation matches release {FAST_LAPLACIAN_MATCHES}, "
                                 f"not the installed {lib})")
        else:
            try:
                L, mass = fast_laplacian(points, n_neighbors=n_neighbors, backend="aot" if method == "auto" else "auto")
                info["laplacian"] = "tergodic.fast_laplacian"
            except FastLaplacianNotBuilt as why:
                info["laplacian"] = f"robust_laplacian ({why})"
            except LaplacianMismatchRisk as risk:
                info["laplacian"] = f"robust_laplacian (the re-implementation declined: {risk})"
            else:
                why = _not_a_cotan_laplacian(L, mass)
                if why:  # never expected; a safety net, O(nnz)
                    L = None
                    info["laplacian"] = f"robust_laplacian (the re-implementation's matrices failed a check: {why})"
    if L is None:
        import robust_laplacian

        try:
            L, M = robust_laplacian.point_cloud_laplacian(points, n_neighbors=n_neighbors)
        except (RuntimeError, ValueError, AssertionError) as exc:
            raise TergodicError(f"robust_laplacian failed on this cloud ({str(exc).splitlines()[0][:80]})",
                                "the points may be degenerate; check the capture or change --neighbors") from None
        mass = np.asarray(M.diagonal(), dtype=np.float64)
    require(np.all(np.isfinite(mass)) and np.all(mass > 0), "the Laplacian has zero-area points (degenerate sampling)",
            "re-capture with a voxel filter, or change --neighbors")
    return sp.csr_matrix(L, dtype=np.float64), mass


def _not_a_cotan_laplacian(L: sp.spmatrix, mass: np.ndarray) -> str | None:
    """What is wrong with (L, mass) as a cotangent Laplacian and lumped mass, or None: L must be
    symmetric with zero row sums and a positive diagonal, the mass positive and finite."""
    L = sp.csr_matrix(L)
    scale = float(np.abs(L.data).max()) if L.nnz else 0.0
    if not (scale > 0 and np.all(np.isfinite(L.data))):
        return "L is empty or not finite"
    Lt = L.T.tocsr()  # CSR of the transpose: same pattern and values when symmetric
    L.sort_indices()
    Lt.sort_indices()
    if not (np.array_equal(L.indptr, Lt.indptr) and np.array_equal(L.indices, Lt.indices)
            and np.abs(L.data - Lt.data).max() <= 1e-12 * scale):
        return "L is not symmetric"
    if np.abs(L @ np.ones(L.shape[0])).max() > 1e-9 * scale:
        return "a row of L does not sum to zero"
    if not np.all(L.diagonal() > 0):
        return "L has a non-positive diagonal entry"
    if not (np.all(np.isfinite(mass)) and np.all(mass > 0)):
        return "a lumped mass is not positive"
    return None


def solve_eigenpairs(L: sp.csr_matrix, mass: np.ndarray, nk: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``nk`` smallest eigenpairs of L φ = λ M φ, ascending and M-orthonormal.

    Shift-invert Lanczos with the null space (one constant per connected component)
    deflated exactly, a shift inside the wanted window and a certified result; see
    :mod:`tergodic_cli.basis.eigensolvers`. Eigenvalues agree with ARPACK shift-invert
    (the authors' ``eigsh(L, nK, M, sigma=1e-12)``) to ~1e-12 relative.

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
    """Laplacian, eigenpairs and spacing for ``points`` (n, 3) metres."""
    from tergodic_cli.capture.filters import mean_spacing

    timings = {} if timings is None else timings
    check_geometry(points)
    require(nk < len(points), f"--nk {nk} is not below the number of points ({len(points)})", f"use --nk < {len(points)}")
    t = time.perf_counter()
    made_by: dict = {}
    L, mass = compute_laplacian(points, n_neighbors, validate=False, info=made_by)
    timings["laplacian_ms"] = 1e3 * (time.perf_counter() - t)
    t = time.perf_counter()
    evals, evecs = solve_eigenpairs(L, mass, nk)
    timings["eigensolver_ms"] = 1e3 * (time.perf_counter() - t)
    t = time.perf_counter()
    h = mean_spacing(points)
    timings["spacing_ms"] = 1e3 * (time.perf_counter() - t)
    return Basis(points, L, mass, evals, evecs, h, {"laplacian": made_by["laplacian"]})
