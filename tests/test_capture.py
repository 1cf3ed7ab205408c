"""Capture: formats round-trip, the voxel rules, segmentation, and every bad-input case of the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli, run_cli_subprocess

from tergodic_cli.capture import CaptureConfig, capture_cloud, load_capture
from tergodic_cli.capture.filters import voxel_downsample
from tergodic_cli.capture.readers import read_cloud, write_ply
from tergodic_cli.capture.segment import parse_target, rgb_to_hsv, target_weight
from tergodic_cli.capture.synthetic import MARKINGS, OBJECTS, generate_synthetic


@pytest.fixture(scope="module")
def bowl():
    return generate_synthetic("bowl", "X", seed=0, spacing=0.003)


def _write(fmt: str, path, points, colors):
    if fmt == "ply":
        write_ply(path, points, colors)
    elif fmt == "pcd":
        import open3d as o3d

        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        pcd.colors = o3d.utility.Vector3dVector(colors)
        o3d.io.write_point_cloud(str(path), pcd, write_ascii=False)
    elif fmt == "xyzrgb":
        np.savetxt(path, np.column_stack([points, np.rint(colors * 255)]), fmt="%.9f")
    elif fmt == "npz":
        np.savez(path, points=points, colors=colors)


@pytest.mark.parametrize("fmt", ["ply", "pcd", "xyzrgb", "npz"])
def test_capture_round_trips_every_format(fmt, tmp_path, bowl):
    src = tmp_path / f"cloud.{fmt}"
    _write(fmt, src, bowl.points, bowl.colors)
    res = run_cli("capture", "--from", src, "--voxel", "0", "--out", tmp_path / "cap")
    assert res.code == 0, res.err
    cap = load_capture(tmp_path / "cap")
    np.testing.assert_allclose(cap.points, bowl.points, atol=1e-6 if fmt == "pcd" else 1e-9)
    np.testing.assert_allclose(cap.colors, bowl.colors, atol=0.5 / 255 + 1e-6)
    # The written PLY reads back to the same cloud too.
    pts, cols = read_cloud(tmp_path / "cap" / "cloud.ply")
    np.testing.assert_array_equal(pts, cap.points)
    side = json.loads((tmp_path / "cap" / "capture.json").read_text())
    assert side["units"] == "m" and side["counts"]["output"] == len(bowl.points)
    assert side["filters"][0] == {"stage": "input", "points": len(bowl.points)}


def test_binary_compressed_pcd_reads_like_the_cloud(tmp_path, bowl):
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(bowl.points))
    pcd.colors = o3d.utility.Vector3dVector(bowl.colors)
    assert o3d.io.write_point_cloud(str(tmp_path / "c.pcd"), pcd, write_ascii=False, compressed=True)
    assert b"DATA binary_compressed" in (tmp_path / "c.pcd").read_bytes()[:400]
    pts, cols = read_cloud(tmp_path / "c.pcd")
    np.testing.assert_allclose(pts, bowl.points, atol=1e-6)
    np.testing.assert_allclose(cols, bowl.colors, atol=0.5 / 255 + 1e-6)


@pytest.mark.parametrize("kind", OBJECTS)
@pytest.mark.parametrize("marking", MARKINGS)
def test_segmentation_recovers_generator_marking(kind, marking):
    cloud = generate_synthetic(kind, marking, seed=5, spacing=0.003)
    mask = target_weight(cloud.colors, parse_target("red"), len(cloud.colors)) >= 1
    iou = (mask & cloud.mask).sum() / (mask | cloud.mask).sum()
    assert iou >= 0.95


def test_voxel_rules_fraction_and_all():
    # Two voxels of 0.01 m: one with 3 red + 1 black point, one all red.
    pts = np.array([[0.001, 0.001, 0.001], [0.002, 0.001, 0.001], [0.001, 0.002, 0.001], [0.002, 0.002, 0.002],
                    [0.021, 0.001, 0.001], [0.022, 0.002, 0.001]])
    red = np.array([True, True, True, False, True, True])
    cols = np.where(red[:, None], [1.0, 0, 0], [0.0, 0, 0])
    p_pts, p_cols, p = voxel_downsample(pts, cols, red, 0.01, "fraction")
    np.testing.assert_allclose(sorted(p), [0.75, 1.0])
    _, _, p_all = voxel_downsample(pts, cols, red, 0.01, "all")
    np.testing.assert_allclose(sorted(p_all), [0.0, 1.0])
    np.testing.assert_allclose(p_pts[np.argmin(p_pts[:, 0])], pts[:4].mean(axis=0))


def test_voxel_grid_matches_open3d_counts(bowl):
    import open3d as o3d

    for voxel in (0.004, 0.0061, 0.009):
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(bowl.points)).voxel_down_sample(voxel)
        ours, _, _ = voxel_downsample(bowl.points, None, np.zeros(len(bowl.points), bool), voxel)
        assert len(ours) == len(pcd.points)


def test_reference_voxel_rule_all_counts(reference, tmp_path):
    for name, n, n_target in (("bun270_X.ply", 2996, 210), ("plate_shapes.ply", 6228, 1216)):
        cap = capture_cloud(CaptureConfig(source="file", path=str(reference / name), voxel=0.003, voxel_rule="all"))
        assert cap.n_points == n and int((cap.target > 0).sum()) == n_target
        frac = capture_cloud(CaptureConfig(source="file", path=str(reference / name), voxel=0.003))
        assert int((frac.target >= 1).sum()) == n_target  # 'all' is the p == 1 subset of 'fraction'


def test_hsv_conversion_and_targets():
    hsv = rgb_to_hsv(np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, 1.0], [0.5, 0.25, 0.25]]))
    np.testing.assert_allclose(hsv[:, 0], [0, 120, 240, 0, 0])
    np.testing.assert_allclose(hsv[:, 1], [1, 1, 1, 0, 0.5])
    custom = parse_target("hsv:350-10,0.4,0.2")  # wraps through 0
    assert custom.contains(rgb_to_hsv(np.array([[1.0, 0.05, 0.1]])))[0]
    assert not custom.contains(rgb_to_hsv(np.array([[0.1, 1.0, 0.1]])))[0]
    assert parse_target("all") is None


def test_faint_ink_weighs_in_by_its_intensity(bowl):
    # ink of intensity m blended with the glazed surface, as the simulated texture renders it
    from tergodic_cli.capture.synthetic import MARKING_RGB, SURFACE_RGB

    m = np.linspace(0.0, 1.0, 101)
    colours = SURFACE_RGB + m[:, None] * (MARKING_RGB - SURFACE_RGB)
    red = parse_target("red")
    w = target_weight(colours * 0.6, red, len(m))  # shading scales the colour: the weight does not change
    np.testing.assert_allclose(w, target_weight(colours, red, len(m)))
    assert w[0] == 0.0 and w[-1] == 1.0 and np.all(np.diff(w) >= 0)
    faint = (m >= 0.1) & ~(target_weight(colours, red, len(m)) >= 1)  # below the threshold: 0 as a mask
    assert faint.sum() >= 40 and np.all(w[faint] > 0) and np.all(w[faint] < 1)
    assert np.all(w[m < 0.04] == 0)  # the plain surface and the faintest trace carry no ink
    # a saturated marking on a noisy plain surface: the mask rules are unchanged, 'intensity' sees more
    cloud = dict(source="synthetic", synthetic="plate", voxel=0.003)
    frac = capture_cloud(CaptureConfig(**cloud))
    ink = capture_cloud(CaptureConfig(**cloud, voxel_rule="intensity"))
    np.testing.assert_array_equal(ink.points, frac.points)
    assert np.all(ink.target >= frac.target) and ink.meta["target"]["voxel_rule"] == "intensity"
    mask = target_weight(bowl.colors, red, len(bowl.colors)) >= 1
    np.testing.assert_array_equal(mask, bowl.mask)


def test_target_all_gives_uniform_weight_without_colours(tmp_path, bowl):
    np.savez(tmp_path / "c.npz", points=bowl.points)
    res = run_cli("capture", "--from", tmp_path / "c.npz", "--target", "all", "--out", tmp_path / "cap")
    assert res.code == 0, res.err
    cap = load_capture(tmp_path / "cap")
    assert cap.colors is None and np.all(cap.target == 1.0)


def test_summary_reports_stages_share_spacing_and_extent(tmp_path, bowl):
    write_ply(tmp_path / "b.ply", bowl.points, bowl.colors)
    res = run_cli("capture", "--from", tmp_path / "b.ply", "--crop", "-1,-1,-1,1,1,1", "--outliers", "20,2",
                  "--out", tmp_path / "cap")
    assert res.code == 0, res.err
    for word in ("input", "crop", "outliers", "voxel 3 mm", "target 'red'", "mean spacing h", "extent"):
        assert word in res.out
    side = json.loads((tmp_path / "cap" / "capture.json").read_text())
    assert [f["stage"] for f in side["filters"]] == ["input", "crop", "outliers", "voxel 3 mm"]
    assert side["spacing_h_m"] == pytest.approx(load_capture(tmp_path / "cap").meta["spacing_h_m"])
    assert 0 < side["target"]["share"] < 0.5


def test_stray_points_are_dropped_unless_kept(tmp_path, bowl):
    # 40 flying pixels scattered 0.2-0.4 m from the bowl: dropped, every one of them and nothing
    # else, so h is the bowl's own; --keep-isolated keeps them. (No voxel grid: strays move its origin.)
    rng = np.random.default_rng(0)
    u = rng.normal(size=(40, 3))
    stray = bowl.points.mean(0) + u / np.linalg.norm(u, axis=1, keepdims=True) * rng.uniform(0.2, 0.4, (40, 1))
    pts = np.vstack([bowl.points, stray])
    cols = np.vstack([bowl.colors, np.full((40, 3), 0.5)])
    np.savez(tmp_path / "s.npz", points=pts, colors=cols)
    np.savez(tmp_path / "clean.npz", points=bowl.points, colors=bowl.colors)
    for name in ("s", "clean"):
        assert run_cli("capture", "--from", tmp_path / f"{name}.npz", "--voxel", "0", "--out", tmp_path / name).code == 0
    res = run_cli("capture", "--from", tmp_path / "s.npz", "--voxel", "0", "--keep-isolated", "--out", tmp_path / "kept")
    assert res.code == 0, res.err
    clean, dropped, kept = (load_capture(tmp_path / n) for n in ("clean", "s", "kept"))
    assert dropped.n_points == clean.n_points and kept.n_points == clean.n_points + 40
    assert np.array_equal(dropped.points, clean.points)
    assert dropped.meta["spacing_h_m"] == clean.meta["spacing_h_m"] < kept.meta["spacing_h_m"]
    assert [f["stage"] for f in dropped.meta["filters"]][-1] == "isolated"
    assert [f["stage"] for f in clean.meta["filters"]] == ["input"]  # a clean cloud loses none


# ---- bad input: one line, exit 2, no traceback, nothing partial written -------------------------

def _bad(tmp_path, *args, needles=()):
    out = tmp_path / "out"
    res = run_cli("capture", *args, "--out", out)
    assert_one_line_error(res, *needles)
    assert not out.exists() or not (out / "capture.json").exists()
    return res


def test_missing_file(tmp_path):
    _bad(tmp_path, "--from", tmp_path / "nope.ply", needles=("no such file",))


def test_unknown_extension(tmp_path):
    (tmp_path / "c.dae").write_text("v 0 0 0\n")  # (.obj is a mesh now: tests/test_capture_mesh.py)
    _bad(tmp_path, "--from", tmp_path / "c.dae", needles=("extension", ".ply", ".obj"))


def test_corrupt_ply(tmp_path, bowl):
    (tmp_path / "junk.ply").write_bytes(b"\x00\x01garbage" * 50)
    _bad(tmp_path, "--from", tmp_path / "junk.ply", needles=("PLY",))
    write_ply(tmp_path / "t.ply", bowl.points, bowl.colors)
    data = (tmp_path / "t.ply").read_bytes()
    (tmp_path / "trunc.ply").write_bytes(data[: len(data) // 2])
    _bad(tmp_path, "--from", tmp_path / "trunc.ply", needles=("truncated",))


def test_empty_and_tiny_clouds(tmp_path):
    (tmp_path / "empty.xyz").write_text("")
    _bad(tmp_path, "--from", tmp_path / "empty.xyz", needles=("empty",))
    np.savez(tmp_path / "tiny.npz", points=np.random.default_rng(0).uniform(0, 0.1, (5, 3)), colors=np.ones((5, 3)))
    _bad(tmp_path, "--from", tmp_path / "tiny.npz", "--target", "all", needles=("only 5 points",))


def test_nan_coordinates(tmp_path, bowl):
    pts = bowl.points.copy()
    pts[3, 1] = np.nan
    pts[9, 0] = np.inf
    np.savez(tmp_path / "nan.npz", points=pts, colors=bowl.colors)
    _bad(tmp_path, "--from", tmp_path / "nan.npz", needles=("2 points with nan", "--drop-invalid"))
    res = run_cli("capture", "--from", tmp_path / "nan.npz", "--drop-invalid", "--out", tmp_path / "ok")
    assert res.code == 0 and "drop invalid" in res.out


def test_no_colours_and_no_target(tmp_path, bowl):
    np.savez(tmp_path / "grey.npz", points=bowl.points)
    _bad(tmp_path, "--from", tmp_path / "grey.npz", needles=("no colours", "--target all"))
    np.savez(tmp_path / "plain.npz", points=bowl.points, colors=np.full_like(bowl.points, 0.8))
    _bad(tmp_path, "--from", tmp_path / "plain.npz", needles=("no points match", "--target"))


def test_duplicate_points(tmp_path, bowl):
    pts = np.vstack([bowl.points, bowl.points[:50]])
    np.savez(tmp_path / "dup.npz", points=pts, colors=np.vstack([bowl.colors, bowl.colors[:50]]))
    _bad(tmp_path, "--from", tmp_path / "dup.npz", "--voxel", "0", needles=("50 duplicate", "--voxel"))


def test_units_mistakes(tmp_path, bowl):
    np.savez(tmp_path / "mm.npz", points=bowl.points * 1000, colors=bowl.colors)
    _bad(tmp_path, "--from", tmp_path / "mm.npz", needles=("millimetres", "--units mm"))
    res = run_cli("capture", "--from", tmp_path / "mm.npz", "--units", "mm", "--out", tmp_path / "ok")
    assert res.code == 0, res.err
    np.savez(tmp_path / "m.npz", points=bowl.points, colors=bowl.colors)
    _bad(tmp_path, "--from", tmp_path / "m.npz", "--units", "mm", needles=("--units m",))
    _bad(tmp_path, "--synthetic", "bowl", "--voxel", "3", needles=("metres",))


def test_bad_options(tmp_path):
    _bad(tmp_path, "--synthetic", "teapot", needles=("unknown synthetic object",))
    _bad(tmp_path, "--synthetic", "bowl", "--target", "chartreuse", needles=("unknown target colour",))
    _bad(tmp_path, "--synthetic", "bowl", "--crop", "1,2,3", needles=("--crop",))
    _bad(tmp_path, "--synthetic", "bowl", "--voxel-rule", "most", needles=("--voxel-rule",))


# ---- precompute bad input -------------------------------------------------------------------------

def test_precompute_refuses_collinear_points(tmp_path):
    t = np.linspace(0, 0.1, 200)
    np.savez(tmp_path / "line.npz", points=np.column_stack([t, 2 * t, -t]))
    assert run_cli("capture", "--from", tmp_path / "line.npz", "--target", "all", "--voxel", "0",
                   "--out", tmp_path / "cap").code == 0
    assert_one_line_error(run_cli("precompute", tmp_path / "cap"), "collinear")


def test_precompute_refuses_nk_not_below_points(tmp_path):
    assert run_cli("capture", "--synthetic", "sphere", "--voxel", "0.02", "--target", "all", "--out", tmp_path / "cap").code == 0
    n = load_capture(tmp_path / "cap").n_points
    assert_one_line_error(run_cli("precompute", tmp_path / "cap", "--nk", n), "--nk")


def test_precompute_refuses_non_capture(tmp_path):
    assert_one_line_error(run_cli("precompute", tmp_path), "not a capture")


def test_precompute_twice_is_a_cache_hit_and_target_change_reuses_it(tmp_path):
    assert run_cli("capture", "--synthetic", "plate", "--voxel", "0.006", "--out", tmp_path / "a").code == 0
    first = run_cli("precompute", tmp_path / "a", "--nk", "30")
    assert first.code == 0 and "computed basis" in first.out and "laplacian" in first.out and "eigensolver" in first.out
    second = run_cli("precompute", tmp_path / "a", "--nk", "30")
    assert second.code == 0 and "cache hit" in second.out and "nothing recomputed" in second.out
    # Same geometry, another target colour rule -> same basis.
    assert run_cli("capture", "--synthetic", "plate", "--voxel", "0.006", "--target", "all", "--out", tmp_path / "b").code == 0
    assert "cache hit" in run_cli("precompute", tmp_path / "b", "--nk", "30").out
    assert "computed basis" in run_cli("precompute", tmp_path / "b", "--nk", "30", "--force").out


def test_cli_process_errors_have_no_traceback(tmp_path):
    res = run_cli_subprocess("capture", "--from", tmp_path / "missing.pcd", "--out", tmp_path / "o")
    assert_one_line_error(res, "no such file")
    help_res = run_cli_subprocess("--help")
    assert help_res.code == 0
    for verb in ("capture", "precompute"):
        assert verb in help_res.out


def test_help_keeps_bracketed_text():
    """Help texts say '[robot] ...' and '[default: ...]': printed literally, not eaten as Rich markup."""
    explore = run_cli("explore", "--help")
    assert explore.code == 0
    flat = " ".join(explore.out.split())
    assert "[robot] Desired contact force" in flat
    assert "[default: $TERGODIC_CACHE_DIR or ~/.cache/tergodic]" in flat
    precompute = " ".join(run_cli("precompute", "--help").out.split())
    assert "[default: $TERGODIC_CACHE_DIR or ~/.cache/tergodic]" in precompute


def test_capture_imports_nothing_from_later_stages():
    """capture/ is the first stage: importing basis/ (or anything after it) would make a cycle."""
    import ast
    from pathlib import Path

    import tergodic_cli.capture as capture_pkg

    later = ("tergodic_cli.basis", "tergodic_cli.explore", "tergodic_cli.robot", "tergodic_cli.runlog",
             "tergodic_cli.sweep")
    found = []
    for path in Path(capture_pkg.__file__).parent.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            found += [f"{path.name}: {n}" for n in names if n.startswith(later)]
    assert not found
