"""The spectral basis against analytic spectra, and its content-keyed cache."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import fibonacci_sphere, jittered_square

from tergodic_cli.basis import BasisConfig, compute_basis, get_basis
from tergodic_cli.basis import cache as cache_mod
from tergodic_cli.basis.cache import array_checksum, geometry_key
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


def _npy_data_offset(path) -> int:
    with open(path, "rb") as f:
        np.lib.format.read_magic(f)
        np.lib.format.read_array_header_1_0(f)
        return f.tell()


def test_cache_detects_a_flipped_byte_a_truncation_and_an_old_layout(isolated_cache):
    pts = generate_synthetic("plate", "X", seed=0, spacing=0.004).points
    cfg = BasisConfig(nk=12, neighbors=20)
    basis, _ = get_basis(pts, cfg)
    entry = isolated_cache / "basis" / basis.meta["key"]
    path = entry / "evecs.npy"
    start = _npy_data_offset(path)
    raw = path.read_bytes()
    assert len(raw) - start == basis.evecs.nbytes > 8 * 4096  # rows and a tail
    for pos in (start, start + len(raw[start:]) // 2 + 3, len(raw) - 1):  # first, middle, last byte
        bad = bytearray(raw)
        bad[pos] ^= 0x10
        path.write_bytes(bytes(bad))
        messages = []
        again, hit = get_basis(pts, cfg, on_event=messages.append)
        assert not hit and any("checksum" in m for m in messages), pos
        np.testing.assert_allclose(again.evecs, basis.evecs)
    path.write_bytes(raw[:-5])  # truncated
    messages = []
    _, hit = get_basis(pts, cfg, on_event=messages.append)
    assert not hit and any("unreadable" in m for m in messages)
    # An entry written by an older layout (no point order, other checksums) is recomputed.
    meta = json.loads((entry / "basis.json").read_text())
    del meta["checksums"]["points_order"]
    (entry / "basis.json").write_text(json.dumps(meta))
    (entry / "points_order.npy").unlink()
    messages = []
    _, hit = get_basis(pts, cfg, on_event=messages.append)
    assert not hit and messages
    _, hit = get_basis(pts, cfg)
    assert hit


def test_checksum_catches_every_single_byte_flip_and_word_swaps():
    rng = np.random.default_rng(0)
    a = rng.standard_normal(2 * 4096 + 5)  # two checksum rows and a 40-byte tail
    ref = array_checksum(a)
    raw = bytearray(a.tobytes())
    for pos in list(range(0, len(raw), 5)) + list(range(len(raw) - 48, len(raw))):
        for bit in (0x01, 0x80):
            raw[pos] ^= bit
            assert array_checksum(np.frombuffer(bytes(raw), dtype=a.dtype)) != ref, (pos, bit)
            raw[pos] ^= bit
    assert array_checksum(np.frombuffer(bytes(raw), dtype=a.dtype)) == ref
    for i, j in ((3, 10), (3, 4096 + 3), (100, 4096 + 7)):  # same row; same lane; neither
        b = a.copy()
        b[[i, j]] = b[[j, i]]
        assert array_checksum(b) != ref, (i, j)
    m = rng.standard_normal((600, 50))  # swapped rows of a matrix, and a changed shape or dtype
    ref = array_checksum(m)
    assert array_checksum(m[[1, 0, *range(2, 600)]]) != ref
    assert array_checksum(m.reshape(50, 600)) != ref
    assert array_checksum(m.view(np.int64)) != ref
    assert array_checksum(np.array(1.5)) != array_checksum(np.array(2.5))


def test_canonical_order_is_the_lexicographic_order():
    rng = np.random.default_rng(3)
    for span in (1000, 1 << 20, 1 << 40):  # packed single sort; its limit; the lexsort fallback
        q = rng.integers(-span, span, size=(5000, 3))
        q[:100, 0] = q[100:200, 0]  # shared x: the order then depends on y and z
        order, ident = cache_mod._canonical_order(q)
        np.testing.assert_array_equal(q[order], q[np.lexsort((q[:, 2], q[:, 1], q[:, 0]))])
        perm = rng.permutation(len(q))
        assert cache_mod._canonical_order(q[perm])[1] == ident  # the key does not depend on the order


def test_cache_hit_in_the_stored_order_and_in_another_order(isolated_cache):
    pts = generate_synthetic("bowl", "X", seed=2, spacing=0.004).points
    cfg = BasisConfig(nk=10, neighbors=20)
    first, _ = get_basis(pts, cfg)
    perm = np.random.default_rng(1).permutation(len(pts))
    again, hit = get_basis(pts, cfg)
    assert hit and again.evecs.flags.c_contiguous
    np.testing.assert_array_equal(again.evecs, first.evecs)
    np.testing.assert_array_equal(again.L.indptr, first.L.indptr)
    shuffled, hit = get_basis(pts[perm], cfg)
    assert hit
    np.testing.assert_array_equal(shuffled.evecs, first.evecs[perm])
    np.testing.assert_array_equal(shuffled.L.toarray(), first.L.toarray()[perm][:, perm])
    # A hit from the shuffled order leaves the stored entry as it was: the original order still hits.
    back, hit = get_basis(pts, cfg)
    assert hit
    np.testing.assert_array_equal(back.evecs, first.evecs)


def test_duplicate_points_are_counted_and_refused():
    from tergodic_cli.basis.core import check_geometry
    from tergodic_cli.errors import TergodicError

    pts = jittered_square(20, 0.1, seed=4)
    check_geometry(pts)
    pts[0] = [0.0, 0.0, 0.0]
    dup = np.vstack([pts, pts[[5, 5, 9]], [[-0.0, 0.0, -0.0]]])  # -0.0 equals 0.0
    with pytest.raises(TergodicError, match="has 4 duplicate points"):
        check_geometry(dup)


def test_laplacian_annihilates_constants_and_is_symmetric():
    basis = compute_basis(fibonacci_sphere(800), nk=5, n_neighbors=20)
    assert abs(basis.L - basis.L.T).max() < 1e-12
    assert np.abs(basis.L @ np.ones(800)).max() < 1e-9


def test_basis_laplacian_is_the_librarys():
    """L and M are robust_laplacian's own output, for both neighbour counts in use."""
    import robust_laplacian

    pts = generate_synthetic("bowl", "X", seed=0, spacing=0.005).points
    for k in (30, 40):
        basis = compute_basis(pts, nk=8, n_neighbors=k)
        L, M = robust_laplacian.point_cloud_laplacian(pts, n_neighbors=k)
        assert (basis.L != L.tocsr()).nnz == 0
        np.testing.assert_array_equal(basis.mass, M.diagonal())


def test_spacing_is_the_mean_distance_to_three_nearest_neighbours():
    pts = jittered_square(15, 0.1, seed=7)
    d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=2)
    expected = np.sort(d, axis=1)[:, 1:4].mean()  # brute force, self excluded
    basis = compute_basis(pts, nk=4, n_neighbors=12)
    assert basis.h == pytest.approx(expected, rel=1e-12)


def test_an_entry_from_an_older_tergodic_is_recomputed_once_with_a_message(isolated_cache):
    """Entries written before basis.json carried its own checksum (e.g. those that recorded the
    removed re-implementation's "laplacian") cannot be told from edited ones: one recompute, said."""
    pts = generate_synthetic("plate", "X", seed=0, spacing=0.006).points
    cfg = BasisConfig(nk=10, neighbors=20)
    basis, _ = get_basis(pts, cfg)
    meta_path = isolated_cache / "basis" / basis.meta["key"] / "basis.json"
    meta = json.loads(meta_path.read_text())
    assert "laplacian" not in meta
    meta["laplacian"] = "tergodic.fast_laplacian"
    del meta["sidecar_sha256"]
    meta_path.write_text(json.dumps(meta))
    messages = []
    again, hit = get_basis(pts, cfg, on_event=messages.append)
    assert not hit and any("older tergodic" in m for m in messages), messages
    np.testing.assert_allclose(again.evecs, basis.evecs, atol=1e-12)
    assert get_basis(pts, cfg)[1]


def test_an_edited_basis_json_is_a_reported_miss_and_is_recomputed(tmp_path):
    import json

    from tergodic_cli.basis import BasisConfig, get_basis
    from tergodic_cli.capture.synthetic import generate_synthetic

    pts = generate_synthetic("plate", "X", seed=0, spacing=0.006).points
    basis, hit = get_basis(pts, BasisConfig(nk=10, neighbors=30), tmp_path)
    assert not hit
    side = tmp_path / "basis" / basis.meta["key"] / "basis.json"
    meta = json.loads(side.read_text())
    meta["h_m"] *= 2.0  # an edit that changes no array: the sidecar's own checksum must catch it
    side.write_text(json.dumps(meta))
    said = []
    again, hit = get_basis(pts, BasisConfig(nk=10, neighbors=30), tmp_path, on_event=said.append)
    assert not hit and any("edited" in m for m in said), said
    assert again.h == pytest.approx(basis.h) and json.loads(side.read_text())["h_m"] == pytest.approx(basis.h)
    assert get_basis(pts, BasisConfig(nk=10, neighbors=30), tmp_path)[1]  # a clean hit after the recompute


def test_an_entry_another_process_wrote_meanwhile_stands(tmp_path, monkeypatch):
    """Two sweep workers computing one basis: the later rename meets the earlier one's entry."""
    import errno
    import os

    entry = tmp_path / "basis" / "k"
    real = os.replace

    def first_wins(src, dst):
        if Path(dst) == entry:  # the other writer got there between our check and our rename
            entry.mkdir(parents=True)
            (entry / "basis.json").write_text("{}")
            raise OSError(errno.ENOTEMPTY, "Directory not empty", str(dst))
        return real(src, dst)

    monkeypatch.setattr(cache_mod.os, "replace", first_wins)
    cache_mod._write_entry(entry, {"h": np.zeros(())}, {"kind": "tergodic.basis"}, BasisConfig())
    assert (entry / "basis.json").read_text() == "{}"  # theirs stands
    assert [p.name for p in entry.parent.iterdir()] == ["k"]  # ours is gone


@pytest.mark.parametrize("shape", [(10**12,), (3, 10**11), (7,)])
def test_a_cache_header_claiming_another_size_is_refused_before_allocating(isolated_cache, shape):
    """A .npy header edited to claim terabytes made every precompute fail (MemoryError) until --force;
    it is checked against the file's size before anything is allocated, reported and recomputed."""
    from numpy.lib import format as npy

    pts = generate_synthetic("plate", "X", seed=0, spacing=0.004).points
    cfg = BasisConfig(nk=12, neighbors=20)
    basis, _ = get_basis(pts, cfg)
    path = isolated_cache / "basis" / basis.meta["key"] / "evals.npy"
    raw = path.read_bytes()
    start = _npy_data_offset(path)
    import io

    head = io.BytesIO()
    npy.write_array_header_1_0(head, {"descr": "<f8", "fortran_order": False, "shape": shape})
    assert len(head.getvalue()) == start  # the same padded header length: only the shape differs
    path.write_bytes(head.getvalue() + raw[start:])
    messages = []
    again, hit = get_basis(pts, cfg, on_event=messages.append)
    assert not hit and any("header claims" in m for m in messages), messages
    np.testing.assert_allclose(again.evals, basis.evals)
    assert get_basis(pts, cfg)[1]  # the entry was rewritten whole
