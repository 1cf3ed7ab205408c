"""Point-cloud filters as in the paper's acquisition node: statistical outlier, voxel grid
(the passthrough crop is one line in the pipeline)."""

from __future__ import annotations

import numpy as np

VOXEL_RULES = ("fraction", "all", "intensity")
#: A point with fewer than ISOLATED_MIN others within ISOLATED_RADIUS median nearest-neighbour
#: distances is a stray point (a flying pixel): dropped by default, since it inflates the spacing h
#: and ties far-apart points together in the Laplacian.
ISOLATED_RADIUS, ISOLATED_MIN = 8.0, 2
#: A cloud much denser than a 3 mm capture has its basis (and the explorer its fields) on one
#: stand-in point per voxel of this edge (metres, :func:`voxel_standins`): the paper's capture
#: voxel, where its α and footprint were tuned. Precompute then costs about the same on any
#: sampling of an object, and a step too (docs/precompute.md, "Dense clouds").
FIELD_VOXEL = 0.003
#: ... when the cloud's spacing h is below this share of FIELD_VOXEL (a 3 mm capture is used whole).
THIN_BELOW = 0.5


def thins(h: float) -> bool:
    """Whether a cloud's basis and fields are carried by stand-ins (:data:`FIELD_VOXEL`, :data:`THIN_BELOW`).

    Parameters
    ----------
    h : float
        The cloud's mean spacing, metres.

    Returns
    -------
    bool
    """
    return h < THIN_BELOW * FIELD_VOXEL


def enough_standins(m: int, nk: int, n_neighbors: int) -> bool:
    """Whether stand-ins can carry the basis (else it is computed on every point).

    Parameters
    ----------
    m : int
        Stand-ins.
    nk, n_neighbors : int
        The basis' eigenpairs and the Laplacian's neighbours.

    Returns
    -------
    bool
        More stand-ins than either.
    """
    return m > max(nk, n_neighbors)


def basis_size(points: np.ndarray, h: float, nk: int, n_neighbors: int) -> int:
    """How many points a basis of this cloud is computed on (``basis.compute_basis``'s rule): its
    stand-ins when the cloud is dense (:func:`thins`) and they are enough, else all of them.

    Parameters
    ----------
    points : (n, 3) float
        Metres.
    h : float
        Their mean spacing, metres.
    nk, n_neighbors : int
        The basis' eigenpairs and neighbours.

    Returns
    -------
    int
    """
    if thins(h):
        m = len(np.unique(_voxel_key(points, FIELD_VOXEL)))
        if enough_standins(m, nk, n_neighbors):
            return m
    return len(points)


def remove_statistical_outliers(points: np.ndarray, nb_neighbors: int, std_ratio: float) -> np.ndarray:
    """Mask (n,) of inliers: a point is an outlier when its mean distance to its
    ``nb_neighbors`` nearest neighbours exceeds mean + ``std_ratio`` * std over the cloud
    (the rule of PCL's StatisticalOutlierRemoval and open3d's remove_statistical_outlier).

    Parameters
    ----------
    points : (n, 3) float
        Metres.
    nb_neighbors : int
        Neighbours of the mean distance.
    std_ratio : float
        Standard deviations above the mean that make an outlier.

    Returns
    -------
    (n,) bool
        True for the inliers.
    """
    from scipy.spatial import cKDTree

    k = min(nb_neighbors + 1, len(points))
    dists, _ = cKDTree(points).query(points, k=k)
    mean_d = dists[:, 1:].mean(axis=1)
    return mean_d <= mean_d.mean() + std_ratio * mean_d.std()


def voxel_downsample(points: np.ndarray, colors: np.ndarray | None, target: np.ndarray,
                     voxel: float, rule: str = "fraction"):
    """Average points, colours and target weight per voxel.

    The grid is open3d's ``voxel_down_sample`` grid (origin at the bounding-box minimum
    minus half a voxel), so point counts match open3d's exactly. Output is ordered by
    voxel index, which makes it deterministic.

    Parameters
    ----------
    points : (n, 3) float64, metres.
    colors : (n, 3) float64 in [0, 1], or None.
    target : (n,) target weight in [0, 1] (bool: target-coloured points).
    voxel : voxel edge length in metres (> 0).
    rule : one of VOXEL_RULES (the pipeline checks it). ``"fraction"`` or ``"intensity"``: p is the
        mean target weight in the voxel (the share of target points for a bool ``target``);
        ``"all"``: p is 1 only when every point in the voxel weighs 1 (the authors' public code), else 0.

    Returns
    -------
    points (m, 3), colors (m, 3) or None, p (m,) float64 in [0, 1].
    """
    origin = points.min(axis=0) - 0.5 * voxel
    idx = np.floor((points - origin) / voxel).astype(np.int64)
    dims = idx.max(axis=0) + 1
    key = (idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]  # 1-D key: much faster than unique(axis=0)
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    m = len(counts)

    def mean_of(values: np.ndarray) -> np.ndarray:
        out = np.zeros((m,) + values.shape[1:])
        np.add.at(out, inverse, values)
        return out / counts.reshape((-1,) + (1,) * (values.ndim - 1))

    p = mean_of(target.astype(np.float64))
    if rule == "all":
        p = (p >= 1.0).astype(np.float64)
    return mean_of(points), (mean_of(colors) if colors is not None else None), p


def mean_spacing(points: np.ndarray, k: int = 3) -> float:
    """Mean distance from each point to its ``k`` nearest neighbours, h in eq. 21 (metres).

    k = 3 matches the edge statistic of the authors' public code, so δt = α h² agrees.

    Parameters
    ----------
    points : (n, 3) float64, metres, n > k.

    Returns
    -------
    h : float, metres.
    """
    from scipy.spatial import cKDTree

    pts = np.ascontiguousarray(points, dtype=np.float64)
    dists, _ = cKDTree(pts).query(pts, k=k + 1)  # the first neighbour is the point itself
    return float(dists[:, 1:].mean())


def _voxel_key(points: np.ndarray, voxel: float) -> np.ndarray:
    """(n,) int64 voxel of each point, numbered in lexicographic (x, y, z) order of the cells
    (as ``np.unique(cell, axis=0)`` orders them, 10x faster); origin at the bounding-box minimum."""
    cell = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
    dims = cell.max(axis=0) + 1
    return (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]


def voxel_standins(points: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """One stand-in point per occupied voxel: the point nearest its voxel's centroid (a real point,
    on the data). The grid's origin is the bounding-box minimum; voxels are numbered in
    lexicographic (x, y, z) order of their cells.

    Parameters
    ----------
    points : (n, 3) float64
        Metres.
    voxel : float
        Voxel edge, metres (> 0).

    Returns
    -------
    sel : (m,) int64
        The stand-ins' indices into ``points``, ascending.
    rep : (n,) int64
        Each point's stand-in, as a position in ``sel`` (``points[sel[rep[i]]]`` stands for point i,
        and lies in point i's voxel).
    """
    _, group, counts = np.unique(_voxel_key(points, voxel), return_inverse=True, return_counts=True)
    group = group.ravel()
    centre = np.zeros((len(counts), 3))
    np.add.at(centre, group, points)
    centre /= counts[:, None]
    d = np.linalg.norm(points - centre[group], axis=1)
    order = np.lexsort((d, group))
    sel = np.sort(order[np.unique(group[order], return_index=True)[1]])
    rep = np.argsort(group[sel])[group]  # each point's voxel's slot in sel (group[sel] inverted)
    return sel.astype(np.int64), rep.astype(np.int64)


def isolated_points(points: np.ndarray) -> np.ndarray:
    """Mask (n,) of stray points: fewer than ISOLATED_MIN other points within ISOLATED_RADIUS times
    the cloud's median nearest-neighbour distance.

    Parameters
    ----------
    points : (n, 3) float
        Metres.

    Returns
    -------
    (n,) bool
        True for the stray points.
    """
    from scipy.spatial import cKDTree

    # Fewer than ISOLATED_MIN others within r <=> the ISOLATED_MIN-th nearest other is farther than r:
    # one k-nearest query, where counting every ball (~200 points each on a dense scan) took minutes at 1M.
    d, _ = cKDTree(points).query(points, k=ISOLATED_MIN + 1)
    r = ISOLATED_RADIUS * float(np.median(d[:, 1]))
    return d[:, ISOLATED_MIN] > r


def count_duplicates(points: np.ndarray) -> int:
    """How many points repeat an earlier one exactly (n minus the distinct points).

    Parameters
    ----------
    points : (n, 3) float
        Metres.

    Returns
    -------
    int
    """
    # one lexicographic sort (np.unique(axis=0) sorts a structured copy: 5x slower)
    ordered = points[np.lexsort((points[:, 2], points[:, 1], points[:, 0]))]
    return int(np.count_nonzero(np.all(ordered[1:] == ordered[:-1], axis=1)))
