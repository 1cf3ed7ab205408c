"""Compiled kernels of one explorer step (numba, cached on disk).

A step is one call of :func:`step_kernel`: numba's call overhead is paid once, not per small
operation. The NumPy references of the fit, projection, tangent frame and cubic gradient are in
``tests/reference_geometry.py``, of the source and metrics in :mod:`~tergodic_cli.explore.metrics`;
``tests/test_incremental_kernels.py`` checks that they agree. The incremental source (the exact
expansion of s = max(p̄ - c̃/Z, 0)² on the active set, with a lazy min-heap of thresholds and a
full :func:`resync` every K steps) is derived in docs/speed.md.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

from tergodic_cli.explore.footprint import footprint, residual, source


def njit(fn):
    return numba.njit(cache=True, nogil=True)(fn)


@intrinsic
def prefetch(typingctx, A, i, q):
    """``prefetch(A, i, q)``: ask the CPU to start loading the cache line of A[i, q] (A a 2-D
    float64 array) and go on without waiting for it."""
    sig = types.void(A, types.intp, types.intp)

    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [args[1], args[2]],
                                       wraparound=False)
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        # a read, kept in the caches (locality 2: L2 and beyond), of data
        flags = [ir.Constant(i32, 0), ir.Constant(i32, 2), ir.Constant(i32, 1)]
        builder.call(fn, [builder.bitcast(ptr, i8p), *flags])
        return context.get_dummy_value()

    return sig, codegen

#: Points per KD-tree leaf.
LEAF_SIZE = 8

# Rows of the per-point float array ``pf`` (n columns).
PF_MASS, PF_PBAR, PF_PHAT, PF_COV, PF_OLDC = 0, 1, 3, 4, 5  # (row 2 unused)
PF_W0, PF_W1, PF_W2 = 6, 7, 8  # scratch: weights of the rows a source update adds
N_PF = 9
# Rows of the per-point int8 array ``pb`` (n columns).
PB_TARGET, PB_ACTIVE, PB_INHEAP, PB_MARK = 0, 1, 2, 3
# ... in the source's pending list (a point the footprint deactivated and still covers).
PB_PEND = 4
N_PB = 5
# Rows of the per-point index array ``pi`` (n columns): changed list, ball buffer, target list,
# the source's pending list.
PI_CHG, PI_BALL, PI_TARGET, PI_PEND = 0, 1, 2, 3
N_PI = 4
# Rows of the spectral array ``sp`` (nK columns).
SP_DECAY, SP_A, SP_B, SP_F0, SP_F1, SP_F2, SP_PBARCOEF = 0, 1, 2, 3, 4, 5, 6
N_SP = 7
# Columns of the agent array ``ag`` (N rows).
AG_POS, AG_VEL, AG_ACC, AG_NRM, AG_T1, AG_T2 = 0, 3, 6, 9, 12, 15
#: A transit (explorer.py, "Never trapped"): AG_TRANSIT > 0 while the agent follows a path, at the
#: velocity AG_VD (3) the explorer sets each step; the drive is then that velocity's, within a_max.
AG_TRANSIT, AG_VD = 18, 19
#: How many of the agent's n_N neighbours (the first ones of its row of ``nbrs``) lie on its sheet.
AG_NKEEP = 22
N_AG = 23
# Float state ``fs``.
FS_Z, FS_MASS_S, FS_G0, FS_G1, FS_G2, FS_REF_UNTOUCHED, FS_DRIFT = 0, 1, 2, 3, 4, 5, 6
# The cloud's Z = ∫_Ω c̃ (the footprint gain's normaliser, whatever the source's is).
FS_ZC = 7
N_FS = 8
# Int state ``is_``.
IS_HEAP, IS_TOUCHED, IS_EDGE, IS_NCHG, IS_SINCE_RESYNC, IS_PHAT, IS_NTARGET, IS_RESYNCS = 0, 1, 2, 3, 4, 5, 6, 7
# Work counters (benchmarks/step.py): footprint points visited, rows of Φ added into F.
IS_FOOTPRINT, IS_ROWS, IS_POPS = 8, 9, 10
# Length of the source's pending list (PI_PEND).
IS_NPEND = 11
N_IS = 12
# Float parameters ``prm``.
PR_EPS2, PR_RA, PR_H2, PR_AMAX, PR_VMAX, PR_DT, PR_MAXSTART = 0, 1, 2, 3, 4, 5, 6
#: An agent position must lie within this distance (metres) of a cloud point: SURFACE_REACH h.
PR_REACH = 8
#: Weights of the heat's gradient and of the footprint gain's (gain_gradient) in the agent's drive.
PR_HEAT, PR_GAIN = 9, 10
#: ε² of the gain's kernel (1/m²).
PR_GAIN_EPS2 = 11
#: 1.0: the source's coverage is normalised over the target (Z = ∫_T c̃); 0.0: over the cloud
#: (Z = ∫_Ω c̃, eq. 2; also when the target covers the cloud).
PR_ZTARGET = 7
#: The sheet gap (metres): neighbours beyond a gap this wide along the nearest point's normal line
#: lie on another sheet (:func:`sheet_select`); inf keeps every neighbour.
PR_SHEET_GAP = 12
N_PR = 13
# Heat modes of :func:`step_kernel`: spectral carry-over, spectral current source, a full field.
HEAT_CARRY, HEAT_SOURCE, HEAT_FULL = 0, 1, 2



class Tree(NamedTuple):
    """A static KD-tree (:func:`tree_build`) over m points: ``perm`` (m,) the points' order in its
    leaves, ``nodes`` (nodes, 4) int64 (first, count, left, right), ``boxes`` (nodes, 6) bounds, m,
    ``tpts`` (m, 3) the points in leaf order, metres."""

    perm: np.ndarray
    nodes: np.ndarray
    boxes: np.ndarray
    tpts: np.ndarray


class Surface(NamedTuple):
    """What a step reads and never writes (internal, KD-tree leaf order).

    ``P`` (m, 3) the field's points, metres; ``Nrm`` (m, 3) their normal lines
    (:func:`sheet_normals`); ``tree`` the :class:`Tree` over P; ``full`` the whole cloud's tree, which
    decides what lies on the data; ``tgt`` the tree over the target's field points and ``tmap``
    (|T|,) their indices into P (the broad gain's); ``Phi`` (m, nK) the eigenvectors' rows.
    """

    P: np.ndarray
    Nrm: np.ndarray
    tree: Tree
    full: Tree
    tgt: Tree
    tmap: np.ndarray
    Phi: np.ndarray


class State(NamedTuple):
    """What a step updates, in place.

    ``pf`` (N_PF, m) float rows per point (PF_*: mass, p̄, p̂, c̃, ...); ``pb`` (N_PB, m) int8 flags
    (PB_*: target, active, in the heap, ...); ``pi`` (N_PI, m) int64 lists (PI_*); ``sp`` (N_SP, nK)
    the spectral rows (SP_*: decay, heat coefficients, accumulators F); ``heap_key``, ``heap_idx``
    (|T|,) the thresholds' min-heap; ``fs`` (N_FS,) float and ``is_`` (N_IS,) int64 scalars (FS_*,
    IS_*: Z, ∫s, counters); ``ag`` (N, N_AG) the agents (AG_* columns: position, velocity, normal,
    frame, transit); ``nbrs`` (N, n_N) each agent's neighbours; ``u_full`` (m,) the full heat field
    of the implicit integrator (empty otherwise).
    """

    pf: np.ndarray
    pb: np.ndarray
    pi: np.ndarray
    sp: np.ndarray
    heap_key: np.ndarray
    heap_idx: np.ndarray
    fs: np.ndarray
    is_: np.ndarray
    ag: np.ndarray
    nbrs: np.ndarray
    u_full: np.ndarray


def plain(t):
    """``t`` with every named tuple in it made a plain tuple: what :func:`step_kernel` takes from
    Python (numba unboxes plain tuples of arrays on its fast path; named ones cost ~0.2 µs an array)."""
    return tuple(plain(v) for v in t) if isinstance(t, tuple) else t


#: A sphere fit larger than this many rms patch radii is its tangent plane (as geometry.py).
PLANE_RADIUS_RATIO = 1e4
#: A sphere smaller than this share of the rms patch radius is noise (as geometry.py).
MIN_RADIUS_RATIO = 1.5
#: A position farther than this many mean spacings h from every cloud point is off the data
#: (the coverage metric's limit is 2 h; the margin absorbs the fit's noise).
SURFACE_REACH = 1.5
#: Projections tried per move before the chord is taken, and the step's shrink factor per try.
STEP_ITERATIONS = 4
SHRINK = 0.98
#: The footprint gain is summed over the points within this many r_a (φ(2 r_a) = e^-16 = 1e-7).
GAIN_REACH = 2.0
#: The broad gain (reach): its kernel is BROAD_WIDTH times the gain's, it weighs BROAD_WEIGHT, and it
#: is summed over the target's points within BROAD_REACH of its width (φ < 1e-7 beyond, as GAIN_REACH).
BROAD_WIDTH = 3.0
BROAD_WEIGHT = 0.15
BROAD_REACH = 2.0
#: Directions per half-turn an agent tries when a move would leave the data (30° apart).
SLIDE_DIRECTIONS = 6
#: Fit-project-requery iterations that bring a start onto the surface (as the explorer).
START_ITERATIONS = 8
#: Sheet separation (docs/explore.md): a gap wider than SHEET_GAP h between the offsets of the
#: neighbours along the nearest point's normal line separates two sheets (a wall's two sides) ...
SHEET_GAP = 0.5
#: ... or than SHEET_NOISE times the cloud's noise (a robust σ of the offsets of each point's nearest
#: from its plane), so that noise never splits one side ...
SHEET_NOISE = 3.0
#: ... and a neighbour whose normal line is turned by more than 60 degrees (cos 0.5) from the
#: nearest point's is on another face (across an edge, a hole's wall).
SHEET_COS = 0.5
#: The per-point normal lines are fitted to this many nearest points (the paper's M), seeded by
#: planes through the point and two of its NORMAL_SEED - 1 nearest.
NORMAL_NEIGHBOURS = 20
NORMAL_SEED = 7
#: Fewer points of a sheet than this: the least-squares plane, not the CGA sphere (5 unknowns).
MIN_SPHERE_FIT = 6
#: Fewer points of a sheet than this: the gradient fits a plane, not the cubic (10 unknowns).
MIN_CUBIC_FIT = 12


# ---------------------------------------------------------------------------------- KD-tree
@njit
def tree_build(points):
    """A static KD-tree over ``points`` (n, 3): median splits on the widest axis.

    Returns (perm (n,) int64, nodes (m, 4) int64 [lo, hi, left, right] with -1 children for
    leaves, boxes (m, 6) float64 [min xyz, max xyz], tree_points (n, 3) = points[perm]).
    """
    n = points.shape[0]
    perm = np.arange(n)
    cap = 4 * (n // LEAF_SIZE) + 8
    nodes = np.full((cap, 4), -1, np.int64)
    boxes = np.empty((cap, 6))
    stack = np.empty((256, 3), np.int64)
    stack[0, 0], stack[0, 1], stack[0, 2] = 0, 0, n
    sp = count = 1
    while sp > 0:
        sp -= 1
        node, lo, hi = stack[sp, 0], stack[sp, 1], stack[sp, 2]
        idx = perm[lo:hi].copy()
        pts = points[idx]
        for d in range(3):
            boxes[node, d] = pts[:, d].min()
            boxes[node, 3 + d] = pts[:, d].max()
        nodes[node, 0], nodes[node, 1] = lo, hi
        if hi - lo <= LEAF_SIZE:
            continue
        axis = 0
        widest = -1.0
        for d in range(3):
            w = boxes[node, 3 + d] - boxes[node, d]
            if w > widest:
                widest = w
                axis = d
        perm[lo:hi] = idx[np.argsort(pts[:, axis], kind="mergesort")]
        mid = (lo + hi) // 2
        left, right = count, count + 1
        count += 2
        nodes[node, 2], nodes[node, 3] = left, right
        stack[sp, 0], stack[sp, 1], stack[sp, 2] = right, mid, hi
        stack[sp + 1, 0], stack[sp + 1, 1], stack[sp + 1, 2] = left, lo, mid
        sp += 2
    return perm, nodes[:count].copy(), boxes[:count].copy(), points[perm]


@njit
def _box_dist2(boxes, node, x0, x1, x2):
    """Squared distance from (x0, x1, x2) to a node's box (0 inside)."""
    d2 = 0.0
    x = (x0, x1, x2)
    for d in range(3):
        v = boxes[node, d] - x[d]
        if v > 0.0:
            d2 += v * v
        else:
            v = x[d] - boxes[node, 3 + d]
            if v > 0.0:
                d2 += v * v
    return d2


@njit
def tree_knn(perm, nodes, boxes, tpts, x, k, out_idx, out_d2):
    """The ``k`` nearest points of ``x`` (3,): indices into out_idx[:k], squared distances
    (m²) into out_d2[:k], ascending."""
    x0, x1, x2 = x[0], x[1], x[2]
    out_d2[:k] = np.inf
    out_idx[:k] = -1
    stack = np.empty(128, np.int64)
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        if _box_dist2(boxes, node, x0, x1, x2) > out_d2[k - 1]:
            continue
        left = nodes[node, 2]
        if left < 0:
            for j in range(nodes[node, 0], nodes[node, 1]):
                a, b, c = tpts[j, 0] - x0, tpts[j, 1] - x1, tpts[j, 2] - x2
                d2 = a * a + b * b + c * c
                if d2 < out_d2[k - 1]:
                    t = k - 1
                    while t > 0 and out_d2[t - 1] > d2:
                        out_d2[t] = out_d2[t - 1]
                        out_idx[t] = out_idx[t - 1]
                        t -= 1
                    out_d2[t] = d2
                    out_idx[t] = perm[j]
        else:
            right = nodes[node, 3]
            near_left = _box_dist2(boxes, left, x0, x1, x2) <= _box_dist2(boxes, right, x0, x1, x2)
            stack[sp], stack[sp + 1] = (right, left) if near_left else (left, right)
            sp += 2


@njit
def _box_far2(boxes, node, x0, x1, x2):
    """Squared distance from (x0, x1, x2) to the farthest corner of a node's box, summed in
    the order the point test sums it."""
    a = max(boxes[node, 3] - x0, x0 - boxes[node, 0])
    b = max(boxes[node, 4] - x1, x1 - boxes[node, 1])
    c = max(boxes[node, 5] - x2, x2 - boxes[node, 2])
    return a * a + b * b + c * c


@njit
def tree_ball(perm, nodes, boxes, tpts, x, r, out):
    """Indices of the points within distance ``r`` (metres) of ``x`` into ``out``; returns their count."""
    x0, x1, x2 = x[0], x[1], x[2]
    r2 = r * r
    stack = np.empty(128, np.int64)
    stack[0] = 0
    sp, cnt = 1, 0
    while sp > 0:
        sp -= 1
        node = stack[sp]
        if _box_dist2(boxes, node, x0, x1, x2) > r2:
            continue
        if _box_far2(boxes, node, x0, x1, x2) <= r2:
            # The whole box is in the ball: each of its points would pass the test below
            # (rounding is monotone), so take them all, in the order the descent would.
            for j in range(nodes[node, 0], nodes[node, 1]):
                out[cnt] = perm[j]
                cnt += 1
            continue
        left = nodes[node, 2]
        if left < 0:
            for j in range(nodes[node, 0], nodes[node, 1]):
                a, b, c = tpts[j, 0] - x0, tpts[j, 1] - x1, tpts[j, 2] - x2
                if a * a + b * b + c * c <= r2:
                    out[cnt] = perm[j]
                    cnt += 1
        else:
            stack[sp], stack[sp + 1] = nodes[node, 3], left
            sp += 2
    return cnt


@njit
def nearest_distance(perm, nodes, boxes, tpts, x):
    """Distance (metres) from ``x`` (3,) to its nearest cloud point."""
    idx = np.empty(1, np.int64)
    d2 = np.empty(1)
    tree_knn(perm, nodes, boxes, tpts, x, 1, idx, d2)
    return math.sqrt(d2[0])


# ---------------------------------------------------------------------------------- geometry
@njit
def sym_eig_min(A, n, V, W):
    """Eigenvector of the smallest eigenvalue of the symmetric ``A[:n, :n]`` by cyclic Jacobi.

    ``V`` (n, n) receives the eigenvectors (columns), ``W`` (n, n) is scratch; returns the
    column index of the smallest eigenvalue.
    """
    for i in range(n):
        for j in range(n):
            W[i, j] = A[i, j]
            V[i, j] = 1.0 if i == j else 0.0
    for _ in range(60):
        off = diag = 0.0
        for i in range(n):
            diag += W[i, i] * W[i, i]
            for j in range(i + 1, n):
                off += W[i, j] * W[i, j]
        if off <= 1e-40 * diag or off == 0.0:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = W[p, q]
                if apq == 0.0:
                    continue
                theta = (W[q, q] - W[p, p]) / (2.0 * apq)
                if abs(theta) > 1e150:
                    t = 0.5 / theta
                else:
                    t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                    if theta < 0.0:
                        t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for r in range(n):
                    if r != p and r != q:
                        arp, arq = W[r, p], W[r, q]
                        W[r, p] = c * arp - s * arq
                        W[p, r] = W[r, p]
                        W[r, q] = s * arp + c * arq
                        W[q, r] = W[r, q]
                W[p, p] -= t * apq
                W[q, q] += t * apq
                W[p, q] = W[q, p] = 0.0
                for r in range(n):
                    vrp, vrq = V[r, p], V[r, q]
                    V[r, p] = c * vrp - s * vrq
                    V[r, q] = s * vrp + c * vrq
    best = 0
    for i in range(1, n):
        if W[i, i] < W[best, best]:
            best = i
    return best


@njit
def fit_project(P, nb, k, x, ref, out_xp, out_n):
    """CGA plane/sphere fit to the points ``P[nb[:k]]`` (eqs. 23-26) and the projection of
    ``x`` onto it (eq. 27), as :func:`geometry.fit_primitive` + :func:`geometry.project_onto`.

    Writes the projected point and its unit normal (oriented like ``ref``); returns 0, or 1
    when the fit is degenerate (then the nearest point and ``ref`` are used, as the explorer does).
    """
    c0 = c1 = c2 = 0.0
    for t in range(k):
        j = nb[t]
        c0 += P[j, 0]
        c1 += P[j, 1]
        c2 += P[j, 2]
    c0, c1, c2 = c0 / k, c1 / k, c2 / k
    y = np.empty((k, 3))
    ss = 0.0
    for t in range(k):
        j = nb[t]
        y[t, 0], y[t, 1], y[t, 2] = P[j, 0] - c0, P[j, 1] - c1, P[j, 2] - c2
        ss += y[t, 0] * y[t, 0] + y[t, 1] * y[t, 1] + y[t, 2] * y[t, 2]
    scale = math.sqrt(ss / k)
    status = 0
    kind = 0  # 0 plane, 1 sphere, 2 least-squares plane
    n0 = n1 = n2 = offset = cx = cy = cz = radius = 0.0
    # Coincident points (their spread is rounding of the centroid): no surface to fit.
    if scale <= 1e-12 * (abs(c0) + abs(c1) + abs(c2)) or scale == 0.0:
        status = 1
    else:
        V = np.empty((5, 5))
        Wk = np.empty((5, 5))
        if k < MIN_SPHERE_FIT:  # too few for a sphere (a sheet's remnant): its least-squares plane
            kind = 2
        else:
            inv = 1.0 / scale
            B = np.zeros((5, 5))
            w = np.empty(5)
            for t in range(k):
                y[t, 0], y[t, 1], y[t, 2] = y[t, 0] * inv, y[t, 1] * inv, y[t, 2] * inv
                w[0], w[1], w[2] = y[t, 0], y[t, 1], y[t, 2]
                w[3] = -1.0
                w[4] = -0.5 * (y[t, 0] * y[t, 0] + y[t, 1] * y[t, 1] + y[t, 2] * y[t, 2])
                for a in range(5):
                    wa = w[a]
                    for b in range(a, 5):
                        B[a, b] += wa * w[b]
            for a in range(5):
                for b in range(a):
                    B[a, b] = B[b, a]
            col = sym_eig_min(B, 5, V, Wk)
            r0, r1, r2 = V[0, col], V[1, col], V[2, col]
            v_inf, v0 = V[3, col], V[4, col]
            n_norm = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
            if abs(v0) * PLANE_RADIUS_RATIO > n_norm:
                s0, s1, s2 = r0 / v0, r1 / v0, r2 / v0
                rr = s0 * s0 + s1 * s1 + s2 * s2 - 2.0 * v_inf / v0
                if rr > MIN_RADIUS_RATIO * MIN_RADIUS_RATIO:
                    kind = 1
                    cx, cy, cz = c0 + scale * s0, c1 + scale * s1, c2 + scale * s2
                    radius = scale * math.sqrt(rr)
                else:
                    kind = 2
            elif n_norm == 0.0:
                kind = 2
            else:
                n0, n1, n2 = r0 / n_norm, r1 / n_norm, r2 / n_norm
                offset = n0 * c0 + n1 * c1 + n2 * c2 + scale * v_inf / n_norm
        if kind == 2:  # the direction of least variance of the (scaled) patch
            G = np.zeros((5, 5))
            for t in range(k):
                for a in range(3):
                    for b in range(3):
                        G[a, b] += y[t, a] * y[t, b]
            col = sym_eig_min(G, 3, V, Wk)
            n0, n1, n2 = V[0, col], V[1, col], V[2, col]
            nn = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            n0, n1, n2 = n0 / nn, n1 / nn, n2 / nn
            offset = n0 * c0 + n1 * c1 + n2 * c2
            kind = 0
        if kind == 0:
            dd = n0 * x[0] + n1 * x[1] + n2 * x[2] - offset
            out_xp[0], out_xp[1], out_xp[2] = x[0] - dd * n0, x[1] - dd * n1, x[2] - dd * n2
        else:
            q0, q1, q2 = x[0] - cx, x[1] - cy, x[2] - cz
            dist = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2)
            if dist < 1e-12 * max(radius, 1e-300):
                status = 1
            else:
                n0, n1, n2 = q0 / dist, q1 / dist, q2 / dist
                out_xp[0], out_xp[1] = cx + radius * n0, cy + radius * n1
                out_xp[2] = cz + radius * n2
    if status == 1:
        j = nb[0]
        out_xp[0], out_xp[1], out_xp[2] = P[j, 0], P[j, 1], P[j, 2]
        n0, n1, n2 = ref[0], ref[1], ref[2]
    if n0 * ref[0] + n1 * ref[1] + n2 * ref[2] < 0.0:
        n0, n1, n2 = -n0, -n1, -n2
    out_n[0], out_n[1], out_n[2] = n0, n1, n2
    return status


@njit
def sheet_select(P, Nrm, nb, k, gap, d, least=3):
    """Reorder the points ``nb[:k]`` so that those on the sheet of the first, j0 = nb[0], come
    first (each group in its order) and return their count: the sheet test of the fit's few
    neighbours (the wider balls of a footprint and a gain use :func:`sheet_of`).

    The sheet of j0: of the points whose normal lines (``Nrm``, either sign) lie within
    60 degrees (SHEET_COS) of j0's, their offsets along j0's line, sorted, are cut wherever two
    consecutive ones are more than ``gap`` (metres) apart; the sheet is the run holding j0's (0).
    A wall's other side lies beyond such a gap; a face across an edge, or a hole's wall, turns its
    normal away and is left out of the fit. Fewer than ``least`` on the sheet: all are kept (as
    with ``gap`` inf; a fit needs 3). ``d`` (k,) is scratch.
    """
    if not gap < np.inf:
        return k
    j0 = nb[0]
    n0, n1, n2 = Nrm[j0, 0], Nrm[j0, 1], Nrm[j0, 2]
    px, py, pz = P[j0, 0], P[j0, 1], P[j0, 2]
    srt = np.empty(k)
    npar = 0
    for t in range(k):
        j = nb[t]
        if abs(Nrm[j, 0] * n0 + Nrm[j, 1] * n1 + Nrm[j, 2] * n2) < SHEET_COS:
            d[t] = np.inf  # another face (over an edge), whatever its offset
            continue
        v = (P[j, 0] - px) * n0 + (P[j, 1] - py) * n1 + (P[j, 2] - pz) * n2
        d[t] = v
        srt[npar] = v
        npar += 1
    if npar <= 32:  # insertion sort: the fit's n_N (20), a footprint's points
        for t in range(1, npar):
            v = srt[t]
            u = t
            while u > 0 and srt[u - 1] > v:
                srt[u] = srt[u - 1]
                u -= 1
            srt[u] = v
    else:  # a gain's ball
        srt[:npar] = np.sort(srt[:npar])
    lo = 0
    while srt[lo] < 0.0:  # j0's own offset is exactly 0
        lo += 1
    hi = lo
    while lo > 0 and srt[lo] - srt[lo - 1] <= gap:
        lo -= 1
    while hi < npar - 1 and srt[hi + 1] - srt[hi] <= gap:
        hi += 1
    if hi - lo + 1 < least:
        return k
    dlo, dhi = srt[lo], srt[hi]
    m = 0
    for t in range(k):
        if dlo <= d[t] <= dhi:
            m += 1
    if m == k:
        return k
    rest = np.empty(k - m, np.int64)
    a = b = 0
    for t in range(k):
        if dlo <= d[t] <= dhi:
            nb[a] = nb[t]
            a += 1
        else:
            rest[b] = nb[t]
            b += 1
    for t in range(b):
        nb[a + t] = rest[t]
    return m


@njit
def sheet_of(P, Nrm, ball, cnt, x, anchor, gap):
    """Reorder ``ball[:cnt]`` (point indices, any order) so that the points on the sheet of
    ``anchor`` (a point index; -1: the point of the ball nearest ``x``) come first and return their
    count: what a footprint or a gain at x on that sheet reaches, never a wall's other side.
    ``Nrm`` must be oriented (``index.sheet_normals``); ``gap`` inf keeps all. An anchor not in the
    ball is put first (the ball must have room for one more)."""
    if not gap < np.inf or cnt == 0:
        return cnt
    pos = -1
    if anchor < 0:
        best = np.inf
        for t in range(cnt):
            dd = _dist2(P[ball[t]], x)
            if dd < best:
                best, pos = dd, t
    else:
        for t in range(cnt):
            if ball[t] == anchor:
                pos = t
                break
        if pos < 0:
            ball[cnt] = anchor
            pos = cnt
            cnt += 1
    ball[0], ball[pos] = ball[pos], ball[0]
    # Oriented normals (index.orient_normal_lines): the anchor's sheet is every point whose normal
    # is within 120 degrees of the anchor's, whatever its offset. A wall's other side points the
    # opposite way; a face over an edge turns by 90; a curved sheet turns gradually, so no part of
    # it is cut off the way offsets along one normal line cut the far rim of a curved ball.
    j0 = ball[0]
    n0, n1, n2 = Nrm[j0, 0], Nrm[j0, 1], Nrm[j0, 2]
    m = 0
    for t in range(cnt):
        j = ball[t]
        if Nrm[j, 0] * n0 + Nrm[j, 1] * n1 + Nrm[j, 2] * n2 > -SHEET_COS:
            ball[m], ball[t] = ball[t], ball[m]
            m += 1
    return m


@njit
def _plane_normal(P, nb, m, G, V, W):
    """Unit normal (3,) of the least-squares plane through ``P[nb[:m]]`` (least variance)."""
    c0 = c1 = c2 = 0.0
    for t in range(m):
        j = nb[t]
        c0 += P[j, 0]
        c1 += P[j, 1]
        c2 += P[j, 2]
    c0, c1, c2 = c0 / m, c1 / m, c2 / m
    G[:3, :3] = 0.0
    for t in range(m):
        j = nb[t]
        y0, y1, y2 = P[j, 0] - c0, P[j, 1] - c1, P[j, 2] - c2
        G[0, 0] += y0 * y0
        G[0, 1] += y0 * y1
        G[0, 2] += y0 * y2
        G[1, 1] += y1 * y1
        G[1, 2] += y1 * y2
        G[2, 2] += y2 * y2
    G[1, 0], G[2, 0], G[2, 1] = G[0, 1], G[0, 2], G[1, 2]
    col = sym_eig_min(G, 3, V, W)
    out = np.empty(3)
    nn = math.sqrt(V[0, col] ** 2 + V[1, col] ** 2 + V[2, col] ** 2)
    for a in range(3):
        out[a] = V[a, col] / nn
    return out


@njit
def _inliers(P, nb, k, j, nrm, tol, out):
    """The points of ``nb[:k]`` within ``tol`` (metres) of the plane through P[j] with normal
    ``nrm`` into ``out``; returns their count."""
    m = 0
    for t in range(k):
        q = nb[t]
        if abs((P[q, 0] - P[j, 0]) * nrm[0] + (P[q, 1] - P[j, 1]) * nrm[1] + (P[q, 2] - P[j, 2]) * nrm[2]) <= tol:
            out[m] = q
            m += 1
    return m


@njit
def sheet_normals(P, perm, nodes, boxes, tpts, k, gap):
    """(n, 3) the normal line of each point of ``P`` (the tree's points, in its order), unoriented,
    fitted to its own sheet: of the planes through the point and two of its NORMAL_SEED - 1 nearest
    neighbours, the one that holds the most of its ``k`` nearest within gap/2 (the own side's: a
    plane through a point of a wall's other side, or across an edge, holds few), then twice the
    least-squares plane of the points within gap/2 of the plane so far. Computed once per cloud
    (``index.sheet_normals``); ``gap`` in metres.

    Also returns (n,) the median absolute offset (metres) of each point's NORMAL_SEED - 1 nearest
    from the plane through it along its line: the sampling's noise at that point (a median, so
    that a wall's other side among them, when thinner than the sampling, does not count).
    """
    n = P.shape[0]
    k = min(k, n)
    out = np.zeros((n, 3))
    mad = np.zeros(n)
    offs = np.empty(max(min(NORMAL_SEED, min(k, n)), 1))
    nb = np.empty(k, np.int64)
    keep = np.empty(k, np.int64)
    d2 = np.empty(k)
    G = np.zeros((3, 3))
    V = np.empty((3, 3))
    W = np.empty((3, 3))
    x = np.empty(3)
    nrm = np.empty(3)
    tol = 0.5 * gap
    top = min(NORMAL_SEED, k)
    for j in range(n):
        x[0], x[1], x[2] = P[j, 0], P[j, 1], P[j, 2]
        tree_knn(perm, nodes, boxes, tpts, x, k, nb, d2)
        best = -1
        for a in range(1, top):
            ax, ay, az = P[nb[a], 0] - x[0], P[nb[a], 1] - x[1], P[nb[a], 2] - x[2]
            la = math.sqrt(ax * ax + ay * ay + az * az)
            for b in range(a + 1, top):
                bx, by, bz = P[nb[b], 0] - x[0], P[nb[b], 1] - x[1], P[nb[b], 2] - x[2]
                lb = math.sqrt(bx * bx + by * by + bz * bz)
                c0, c1, c2 = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
                lc = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
                if not lc > 0.25 * la * lb:  # within ~15 degrees of collinear: no plane
                    continue
                d2[0], d2[1], d2[2] = c0 / lc, c1 / lc, c2 / lc
                cnt = _inliers(P, nb, k, j, d2, tol, keep)
                if cnt > best:
                    best = cnt
                    nrm[0], nrm[1], nrm[2] = d2[0], d2[1], d2[2]
        if best < 0:  # every pair nearly collinear with the point
            nrm[:] = _plane_normal(P, nb, top, G, V, W)
        for _ in range(2):
            m = _inliers(P, nb, k, j, nrm, tol, keep)
            if m < 3:
                break
            nrm[:] = _plane_normal(P, keep, m, G, V, W)
        out[j] = nrm
        for t in range(1, top):
            q = nb[t]
            offs[t - 1] = abs((P[q, 0] - x[0]) * nrm[0] + (P[q, 1] - x[1]) * nrm[1] + (P[q, 2] - x[2]) * nrm[2])
        mad[j] = np.median(offs[: top - 1]) if top > 1 else 0.0
    return out, mad


@njit
def tangent_frame(n, out_t1, out_t2):
    """t1, t2 with (t1, t2, n) right-handed orthonormal, as :func:`geometry.tangent_basis`."""
    nx, ny, nz = n[0], n[1], n[2]
    ax, ay, az = abs(nx), abs(ny), abs(nz)
    if ax <= ay and ax <= az:
        a, b, c = 0.0, nz, -ny
    elif ay <= az:
        a, b, c = -nz, 0.0, nx
    else:
        a, b, c = ny, -nx, 0.0
    inv = 1.0 / math.sqrt(a * a + b * b + c * c)
    a, b, c = a * inv, b * inv, c * inv
    out_t1[0], out_t1[1], out_t1[2] = a, b, c
    out_t2[0], out_t2[1], out_t2[2] = ny * c - nz * b, nz * a - nx * c, nx * b - ny * a


@njit
def tangential(v, n):
    """``v`` (3,) turned into the plane normal to ``n`` keeping its speed (in place)."""
    speed = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    vn = v[0] * n[0] + v[1] * n[1] + v[2] * n[2]
    t0, t1, t2 = v[0] - vn * n[0], v[1] - vn * n[1], v[2] - vn * n[2]
    norm = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    if norm > 0.0:
        f = speed / norm
        v[0], v[1], v[2] = t0 * f, t1 * f, t2 * f
    else:
        v[0], v[1], v[2] = 0.0, 0.0, 0.0


# ---------------------------------------------------------------------------------- gradient
@njit
def cubic_slope(uv, values, weights, k, degree):
    """(∂f/∂u, ∂f/∂v) at the origin of the weighted least-squares cubic (``degree`` 3) or plane
    (``degree`` 1) through ``values[:k]`` at ``uv[:k]`` (metres), as :func:`gradient.fit_cubic`."""
    rho2 = 0.0
    for t in range(k):
        r2 = uv[t, 0] * uv[t, 0] + uv[t, 1] * uv[t, 1]
        if r2 > rho2:
            rho2 = r2
    if rho2 == 0.0:
        return 0.0, 0.0
    rho = math.sqrt(rho2)
    m = 10 if degree == 3 else 3
    X = np.empty((k, m))
    for t in range(k):
        u = uv[t, 0] / rho
        v = uv[t, 1] / rho
        X[t, 0], X[t, 1], X[t, 2] = 1.0, u, v
        if m == 10:
            uu, vv = u * u, v * v
            X[t, 3], X[t, 4], X[t, 5] = uu, u * v, vv
            X[t, 6], X[t, 7], X[t, 8], X[t, 9] = uu * u, uu * v, u * vv, vv * v
    A = np.zeros((m, m))
    rhs = np.zeros(m)
    for t in range(k):
        wt = weights[t]
        for a in range(m):
            xa = X[t, a] * wt
            rhs[a] += xa * values[t]
            for b in range(a, m):
                A[a, b] += xa * X[t, b]
    # Cholesky A = L Lᵀ; a singular or badly conditioned layout falls back to SVD least squares.
    L = np.zeros((m, m))
    ok = True
    dmin, dmax = np.inf, 0.0
    for j in range(m):
        s = A[j, j]
        for t in range(j):
            s -= L[j, t] * L[j, t]
        if not (s > 0.0) or not math.isfinite(s):
            ok = False
            break
        d = math.sqrt(s)
        L[j, j] = d
        dmin = min(dmin, d)
        dmax = max(dmax, d)
        for i in range(j + 1, m):
            s = A[j, i]
            for t in range(j):
                s -= L[i, t] * L[j, t]
            L[i, j] = s / d
    coef = np.zeros(m)
    if ok and dmin * 1e6 >= dmax:
        z = np.empty(m)
        for i in range(m):
            s = rhs[i]
            for t in range(i):
                s -= L[i, t] * z[t]
            z[i] = s / L[i, i]
        for i in range(m - 1, -1, -1):
            s = z[i]
            for t in range(i + 1, m):
                s -= L[t, i] * coef[t]
            coef[i] = s / L[i, i]
        for i in range(m):
            if not math.isfinite(coef[i]):
                ok = False
    else:
        ok = False
    if not ok:
        sw = np.sqrt(weights[:k])
        coef[:] = np.linalg.lstsq(X * sw.reshape(k, 1), values[:k] * sw, 1e-10)[0]
    return coef[1] / rho, coef[2] / rho


# ---------------------------------------------------------------------------------- heap
#: Children per node of the thresholds' min-heap. A binary heap of 100k entries is 17 levels
#: deep and each level is a cache miss; with 8 children it is 6 levels, and the 8 keys a level
#: compares are adjacent in memory.
HEAP_ARITY = 8


@njit
def heap_push(hk, hi, size, key, idx):
    """Insert (key, idx) into the min-heap hk[:size], hi[:size]; returns the new size."""
    i = size
    while i > 0:
        parent = (i - 1) // HEAP_ARITY
        if hk[parent] <= key:
            break
        hk[i], hi[i] = hk[parent], hi[parent]
        i = parent
    hk[i], hi[i] = key, idx
    return size + 1


@njit
def heap_pop(hk, hi, size):
    """Remove the smallest key; returns (key, idx, new size)."""
    key, idx = hk[0], hi[0]
    size -= 1
    if size > 0:
        last_k, last_i = hk[size], hi[size]
        i = 0
        while True:
            first = HEAP_ARITY * i + 1
            if first >= size:
                break
            child = first
            ck = hk[first]
            end = min(first + HEAP_ARITY, size)
            for c in range(first + 1, end):
                if hk[c] < ck:
                    ck = hk[c]
                    child = c
            if last_k <= ck:
                break
            hk[i], hi[i] = ck, hi[child]
            i = child
        hk[i], hi[i] = last_k, last_i
    return key, idx, size


# ---------------------------------------------------------------------------------- source
@njit
def _prefetch_row(Phi, j):
    """Start loading row j of Φ: the rows a step adds are scattered over a large array (160 MB
    at 100k points, nK = 200), and loads issued together overlap instead of waiting in turn."""
    nK = Phi.shape[1]
    for q in range(0, nK, 8):  # 8 doubles per 64-byte cache line
        prefetch(Phi, j, q)
    prefetch(Phi, j, nK - 1)


@njit
def _add_row(sp, Phi, j, w0, w1, w2):
    """F_k += w_k φ_j (one row of Φ)."""
    row = Phi[j]
    f0 = sp[SP_F0]
    f1 = sp[SP_F1]
    f2 = sp[SP_F2]
    if w0 == 0.0:  # a point that stays active: p̄² does not change (the step is store-bound)
        for q in range(row.shape[0]):
            r = row[q]
            f1[q] += w1 * r
            f2[q] += w2 * r
    else:
        for q in range(row.shape[0]):
            r = row[q]
            f0[q] += w0 * r
            f1[q] += w1 * r
            f2[q] += w2 * r


@njit
def _add_rows(sp, Phi, rows, W0, W1, W2, m):
    """F_k += Σ_t W_k[t] φ_rows[t] for t < m, four rows per pass: the accumulators are read and
    written once per four rows (the loop is bound by memory traffic, not arithmetic), and the
    four rows' loads overlap (rows at the footprint's leading edge are not in cache)."""
    f0 = sp[SP_F0]
    f1 = sp[SP_F1]
    f2 = sp[SP_F2]
    nK = Phi.shape[1]
    t = 0
    while t + 4 <= m:
        ra, rb, rc, rd = Phi[rows[t]], Phi[rows[t + 1]], Phi[rows[t + 2]], Phi[rows[t + 3]]
        a0, a1, a2 = W0[t], W1[t], W2[t]
        b0, b1, b2 = W0[t + 1], W1[t + 1], W2[t + 1]
        c0, c1, c2 = W0[t + 2], W1[t + 2], W2[t + 2]
        d0, d1, d2 = W0[t + 3], W1[t + 3], W2[t + 3]
        for q in range(nK):
            x, y, z, w = ra[q], rb[q], rc[q], rd[q]
            f0[q] += (a0 * x + b0 * y) + (c0 * z + d0 * w)
            f1[q] += (a1 * x + b1 * y) + (c1 * z + d1 * w)
            f2[q] += (a2 * x + b2 * y) + (c2 * z + d2 * w)
        t += 4
    while t < m:
        _add_row(sp, Phi, rows[t], W0[t], W1[t], W2[t])
        t += 1


@njit
def _is_active(c, pbar, Z):
    # e = p̄ - c̃/Z > 0, written without the division (c̃ = 0 is active even at Z = 0).
    return c == 0.0 or c < pbar * Z


@njit
def resync(Phi, st, ztarget):
    """Full recompute of Z (the target's when ``ztarget``, PR_ZTARGET), the cloud's Z, the active
    set, the heap and the accumulators F, G (O(|T| nK)) of the :class:`State` ``st``.

    Records in fs[FS_DRIFT] the largest relative change of ∫s and of Φᵀ M s that it made
    (the round-off the incremental updates had accumulated).
    """
    pf, pb, pi, sp, hk, hi, fs, is_ = st.pf, st.pb, st.pi, st.sp, st.heap_key, st.heap_idx, st.fs, st.is_
    n = pf.shape[1]
    mass, pbar, cov = pf[PF_MASS], pf[PF_PBAR], pf[PF_COV]
    active, inheap = pb[PB_ACTIVE], pb[PB_INHEAP]
    targets = pi[PI_TARGET]
    nt = is_[IS_NTARGET]
    old_ms, Zold = fs[FS_MASS_S], fs[FS_Z]
    nK = sp.shape[1]
    inv = 1.0 / Zold if Zold > 0.0 else 0.0
    old_coef = sp[SP_F0] - 2.0 * inv * sp[SP_F1] + inv * inv * sp[SP_F2]
    Zc = 0.0
    for j in range(n):
        Zc += mass[j] * cov[j]
    fs[FS_ZC] = Zc
    if ztarget != 0.0:  # the source's coverage is normalised over the target
        Z = 0.0
        for t in range(nt):
            Z += mass[targets[t]] * cov[targets[t]]
    else:
        Z = Zc
    fs[FS_Z] = Z
    sp[SP_F0:SP_F2 + 1] = 0.0
    g0 = g1 = g2 = 0.0
    size = 0
    pending = pb[PB_PEND]
    is_[IS_NPEND] = 0
    for t in range(nt):
        j = targets[t]
        c = cov[j]
        p = pbar[j]
        pending[j] = 0
        if _is_active(c, p, Z):
            active[j], inheap[j] = 1, 0
            m = mass[j]
            w0, w1, w2 = m * p * p, m * p * c, m * c * c
            g0 += w0
            g1 += w1
            g2 += w2
            _add_row(sp, Phi, j, w0, w1, w2)
        else:
            active[j], inheap[j] = 0, 1
            size = heap_push(hk, hi, size, max(c / p, Z), j)
    is_[IS_HEAP] = size
    fs[FS_G0], fs[FS_G1], fs[FS_G2] = g0, g1, g2
    inv = 1.0 / Z if Z > 0.0 else 0.0
    ms = g0 - 2.0 * inv * g1 + inv * inv * g2
    fs[FS_MASS_S] = ms
    is_[IS_SINCE_RESYNC] = 0
    is_[IS_RESYNCS] += 1
    if is_[IS_RESYNCS] > 1 and ms > 0.0:  # the first resync initialises; later ones measure drift
        drift = abs(old_ms - ms) / ms
        big = dev = 0.0
        for q in range(nK):
            new = sp[SP_F0, q] - 2.0 * inv * sp[SP_F1, q] + inv * inv * sp[SP_F2, q]
            big = max(big, abs(new))
            dev = max(dev, abs(new - old_coef[q]))
        if big > 0.0:
            drift = max(drift, dev / big)
        fs[FS_DRIFT] = max(fs[FS_DRIFT], drift)


@njit
def _take_row(pf, pi, fs, is_, j, n, w0, w1, w2):
    """Queue row j of Φ as the n-th row this step adds (F_k += w_k φ_j), add w to G; returns n + 1.
    The rows go in pi[PI_BALL] (free after the deposits), the weights in pf[PF_W0..PF_W2]."""
    is_[IS_ROWS] += 1
    fs[FS_G0] += w0
    fs[FS_G1] += w1
    fs[FS_G2] += w2
    pi[PI_BALL, n] = j
    pf[PF_W0, n], pf[PF_W1, n], pf[PF_W2, n] = w0, w1, w2
    return n + 1


@njit
def _enter_or_wait(Phi, pf, pb, pi, hk, hi, fs, is_, j, n, size):
    """A point off the active set: it enters (its row queued) when Z has passed its threshold
    c̃/p̄, else its threshold goes onto the heap. Returns (rows queued, heap size). (The arrays one
    by one, not the :class:`State`: it runs per re-entering point, docs/speed.md.)"""
    c, p, m, Z = pf[PF_COV, j], pf[PF_PBAR, j], pf[PF_MASS, j], fs[FS_Z]
    if _is_active(c, p, Z):
        n = _take_row(pf, pi, fs, is_, j, n, m * p * p, m * p * c, m * c * c)
        _prefetch_row(Phi, j)
        pb[PB_ACTIVE, j] = 1
    else:
        size = heap_push(hk, hi, size, max(c / p, Z), j)
        pb[PB_INHEAP, j] = 1
    return n, size


@njit
def update_source(Phi, st):
    """Bring the accumulators of the :class:`State` ``st`` up to date after this step's deposits
    (points in the changed list) and the growth of Z (points whose threshold c̃/p̄ it passed enter
    the active set)."""
    pf, pb, pi, sp, hk, hi, fs, is_ = st.pf, st.pb, st.pi, st.sp, st.heap_key, st.heap_idx, st.fs, st.is_
    mass, pbar, cov, oldc = pf[PF_MASS], pf[PF_PBAR], pf[PF_COV], pf[PF_OLDC]
    active, inheap, mark, pending = pb[PB_ACTIVE], pb[PB_INHEAP], pb[PB_MARK], pb[PB_PEND]
    chg = pi[PI_CHG]
    pend = pi[PI_PEND]
    Z = fs[FS_Z]
    nrows, size = 0, is_[IS_HEAP]
    # A point the footprint deactivates waits in the pending list, not in the heap, while the
    # footprint still covers it: its c̃ (hence its threshold) is still growing, and a heap key
    # would go stale and be popped and re-pushed. Once it is left alone its key is final.
    npend = 0
    for t in range(is_[IS_NPEND]):
        j = pend[t]
        if active[j] == 1:  # re-entered through its own deposit
            pending[j] = 0
        elif mark[j] == 1:  # covered again this step: the changed list below decides
            pend[npend] = j
            npend += 1
        else:  # enters if Z passed its threshold while it was pending
            pending[j] = 0
            nrows, size = _enter_or_wait(Phi, pf, pb, pi, hk, hi, fs, is_, j, nrows, size)
    for t in range(is_[IS_NCHG]):
        j = chg[t]
        mark[j] = 0
        c0 = oldc[j]
        c1 = cov[j]
        p = pbar[j]
        m = mass[j]
        was = active[j] == 1
        now = _is_active(c1, p, Z)
        if was or now:
            fw = 1.0 if was else 0.0
            fn = 1.0 if now else 0.0
            nrows = _take_row(pf, pi, fs, is_, j, nrows, (fn - fw) * m * p * p,
                              m * p * (fn * c1 - fw * c0), m * (fn * c1 * c1 - fw * c0 * c0))
            if c0 != 0.0:  # (an untouched point's row was requested by the deposit)
                _prefetch_row(Phi, j)
        active[j] = 1 if now else 0
        if not now and inheap[j] == 0 and pending[j] == 0:
            pend[npend] = j
            npend += 1
            pending[j] = 1
    is_[IS_NCHG] = 0
    is_[IS_NPEND] = npend
    while size > 0 and hk[0] < Z:
        key, j, size = heap_pop(hk, hi, size)
        is_[IS_POPS] += 1
        inheap[j] = 0
        if active[j] == 1:
            continue  # a stale entry of a point that re-entered through its own deposit step
        # enters, or its key was stale (c̃ has grown since) and it waits for the true threshold
        nrows, size = _enter_or_wait(Phi, pf, pb, pi, hk, hi, fs, is_, j, nrows, size)
    _add_rows(sp, Phi, pi[PI_BALL], pf[PF_W0], pf[PF_W1], pf[PF_W2], nrows)
    is_[IS_HEAP] = size
    inv = 1.0 / Z if Z > 0.0 else 0.0
    fs[FS_MASS_S] = fs[FS_G0] - 2.0 * inv * fs[FS_G1] + inv * inv * fs[FS_G2]


@njit
def diffuse(sp, fs, carry):
    """One diffusion step in the eigenbasis: carry u <- D u + s̄ (a <- d ⊙ (a + b), b <- Φᵀ M s̄),
    or source u = D s̄ (a <- d ⊙ Φᵀ M s̄), with s̄ = s / ∫s."""
    Z = fs[FS_Z]
    inv = 1.0 / Z if Z > 0.0 else 0.0
    ms = fs[FS_MASS_S]
    scale = 1.0 / ms if ms > 0.0 else 0.0
    d, a, b = sp[SP_DECAY], sp[SP_A], sp[SP_B]
    f0, f1, f2 = sp[SP_F0], sp[SP_F1], sp[SP_F2]
    c1, c2 = -2.0 * inv, inv * inv
    for q in range(sp.shape[1]):
        coef = (f0[q] + c1 * f1[q] + c2 * f2[q]) * scale
        if carry:
            a[q] = d[q] * (a[q] + b[q])
            b[q] = coef
        else:
            a[q] = d[q] * coef


@njit
def sbar_at(pf, fs, j):
    """The injected source s̄ = max(p̄ - c̃/Z, 0)² / ∫s at point ``j``."""
    Z = fs[FS_Z]
    ms = fs[FS_MASS_S]
    p = pf[PF_PBAR, j]
    if not (ms > 0.0) or p == 0.0:
        return 0.0
    e = residual(p, pf[PF_COV, j] / Z if Z > 0.0 else 0.0)
    return e * e / ms


@njit
def row_dot(x, y):
    """x · y with four independent partial sums: a single running sum is bound by the
    latency of the floating-point add (the compiler may not reorder it)."""
    n = x.shape[0]
    s0 = s1 = s2 = s3 = 0.0
    m = n - n % 4
    for q in range(0, m, 4):
        s0 += x[q] * y[q]
        s1 += x[q + 1] * y[q + 1]
        s2 += x[q + 2] * y[q + 2]
        s3 += x[q + 3] * y[q + 3]
    for q in range(m, n):
        s0 += x[q] * y[q]
    return (s0 + s1) + (s2 + s3)


@njit
def project_rows(Phi, w):
    """Φᵀ w (nK,) for Φ (n, nK), w (n,), summed in a fixed order (no BLAS: a sweep's results
    must not depend on how many threads a worker's BLAS uses)."""
    out = np.zeros(Phi.shape[1])
    for j in range(Phi.shape[0]):
        wj = w[j]
        if wj != 0.0:
            row = Phi[j]
            for q in range(row.shape[0]):
                out[q] += wj * row[q]
    return out


@njit
def expand_rows(Phi, c):
    """Φ c (n,) for Φ (n, nK), c (nK,), in a fixed order (see :func:`project_rows`)."""
    out = np.empty(Phi.shape[0])
    for j in range(Phi.shape[0]):
        out[j] = row_dot(Phi[j], c)
    return out


@njit
def heat_at(Phi, pf, sp, fs, j, mode, u_full):
    """u at point ``j`` as the agents see it: Φ_j · a (+ s̄_j for carry-over), or u_full[j]. (The
    arrays one by one, not the :class:`State`: it runs per neighbour.)"""
    if mode == HEAT_FULL:
        return u_full[j]
    u = row_dot(Phi[j], sp[SP_A])
    if mode == HEAT_CARRY:
        u += sbar_at(pf, fs, j)
    return u


# ---------------------------------------------------------------------------------- coverage
@njit
def deposit(sf, st, prm, x, n):
    """Add the footprint φ(r) = exp(-ε² r²) (eq. 30, :func:`~tergodic_cli.explore.footprint.footprint`),
    r the tangent-plane distance to ``x`` with normal ``n`` (eq. 31), to every point within r_a of
    ``x`` on the sheet of the one nearest x (:func:`sheet_of`, when PR_SHEET_GAP is finite: a wall's
    other side gets nothing); note changed target points. ``sf`` :class:`Surface`, ``st`` :class:`State`."""
    P, Nrm, Phi = sf.P, sf.Nrm, sf.Phi
    pf, pb, pi, fs, is_ = st.pf, st.pb, st.pi, st.fs, st.is_
    ball = pi[PI_BALL]
    visited = tree_ball(sf.tree.perm, sf.tree.nodes, sf.tree.boxes, sf.tree.tpts, x, prm[PR_RA], ball)
    cnt = sheet_of(P, Nrm, ball, visited, x, -1, prm[PR_SHEET_GAP])
    mass, cov, oldc, phat = pf[PF_MASS], pf[PF_COV], pf[PF_OLDC], pf[PF_PHAT]
    target, mark = pb[PB_TARGET], pb[PB_MARK]
    chg = pi[PI_CHG]
    eps2, ztarget = prm[PR_EPS2], prm[PR_ZTARGET]
    have_phat = is_[IS_PHAT] == 1
    nchg, touched = is_[IS_NCHG], is_[IS_TOUCHED]
    untouched = fs[FS_REF_UNTOUCHED]
    dz = dzc = 0.0
    for t in range(cnt):
        j = ball[t]
        d0, d1, d2 = P[j, 0] - x[0], P[j, 1] - x[1], P[j, 2] - x[2]
        off = d0 * n[0] + d1 * n[1] + d2 * n[2]
        r2 = max(d0 * d0 + d1 * d1 + d2 * d2 - off * off, 0.0)
        phi = footprint(eps2, r2)
        c = cov[j]
        if target[j] == 1 and mark[j] == 0:
            mark[j] = 1
            oldc[j] = c
            chg[nchg] = j
            nchg += 1
            if c == 0.0:  # untouched, hence active: its row will be added, start loading it now
                _prefetch_row(Phi, j)
        if c == 0.0 and phi > 0.0:
            if target[j] == 1:
                touched += 1
            if have_phat:
                untouched -= phat[j] * phat[j]
        cov[j] = c + phi
        dm = mass[j] * phi
        dzc += dm
        if ztarget == 0.0 or target[j] == 1:
            dz += dm
    fs[FS_Z] += dz
    fs[FS_ZC] += dzc
    fs[FS_REF_UNTOUCHED] = untouched
    is_[IS_NCHG] = nchg
    is_[IS_TOUCHED] = touched
    is_[IS_FOOTPRINT] += visited
    return cnt


# ---------------------------------------------------------------------------------- agents
@njit
def locate(sf, x, ref, k, gap, out_xp, out_n, out_nb, d2buf):
    """Project ``x`` onto the surface fitted to those of its ``k`` nearest points (of the
    :class:`Surface` ``sf``) that lie on the nearest one's sheet (:func:`sheet_select`, ``sf.Nrm``
    the points' normal lines, ``gap`` metres);
    writes the point, its normal (oriented like ``ref``) and the neighbours (those on the sheet
    first, each group by distance to ``x``); returns how many are on the sheet. When the point
    lands nearest a neighbour off the sheet, the fit is made once more from there."""
    P, Nrm = sf.P, sf.Nrm
    tree_knn(sf.tree.perm, sf.tree.nodes, sf.tree.boxes, sf.tree.tpts, x, k, out_nb, d2buf)
    m = sheet_select(P, Nrm, out_nb, k, gap, d2buf)
    fit_project(P, out_nb, m, x, ref, out_xp, out_n)
    if m < k:
        # The projection may land nearer another sheet's point (past a convex edge, where the fit
        # of one face extends beyond it): then the surface there is that sheet's; fit it from there.
        best, near = np.inf, 0
        for t in range(k):
            dd = _dist2(P[out_nb[t]], out_xp)
            if dd < best:
                best, near = dd, t
        if near >= m:
            xq = out_xp.copy()
            tree_knn(sf.tree.perm, sf.tree.nodes, sf.tree.boxes, sf.tree.tpts, xq, k, out_nb, d2buf)
            m = sheet_select(P, Nrm, out_nb, k, gap, d2buf)
            fit_project(P, out_nb, m, xq, ref, out_xp, out_n)
    return m


@njit
def place_agent(sf, st, i, x0, ref, prm_reach, gap):
    """Project a start or reset position onto the surface (fit, project, re-query up to
    START_ITERATIONS times) and set agent ``i``'s position, normal, frame, tangent velocity."""
    P, ag, nbrs = sf.P, st.ag, st.nbrs
    k = nbrs.shape[1]
    x = x0.copy()
    r = ref.copy()
    xp = np.empty(3)
    nn = np.empty(3)
    nb = np.empty(k, np.int64)
    d2 = np.empty(k)
    m = k
    for _ in range(START_ITERATIONS):
        m = locate(sf, x, r, k, gap, xp, nn, nb, d2)
        moved = math.sqrt(_dist2(xp, x))
        x[:] = xp
        r[:] = nn
        if moved < 1e-9:
            break
    # projected into a hole or past an edge
    if nearest_distance(sf.full.perm, sf.full.nodes, sf.full.boxes, sf.full.tpts, x) > prm_reach:
        x[:] = P[nb[0]]
    ag[i, AG_POS:AG_POS + 3] = x
    ag[i, AG_NRM:AG_NRM + 3] = r
    nbrs[i, :] = nb
    ag[i, AG_NKEEP] = m
    tangent_frame(r, ag[i, AG_T1:AG_T1 + 3], ag[i, AG_T2:AG_T2 + 3])
    tangential(ag[i, AG_VEL:AG_VEL + 3], r)


@njit
def agent_gradient(sf, st, i, prm, mode):
    """∇u (3,) at agent i's projected position in its tangent plane (eqs. 32-33), fitted to its
    neighbours on its sheet (the first ag[i, AG_NKEEP] of its row of ``nbrs``), each weighted by
    the footprint at its distance."""
    P, Phi, ag, nbrs = sf.P, sf.Phi, st.ag, st.nbrs
    pf, sp, fs, u_full = st.pf, st.sp, st.fs, st.u_full
    k = int(ag[i, AG_NKEEP])
    uv = np.empty((k, 2))
    vals = np.empty(k)
    w = np.empty(k)
    eps2 = prm[PR_EPS2]
    r2min = np.inf
    for t in range(k):
        j = nbrs[i, t]
        d0, d1 = P[j, 0] - ag[i, AG_POS], P[j, 1] - ag[i, AG_POS + 1]
        d2 = P[j, 2] - ag[i, AG_POS + 2]
        u = d0 * ag[i, AG_T1] + d1 * ag[i, AG_T1 + 1] + d2 * ag[i, AG_T1 + 2]
        v = d0 * ag[i, AG_T2] + d1 * ag[i, AG_T2 + 1] + d2 * ag[i, AG_T2 + 2]
        uv[t, 0], uv[t, 1] = u, v
        r2 = u * u + v * v
        r2min = min(r2min, r2)
        w[t] = footprint(eps2, r2)
        vals[t] = heat_at(Phi, pf, sp, fs, j, mode, u_full)
    # Off the sampled surface the neighbours lie on one side: a plane, not an extrapolated cubic.
    # (too few on the sheet for the cubic's 10 unknowns: a plane too)
    degree = 3 if r2min <= prm[PR_H2] and k >= MIN_CUBIC_FIT else 1
    gu, gv = cubic_slope(uv, vals, w, k, degree)
    return ag[i, AG_T1:AG_T1 + 3] * gu + ag[i, AG_T2:AG_T2 + 3] * gv


@njit
def gain_gradient(sf, st, prm, x, t1, t2, ball, anchor, gap, broad):
    """∇G (3,) in the tangent plane (t1, t2) at ``x``, and G itself, where G(x) = Σ_j M_j e_j φ(|x - x_j|)
    is the footprint-weighted residual e = max(p̄ - c̃/Z_Ω, 0) a deposit at x would reduce: the
    descent direction of the coverage error ε (eq. 48) for the next deposit. Exact, over the points
    within GAIN_REACH r_a (φ < 1e-7 beyond, at the default ε = 2/r_a) that lie on the sheet of the
    point ``anchor`` (:func:`sheet_of`; with ``gap`` inf, or ``anchor`` -1 and ``broad``, all):
    a deposit on one side of a wall removes nothing on the other. ``broad``: the broad gain, over
    the target's tree (``sf.tgt``, its points mapped to P's by ``sf.tmap``) with a kernel BROAD_WIDTH
    times as wide, summed within BROAD_REACH widths; else over ``sf.tree`` within GAIN_REACH.
    ``ball`` (n + 1,) is scratch (left holding the indices summed)."""
    P, Nrm, pf, pb, fs, tmap = sf.P, sf.Nrm, st.pf, st.pb, st.fs, sf.tmap
    if broad:
        eps2 = prm[PR_GAIN_EPS2] / (BROAD_WIDTH * BROAD_WIDTH)
        t = sf.tgt
        cnt = tree_ball(t.perm, t.nodes, t.boxes, t.tpts, x, BROAD_REACH * 2.0 / math.sqrt(eps2), ball)
    else:
        eps2 = prm[PR_GAIN_EPS2] / (1.0 * 1.0)
        t = sf.tree
        cnt = tree_ball(t.perm, t.nodes, t.boxes, t.tpts, x, GAIN_REACH * 2.0 / math.sqrt(eps2), ball)
    mapped = not broad
    if gap < np.inf and (anchor >= 0 or not broad):  # (no extra pass over the ball otherwise)
        if broad:
            for t in range(cnt):
                ball[t] = tmap[ball[t]]
            mapped = True
        cnt = sheet_of(P, Nrm, ball, cnt, x, anchor, gap)
    mass, pbar, cov, target = pf[PF_MASS], pf[PF_PBAR], pf[PF_COV], pb[PB_TARGET]
    Z = fs[FS_ZC]
    inv = 1.0 / Z if Z > 0.0 else 0.0
    g0 = g1 = g2 = G = 0.0
    for t in range(cnt):
        j = ball[t] if mapped else tmap[ball[t]]
        if target[j] == 0:
            continue
        e = residual(pbar[j], cov[j] * inv)
        if e == 0.0:
            continue
        d0, d1, d2 = P[j, 0] - x[0], P[j, 1] - x[1], P[j, 2] - x[2]
        w = mass[j] * e * footprint(eps2, d0 * d0 + d1 * d1 + d2 * d2)
        G += w
        g0 += w * d0
        g1 += w * d1
        g2 += w * d2
    f = 2.0 * eps2
    a = f * (g0 * t1[0] + g1 * t1[1] + g2 * t1[2])
    b = f * (g0 * t2[0] + g1 * t2[1] + g2 * t2[2])
    return a * t1 + b * t2, G


@njit
def _dist2(a, b):
    d0, d1, d2 = a[0] - b[0], a[1] - b[1], a[2] - b[2]
    return d0 * d0 + d1 * d1 + d2 * d2


@njit
def try_move(sf, x, disp, ref, k, prm, out_xp, out_n, out_nb, d2buf):
    """Move from ``x`` by ``disp`` (3,) and project onto the surface fitted there (eqs. 23-27),
    shrinking the step until the projected displacement is at most v_max dt (the projection can
    lengthen it). Returns True when the result lies on the data: its nearest point of the whole
    cloud (``full``: its tree) is within PR_REACH (the fit, a plane past a sheet's edge or across
    a hole, extends beyond the points, so a projection there is refused), and how many of the
    neighbours ``out_nb`` lie on the sheet the move lands on."""
    limit = prm[PR_VMAX] * prm[PR_DT]
    xt = np.empty(3)
    scale = 1.0
    m = k
    for _ in range(STEP_ITERATIONS):
        for d in range(3):
            xt[d] = x[d] + scale * disp[d]
        m = locate(sf, xt, ref, k, prm[PR_SHEET_GAP], out_xp, out_n, out_nb, d2buf)
        moved = math.sqrt(_dist2(out_xp, x))
        if moved <= limit:
            break
        scale *= SHRINK * limit / moved
    moved = math.sqrt(_dist2(out_xp, x))
    if moved > limit:  # still long (a strongly curved fit): the chord, within round-off of the fit
        f = limit / moved
        for d in range(3):
            out_xp[d] = x[d] + (out_xp[d] - x[d]) * f
    return nearest_distance(sf.full.perm, sf.full.nodes, sf.full.boxes, sf.full.tpts, out_xp) <= prm[PR_REACH], m


@njit
def move_agent(sf, st, i, prm, mode):
    """Gradient step of agent i (eq. 6, saturated), semi-implicit Euler within v_max, then the
    move onto the surface (:func:`try_move`). A move that would leave the data (an edge, a hole,
    a gap) is not made: the velocity is reflected off the boundary (its outward normal estimated
    from where the agent's neighbours lie) and the reflected move tried, then the reversed one;
    when neither stays on the data the agent waits with zero velocity."""
    ag, nbrs, is_ = st.ag, st.nbrs, st.is_
    k = nbrs.shape[1]
    g = agent_gradient(sf, st, i, prm, mode)
    if prm[PR_GAIN] > 0.0:
        # taken where the agent's momentum carries it next (x + v dt): it cannot turn at once
        ahead = ag[i, AG_POS:AG_POS + 3] + ag[i, AG_VEL:AG_VEL + 3] * prm[PR_DT]
        # over the agent's sheet (its nearest point's): a deposit there removes nothing through a wall
        gl = gain_gradient(sf, st, prm, ahead, ag[i, AG_T1:AG_T1 + 3], ag[i, AG_T2:AG_T2 + 3], st.pi[PI_BALL],
                           nbrs[i, 0], prm[PR_SHEET_GAP], False)[0]
        # plus the same gain seen wider, over the target's points only: it pulls towards residual
        # a few footprints away that the local gain cannot see (the plate's separate shapes); on the
        # agent's sheet too (summed in 3-D it held the agent under a marking on a wall's other side:
        # median ε .741 against .706 on the mug and the shape sorter, docs/explore.md)
        gb = gain_gradient(sf, st, prm, ahead, ag[i, AG_T1:AG_T1 + 3], ag[i, AG_T2:AG_T2 + 3], st.pi[PI_BALL],
                           nbrs[i, 0], prm[PR_SHEET_GAP], True)[0]
        for d in range(3):
            g[d] = prm[PR_HEAT] * g[d] + prm[PR_GAIN] * (gl[d] + BROAD_WEIGHT * gb[d])
    gn = math.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
    a_max, v_max, dt = prm[PR_AMAX], prm[PR_VMAX], prm[PR_DT]
    acc = np.zeros(3)
    if gn > 0.0 and math.isfinite(gn):
        for d in range(3):
            acc[d] = g[d] * (a_max / gn)
    if ag[i, AG_TRANSIT] > 0.0:  # a transit: track the path's velocity, the acceleration within a_max
        for d in range(3):
            acc[d] = (ag[i, AG_VD + d] - ag[i, AG_VEL + d]) / dt
        an = math.sqrt(acc[0] * acc[0] + acc[1] * acc[1] + acc[2] * acc[2])
        if an > a_max:
            acc *= a_max / an
    x = ag[i, AG_POS:AG_POS + 3].copy()
    nrm = ag[i, AG_NRM:AG_NRM + 3].copy()
    v = ag[i, AG_VEL:AG_VEL + 3] + acc * dt
    tangential(v, nrm)  # the acceleration lies in the tangent plane already; keep v there too
    speed = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    if speed > v_max:
        v *= v_max / speed
    xp = np.empty(3)
    nn = np.empty(3)
    nb = np.empty(k, np.int64)
    d2 = np.empty(k)
    disp = v * dt
    ok, m = try_move(sf, x, disp, nrm, k, prm, xp, nn, nb, d2)
    if not ok:
        # The move leaves the data (an edge, a hole, a gap). Slide instead: of the tangent
        # directions turned by ±30°, ±60°, ... from the intended one, take the nearest that stays
        # on the data (at full, then half length), keeping the speed; else wait.
        is_[IS_EDGE] += 1
        t1 = ag[i, AG_T1:AG_T1 + 3]
        t2 = ag[i, AG_T2:AG_T2 + 3]
        vs = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
        a = v[0] * t1[0] + v[1] * t1[1] + v[2] * t1[2]
        b = v[0] * t2[0] + v[1] * t2[1] + v[2] * t2[2]
        if vs == 0.0:  # standing still: the intended way is the gradient's
            a = g[0] * t1[0] + g[1] * t1[1] + g[2] * t1[2]
            b = g[0] * t2[0] + g[1] * t2[1] + g[2] * t2[2]
            vs = v_max
        theta0 = math.atan2(b, a)
        for length in (1.0, 0.5):
            for m in range(1, 2 * SLIDE_DIRECTIONS):
                turn = (m + 1) // 2 * (math.pi / SLIDE_DIRECTIONS) * (1.0 if m % 2 == 1 else -1.0)
                ca, sa = math.cos(theta0 + turn), math.sin(theta0 + turn)
                for d in range(3):
                    v[d] = vs * (ca * t1[d] + sa * t2[d])
                    disp[d] = length * v[d] * dt
                ok, m = try_move(sf, x, disp, nrm, k, prm, xp, nn, nb, d2)
                if ok:
                    break
            if ok:
                break
        if not ok:  # wait where it is; the next gradient step picks a new way
            v[:] = 0.0
            xp[:] = x
            nn[:] = nrm
            nb[:] = nbrs[i]
            m = int(ag[i, AG_NKEEP])
    ag[i, AG_ACC:AG_ACC + 3] = acc
    ag[i, AG_POS:AG_POS + 3] = xp
    ag[i, AG_NRM:AG_NRM + 3] = nn
    nbrs[i, :] = nb
    ag[i, AG_NKEEP] = m
    tangential(v, nn)
    ag[i, AG_VEL:AG_VEL + 3] = v
    tangent_frame(nn, ag[i, AG_T1:AG_T1 + 3], ag[i, AG_T2:AG_T2 + 3])


# ---------------------------------------------------------------------------------- the step
@njit
def step_kernel(surface, state, prm, deposits, n_deposits, resets, reset_status, mode, resync_every, phase):
    """One explorer step (see explorer.py), or part of it.

    ``surface`` and ``state`` are a :class:`Surface` and a :class:`State` as plain tuples
    (:func:`plain`); ``prm`` (N_PR,) the float parameters (PR_*).
    ``n_deposits`` < 0: deposit at the agents (kinematic); otherwise at the first ``n_deposits``
    rows of ``deposits`` (contact points; each projected onto the surface, skipped when farther
    than r_a from the cloud). ``resets`` (N, 3) with ``reset_status`` (N,): when
    reset_status[i] >= 0 the agent is put at resets[i] before its gradient step (eq. 22);
    a reset farther than the start limit is refused (reset_status[i] = -2, its distance in
    resets[i, 0]). ``mode`` HEAT_*; ``resync_every`` K of :func:`resync` (0: never). ``phase`` 0:
    the whole step; 1: coverage and source only (the caller then diffuses a full field into
    ``u_full``); 2: resets and agent moves only.
    """
    sf = Surface(surface[0], surface[1], Tree(*surface[2]), Tree(*surface[3]), Tree(*surface[4]), surface[5],
                 surface[6])
    st = State(*state)
    Phi, ag = sf.Phi, st.ag
    k = st.nbrs.shape[1]
    N = ag.shape[0]
    if phase != 2:
        if n_deposits < 0:
            for i in range(N):
                deposit(sf, st, prm, ag[i, AG_POS:AG_POS + 3], ag[i, AG_NRM:AG_NRM + 3])
        else:
            xp = np.empty(3)
            nn = np.empty(3)
            nb = np.empty(k, np.int64)
            d2 = np.empty(k)
            ref = ag[0, AG_NRM:AG_NRM + 3].copy()
            for t in range(n_deposits):
                q = deposits[t]
                if nearest_distance(sf.tree.perm, sf.tree.nodes, sf.tree.boxes, sf.tree.tpts, q) > prm[PR_RA]:
                    continue  # a contact off the cloud covers no cloud point
                locate(sf, q, ref, k, prm[PR_SHEET_GAP], xp, nn, nb, d2)
                deposit(sf, st, prm, xp, nn)
        update_source(Phi, st)
        st.is_[IS_SINCE_RESYNC] += 1
        if resync_every > 0 and st.is_[IS_SINCE_RESYNC] >= resync_every:
            resync(Phi, st, prm[PR_ZTARGET])
        if phase == 1:
            return
        diffuse(st.sp, st.fs, mode == HEAT_CARRY)
    for i in range(N):
        if reset_status[i] >= 0:
            d0 = nearest_distance(sf.tree.perm, sf.tree.nodes, sf.tree.boxes, sf.tree.tpts, resets[i])
            if d0 > prm[PR_MAXSTART]:
                reset_status[i] = -2
                resets[i, 0] = d0
            else:
                place_agent(sf, st, i, resets[i], ag[i, AG_NRM:AG_NRM + 3].copy(), prm[PR_REACH], prm[PR_SHEET_GAP])
    for i in range(N):
        move_agent(sf, st, i, prm, mode)


# ---------------------------------------------------------------------------------- coverage score
# The neutral score of a trajectory (metrics.CoverageScore): c_i = Σ_t exp(-ε² |P_i - X_t|²) with
# 3-D distance, and ε = ‖max(p̄ - c̄, 0)‖₂ / ‖p̄‖₂ with p̄, c̄ unit mass in plain sums over the cloud.
# State ``ss``: SS_C = Σ c, SS_TOUCHED target points within r_a of some X_t, SS_OFF positions more
# than SC_OFFDIST from every point or than SC_OFFSHEET from the local surface of one sheet,
# SS_STEPMAX, SS_N positions scored. Parameters ``sp_``:
SS_C, SS_TOUCHED, SS_OFF, SS_STEPMAX, SS_N = 0, 1, 2, 3, 4
SC_EPS2, SC_CUT, SC_RA, SC_OFFDIST = 0, 1, 2, 3
#: The sheet gap (metres, :func:`sheet_select`) and the largest distance (metres) of a position
#: from the surface fitted to its nearest points on one sheet.
SC_GAP, SC_OFFSHEET = 4, 5
N_SC = 6


class Score(NamedTuple):
    """The score's arrays (:func:`score_position`), over the n points in the tree's order: ``cov``
    (n,) Σ_t φ, ``touched`` (n,) int8, ``target`` (n,) int8 (p > 0), ``ss`` (5,) the SS_* sums,
    and scratch: ``ball`` (n,), ``nb`` (k,) int64, ``nd2`` (k,)."""

    cov: np.ndarray
    touched: np.ndarray
    target: np.ndarray
    ss: np.ndarray
    ball: np.ndarray
    nb: np.ndarray
    nd2: np.ndarray


@njit
def sheet_distance(tree, Nrm, x, gap, nb, d2):
    """Distance (metres) from ``x`` (3,) to the surface (:func:`fit_project`) fitted to its
    ``len(nb)`` nearest points that lie on the nearest one's sheet (:func:`sheet_select`):
    how far x is off the one sheet it is nearest to; between a wall's two sides, about half
    the wall. 0 when all of them are on that sheet (nothing else is near: how far x is from the
    data is the 2h test's). ``tree`` the points' :class:`Tree`; ``nb``, ``d2`` are scratch."""
    tpts = tree.tpts
    k = nb.shape[0]
    tree_knn(tree.perm, tree.nodes, tree.boxes, tree.tpts, x, k, nb, d2)
    m = sheet_select(tpts, Nrm, nb, k, gap, d2)
    if m == k:
        return 0.0
    xp = np.empty(3)
    nn = np.empty(3)
    fit_project(tpts, nb, m, x, Nrm[nb[0]], xp, nn)
    return math.sqrt(_dist2(x, xp))


@njit
def score_position(tree, Nrm, sc, sp_, x, prev, has_prev):
    """Add position ``x`` (3,) to the :class:`Score` ``sc``: its footprint on every point within
    SC_CUT, the target points it touches (within r_a), whether it is off the surface (farther than
    SC_OFFDIST from every point, or than SC_OFFSHEET from its nearest sheet's local surface,
    :func:`sheet_distance`; ``Nrm`` the points' normal lines, ``tree`` their :class:`Tree`), its
    step from ``prev``; ``sp_`` (N_SC,) the SC_* parameters."""
    tpts = tree.tpts
    cov, touched, target, ss, ball = sc.cov, sc.touched, sc.target, sc.ss, sc.ball
    cnt = tree_ball(tree.perm, tree.nodes, tree.boxes, tree.tpts, x, sp_[SC_CUT], ball)
    eps2, ra2 = sp_[SC_EPS2], sp_[SC_RA] * sp_[SC_RA]
    near, add = np.inf, 0.0
    for t in range(cnt):
        j = ball[t]
        d0, d1, d2 = tpts[j, 0] - x[0], tpts[j, 1] - x[1], tpts[j, 2] - x[2]
        dd = d0 * d0 + d1 * d1 + d2 * d2
        near = min(near, dd)
        phi = footprint(eps2, dd)
        cov[j] += phi
        add += phi
        if dd <= ra2 and target[j] != 0 and touched[j] == 0:
            touched[j] = 1
            ss[SS_TOUCHED] += 1.0
    ss[SS_C] += add
    off = False
    if near > sp_[SC_OFFDIST] * sp_[SC_OFFDIST]:  # (the ball reaches past SC_OFFDIST: else ask the tree)
        off = nearest_distance(tree.perm, tree.nodes, tree.boxes, tree.tpts, x) > sp_[SC_OFFDIST]
    if not off:
        off = sheet_distance(tree, Nrm, x, sp_[SC_GAP], sc.nb, sc.nd2) > sp_[SC_OFFSHEET]
    if off:
        ss[SS_OFF] += 1.0
    if has_prev:
        ss[SS_STEPMAX] = max(ss[SS_STEPMAX], math.sqrt(_dist2(x, prev)))
    ss[SS_N] += 1.0


@njit
def score_step(tree, Nrm, score, sp_, X, prev):
    """:func:`score_position` for each agent's position X[i] (N, 3), then prev[i] = X[i]: one step of
    the score. ``tree`` and ``score`` are a :class:`Tree` and a :class:`Score` as plain tuples
    (:func:`plain`: one call a step, on numba's fast path)."""
    tr, sc = Tree(*tree), Score(*score)
    has_prev = sc.ss[SS_N] > 0
    for i in range(X.shape[0]):
        score_position(tr, Nrm, sc, sp_, X[i], prev[i], has_prev)
        prev[i, :] = X[i]


@njit
def score_epsilon(cov, tlist, pplain, ss):
    """ε = ‖max(p̄ - c/Σc, 0)‖₂ / ‖p̄‖₂ over the target points ``tlist`` (p̄ = 0 elsewhere): O(|T|)."""
    C = ss[SS_C]
    inv = 1.0 / C if C > 0.0 else 0.0
    num = den = 0.0
    for t in range(tlist.shape[0]):
        j = tlist[t]
        p = pplain[j]
        den += p * p
        num += source(p, cov[j] * inv)
    return math.sqrt(num / den) if den > 0.0 else 0.0
