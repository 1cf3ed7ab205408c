"""The spectral basis against analytic spectra, and its content-keyed cache."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import fibonacci_sphere, jittered_square

from tergodic_cli.basis import BasisConfig, compute_basis, get_basis
from tergodic_cli.basis.cache import geometry_key
from tergodic_cli.capture.synthetic import generate_synthetic


def test_sphere_eigenvalues_match_spherical_harmonics():
    # Laplace-Beltrami on the unit sphere: λ = l(l+1) with multiplicity 2l+1.
    basis = compute_basis(fibonacci_sphere(5000), nk=16, n_neighbors=30)
    expected = np.concatenate([[l * (l + 1)] * (2 * l + 1) for l in range(4)]).astype(float)
    assert abs(basis.evals[0]) < 1e-6
    np.testing.assert_allclose(basis.evals[1:], expected[1:], rtol=0.03)


def test_flat_patch_eigenvalues_match_neumann_modes():
    side = 1.0
    basis = compute_basis(jittered_square(70, side), nk=12, n_neighbors=30)
    modes = sorted(np.pi**2 * (m * m + n * n) / side**2 for m in range(6) for n in range(6))[:12]
    assert abs(basis.evals[0]) < 1e-6
    np.testing.assert_allclose(basis.evals[1:], modes[1:], rtol=0.03)


def test_eigenvectors_are_mass_orthonormal_and_sorted():
    cloud = generate_synthetic("bowl", "X", seed=1, spacing=0.003)
    basis = compute_basis(cloud.points, nk=40, n_neighbors=30)
    gram = basis.evecs.T @ (basis.mass[:, None] * basis.evecs)
    np.testing.assert_allclose(gram, np.eye(40), atol=1e-8)
    assert np.all(np.diff(basis.evals) >= 0)
    # One connected component: exactly one (near-)zero eigenvalue.
    assert (basis.evals < 1e-6 * basis.evals[-1]).sum() == 1


def test_one_zero_eigenvalue_per_connected_component():
    a = jittered_square(25, 0.1, seed=1)
    b = jittered_square(25, 0.1, seed=2) + np.array([0.5, 0.0, 0.0])
    basis = compute_basis(np.vstack([a, b]), nk=6, n_neighbors=12)
    assert (basis.evals < 1e-6 * basis.evals[-1]).sum() == 2


def _random_rigid(seed: int) -> tuple[np.ndarray, np.ndarray]:
    q = np.random.default_rng(seed).normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    return R, np.array([0.4, -0.2, 0.1])


def test_cache_hit_on_repeat_rigid_motion_and_reordering(isolated_cache):
    pts = generate_synthetic("bowl", "X", seed=3, spacing=0.003).points
    cfg = BasisConfig(nk=20, neighbors=20)
    first, hit = get_basis(pts, cfg)
    assert not hit
    again, hit = get_basis(pts, cfg)
    assert hit
    np.testing.assert_array_equal(again.evecs, first.evecs)

    R, t = _random_rigid(7)
    perm = np.random.default_rng(8).permutation(len(pts))
    moved = (pts @ R.T + t)[perm]
    assert geometry_key(moved, cfg)[0] == geometry_key(pts, cfg)[0]
    reused, hit = get_basis(moved, cfg)
    assert hit
    # The reused basis follows the caller's point order.
    np.testing.assert_allclose(reused.evecs, first.evecs[perm])
    np.testing.assert_allclose(reused.mass, first.mass[perm])
    np.testing.assert_allclose(reused.L.toarray(), first.L.toarray()[perm][:, perm])

    _, hit = get_basis(pts, BasisConfig(nk=21, neighbors=20))
    assert not hit  # a parameter is part of the key
    _, hit = get_basis(pts, cfg, force=True)
    assert not hit


def test_tampered_cache_is_detected_and_recomputed(isolated_cache):
    pts = generate_synthetic("plate", "X", seed=0, spacing=0.004).points
    cfg = BasisConfig(nk=10, neighbors=20)
    basis, _ = get_basis(pts, cfg)
    entry = isolated_cache / "basis" / basis.meta["key"]
    evecs = np.load(entry / "evecs.npy")
    evecs[0, 0] += 1e-3
    np.save(entry / "evecs.npy", evecs)
    messages = []
    again, hit = get_basis(pts, cfg, on_event=messages.append)
    assert not hit and any("checksum" in m for m in messages)
    np.testing.assert_allclose(again.evecs, basis.evecs)

    (entry / "mass.npy").write_bytes(b"not an npy file")
    messages.clear()
    _, hit = get_basis(pts, cfg, on_event=messages.append)
    assert not hit and any("unreadable" in m for m in messages)

    # An object array smuggled in is refused, never unpickled.
    np.save(entry / "h.npy", np.array([{"evil": 1}], dtype=object), allow_pickle=True)
    messages.clear()
    _, hit = get_basis(pts, cfg, on_event=messages.append)
    assert not hit and any("unreadable" in m for m in messages)
    meta = json.loads((entry / "basis.json").read_text())
    assert meta["key"] == basis.meta["key"]


def test_laplacian_annihilates_constants_and_is_symmetric():
    basis = compute_basis(fibonacci_sphere(800), nk=5, n_neighbors=20)
    assert abs(basis.L - basis.L.T).max() < 1e-12
    assert np.abs(basis.L @ np.ones(800)).max() < 1e-9
