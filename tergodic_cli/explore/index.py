"""The explorer's per-cloud index: the compiled KD-tree and the point order it defines.

Its own module so that the explorer and the coverage score both use it without importing each other.
"""

from __future__ import annotations

import weakref

import numpy as np

from tergodic_cli.explore import kernels as K

# Static per-cloud data, shared by every explorer of the same arrays (a sweep builds hundreds).
_STORE: dict[tuple[str, int], tuple] = {}


def cached(kind: str, owner, build):
    """``build()``, computed once per ``owner`` array and ``kind`` while that array lives.

    Parameters
    ----------
    kind : str
        What is cached ("tree", "phi", ...).
    owner : np.ndarray
        The array the value belongs to (held by a weak reference).
    build : callable
        Computes the value.

    Returns
    -------
    object
        The cached value.
    """
    key = (kind, id(owner))
    hit = _STORE.get(key)
    if hit is not None and hit[0]() is owner:
        return hit[1]
    value = build()
    # (the store bound now: at interpreter exit the module's globals may already be None)
    _STORE[key] = (weakref.ref(owner, lambda _ref, key=key, store=_STORE: store.pop(key, None)), value)
    return value


class CloudIndex:
    """The compiled KD-tree of a cloud and the internal point order it defines.

    The explorer keeps every per-point array, and the rows of Φ, in the tree's leaf order
    (``order``: internal i is cloud point order[i]; ``rank`` is the inverse), so that the
    points under a footprint, and their rows of Φ, are close in memory: on a 100k-point cloud
    this halves the step (cache and TLB misses). ``tree`` is the kernels' :class:`~kernels.Tree` (perm, nodes,
    boxes, points) in internal indices, ``points`` the cloud in internal order.
    """

    def __init__(self, points: np.ndarray):
        perm, nodes, boxes, tpts = K.tree_build(points)
        self.order = perm
        self.rank = np.argsort(perm)  # the inverse permutation
        self.points = tpts
        self.tree = K.Tree(np.arange(len(perm)), nodes, boxes, tpts)


def cloud_index(points: np.ndarray) -> CloudIndex:
    """The :class:`CloudIndex` of a cloud, built once per array.

    Parameters
    ----------
    points : (n, 3) float
        Metres.

    Returns
    -------
    CloudIndex
    """
    return cached("tree", points, lambda: CloudIndex(points))


def sheet_normals(index: CloudIndex, h: float, oriented: bool = False) -> tuple[np.ndarray, float]:
    """Each point's normal line, fitted to its own sheet, and the sheet gap: once per cloud and
    spacing (:func:`kernels.sheet_normals`); with ``oriented``, also oriented once.

    The gap (metres) is the wider of ``kernels.SHEET_GAP`` h and ``kernels.SHEET_NOISE`` times
    the cloud's noise (a robust σ: the median over its points of the median absolute offset of
    their nearest from their plane, / 0.6745): offsets along a normal line that leave a wider gap
    lie on another sheet (a wall's other side), and noise alone never leaves one.

    Parameters
    ----------
    index : CloudIndex
        The cloud's index.
    h : float
        Its mean point spacing, metres.
    oriented : bool
        Orient the lines consistently along each sheet (:func:`orient_normal_lines`: the two sides
        of a wall point opposite ways), what ``--sheets separate`` needs; the fit and the score use
        the lines only (either sign), so they skip its cost (a second neighbour search and a
        spanning tree over the points).

    Returns
    -------
    normals : (n, 3) float
        Unit vectors, in the index's internal order.
    gap : float
        Metres.
    """

    def build():
        gap = K.SHEET_GAP * h
        normals, mad = K.sheet_normals(index.points, *index.tree, K.NORMAL_NEIGHBOURS, gap)
        noisy = K.SHEET_NOISE * float(np.median(mad)) / 0.6745
        if noisy > gap:  # a noisy cloud: its sheets' normals again, with the gap noise allows
            gap = noisy
            normals, _ = K.sheet_normals(index.points, *index.tree, K.NORMAL_NEIGHBOURS, gap)
        return normals, gap

    lines = cached(f"normals {h!r}", index.points, build)
    if not oriented:
        return lines
    return cached(f"oriented normals {h!r}", index.points, lambda: (orient_normal_lines(index.points, lines[0]), lines[1]))


#: Neighbours each point links to when the normal lines are oriented (:func:`orient_normal_lines`).
ORIENT_NEIGHBOURS = 12
#: A link stays on one sheet when the chord between the two points lies within 30 degrees of both
#: tangent planes (|chord . n| <= this share of its length): across a wall the chord runs along the
#: normal, along the surface it lies in the tangent plane (a sphere of radius R: chord/2R).
ORIENT_CHORD = 0.5
#: Pieces of fewer points (stray bits of a noisy cloud) are oriented together in one vote.
ORIENT_PIECE = 20


def orient_normal_lines(points: np.ndarray, lines: np.ndarray) -> np.ndarray:
    """Orient unoriented normal lines consistently along each sheet (Hoppe et al. 1992).

    The signs are propagated along a minimum spanning tree (weights 1 - |n_i . n_j|) of the
    links between near neighbours that stay on one sheet (:data:`ORIENT_CHORD`, lines within
    60 degrees): they go round a rim but never straight through a wall, so the two sides of a
    thin wall, joined at its rim, end up pointing opposite ways. A piece not joined to the
    others (a closed inner surface, a sheet split by a gap) takes the sign its nearest oriented
    neighbours ask for: the same where the step to them runs along the surface, opposite
    where it runs along the normal (across a wall or a slot). The first (largest) piece points
    away from the cloud's centroid on average.

    Parameters
    ----------
    points : (n, 3) float
        Metres.
    lines : (n, 3) float
        Unit normal lines, either sign.

    Returns
    -------
    (n, 3) float
        ``lines`` with some rows negated.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
    from scipy.spatial import cKDTree

    n = len(points)
    if n < 3:
        return lines.copy()
    k = min(ORIENT_NEIGHBOURS, n - 1)
    dist, nb = cKDTree(points).query(points, k + 1)
    i = np.repeat(np.arange(n), k)
    j = nb[:, 1:].ravel()
    d = np.maximum(dist[:, 1:].ravel(), 1e-12)
    chord = points[j] - points[i]
    along_i = np.abs(np.einsum("ij,ij->i", chord, lines[i]))
    along_j = np.abs(np.einsum("ij,ij->i", chord, lines[j]))
    agree = np.abs(np.einsum("ij,ij->i", lines[i], lines[j]))
    ok = (agree >= K.SHEET_COS) & (along_i <= ORIENT_CHORD * d) & (along_j <= ORIENT_CHORD * d)
    w = coo_matrix((1.0 - agree[ok] + 1e-9, (i[ok], j[ok])), shape=(n, n)).tocsr()
    tree = minimum_spanning_tree(w.maximum(w.T))
    tree = (tree + tree.T).tocsr()
    count, label = connected_components(tree, directed=False)
    # One breadth-first pass over every piece at once: a virtual node n joined to each piece's first point.
    roots = np.unique(label, return_index=True)[1]
    tc = tree.tocoo()
    ext = coo_matrix((np.r_[tc.data, np.ones(len(roots))], (np.r_[tc.row, np.full(len(roots), n)], np.r_[tc.col, roots])),
                     shape=(n + 1, n + 1)).tocsr()
    _, pred = breadth_first_order(ext, n, directed=False)
    parent = pred[:n].copy()
    top = parent == n
    parent[top] = np.flatnonzero(top)  # a piece's root is its own parent
    rel = np.where(np.einsum("ij,ij->i", lines, lines[parent]) < 0.0, -1.0, 1.0)
    # Each point's sign relative to its piece's root: the product of the flips along its path, by pointer
    # jumping (log2 of the depth passes).
    sign, up = rel, parent
    while np.any(up[up] != up):
        sign, up = sign * sign[up], up[up]
    sign = sign * sign[up]  # (the root's own factor is 1)
    oriented = lines * sign[:, None]
    # Pieces, largest first, take the sign their nearest oriented neighbours ask for (_piece_vote).
    size = np.bincount(label, minlength=count)
    order = np.argsort(-size, kind="stable")
    done = np.zeros(n, bool)
    centroid = points.mean(axis=0)
    small = size[order] < ORIENT_PIECE
    for piece in order[~small]:
        members = np.flatnonzero(label == piece)
        if _piece_vote(points, oriented, members, done, centroid):
            oriented[members] *= -1.0
        done[members] = True
    rest = np.flatnonzero(small[np.argsort(order)][label])  # the points of the small pieces (stray bits)
    if len(rest):
        if done.any():  # each small piece: one vote over its points, against the large pieces only
            vote = np.bincount(label[rest], weights=_votes(points, oriented, rest, done)[0], minlength=count)
            oriented[rest] *= np.where(vote[label[rest]] < 0.0, -1.0, 1.0)[:, None]
        elif _piece_vote(points, oriented, rest, done, centroid):
            oriented[rest] *= -1.0
    return oriented


def _piece_vote(points, oriented, members, done, centroid) -> bool:
    """Whether a piece (``members``, oriented among themselves) should be flipped: by the votes of
    its points' nearest already-oriented points of other pieces, else outward from ``centroid``."""
    if done.any():
        vote, dist, agree = _votes(points, oriented, members, done)
        near = (dist <= 3.0 * np.median(dist)) & (np.abs(agree) >= K.SHEET_COS)
        if near.any():
            return float(np.sum(vote[near])) < 0.0
    out = np.einsum("ij,ij->i", points[members] - centroid, oriented[members])
    return float(out.sum()) < 0.0


def _votes(points, oriented, members, done):
    """Each of ``members``' vote (+1 keep, -1 flip) from its nearest point among ``done`` (n,) bool:
    the same sign where the step to it runs along the surface, opposite where it runs along the
    normal (across a wall or a slot). Returns (votes, distances m, n_i . n_j), each (len(members),)."""
    from scipy.spatial import cKDTree

    others = np.flatnonzero(done)
    dist, idx = cKDTree(points[others]).query(points[members], 1)
    j = others[idx]
    along = np.abs(np.einsum("ij,ij->i", points[j] - points[members], oriented[members]))
    agree = np.einsum("ij,ij->i", oriented[members], oriented[j])
    want = np.where(along <= ORIENT_CHORD * np.maximum(dist, 1e-12), 1.0, -1.0)
    return want * np.sign(agree), dist, agree
