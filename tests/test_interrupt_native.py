"""Ctrl-C during the Laplacian (issue 27): robust_laplacian holds the GIL for the whole call, so it runs
in a child process that is killed when the parent is interrupted."""

from __future__ import annotations

import os
import shutil
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


# --------------------------------------------------------------------------------------------------
# tergodic_cli.native: a GIL-releasing call in a thread (qdldl's factorisation), a GIL-holding one in a fork


FACTOR = """
import sys, threading, numpy as np, scipy.sparse as sp
from tergodic_cli.basis.eigensolvers import SymmetricFactor
g = {g}
T = sp.diags([-np.ones(g - 1), 2 * np.ones(g), -np.ones(g - 1)], [-1, 0, 1])
K = (sp.kronsum(T, T) + 1e-3 * sp.identity(g * g)).tocsc()  # a 2-D grid's Laplacian, shifted: SPD
def busy():
    return any(t.name.startswith("tergodic-native") and t.is_alive() for t in threading.enumerate())
def announce():  # "factorising" once the factorisation runs in its worker
    while not busy():
        threading.Event().wait(0.005)
    print("factorising", flush=True)
threading.Thread(target=announce, daemon=True).start()
try:
    while True:
        SymmetricFactor(K, check_accuracy=False)
except KeyboardInterrupt:
    print("interrupted", "while-factorising" if busy() else "after-factorising", flush=True)
    sys.exit(130)
"""


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_is_answered_while_qdldl_factorises(tmp_path, sig):
    """qdldl releases the GIL, so the factorisation runs in a worker thread and the main thread answers
    SIGINT/SIGTERM at once: the handler runs while the factorisation (1-4 s at 160k unknowns) still works.
    In the main thread it would run only after the factorisation returned."""
    prog = FACTOR.format(g=400)
    if sig == signal.SIGTERM:  # as the CLI does: SIGTERM raised as a KeyboardInterrupt where the program is
        prog = prog.replace("try:\n", "import signal\nfrom tergodic_cli.cli import _on_sigterm\n"
                                      "signal.signal(signal.SIGTERM, _on_sigterm)\ntry:\n", 1)
    proc = subprocess.Popen([sys.executable, "-c", prog], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=default_signals, env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    try:
        assert proc.stdout.readline().strip() == "factorising", proc.stderr.read()
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, (proc.returncode, out, err)
    assert out.strip() == "interrupted while-factorising", (out, err)


def test_in_fork_returns_the_arrays_and_errors_of_the_child():
    from tergodic_cli.errors import TergodicError
    from tergodic_cli.native import in_fork
    from tergodic_cli.robot.surface import FORK_POINTS, _oriented_normals, oriented_normals

    pts = fibonacci_sphere(FORK_POINTS + 10, 0.1)
    here = _oriented_normals(pts, "outward", 20)
    there = oriented_normals(pts, "outward")  # in a fork
    assert there.dtype == here.dtype and np.array_equal(there, here)
    assert np.all(np.einsum("ij,ij->i", there, pts) > 0)  # outward on a sphere: an independent check

    def refuse():
        raise TergodicError("the problem", "the fix")

    with pytest.raises(TergodicError) as exc:
        in_fork(refuse, "a test")
    assert (exc.value.problem, exc.value.fix) == ("the problem", "the fix")

    def die():
        os.kill(os.getpid(), signal.SIGKILL)  # as the kernel's out-of-memory killer would
        return {}

    with pytest.raises(TergodicError, match="a test failed in its process .killed by signal 9"):
        in_fork(die, "a test")

    def strings():
        return {"method": np.array("poisson"), "n": np.arange(3)}

    got = in_fork(strings, "a test")
    assert str(got["method"]) == "poisson" and got["n"].tolist() == [0, 1, 2]


def _forks(pid: int) -> list[int]:
    """The children of ``pid`` that are forks of it (the same command line)."""
    out = []
    try:
        mine = Path(f"/proc/{pid}/cmdline").read_bytes()
        for c in _children(pid):
            if Path(f"/proc/{c}/cmdline").read_bytes() == mine:
                out.append(c)
    except OSError:
        pass
    return out


@pytest.fixture(scope="module")
def dense_dome(tmp_path_factory):
    """A 20k-point dome (h 1.6 mm, 8 cm radius) captured and precomputed, and a complete earlier run in OUT."""
    root = tmp_path_factory.mktemp("dome")
    pts = fibonacci_sphere(26000, 0.08)
    pts = pts[pts[:, 2] > -0.3 * 0.08]
    colors = np.full((len(pts), 3), 200, np.uint8)
    colors[pts[:, 2] > 0.048] = (220, 20, 20)
    np.savez(root / "dome.npz", points=pts, colors=colors)
    env = {**os.environ, "TERGODIC_CACHE_DIR": str(root / "cache"), "TERGODIC_NO_PROGRESS": "1",
           "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "TMPDIR": str(root)}
    exe = str(Path(sys.executable).with_name("tergodic"))
    for args in (["capture", "--from", root / "dome.npz", "--voxel", "0", "--target", "red", "--out", root / "cap"],
                 ["precompute", root / "cap"],
                 ["explore", root / "cap", "--steps", "5", "--out", root / "out"]):
        res = subprocess.run([exe, *map(str, args)], capture_output=True, text=True, env=env, timeout=600)
        assert res.returncode == 0, res.stderr
    return root, env, exe


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc")
@pytest.mark.parametrize("sig, nth, code", [(signal.SIGTERM, 1, 143), (signal.SIGINT, 2, 130)],
                         ids=["SIGTERM-normals", "SIGINT-surface"])
def test_robot_setup_answers_a_signal_inside_open3d(dense_dome, sig, nth, code):
    """``explore --robot pybullet --overwrite`` on a dense cloud without a mesh: the signal lands while a forked
    child runs open3d (the 1st fork: the normals; the 2nd: the Poisson surface). The run exits with 130/143
    well before open3d would have finished, the child is gone, the earlier run is intact byte for byte, the
    partial run goes beside it (named in the message, no summary), and no temporary folder is left."""
    root, env, exe = dense_dome
    before = {p.name: p.read_bytes() for p in (root / "out").iterdir()}
    proc = subprocess.Popen([exe, "explore", str(root / "cap"), "--robot", "pybullet", "--steps", "20", "--overwrite",
                             "--out", str(root / "out")], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env, preexec_fn=default_signals)
    try:
        seen, child, deadline = [], None, time.monotonic() + 300
        while time.monotonic() < deadline and proc.poll() is None and child is None:
            for c in _forks(proc.pid):
                if c not in seen:
                    seen.append(c)
            child = seen[nth - 1] if len(seen) >= nth and seen[nth - 1] in _children(proc.pid) else None
            time.sleep(0.005)
        assert child is not None, f"no fork #{nth} was seen ({seen})"
        time.sleep(0.3)
        assert child in _children(proc.pid), "the fork ended before the signal: too little work to test"
        t0 = time.monotonic()
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=60)
        answered = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == code, (proc.returncode, out, err)
    assert answered < 10.0, answered  # generous on a loaded machine; docs/speed.md has the measured times
    assert "Traceback" not in err
    state = Path(f"/proc/{child}/stat")
    assert not state.exists() or state.read_text().split()[2] == "Z", "the fork was left running"
    assert {p.name: p.read_bytes() for p in (root / "out").iterdir()} == before
    partial = sorted(root.glob("out.interrupted-*"))
    assert len(partial) <= 1 and not list(root.glob(".out.tmp-*"))
    for p in partial:  # interrupted before its first step: a log without steps, never a summary
        assert "summary.json" not in {q.name for q in p.iterdir()} and p.name in out + err, (out, err)
        shutil.rmtree(p)
    assert not list(root.glob("tergodic-native-*"))
