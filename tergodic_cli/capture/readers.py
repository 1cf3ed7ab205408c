"""Readers for point-cloud files: PLY, PCD, XYZ/XYZRGB text and NPZ.

Every reader returns ``(points, colors)``: points float64 (n, 3) in the file's
units, colours float64 (n, 3) in [0, 1] or ``None`` when the file has none.

The readers are strict: a header/body count mismatch, a non-finite value, an
ambiguous or out-of-range colour depth and a wrong column count each raise a
one-line :class:`TergodicError` naming the file, the line (or field) and the fix.
PLY and PCD are parsed here with numpy, not by open3d, whose reader keeps the rows
before a bad one without failing and prints its own ``RPly:`` lines.
"""

from __future__ import annotations

import io
import re
from contextlib import suppress
from pathlib import Path

import numpy as np

from tergodic_cli.errors import TergodicError, require

SUPPORTED = (".ply", ".pcd", ".xyz", ".xyzrgb", ".txt", ".npz")

_FIX_EXPORT = "re-export the cloud"
_FIX_INVALID = "remove those rows, or pass --drop-invalid to drop them"
_FIX_PLY_COUNT = "fix the 'element vertex' count in the header or re-export the cloud"
_FIX_PCD_COUNT = "fix POINTS (and WIDTH) in the header or re-export the cloud"


#: The most a user's NPZ may unpack to: half the free memory (an NPZ is a zip; a few kilobytes can
#: claim gigabytes), never below 64 MB.
NPZ_MIN_CAP = 64 << 20


def npz_cap() -> int:
    """Bytes a user's NPZ may unpack to.

    Returns
    -------
    int
        Half the free memory, at least :data:`NPZ_MIN_CAP` (16 GB where the OS does not say).
    """
    from tergodic_cli.resources import free_memory

    free = free_memory()
    return 1 << 34 if free is None else max(NPZ_MIN_CAP, free // 2)


def check_npz_size(source, name: str, fix: str) -> None:
    """A one-line :class:`TergodicError`, before anything is unpacked, when the members of an NPZ
    declare more bytes than :func:`npz_cap`.

    The declared sizes bound what is unpacked: zipfile reads a member only up to its declared size.

    Parameters
    ----------
    source : path or binary file object
        The NPZ (a file object is rewound afterwards).
    name : str
        How the message names the file.
    fix : str
        The message's fix.

    Returns
    -------
    None
    """
    import zipfile

    try:
        with zipfile.ZipFile(source) as z:
            declared = sum(i.file_size for i in z.infolist())
    except (zipfile.BadZipFile, OSError, EOFError, ValueError):
        return  # np.load then names the damage
    finally:
        if hasattr(source, "seek"):
            source.seek(0)
    cap = npz_cap()
    require(declared <= cap, f"{name} unpacks to {declared / 1e9:.1f} GB, more than half the free memory "
            f"({2 * cap / 1e9:.1f} GB)", fix)


def read_cloud(path: str | Path, drop_invalid: bool = False,
               colour_depth: int | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a coloured point cloud from ``path`` (format from the extension).

    Parameters
    ----------
    path : str or Path
        .ply, .pcd, .xyz/.xyzrgb/.txt or .npz.
    drop_invalid : bool
        Keep rows with NaN/inf (the pipeline drops them) instead of refusing.
    colour_depth : int, optional
        8 or 16 bits per channel (checked by the pipeline) for integer colours whose depth the
        file does not say (text, NPZ); None reads 0..1 as floats, 0..255 as 8-bit and refuses more.

    Returns
    -------
    points : (n, 3) float64
        In the file's units.
    colors : (n, 3) float or None
        In [0, 1]; None for a colourless cloud.
    """
    path = Path(path)
    require(path.exists(), f"no such file: {path}", "check the path given to --from")
    require(path.is_file(), f"not a file: {path}", "give a PLY, PCD, XYZRGB or NPZ file to --from")
    suffix = path.suffix.lower()
    require(suffix in SUPPORTED, f"unknown point-cloud extension '{suffix}' for {path.name}",
            f"use a cloud ({', '.join(SUPPORTED)}) or a triangle mesh (.obj, .stl, .ply with faces, .glb, .gltf, .off)")
    try:
        blob = path.read_bytes()
    except OSError as exc:
        raise TergodicError(f"cannot read {path}: {(exc.strerror or str(exc)).lower()}", "check the file's permissions") from None
    require(len(blob) > 0, f"{path.name} is an empty file", "re-export the point cloud")
    reader = _Reader(path.name, blob, drop_invalid, colour_depth)
    read = {".ply": reader.ply, ".pcd": reader.pcd, ".npz": reader.npz}.get(suffix, reader.text)
    with np.errstate(all="ignore"):  # a garbage body's NaNs are reported as such, not as numpy warnings
        return read()


class _Reader:
    """One file's bytes and the options that decide what is an error."""

    def __init__(self, name: str, blob: bytes, drop_invalid: bool, colour_depth: int | None):
        self.name, self.blob = name, blob
        self.drop_invalid, self.colour_depth = drop_invalid, colour_depth

    def fail(self, where: str, problem: str, fix: str = _FIX_EXPORT):
        raise TergodicError(f"{self.name}{', ' + where if where else ''}: {problem}", fix)

    # ------------------------------------------------------------------------------- PLY
    def ply(self):
        if not self.blob.startswith(b"ply"):
            self.fail("", "not a valid PLY (no 'ply' header)", "re-export it as PLY")
        end = self.blob.find(b"end_header")
        if end < 0:
            self.fail("", "no PLY end_header line (corrupt or not a PLY?)", "re-export it as PLY")
        nl = self.blob.find(b"\n", end)
        body_start = len(self.blob) if nl < 0 else nl + 1
        header = self.blob[:end].decode("ascii", "replace").splitlines()
        fmt, elements = None, []  # [name, count, [(type, name) | ("list", ct, it, name)], header line]
        for lineno, line in enumerate(header, 1):
            parts = line.split()
            if not parts or parts[0] in ("ply", "comment", "obj_info"):
                continue
            if parts[0] == "format" and len(parts) >= 2:
                fmt = parts[1]
            elif parts[0] == "element" and len(parts) == 3:
                count = _int(parts[2])
                if count is None or count < 0:
                    self.fail(f"header line {lineno}", f"bad element count '{parts[2]}'")
                elements.append([parts[1], count, [], lineno])
            elif parts[0] == "property" and elements and len(parts) == 3 and parts[1] in _PLY_TYPES:
                elements[-1][2].append((parts[1], parts[2]))
            elif parts[0] == "property" and elements and len(parts) == 5 and parts[1] == "list" \
                    and parts[2] in _PLY_TYPES and parts[3] in _PLY_TYPES:
                elements[-1][2].append(("list", parts[2], parts[3], parts[4]))
            else:
                self.fail(f"header line {lineno}", f"cannot parse '{_printable(line.strip()[:60])}'")
        if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
            self.fail("header", f"unknown PLY format '{fmt}'", "re-export it as ascii or binary PLY")
        names = [e[0] for e in elements]
        if "vertex" not in names:
            self.fail("header", "no 'element vertex'", "re-export the cloud; PLY needs x, y, z vertex properties")
        vi = names.index("vertex")
        _, n, props, vline = elements[vi]
        pnames = [p[-1] for p in props]
        if any(p[0] == "list" for p in props):
            self.fail(f"header line {vline}", "list properties on vertices are not supported", "re-export xyz and colours only")
        if fmt == "ascii":  # one line per row: the vertices come after the earlier elements' rows
            skip = sum(count for _, count, _, _ in elements[:vi])
            first = len(header) + 2  # file line number of the body's first line (after end_header's)
            lines = self.blob[body_start:].decode("ascii", "replace").split("\n")
            rows = self._ascii_rows(lines, skip, n, first, f"{n} vertices", _FIX_PLY_COUNT,
                                    more_follow=len(elements) > vi + 1)
            table = self._parse_rows(rows, len(props), lambda i: first + skip + i)
            where = lambda i, j: f"line {first + skip + i} ('{props[j][1]}')"
        else:
            table, where = self._ply_binary(elements, vi, body_start, "<" if fmt.endswith("little_endian") else ">")
        return self._columns(table, pnames, [p[0] for p in props], where)

    def _ply_binary(self, elements, vi, body_start, endian):
        def row_dtype(props):
            return np.dtype([(f"f{j}", endian + _PLY_TYPES[p[0]]) for j, p in enumerate(props)])

        offset = body_start
        for name, count, props, line in elements[:vi]:
            if any(p[0] == "list" for p in props):
                self.fail(f"header line {line}", f"element '{name}' with list properties comes before the vertices",
                          "re-export with the vertices first")
            offset += count * row_dtype(props).itemsize
        _, n, props, _ = elements[vi]
        dtype = row_dtype(props)
        after = elements[vi + 1:]
        rest = None  # the rest's length is known when it has fixed-size rows only
        if not any(p[0] == "list" for e in after for p in e[2]):
            rest = sum(count * row_dtype(props).itemsize for _, count, props, _ in after)
        label = ("vertices", f"{n} vertices", "'element vertex'", _FIX_PLY_COUNT)
        table = _float_columns(self._records(offset, dtype, n, label, rest))
        return table, lambda i, j: f"vertex {i} ('{props[j][1]}')"

    # ------------------------------------------------------------------------------- PCD
    def pcd(self):
        head, pos, lineno = {}, 0, 0  # KEY -> its values (WIDTH, HEIGHT, POINTS: the number)
        while "DATA" not in head:
            nl = self.blob.find(b"\n", pos)
            if nl < 0:
                self.fail("header", "no DATA line (not a PCD, or truncated?)", "re-export it as PCD")
            line = self.blob[pos:nl].decode("ascii", "replace").strip()
            pos, lineno = nl + 1, lineno + 1
            if not line or line.startswith("#"):
                continue
            key, *vals = line.split()
            key = key.upper()
            if key in ("WIDTH", "HEIGHT", "POINTS"):
                value = _int(vals[0]) if len(vals) == 1 else None
                if value is None or value < 0:
                    self.fail(f"line {lineno}", f"bad {key} '{' '.join(vals)}'", "re-export it as PCD")
                vals = value
            elif key not in ("FIELDS", "SIZE", "TYPE", "COUNT", "DATA", "VERSION", "VIEWPOINT"):
                self.fail(f"line {lineno}", f"cannot parse the PCD header line '{_printable(line[:60])}'", "re-export it as PCD")
            head[key] = vals
        fields, data = head.get("FIELDS"), (head["DATA"] or [""])[0].lower()
        if not fields:
            self.fail("header", "no FIELDS line", "re-export it as PCD")
        width, height, points = (head.get(key) for key in ("WIDTH", "HEIGHT", "POINTS"))
        k = len(fields)
        size, counts = ([_int(v) for v in head[key]] if key in head else None for key in ("SIZE", "COUNT"))
        types = [v.upper() for v in head.get("TYPE", [])]
        counts = counts or [1] * k
        if size is None or len(size) != k or len(types) != k or len(counts) != k \
                or None in size or None in counts:
            self.fail("header", f"FIELDS, SIZE, TYPE and COUNT disagree ({k} fields)", "re-export it as PCD")
        if points is None:
            points = (width or 0) * (height or 1)
        if width is not None and width * (height or 1) != points:
            self.fail("header", f"WIDTH x HEIGHT = {width * (height or 1)} but POINTS = {points}",
                      _FIX_PCD_COUNT)
        names, kinds = [], []  # one column per scalar
        for f, s, t, c in zip(fields, size, types, counts):
            if (t, s) not in _PCD_AS_PLY:
                self.fail("header", f"field '{f}' has an unsupported TYPE {t} / SIZE {s}", "re-export it as PCD")
            for ci in range(c):
                names.append(f if c == 1 else f"{f}[{ci}]")
                kinds.append((t, s))
        packed = next((names.index(f) for f in ("rgb", "rgba") if f in names), None)  # its column
        if packed is not None and kinds[packed][1] != 4:
            self.fail("header", f"field '{names[packed]}' has SIZE {kinds[packed][1]}, expected 4 (packed 8-bit colour)",
                      "re-export it as PCD")
        bits = None  # packed colours: 0x00RRGGBB in a float's or uint32's bits (PCL's layout)
        if data == "ascii":
            lines = self.blob[pos:].decode("ascii", "replace").split("\n")
            first = lineno + 1
            rows = self._ascii_rows(lines, 0, points, first, f"POINTS {points}", _FIX_PCD_COUNT)
            table = self._parse_rows(rows, len(names), lambda i: first + i)
            if packed is not None:
                col = np.nan_to_num(table[:, packed], nan=0, posinf=0, neginf=0)
                bits = col.astype(np.float32).view(np.uint32) if kinds[packed][0] == "F" else col.astype(np.uint32)
            where = lambda i, j: f"line {first + i} ('{names[j]}')"
        elif data in ("binary", "binary_compressed"):
            dtype = np.dtype([(f"f{j}", f"<{t.lower()}{s}") for j, (t, s) in enumerate(kinds)])
            if data == "binary":
                label = ("points", f"POINTS {points}", "POINTS", _FIX_PCD_COUNT)
                rec = self._records(pos, dtype, points, label, 0)
            else:
                rec = self._pcd_compressed(pos, dtype, points)
            table = _float_columns(rec)
            if packed is not None:
                bits = rec[f"f{packed}"].view(np.uint32)
            where = lambda i, j: f"point {i} ('{names[j]}')"
        else:
            self.fail("header", f"unknown PCD DATA '{data}'", "re-export it as ascii or binary PCD")
        if bits is not None:  # three 8-bit columns
            table = np.column_stack([table, (bits >> 16) & 255, (bits >> 8) & 255, bits & 255])
            names, kinds = names + ["r", "g", "b"], kinds + [("U", 1)] * 3
        return self._columns(table, names, [_PCD_AS_PLY[k_] for k_ in kinds], where)

    def _pcd_compressed(self, pos, dtype, points):
        """PCL's binary_compressed: two uint32 sizes, then LZF of the fields stored one after another."""
        if len(self.blob) - pos < 8:
            self.fail("body", "truncated before the compressed block's sizes")
        csize, usize = (int(v) for v in np.frombuffer(self.blob, "<u4", 2, pos))
        if len(self.blob) - pos - 8 < csize:
            self.fail("body", f"truncated: the compressed block needs {csize} bytes, {len(self.blob) - pos - 8} are left")
        if usize != points * dtype.itemsize:
            self.fail("body", f"the compressed block holds {usize} bytes but POINTS {points} needs {points * dtype.itemsize}",
                      _FIX_PCD_COUNT)
        import lzf  # python-neo-lzf: liblzf, as PCL writes it

        try:
            raw = lzf.decompress(self.blob[pos + 8:pos + 8 + csize], usize)
        except ValueError:
            raw = None
        if raw is None or len(raw) != usize:
            self.fail("body", "the compressed block is corrupt")
        rec = np.empty(points, dtype=dtype)
        off = 0
        for name in dtype.names:
            fdt = dtype.fields[name][0]
            rec[name] = np.frombuffer(raw, fdt, points, off)
            off += points * fdt.itemsize
        return rec

    # ------------------------------------------------------------------------------ text
    def text(self):
        lines = self.blob.decode("utf-8-sig", "replace").split("\n")  # -sig: a BOM is not part of x
        data_lines, lineno = [], []
        for i, ln in enumerate(lines, 1):
            s = ln.split("#", 1)[0].split("//", 1)[0].strip()
            if s:
                data_lines.append(s)
                lineno.append(i)
        if not data_lines:
            self.fail("", "holds no points", "one point per line: x y z [r g b]")
        k = len(data_lines[0].replace(",", " ").split())
        if k not in (3, 6):
            self.fail(f"line {lineno[0]}", f"{k} columns", "use 3 (x y z) or 6 (x y z r g b) columns per line")
        table = self._parse_rows(data_lines, k, lambda i: lineno[i], "use 3 (x y z) or 6 (x y z r g b) columns on every line")
        return self._columns(table, ["x", "y", "z", "r", "g", "b"][:k], [None] * k,
                             lambda i, j: f"line {lineno[i]} (column {j + 1})")

    # ------------------------------------------------------------------------------- NPZ
    def npz(self):
        import zipfile

        blob = io.BytesIO(self.blob)
        check_npz_size(blob, self.name, "save a smaller cloud (or voxel it first) with np.savez(points=..., colors=...)")
        try:
            with np.load(blob, allow_pickle=False) as data:
                other = [n for n in data.zip.namelist() if not n.endswith(".npy")]  # np.load gives their raw bytes
                if other:
                    self.fail(f"member '{other[0]}'", "is not a .npy array", "save the cloud with np.savez(points=..., colors=...)")
                if "points" not in data.files:
                    self.fail("", "no 'points' array", "save the cloud with np.savez(points=..., colors=...)")
                points = data["points"]
                colors = data["colors"] if "colors" in data.files else None
        except (ValueError, OSError, EOFError, zipfile.BadZipFile, KeyError):  # corrupt zip, object arrays
            self.fail("", "not a readable NPZ (corrupt, or holding pickled objects)", "re-save it with np.savez (numbers only)")
        for field, arr in (("points", points), ("colors", colors)):
            if arr is not None and arr.dtype.kind not in "biuf":
                self.fail(f"field '{field}'", f"dtype {arr.dtype} is not numeric", "store numbers (float or int)")
        if points.ndim != 2 or points.shape[1] != 3:
            self.fail("field 'points'", f"shape {points.shape}, expected (n, 3)", "store points as an (n, 3) array")
        if colors is not None and (colors.ndim != 2 or colors.shape[1] != 3 or len(colors) != len(points)):
            self.fail("field 'colors'", f"shape {colors.shape} for {len(points)} points, expected ({len(points)}, 3)",
                      "give one RGB triple per point")
        table = points.astype(np.float64)
        names, types = ["x", "y", "z"], [None] * 3
        if colors is not None:
            table = np.column_stack([table, colors.astype(np.float64)])
            names += ["r", "g", "b"]
            types += ["uchar" if colors.dtype == np.uint8 else None] * 3  # uint16 may hold 8-bit values: ambiguous
        return self._columns(table, names, types,
                             lambda i, j: f"row {i} of '{'points' if j < 3 else 'colors'}'")

    # ---------------------------------------------------------------------------- common
    def _ascii_rows(self, lines, skip, n, first, declared, fix, more_follow=False):
        """The ``n`` text rows after ``skip`` lines; a blank line among them, or more rows than
        ``n`` with no other element to follow, fails naming the line (``first``: the body's)."""
        rows = lines[skip:skip + n]
        short = next((i for i, ln in enumerate(rows) if not ln.strip()), len(rows))
        got = sum(1 for ln in lines[skip:] if ln.strip())
        if short < n or (got > n and not more_follow):
            self.fail(f"line {first + skip + min(short, n)}",
                      f"the header declares {declared} but the body holds {got} rows", fix)
        return rows

    def _records(self, offset, dtype, n, label, rest):
        """``n`` binary records at ``offset``; fails when the body is too short or, with ``rest``
        (bytes of what follows) known, too long. ``label``: (unit, declared, count, fix), for
        the message."""
        unit, declared, count, fix = label
        need, have = n * dtype.itemsize, len(self.blob) - offset
        if have < need:
            self.fail("body", f"truncated: {len(self.blob)} of {offset + need} bytes; the header "
                      f"declares {declared} but only {max(have, 0) // dtype.itemsize} are complete")
        if rest is not None and have > need + rest:
            extra = have - need - rest
            self.fail("body", f"{extra} bytes after the {n} {unit} the header declares "
                      f"(room for {extra // dtype.itemsize} more: a wrong {count} count?)", fix)
        if rest is not None and have < need + rest:
            self.fail("body", f"truncated: {len(self.blob)} of {offset + need + rest} bytes")
        return np.frombuffer(self.blob, dtype=dtype, count=n, offset=offset)

    def _parse_rows(self, rows, k, line_of, fix="every row needs the columns the header declares"):
        """Rows of text into an (n, k) float table; a row with another column count fails naming its line."""
        with suppress(ValueError):  # fast path in C; on any doubt, the row-by-row scan below finds and names the bad line
            table = np.loadtxt(io.StringIO("\n".join(rows)), dtype=np.float64, ndmin=2, comments=None)
            if table.shape == (len(rows), k):
                return table
        split = [r.replace(",", " ").split() for r in rows]
        for i, toks in enumerate(split):
            if len(toks) != k:
                self.fail(f"line {line_of(i)}", f"{len(toks)} values where {k} were expected", fix)
        try:
            return np.array([t for toks in split for t in toks], dtype=np.float64).reshape(len(rows), k)
        except ValueError:
            for i, toks in enumerate(split):
                for j, tok in enumerate(toks):
                    try:
                        float(tok)
                    except ValueError:
                        self.fail(f"line {line_of(i)}", f"'{_printable(tok[:20])}' in column {j + 1} is not a number", _FIX_EXPORT)
            raise

    def _finite(self, table, where):
        bad = ~np.isfinite(table)
        if bad.any() and not self.drop_invalid:
            huge = ~bad & (np.abs(np.where(bad, 0, table)) > _ABSURD)
            if huge.any():  # NaNs among absurd magnitudes: a garbage body (wrong layout or byte order), not stray rows
                i, j = (int(v) for v in np.argwhere(huge)[0])
                self.fail(where(i, j), f"value {table[i, j]:.3g} beside {int(bad.sum())} NaN/inf values: the body looks corrupt",
                          "re-export the cloud (check its declared types and byte order)")
            i, j = (int(v) for v in np.argwhere(bad)[0])  # the first row with one, its first column
            rows = int(bad.any(axis=1).sum())
            self.fail(where(i, j), f"non-finite value {table[i, j]} ({rows} {'point' if rows == 1 else 'points'} with NaN or inf in all)", _FIX_INVALID)

    def _columns(self, table, names, types, where):
        """Pick x, y, z and the colour channels; check their finiteness and the colour depth.
        Other columns (normals, curvature, intensity) are not used, so their NaNs do not matter."""
        missing = [a for a in "xyz" if a not in names]
        if missing:
            self.fail("header", f"no '{missing[0]}' coordinate", "re-export the cloud with x, y, z")
        ix = [names.index(a) for a in "xyz"]
        ic = next(([names.index(c) for c in trio] for trio in
                   (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue"))
                   if all(c in names for c in trio)), [])
        used = ix + ic
        self._finite(table[:, used], lambda i, j: where(i, used[j]))
        points = np.ascontiguousarray(table[:, ix])
        if not ic:
            return points, None
        return points, self._colour(table[:, ic], [types[j] for j in ic], ic, where)

    def _colour(self, rgb, types, ic, where):
        """Colours in [0, 1]: by the declared type when it says, else by --colour-depth or the values."""
        finite = np.isfinite(rgb)
        vals = rgb[finite]
        if vals.size and vals.min() < 0:
            i, j = np.argwhere(finite & (rgb < 0))[0]
            self.fail(where(int(i), ic[j]), f"negative colour value {rgb[i, j]:g}", "colours are 0..255, 0..65535 or 0..1")
        declared = {"uchar": 8, "uint8": 8, "ushort": 16, "uint16": 16, "float": 0, "float32": 0, "double": 0, "float64": 0}
        # The file's type says it when it can (ushort is 16-bit, float is 0..1); else --colour-depth; else the values.
        depth = declared.get(types[0], self.colour_depth)
        hi = float(vals.max()) if vals.size else 0.0
        if depth is None:  # text, NPZ or an unusual PLY type: 0..1 or 8-bit by the values, above is refused
            depth = 0 if hi <= 1.0 else 8
        limit = {0: 1.0, 8: 255.0, 16: 65535.0}[depth]
        if hi > limit:
            i, j = np.argwhere(finite & (rgb > limit))[0]
            label = "0..1 (float type)" if depth == 0 else f"{depth}-bit"
            fix = ("pass --colour-depth 16 if the colours are 16-bit (0..65535)" if depth in (0, 8) and hi <= 65535
                   else "re-export the colours as 8-bit (0..255)")
            self.fail(where(int(i), ic[j]), f"colour value {rgb[i, j]:g} is above {limit:g}: out of range for "
                      f"{label} colour", fix)
        return rgb / limit


#: No coordinate (metres or millimetres) or colour channel comes near this: such values are garbage.
_ABSURD = 1e9

_PLY_TYPES = {"char": "i1", "uchar": "u1", "int8": "i1", "uint8": "u1", "short": "i2", "ushort": "u2",
              "int16": "i2", "uint16": "u2", "int": "i4", "uint": "u4", "int32": "i4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_PCD_AS_PLY = {("U", 1): "uchar", ("U", 2): "ushort", ("F", 4): "float", ("F", 8): "double",
               ("I", 1): "char", ("I", 2): "short", ("I", 4): "int", ("U", 4): "uint", ("I", 8): "int64", ("U", 8): "uint64"}


def _printable(text: str) -> str:
    """Quoted file content for a one-line message: control characters become '?'."""
    return "".join(ch if ch.isprintable() else "?" for ch in text)


def _float_columns(rec: np.ndarray) -> np.ndarray:
    """(n, k) float64 of a structured array's k scalar fields (numpy.lib.recfunctions imports numpy.ma: 60 ms)."""
    return np.column_stack([rec[name].astype(np.float64) for name in rec.dtype.names])


def _int(text: str) -> int | None:
    return int(text) if re.fullmatch(r"[+-]?\d+", text or "") else None


def write_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None) -> None:
    """Write a binary little-endian PLY (double xyz, uchar rgb), the reference clouds' layout.

    Written in place: :func:`~tergodic_cli.capture.artefact.save_capture` builds the whole
    folder aside.

    Parameters
    ----------
    path : str or Path
    points : (n, 3) float
        Metres.
    colors : (n, 3) float or None
        In [0, 1].
    """
    columns = {a: points[:, i].astype("<f8") for i, a in enumerate("xyz")}
    if colors is not None:
        rgb = np.clip(np.rint(colors * 255.0), 0, 255).astype(np.uint8)
        columns.update(red=rgb[:, 0], green=rgb[:, 1], blue=rgb[:, 2])
    rec = np.rec.fromarrays(list(columns.values()), names=list(columns))  # packed, in this order
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(points)}"]
    header += [f"property {'double' if c.dtype == '<f8' else 'uchar'} {n}" for n, c in columns.items()]
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\nend_header\n").encode("ascii"))
        fh.write(rec.tobytes())
