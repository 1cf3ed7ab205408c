"""Ctrl-C during the Laplacian (issue 27): robust_laplacian holds the GIL for the whole call, so it runs
in a child process that is killed when the parent is interrupted."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import default_signals, fibonacci_sphere

from tergodic_cli.basis import core

PARENT = """
import sys, numpy as np
from tergodic_cli.basis.core import compute_laplacian, CHILD_POINTS
from conftest import fibonacci_sphere
print("ready", flush=True)
try:
    compute_laplacian(fibonacci_sphere(CHILD_POINTS + 1000, 0.1), 30)
except KeyboardInterrupt:
    print("interrupted", flush=True)
    sys.exit(130)
print("finished", flush=True)
"""


def test_laplacian_in_a_child_equals_the_one_in_process(monkeypatch):
    pts = fibonacci_sphere(3000, 0.1)
    L_in, m_in = core.compute_laplacian(pts, 30)
    monkeypatch.setattr(core, "CHILD_POINTS", 100)
    L_child, m_child = core.compute_laplacian(pts, 30)
    assert (L_in != L_child).nnz == 0
    assert np.array_equal(m_in, m_child)


def test_a_failing_laplacian_child_is_one_line(monkeypatch):
    monkeypatch.setattr(core, "CHILD_POINTS", 10)
    pts = fibonacci_sphere(200, 0.1)
    pts[:, 2] = np.nan  # robust_laplacian rejects or fails on non-finite input: either way one TergodicError
    with pytest.raises(core.TergodicError):
        core.compute_laplacian(pts, 30, validate=False)


def _children(pid: int) -> list[int]:
    path = Path(f"/proc/{pid}/task/{pid}/children")
    return [int(c) for c in path.read_text().split()] if path.exists() else []


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return b""


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc")
def test_ctrl_c_is_answered_while_the_laplacian_child_works(tmp_path):
    """The child is frozen (SIGSTOP), so it can never finish: the parent still exits 130 on SIGINT,
    and the child is gone afterwards (killed, not left running)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-c", PARENT], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env, preexec_fn=default_signals)
    assert proc.stdout.readline().strip() == "ready"
    deadline, child = time.monotonic() + 600, None  # event-based: ends when the child appears
    while time.monotonic() < deadline and proc.poll() is None and child is None:
        # the child once it runs the Laplacian's module: frozen between fork and exec, it would hold the
        # parent inside subprocess.Popen (waiting for the exec), before the code that kills it on Ctrl-C
        kids = [k for k in _children(proc.pid) if b"_laplacian_child" in _cmdline(k)]
        child = kids[0] if kids else None
        time.sleep(0.02)
    assert child is not None, "no Laplacian child was started"
    os.kill(child, signal.SIGSTOP)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=300)  # a hang guard, not a timing assertion
    assert proc.returncode == 130, (proc.returncode, out, err)
    assert "interrupted" in out and "finished" not in out
    time.sleep(0.2)
    state = Path(f"/proc/{child}/stat")
    assert not state.exists() or state.read_text().split()[2] == "Z", "the child was left running"
