"""A run log cut anywhere reads as truncated, never as corrupt (a SIGKILL can stop the writer at any byte).

Unit tests on the bytes of a real log written by RunLog: cut at many seeded random offsets, and the
writer's own intermediate state of a chunk (header written with placeholder sizes, records streamed,
header filled in last) cut at every byte of that last write.
"""

from __future__ import annotations

import struct
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_runlog import demo_inputs, write_demo_log  # noqa: E402

from tergodic_cli.errors import TergodicError
from tergodic_cli.runlog import read_run_log

MAGIC = b"\x89MCAP0\r\n"


def _records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, length) of every top-level record after the leading magic."""
    out, at = [], len(MAGIC)
    while at + 9 <= len(data):
        op, length = data[at], struct.unpack_from("<Q", data, at + 1)[0]
        out.append((at, op, length))
        if op == 0x02:  # footer: then the closing magic
            break
        at += 9 + length
    return out


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """The bytes of a finished log and of one left open (as a killed run leaves it), 300 steps, 2 agents."""
    d = tmp_path_factory.mktemp("cuts")
    inp = demo_inputs(steps=300, robot=True)
    write_demo_log(d / "done.mcap", inp)
    open_log = write_demo_log(d / "open.mcap", inp, close=False)
    open_log.sync()
    data = {"done": (d / "done.mcap").read_bytes(), "open": (d / "open.mcap").read_bytes()}
    open_log.close()
    return data


def _verdict(path: Path) -> str:
    """'truncated', 'complete' or the error line."""
    try:
        return "truncated" if read_run_log(path, clouds=False).truncated else "complete"
    except TergodicError as exc:
        return str(exc)


def _first_step_end(data: bytes) -> int:
    """The end of the first chunk holding messages: cuts after it keep at least one step."""
    return next(at + 9 + length for at, op, length in _records(data) if op == 0x06)


@pytest.mark.parametrize("which", ["open", "done"])
def test_a_log_cut_at_random_offsets_reads_as_truncated(logs, tmp_path, which):
    data = logs[which]
    first = _first_step_end(data)
    rng = np.random.default_rng(27)
    cuts = sorted(set(rng.integers(first, len(data), 300).tolist()) | {first, len(data) - 1, len(data) - 9})
    early = sorted(set(rng.integers(len(MAGIC) + 1, first, 40).tolist()))
    path = tmp_path / "run.mcap"
    for off in cuts:
        path.write_bytes(data[:off])
        assert _verdict(path) == "truncated", (which, off, len(data))
    for off in early:  # before the first step: "cut", never "corrupt"
        path.write_bytes(data[:off])
        verdict = _verdict(path)
        assert "corrupt" not in verdict and ("cut" in verdict or "truncated" in verdict), (off, verdict)


def test_a_chunk_whose_header_was_being_filled_in_reads_as_truncated(logs, tmp_path):
    """The SDK's writer streams a chunk after a header with placeholder sizes (2^64 - 1) and fills
    the header in last; a SIGKILL inside that write (split at a page boundary) leaves any prefix of
    the real header over the placeholder one, and no message index after the chunk."""
    data = logs["open"]
    chunks = [(at, length) for at, op, length in _records(data) if op == 0x06]
    at, length = chunks[-1]
    end = at + 9 + length
    name_len = struct.unpack_from("<I", data, at + 37)[0]
    header_end = at + 41 + name_len + 8
    real = data[at:header_end]
    placeholder = bytearray(real)
    placeholder[1:9] = b"\xff" * 8  # the record length
    placeholder[9:25] = bytes(16)  # start and end time
    placeholder[25:37] = b"\xff" * 12  # uncompressed size and crc
    placeholder[-8:] = b"\xff" * 8  # compressed size
    path = tmp_path / "run.mcap"
    for k in range(len(real) + 1):  # k bytes of the real header written over the placeholder
        header = real[:k] + bytes(placeholder[k:])
        path.write_bytes(data[:at] + header + data[header_end:end])
        verdict = _verdict(path)
        assert verdict == "truncated", (k, verdict)
        if k == len(real):
            assert read_run_log(path, clouds=False).steps == 300  # the finished chunk is read


def test_damage_inside_a_finished_log_is_still_corrupt(logs, tmp_path):
    """The cut rules do not hide damage: a flipped byte in a chunk's data of a finished log."""
    data = bytearray(logs["done"])
    at, length = [(a, n) for a, op, n in _records(bytes(data)) if op == 0x06][1]
    data[at + 9 + length - 20] ^= 0xFF
    path = tmp_path / "run.mcap"
    path.write_bytes(bytes(data))
    assert "corrupt" in _verdict(path)
