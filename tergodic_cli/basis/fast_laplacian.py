"""Exact, faster re-implementation of ``robust_laplacian.point_cloud_laplacian`` (version 1.1.0).

The robust point-cloud Laplacian (Sharp & Crane 2020) is built in five steps. This module redoes each
of them in numba, following the library's (C++, with geometry-central, nanoflann and Eigen) choices
closely enough that the stiffness matrix ``L`` and the lumped mass are the library's to round-off
(about 1e-14 of max|L|), and it refuses (:class:`LaplacianMismatchRisk`) where round-off could still
make the two choose differently. The caller then falls back to ``robust_laplacian`` itself.

The kernels are in :mod:`tergodic_cli.basis.fast_laplacian_kernels`. They run from an ahead-of-time
build (:mod:`tergodic_cli.basis.fast_laplacian_aot`, made by ``make``; no numba import) or, without
one, from numba just in time. This module itself imports neither numba nor the kernels until asked.

1. **Neighbours.** The ``k`` nearest other points of every point, nearest first. The library's k-d
   tree (nanoflann: cells split at the middle of their widest side, leaves of at most 10 points) is
   rebuilt and searched in the same order, so points at exactly equal distance come out in the same
   order and the same one is left out at the k-th place.
2. **Tangent planes.** The normal is the last left singular vector of the 3 x k matrix of neighbour
   offsets from their sum divided by k + 1 (the library's divisor). Its direction is any SVD's, but
   its sign decides the orientation of the chart and with it the order in which triangles are
   emitted, so the steps of Eigen's JacobiSVD (pivoted Householder QR, then 2x2 Jacobi sweeps) are
   followed to get the same sign. Neighbours relative to the point are projected on the plane and
   written in geometry-central's tangent basis.
3. **Local fans.** Neighbours are sorted by angle. If the largest gap between consecutive angles
   exceeds pi - 1e-5 the point is on a boundary and the walk starts after that gap (the library
   never counts the gap across the +-pi cut of atan2); otherwise it starts at the nearest projected
   neighbour. From each start, the first later neighbour whose circle through the centre and the two
   points is empty, up to 1e-4 of the farthest projected distance, closes a triangle
   (centre, start, end) and becomes the next start; nearly collinear pairs are skipped.
4. **Tufted cover.** All fans are pooled in order, duplicates kept (a triangle found from its three
   corners appears three times). Edges are the distinct vertex pairs, numbered by first appearance;
   their 3-D lengths are lengthened by the intrinsic mollification (every triangle inequality then
   holds with a slack of ``mollify_factor`` times the mean edge length). Every triangle gets a
   reversed copy; around each edge the triangles are sorted by the angle of their third vertex
   (stable for equal angles, in the library's sibling order) and consecutive sheets are glued into a
   closed oriented surface.
5. **Intrinsic Delaunay, cotangent weights.** Edges of the cover are flipped, by edge lengths alone,
   in the library's first-in-first-out order until every cotangent weight is at least -1e-6. ``L`` is
   the cotangent Laplacian, the mass one third of the incident face areas, both halved (two sheets)
   and divided by three (each triangle is found about three times).

Guards (the reasons in :data:`GUARD_REASONS`): duplicate points; a neighbour in the library's
perturbation zone; a sign decision of the SVD within round-off of its switch point, or a nearly
degenerate normal; a point on the atan2 cut; near-equal angles or radii in a chart when the
alternatives give different fans (both are walked and compared); collinearity, boundary-gap,
empty-circle or flip tests within a margin of their thresholds; a run of equal angles around an edge
with more than 16 triangles (the C++ sort is then not stable); a point in no triangle. On the
reference bunny (2996 points) and plate, and on the synthetic objects, none fires. On an exactly
regular grid, and on the bunny at 18001 points (where neighbours nearly coincide once projected),
they do: there the library's own result is decided by its round-off.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["LaplacianMismatchRisk", "FastLaplacianNotBuilt", "point_cloud_laplacian", "compiled_pipeline", "GUARD_REASONS"]

#: Backends of :func:`point_cloud_laplacian`: the ahead-of-time build, numba just in time, or the first available.
BACKENDS = ("auto", "aot", "jit")

#: reason code -> text, for the exception message
GUARD_REASONS = {
    1: "duplicate points",
    4: "sign of a local normal (Eigen SVD emulation) near a switch point",
    5: "neighbour in the perturbation zone of the centre",
    6: "near-tie in the angular order of a neighbourhood that changes its fan",
    7: "near-tie for the nearest projected neighbour that changes its fan",
    8: "boundary-gap test near its threshold",
    9: "collinearity test near its threshold",
    10: "empty-circle test near its threshold",
    11: "near-tie in the angular order of distinct triangles around an edge (only with _tie_guard)",
    12: "more than 16 tied triangles around one edge",
    13: "a point is in no triangle",
    14: "flip test near its threshold",
    15: "degenerate neighbourhood (zero length scale)",
    16: "non-finite edge length after a flip",
}


class LaplacianMismatchRisk(RuntimeError):
    """The fast Laplacian could differ from robust_laplacian's on this input (a near-tie); use the library.

    Attributes
    ----------
    code : int
        Key of :data:`GUARD_REASONS`.
    point : int
        Index of the point (or edge) where the guard fired, -1 if not applicable.
    """

    def __init__(self, code: int, point: int = -1):
        self.code = int(code)
        self.point = int(point)
        super().__init__(f"fast Laplacian refused: {GUARD_REASONS.get(self.code, 'unknown')} (at {self.point})")



class FastLaplacianNotBuilt(RuntimeError):
    """``backend="aot"`` was asked for, but no current ahead-of-time build was found (the message says why)."""


def compiled_pipeline(backend: str = "auto"):
    """The compiled kernel pipeline and which build it is.

    Parameters
    ----------
    backend : ``"aot"`` the ahead-of-time build (:mod:`tergodic_cli.basis.fast_laplacian_aot`; loads in
        under a millisecond, no numba), ``"jit"`` numba just in time (0.6-0.8 s to load per process,
        ~30 s to compile once), ``"auto"`` the build if there is a current one, else numba.

    Returns
    -------
    (function, "aot" or "jit").

    Raises
    ------
    FastLaplacianNotBuilt
        ``backend="aot"`` without a current build.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend in ("auto", "aot"):
        from tergodic_cli.basis.fast_laplacian_aot import load_pipeline

        fn, why = load_pipeline()
        if fn is not None:
            return fn, "aot"
        if backend == "aot":
            raise FastLaplacianNotBuilt(why)
    from tergodic_cli.basis.fast_laplacian_kernels import laplacian_pipeline

    return laplacian_pipeline, "jit"


def point_cloud_laplacian(points, n_neighbors: int = 30, mollify_factor: float = 1e-5, *, backend: str = "auto",
                          _normal_sign: float = 1.0, _tie_guard: bool = False):
    """Robust point-cloud Laplacian, equal to ``robust_laplacian.point_cloud_laplacian`` (1.1.0) to round-off.

    Parameters
    ----------
    points : (n, 3) float64
        Point positions (any length unit; L is scale-free, the mass scales with length²).
    n_neighbors : int
        Neighbours per point (the library's ``n_neighbors``), at most n - 1.
    mollify_factor : float
        Intrinsic mollification, relative to the mean edge length (the library's ``mollify_factor``).
    backend : str
        Which compiled kernels: ``"auto"`` (the ahead-of-time build if current, else numba), ``"aot"``
        or ``"jit"``; see :func:`compiled_pipeline`. Both give the same matrices.

    Returns
    -------
    L : scipy.sparse.csr_matrix (n, n) float64
        Symmetric positive semi-definite cotangent stiffness matrix (rows sum to zero).
    mass : (n,) float64
        Lumped mass (area per point, length²).

    Raises
    ------
    LaplacianMismatchRisk
        When a near-tie makes equality with the library uncertain; call the library instead.
    FastLaplacianNotBuilt
        ``backend="aot"`` without a current build.
    ValueError
        Points not (n, 3), or n_neighbors outside [3, n - 1].

    Notes
    -----
    The library's signature is ``(points, mollify_factor, n_neighbors)``; here ``n_neighbors`` comes
    second. ``_normal_sign`` (flips every normal) and ``_tie_guard`` (also refuse near-equal angles of
    distinct triangles around an edge) exist for tests. Single-threaded.
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {pts.shape}")
    n = len(pts)
    k = int(n_neighbors)
    if k < 3 or k + 1 > n:
        raise ValueError(f"n_neighbors must be in [3, n - 1], got {k} for {n} points")
    pipeline, _ = compiled_pipeline(backend)
    indptr, indices, data, mass, code, where = pipeline(pts, k, float(mollify_factor), np.full(n, float(_normal_sign)),
                                                        bool(_tie_guard))
    if code:
        raise LaplacianMismatchRisk(code, where)
    return sp.csr_matrix((data, indices, indptr), shape=(n, n)), mass
