"""An overwrite is a swap, never a delete (issue 27): the earlier run stays whole, byte for byte,
whatever ends the new one (Ctrl-C, SIGTERM, a robot fault, an error), and the new run's partial
folder goes beside it, named in the message. Concurrent writers to one --out are refused by a lock.
Outputs that are not regular files, or that are the command's own input, are refused.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import assert_one_line_error, default_signals, run_cli
from test_bad_input_runs import Good, hashes, leftovers

REPO = Path(__file__).resolve().parents[1]
EXE = str(Path(sys.executable).with_name("tergodic"))
ENV = {**os.environ, "TERGODIC_NO_PROGRESS": "1"}


@pytest.fixture(scope="module")
def cap(tmp_path_factory) -> Path:
    cap = tmp_path_factory.mktemp("cap") / "cap"
    res = run_cli("capture", "--synthetic", "bowl", "--marking", "X", "--seed", "0", "--voxel", "0.008", "--out", cap)
    assert res.code == 0, res.err
    return cap


@pytest.fixture(scope="module")
def template(cap, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("template") / "run"
    assert run_cli("explore", cap, "--steps", "40", "--nk", "30", "--out", run).code == 0
    return run


@pytest.fixture
def good(template, tmp_path) -> Good:
    return Good(template, tmp_path)


def _beside(good: Good, kind: str) -> list[Path]:
    return sorted(good.path.parent.glob(f"{good.path.name}.{kind}-*"))


def _start_explore(cap: Path, out: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen([EXE, "explore", str(cap), "--steps", "2000000", "--nk", "30", "--log-cloud-every", "100000",
                             "--out", str(out), *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=ENV, preexec_fn=default_signals)


def _wait_for_log(proc: subprocess.Popen, parent: Path, name: str, size: int = 200_000) -> None:
    """Until the run's log (in its temporary sibling) holds steps."""
    deadline = time.monotonic() + 600  # event-based: a loaded machine takes long to start the loop
    while time.monotonic() < deadline and proc.poll() is None:
        logs = list(parent.glob(f".{name}.tmp-*/run.mcap"))
        if logs and logs[0].stat().st_size > size:
            return
        time.sleep(0.05)
    raise AssertionError(f"the run did not get going: {proc.poll()}")


def _finish(proc: subprocess.Popen, sig: int | None = None, timeout: float = 300) -> tuple[int, str, str]:
    try:
        if sig is not None:
            proc.send_signal(sig)
        out, err = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return proc.returncode, out, err


@pytest.mark.parametrize("sig, code, word", [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated")])
def test_an_interrupted_overwrite_keeps_the_earlier_run_whole(cap, good, sig, code, word):
    """Today's bug: the earlier complete run was destroyed, the folder left with the partial run.mcap."""
    proc = _start_explore(cap, good.path, "--overwrite", "--seed", "9")
    _wait_for_log(proc, good.path.parent, good.path.name)
    got, _, err = _finish(proc, sig)
    assert got == code, err
    assert hashes(good.path) == good.before  # byte for byte
    (beside,) = _beside(good, "interrupted")
    lines = [ln for ln in err.splitlines() if ln.startswith("tergodic:")]
    assert lines == [f"tergodic: {word}; {good.path}/ still holds the earlier run; this partial run is in "
                     f"{beside}/ (its log is marked interrupted)"], err
    assert leftovers(good.path.parent) == [] and not list(good.path.parent.glob(".*.lock"))
    res = run_cli("replay", beside, "--json")
    assert res.code == 0 and json.loads(res.out)["status"] == "interrupted", res.err
    assert json.loads(run_cli("replay", good.path, "--json").out)["status"] == "complete"


def test_an_interrupted_run_into_a_fresh_folder_is_put_in_place(cap, tmp_path):
    run = tmp_path / "run"
    proc = _start_explore(cap, run)
    _wait_for_log(proc, tmp_path, "run")
    got, _, err = _finish(proc, signal.SIGINT)
    assert got == 130, err
    assert f"the partial run is in {run}/" in err and (run / "run.mcap").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_a_robot_fault_does_not_replace_the_earlier_run(tmp_path):
    """Today's bug: a robot run that faults replaced the good run given to --overwrite."""
    bowl = REPO / "data" / "bowl"
    run = tmp_path / "run"
    assert run_cli("explore", bowl, "--steps", "30", "--nk", "60", "--out", run).code == 0
    before = hashes(run)
    res = run_cli("explore", bowl, "--robot", "pybullet", "--steps", "120", "--nk", "60", "--start=-0.02,0,0",
                  "--workspace", "0.15,-0.6,-0.01,0.50,0.6,0.9", "--no-log", "--overwrite", "--out", run)
    assert res.code == 3, res.err[-2000:]
    assert hashes(run) == before
    (beside,) = sorted(tmp_path.glob("run.partial-*"))
    line = [ln for ln in res.err.splitlines() if ln.startswith("robot stopped:")]
    assert len(line) == 1 and "workspace" in line[0] and f"this partial run is in {beside}/" in line[0], res.err
    summary = json.loads((beside / "summary.json").read_text())
    assert summary["final_state"] == "stopped" and "workspace" in summary["stop_reason"]


def test_an_error_during_an_overwrite_keeps_the_earlier_run(cap, good, monkeypatch):
    import tergodic_cli.run as run_mod

    def boom(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(run_mod.RunRecorder, "write", boom)
    assert_one_line_error(run_cli("explore", cap, "--steps", "20", "--nk", "30", "--overwrite", "--out", good.path),
                          "no space left on device")
    good.check()
    assert not list(good.path.parent.glob("good.*"))


# ------------------------------------------------------------------ concurrent writers
def test_a_second_writer_to_one_out_is_refused(cap, tmp_path):
    """Two explore processes into one fresh --out: today both printed 'wrote' and one replaced the other."""
    run = tmp_path / "run"
    first = _start_explore(cap, run)
    try:
        _wait_for_log(first, tmp_path, "run", size=1)
        second = subprocess.run([EXE, "explore", str(cap), "--steps", "20", "--nk", "30", "--out", str(run)],
                                capture_output=True, text=True, env=ENV, timeout=600)
        assert second.returncode == 2, second.stderr
        lines = second.stderr.strip().splitlines()
        assert len(lines) == 1 and "being written by another tergodic process" in lines[0], second.stderr
        assert first.poll() is None  # the first one goes on
    finally:
        got, _, err = _finish(first, signal.SIGINT)
    assert got == 130, err
    d = json.loads(run_cli("replay", run, "--json").out)
    assert d["status"] == "interrupted" and d["config"]["steps"] == 2000000  # the first run's, alone


def test_a_held_lock_refuses_overwrite_too_and_leaves_the_run(cap, good):
    from tergodic_cli.atomic import AtomicFolder

    holder = AtomicFolder(good.path, overwrite=True, what="run")
    holder.check()
    try:
        assert_one_line_error(run_cli("explore", cap, "--steps", "20", "--nk", "30", "--overwrite", "--out", good.path),
                              "being written by another tergodic process", "good.lock")
    finally:
        holder.release()
    good.check()
    assert not (good.path.parent / ".good.lock").exists()
    assert run_cli("explore", cap, "--steps", "20", "--nk", "30", "--overwrite", "--out", good.path).code == 0


# ------------------------------------------------------------------ outputs that are not regular files
def test_a_fifo_out_is_refused(cap, tmp_path):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    assert_one_line_error(run_cli("explore", cap, "--steps", "20", "--nk", "30", "--overwrite", "--out", fifo),
                          "is a FIFO, not a folder")
    assert fifo.is_fifo()


@pytest.mark.parametrize("option", ["--export-out", "--html"])
def test_replay_refuses_a_fifo_and_a_device_output(good, tmp_path, option):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    args = ("--export", "csv") if option == "--export-out" else ()
    assert_one_line_error(run_cli("replay", good.path, *args, option, fifo, "--overwrite"), "FIFO", option)
    assert fifo.is_fifo()
    assert_one_line_error(run_cli("replay", good.path, *args, option, "/dev/null", "--overwrite"), "device node")
    good.check()


def test_an_export_onto_the_runs_own_log_is_refused(good):
    """Today's bug: --export-out RUN/run.mcap destroyed the log."""
    for args in (("--export", "npz", "--export-out", good.path / "run.mcap"),
                 ("--html", good.path / "run.mcap"), ("--export", "csv", "--export-out", good.path / "." / "run.mcap")):
        assert_one_line_error(run_cli("replay", good.path, *args, "--overwrite"), "own input")
    link = good.path.parent / "link.csv"
    link.symlink_to(good.path / "run.mcap")
    assert_one_line_error(run_cli("replay", good.path, "--export", "csv", "--export-out", link, "--overwrite"),
                          "own input")
    link.unlink()
    good.check()


# ------------------------------------------------------------------ a killed run is found
def test_replay_of_a_killed_run_names_its_temporary_folder(cap, tmp_path):
    run = tmp_path / "run"
    proc = _start_explore(cap, run)
    _wait_for_log(proc, tmp_path, "run")
    got, _, _ = _finish(proc, signal.SIGKILL)
    assert got == -signal.SIGKILL and not run.exists()
    (tmp,) = tmp_path.glob(".run.tmp-*")
    res = run_cli("replay", run)
    assert_one_line_error(res, f"{run} does not exist", str(tmp), f"tergodic replay {tmp}", f"mv {tmp} {run}")
    res = run_cli("replay", tmp, "--json")  # the recovery it names works
    assert res.code == 0 and json.loads(res.out)["status"] == "truncated", res.err
    new = run_cli("explore", cap, "--steps", "20", "--nk", "30", "--out", run)  # a new run there says so too
    assert new.code == 0, new.err
    assert f"note: {tmp} is left from a run that was killed" in new.err
    assert tmp.exists()  # never removed for the user
