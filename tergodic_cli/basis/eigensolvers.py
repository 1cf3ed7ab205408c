"""Eigensolvers for the smallest eigenpairs of L φ = λ M φ (M diagonal, L symmetric PSD).

The default, :func:`smallest_eigenpairs`, is shift-invert Lanczos written for this problem: the
symmetric form A = S⁻¹ L S⁻¹ (S = √M), the connected components' null space deflated exactly, one
LDLᵀ factorisation (``qdldl``) of A − σI with σ inside the wanted window (its inertia counts the
eigenvalues below σ), full reorthogonalisation without restarts, and certificates (inertia counts,
true residuals) that hand over to another start vector, a negative shift, then ARPACK when they
fail.
docs/precompute.md, "The eigensolver", gives the method and its measured accuracy against
:func:`arpack_eigenpairs` (the authors' ``eigsh(L, nK, M, sigma=1e-12)``).
"""

from __future__ import annotations

import functools
import math
import warnings

import numpy as np
import qdldl
import scipy.sparse as sp
from scipy.linalg.lapack import dstevd
from scipy.sparse.csgraph import connected_components
from threadpoolctl import ThreadpoolController

from tergodic_cli.native import in_thread

#: Lanczos convergence: ‖OP y − θ y‖ ≤ TOL_RITZ |θ| for every wanted Ritz pair.
TOL_RITZ = 1e-10
#: Accepted true residual ‖A y − λ y‖ relative to the largest wanted eigenvalue ...
TOL_RESIDUAL = 1e-7
#: ... or, for very fine clouds where ‖A‖ ≫ λ_nK, relative to ‖A‖ (a backward error).
TOL_BACKWARD = 1e-10
#: Dense LAPACK below this many points, or up to DENSE_CAP_N when nK is a third of them or more.
DENSE_MAX_N = 800
DENSE_CAP_N = 6000
#: Reorthogonalisation corrections below this share of the vector are applied in float32.
SMALL_CORRECTION = 1e-6
#: Aim for this share of the wanted non-zero eigenvalues below the shift σ.
SHIFT_SHARE = 0.55


class EigensolverFailure(RuntimeError):
    """A solver could not certify its result; the caller falls back to a safer one."""


# ---------------------------------------------------------------------------------------
# Pieces


def _null_basis(L: sp.spmatrix, sqrt_mass: np.ndarray) -> np.ndarray:
    """Orthonormal null vectors Z (n, c) of A = S⁻¹ L S⁻¹: s on each connected component."""
    graph = sp.csr_matrix(L, copy=True)
    graph.data = np.abs(graph.data)
    graph.eliminate_zeros()
    n_comp, labels = connected_components(graph, directed=False)
    Z = np.zeros((L.shape[0], n_comp))
    Z[np.arange(L.shape[0]), labels] = sqrt_mass
    Z /= np.linalg.norm(Z, axis=0)
    return Z


class SymmetricFactor:
    """Sparse LDLᵀ of a symmetric (possibly indefinite) matrix K, with its inertia.

    Uses ``qdldl`` (AMD ordering, no pivoting), given only K's upper triangle.
    :meth:`refactor` factorises another matrix with the same sparsity pattern (another
    shift) reusing the ordering and symbolic analysis: 3-5x cheaper than a new factor.

    Attributes
    ----------
    n_negative : number of negative eigenvalues of K (Sylvester's law of inertia).
    """

    def __init__(self, K: sp.spmatrix, check_accuracy: bool = True):
        K = sp.csc_matrix(K)
        self.n = K.shape[0]
        try:
            # the factorisation releases the GIL but takes seconds on a dense cloud: off the main thread,
            # so Ctrl-C and SIGTERM are answered while it runs (tergodic_cli.native)
            self._solver = in_thread(qdldl.Solver, sp.triu(K, format="csc"), upper=True)
        except Exception as exc:  # zero pivot: the shift hit the spectrum
            raise EigensolverFailure(f"LDL factorisation failed ({exc})") from None
        self.solve = self._solver.solve
        self._set_inertia(self._solver.factors()[1], K if check_accuracy else None)

    def refactor(self, K: sp.spmatrix) -> "SymmetricFactor":
        """Factorise K in place (its inertia only: no accuracy check).

        Parameters
        ----------
        K : (n, n) sparse
            Same sparsity pattern as the first matrix.

        Returns
        -------
        SymmetricFactor
            ``self``.
        """
        try:
            in_thread(self._solver.update, sp.triu(K, format="csc"), upper=True)
        except Exception as exc:
            raise EigensolverFailure(f"LDL factorisation failed ({exc})") from None
        self._set_inertia(self._solver.factors()[1], None)
        return self

    def _set_inertia(self, d, K: sp.spmatrix | None) -> None:
        d = np.asarray(d, dtype=np.float64)
        if not np.all(np.isfinite(d)) or np.any(d == 0):
            raise EigensolverFailure("singular pivot")
        self.n_negative = int(np.count_nonzero(d < 0))
        if K is None:
            return
        # Without pivoting an indefinite LDLᵀ can lose accuracy to element growth: measure it.
        x = np.random.default_rng(12345).standard_normal(self.n)
        err = np.linalg.norm(self.solve(K @ x) - x) / np.linalg.norm(x)
        if not err < 1e-6:
            raise EigensolverFailure(f"inaccurate factorisation (solve error {err:.1e})")


class ShiftedMatrix:
    """A − σI for many σ with one fixed sparsity pattern (A sparse symmetric, CSC).

    ``A - sigma * identity`` would drop an entry that happens to cancel to zero, which
    would change the pattern that :meth:`SymmetricFactor.refactor` relies on.
    """

    def __init__(self, A: sp.spmatrix):
        A = sp.csc_matrix(A + sp.identity(A.shape[0], format="csc") * 0.0)  # every diagonal entry stored
        A.sort_indices()
        self.A = A
        cols = np.repeat(np.arange(A.shape[1]), np.diff(A.indptr))
        self._diag = np.flatnonzero(A.indices == cols)

    def __call__(self, sigma: float) -> sp.csc_matrix:
        data = self.A.data.copy()
        data[self._diag] -= sigma
        return sp.csc_matrix((data, self.A.indices, self.A.indptr), shape=self.A.shape)


def _choose_shift(A: "ShiftedMatrix", area: float, n_wanted: int, n_null: int) -> tuple[float, SymmetricFactor]:
    """σ with about ``SHIFT_SHARE`` of the ``n_wanted`` non-zero eigenvalues below it, and the
    factor of A − σI: Weyl's law for a surface (λ_k ≈ 4πk / area) first, then corrected by
    each factor's inertia (the exact count below σ), assuming N(λ) ∝ λ (2-D)."""
    target = max(1.0, SHIFT_SHARE * n_wanted)
    sigma = 4.0 * math.pi * (n_wanted + n_null) / area * SHIFT_SHARE * 0.75
    best = None
    for _ in range(4):
        try:
            factor = SymmetricFactor(A(sigma))
        except EigensolverFailure:
            sigma *= 0.97  # nudged off a pivot breakdown
            continue
        below = factor.n_negative - n_null
        if below <= 0.8 * n_wanted:
            best = (sigma, factor)
            if below >= 0.3 * n_wanted:
                return best
        sigma *= min(4.0, max(0.25, target / max(below, 0.5)))
    if best is None:
        raise EigensolverFailure("no usable shift found")
    return best


def _lanczos(apply_op, q0: np.ndarray, Z: np.ndarray, max_dim: int, on_check, check_from: int,
             check_every):
    """Symmetric Lanczos with full reorthogonalisation, ``Z`` (n, c) kept out of the Krylov space.

    Each new vector is orthogonalised by classical Gram-Schmidt against ``Z`` (stored in front
    of the Lanczos vectors: one product does both) and every previous vector, repeated only
    when it cancelled badly (Daniel-Gragg-Kaufman-Stewart); a tiny correction is applied from
    a float32 copy of the basis (half the memory traffic). ``on_check(alpha (m,), beta (m + 1,),
    m)`` is called from ``check_from`` steps on, then every ``check_every(m)``; True stops.
    ``beta[i]`` couples q_{i-1} and q_i, ``beta[m]`` is the residual coupling. Returns Q
    (≥ m + 1, n), whose first m rows are the Lanczos vectors, and m.
    """
    n = q0.size
    c = Z.shape[1]
    eps = np.finfo(np.float64).eps
    Q = np.empty((c + max_dim + 1, n))
    Q32 = np.empty((c + max_dim + 1, n), dtype=np.float32)
    Q[:c] = Z.T
    Q[c] = q0
    Q32[:c + 1] = Q[:c + 1]
    alpha = np.zeros(max_dim)
    beta = np.zeros(max_dim + 1)
    anorm = 0.0
    next_check = check_from
    rng = np.random.default_rng(2024)
    for j in range(max_dim):
        k = c + j  # row of q_j
        q = Q[k]
        r = apply_op(q)
        if j:
            r -= beta[j] * Q[k - 1]
        a = q @ r
        r -= a * q
        b0 = math.sqrt(r @ r)
        V = Q[:k + 1]
        h = V @ r  # against Z and every Lanczos vector
        if np.max(np.abs(h)) <= SMALL_CORRECTION * b0:
            # A tiny correction may be applied from a float32 copy of the basis: its error
            # (≤ 1e-7 of the correction) is below double rounding, and it halves the traffic.
            r -= h.astype(np.float32) @ Q32[:k + 1]
        else:
            r -= h @ V
        a += h[k]
        b = math.sqrt(r @ r)
        if b < 0.7 * b0:  # cancellation: one more pass
            h = V @ r
            r -= h @ V
            a += h[k]
            b = math.sqrt(r @ r)
        alpha[j] = a
        anorm = max(anorm, abs(a) + beta[j] + b)
        if b <= 1e3 * eps * anorm:  # invariant subspace: go on with a fresh direction
            r = rng.standard_normal(n)
            for _ in range(2):
                r -= (V @ r) @ V
            Q[k + 1] = r / math.sqrt(r @ r)
            b = 0.0
        else:
            np.multiply(r, 1.0 / b, out=Q[k + 1])
        Q32[k + 1] = Q[k + 1]
        beta[j + 1] = b
        m = j + 1
        if m >= next_check:
            if on_check(alpha[:m], beta[:m + 1], m):
                return Q[c:], m
            next_check = m + check_every(m)
    raise EigensolverFailure(f"Lanczos did not converge in {max_dim} steps")


def tridiagonal_eigh(alpha: np.ndarray, beta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenpairs of a symmetric tridiagonal matrix.

    LAPACK ``dstevd`` (divide and conquer), called directly: on this solver's Lanczos
    matrices it took half the time of ``dstemr`` (what ``scipy.linalg.eigh_tridiagonal``
    calls; 6 against 12 ms for the 4 checks at 2996 points, nK = 100). A LAPACK failure
    raises :class:`EigensolverFailure` (the next method takes over).

    Parameters
    ----------
    alpha : (m,) float
        Diagonal.
    beta : (m - 1,) float
        Off-diagonal.

    Returns
    -------
    evals : (m,) float
        Ascending.
    evecs : (m, m) float
        Orthonormal columns.
    """
    w, z, info = dstevd(alpha, beta, compute_v=1)
    if info:
        raise EigensolverFailure(f"dstevd failed (info {info})")
    return w, z


# ---------------------------------------------------------------------------------------
# Solvers


def _finish(Y: np.ndarray, L: sp.spmatrix, s: np.ndarray, Z: np.ndarray, lam_scale: float,
            report: dict) -> tuple[np.ndarray, np.ndarray]:
    """Certify Ritz vectors Y (n, ne >= 1) of A, orthonormal and orthogonal to Z (n, c), and return
    (evals (c + ne,), evecs φ (n, c + ne)). Eigenvalues are Rayleigh quotients; every true residual
    must satisfy ‖A y − λ y‖ ≤ max(TOL_RESIDUAL · max λ, TOL_BACKWARD · ‖A‖)."""
    n, ne = Y.shape
    c = Z.shape[1]
    evecs = np.empty((n, c + ne))
    evecs[:, :c] = Z / s[:, None]
    Phi = evecs[:, c:]
    np.divide(Y, s[:, None], out=Phi)  # φ = S⁻¹ y
    AY = L @ Phi  # L φ, (n, ne)
    AY /= s[:, None]  # A y
    lam = np.einsum("ij,ij->j", Y, AY)
    AY -= Y * lam
    res = np.sqrt(np.einsum("ij,ij->j", AY, AY))
    lam_top = max(lam_scale, float(np.max(np.abs(lam))))
    a_norm = float(np.max((abs(L) @ (1.0 / s)) / s))  # Gershgorin bound on ‖A‖
    worst = float(res.max() / lam_top)
    report["max_relative_residual"] = worst
    if not res.max() <= max(TOL_RESIDUAL * lam_top, TOL_BACKWARD * a_norm):
        raise EigensolverFailure(f"residual {worst:.1e} (relative to λ_max) above {TOL_RESIDUAL:.0e}")
    if np.any(lam <= 0):
        raise EigensolverFailure("a non-null Ritz value is not positive")
    evals = np.concatenate([np.zeros(c), lam])
    order = np.argsort(evals, kind="stable")
    if np.any(np.diff(order) < 0):
        evals, evecs = evals[order], np.ascontiguousarray(evecs[:, order])
    return evals, evecs


def lanczos_eigenpairs(L: sp.spmatrix, mass: np.ndarray, nk: int, *, seed: int = 0,
                       interior_shift: bool = True, report: dict | None = None):
    """Shift-invert Lanczos with deflated null space (see the module docstring).

    Parameters
    ----------
    L : (n, n) sparse symmetric PSD stiffness matrix.
    mass : (n,) positive lumped masses.
    nk : number of eigenpairs.
    seed : start-vector seed (results are deterministic).
    interior_shift : σ inside the wanted window (fast) or σ < 0 (positive definite, slower).
    report : optional dict, filled with what was done (method, shift, residual).

    Returns
    -------
    evals (nk,) ascending, evecs (n, nk) M-orthonormal.
    """
    report = {} if report is None else report
    L = sp.csr_matrix(L)
    n = L.shape[0]
    s = np.sqrt(mass)
    Z = _null_basis(L, s)
    c = Z.shape[1]
    report["components"] = c
    ne = nk - c
    if ne <= 0:  # only null vectors are wanted: they are exact
        report["method"] = "null-space"
        return np.zeros(nk), np.ascontiguousarray(Z[:, :nk] / s[:, None])
    A = L.tocoo()
    A = ShiftedMatrix(sp.csc_matrix((A.data / (s[A.row] * s[A.col]), (A.row, A.col)), shape=L.shape))  # S⁻¹ L S⁻¹
    if interior_shift:
        sigma, factor = _choose_shift(A, float(mass.sum()), ne, c)
    else:
        # 1 % of Weyl's first non-zero eigenvalue below zero: A − σI is positive definite.
        sigma = -0.01 * 4.0 * math.pi / float(mass.sum())
        factor = SymmetricFactor(A(sigma))
    n_below = factor.n_negative - (c if sigma > 0 else 0)  # non-zero eigenvalues in (0, σ)
    report.update(method="lanczos", sigma=sigma, seed=seed)
    state = {}

    def on_check(alpha, beta, m):
        theta, U = tridiagonal_eigh(alpha, beta[1:m])
        coupling = beta[m:m + 1, None]
        with np.errstate(divide="ignore"):
            lam = sigma + 1.0 / theta
        # Ritz values in the spectral gap (−1/σ, 0) map to λ < 0: never eigenvalues.
        valid = np.flatnonzero(lam > 0)
        if len(valid) < ne:
            return False
        ranked = valid[np.argsort(lam[valid], kind="stable")]
        sel = ranked[:ne]
        res = np.linalg.norm(coupling @ U[m - len(coupling):m, sel], axis=0)
        worst = float(np.max(res / (TOL_RITZ * np.abs(theta[sel]))))
        # Check again when the worst residual should pass, at the rate it fell since the
        # last check (0.5 decades a step before there is one); a check costs a few steps,
        # a late stop one step each.
        decades = math.log10(max(worst, 1e-300))
        rate = 0.5
        if "last" in state and m > state["last"][0]:
            rate = min(1.0, max(0.1, (state["last"][1] - decades) / (m - state["last"][0])))
        state["last"] = (m, decades)
        state["next_in"] = int(min(max(1, math.ceil(max(decades, 0.0) / rate)), max(4, m // 20)))
        if not worst <= 1.0:
            return False
        if int(np.count_nonzero(lam[sel] < sigma)) != n_below:
            state["next_in"] = max(4, m // 20)
            return False  # an eigenvalue below σ is still missing
        # The next Ritz value up and how far below it the next eigenvalue can be (for the count check).
        next_lo = -np.inf
        if len(ranked) > ne and theta[ranked[ne]] > 0:
            i = ranked[ne]
            r_next = float(np.linalg.norm(coupling @ U[m - len(coupling):m, i]))
            next_lo = sigma + 1.0 / (theta[i] + r_next)
        state.update(U=U[:, sel], lam=lam[sel], next_lo=next_lo)
        return True

    rng = np.random.default_rng(seed)
    X = rng.standard_normal((1, n))
    X -= (X @ Z) @ Z.T
    q0 = np.linalg.qr(X.T)[0][:, 0]
    max_dim = int(min(n - c - 1, 3 * ne + 100))
    # Lanczos typically needs ne + ~7 √ne steps here; start checking a little before.
    check_from = int(min(max_dim, ne + max(8, 5 * math.sqrt(ne))))
    Q, m = _lanczos(factor.solve, q0, Z, max_dim, on_check, check_from,
                   check_every=lambda m: state.get("next_in", max(4, m // 20)))
    Y = Q[:m].T @ state["U"]  # Ritz vectors as columns, (n, ne)
    evals, evecs = _finish(Y, L, s, Z, float(np.max(state["lam"])), report)
    # Completeness: Sylvester's law must count exactly nk eigenvalues below a point τ just
    # above the largest one found. This catches an eigenvalue Lanczos skipped (e.g. one
    # copy of an exactly repeated eigenvalue), above σ where the first count cannot see.
    top = float(evals[-1])
    tau = 0.5 * (top + state["next_lo"]) if state["next_lo"] > top * (1 + 1e-6) else top * (1 + 1e-7)
    count = factor.refactor(A(tau)).n_negative  # the solves are done: reuse the factor's analysis
    if count != nk:
        raise EigensolverFailure(f"{count} eigenvalues lie below {tau:.6g}, {nk} were found")
    return evals, evecs


def _dense_eigenpairs(L: sp.spmatrix, mass: np.ndarray, nk: int, report: dict):
    """LAPACK on the dense symmetric form, null space deflated exactly (small clouds)."""
    from scipy.linalg import eigh

    s = np.sqrt(mass)
    Z = _null_basis(L, s)
    c = Z.shape[1]
    report.update(method="dense", components=c)
    ne = nk - c
    if ne <= 0:  # only null vectors are wanted: they are exact
        report["method"] = "null-space"
        return np.zeros(nk), np.ascontiguousarray(Z[:, :nk] / s[:, None])
    A = (sp.csr_matrix(L).toarray() / s) / s[:, None]
    A = 0.5 * (A + A.T)
    # Lift the null space above the spectrum so the first ne eigenpairs are the wanted ones.
    A += (2.0 * np.abs(A).sum(axis=1).max() + 1.0) * (Z @ Z.T)
    w, Y = eigh(A, subset_by_index=[0, ne - 1], driver="evr")
    return _finish(np.ascontiguousarray(Y), L, s, Z, float(np.max(np.abs(w))), report)


def arpack_eigenpairs(L: sp.spmatrix, mass: np.ndarray, nk: int, sigma: float = 1e-12,
                      v0: np.ndarray | None = None):
    """The reference method of the authors' code: ``eigsh(L, nk, M, sigma=1e-12)``, sorted.

    Parameters
    ----------
    L : (n, n) sparse
        The Laplacian.
    mass : (n,) float
        Lumped mass, m².
    nk : int
        Eigenpairs wanted.
    sigma : float
        The shift, 1/m².
    v0 : (n,) float, optional
        ARPACK's start vector.

    Returns
    -------
    evals : (nk,) float
        Ascending, 1/m².
    evecs : (n, nk) float
        M-orthonormal (as ARPACK returns them).
    """
    from scipy.sparse.linalg import eigsh

    evals, evecs = in_thread(eigsh, sp.csc_matrix(L), k=nk, M=sp.diags(mass).tocsc(), sigma=sigma, v0=v0)
    order = np.argsort(evals)
    return evals[order], evecs[:, order]


@functools.lru_cache(maxsize=1)
def _blas_controller():
    """The controller limiting BLAS to one thread per solve, built once (~5 ms). The solver's dense
    work is memory-bound: a second thread gains little on a quiet machine and costs 2-3x when the
    other core is busy (2.4-3.0 s instead of 0.8-1.1 s at 3684 points, nK = 200)."""
    return ThreadpoolController()


def smallest_eigenpairs(L: sp.spmatrix, mass: np.ndarray, nk: int, *, seed: int = 0,
                        report: dict | None = None):
    """The ``nk`` smallest eigenpairs of L φ = λ M φ by the fastest certified method.

    Tries, in order: dense LAPACK (small clouds) or Lanczos with an interior shift, the
    same from another start vector, Lanczos with a negative shift, ARPACK. Each but the
    last certifies its result (see the module docstring) or hands over to the next.

    Parameters
    ----------
    L : (n, n) sparse
        The Laplacian.
    mass : (n,) float
        Lumped mass, m².
    nk : int
        Eigenpairs wanted.
    seed : int
        Seed of the Lanczos start vectors.
    report : dict, optional
        Filled with the methods tried and their checks.

    Returns
    -------
    evals : (nk,) float
        Ascending, 1/m² (exact zeros for the c connected components).
    evecs : (n, nk) float
        Φᵀ M Φ = I.
    """
    report = {} if report is None else report
    n = L.shape[0]
    if n <= DENSE_MAX_N or (3 * nk >= n and n <= DENSE_CAP_N):
        attempts = [("dense", lambda: _dense_eigenpairs(L, mass, nk, report))]
    else:  # another start vector may show a copy of a repeated eigenvalue the first one missed
        lanczos = functools.partial(lanczos_eigenpairs, L, mass, nk, report=report)
        attempts = [("lanczos", lambda: lanczos(seed=seed)), ("lanczos-restart", lambda: lanczos(seed=seed + 1)),
                    ("lanczos-negative-shift", lambda: lanczos(seed=seed, interior_shift=False))]
    for name, attempt in attempts:
        try:
            with _blas_controller().limit(limits=1, user_api="blas"):
                return attempt()
        except EigensolverFailure as exc:
            report.setdefault("fallbacks", []).append(f"{name}: {exc}")
    warnings.warn(f"eigensolver fell back to ARPACK ({'; '.join(report['fallbacks'])})", RuntimeWarning,
                  stacklevel=2)
    report["method"] = "arpack"
    rng = np.random.default_rng(seed)
    # A shift below zero keeps L − σM non-singular however many components the cloud has.
    sigma = -0.01 * 4.0 * math.pi / float(mass.sum())
    evals, evecs = arpack_eigenpairs(L, mass, nk, sigma=sigma, v0=rng.standard_normal(n))
    evals[np.abs(evals) < 1e-9 * max(abs(float(evals[-1])), 1e-300)] = 0.0
    return evals, evecs
