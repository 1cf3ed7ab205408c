"""Plain ``.npy`` files read and checksummed in one pass, never unpickled (the basis cache's arrays).

Light on purpose (numpy and hashlib only): the run log's writer process imports it to read Φ
from the cache without importing scipy.

The checksum is BLAKE2b over the array's dtype and shape, the wrapping 64-bit sums of each run
of 4096 words (the "rows"), the 4096 per-position sums across those runs (the "lanes"), and the
few trailing bytes. Any change inside one 8-byte word (a flipped bit or byte) changes its row's
sum, so it is always detected; two swapped words differ in their row or in their lane, so a swap
is detected too. It detects corruption and edits; it is not a cryptographic seal against a
deliberate forgery.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

#: Checksum geometry: 64-bit words per "row" (the lanes), rows read per chunk (512 KB).
_LANES = 4096
_CHUNK_ROWS = 16


class CacheMiss(Exception):
    """The entry is absent; the message says why when it was present but unusable."""


class _Checksum:
    """Incremental checksum of an array's bytes: feed whole rows of ``_LANES`` words, then the tail."""

    def __init__(self, dtype: np.dtype, shape: tuple, fortran: bool):
        self._hash = hashlib.blake2b(f"{np.dtype(dtype).str}{tuple(shape)}{bool(fortran)}".encode(), digest_size=16)
        self._lanes = np.zeros(_LANES, dtype=np.uint64)

    def rows(self, words: np.ndarray) -> None:
        """``words``: uint64, a whole number of rows."""
        block = words.reshape(-1, _LANES)
        self._hash.update(block.sum(axis=1, dtype=np.uint64).tobytes())  # sums wrap modulo 2**64
        self._lanes += block.sum(axis=0, dtype=np.uint64)

    def finish(self, tail: bytes | memoryview) -> str:
        self._hash.update(tail)
        self._hash.update(self._lanes.tobytes())
        return self._hash.hexdigest()


def _body_bytes(nbytes: int) -> int:
    """Bytes covered by whole rows of the checksum; the rest is the tail."""
    return nbytes // (8 * _LANES) * (8 * _LANES)


def array_checksum(a: np.ndarray) -> str:
    """Checksum (32 hex digits) of an array as :func:`np.save` writes it (C order)."""
    a = np.require(a, requirements="C")  # (ascontiguousarray would turn 0-d into 1-d)
    raw = memoryview(a).cast("B") if a.nbytes else memoryview(b"")
    body = _body_bytes(a.nbytes)
    c = _Checksum(a.dtype, a.shape, False)
    if body:
        c.rows(np.frombuffer(raw[:body], dtype=np.uint64))
    return c.finish(raw[body:])


def read_checked(path: Path, expected: str | None) -> np.ndarray:
    """Read a ``.npy`` file and check its checksum in the same pass; never unpickles.

    Raises
    ------
    CacheMiss
        unreadable, truncated, an object dtype, or a checksum mismatch.
    """
    fmt = np.lib.format
    try:
        with open(path, "rb", buffering=0) as f:
            version = fmt.read_magic(f)
            if version == (1, 0):
                shape, fortran, dtype = fmt.read_array_header_1_0(f)
            elif version in ((2, 0), (3, 0)):
                shape, fortran, dtype = fmt.read_array_header_2_0(f)
            else:
                raise ValueError(f"npy version {version}")
            if dtype.hasobject:
                raise ValueError("object arrays are never loaded (they would need unpickling)")
            out = np.empty(int(np.prod(shape, dtype=np.int64)) * dtype.itemsize, dtype=np.uint8)
            raw = memoryview(out)
            body = _body_bytes(out.nbytes)
            c = _Checksum(dtype, shape, fortran)
            step = 8 * _LANES * _CHUNK_ROWS
            for pos in range(0, body, step):
                end = min(body, pos + step)
                _read_exactly(f, raw[pos:end])
                c.rows(out[pos:end].view(np.uint64))  # while the chunk is still in the CPU cache
            _read_exactly(f, raw[body:])
            digest = c.finish(raw[body:])
    except (OSError, ValueError, EOFError, TypeError) as exc:
        raise CacheMiss(f"unreadable ({type(exc).__name__})") from None
    if digest != expected:
        raise CacheMiss("checksum mismatch (corrupt or modified)")
    a = out.view(dtype)
    return a.reshape(shape[::-1]).T if fortran else a.reshape(shape)


def read_checked_array(path: str | Path, checksum: str) -> np.ndarray:
    """An array of a cache entry (``basis.meta["evecs_file"]``), read and checked against its checksum.

    Raises
    ------
    CacheMiss
        unreadable, truncated, or modified since the entry was written.
    """
    return read_checked(Path(path), checksum)


def _read_exactly(f, view: memoryview) -> None:
    pos = 0
    while pos < len(view):
        got = f.readinto(view[pos:])
        if not got:
            raise ValueError("truncated file")
        pos += got
