"""The numba re-implementation of the robust point-cloud Laplacian against robust_laplacian itself.

Both builds of its kernels are tested: numba just in time (``jit``) and the ahead-of-time extension
(``aot``, built by ``make``). Without a build the ``aot`` cases skip, unless ``TERGODIC_EXPECT_AOT=1``
(set by ``make test``), where a missing build fails.

Equality means: the same sparsity pattern (exact zeros dropped), every entry within 1e-10 of max|L|,
and the lumped mass within 1e-12 of its maximum. When the fast path refuses a cloud
(LaplacianMismatchRisk) the test says so instead of passing silently, except where refusing is the
expected outcome (an exactly regular grid).
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import robust_laplacian
import scipy.sparse as sp
from conftest import assert_one_line_error, run_cli

from tergodic_cli.basis import fast_laplacian_aot
from tergodic_cli.basis.fast_laplacian import (GUARD_REASONS, FastLaplacianNotBuilt, LaplacianMismatchRisk,
                                               point_cloud_laplacian)
from tergodic_cli.capture.synthetic import generate_synthetic

L_RTOL = 1e-10
MASS_RTOL = 1e-12


def require_build() -> None:
    """Skip without an ahead-of-time build, or fail where one is expected (``make test``)."""
    path, why = fast_laplacian_aot.find_build()
    if path is None:
        if os.environ.get("TERGODIC_EXPECT_AOT") == "1":
            pytest.fail(f"TERGODIC_EXPECT_AOT=1 but {why}")
        pytest.skip(why)


@pytest.fixture(params=["aot", "jit"])
def backend(request) -> str:
    if request.param == "aot":
        require_build()
    return request.param


def library(points: np.ndarray, k: int) -> tuple[sp.csr_matrix, np.ndarray]:
    L, M = robust_laplacian.point_cloud_laplacian(points, mollify_factor=1e-5, n_neighbors=k)
    return sp.csr_matrix(L), np.asarray(M.diagonal())


def differences(points: np.ndarray, k: int, **kw) -> tuple[int, float, float]:
    """(entries in only one pattern, max |ΔL| / max|L|, max |Δmass| / max mass) of ours against the library."""
    L0, m0 = library(points, k)
    L1, m1 = point_cloud_laplacian(points, n_neighbors=k, **kw)
    assert L1.shape == L0.shape and m1.shape == m0.shape
    L0 = L0.copy()
    L1 = L1.copy()
    L0.eliminate_zeros()
    L1.eliminate_zeros()
    only_one = int(abs((L0 != 0).astype(np.int8) - (L1 != 0).astype(np.int8)).sum())
    dL = float(abs(L0 - L1).max() / abs(L0).max())
    dm = float(np.max(np.abs(m0 - m1)) / np.max(m0))
    return only_one, dL, dm


def assert_same_as_library(points: np.ndarray, k: int, backend: str = "auto") -> None:
    only_one, dL, dm = differences(points, k, backend=backend)
    assert only_one == 0, f"{only_one} entries in only one sparsity pattern"
    assert dL <= L_RTOL, f"L differs by {dL:.2e} of max|L|"
    assert dm <= MASS_RTOL, f"mass differs by {dm:.2e} of its maximum"


def noisy_height_field(n: int, seed: int) -> np.ndarray:
    """A wavy 10 cm patch sampled at random, with 0.2 mm normal noise (metres)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.05, 0.05, size=(n, 2))
    z = 0.01 * np.sin(40 * xy[:, 0]) * np.cos(30 * xy[:, 1]) + rng.normal(0, 2e-4, n)
    return np.column_stack([xy, z])


def noisy_sphere(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return 0.05 * v * (1 + rng.normal(0, 0.003, (n, 1)))


@pytest.mark.parametrize("k", [30, 40])
@pytest.mark.parametrize("kind", ["bowl", "plate", "mug", "sphere"])
def test_synthetic_objects_equal_library(kind, k, backend):
    assert_same_as_library(generate_synthetic(kind, "X", seed=0, spacing=0.004).points, k, backend)


@pytest.mark.parametrize("k", [30, 40])
@pytest.mark.parametrize("cloud", ["height_field", "sphere"])
def test_noisy_random_surfaces_equal_library(cloud, k, backend):
    pts = noisy_height_field(1500, seed=7) if cloud == "height_field" else noisy_sphere(1500, seed=8)
    assert_same_as_library(pts, k, backend)


@pytest.mark.parametrize("k", [30, 40])
@pytest.mark.parametrize("name, count", [("bun270_X.ply", 2996), ("plate_shapes.ply", 6228)])
def test_reference_clouds_equal_library(reference, name, count, k, backend):
    from tergodic_cli.capture import CaptureConfig, capture_cloud

    cap = capture_cloud(CaptureConfig(source="file", path=str(reference / name), voxel=0.003, voxel_rule="all"))
    assert len(cap.points) == count
    assert_same_as_library(cap.points, k, backend)


def test_exact_grid_is_refused_or_equal():
    # A perfectly regular grid is all ties (equal distances, equal column norms in the normal's SVD,
    # collinear neighbours): the library's result there depends on its round-off.
    g = np.arange(20) * 0.01
    pts = np.stack(np.meshgrid(g, g, [0.0]), axis=-1).reshape(-1, 3)
    try:
        only_one, dL, dm = differences(pts, 30)
    except LaplacianMismatchRisk as exc:
        assert exc.code in GUARD_REASONS and GUARD_REASONS[exc.code] in str(exc)
        return
    assert only_one == 0 and dL <= L_RTOL and dm <= MASS_RTOL


def test_the_comparison_can_fail():
    # Flipping every normal mirrors each local chart, so the walk emits its fans in the opposite order:
    # the union of triangles is the same but the tufted cover glues duplicates differently. The
    # equality check must see that.
    pts = generate_synthetic("bowl", "X", seed=0, spacing=0.004).points
    only_one, dL, dm = differences(pts, 30, _normal_sign=-1.0)
    assert only_one > 0 or dL > L_RTOL or dm > MASS_RTOL


def test_laplacian_properties_independent_of_library():
    pts = noisy_height_field(800, seed=3)
    L, mass = point_cloud_laplacian(pts, 30)
    assert L.shape == (800, 800) and mass.shape == (800,)
    assert abs(L - L.T).max() <= 1e-12 * abs(L).max()  # symmetric
    np.testing.assert_allclose(np.asarray(L.sum(axis=1)).ravel(), 0.0, atol=1e-12 * abs(L).max())
    assert np.all(L.diagonal() > 0) and np.all(mass > 0)
    # the patch is about 10 cm x 10 cm (a little more: it is wavy): total mass ~ its area
    assert 0.0095 < mass.sum() < 0.0125


def test_bad_input_raises_value_error():
    with pytest.raises(ValueError):
        point_cloud_laplacian(np.zeros((10, 2)))
    with pytest.raises(ValueError):
        point_cloud_laplacian(np.random.default_rng(0).normal(size=(20, 3)), n_neighbors=30)


def test_duplicate_points_are_refused():
    pts = noisy_height_field(500, seed=4)
    pts[10] = pts[11]
    with pytest.raises(LaplacianMismatchRisk) as info:
        point_cloud_laplacian(pts, 30)
    assert info.value.code == 1


# --- how compute_laplacian uses it ---------------------------------------------------------------

def test_compute_laplacian_methods_and_what_they_record(monkeypatch):
    from tergodic_cli.basis import core

    require_build()
    pts = generate_synthetic("bowl", "X", seed=0, spacing=0.004).points
    L0, m0 = library(pts, 30)
    made: dict = {}
    monkeypatch.setenv(core.ENV_LAPLACIAN, "robust_laplacian")
    core.compute_laplacian(pts, 30, info=made)
    assert made["laplacian"] == "robust_laplacian"
    for method in ("auto", "fast", ""):  # "" (unset): auto
        monkeypatch.setenv(core.ENV_LAPLACIAN, method)
        L1, m1 = core.compute_laplacian(pts, 30, info=made)
        assert made["laplacian"] == "tergodic.fast_laplacian"
        assert abs(L1 - L0).max() <= L_RTOL * abs(L0).max() and np.abs(m1 - m0).max() <= MASS_RTOL * m0.max()
    # another robust_laplacian release: the library is called, and the reason recorded
    monkeypatch.setattr(core, "_robust_laplacian_version", lambda: "9.9.9")
    core.compute_laplacian(pts, 30, info=made)
    assert made["laplacian"].startswith("robust_laplacian") and "9.9.9" in made["laplacian"]


def test_aot_and_jit_builds_give_identical_bits():
    require_build()
    for pts in (generate_synthetic("mug", "X", seed=0, spacing=0.004).points, noisy_sphere(1200, seed=9)):
        La, ma = point_cloud_laplacian(pts, 30, backend="aot")
        Lj, mj = point_cloud_laplacian(pts, 30, backend="jit")
        assert np.array_equal(La.indptr, Lj.indptr) and np.array_equal(La.indices, Lj.indices)
        assert np.array_equal(La.data, Lj.data) and np.array_equal(ma, mj)


def test_default_in_a_fresh_process_is_the_build_without_numba():
    """The point of the ahead-of-time build: the default path never imports numba."""
    require_build()
    code = (
        "import sys, numpy as np\n"
        "from tergodic_cli.basis.core import compute_laplacian\n"
        "from tergodic_cli.capture.synthetic import generate_synthetic\n"
        "info = {}\n"
        "L, m = compute_laplacian(generate_synthetic('bowl', 'X', seed=0, spacing=0.004).points, 30, info=info)\n"
        "print(info['laplacian'], 'numba' in sys.modules, L.shape[0] == len(m))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "TERGODIC_LAPLACIAN"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["tergodic.fast_laplacian", "False", "True"]


def test_without_a_current_build_auto_uses_the_library_and_says_why(monkeypatch, tmp_path):
    from tergodic_cli.basis import core

    pts = noisy_height_field(600, seed=10)
    monkeypatch.setenv(core.ENV_LAPLACIAN, "auto")
    monkeypatch.setattr(fast_laplacian_aot, "search_dirs", lambda: [tmp_path])
    monkeypatch.setattr(fast_laplacian_aot, "_LOADED", {})  # forget a build loaded by an earlier test
    made: dict = {}
    core.compute_laplacian(pts, 20, info=made)
    assert made["laplacian"].startswith("robust_laplacian") and "not built" in made["laplacian"]
    with pytest.raises(FastLaplacianNotBuilt, match="not built"):
        point_cloud_laplacian(pts, 20, backend="aot")
    # a build of other kernels (an edit since): stale, ignored
    suffix = fast_laplacian_aot._suffix()
    (tmp_path / ("fast_laplacian_0123456789abcdef" + suffix)).write_bytes(b"old")
    core.compute_laplacian(pts, 20, info=made)
    assert made["laplacian"].startswith("robust_laplacian") and "stale" in made["laplacian"]
    # a damaged file under the current name: no build, and the reason names the file
    (tmp_path / (fast_laplacian_aot.module_name() + suffix)).write_bytes(b"\x7fELF not really")
    core.compute_laplacian(pts, 20, info=made)
    assert made["laplacian"].startswith("robust_laplacian") and "does not load" in made["laplacian"]
    L, mass = core.compute_laplacian(pts, 20)
    L0, m0 = library(pts, 20)
    assert abs(L - L0).max() == 0.0 and np.array_equal(mass, m0)  # the library's own matrices


def test_compute_laplacian_hands_a_regular_grid_to_the_library(monkeypatch):
    from tergodic_cli.basis import core

    g = np.arange(20) * 0.01
    pts = np.stack(np.meshgrid(g, g, [0.0]), axis=-1).reshape(-1, 3)
    pts[:, 2] = 0.002 * np.sin(pts[:, 0] * 40)  # not flat (a flat cloud is refused before)
    pts[:, :2] = np.round(pts[:, :2], 6)
    monkeypatch.setenv(core.ENV_LAPLACIAN, "fast")
    made: dict = {}
    L1, m1 = core.compute_laplacian(pts, 30, info=made)
    L0, m0 = library(pts, 30)
    if made["laplacian"] != "tergodic.fast_laplacian":
        assert "declined" in made["laplacian"]
    assert abs(L1 - L0).max() <= L_RTOL * abs(L0).max()  # either way: the library's matrices


def test_the_safety_net_catches_a_broken_laplacian():
    from tergodic_cli.basis.core import _not_a_cotan_laplacian

    pts = noisy_height_field(400, seed=5)
    L, mass = library(pts, 20)
    assert _not_a_cotan_laplacian(L, mass) is None
    bad = L.tolil()
    bad[0, 1] += 1e-3 * abs(L).max()
    assert "symmetric" in _not_a_cotan_laplacian(bad.tocsr(), mass)
    bad = L + 1e-6 * abs(L).max() * sp.eye(400)
    assert "sum to zero" in _not_a_cotan_laplacian(bad.tocsr(), mass)
    assert "mass" in _not_a_cotan_laplacian(L, np.where(np.arange(400) == 3, 0.0, mass))


def test_a_bad_method_is_one_line(monkeypatch):
    from tergodic_cli.basis import core
    from tergodic_cli.errors import TergodicError

    monkeypatch.setenv(core.ENV_LAPLACIAN, "cotan-please")
    with pytest.raises(TergodicError, match="not a Laplacian method"):
        core.compute_laplacian(noisy_height_field(100, seed=6), 10)


def test_spacing_from_the_build_equals_scipy(monkeypatch, tmp_path):
    from scipy.spatial import cKDTree

    from tergodic_cli.capture.filters import mean_spacing

    require_build()
    for pts in (noisy_sphere(2000, seed=11), generate_synthetic("plate", "X", seed=0, spacing=0.004).points):
        dists, _ = cKDTree(pts).query(pts, k=4)
        expected = float(dists[:, 1:].mean())
        assert mean_spacing(pts) == pytest.approx(expected, rel=1e-13)
        assert mean_spacing(pts, k=8) == pytest.approx(float(cKDTree(pts).query(pts, k=9)[0][:, 1:].mean()), rel=1e-13)
    # without a build: scipy's, the same number
    monkeypatch.setattr(fast_laplacian_aot, "search_dirs", lambda: [tmp_path])
    monkeypatch.setattr(fast_laplacian_aot, "_LOADED", {})
    assert mean_spacing(pts) == pytest.approx(expected, rel=1e-15)


def test_precompute_laplacian_flag(tmp_path, monkeypatch):
    """--laplacian chooses for this command only; a bad value is one line naming the flag."""
    from tergodic_cli.basis import core

    monkeypatch.delenv(core.ENV_LAPLACIAN, raising=False)
    assert run_cli("capture", "--synthetic", "plate", "--voxel", "0.006", "--out", tmp_path / "cap").code == 0
    assert_one_line_error(run_cli("precompute", tmp_path / "cap", "--laplacian", "cotan"),
                          "--laplacian cotan is not a Laplacian method", "robust_laplacian")
    lib = run_cli("precompute", tmp_path / "cap", "--nk", "20", "--laplacian", "robust_laplacian")
    assert lib.code == 0 and "L and M by robust_laplacian" in lib.out
    assert core.ENV_LAPLACIAN not in os.environ  # not left behind for the rest of the process


def test_without_the_kernels_source_there_is_no_build(monkeypatch, tmp_path):
    """A bytecode-only install cannot date a build: no build, a reason, and the library is used."""
    from tergodic_cli.basis import core

    monkeypatch.setattr(fast_laplacian_aot, "KERNELS", tmp_path / "fast_laplacian_kernels.py")
    path, why = fast_laplacian_aot.find_build()
    assert path is None and "unreadable" in why
    made: dict = {}
    monkeypatch.setenv(core.ENV_LAPLACIAN, "auto")
    core.compute_laplacian(noisy_height_field(300, seed=12), 12, info=made)
    assert made["laplacian"].startswith("robust_laplacian") and "unreadable" in made["laplacian"]
