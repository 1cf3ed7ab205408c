"""Numba kernels of :mod:`tergodic_cli.basis.fast_laplacian` (the algorithm is described there).

This file is compiled twice: just in time by numba (``backend="jit"``), and ahead of time into a
standalone extension by :mod:`tergodic_cli.basis.fast_laplacian_aot` (``make`` does it), which loads
in under a millisecond without importing numba. The compiled module's name carries a hash of this
file, so an edit here makes the built module stale, and it is ignored until it is rebuilt.

Entry point: :func:`laplacian_pipeline`, with the signature :data:`PIPELINE_SIGNATURE`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


# Constants of robust_laplacian 1.1.0 (build_delaunay_triangulations) and geometry-central (flipToDelaunay).
_PERTURB_THRESH = 1e-7
_ANGLE_COLLINEAR_THRESH = 1e-5
_OUTSIDE_EPS = 1e-4
_DELAUNAY_EPS = 1e-6

#: Guard margins. Our normals differ from Eigen's by ~1e-15, chart coordinates by ~1e-15 relative;
#: decisions closer than these to a threshold are refused.
_MARGIN = 1e-9  # dimensionless tests (sine, angle, cotan weight)
_CIRCLE_MARGIN = 1e-12  # empty-circle test, times (size / sine of the angle between the legs)



@njit(cache=True)
def _pseudo_angle(x, y):
    """A cheap stand-in for atan2(y, x): same order on (-pi, pi] (signed zeros included), range (-2, 2],
    p(angle + pi) = p(angle) + 2, and slope between 1/2 and 1 per radian. Exact atan2 is taken only near ties."""
    t = 1.0 - x / (abs(x) + abs(y))
    if y > 0.0 or (y == 0.0 and math.copysign(1.0, y) > 0.0):
        return t
    return -t


# ----------------------------------------------------------------------------------------------------------------
# step 1: neighbours. The library's k-d tree (nanoflann 1.3.2, leaves of at most 10 points, splits at the middle
# of the cell's widest side) is rebuilt here and searched in the same order, so that points at exactly equal
# distance come out in the library's order and the same one is left out at the k-th place.



@njit(cache=True)
def _split_pass(points, vind, left, count, cut, cutval, lft, strict):
    """One pass of nanoflann's planeSplit over ``vind[left:left + count]`` from position ``lft``:
    points with coordinate ``cut`` below ``cutval`` (``<`` when ``strict``, else ``<=``) are
    swapped to the front, with nanoflann's exact swaps; returns where the front ends."""
    rgt = count - 1
    while True:
        while lft <= rgt and (points[vind[left + lft], cut] < cutval if strict
                              else points[vind[left + lft], cut] <= cutval):
            lft += 1
        while rgt != 0 and lft <= rgt and not (points[vind[left + rgt], cut] < cutval if strict
                                               else points[vind[left + rgt], cut] <= cutval):
            rgt -= 1
        if lft > rgt or rgt == 0:
            break
        t = vind[left + lft]
        vind[left + lft] = vind[left + rgt]
        vind[left + rgt] = t
        lft += 1
        rgt -= 1
    return lft


@njit(cache=True)
def _kd_build(points):
    """The k-d tree: (vind, child1, child2, lo, hi, feat, divlow, divhigh); leaves have child1 = -1, range [lo, hi)."""
    n = points.shape[0]
    leaf_max = 10
    vind = np.arange(n)
    cap = 2 * n + 8  # a node splits only above 10 points, but its children can be as small as one point
    child1 = np.full(cap, -1, dtype=np.int64)
    child2 = np.full(cap, -1, dtype=np.int64)
    lo = np.zeros(cap, dtype=np.int64)
    hi = np.zeros(cap, dtype=np.int64)
    feat = np.zeros(cap, dtype=np.int64)
    divlow = np.zeros(cap)
    divhigh = np.zeros(cap)
    box_in = np.empty((cap, 3, 2))  # the cell handed down by the parent
    box_out = np.empty((cap, 3, 2))  # the points' actual bounds, handed up
    for d in range(3):
        box_in[0, d, 0] = points[0, d]
        box_in[0, d, 1] = points[0, d]
    for q in range(1, n):
        for d in range(3):
            if points[q, d] < box_in[0, d, 0]:
                box_in[0, d, 0] = points[q, d]
            if points[q, d] > box_in[0, d, 1]:
                box_in[0, d, 1] = points[q, d]
    lo[0] = 0
    hi[0] = n
    nn = 1
    stack = np.empty(cap, dtype=np.int64)
    sp_ = 0
    stack[sp_] = 0
    sp_ += 1
    while sp_ > 0:
        sp_ -= 1
        node = stack[sp_]
        left = lo[node]
        right = hi[node]
        if right - left <= leaf_max:
            for d in range(3):
                box_out[node, d, 0] = points[vind[left], d]
                box_out[node, d, 1] = points[vind[left], d]
            for t in range(left + 1, right):
                for d in range(3):
                    v = points[vind[t], d]
                    if box_out[node, d, 0] > v:
                        box_out[node, d, 0] = v
                    if box_out[node, d, 1] < v:
                        box_out[node, d, 1] = v
            continue
        count = right - left
        # middle split: among sides within (1 - 1e-5) of the widest, the one whose points spread most
        max_span = box_in[node, 0, 1] - box_in[node, 0, 0]
        for d in range(1, 3):
            span = box_in[node, d, 1] - box_in[node, d, 0]
            if span > max_span:
                max_span = span
        max_spread = -1.0
        cut = 0
        cut_mn = cut_mx = points[vind[left], 0]  # what the scan gives when the box is a point
        for d in range(3):
            span = box_in[node, d, 1] - box_in[node, d, 0]
            if span > (1.0 - 0.00001) * max_span:
                mn = points[vind[left], d]
                mx = mn
                for t in range(left + 1, right):
                    v = points[vind[t], d]
                    if v < mn:
                        mn = v
                    if v > mx:
                        mx = v
                if mx - mn > max_spread:
                    cut = d
                    max_spread = mx - mn
                    cut_mn = mn  # nanoflann scans the cut dimension again; the same values
                    cut_mx = mx
        split = (box_in[node, cut, 0] + box_in[node, cut, 1]) / 2
        mn = cut_mn
        mx = cut_mx
        cutval = mn if split < mn else (mx if split > mx else split)
        # two-pass partition: < cutval | == cutval | > cutval, with nanoflann's swaps
        lim1 = _split_pass(points, vind, left, count, cut, cutval, 0, True)
        lim2 = _split_pass(points, vind, left, count, cut, cutval, lim1, False)
        half = count // 2
        idx = lim1 if lim1 > half else (lim2 if lim2 < half else half)
        feat[node] = cut
        c1 = nn
        c2 = nn + 1
        nn += 2
        child1[node] = c1
        child2[node] = c2
        lo[c1] = left
        hi[c1] = left + idx
        lo[c2] = left + idx
        hi[c2] = right
        for d in range(3):
            for e in range(2):
                box_in[c1, d, e] = box_in[node, d, e]
                box_in[c2, d, e] = box_in[node, d, e]
        box_in[c1, cut, 1] = cutval
        box_in[c2, cut, 0] = cutval
        stack[sp_] = c2
        stack[sp_ + 1] = c1
        sp_ += 2
    # bounds flow back up: children are created after their parents
    for node in range(nn - 1, -1, -1):
        if child1[node] < 0:
            continue
        c1 = child1[node]
        c2 = child2[node]
        divlow[node] = box_out[c1, feat[node], 1]
        divhigh[node] = box_out[c2, feat[node], 0]
        for d in range(3):
            box_out[node, d, 0] = min(box_out[c1, d, 0], box_out[c2, d, 0])
            box_out[node, d, 1] = max(box_out[c1, d, 1], box_out[c2, d, 1])
    return vind, child1[:nn], child2[:nn], lo[:nn], hi[:nn], feat[:nn], divlow[:nn], divhigh[:nn]


@njit(cache=True)
def _knn(points, k):
    """Each point's k + 1 nearest points (itself included), in nanoflann's order.

    Returns
    -------
    nbr : (n, k + 1) int64
        Row i: i itself, then its k neighbours nearest first (the library's list).
    d2 : (n, k + 1) float64
        Squared distances as nanoflann computes them.
    dup : (n,) bool
        A distinct point at distance 0 (the library then drops the last neighbour instead of i).
    """
    n = points.shape[0]
    vind, child1, child2, lo, hi, feat, divlow, divhigh = _kd_build(points)
    kk = k + 1
    rid = np.empty(kk, dtype=np.int64)
    rd = np.empty(kk)
    nbr = np.empty((n, kk), dtype=np.int64)
    d2 = np.empty((n, kk))
    dup = np.zeros(n, dtype=np.bool_)
    cap = child1.shape[0] + 8  # one deferred child per tree level at most
    st_node = np.empty(cap, dtype=np.int64)
    st_min = np.empty(cap)
    st_d = np.empty((cap, 3))
    q = np.empty(3)
    dd = np.empty(3)
    for ii in range(n):
        i = vind[ii]  # queries in leaf order: consecutive queries walk the same part of the tree
        q[0] = points[i, 0]
        q[1] = points[i, 1]
        q[2] = points[i, 2]
        cnt = 0
        rd[kk - 1] = 1.7976931348623157e308  # DBL_MAX, as nanoflann initialises the worst distance
        dd[0] = 0.0
        dd[1] = 0.0
        dd[2] = 0.0
        node = 0
        mind = 0.0
        sp_ = 0
        while True:
            # descend to the nearer child; the farther one is searched later (nanoflann's recursion order)
            # if its cell can still hold a point nearer than the k-th found by then
            while child1[node] >= 0:
                f = feat[node]
                val = q[f]
                if (val - divlow[node]) + (val - divhigh[node]) < 0:
                    best = child1[node]
                    st_node[sp_] = child2[node]
                    cut_dist = (val - divhigh[node]) * (val - divhigh[node])
                else:
                    best = child2[node]
                    st_node[sp_] = child1[node]
                    cut_dist = (val - divlow[node]) * (val - divlow[node])
                st_min[sp_] = mind + cut_dist - dd[f]
                st_d[sp_, 0] = dd[0]
                st_d[sp_, 1] = dd[1]
                st_d[sp_, 2] = dd[2]
                st_d[sp_, f] = cut_dist
                sp_ += 1
                node = best
            worst = rd[kk - 1]  # nanoflann reads it once per leaf
            for t in range(lo[node], hi[node]):
                j = vind[t]
                e0 = q[0] - points[j, 0]
                e1 = q[1] - points[j, 1]
                e2 = q[2] - points[j, 2]
                dist = 0.0
                dist += e0 * e0
                dist += e1 * e1
                dist += e2 * e2
                if dist < worst:
                    c = cnt
                    while c > 0 and rd[c - 1] > dist:
                        if c < kk:
                            rd[c] = rd[c - 1]
                            rid[c] = rid[c - 1]
                        c -= 1
                    if c < kk:
                        rd[c] = dist
                        rid[c] = j
                    if cnt < kk:
                        cnt += 1
            node = -1
            while sp_ > 0:
                sp_ -= 1
                if st_min[sp_] <= rd[kk - 1]:
                    node = st_node[sp_]
                    mind = st_min[sp_]
                    dd[0] = st_d[sp_, 0]
                    dd[1] = st_d[sp_, 1]
                    dd[2] = st_d[sp_, 2]
                    break
            if node < 0:
                break
        # the library removes i from the list, or the last entry when i is not in it
        pos = -1
        for t in range(kk):
            if rid[t] == i:
                pos = t
                break
        nbr[i, 0] = i
        d2[i, 0] = 0.0
        c = 1
        for t in range(kk):
            if t == pos:
                continue
            if c < kk:
                nbr[i, c] = rid[t]
                d2[i, c] = rd[t]
                if rd[t] == 0.0:
                    dup[i] = True
                c += 1
        if pos < 0:
            dup[i] = True
    return nbr, d2, dup


# ----------------------------------------------------------------------------------------------------------------
# step 2: normals. The library takes the last left singular vector of a JacobiSVD (Eigen 3.3): a column-pivoted
# Householder QR of the transposed 3 x k matrix, then two-sided 2x2 Jacobi sweeps on the 3x3 triangle. The
# direction is the same for any SVD, but its sign (which decides the orientation of the local chart, hence the
# order in which triangles are emitted) is that algorithm's. We follow the same steps so the sign is the same,
# and refuse where a sign decision is within round-off of its switch point.

_DBL_MIN = 2.2250738585072014e-308
_DBL_EPS = 2.220446049250313e-16


@njit(cache=True)
def _jacobi_2x2(w, p, q):
    """Left and right plane rotations (cl, sl, cr, sr) that diagonalise w[[p, q]][:, [p, q]]; code 4 if ambiguous."""
    m00 = w[p, p]
    m01 = w[p, q]
    m10 = w[q, p]
    m11 = w[q, q]
    t = m00 + m11
    d = m10 - m01
    if abs(d) < _DBL_MIN:
        c1 = 1.0
        s1 = 0.0
    else:
        u = t / d
        tmp = np.sqrt(1.0 + u * u)
        s1 = 1.0 / tmp
        c1 = u / tmp
    # rotate rows of the 2x2 block: row0' = c row0 + s row1, row1' = -s row0 + c row1
    a00 = c1 * m00 + s1 * m10
    a01 = c1 * m01 + s1 * m11
    a11 = -s1 * m01 + c1 * m11
    deno = 2.0 * abs(a01)
    code = 0
    if deno < _DBL_MIN:
        cr = 1.0
        sr = 0.0
    else:
        tau = (a00 - a11) / deno
        if abs(tau) < 1e-7:
            code = 4
        wv = np.sqrt(tau * tau + 1.0)
        if tau > 0.0:
            tt = 1.0 / (tau + wv)
        else:
            tt = 1.0 / (tau - wv)
        sign_t = 1.0 if tt > 0.0 else -1.0
        nn = 1.0 / np.sqrt(tt * tt + 1.0)
        sr = -sign_t * (a01 / abs(a01)) * abs(tt) * nn
        cr = nn
    # left = rot1 * right^T, with right^T = (cr, -sr)
    cl = c1 * cr + s1 * sr
    sl = c1 * (-sr) + s1 * cr
    return cl, sl, cr, sr, code


@njit(cache=True)
def _svd_normal(b, wk):
    """Unit normal (last left singular vector, with Eigen JacobiSVD's sign) of the 3 x k matrix b.T.

    Parameters
    ----------
    b : (k, 3) float64
        Neighbour offsets (rows); overwritten.
    wk : (8, 3) float64
        Scratch.

    Returns
    -------
    nx, ny, nz : float
    code : int
        0, or 4 when a sign decision is too close to its switch point.
    """
    k = b.shape[0]
    # (Eigen first divides by the largest |entry|; every sign decision below is invariant to that scale)
    # column-pivoted Householder QR of b (k x 3)
    upd = wk[3]
    direct = wk[4]
    for c in range(3):
        acc = 0.0
        for j in range(k):
            acc += b[j, c] * b[j, c]
        direct[c] = np.sqrt(acc)
        upd[c] = direct[c]
    perm = np.empty(3, dtype=np.int64)
    for c in range(3):
        perm[c] = c
    code = 0
    for kk in range(3):
        big = kk
        for c in range(kk + 1, 3):
            if upd[c] > upd[big]:
                big = c
        for c in range(kk, 3):
            if c != big and abs(upd[c] - upd[big]) <= 1e-9 * upd[big] and upd[big] > 0.0:
                code = 4
        if big != kk:
            for j in range(k):
                tmp = b[j, kk]
                b[j, kk] = b[j, big]
                b[j, big] = tmp
            upd[kk], upd[big] = upd[big], upd[kk]
            direct[kk], direct[big] = direct[big], direct[kk]
            perm[kk], perm[big] = perm[big], perm[kk]
        c0 = b[kk, kk]
        tail = 0.0
        for j in range(kk + 1, k):
            tail += b[j, kk] * b[j, kk]
        if tail <= _DBL_MIN:
            tau = 0.0
            beta = c0
            for j in range(kk + 1, k):
                b[j, kk] = 0.0
        else:
            beta = np.sqrt(c0 * c0 + tail)
            if abs(c0) <= 1e-9 * beta:
                code = 4
            if c0 >= 0.0:
                beta = -beta
            inv = 1.0 / (c0 - beta)
            for j in range(kk + 1, k):
                b[j, kk] = b[j, kk] * inv
            tau = (beta - c0) / beta
        b[kk, kk] = beta
        if tau != 0.0:
            for c in range(kk + 1, 3):
                acc = 0.0
                for j in range(kk + 1, k):
                    acc += b[j, kk] * b[j, c]
                acc += b[kk, c]
                b[kk, c] -= tau * acc
                for j in range(kk + 1, k):
                    b[j, c] -= tau * b[j, kk] * acc
        for c in range(kk + 1, 3):
            if upd[c] != 0.0:
                tmp = abs(b[kk, c]) / upd[c]
                tmp = (1.0 + tmp) * (1.0 - tmp)
                if tmp < 0.0:
                    tmp = 0.0
                r = upd[c] / direct[c]
                tmp2 = tmp * r * r
                if tmp2 <= np.sqrt(_DBL_EPS):
                    acc = 0.0
                    for j in range(kk + 1, k):
                        acc += b[j, c] * b[j, c]
                    direct[c] = np.sqrt(acc)
                    upd[c] = direct[c]
                else:
                    upd[c] *= np.sqrt(tmp)
    # work matrix W = R^T (lower triangular), U = the column permutation
    for i in range(3):
        for j in range(3):
            wk[i, j] = b[j, i] if j <= i else 0.0
    u = wk[5:8]
    for r in range(3):
        for c in range(3):
            u[r, c] = 0.0
    for i in range(3):
        u[perm[i], i] = 1.0
    maxdiag = max(abs(wk[0, 0]), max(abs(wk[1, 1]), abs(wk[2, 2])))
    finished = False
    sweeps = 0
    while not finished and sweeps < 100:
        finished = True
        sweeps += 1
        for p in range(1, 3):
            for q in range(p):
                thr = max(_DBL_MIN, 2.0 * _DBL_EPS * maxdiag)
                if abs(wk[p, q]) > thr or abs(wk[q, p]) > thr:
                    finished = False
                    cl, sl, cr, sr, c2 = _jacobi_2x2(wk, p, q)
                    if c2:
                        code = c2
                    for c in range(3):  # W <- J_left W (rows p, q)
                        x = wk[p, c]
                        y = wk[q, c]
                        wk[p, c] = cl * x + sl * y
                        wk[q, c] = -sl * x + cl * y
                    for r in range(3):  # U <- U J_left^T (columns p, q)
                        x = u[r, p]
                        y = u[r, q]
                        u[r, p] = cl * x + sl * y
                        u[r, q] = -sl * x + cl * y
                    for r in range(3):  # W <- W J_right (columns p, q)
                        x = wk[r, p]
                        y = wk[r, q]
                        wk[r, p] = cr * x - sr * y
                        wk[r, q] = sr * x + cr * y
                    maxdiag = max(maxdiag, max(abs(wk[p, p]), abs(wk[q, q])))
    sv = wk[3]  # (the column norms are no longer needed)
    for i in range(3):
        a = wk[i, i]
        sv[i] = abs(a)
        if a < 0.0:
            for r in range(3):
                u[r, i] = -u[r, i]
    for i in range(3):
        pos = i
        for j in range(i + 1, 3):
            if sv[j] > sv[pos]:
                pos = j
        if pos != i:
            sv[i], sv[pos] = sv[pos], sv[i]
            for r in range(3):
                u[r, i], u[r, pos] = u[r, pos], u[r, i]
    # the sign of the last column follows the sign of a tiny W entry: refuse unless it is exactly zero or clear
    if sv[2] != 0.0 and sv[2] <= 1e-10 * sv[0]:
        code = 4
    if sv[1] - sv[2] <= 1e-6 * sv[0]:  # the normal itself is ill-determined
        code = 4
    nx = u[0, 2]
    ny = u[1, 2]
    nz = u[2, 2]
    r = 1.0 / np.sqrt(nx * nx + ny * ny + nz * nz)
    return nx * r, ny * r, nz * r, code


# ----------------------------------------------------------------------------------------------------------------
# steps 2-3: local fans


@njit(cache=True)
def _tangent_basis(x, y, z):
    """Two unit vectors completing (x, y, z) to a right-handed frame, exactly as geometry-central's
    ``Vector3::buildTangentBasis`` computes them (the same operations in the same order)."""
    r = 1.0 / np.sqrt(x * x + y * y + z * z)
    ux = x * r
    uy = y * r
    uz = z * r
    if abs(ux) > 0.9:
        tx, ty, tz = 0.0, 1.0, 0.0
    else:
        tx, ty, tz = 1.0, 0.0, 0.0
    ax = ty * uz - tz * uy
    ay = tz * ux - tx * uz
    az = tx * uy - ty * ux
    r = 1.0 / np.sqrt(ax * ax + ay * ay + az * az)
    ax *= r
    ay *= r
    az *= r
    bx = uy * az - uz * ay
    by = uz * ax - ux * az
    bz = ux * ay - uy * ax
    r = 1.0 / np.sqrt(bx * bx + by * by + bz * bz)
    return ax, ay, az, bx * r, by * r, bz * r


@njit(cache=True)
def _chart(i, points, nb, normal_sign, offs, wk, cx, cy, rad, ang, dirx, diry):
    """Normal and 2-D chart coordinates of point ``i``'s neighbours ``nb`` (k,), as the library computes them.

    Fills cx, cy (chart coordinates), rad (their norms), ang (pseudo-angle) and dirx, diry (unit vectors);
    returns a guard code (0 = fine).
    """
    k = nb.shape[0]
    sx = 0.0
    sy = 0.0
    sz = 0.0
    for j in range(k):
        q = nb[j]
        sx += points[q, 0]
        sy += points[q, 1]
        sz += points[q, 2]
    sx /= k + 1  # sic: the library divides the sum of k points by k + 1
    sy /= k + 1
    sz /= k + 1
    for j in range(k):
        q = nb[j]
        offs[j, 0] = points[q, 0] - sx
        offs[j, 1] = points[q, 1] - sy
        offs[j, 2] = points[q, 2] - sz
    nx, ny, nz, code = _svd_normal(offs, wk)
    if code:
        return code
    nx *= normal_sign
    ny *= normal_sign
    nz *= normal_sign
    bxx, bxy, bxz, byx, byy, byz = _tangent_basis(nx, ny, nz)
    for j in range(k):
        q = nb[j]
        vx = points[q, 0] - points[i, 0]
        vy = points[q, 1] - points[i, 1]
        vz = points[q, 2] - points[i, 2]
        d = nx * vx + ny * vy + nz * vz
        vx -= nx * d
        vy -= ny * d
        vz -= nz * d
        cx[j] = bxx * vx + bxy * vy + bxz * vz
        cy[j] = byx * vx + byy * vy + byz * vz
        rad[j] = np.sqrt(cx[j] * cx[j] + cy[j] * cy[j])
        ang[j] = _pseudo_angle(cx[j], cy[j])  # atan2 only where it decides (_walk)
        r = 1.0 / rad[j]  # the library's unit(): x * (1 / sqrt(x.x))
        dirx[j] = cx[j] * r
        diry[j] = cy[j] * r
    len_scale = rad[k - 1]
    if not np.isfinite(len_scale) or len_scale <= 0.0:
        return 15
    for j in range(k):
        if rad[j] < 2.0 * _PERTURB_THRESH * len_scale:
            return 5  # the library would perturb this point; leave such clouds to it
    return 0


@njit(cache=True)
def _walk(cx, cy, rad, ang, dirx, diry, skey, tie_swap, closest_alt, out, amb):
    """The library's angular walk over one chart. Returns (number of triangles, guard code, number of ambiguities).

    ``out[t] = (a, b)``: local indices of triangle t = (centre, a, b). ``tie_swap`` >= 0 exchanges sorted positions
    tie_swap and tie_swap + 1; ``closest_alt`` >= 0 starts at that neighbour instead of the nearest. In the plain run
    (both -1), ``amb`` receives the alternatives round-off could select: s >= 0 for a near-tie of sorted angles s and
    s + 1, -1 - j for a near-tie of neighbour j with the nearest.
    """
    k = cx.shape[0]
    plain = tie_swap < 0 and closest_alt < 0
    namb = 0
    len_scale = rad[k - 1]
    order = amb[3 * k + 1 : 4 * k + 1]  # scratch (amb: up to 2k ambiguities, then rot, then order)
    for j in range(k):  # insertion sort by angle (ties, which the caller handles, in index order)
        a = ang[j]
        t = j
        while t > 0 and skey[t - 1] > a:
            order[t] = order[t - 1]
            skey[t] = skey[t - 1]
            t -= 1
        order[t] = j
        skey[t] = a
    for s in range(k):
        if abs(ang[order[s]]) > 2.0 - 1e-11:
            return 0, 6, 0  # a point on the +-pi cut of atan2: its place in the order is round-off
    if plain:
        for s in range(k - 1):
            if ang[order[s + 1]] - ang[order[s]] <= 1e-11:  # pseudo-angle: implies within 2e-11 rad
                amb[namb] = s
                namb += 1
    if tie_swap >= 0:
        t = order[tie_swap]
        order[tie_swap] = order[tie_swap + 1]
        order[tie_swap + 1] = t
    closest = 0
    for j in range(k):
        if rad[j] < rad[closest]:
            closest = j
    if closest_alt >= 0:
        closest = closest_alt
    # Largest angular gap between consecutive sorted points, as the library computes it from atan2 values
    # (its wrap-around gap comes out negative, so it never wins). Only gaps near pi can exceed the boundary
    # threshold; a pseudo-angle gap of at least 2 - 3e-5 picks them out, and atan2 is evaluated for those.
    largest = -1.0
    largest_end = 0
    second = -1.0
    for s in range(k - 1):
        if ang[order[s + 1]] - ang[order[s]] < 2.0 - 3e-5:
            continue
        a0 = order[s]
        a1 = order[s + 1]
        g = np.arctan2(cy[a1], cx[a1]) - np.arctan2(cy[a0], cx[a0])
        if g > largest:
            second = largest
            largest = g
            largest_end = s + 1
        elif g > second:
            second = g
    gap_thresh = np.pi - _ANGLE_COLLINEAR_THRESH
    if abs(largest - gap_thresh) <= _MARGIN:
        return 0, 8, 0
    boundary = largest > gap_thresh
    if boundary:
        if largest - second <= _MARGIN:
            return 0, 8, 0
        first = largest_end
    else:
        if plain:
            for j in range(k):
                if j != closest and rad[j] - rad[closest] <= 1e-12 * rad[closest]:
                    amb[namb] = -1 - j
                    namb += 1
        first = 0
        for s in range(k):
            if order[s] == closest:
                first = s
                break
    search_end = k if boundary else k + 1
    eps = len_scale * _OUTSIDE_EPS
    rot = amb[2 * k : 3 * k + 1]  # rot[s] = order[(s + first) % k], with rot[k] = rot[0] for the wrap-around
    for s in range(k):
        q = s + first
        if q >= k:
            q -= k
        rot[s] = order[q]
    rot[k] = rot[0]
    nt = 0
    start = 0
    while start < k:
        i0 = rot[start]
        px = cx[i0]
        py = cy[i0]
        dsx = dirx[i0]
        dsy = diry[i0]
        found = False
        for end in range(start + 1, search_end):
            i1 = rot[end]
            qx = cx[i1]
            qy = cy[i1]
            dex = dirx[i1]
            dey = diry[i1]
            crs = abs(dsx * dey - dsy * dex)
            if abs(crs - _ANGLE_COLLINEAR_THRESH) <= _MARGIN:
                return 0, 9, 0
            if crs < _ANGLE_COLLINEAR_THRESH:
                continue
            # circumcentre of (0, p, q): the perpendicular bisectors of the two legs meet there
            v1x = 0.5 * px - 0.5 * qx
            v1y = 0.5 * py - 0.5 * qy
            v2x = dey
            v2y = -dex
            v3x = -dsx
            v3y = -dsy
            t1 = (v2x * v1y - v2y * v1x) / (v2x * v3x + v2y * v3y)
            ccx = 0.5 * px + t1 * (-dsy)
            ccy = 0.5 * py + t1 * dsx
            cr = np.sqrt(ccx * ccx + ccy * ccy)
            # its round-off grows like size / sin(angle between the legs)
            margin = _CIRCLE_MARGIN * (len_scale + cr) / crs
            near2 = np.inf
            lo = cr - eps - margin
            lo2 = lo * lo if lo > 0.0 else -1.0
            for j in range(k):
                if j == i0 or j == i1:
                    continue
                ex = ccx - cx[j]
                ey = ccy - cy[j]
                d2 = ex * ex + ey * ey
                if d2 < near2:
                    near2 = d2
                    if near2 < lo2:
                        break  # clearly not empty
            test = np.sqrt(near2) + eps - cr
            if abs(test) <= margin:
                return 0, 10, 0
            if test > 0.0:
                out[nt, 0] = i0
                out[nt, 1] = i1
                nt += 1
                start = end
                found = True
                break
        if not found:
            start += 1
    return nt, 0, namb


@njit(cache=True)
def _same_fan(na, outa, nba, nb_, outb, nbb):
    if na != nb_:
        return False
    for t in range(na):
        if nba[outa[t, 0]] != nbb[outb[t, 0]] or nba[outa[t, 1]] != nbb[outb[t, 1]]:
            return False
    return True


@njit(cache=True)
def _fan_one(i, points, nbr, dup, k, normal_sign, tris, nt, ws):
    """Append point ``i``'s fan (the library's) to ``tris`` from row ``nt``; return (new row count, guard code).

    Where round-off could make the library choose otherwise (the order of nearly equal angles, the nearest of
    nearly equal radii), the alternatives are walked too; if any of them gives a different fan the point is
    refused.
    """
    nb, offs, wk, cx, cy, rad, ang, dirx, diry, skey, out, out2, amb, amb2 = ws
    if dup[i]:
        return nt, 1
    for j in range(k):
        nb[j] = nbr[i, j + 1]
    code = _chart(i, points, nb, normal_sign, offs, wk, cx, cy, rad, ang, dirx, diry)
    if code:
        return nt, code
    cnt, code, namb = _walk(cx, cy, rad, ang, dirx, diry, skey, -1, -1, out, amb)
    if code:
        return nt, code
    for a in range(namb):
        swap = amb[a] if amb[a] >= 0 else -1
        alt = -1 - amb[a] if amb[a] < 0 else -1
        c2, code, _ = _walk(cx, cy, rad, ang, dirx, diry, skey, swap, alt, out2, amb2)
        if code:
            return nt, code
        if not _same_fan(cnt, out, nb, c2, out2, nb):
            return nt, 6 if amb[a] >= 0 else 7
    for t in range(cnt):
        tris[nt, 0] = i
        tris[nt, 1] = nb[out[t, 0]]
        tris[nt, 2] = nb[out[t, 1]]
        nt += 1
    return nt, 0


@njit(cache=True)
def _local_fans(points, nbr, dup, k, normal_sign, stop_early):
    """Triangles of every local fan, in the library's order.

    Parameters
    ----------
    points : (n, 3) float64
    nbr : (n, k + 1) int64
        Each point, then its neighbours (:func:`_knn`).
    dup : (n,) bool
        Points with a duplicate.
    k : int
        Neighbours per point.
    normal_sign : (n,) float64
        +1 (the library's normal) or -1 (tests only).
    stop_early : bool
        Return at the first refused point.

    Returns
    -------
    tris : (m, 3) int64
        Triangles (centre, a, b).
    codes : (n,) int8
        Guard code per point, 0 where the fan is certain to be the library's.
    """
    n = points.shape[0]
    tris = np.empty((n * k, 3), dtype=np.int64)
    ws = (np.empty(k, dtype=np.int64), np.empty((k, 3)), np.empty((8, 3)),
          np.empty(k), np.empty(k), np.empty(k), np.empty(k), np.empty(k), np.empty(k), np.empty(k),
          np.empty((k, 2), dtype=np.int64),
          np.empty((k, 2), dtype=np.int64), np.empty(4 * k + 1, dtype=np.int64), np.empty(4 * k + 1, dtype=np.int64))
    codes = np.zeros(n, dtype=np.int8)
    nt = 0
    for i in range(n):
        nt2, c = _fan_one(i, points, nbr, dup, k, normal_sign[i], tris, nt, ws)
        if c:
            codes[i] = c
            if stop_early:
                return tris[:0], codes
        else:
            nt = nt2
    used = np.zeros(n, dtype=np.bool_)
    for t in range(nt):
        for c in range(3):
            used[tris[t, c]] = True
    for i in range(n):
        if not used[i] and codes[i] == 0:
            codes[i] = 13
    return tris[:nt], codes


# ----------------------------------------------------------------------------------------------------------------
# steps 4-5: tufted cover, intrinsic Delaunay flips, cotan Laplacian


@njit(cache=True)
def _heron(a, b, c):
    s = (a + b + c) / 2.0
    arg = max(0.0, s * (s - a) * (s - b) * (s - c))
    return np.sqrt(arg)


@njit(cache=True)
def _face_cots(h, nxt, hedge, length, hc, farea):
    """Half-cotangents of the three angles of the face of halfedge ``h`` (each stored on the halfedge opposite
    the angle) and its area, from edge lengths (geometry-central's formulas)."""
    h2 = nxt[h]
    h3 = nxt[h2]
    a = length[hedge[h]]
    b = length[hedge[h2]]
    c = length[hedge[h3]]
    area = _heron(a, b, c)
    hc[h] = (-a * a + b * b + c * c) / (4.0 * area) / 2.0
    hc[h2] = (-b * b + c * c + a * a) / (4.0 * area) / 2.0
    hc[h3] = (-c * c + a * a + b * b) / (4.0 * area) / 2.0
    farea[h] = area
    farea[h2] = area
    farea[h3] = area


@njit(cache=True)
def _layout(pax, pay, pbx, pby, lbc, lca):
    dx = pbx - pax
    dy = pby - pay
    lab = np.sqrt(dx * dx + dy * dy)
    area = _heron(lab, lbc, lca)
    h = 2.0 * area / lab
    w = (lab * lab - lbc * lbc + lca * lca) / (2.0 * lab)
    ux = dx / lab
    uy = dy / lab
    return pax + w * ux - h * uy, pay + w * uy + h * ux


@njit(cache=True)
def _sort_by_angle(faces, angles, slot, lo, hi):
    """Insertion sort of ``[lo, hi)`` by angle descending, then input position (``slot``) ascending;
    that tie-break is what libstdc++'s insertion sort does for up to 16 elements (stable)."""
    for a in range(lo + 1, hi):
        hv = faces[a]
        av = angles[a]
        sv = slot[a]
        t = a
        while t > lo and (angles[t - 1] < av or (angles[t - 1] == av and slot[t - 1] > sv)):
            faces[t] = faces[t - 1]
            angles[t] = angles[t - 1]
            slot[t] = slot[t - 1]
            t -= 1
        faces[t] = hv
        angles[t] = av
        slot[t] = sv


@njit(cache=True)
def _tufted_cover(points, tris, mollify_factor, tie_guard):
    """Intrinsic tufted cover of the triangle soup ``tris`` (m, 3) with mollified 3-D edge lengths.

    Returns (nxt, tail, twin, hedge, ehalf, length, code, where): halfedge arrays (next, tail vertex, twin, edge),
    edge arrays (a halfedge, length), and a guard code (11, 12) with the edge where it fired.
    """
    n = points.shape[0]
    nf = tris.shape[0]
    nh = 3 * nf
    # ---- distinct edges (vertex pairs), numbered by first appearance; members in creation order.
    # Halfedges are bucketed by their smaller vertex; a bucket holds few distinct pairs.
    htail = np.empty(nh, dtype=np.int64)
    htip = np.empty(nh, dtype=np.int64)
    for f in range(nf):
        a0 = tris[f, 0]
        a1 = tris[f, 1]
        a2 = tris[f, 2]
        htail[3 * f] = a0
        htip[3 * f] = a1
        htail[3 * f + 1] = a1
        htip[3 * f + 1] = a2
        htail[3 * f + 2] = a2
        htip[3 * f + 2] = a0
    bcount = np.zeros(n + 1, dtype=np.int64)
    for h in range(nh):
        bcount[min(htail[h], htip[h]) + 1] += 1
    for u in range(n):
        bcount[u + 1] += bcount[u]
    bfill = bcount[:n].copy()
    bother = np.empty(nh, dtype=np.int64)  # larger vertex of each distinct pair in the bucket
    bedge = np.empty(nh, dtype=np.int64)
    hedge0 = np.empty(nh, dtype=np.int64)  # original edge of each front halfedge
    ecount = np.zeros(nh + 1, dtype=np.int64)
    ne = 0
    for h in range(nh):
        u = htail[h]
        v = htip[h]
        lo_ = min(u, v)
        hi_ = max(u, v)
        e = -1
        for t in range(bcount[lo_], bfill[lo_]):
            if bother[t] == hi_:
                e = bedge[t]
                break
        if e < 0:
            e = ne
            ne += 1
            bother[bfill[lo_]] = hi_
            bedge[bfill[lo_]] = e
            bfill[lo_] += 1
        hedge0[h] = e
        ecount[e + 1] += 1
    estart = np.empty(ne + 1, dtype=np.int64)
    estart[0] = 0
    for e in range(ne):
        estart[e + 1] = estart[e] + ecount[e + 1]
    efill = estart[:ne].copy()
    members = np.empty(nh, dtype=np.int64)
    for h in range(nh):
        e = hedge0[h]
        members[efill[e]] = h
        efill[e] += 1
    # ---- 3-D edge lengths (from the first halfedge's tail to tip)
    ncov = nh  # edges of the cover: one per pair of glued halfedges = 3 nf
    length = np.empty(ncov)
    for e in range(ne):
        h1 = members[estart[e]]
        u = htail[h1]
        v = htip[h1]
        dx = points[v, 0] - points[u, 0]
        dy = points[v, 1] - points[u, 1]
        dz = points[v, 2] - points[u, 2]
        length[e] = np.sqrt(dx * dx + dy * dy + dz * dz)
    # ---- intrinsic mollification
    if mollify_factor > 0.0:
        tot = 0.0
        for e in range(ne):
            tot += length[e]
        delta = tot / ne * mollify_factor
        meps = 0.0
        for f in range(nf):
            l0 = length[hedge0[3 * f]]
            l1 = length[hedge0[3 * f + 1]]
            l2 = length[hedge0[3 * f + 2]]
            meps = max(meps, l2 - l0 - l1 + delta)  # halfedge 3f: lA = l0, lB = l1, lC = l2
            meps = max(meps, l0 - l1 - l2 + delta)
            meps = max(meps, l1 - l2 - l0 + delta)
        for e in range(ne):
            length[e] += meps
    # ---- cover connectivity. front halfedge 3f+s: tail tris[f,s]; back copy nh+3f+s runs the other way.
    nh2 = 2 * nh
    nxt = np.empty(nh2, dtype=np.int64)
    tail = np.empty(nh2, dtype=np.int64)
    twin = np.empty(nh2, dtype=np.int64)
    hedge = np.empty(nh2, dtype=np.int64)
    for f in range(nf):
        for s in range(3):
            nxt[3 * f + s] = 3 * f + (s + 1) % 3
            tail[3 * f + s] = tris[f, s]
            nxt[nh + 3 * f + s] = nh + 3 * f + (s + 2) % 3
            tail[nh + 3 * f + s] = tris[f, (s + 1) % 3]
    ehalf = np.empty(ncov, dtype=np.int64)
    mmax = 0
    for e in range(ne):
        mmax = max(mmax, estart[e + 1] - estart[e])
    faces = np.empty(mmax, dtype=np.int64)
    angles = np.empty(mmax)
    ang_x = np.empty(mmax)
    ang_y = np.empty(mmax)
    slot = np.empty(mmax, dtype=np.int64)
    cyc = np.empty(2 * mmax, dtype=np.int64)
    alive = np.empty(2 * mmax, dtype=np.bool_)
    newe = ne
    for e in range(ne):
        m = estart[e + 1] - estart[e]
        h1 = members[estart[e]]
        # library's sibling order: h1, then the others newest first
        faces[0] = h1
        for j in range(1, m):
            faces[j] = members[estart[e] + m - j]
        ptail = tail[h1]
        ptip = tail[nxt[h1]]
        ex = points[ptip, 0] - points[ptail, 0]
        ey = points[ptip, 1] - points[ptail, 1]
        ez = points[ptip, 2] - points[ptail, 2]
        b0x, b0y, b0z, b1x, b1y, b1z = _tangent_basis(ex, ey, ez)
        for j in range(m):
            opp = tail[nxt[nxt[faces[j]]]]
            ox = points[opp, 0] - points[ptail, 0]
            oy = points[opp, 1] - points[ptail, 1]
            oz = points[opp, 2] - points[ptail, 2]
            r = 1.0 / np.sqrt(ox * ox + oy * oy + oz * oz)
            ox *= r
            oy *= r
            oz *= r
            ax = b0x * ox + b0y * oy + b0z * oz
            ay = b1x * ox + b1y * oy + b1z * oz
            ang_x[j] = ax
            ang_y[j] = ay
            angles[j] = _pseudo_angle(ax, ay)
            slot[j] = j
        # the library: std::sort by atan2, descending; for <= 16 elements libstdc++ does a stable insertion sort.
        # Sort by pseudo-angle, then redo runs of near-equal pseudo-angles with exact atan2 (ties there are real).
        _sort_by_angle(faces, angles, slot, 0, m)
        j = 0
        while j < m - 1:
            if angles[j] - angles[j + 1] > 1e-9:
                j += 1
                continue
            r0 = j
            while j < m - 1 and angles[j] - angles[j + 1] <= 1e-9:
                j += 1
            r1 = j + 1  # run [r0, r1)
            if m > 16:  # libstdc++ then uses introsort, which does not keep tied elements in order
                return nxt, tail, twin, hedge, ehalf, length, 12, e
            if tie_guard:  # optional: refuse near-ties between distinct triangles (see module docstring)
                for t in range(r0 + 1, r1):
                    if tail[nxt[nxt[faces[t]]]] != tail[nxt[nxt[faces[r0]]]]:
                        return nxt, tail, twin, hedge, ehalf, length, 11, e
            for t in range(r0, r1):
                angles[t] = np.arctan2(ang_y[slot[t]], ang_x[slot[t]])
            _sort_by_angle(faces, angles, slot, r0, r1)  # by exact angle now
        # the sibling cycle after face duplication: each front halfedge followed by its back copy
        for j in range(m):
            hs = members[estart[e]] if j == 0 else members[estart[e] + m - j]
            cyc[2 * j] = hs
            cyc[2 * j + 1] = hs + nh
            alive[2 * j] = True
            alive[2 * j + 1] = True
        eh = h1
        # glue consecutive sheets: opposite-running copy of face j with along-running copy of face j+1
        for j in range(m):
            fa = faces[j]
            fb = faces[j + 1] if j + 1 < m else faces[0]
            along_a = tail[fa] == ptail
            along_b = tail[fb] == ptail
            ha = fa + nh if along_a else fa
            hb = fb if along_b else fb + nh
            twin[ha] = hb
            twin[hb] = ha
            if j < m - 1:
                # library: e.halfedge() moves to the first remaining sibling other than ha, hb
                pe = 0
                for t in range(2 * m):
                    if cyc[t] == eh:
                        pe = t
                        break
                for t in range(2 * m):
                    q = pe + t
                    if q >= 2 * m:
                        q -= 2 * m
                    c = cyc[q]
                    if alive[q] and c != ha and c != hb:
                        eh = c
                        break
                for t in range(2 * m):
                    if cyc[t] == ha or cyc[t] == hb:
                        alive[t] = False
                hedge[ha] = newe
                hedge[hb] = newe
                ehalf[newe] = ha
                length[newe] = length[e]
                newe += 1
            else:
                hedge[ha] = e
                hedge[hb] = e
                ehalf[e] = eh
    return nxt, tail, twin, hedge, ehalf, length, 0, -1


@njit(cache=True)
def _flip_to_delaunay(nxt, tail, twin, hedge, ehalf, length):
    """Intrinsic edge flips until every cotan weight is >= -1e-6, in geometry-central's FIFO order (in place).

    Returns (hc, farea, guard code, edge): per-halfedge half-cotangent and face area of the final triangulation,
    and 14 if a weight came within 1e-9 of the flip threshold, 16 for a non-finite length.
    """
    ncov = ehalf.shape[0]
    nh2 = nxt.shape[0]
    hc = np.empty(nh2)
    farea = np.empty(nh2)
    for h in range(nh2):
        if h < nxt[h] and h < nxt[nxt[h]]:
            _face_cots(h, nxt, hedge, length, hc, farea)
    queue = np.empty(ncov, dtype=np.int64)
    inq = np.ones(ncov, dtype=np.bool_)
    for e in range(ncov):
        queue[e] = e
    qh = 0
    qn = ncov
    while qn > 0:
        e = queue[qh]
        qh += 1
        if qh == ncov:
            qh = 0
        qn -= 1
        inq[e] = False
        ha1 = ehalf[e]
        hb1 = twin[ha1]
        w = hc[ha1] + hc[hb1]
        if abs(w + _DELAUNAY_EPS) <= _MARGIN:
            return hc, farea, 14, e
        if not (w < -_DELAUNAY_EPS):
            continue
        ha2 = nxt[ha1]
        ha3 = nxt[ha2]
        hb2 = nxt[hb1]
        hb3 = nxt[hb2]
        l01 = length[hedge[ha2]]
        l12 = length[hedge[ha3]]
        l23 = length[hedge[hb2]]
        l30 = length[hedge[hb3]]
        l02 = length[e]
        p2x, p2y = _layout(0.0, 0.0, l30, 0.0, l02, l23)
        p1x, p1y = _layout(p2x, p2y, l30, 0.0, l01, l12)
        newlen = np.sqrt(p1x * p1x + p1y * p1y)
        if not np.isfinite(newlen):
            return hc, farea, 16, e
        if ha2 == hb1 or hb2 == ha1:
            continue  # a degree-1 vertex: geometry-central refuses this flip
        vc = tail[ha3]
        vd = tail[hb3]
        nxt[ha1] = hb3
        nxt[hb3] = ha2
        nxt[ha2] = ha1
        nxt[hb1] = ha3
        nxt[ha3] = hb2
        nxt[hb2] = hb1
        tail[ha1] = vc
        tail[hb1] = vd
        length[e] = newlen
        _face_cots(ha1, nxt, hedge, length, hc, farea)
        _face_cots(hb1, nxt, hedge, length, hc, farea)
        for h in (hb3, ha2, ha3, hb2):
            ee = hedge[h]
            if not inq[ee]:
                q = qh + qn
                if q >= ncov:
                    q -= ncov
                queue[q] = ee
                qn += 1
                inq[ee] = True
    return hc, farea, 0, -1


@njit(cache=True)
def _assemble(n, nxt, tail, twin, ehalf, hc, farea):
    """Cotan Laplacian (CSR, sorted columns) and lumped mass of the cover, halved and divided by three.

    Returns (indptr (n + 1,), indices, data, mass (n,)).
    """
    nh2 = nxt.shape[0]
    ncov = ehalf.shape[0]
    mass = np.zeros(n)
    for h in range(nh2):
        h2 = nxt[h]
        h3 = nxt[h2]
        if h < h2 and h < h3:  # once per face
            area = farea[h]
            mass[tail[h]] += area / 3.0
            mass[tail[h2]] += area / 3.0
            mass[tail[h3]] += area / 3.0
    for i in range(n):
        mass[i] = mass[i] * 0.5 / 3.0
    # edge weights summed per vertex pair; pairs bucketed by their smaller vertex
    diag = np.zeros(n)
    bstart = np.zeros(n + 1, dtype=np.int64)
    for e in range(ncov):
        ha = ehalf[e]
        vt = tail[ha]
        vh = tail[nxt[ha]]
        if vt != vh:
            bstart[min(vt, vh) + 1] += 1
    for u in range(n):
        bstart[u + 1] += bstart[u]
    bfill = bstart[:n].copy()
    bother = np.empty(bstart[n], dtype=np.int64)
    bsum = np.empty(bstart[n])
    deg = np.ones(n, dtype=np.int64)  # the diagonal
    for e in range(ncov):
        ha = ehalf[e]
        w = hc[ha] + hc[twin[ha]]
        vt = tail[ha]
        vh = tail[nxt[ha]]
        if vt == vh:
            continue  # a loop edge adds w + w - w - w = 0
        diag[vt] += w
        diag[vh] += w
        lo_ = min(vt, vh)
        hi_ = max(vt, vh)
        found = False
        for t in range(bstart[lo_], bfill[lo_]):
            if bother[t] == hi_:
                bsum[t] += w
                found = True
                break
        if not found:
            t = bfill[lo_]
            bother[t] = hi_
            bsum[t] = w
            bfill[lo_] += 1
            deg[lo_] += 1
            deg[hi_] += 1
    indptr = np.zeros(n + 1, dtype=np.int64)
    for i in range(n):
        indptr[i + 1] = indptr[i] + deg[i]
    nnz = indptr[n]
    indices = np.empty(nnz, dtype=np.int64)
    data = np.empty(nnz)
    fill = indptr[:n].copy()
    for i in range(n):
        indices[fill[i]] = i
        data[fill[i]] = diag[i] * 0.5 / 3.0
        fill[i] += 1
    for u in range(n):
        for t in range(bstart[u], bfill[u]):
            v = bother[t]
            val = -bsum[t] * 0.5 / 3.0
            indices[fill[u]] = v
            data[fill[u]] = val
            fill[u] += 1
            indices[fill[v]] = u
            data[fill[v]] = val
            fill[v] += 1
    for i in range(n):  # sort each row by column (rows are short)
        for a in range(indptr[i] + 1, indptr[i + 1]):
            c = indices[a]
            d = data[a]
            t = a
            while t > indptr[i] and indices[t - 1] > c:
                indices[t] = indices[t - 1]
                data[t] = data[t - 1]
                t -= 1
            indices[t] = c
            data[t] = d
    return indptr, indices, data, mass


#: numba signature of :func:`laplacian_pipeline` (the ahead-of-time build needs one).
PIPELINE_SIGNATURE = "Tuple((i8[::1], i8[::1], f8[::1], f8[::1], i8, i8))(f8[:, ::1], i8, f8, f8[::1], b1)"


@njit(cache=True)
def laplacian_pipeline(points, k, mollify_factor, normal_sign, tie_guard):
    """Steps 1-5 of the fast Laplacian in one compiled call.

    Parameters
    ----------
    points : (n, 3) float64, C-contiguous.
    k : neighbours per point.
    mollify_factor : intrinsic mollification, relative to the mean edge length.
    normal_sign : (n,) float64, +1 (or -1 to flip every normal: tests only).
    tie_guard : also refuse near-equal angles of distinct triangles around an edge (tests only).

    Returns
    -------
    indptr (n + 1,), indices, data: L in CSR with sorted columns; mass (n,); guard code (0: none)
    and where it fired (-1: nowhere). When the code is not 0 the arrays are empty.
    """
    n = points.shape[0]
    nbr, _, dup = _knn(points, k)
    tris, codes = _local_fans(points, nbr, dup, k, normal_sign, True)
    no_int = np.empty(0, dtype=np.int64)
    no_float = np.empty(0)
    for i in range(n):
        if codes[i] != 0:
            return no_int, no_int, no_float, no_float, int(codes[i]), i
    nxt, tail, twin, hedge, ehalf, length, code, where = _tufted_cover(points, tris, mollify_factor, tie_guard)
    if code:
        return no_int, no_int, no_float, no_float, code, where
    hc, farea, code, where = _flip_to_delaunay(nxt, tail, twin, hedge, ehalf, length)
    if code:
        return no_int, no_int, no_float, no_float, code, where
    indptr, indices, data, mass = _assemble(n, nxt, tail, twin, ehalf, hc, farea)
    return indptr, indices, data, mass, 0, -1


#: numba signature of :func:`mean_neighbour_distance`.
MEAN_DISTANCE_SIGNATURE = "f8(f8[:, ::1], i8)"


@njit(cache=True)
def mean_neighbour_distance(points, k):
    """Mean distance from each point to its k nearest other points (step 1's k-d tree), metres.

    The spacing h without importing ``scipy.spatial`` (~0.15 s in a fresh process). Needs k < n.
    """
    n = points.shape[0]
    _, d2, _ = _knn(points, k)
    total = 0.0
    for i in range(n):
        for j in range(1, k + 1):
            total += math.sqrt(d2[i, j])
    return total / (n * k)
