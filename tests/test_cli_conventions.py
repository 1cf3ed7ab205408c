"""CLI conventions: --version, help texts printed as written, usage lines, bars and log lines, Ctrl-C."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from importlib import metadata
from pathlib import Path

import pytest

from conftest import default_signals, run_cli

VERBS = ("capture", "precompute", "explore", "replay", "sweep")


def _dist_version(*names: str) -> str:
    for name in names:
        try:
            return metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return "not installed"


def test_version_prints_tergodic_and_key_library_versions():
    res = run_cli("--version")
    assert res.code == 0, res.err
    from tergodic_cli import __version__

    lines = res.out.splitlines()
    assert lines[0].startswith(f"tergodic {__version__} ")
    for names in (("numpy",), ("scipy",), ("open3d", "open3d-cpu"), ("robust_laplacian",), ("pybullet",),
                  ("numba",), ("mcap",)):
        expected = _dist_version(*names)
        assert any(ln.split()[:2] == [names[0], expected] for ln in lines), (names, res.out)


def test_sweep_help_prints_the_grid_example_verbatim():
    res = run_cli("sweep", "--help")
    assert res.code == 0
    from tergodic_cli.commands.sweep import sweep

    doc = sweep.__doc__
    block = doc[doc.index("[objects.bowl]"): doc.index("Examples:")]
    lines = [ln.strip() for ln in block.splitlines() if ln.strip() and ln.strip() != "\b"]
    assert len(lines) >= 10
    shown = [ln.strip() for ln in res.out.splitlines()]
    at = [shown.index(ln) for ln in lines]  # each example line is a line of its own, in order
    assert at == sorted(at) and at[-1] - at[0] < len(lines) + 3, res.out
    assert "\b" not in res.out


def test_capture_help_shows_the_optional_colour_columns_without_an_escape():
    out = run_cli("capture", "--help").out
    assert "(x y z [r g b])" in " ".join(out.split())
    assert "\\[" not in out


@pytest.mark.parametrize("verb", VERBS)
def test_usage_lines_name_the_arguments_in_capitals(verb):
    first = run_cli(verb, "--help").out.splitlines()[0]
    assert first.startswith(f"Usage: tergodic {verb} [OPTIONS]"), first
    assert "{" not in first and "}" not in first, first
    rest = first.removeprefix(f"Usage: tergodic {verb} [OPTIONS]").split()
    assert all(re.fullmatch(r"\[?[A-Z_]+\]?(\.\.\.)?", piece) for piece in rest), first


def test_sweep_bar_counts_runs_not_batches(tmp_path, monkeypatch):
    from tergodic_cli import progress
    from tergodic_cli.sweep import run_sweep

    seen = {}

    def fake_track(iterable, total=None, description="", weight=None):
        seen["total"], seen["done"] = total, 0
        for item in iterable:
            yield item
            seen["done"] += 1 if weight is None else weight(item)

    monkeypatch.setattr(progress, "track", fake_track)
    grid = tmp_path / "grid.toml"
    grid.write_text('steps = 5\n[objects.plate]\nsynthetic = "plate"\nmarking = "dots"\nvoxel = 0.008\n'
                    'agent_radius = 0.012\n[grid]\nstart = 4\nnk = [10]\nalpha = [5, 10]\n')
    res = run_sweep(grid, tmp_path / "out", jobs=2, plots=False)
    assert res.n_runs == 8
    assert seen == {"total": 8, "done": 8}


def test_a_log_line_ends_the_spinner_line_first(monkeypatch, capsys):
    """With a spinner or bar on a terminal, a log line is written on a line of its own."""
    monkeypatch.setenv("FORCE_COLOR", "1")  # rich treats stderr as a terminal
    monkeypatch.delenv("TERGODIC_NO_PROGRESS", raising=False)
    from tergodic_cli.progress import Spinner, echo, track

    with Spinner("robot: moving to the start and approaching"):
        time.sleep(0.15)
        echo("robot: at hover")
    for _ in track(range(2), total=2, description="exploring"):
        echo("robot: contact")
    err = capsys.readouterr().err
    assert "approachingrobot" not in err
    for msg in ("robot: at hover", "robot: contact"):
        assert re.search(r"(\r\x1b\[2K|\n|^)" + re.escape(msg) + r"\r?\n", err), repr(err)


# -------------------------------------------------------------------------- Ctrl-C and SIGTERM
GRID = """
steps = 20000
seed = 3

[objects.bowl]
synthetic = "bowl"
marking = "X"
voxel = 0.004
agent_radius = 0.012

[grid]
start = 6
nk = [20, 40]
alpha = [5, 10]
"""


def _start(args, wait_for: str | None, delay: float):
    """Start ``tergodic ARGS`` in its own process group (as a terminal does), once ready."""
    exe = Path(sys.executable).with_name("tergodic")
    proc = subprocess.Popen([str(exe), *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, env={**os.environ, "TERGODIC_NO_PROGRESS": "1"},
                            preexec_fn=default_signals)  # whatever the shell that started the suite ignores
    head = []
    if wait_for is not None:
        for line in proc.stderr:
            head.append(line)
            if wait_for in line:
                break
    time.sleep(delay)
    assert proc.poll() is None, "finished before the signal"
    return proc, head


def _stop(proc, sig, group: bool):
    (os.killpg if group else os.kill)(proc.pid, sig)
    out, err = proc.communicate(timeout=300)  # a hang guard, not a timing assertion
    return proc.returncode, out, err


@pytest.mark.slow
def test_ctrl_c_on_a_sweep_is_one_line_with_how_to_resume_and_exit_130(tmp_path):
    (tmp_path / "grid.toml").write_text(GRID)
    proc, _ = _start(["sweep", tmp_path / "grid.toml", "--out", tmp_path / "out", "--jobs", "2"], "to run", 2.0)
    code, out, err = _stop(proc, signal.SIGINT, group=True)  # workers get it too, as from a terminal
    assert code == 130, (code, err)
    assert err.strip().splitlines() == ["tergodic: interrupted; rerun the same command to resume"], err
    assert "Traceback" not in out + err


@pytest.mark.slow
@pytest.mark.parametrize("sig, code, word", [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated")])
def test_interrupting_explore_is_one_line(tmp_path, sig, code, word):
    cap = Path(__file__).resolve().parents[1] / "data" / "bowl"
    # three agents: a step costs ~3x, so the run is still mid-loop once its log holds steps, on any machine
    proc, _ = _start(["explore", cap, "--steps", "400000", "--agents", "3", "--out", tmp_path / "run",
                      "--cache-dir", tmp_path / "cache"], None, 0.0)
    deadline = time.monotonic() + 600  # a loaded machine takes long to compute the basis: wait for the loop itself
    while time.monotonic() < deadline and proc.poll() is None:
        logs = list(tmp_path.glob(".run.tmp-*/run.mcap"))
        if logs and logs[0].stat().st_size > 50_000:
            break
        time.sleep(0.05)
    got, out, err = _stop(proc, sig, group=sig == signal.SIGINT)
    assert got == code, (got, err)
    lines = [ln for ln in err.splitlines()
             if not ln.startswith(("computing basis", "note:")) and "cache" not in ln]  # notes: the run's size
    assert len(lines) == 1 and lines[0].startswith(f"tergodic: {word}; the partial run is in"), err
    assert "Traceback" not in out + err
    assert (tmp_path / "run" / "run.mcap").exists()  # the partial run was renamed into place
