"""The fast eigensolver against independent references: ARPACK shift-invert and dense LAPACK.

Agreement is checked the way it matters for a basis: eigenvalues to 1e-6 relative, and
eigenspaces (not individual vectors, which are arbitrary inside a cluster of equal
eigenvalues) by the largest principal angle per cluster.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from conftest import jittered_square

from tergodic_cli.basis import eigensolvers as es
from tergodic_cli.basis.core import compute_laplacian, solve_eigenpairs
from tergodic_cli.capture.synthetic import generate_synthetic

EIG_RTOL = 1e-6
ANGLE_TOL = 1e-6
CLUSTER_RTOL = 1e-3  # eigenvalues closer than this (relative) form one eigenspace


def arpack_reference(L, mass, nk):
    """scipy eigsh in shift-invert mode; a shift below 0 keeps it non-singular for any number of components."""
    return es.arpack_eigenpairs(L, mass, nk, sigma=-1e-3 * 4 * np.pi / mass.sum())


def clusters(evals: np.ndarray, rtol: float = CLUSTER_RTOL) -> list[list[int]]:
    """Index groups of (near-)equal ascending eigenvalues, the zeros one group: eigenvectors are
    defined only up to a rotation inside a group, so solvers are compared per group."""
    floor = 1e-9 * abs(evals[-1])
    groups = [[0]]
    for i in range(1, len(evals)):
        if evals[i] - evals[i - 1] <= rtol * max(abs(evals[i]), floor):
            groups[-1].append(i)
        else:
            groups.append([i])
    return groups


def max_principal_angle_sine(A: np.ndarray, B: np.ndarray, mass: np.ndarray) -> float:
    """sin of the largest principal angle between span(A) and span(B), both M-orthonormal (n, p)."""
    resid = B - A @ (A.T @ (mass[:, None] * B))
    return float(np.linalg.norm(np.sqrt(mass)[:, None] * resid, 2))


def assert_same_eigenpairs(evals, evecs, ref_evals, ref_evecs, mass, nk):
    """Eigenvalues to EIG_RTOL relative (absolute floor for the zeros) and the same eigenspaces."""
    floor = 1e-9 * ref_evals[-1]
    rel = np.abs(evals - ref_evals) / np.maximum(np.abs(ref_evals), floor)
    assert rel.max() <= EIG_RTOL, (rel.argmax(), evals[rel.argmax()], ref_evals[rel.argmax()])
    groups = clusters(ref_evals)
    if groups[-1][-1] == nk - 1 and len(groups[-1]) > 1:
        groups = groups[:-1]  # a cluster cut by the nK boundary has no well-defined span
    for g in groups:
        sine = max_principal_angle_sine(evecs[:, g], ref_evecs[:, g], mass)
        assert sine <= ANGLE_TOL, (g, ref_evals[g], sine)


def assert_basis_invariants(evals, evecs, mass, n_components):
    nk = len(evals)
    gram = evecs.T @ (mass[:, None] * evecs)
    np.testing.assert_allclose(gram, np.eye(nk), atol=1e-8)
    assert np.all(np.diff(evals) >= 0)
    assert np.count_nonzero(evals <= 1e-9 * evals[-1]) == n_components
    assert np.all(evals[n_components:] > 0)


@pytest.fixture(scope="module")
def bowl():
    points = generate_synthetic("bowl", "X", seed=1, spacing=0.003).points  # ~2.9k points
    L, mass = compute_laplacian(points, 30)
    return L, mass


def test_matches_arpack_on_a_bowl(bowl):
    L, mass = bowl
    nk = 50
    report = {}
    evals, evecs = es.smallest_eigenpairs(L, mass, nk, report=report)
    assert report["method"] == "lanczos" and "fallbacks" not in report
    ref_evals, ref_evecs = arpack_reference(L, mass, nk)
    assert_same_eigenpairs(evals, evecs, ref_evals, ref_evecs, mass, nk)
    assert_basis_invariants(evals, evecs, mass, 1)
    # The constant (over the area) is the null vector.
    np.testing.assert_allclose(np.abs(evecs[:, 0]), 1 / np.sqrt(mass.sum()), rtol=1e-12)


def test_public_entry_point_is_deterministic_and_sign_fixed(bowl):
    L, mass = bowl
    a_vals, a_vecs = solve_eigenpairs(L, mass, 30)
    b_vals, b_vecs = solve_eigenpairs(L, mass, 30)
    np.testing.assert_array_equal(a_vals, b_vals)
    np.testing.assert_array_equal(a_vecs, b_vecs)
    top = a_vecs[np.abs(a_vecs).argmax(axis=0), np.arange(30)]
    assert np.all(top > 0)


def test_several_components_give_several_zero_eigenvalues():
    # Three separate jittered patches: three exact null vectors, one constant per patch.
    patches = [jittered_square(32, 0.1, seed=i) + np.array([0.3 * i, 0.0, 0.0]) for i in range(3)]
    points = np.vstack(patches)
    L, mass = compute_laplacian(points, 30)
    nk = 40
    report = {}
    evals, evecs = es.smallest_eigenpairs(L, mass, nk, report=report)
    assert report["components"] == 3 and report["method"] == "lanczos"
    assert_basis_invariants(evals, evecs, mass, 3)
    np.testing.assert_array_equal(evals[:3], 0.0)
    # Each null vector is constant on its patch and zero elsewhere.
    labels = np.repeat(np.arange(3), 32 * 32)
    for j in range(3):
        for p in range(3):
            vals = evecs[labels == p, j]
            assert np.ptp(vals) < 1e-12
    ref_evals, ref_evecs = arpack_reference(L, mass, nk)
    assert_same_eigenpairs(evals, evecs, ref_evals, ref_evecs, mass, nk)
    # The nearly equal patches give nearly triple eigenvalues: the spans must still agree.
    assert max(len(g) for g in clusters(ref_evals)) >= 3


def grid_graph_laplacian(m: int, h: float):
    """Graph Laplacian of an m × m grid (spacing h), uniform mass h², and its exact eigenpairs.

    The eigenvalues are (μ_i + μ_j) / h² with μ_k = 2 − 2 cos(π k / m) and eigenvectors
    u_i ⊗ u_j with u_k(x) = cos(π k (x + ½) / m), so every i ≠ j pair is exactly repeated.
    Returns L (m², m²), mass (m²,), exact eigenvalues (m²,) ascending, eigenvectors (m², m²).
    """
    path = sp.diags([-np.ones(m - 1), np.r_[1.0, 2 * np.ones(m - 2), 1.0], -np.ones(m - 1)], [-1, 0, 1])
    eye = sp.identity(m)
    L = sp.csr_matrix(sp.kron(path, eye) + sp.kron(eye, path))
    mass = np.full(m * m, h * h)
    k = np.arange(m)
    mu = 2 - 2 * np.cos(np.pi * k / m)
    u = np.cos(np.pi * np.outer(np.arange(m) + 0.5, k) / m)
    vals = (mu[:, None] + mu[None, :]).ravel() / h**2
    vecs = np.einsum("ai,bj->abij", u, u).reshape(m * m, m * m)
    vecs /= np.sqrt((mass[:, None] * vecs**2).sum(axis=0))
    order = np.argsort(vals, kind="stable")
    return L, mass, vals[order], vecs[:, order]


def test_exactly_repeated_eigenvalues_are_all_found():
    # Single-vector Lanczos sees one vector of an exactly repeated eigenspace per start vector;
    # the others only through rounding, and the completeness count must notice a missing copy.
    m, h, nk = 40, 0.01, 60  # nK = 60 does not cut a repeated pair
    L, mass, exact_vals, exact_vecs = grid_graph_laplacian(m, h)
    assert exact_vals[nk] - exact_vals[nk - 1] > 1e-6 * exact_vals[nk]
    assert max(len(c) for c in clusters(exact_vals[:nk], 1e-12)) >= 2  # true repeats
    evals, evecs = es.smallest_eigenpairs(L, mass, nk)
    assert_same_eigenpairs(evals, evecs, exact_vals[:nk], exact_vecs[:, :nk], mass, nk)
    assert_basis_invariants(evals, evecs, mass, 1)


def test_inertia_counts_eigenvalues_below_the_shift(bowl):
    # The certificate the solver relies on: LDLᵀ inertia = number of eigenvalues below σ.
    L, mass = bowl
    s = np.sqrt(mass)
    A = sp.csc_matrix(sp.diags(1 / s) @ L @ sp.diags(1 / s))
    ref_evals, _ = arpack_reference(L, mass, 40)
    for sigma in (0.5 * (ref_evals[9] + ref_evals[10]), 0.5 * (ref_evals[30] + ref_evals[31])):
        factor = es.SymmetricFactor(A - sigma * sp.identity(A.shape[0], format="csc"))
        assert factor.n_negative == np.count_nonzero(ref_evals < sigma)


def test_refactor_at_another_shift_counts_like_a_fresh_factor(bowl):
    # The completeness count re-factorises with the first factor's analysis; the shifted
    # matrices keep one sparsity pattern even when a diagonal entry cancels exactly.
    L, mass = bowl
    s = np.sqrt(mass)
    A = sp.csc_matrix(sp.diags(1 / s) @ L @ sp.diags(1 / s))
    shifted = es.ShiftedMatrix(A)
    ref_evals, _ = arpack_reference(L, mass, 40)
    sigmas = [0.5 * (ref_evals[k] + ref_evals[k + 1]) for k in (9, 30, 20)]
    factor = es.SymmetricFactor(shifted(sigmas[0]))
    for sigma in sigmas:
        K = shifted(sigma)
        assert K.nnz == shifted.A.nnz
        np.testing.assert_allclose(K.toarray(), A.toarray() - sigma * np.eye(A.shape[0]))
        assert factor.refactor(K).n_negative == np.count_nonzero(ref_evals < sigma)
    # A shift equal to a diagonal entry makes that entry exactly zero: it stays stored.
    d0 = float(A.diagonal()[0])
    assert shifted(d0).nnz == shifted.A.nnz and shifted(d0)[0, 0] == 0.0


def test_tridiagonal_eigh_matches_scipy():
    from scipy.linalg import eigh_tridiagonal

    rng = np.random.default_rng(7)
    a, b = rng.standard_normal(150), rng.random(149)
    w, z = es.tridiagonal_eigh(a, b)
    w_ref, z_ref = eigh_tridiagonal(a, b)
    np.testing.assert_allclose(w, w_ref, atol=1e-12)
    T = np.diag(a) + np.diag(b, 1) + np.diag(b, -1)
    np.testing.assert_allclose(T @ z, z * w, atol=1e-12)
    np.testing.assert_allclose(z.T @ z, np.eye(150), atol=1e-12)


def test_a_failed_certificate_falls_back_to_the_next_method(bowl, monkeypatch):
    L, mass = bowl
    real = es.lanczos_eigenpairs

    def failing_first(*args, **kwargs):
        if kwargs.get("seed", 0) == 0 and kwargs.get("interior_shift", True):
            raise es.EigensolverFailure("simulated")
        return real(*args, **kwargs)

    monkeypatch.setattr(es, "lanczos_eigenpairs", failing_first)
    report = {}
    evals, evecs = es.smallest_eigenpairs(L, mass, 30, report=report)
    assert report["fallbacks"] == ["lanczos: simulated"] and report["seed"] == 1  # another start vector
    ref_evals, ref_evecs = arpack_reference(L, mass, 30)
    assert_same_eigenpairs(evals, evecs, ref_evals, ref_evecs, mass, 30)


def test_a_wrong_operator_is_caught_and_arpack_takes_over(bowl, monkeypatch):
    # Corrupt every factorisation's solve by a symmetric 0.1 % error (as element growth in
    # an unpivoted LDLᵀ could): Lanczos converges for the wrong operator, the residual
    # certificate must reject every Lanczos variant, and ARPACK must still be right.
    real_init = es.SymmetricFactor.__init__

    def noisy_init(self, K, check_accuracy=True):
        real_init(self, K, check_accuracy)
        exact = self.solve
        d = 1 + 1e-3 * np.random.default_rng(0).standard_normal(K.shape[0])
        self.solve = lambda b: d * exact(d * b)

    monkeypatch.setattr(es.SymmetricFactor, "__init__", noisy_init)
    L, mass = bowl
    report = {}
    with pytest.warns(RuntimeWarning, match="fell back to ARPACK"):
        evals, evecs = es.smallest_eigenpairs(L, mass, 30, report=report)
    assert report["method"] == "arpack" and len(report["fallbacks"]) == 3
    assert all("residual" in f or "eigenvalues lie below" in f for f in report["fallbacks"])
    ref_evals, ref_evecs = arpack_reference(L, mass, 30)
    assert_same_eigenpairs(evals, evecs, ref_evals, ref_evecs, mass, 30)


def test_negative_shift_path_agrees(bowl):
    L, mass = bowl
    evals, evecs = es.lanczos_eigenpairs(L, mass, 30, interior_shift=False)
    ref_evals, ref_evecs = arpack_reference(L, mass, 30)
    assert_same_eigenpairs(evals, evecs, ref_evals, ref_evecs, mass, 30)


def test_small_clouds_use_dense_lapack_and_agree():
    points = jittered_square(24, 0.1, seed=5)  # 576 points
    L, mass = compute_laplacian(points, 20)
    report = {}
    evals, evecs = es.smallest_eigenpairs(L, mass, 25, report=report)
    assert report["method"] == "dense"
    ref_evals, ref_evecs = arpack_reference(L, mass, 25)
    assert_same_eigenpairs(evals, evecs, ref_evals, ref_evecs, mass, 25)
    assert_basis_invariants(evals, evecs, mass, 1)


def test_reference_bunny_matches_the_authors_eigsh(reference):
    from tergodic_cli.capture import CaptureConfig, capture_cloud

    cap = capture_cloud(CaptureConfig(source="file", path=str(reference / "bun270_X.ply"), voxel=3.0 / 1000,
                                      voxel_rule="all"))
    assert len(cap.points) == 2996
    L, mass = compute_laplacian(cap.points, 30)
    nk = 100
    evals, evecs = solve_eigenpairs(L, mass, nk)
    ref_evals, ref_evecs = es.arpack_eigenpairs(L, mass, nk, sigma=1e-12)  # exactly the authors' call
    assert_same_eigenpairs(evals, evecs, ref_evals, ref_evecs, mass, nk)
    assert_basis_invariants(evals, evecs, mass, 2)  # the 3 mm bunny has a detached fragment
