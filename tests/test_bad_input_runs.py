"""Bad input and faults for ``explore``, ``replay`` and ``sweep`` (issue 16), through the real CLI.

Each case asserts the exit code, one line naming the problem (no traceback, no library lines),
and that a good run folder made earlier is byte-identical afterwards (every file hashed before
and after) with no temporary sibling left behind.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import assert_one_line_error, default_signals, run_cli

STEPS = "60"


def hashes(folder: Path) -> dict[str, str]:
    """sha256 of every file under ``folder`` (hidden ones too), by relative path."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def leftovers(parent: Path) -> list[str]:
    return [p.name for p in parent.iterdir() if ".tmp-" in p.name or ".old-" in p.name]


@pytest.fixture(scope="module")
def cap(tmp_path_factory) -> Path:
    cap = tmp_path_factory.mktemp("cap") / "cap"
    res = run_cli("capture", "--synthetic", "bowl", "--marking", "X", "--seed", "0", "--voxel", "0.008", "--out", cap)
    assert res.code == 0, res.err
    return cap


@pytest.fixture(scope="module")
def template(cap, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("template") / "run"
    res = run_cli("explore", cap, "--steps", STEPS, "--nk", "30", "--out", run)
    assert res.code == 0, res.err
    assert sorted(p.name for p in run.iterdir()) == ["config.json", "run.mcap", "summary.json", "trajectory.npz"]
    return run


class Good:
    """A copy of a good run, with its hashes; ``check()`` asserts it is unchanged and alone."""

    def __init__(self, template: Path, tmp_path: Path):
        self.path = tmp_path / "good"
        shutil.copytree(template, self.path)
        self.before = hashes(self.path)

    def check(self) -> None:
        assert hashes(self.path) == self.before
        assert leftovers(self.path.parent) == []


@pytest.fixture
def good(template, tmp_path) -> Good:
    return Good(template, tmp_path)


def explore(cap, out, *args):
    return run_cli("explore", cap, "--steps", STEPS, "--nk", "30", "--out", out, *args)


# ------------------------------------------------------------------ explore: refused before writing
REJECTED = [
    (("--robot", "pybullet", "--force", "500"), "--force"),
    (("--robot", "pybullet", "--force", "0"), "--force must be > 0"),
    (("--robot", "pybullet", "--force", "-3"), "--force must be > 0"),
    (("--robot", "pybullet", "--force", "nan"), "--force"),
    (("--robot", "pybullet", "--contact-force", "10"), "contact threshold"),
    (("--robot", "pybullet", "--force-limit", "1"), "force limit"),
    (("--robot", "pybullet", "--gains", "stiff"), "--gains"),
    (("--robot", "pybullet", "--explore-dt", "0.0005"), "whole number"),
    (("--robot", "pybullet", "--object-pose", "2.5,0,0"), "reach"),
    (("--robot", "pybullet", "--object-pose", "0,0,0"), "overlaps the robot's base"),
    (("--robot", "pybullet", "--object-pose", "1,2"), "--object-pose"),
    (("--robot", "pybullet", "--workspace", "0,0,0,0.1,0.1,0.1"), "workspace box"),
    (("--robot", "pybullet", "--workspace", "1,0,0,0.1,0.1,0.1"), "workspace box"),
    (("--robot", "pybullet", "--recapture-every", "0"), "--recapture-every"),
    (("--robot", "pybullet", "--until-clean", "1.5"), "--until-clean"),
    (("--robot", "warp"), "--robot"),
    (("--steps", "0"), "--steps"),
    (("--log-cloud-every", "0"), "--log-cloud-every"),
    (("--start", "a,b,c"), "--start"),
    (("--nk", "100000"), "--nk"),
    (("--robot", "pybullet", "--agents", "3"), "--agents 3 with --robot pybullet"),  # issue 27: drove into contact first
    (("--seed", "-1"), "--seed must be a whole number >= 0"),
]


@pytest.mark.parametrize("args, needle", REJECTED, ids=[" ".join(a) for a, _ in REJECTED])
def test_rejected_option_into_an_existing_run_leaves_it_whole(cap, good, args, needle):
    """Today's bug: --robot pybullet --force 500 replaced a good run.mcap with an empty one."""
    assert_one_line_error(explore(cap, good.path, "--overwrite", *args), needle)
    good.check()


def test_gui_without_a_display_is_refused_before_pybullet(cap, good, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    res = explore(cap, good.path, "--overwrite", "--robot", "pybullet", "--gui")
    assert_one_line_error(res, "no display", "--gui")
    assert "pybullet build time" not in res.out + res.err
    good.check()


def test_gui_with_a_display_that_names_no_x_server_is_refused(cap, good, monkeypatch):
    """Issue 27: PyBullet ended the whole process when DISPLAY named no reachable X server."""
    monkeypatch.setenv("DISPLAY", ":987")
    res = explore(cap, good.path, "--overwrite", "--robot", "pybullet", "--gui")
    assert_one_line_error(res, "DISPLAY=:987 names no X server that answers")
    good.check()


def test_a_listening_x_socket_counts_as_a_display(tmp_path):
    import socket

    from tergodic_cli.runlog.viewers import x_server_answers

    sock_path = tmp_path / "X0"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as srv:
        srv.bind(str(sock_path))
        srv.listen(1)
        assert x_server_answers(f"{sock_path}:0")
    assert not x_server_answers(f"{sock_path}:0")  # closed: nothing answers
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as srv:  # Linux's abstract X socket
        srv.bind("\0/tmp/.X11-unix/X4321")
        srv.listen(1)
        assert x_server_answers(":4321.0")
    assert not x_server_answers("not a display")


def test_existing_run_needs_overwrite(cap, good):
    assert_one_line_error(explore(cap, good.path), "already holds a run", "--overwrite")
    good.check()


def test_no_log_into_an_existing_run_needs_overwrite(cap, good):
    assert_one_line_error(explore(cap, good.path, "--no-log"), "already holds a run", "--overwrite")
    good.check()


def test_overwrite_with_no_log_replaces_the_run_whole(cap, good):
    (good.path / "plots").mkdir()
    (good.path / "plots" / "old.png").write_bytes(b"old")
    res = explore(cap, good.path, "--no-log", "--overwrite", "--seed", "5")
    assert res.code == 0, res.err
    assert sorted(p.name for p in good.path.iterdir()) == ["config.json", "summary.json", "trajectory.npz"]  # no old run.mcap
    assert json.loads((good.path / "summary.json").read_text())["config"]["seed"] == 5
    assert leftovers(good.path.parent) == []


def test_overwrite_replaces_the_run_whole(cap, good):
    (good.path / "series.csv").write_text("step,t\n1,1.0\n")  # the old run's export: replaced with it
    res = explore(cap, good.path, "--overwrite", "--seed", "7")
    assert res.code == 0, res.err
    assert sorted(p.name for p in good.path.iterdir()) == ["config.json", "run.mcap", "summary.json", "trajectory.npz"]
    assert hashes(good.path)["run.mcap"] != good.before["run.mcap"]
    assert run_cli("replay", good.path).code == 0


def test_overwrite_refuses_a_folder_that_is_not_a_run(cap, good):
    (good.path / "notes.txt").write_text("mine")
    good.before = hashes(good.path)
    assert_one_line_error(explore(cap, good.path, "--overwrite"), "not a run's", "notes.txt")
    good.check()


def test_replay_overwrite_refuses_a_folder_that_is_not_plots(good, tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("mine")
    assert_one_line_error(run_cli("replay", good.path, "--plot", mine, "--overwrite"), "thesis.tex")
    assert (mine / "thesis.tex").read_text() == "mine"
    good.check()


def test_out_is_a_file(cap, good):
    assert_one_line_error(explore(cap, good.path / "summary.json"), "is a file, not a folder")
    good.check()


def test_out_under_a_file(cap, good):
    assert_one_line_error(explore(cap, good.path / "summary.json" / "run"), "is a file, not a folder")
    good.check()


def test_out_is_the_current_folder(cap, good, monkeypatch):
    monkeypatch.chdir(good.path)
    assert_one_line_error(explore(cap, ".", "--overwrite"), "current folder")
    good.check()


@contextlib.contextmanager
def mounted(tmp_path: Path, *options: str, source: str = "tmpfs", kind: str | None = "tmpfs"):
    """A real filesystem at tmp_path/mnt; skip (with the reason) where mounting is not permitted."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    cmd = ["mount"] + (["-t", kind] if kind else []) + [*options, source, str(mnt)]
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as exc:
        pytest.skip(f"cannot mount ({exc})")
    if done.returncode != 0:
        pytest.skip(f"mount is not permitted here: {done.stderr.strip()[:120]}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True, timeout=30)


def test_read_only_parent(cap, good, tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    with mounted(tmp_path, "--bind", source=str(src), kind=None) as mnt:
        ro = subprocess.run(["mount", "-o", "remount,ro,bind", str(mnt)], capture_output=True, text=True)
        if ro.returncode != 0:
            pytest.skip(f"cannot remount read-only: {ro.stderr.strip()[:120]}")
        assert_one_line_error(explore(cap, mnt / "run"), "read-only filesystem", "--out")
        assert list(mnt.iterdir()) == []
    good.check()


def test_full_disk_new_run(cap, good, tmp_path):
    with mounted(tmp_path, "-o", "size=300k") as mnt:
        assert_one_line_error(explore(cap, mnt / "run", "--steps", "3000"), "no space left on device", "free space")
        assert list(mnt.iterdir()) == []  # nothing partial
    good.check()


def test_full_disk_keeps_the_old_run(cap, good, tmp_path):
    with mounted(tmp_path, "-o", "size=400k") as mnt:
        old = mnt / "run"
        assert explore(cap, old, "--no-log").code == 0
        before = hashes(old)
        assert_one_line_error(explore(cap, old, "--overwrite", "--steps", "3000"), "no space left on device")
        assert hashes(old) == before
        assert leftovers(mnt) == []
    good.check()


# ------------------------------------------------------------------ explore: interrupted
def _interrupt(cap: Path, run: Path, sig: int) -> subprocess.CompletedProcess:
    exe = str(Path(sys.executable).with_name("tergodic"))
    proc = subprocess.Popen([exe, "explore", str(cap), "--steps", "2000000", "--nk", "30", "--log-cloud-every", "100000",
                             "--out", str(run)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "TERGODIC_NO_PROGRESS": "1"}, preexec_fn=default_signals)
    try:
        deadline = time.monotonic() + 600  # event-based: a loaded machine takes long to start the loop
        while time.monotonic() < deadline and proc.poll() is None:  # until the log has steps in it
            logs = list(run.parent.glob(f".{run.name}.tmp-*/run.mcap"))
            if logs and logs[0].stat().st_size > 200_000:
                break
            time.sleep(0.05)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=300)  # a hang guard, not a timing assertion
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


@pytest.mark.parametrize("sig, code, word", [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated")])
def test_interrupted_run_keeps_what_it_has(cap, good, tmp_path, sig, code, word):
    run = tmp_path / "run"
    done = _interrupt(cap, run, sig)
    assert done.returncode == code, done.stderr
    lines = [ln for ln in done.stderr.splitlines() if ln.startswith("tergodic:")]
    assert lines == [f"tergodic: {word}; the partial run is in {run}/ (its log is marked interrupted)"], done.stderr
    assert "Traceback" not in done.stderr
    assert (run / "run.mcap").exists() and leftovers(tmp_path) == []
    res = run_cli("replay", run, "--json")
    assert res.code == 0, res.err
    out = json.loads(res.out)
    assert out["status"] == "interrupted" and out["truncated"] is False and out["steps"] > 0
    assert "interrupted run" in res.err
    good.check()


# ------------------------------------------------------------------ replay: damaged logs
def _damaged(good: Good, tmp_path: Path, how: str) -> Path:
    data = (good.path / "run.mcap").read_bytes()
    if how == "truncated":
        data = data[: int(len(data) * 0.6)]
    elif how == "corrupt":
        b = bytearray(data)
        b[len(b) // 2] ^= 0xFF
        data = bytes(b)
    elif how == "appended":
        data = data + b"not part of the log\n"
    path = tmp_path / f"{how}.mcap"
    path.write_bytes(data)
    return path


def test_replay_truncated_log(good, tmp_path):
    res = run_cli("replay", _damaged(good, tmp_path, "truncated"), "--json")
    assert res.code == 0, res.err
    assert json.loads(res.out)["status"] == "truncated"
    assert "truncated" in res.err and "Traceback" not in res.err
    good.check()


def test_replay_corrupt_log_names_the_offset(good, tmp_path):
    assert_one_line_error(run_cli("replay", _damaged(good, tmp_path, "corrupt")), "corrupt at byte")
    good.check()


def test_replay_garbage_appended_is_reported(good, tmp_path):
    path = _damaged(good, tmp_path, "appended")
    size = (good.path / "run.mcap").stat().st_size
    assert_one_line_error(run_cli("replay", path), "garbage after the end", f"from byte {size}")
    good.check()


def test_replay_complete_log_says_complete(good):
    res = run_cli("replay", good.path, "--json")
    assert res.code == 0 and json.loads(res.out)["status"] == "complete" and res.err.strip() == ""
    good.check()


# ------------------------------------------------------------------ replay: outputs
def test_replay_plot_into_a_file(good):
    assert_one_line_error(run_cli("replay", good.path, "--plot", good.path / "summary.json"), "is a file, not a folder")
    good.check()


def test_replay_plot_under_a_file(good):
    assert_one_line_error(run_cli("replay", good.path, "--plot", good.path / "summary.json" / "plots"),
                          "is a file, not a folder")
    good.check()


def test_replay_existing_plots_need_overwrite_then_are_replaced_whole(good, tmp_path):
    plots = tmp_path / "plots"
    assert run_cli("replay", good.path, "--plot", plots).code == 0
    (plots / "old.png").write_bytes(b"a plot an older version drew")
    before = hashes(plots)
    assert_one_line_error(run_cli("replay", good.path, "--plot", plots), "--plot", "--overwrite")
    assert hashes(plots) == before
    res = run_cli("replay", good.path, "--plot", plots, "--overwrite")
    assert res.code == 0, res.err
    assert not (plots / "old.png").exists() and (plots / "ergodicity.png").exists()
    assert leftovers(tmp_path) == []
    good.check()


def test_replay_existing_export_needs_overwrite(good, tmp_path):
    dest = tmp_path / "series.csv"
    assert run_cli("replay", good.path, "--export", "csv", "--export-out", dest).code == 0
    before = dest.read_bytes()
    assert_one_line_error(run_cli("replay", good.path, "--export", "csv", "--export-out", dest), "already exists",
                          "--overwrite")
    assert dest.read_bytes() == before
    good.check()


def test_replay_export_under_a_file(good):
    assert_one_line_error(run_cli("replay", good.path, "--export", "npz", "--export-out",
                                  good.path / "summary.json" / "s.npz"), "is a file, not a folder")
    good.check()


# ------------------------------------------------------------------ sweep: resume verifies
GRID = """
steps = 20
seed = 1

[objects.bowl]
synthetic = "bowl"
marking = "X"
voxel = 0.008
agent_radius = 0.012

[grid]
start = 1
nk = [20]
alpha = [5, 10]
"""


@pytest.fixture
def swept(tmp_path):
    grid = tmp_path / "grid.toml"
    grid.write_text(GRID)
    out = tmp_path / "sweep"
    res = run_cli("sweep", grid, "--out", out, "--jobs", "1", "--no-plots")
    assert res.code == 0, res.err
    return grid, out


def _damage_record(path: Path, how: str) -> None:
    if how == "not json":
        path.write_text('{"run_id": "abc", "summ')
    elif how == "missing key":
        rec = json.loads(path.read_text())
        del rec["summary"]["ergodicity"]
        path.write_text(json.dumps(rec))
    elif how == "edited value":
        rec = json.loads(path.read_text())
        rec["summary"]["ergodicity"] = 0.001
        path.write_text(json.dumps(rec))
    elif how == "series changed":
        npz = path.with_suffix(".npz")
        npz.write_bytes(npz.read_bytes()[:-10])
    elif how == "series missing":
        path.with_suffix(".npz").unlink()


@pytest.mark.parametrize("how", ["not json", "missing key", "edited value", "series changed", "series missing"])
def test_sweep_resume_reruns_a_bad_finished_record(swept, good, how):
    grid, out = swept
    table = (out / "results.csv").read_text()
    victim = sorted((out / "runs").glob("*.json"))[0]
    _damage_record(victim, how)
    res = run_cli("sweep", grid, "--out", out, "--jobs", "1", "--no-plots")
    assert res.code == 0, res.err
    assert "Traceback" not in res.err
    said = [ln for ln in res.err.splitlines() if "do not verify" in ln]
    assert len(said) == 1 and victim.stem in said[0] and "running them again" in said[0], res.err
    assert "(1 computed, 1 already done, 0 failed)" in res.out
    rec = json.loads(victim.read_text())
    assert rec["summary"]["ergodicity"] != 0.001
    assert (out / "results.csv").read_text().splitlines()[1:] and len(table.splitlines()) == len(
        (out / "results.csv").read_text().splitlines())
    assert leftovers(out) == [] and not list(out.glob(".results.tmp-*"))
    good.check()


def test_sweep_out_under_a_file(good, tmp_path):
    grid = tmp_path / "grid.toml"
    grid.write_text(GRID)
    assert_one_line_error(run_cli("sweep", grid, "--out", good.path / "summary.json" / "sw", "--jobs", "1"),
                          "is a file, not a folder")
    good.check()


# ------------------------------------------------------------------ exit codes in --help
@pytest.mark.parametrize("verb", ["capture", "precompute", "explore", "replay", "sweep"])
def test_help_lists_the_exit_codes(verb):
    res = run_cli(verb, "--help")
    assert res.code == 0
    text = " ".join(res.out.split())
    for part in ("Exit codes", "0 complete", "2 bad input", "130 interrupted", "143 terminated"):
        assert part in text, (verb, part)
    # only the verbs that drive a robot can end on a fault
    assert ("3 the robot stopped on a fault" in text) == (verb not in ("capture", "precompute")), verb


@pytest.mark.parametrize("json_out", [False, True])
def test_robot_fault_stop_exits_3(cap, tmp_path, monkeypatch, json_out):
    """A run the library reports as stopped on a fault (final_state 'stopped', safe) exits 3, also with --json."""
    import tergodic_cli.run as run_mod

    summary = {"steps": 21, "ergodicity": 0.9, "touched_fraction": 0.1, "step_ms_median": 0.1, "files": [],
               "final_state": "stopped", "stop_reason": "joint 4 near its limit", "interrupted": False}
    monkeypatch.setattr(run_mod, "run_explore", lambda *a, **k: summary)
    res = run_cli("explore", cap, "--out", tmp_path / "run", "--no-log", *(["--json"] if json_out else []))
    assert res.code == 3, res.err
    summary["final_state"] = "done"
    assert run_cli("explore", cap, "--out", tmp_path / "run", "--no-log").code == 0
