"""``capture --from MESH``: a triangle mesh sampled into a coloured cloud, the mesh kept in the capture."""

from __future__ import annotations

import json
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli

from tergodic_cli.capture import load_capture
from tergodic_cli.capture.mesh import mesh_distance

# A 10 cm square textured in four quadrants: top-left red, top-right green, bottom-left blue, bottom-right white.
SQUARE_V = np.array([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0]], float)
SQUARE_T = np.array([[0, 1, 2], [0, 2, 3]])
QUADRANTS = {(0, 1): (1, 0, 0), (1, 1): (0, 1, 0), (0, 0): (0, 0, 1), (1, 0): (1, 1, 1)}  # (right?, top?) -> rgb


def _quadrant_png(path: Path) -> None:
    from PIL import Image

    im = np.zeros((64, 64, 3), np.uint8)  # image rows run down: the top half is the square's top (v = 1)
    for (right, top), rgb in QUADRANTS.items():
        im[(slice(0, 32) if top else slice(32, 64)), (slice(32, 64) if right else slice(0, 32))] = np.array(rgb) * 255
    Image.fromarray(im).save(path)


def _square_obj(folder: Path) -> Path:
    _quadrant_png(folder / "quad.png")
    (folder / "quad.mtl").write_text("newmtl m\nKd 1 1 1\nmap_Kd quad.png\n")
    lines = ["mtllib quad.mtl"] + [f"v {x} {y} {z}" for x, y, z in SQUARE_V] + [f"vt {x * 10} {y * 10}" for x, y, _ in SQUARE_V]
    lines += ["usemtl m"] + [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in SQUARE_T]
    (folder / "quad.obj").write_text("\n".join(lines) + "\n")
    return folder / "quad.obj"


def _square_glb(folder: Path) -> Path:
    """The same square as glTF binary (written by hand: POSITION, TEXCOORD_0 with v down, an embedded PNG)."""
    _quadrant_png(folder / "quad.png")
    v, t = SQUARE_V.astype("<f4"), SQUARE_T.astype("<u4")
    uv = np.column_stack([SQUARE_V[:, 0] * 10, 1 - SQUARE_V[:, 1] * 10]).astype("<f4")  # glTF: v = 0 at the top
    views, blob = [], b""
    for chunk in (v.tobytes(), uv.tobytes(), t.tobytes(), (folder / "quad.png").read_bytes()):
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(chunk)})
        blob += chunk + b"\0" * (-len(chunk) % 4)
    gl = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
          "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "material": 0}]}],
          "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
          "textures": [{"source": 0}], "images": [{"bufferView": 3, "mimeType": "image/png"}],
          "buffers": [{"byteLength": len(blob)}], "bufferViews": views,
          "accessors": [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
                         "min": v.min(0).tolist(), "max": v.max(0).tolist()},
                        {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC2"},
                        {"bufferView": 2, "componentType": 5125, "count": t.size, "type": "SCALAR"}]}
    js = json.dumps(gl).encode()
    js += b" " * (-len(js) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(blob), 0x004E4942) + blob
    (folder / "quad.glb").write_bytes(struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body)
    return folder / "quad.glb"


def _capture(tmp_path, src, *args):
    out = tmp_path / "cap"
    res = run_cli("capture", "--from", src, *args, "--out", out)
    assert res.code == 0, res.err
    return res, load_capture(out)


@pytest.mark.parametrize("make", [_square_obj, _square_glb], ids=["obj", "glb"])
def test_colour_from_the_texture(tmp_path, make):
    res, cap = _capture(tmp_path, make(tmp_path), "--target", "all", "--voxel", "0.004")
    assert "mesh: 4 vertices, 2 triangles" in res.out and "mesh.npz" in res.out
    p, c = cap.points, cap.colors
    # away from the quadrants' borders (voxel averaging mixes colours there) every colour is its quadrant's
    inner = np.all(np.abs(p[:, :2] - 0.05) > 0.006, axis=1) & np.all(np.abs(p[:, :2] - 0.05) < 0.044, axis=1)
    assert inner.sum() > 200
    for (right, top), rgb in QUADRANTS.items():
        sel = inner & ((p[:, 0] > 0.05) == bool(right)) & ((p[:, 1] > 0.05) == bool(top))
        assert sel.sum() > 30
        np.testing.assert_allclose(c[sel], np.tile(rgb, (sel.sum(), 1)), atol=1 / 255 + 1e-6)
    assert cap.meta["provenance"]["mesh"]["colour"] == "texture"


def test_mesh_round_trip_through_capture_with_the_textured_duck(tmp_path):
    import pybullet_data

    data = Path(pybullet_data.getDataPath())
    # the duck as a user would have it, scaled to 16.5 cm (the file is 1.65 m): v lines x 0.1
    lines = [(" ".join(["v"] + [f"{0.1 * float(x):.6f}" for x in ln.split()[1:4]]) if ln.startswith("v ") else ln)
             for ln in (data / "duck.obj").read_text().splitlines()]
    (tmp_path / "duck.obj").write_text("\n".join(lines) + "\n")
    for name in ("duck.mtl", "duckCM.png"):
        shutil.copy(data / name, tmp_path / name)
    _, cap = _capture(tmp_path, tmp_path / "duck.obj", "--target", "yellow", "--seed", "2")
    V, T = cap.mesh
    assert V.dtype == np.float64 and T.dtype == np.int64 and V.shape[1] == 3 and T.shape == (4212, 3)
    # the mesh kept is the file's, in metres, in the frame of the points
    file_v = np.array([[float(x) for x in ln.split()[1:4]] for ln in lines if ln.startswith("v ")])
    np.testing.assert_allclose(np.unique(V, axis=0), np.unique(file_v, axis=0), atol=1e-12)
    d = mesh_distance(V, T, cap.points)
    assert np.percentile(d, 99) < 0.5e-3 and np.median(d) < 1e-4
    # the duck is yellow (its texture): most of the cloud is segmented as yellow, none as red
    assert cap.meta["target"]["share"] > 0.6 and cap.meta["provenance"]["mesh"]["colour"] == "texture"
    assert cap.meta["provenance"]["mesh"]["seed"] == 2
    # mesh.npz is checksummed and loads strictly
    folder = tmp_path / "cap"
    assert json.loads((folder / "capture.json").read_text())["mesh"]["triangles"] == 4212
    with np.load(folder / "mesh.npz", allow_pickle=False) as z:
        assert sorted(z.files) == ["triangles", "vertices"]


def _ply_with_faces(path: Path, V, T, colors=None, nan=False) -> None:
    head = ["ply", "format ascii 1.0", f"element vertex {len(V)}", "property float x", "property float y", "property float z"]
    if colors is not None:
        head += ["property uchar red", "property uchar green", "property uchar blue"]
    head += [f"element face {len(T)}", "property list uchar int vertex_indices", "end_header"]
    rows = []
    for i, v in enumerate(V):
        row = " ".join("nan" if nan and i == 0 else f"{x:.7f}" for x in v)
        if colors is not None:
            row += " " + " ".join(str(int(round(c * 255))) for c in colors[i])
        rows.append(row)
    rows += [f"3 {a} {b} {c}" for a, b, c in T]
    path.write_text("\n".join(head + rows) + "\n")


def test_a_ply_with_faces_is_a_mesh_and_one_without_stays_a_cloud(tmp_path):
    import open3d as o3d

    sphere = o3d.geometry.TriangleMesh.create_sphere(0.05, 12)
    V, T = np.asarray(sphere.vertices), np.asarray(sphere.triangles)
    red_top = np.where((V[:, 2] > 0.0)[:, None], [0.8, 0.08, 0.08], [0.9, 0.9, 0.9])
    _ply_with_faces(tmp_path / "ball.ply", V, T, red_top)
    _, cap = _capture(tmp_path, tmp_path / "ball.ply", "--seed", "1")
    assert cap.mesh is not None and len(cap.mesh[1]) == len(T)
    assert cap.n_points > 5 * len(V)  # sampled every 3 mm, not the vertices
    from tergodic_cli.capture.filters import mean_spacing

    assert 0.0025 < mean_spacing(cap.points, k=1) < 0.0036
    assert cap.meta["provenance"]["mesh"]["colour"] == "vertex"
    # the red top half (vertex colours interpolated; the equator's triangles blend): about half the points
    assert 0.4 < cap.meta["target"]["share"] < 0.6
    ring = 0.05 * np.sin(np.pi / 12)  # one band of triangles blends (12 rings: 15° apart)
    assert np.all(cap.points[cap.target > 0][:, 2] > -ring - 0.002)
    assert np.mean(cap.points[cap.target > 0][:, 2] > 0) > 0.9
    # the same vertices without faces: a cloud, as before
    from tergodic_cli.capture.readers import write_ply

    write_ply(tmp_path / "verts.ply", V, red_top)
    out = tmp_path / "cloud"
    assert run_cli("capture", "--from", tmp_path / "verts.ply", "--voxel", "0", "--out", out).code == 0
    cloud = load_capture(out)
    assert cloud.mesh is None and cloud.n_points == len(np.unique(V, axis=0))
    assert not (out / "mesh.npz").exists() and "mesh" not in cloud.meta


def test_sampling_is_seeded(tmp_path):
    src = _square_obj(tmp_path)
    a = run_cli("capture", "--from", src, "--target", "all", "--seed", "0", "--out", tmp_path / "a")
    b = run_cli("capture", "--from", src, "--target", "all", "--seed", "0", "--out", tmp_path / "b")
    c = run_cli("capture", "--from", src, "--target", "all", "--seed", "1", "--out", tmp_path / "c")
    assert a.code == b.code == c.code == 0
    pa, pb, pc = (load_capture(tmp_path / k).points for k in "abc")
    assert np.array_equal(pa, pb) and not np.array_equal(pa, pc)


@pytest.mark.parametrize("name, content, needles", [
    ("empty.obj", "", ("empty",)),
    ("points.obj", "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\n", ("no triangles",)),
    ("nan.obj", "v nan 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 1 2 3\n", ("non-finite",)),
    ("flat.obj", "v 0 0 0\nv 0.1 0 0\nv 0.2 0 0\nf 1 2 3\n", ("degenerate",)),
    ("bad.obj", "v 0 0 zero\nf 1 2 3\n", ("not a readable",)),
    ("junk.stl", "this is not an stl file at all\n" * 5, ("junk.stl",)),
    ("big.obj", "v 0 0 0\nv 100 0 0\nv 0 100 0\nf 1 2 3\n", ("millimetres", "--units mm")),
])
def test_bad_mesh_files_exit_2_with_one_line(tmp_path, name, content, needles):
    (tmp_path / name).write_text(content)
    out = tmp_path / "out"
    res = run_cli("capture", "--from", tmp_path / name, "--target", "all", "--out", out)
    assert_one_line_error(res, *needles)
    assert not out.exists()


def test_bad_face_ply_exits_2(tmp_path):
    V = SQUARE_V
    _ply_with_faces(tmp_path / "nan.ply", V, SQUARE_T, nan=True)
    assert_one_line_error(run_cli("capture", "--from", tmp_path / "nan.ply", "--target", "all", "--out", tmp_path / "o"),
                          "nan.ply", "non-finite")


def test_load_capture_refuses_a_tampered_or_missing_mesh(tmp_path):
    _capture(tmp_path, _square_obj(tmp_path), "--target", "all")
    folder = tmp_path / "cap"
    with np.load(folder / "mesh.npz", allow_pickle=False) as z:
        v, t = z["vertices"], z["triangles"]
    np.savez(folder / "mesh.npz", vertices=v + 0.001, triangles=t)
    res = run_cli("precompute", folder)
    assert_one_line_error(res, "mesh.npz", "checksum")
    (folder / "mesh.npz").unlink()
    assert_one_line_error(run_cli("precompute", folder), "no mesh.npz")


def test_a_marking_the_mesh_does_not_have_is_refused_before_sampling(tmp_path, monkeypatch):
    """pybullet_data's duck as shipped (1.65 m across, yellow): '--target red' is refused from a quick
    look at its texture, before the Poisson-disk sampling of ~0.5 M points (8 min here) starts."""
    import pybullet_data

    import tergodic_cli.capture.mesh as mesh_mod

    def never(*a, **k):
        raise AssertionError("the mesh was sampled before its marking was checked")

    monkeypatch.setattr(mesh_mod, "sample_mesh", never)
    res = run_cli("capture", "--from", Path(pybullet_data.getDataPath()) / "duck.obj", "--target", "red",
                  "--out", tmp_path / "cap")
    assert res.code == 2 and "no points match the target colour 'red'" in res.err, res.err
    assert len(res.err.strip().splitlines()) == 1 and not (tmp_path / "cap").exists()
