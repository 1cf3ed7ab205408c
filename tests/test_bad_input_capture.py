"""Bad input and operating-system faults for ``capture`` and ``precompute`` (issue 16, items 3-6).

Every case runs the installed ``tergodic`` in a subprocess (so C-level stderr from libraries
would show) and asserts: exit 2, exactly one non-empty output line, ``tergodic: error:``
naming the problem, no traceback, no ``RPly``, and that an earlier good capture folder is
byte-identical afterwards with no temporary sibling left beside it.

Read-only and full filesystems are real: a read-only bind mount and a small tmpfs (root
ignores chmod). Where mount is not permitted the test skips, saying so.
"""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
import sys
import uuid
from pathlib import Path

import numpy as np
import pytest

EXE = Path(sys.executable).with_name("tergodic")


# ------------------------------------------------------------------------------------ helpers

def run(*args, env=None):
    proc = subprocess.run([str(EXE), *map(str, args)], capture_output=True, text=True, timeout=600,
                          env={**os.environ, "TERGODIC_NO_PROGRESS": "1", **(env or {})})
    return proc.returncode, proc.stdout, proc.stderr


def snapshot(folder: Path) -> dict:
    """Every file under ``folder`` with its bytes and mode, and the names beside it."""
    files = {str(p.relative_to(folder)): (p.read_bytes(), p.stat().st_mode) for p in sorted(folder.rglob("*"))}
    return {"files": files, "siblings": sorted(p.name for p in folder.parent.iterdir())}


def one_line_error(code, out, err, *needles, absent=()):
    text = out + err
    lines = [ln for ln in text.splitlines() if ln.strip()]
    assert code == 2, (code, text)
    assert len(lines) == 1, text
    assert lines[0].startswith("tergodic: error:"), text
    assert "Traceback" not in text and "RPly" not in text
    low = lines[0].lower()
    for needle in needles:
        assert needle.lower() in low, (needle, lines[0])
    for word in absent:
        assert word.lower() not in low, (word, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def cloud():
    from tergodic_cli.capture.synthetic import generate_synthetic

    syn = generate_synthetic("bowl", "X", 0)
    idx = np.random.default_rng(0).choice(len(syn.points), 1500, replace=False)
    return syn.points[idx], np.rint(syn.colors[idx] * 255).astype(np.int64)


def _bowl_capture(out: Path, voxel: str) -> Path:
    code, _, err = run("capture", "--synthetic", "bowl", "--voxel", voxel, "--out", out)
    assert code == 0, err
    return out


@pytest.fixture(scope="module")
def good_template(tmp_path_factory) -> Path:
    """The good capture, made once a module (a process of its own: each copy below is byte-identical to a fresh one)."""
    return _bowl_capture(tmp_path_factory.mktemp("good") / "good", "0.006")


@pytest.fixture
def good(tmp_path, good_template):
    """A good capture folder (a copy, modes kept); each test checks it is byte-identical after the bad run."""
    return Path(shutil.copytree(good_template, tmp_path / "good"))


def bad_capture(good: Path, *args, needles=(), absent=()):
    """``capture ARGS --out GOOD --overwrite`` must fail in one line and leave GOOD untouched."""
    before = snapshot(good)
    line = one_line_error(*run("capture", *args, "--out", good, "--overwrite"), *needles, absent=absent)
    assert snapshot(good) == before
    return line


def ply_header(n, fmt="ascii", colour="uchar", xyz="float"):
    props = [f"property {xyz} {a}" for a in "xyz"] + [f"property {colour} {c}" for c in ("red", "green", "blue")]
    return ("\n".join(["ply", f"format {fmt} 1.0", f"element vertex {n}", *props, "end_header"]) + "\n").encode()


def ascii_rows(points, colours):
    return [f"{p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {c[0]} {c[1]} {c[2]}" for p, c in zip(points, colours)]


def write_ascii_ply(path, rows, n=None, colour="uchar"):
    path.write_bytes(ply_header(len(rows) if n is None else n, colour=colour) + ("\n".join(rows) + "\n").encode())
    return path


def binary_ply_bytes(points, colours, n=None):
    rec = np.empty(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    rec["x"], rec["y"], rec["z"] = points.T
    rec["r"], rec["g"], rec["b"] = colours.T
    return ply_header(len(points) if n is None else n, "binary_little_endian") + rec.tobytes()


def pcd_ascii(points, colours, n=None, width=None, rows=None):
    rgb = [(int(c[0]) << 16) | (int(c[1]) << 8) | int(c[2]) for c in colours]
    rows = rows if rows is not None else [f"{p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {v}" for p, v in zip(points, rgb)]
    n = len(rows) if n is None else n
    head = ["# .PCD v0.7", "VERSION 0.7", "FIELDS x y z rgb", "SIZE 4 4 4 4", "TYPE F F F U", "COUNT 1 1 1 1",
            f"WIDTH {n if width is None else width}", "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {n}", "DATA ascii"]
    return ("\n".join(head + rows) + "\n").encode(), rows


def pcd_binary(points, colours, n=None):
    rec = np.empty(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    rec["x"], rec["y"], rec["z"] = points.T
    rec["rgb"] = (colours[:, 0] << 16) | (colours[:, 1] << 8) | colours[:, 2]
    n = len(points) if n is None else n
    head = ["VERSION 0.7", "FIELDS x y z rgb", "SIZE 4 4 4 4", "TYPE F F F U", "COUNT 1 1 1 1",
            f"WIDTH {n}", "HEIGHT 1", f"POINTS {n}", "DATA binary"]
    return ("\n".join(head) + "\n").encode() + rec.tobytes()


# ------------------------------------------------------------------------------- PLY (ascii)

def test_ply_ascii_header_declares_more_vertices_than_the_body(tmp_path, good, cloud):
    f = write_ascii_ply(tmp_path / "more.ply", ascii_rows(*cloud), n=1600)
    bad_capture(good, "--from", f, needles=("more.ply", "line 1511", "declares 1600", "1500"), absent=("units",))


def test_ply_ascii_header_declares_fewer_vertices_than_the_body(tmp_path, good, cloud):
    f = write_ascii_ply(tmp_path / "fewer.ply", ascii_rows(*cloud), n=20)
    bad_capture(good, "--from", f, needles=("fewer.ply", "declares 20", "1500 rows", "element vertex"))


def test_ply_ascii_inf_in_one_row(tmp_path, good, cloud):
    rows = ascii_rows(*cloud)
    rows[40] = "inf " + rows[40].split(" ", 1)[1]
    f = write_ascii_ply(tmp_path / "inf.ply", rows)
    # 10 header lines, so row 40 is line 51.
    bad_capture(good, "--from", f, needles=("inf.ply", "line 51", "inf", "--drop-invalid"), absent=("units",))


def test_ply_ascii_nan_in_one_row(tmp_path, good, cloud):
    rows = ascii_rows(*cloud)
    parts = rows[7].split()
    parts[2] = "nan"
    rows[7] = " ".join(parts)
    f = write_ascii_ply(tmp_path / "nan.ply", rows)
    bad_capture(good, "--from", f, needles=("nan.ply", "line 18", "'z'", "--drop-invalid"))


def test_ply_ascii_nan_is_dropped_with_drop_invalid(tmp_path, cloud):
    rows = ascii_rows(*cloud)
    rows[7] = "nan " + rows[7].split(" ", 1)[1]
    f = write_ascii_ply(tmp_path / "nan.ply", rows)
    code, out, err = run("capture", "--from", f, "--drop-invalid", "--voxel", "0", "--out", tmp_path / "ok")
    assert code == 0, err
    side = json.loads((tmp_path / "ok" / "capture.json").read_text())
    assert side["counts"]["output"] == 1499 and "drop invalid" in out


def test_ply_ascii_row_with_a_missing_column(tmp_path, good, cloud):
    rows = ascii_rows(*cloud)
    rows[100] = " ".join(rows[100].split()[:5])
    f = write_ascii_ply(tmp_path / "cols.ply", rows)
    bad_capture(good, "--from", f, needles=("cols.ply", "line 111", "5 values where 6"))


def test_ply_ascii_non_number(tmp_path, good, cloud):
    rows = ascii_rows(*cloud)
    rows[3] = rows[3].replace(rows[3].split()[1], "0.1x", 1)
    f = write_ascii_ply(tmp_path / "word.ply", rows)
    bad_capture(good, "--from", f, needles=("word.ply", "line 14", "not a number"))


def test_ply_no_end_header(tmp_path, good):
    (tmp_path / "nohead.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n0 0 0\n")
    bad_capture(good, "--from", tmp_path / "nohead.ply", needles=("nohead.ply", "end_header"))


def test_ply_without_z(tmp_path, good):
    text = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nend_header\n0 0\n1 1\n"
    (tmp_path / "noz.ply").write_text(text)
    bad_capture(good, "--from", tmp_path / "noz.ply", needles=("noz.ply", "'z'"))


# ------------------------------------------------------------------------------ PLY (binary)

def test_ply_binary_truncated(tmp_path, good, cloud):
    data = binary_ply_bytes(*cloud)
    (tmp_path / "cut.ply").write_bytes(data[: len(data) - 1000])
    bad_capture(good, "--from", tmp_path / "cut.ply", needles=("cut.ply", "truncated", "1500 vertices"), absent=("units",))


def test_ply_binary_header_count_too_small(tmp_path, good, cloud):
    (tmp_path / "short.ply").write_bytes(binary_ply_bytes(*cloud, n=1000))
    bad_capture(good, "--from", tmp_path / "short.ply", needles=("short.ply", "bytes after the 1000 vertices", "500 more"))


def test_ply_binary_nan(tmp_path, good, cloud):
    pts = cloud[0].copy()
    pts[12, 1] = np.nan
    (tmp_path / "nanb.ply").write_bytes(binary_ply_bytes(pts, cloud[1]))
    bad_capture(good, "--from", tmp_path / "nanb.ply", needles=("nanb.ply", "vertex 12", "'y'", "--drop-invalid"))


def test_ply_binary_garbage_body_is_not_a_units_problem(tmp_path, good, cloud):
    data = bytearray(binary_ply_bytes(*cloud))
    head = len(ply_header(1500, "binary_little_endian"))
    rng = np.random.default_rng(3)
    data[head:] = rng.integers(0, 256, len(data) - head, dtype=np.uint8).tobytes()
    (tmp_path / "garbage.ply").write_bytes(bytes(data))
    bad_capture(good, "--from", tmp_path / "garbage.ply", needles=("garbage.ply", "corrupt", "re-export"),
                absent=("units", "millimetres", "--drop-invalid"))


def test_ply_ushort_colours_are_read_as_16_bit(tmp_path, cloud):
    pts, c8 = cloud
    f = write_ascii_ply(tmp_path / "us.ply", ascii_rows(pts, c8 * 257), colour="ushort")
    code, _, err = run("capture", "--from", f, "--voxel", "0", "--out", tmp_path / "cap")
    assert code == 0, err
    with np.load(tmp_path / "cap" / "cloud.npz") as d:
        colours = d["colors"]
    assert np.allclose(colours, c8 / 255.0, atol=1e-6)  # as 8-bit they would all be clipped to white


def test_ply_nan_in_an_unused_property_is_fine(tmp_path, cloud):
    pts, c8 = cloud
    head = ("ply\nformat ascii 1.0\nelement vertex 1500\n" + "".join(f"property float {a}\n" for a in "xyz")
            + "property float nx\n" + "".join(f"property uchar {c}\n" for c in ("red", "green", "blue")) + "end_header\n")
    rows = [f"{p[0]:.6f} {p[1]:.6f} {p[2]:.6f} nan {c[0]} {c[1]} {c[2]}" for p, c in zip(pts, c8)]
    (tmp_path / "normals.ply").write_text(head + "\n".join(rows) + "\n")
    code, _, err = run("capture", "--from", tmp_path / "normals.ply", "--voxel", "0", "--out", tmp_path / "cap")
    assert code == 0, err


def test_ply_float_colours_above_one(tmp_path, good, cloud):
    f = write_ascii_ply(tmp_path / "fc.ply", ascii_rows(cloud[0], cloud[1] * 257), colour="float")
    bad_capture(good, "--from", f, needles=("fc.ply", "out of range", "--colour-depth 16"))


# ------------------------------------------------------------------------------------- PCD

def test_pcd_ascii_points_more_than_body(tmp_path, good, cloud):
    data, _ = pcd_ascii(*cloud, n=1700)
    (tmp_path / "more.pcd").write_bytes(data)
    bad_capture(good, "--from", tmp_path / "more.pcd", needles=("more.pcd", "points 1700", "1500 rows"))


def test_pcd_ascii_points_fewer_than_body(tmp_path, good, cloud):
    data, _ = pcd_ascii(*cloud, n=100)
    (tmp_path / "fewer.pcd").write_bytes(data)
    bad_capture(good, "--from", tmp_path / "fewer.pcd", needles=("fewer.pcd", "points 100", "1500 rows"))


def test_pcd_width_times_height_is_not_points(tmp_path, good, cloud):
    data, _ = pcd_ascii(*cloud, width=1400)
    (tmp_path / "wh.pcd").write_bytes(data)
    bad_capture(good, "--from", tmp_path / "wh.pcd", needles=("wh.pcd", "width x height = 1400", "points = 1500"))


def test_pcd_ascii_nan_point(tmp_path, good, cloud):
    _, rows = pcd_ascii(*cloud)
    rows[5] = "nan nan nan 0"
    data, _ = pcd_ascii(*cloud, rows=rows)
    (tmp_path / "nan.pcd").write_bytes(data)
    # 11 header lines: row 5 is line 17.
    bad_capture(good, "--from", tmp_path / "nan.pcd", needles=("nan.pcd", "line 17", "--drop-invalid"))


def test_pcd_ascii_wrong_column_count(tmp_path, good, cloud):
    _, rows = pcd_ascii(*cloud)
    rows[30] = rows[30] + " 7"
    data, _ = pcd_ascii(*cloud, rows=rows)
    (tmp_path / "cols.pcd").write_bytes(data)
    bad_capture(good, "--from", tmp_path / "cols.pcd", needles=("cols.pcd", "line 42", "5 values where 4"))


def test_pcd_binary_truncated(tmp_path, good, cloud):
    data = pcd_binary(*cloud)
    (tmp_path / "cut.pcd").write_bytes(data[:-160])
    bad_capture(good, "--from", tmp_path / "cut.pcd", needles=("cut.pcd", "truncated", "1490 are complete"))


def test_pcd_binary_garbage_body_is_not_a_units_problem(tmp_path, good, cloud):
    data = bytearray(pcd_binary(*cloud))
    body = len(data) - 1500 * 16
    data[body:] = np.random.default_rng(5).integers(0, 256, 1500 * 16, dtype=np.uint8).tobytes()
    (tmp_path / "garbage.pcd").write_bytes(bytes(data))
    bad_capture(good, "--from", tmp_path / "garbage.pcd", needles=("garbage.pcd", "corrupt"), absent=("units", "millimetres"))


def test_pcd_binary_reads_packed_colours(tmp_path, cloud):
    (tmp_path / "ok.pcd").write_bytes(pcd_binary(*cloud))
    code, _, err = run("capture", "--from", tmp_path / "ok.pcd", "--voxel", "0", "--out", tmp_path / "cap")
    assert code == 0, err
    with np.load(tmp_path / "cap" / "cloud.npz") as d:
        assert np.allclose(d["colors"], cloud[1] / 255.0, atol=1e-6)
        assert np.allclose(d["points"], cloud[0], atol=1e-6)


# ------------------------------------------------------------------------------ XYZ / XYZRGB

def test_xyzrgb_16_bit_colours_are_refused_without_colour_depth(tmp_path, good, cloud):
    (tmp_path / "c16.xyzrgb").write_text("\n".join(ascii_rows(cloud[0], cloud[1] * 257)) + "\n")
    bad_capture(good, "--from", tmp_path / "c16.xyzrgb", needles=("c16.xyzrgb", "line 1", "above 255", "--colour-depth 16"))


def test_xyzrgb_16_bit_colours_with_colour_depth_16(tmp_path, cloud):
    (tmp_path / "c16.xyzrgb").write_text("\n".join(ascii_rows(cloud[0], cloud[1] * 257)) + "\n")
    code, _, err = run("capture", "--from", tmp_path / "c16.xyzrgb", "--colour-depth", "16", "--voxel", "0",
                       "--out", tmp_path / "cap")
    assert code == 0, err
    with np.load(tmp_path / "cap" / "cloud.npz") as d:
        assert np.allclose(d["colors"], cloud[1] / 255.0, atol=1e-6)


def test_xyzrgb_colour_depth_8_with_16_bit_values(tmp_path, good, cloud):
    (tmp_path / "c16.xyzrgb").write_text("\n".join(ascii_rows(cloud[0], cloud[1] * 257)) + "\n")
    bad_capture(good, "--from", tmp_path / "c16.xyzrgb", "--colour-depth", "8",
                needles=("c16.xyzrgb", "out of range for 8-bit", "--colour-depth 16"))


def test_colour_depth_must_be_8_or_16(tmp_path, good, cloud):
    (tmp_path / "c.xyzrgb").write_text("\n".join(ascii_rows(*cloud)) + "\n")
    bad_capture(good, "--from", tmp_path / "c.xyzrgb", "--colour-depth", "12", needles=("--colour-depth 12", "8 or 16"))


def test_xyzrgb_inf_names_the_line(tmp_path, good, cloud):
    rows = ascii_rows(*cloud)
    rows[200] = rows[200].replace(rows[200].split()[1], "-inf", 1)
    (tmp_path / "inf.xyzrgb").write_text("# exported\n" + "\n".join(rows) + "\n")
    bad_capture(good, "--from", tmp_path / "inf.xyzrgb", needles=("inf.xyzrgb", "line 202", "column 2", "--drop-invalid"))


def test_xyzrgb_row_with_three_columns(tmp_path, good, cloud):
    rows = ascii_rows(*cloud)
    rows[6] = "0.01 0.02 0.03"
    (tmp_path / "mixed.xyzrgb").write_text("\n".join(rows) + "\n")
    bad_capture(good, "--from", tmp_path / "mixed.xyzrgb", needles=("mixed.xyzrgb", "line 7", "3 values where 6"))


def test_xyz_with_four_columns(tmp_path, good, cloud):
    (tmp_path / "four.xyz").write_text("\n".join(f"{p[0]} {p[1]} {p[2]} 0.5" for p in cloud[0]) + "\n")
    bad_capture(good, "--from", tmp_path / "four.xyz", needles=("four.xyz", "line 1", "4 columns", "3 (x y z) or 6"))


def test_xyzrgb_negative_colour(tmp_path, good, cloud):
    rows = ascii_rows(*cloud)
    rows[9] = " ".join(rows[9].split()[:3] + ["-5", "0", "0"])
    (tmp_path / "neg.xyzrgb").write_text("\n".join(rows) + "\n")
    bad_capture(good, "--from", tmp_path / "neg.xyzrgb", needles=("neg.xyzrgb", "line 10", "negative colour"))


# ------------------------------------------------------------------------------------- NPZ

def test_npz_colours_for_another_point_count(tmp_path, good, cloud):
    np.savez(tmp_path / "n.npz", points=cloud[0], colors=cloud[1][:-3])
    bad_capture(good, "--from", tmp_path / "n.npz", needles=("n.npz", "field 'colors'", "1500 points"))


def test_npz_with_pickled_objects_is_never_unpickled(tmp_path, good, cloud):
    marker = tmp_path / "unpickled"
    obj = np.empty(1, dtype=object)
    obj[0] = _Boom(str(marker))
    np.savez(tmp_path / "pickle.npz", points=obj)
    bad_capture(good, "--from", tmp_path / "pickle.npz", needles=("pickle.npz", "not a readable npz"))
    assert not marker.exists()


class _Boom:
    """Unpickling this would create a file: proof that it happened."""

    def __init__(self, path):
        self.path = path

    def __reduce__(self):
        return (open, (self.path, "w"))


def test_npz_that_is_not_a_zip(tmp_path, good):
    (tmp_path / "junk.npz").write_bytes(b"PK\x03\x04" + b"\x00garbage" * 40)
    bad_capture(good, "--from", tmp_path / "junk.npz", needles=("junk.npz", "not a readable npz"))


def test_pcd_unknown_data_kind(tmp_path, good, cloud):
    data, _ = pcd_ascii(*cloud)
    (tmp_path / "lzma.pcd").write_bytes(data.replace(b"DATA ascii", b"DATA lzma"))
    bad_capture(good, "--from", tmp_path / "lzma.pcd", needles=("lzma.pcd", "unknown pcd data 'lzma'"))


def test_npz_nan_row(tmp_path, good, cloud):
    pts = cloud[0].copy()
    pts[33] = np.nan
    np.savez(tmp_path / "nan.npz", points=pts, colors=cloud[1])
    bad_capture(good, "--from", tmp_path / "nan.npz", needles=("nan.npz", "row 33", "--drop-invalid"))


def test_identical_points_are_not_a_units_problem(tmp_path, good):
    np.savez(tmp_path / "same.npz", points=np.full((200, 3), 0.1), colors=np.ones((200, 3)))
    bad_capture(good, "--from", tmp_path / "same.npz", "--target", "all", needles=("same.npz", "identical"),
                absent=("units", "millimetres"))


def test_huge_corrupt_values_are_not_a_units_problem(tmp_path, good, cloud):
    pts = cloud[0].copy()
    pts[5] = [3e28, -1e30, 7e25]
    np.savez(tmp_path / "huge.npz", points=pts, colors=cloud[1])
    bad_capture(good, "--from", tmp_path / "huge.npz", needles=("huge.npz", "corrupt"), absent=("--units", "millimetres read"))


def test_millimetres_still_get_the_units_message(tmp_path, good, cloud):
    np.savez(tmp_path / "mm.npz", points=cloud[0] * 1000, colors=cloud[1])
    bad_capture(good, "--from", tmp_path / "mm.npz", needles=("mm.npz", "millimetres", "--units mm"))


@pytest.mark.parametrize("spec, needle", [("hsv:400-10,0.5,0.3", "hue 400"), ("hsv:340-20,1.5,0.3", "0..1"),
                                          ("hsv:nan-20,0.5,0.3", "hue nan")])
def test_hsv_target_out_of_range(good, spec, needle):
    bad_capture(good, "--synthetic", "bowl", "--target", spec, needles=(needle, "hsv:340-20,0.5,0.3"), absent=("no points match",))


# ----------------------------------------------------------------------------- --out faults

def test_out_under_a_file(tmp_path, good):
    (tmp_path / "afile").write_text("x")
    before = snapshot(good)
    one_line_error(*run("capture", "--synthetic", "bowl", "--out", tmp_path / "afile" / "cap"), "afile", "is a file", "--out")
    assert snapshot(good) == before and (tmp_path / "afile").read_text() == "x"


def test_out_is_a_file(tmp_path):
    (tmp_path / "afile").write_text("x")
    one_line_error(*run("capture", "--synthetic", "bowl", "--out", tmp_path / "afile"), "afile", "is a file")
    assert (tmp_path / "afile").read_text() == "x"


def test_existing_capture_needs_overwrite(good):
    before = snapshot(good)
    one_line_error(*run("capture", "--synthetic", "plate", "--out", good), "already holds a capture", "--overwrite")
    assert snapshot(good) == before


def test_overwrite_replaces_the_whole_folder(tmp_path, good):
    code, _, err = run("capture", "--synthetic", "plate", "--voxel", "0.006", "--out", good, "--overwrite")
    assert code == 0, err
    assert json.loads((good / "capture.json").read_text())["provenance"]["object"] == "plate"
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".good")) == []


def test_out_that_is_the_current_folder(good):
    before = snapshot(good)
    proc = subprocess.run([str(EXE), "capture", "--synthetic", "bowl", "--out", ".", "--overwrite"], cwd=good,
                          capture_output=True, text=True, timeout=600, env={**os.environ, "TERGODIC_NO_PROGRESS": "1"})
    one_line_error(proc.returncode, proc.stdout, proc.stderr, "--out .", "current folder")
    assert snapshot(good) == before


def test_overwrite_refuses_a_folder_of_other_files(tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("keep me")
    one_line_error(*run("capture", "--synthetic", "bowl", "--out", mine, "--overwrite"), "not a capture", "another --out")
    assert (mine / "thesis.tex").read_text() == "keep me"


@pytest.fixture
def mount(tmp_path):
    """mount(kind, path, size=None): a tmpfs or a read-only bind mount, unmounted after the test."""
    mounted = []

    def _mount(kind: str, path: Path, size: str = "256k") -> Path:
        path.mkdir(parents=True, exist_ok=True)
        if kind == "tmpfs":
            cmds = [["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)]]
        else:  # read-only bind of the folder onto itself
            cmds = [["mount", "--bind", str(path), str(path)], ["mount", "-o", "remount,ro,bind", str(path)]]
        for i, cmd in enumerate(cmds):
            try:
                proc = subprocess.run(cmd, capture_output=True, text=True)
            except FileNotFoundError:
                pytest.skip("no mount command: cannot make a real read-only or full filesystem")
            if proc.returncode != 0:
                if i:
                    subprocess.run(["umount", str(path)], capture_output=True)
                pytest.skip(f"mount is not permitted here ({proc.stderr.strip() or proc.returncode}): "
                            "a read-only or full filesystem needs root and mount")
            if i == 0:
                mounted.append(path)
        return path

    yield _mount
    for path in reversed(mounted):
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def fill(folder: Path, leave: int = 4096) -> None:
    """Fill the filesystem of ``folder`` until about ``leave`` bytes are free."""
    st = os.statvfs(folder)
    free = st.f_bavail * st.f_frsize
    with open(folder / "filler", "wb") as fh:
        try:
            fh.write(b"\0" * max(free - leave, 0))
        except OSError:
            pass


def test_out_on_a_read_only_filesystem(tmp_path, mount):
    ro = tmp_path / "ro"
    ro.mkdir()
    code, _, err = run("capture", "--synthetic", "bowl", "--voxel", "0.006", "--out", ro / "cap")
    assert code == 0, err
    mount("ro", ro)
    before = snapshot(ro / "cap")
    one_line_error(*run("capture", "--synthetic", "bowl", "--out", ro / "new"), "read-only filesystem", str(ro / "new"))
    one_line_error(*run("capture", "--synthetic", "plate", "--out", ro / "cap", "--overwrite"), "read-only filesystem")
    assert snapshot(ro / "cap") == before and not (ro / "new").exists()


def test_out_in_a_chmod_read_only_folder(tmp_path):
    if os.geteuid() == 0:
        pytest.skip("root ignores chmod; test_out_on_a_read_only_filesystem covers this with a read-only mount")
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        one_line_error(*run("capture", "--synthetic", "bowl", "--out", locked / "cap"), "permission denied", "--out")
        assert list(locked.iterdir()) == []
    finally:
        locked.chmod(0o755)


def test_out_on_a_full_disk_keeps_the_old_capture(tmp_path, mount):
    disk = mount("tmpfs", tmp_path / "disk", "512k")
    code, _, err = run("capture", "--synthetic", "bowl", "--voxel", "0.006", "--out", disk / "cap")
    assert code == 0, err
    fill(disk, leave=8192)
    before = snapshot(disk / "cap")
    one_line_error(*run("capture", "--synthetic", "bowl", "--voxel", "0.004", "--out", disk / "cap", "--overwrite"),
                   "no space left on device", str(disk / "cap"), "free space")
    assert snapshot(disk / "cap") == before  # also: no temporary sibling left behind


def test_out_on_a_full_disk_leaves_nothing_new(tmp_path, mount):
    disk = mount("tmpfs", tmp_path / "disk", "256k")
    fill(disk, leave=8192)
    one_line_error(*run("capture", "--synthetic", "bowl", "--out", disk / "deep" / "cap"), "no space left on device")
    assert sorted(p.name for p in disk.iterdir()) == ["filler"]


# ------------------------------------------------------------------------- --cache-dir faults

@pytest.fixture(scope="module")
def small_template(tmp_path_factory) -> Path:
    return _bowl_capture(tmp_path_factory.mktemp("small") / "small", "0.008")


@pytest.fixture
def small(tmp_path, small_template):
    """A small capture (a few hundred points) for precompute: a copy of one made once a module."""
    return Path(shutil.copytree(small_template, tmp_path / "small"))


def test_cache_dir_is_a_file(tmp_path, small):
    (tmp_path / "cachefile").write_text("x")
    one_line_error(*run("precompute", small, "--nk", "20", "--cache-dir", tmp_path / "cachefile"),
                   "cachefile", "is a file", "--cache-dir")
    assert (tmp_path / "cachefile").read_text() == "x"


def test_cache_dir_read_only(tmp_path, small, mount):
    ro = mount("ro", tmp_path / "rocache")
    one_line_error(*run("precompute", small, "--nk", "20", "--cache-dir", ro), "read-only filesystem", "--cache-dir")
    assert list(ro.iterdir()) == []


def test_cache_dir_full(tmp_path, small, mount):
    disk = mount("tmpfs", tmp_path / "fullcache", "64k")
    one_line_error(*run("precompute", small, "--nk", "40", "--cache-dir", disk),
                   "no space left on device", "basis cache", "--cache-dir")
    # Nothing partial: no entry and no temporary folder under basis/.
    assert not (disk / "basis").exists() or list((disk / "basis").iterdir()) == []


def test_cache_dir_read_only_still_serves_a_cached_basis(tmp_path, small, mount):
    cache = tmp_path / "warm"
    code, _, err = run("precompute", small, "--nk", "20", "--cache-dir", cache)
    assert code == 0, err
    mount("ro", cache)
    code, out, err = run("precompute", small, "--nk", "20", "--cache-dir", cache)
    assert code == 0 and "cache hit" in out, err


# -------------------------------------------------------------------- capture.json integrity

def test_stub_capture_json_is_refused_by_precompute(small):
    (small / "capture.json").write_text("{}\n")
    one_line_error(*run("precompute", small, "--nk", "20"), "capture.json", "stub", "re-run 'tergodic capture")


def test_edited_capture_json_is_refused_by_precompute(small):
    side = json.loads((small / "capture.json").read_text())
    side["spacing_h_m"] *= 2
    (small / "capture.json").write_text(json.dumps(side, indent=2))
    one_line_error(*run("precompute", small, "--nk", "20"), "capture.json", "edited", "re-run 'tergodic capture")


def test_changed_cloud_npz_is_refused(small):
    with np.load(small / "cloud.npz") as d:
        arrays = dict(d)
    arrays["target"][:] = 1.0
    np.savez(small / "cloud.npz", **arrays)
    one_line_error(*run("precompute", small, "--nk", "20"), "cloud.npz", "checksum", "re-run 'tergodic capture")


def test_stub_capture_json_is_refused_by_explore(tmp_path, small):
    side = json.loads((small / "capture.json").read_text())
    del side["sidecar_sha256"]
    (small / "capture.json").write_text(json.dumps(side))
    one_line_error(*run("explore", small, "--steps", "2", "--out", tmp_path / "run"), "capture.json", "re-run")
    assert not (tmp_path / "run").exists()


# ------------------------------------------------------------------------------- size guard

def test_size_guard_with_a_low_limit(tmp_path, small):
    code, out, err = run("capture", "--synthetic", "bowl", "--voxel", "0.008", "--max-points", "100", "--out", tmp_path / "c")
    assert code == 0
    warning = [ln for ln in err.splitlines() if ln.startswith("warning:")]
    assert len(warning) == 1 and "--voxel" in warning[0] and " MB and over " in warning[0] and "--max-points" in warning[0]
    n = json.loads((small / "capture.json").read_text())["counts"]["output"]
    one_line_error(*run("precompute", small, "--max-points", "100"), f"{n:,} points", "--max-points", "--voxel")


@pytest.mark.long
def test_size_guard_default_limit_on_a_large_cloud(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 0.2, (520_000, 3))
    np.savez(tmp_path / "big.npz", points=pts)
    code, out, err = run("capture", "--from", tmp_path / "big.npz", "--voxel", "0", "--target", "all", "--out", tmp_path / "big")
    assert code == 0, err
    assert "warning: 520,000 points" in err and "--voxel" in err
    one_line_error(*run("precompute", tmp_path / "big"), "520,000 points", "500,000", "GB", "--max-points 520000")


@pytest.mark.parametrize("member", ["colors", "points.txt"])
def test_npz_member_that_is_not_npy(tmp_path, good, cloud, member):
    """np.load hands such a member back as raw bytes (a traceback further on, today)."""
    import io
    import zipfile

    path = tmp_path / "odd.npz"
    buf = io.BytesIO()
    np.save(buf, cloud[0])
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("points.npy", buf.getvalue())
        z.writestr(member, b"1 2 3\n")
    bad_capture(good, "--from", path, needles=("odd.npz", f"member '{member}'", "not a .npy array"))


def test_negative_seed(good):
    bad_capture(good, "--synthetic", "bowl", "--seed", "-1", needles=("--seed", ">= 0", "-1"))


def test_an_input_inside_the_out_it_replaces_is_refused(tmp_path, good):
    """--from GOOD/cloud.ply --out GOOD --overwrite would replace the folder its own input is in."""
    bad_capture(good, "--from", good / "cloud.ply", needles=("cloud.ply", "is inside --out"))
