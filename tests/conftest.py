"""Shared fixtures: an isolated basis cache, the reference data (skipped when absent), a CLI runner."""

from __future__ import annotations

import contextlib
import io
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
REFERENCE = REPO.parent / "shared" / "data" / "reference"

os.environ.setdefault("TERGODIC_NO_PROGRESS", "1")


@pytest.fixture(autouse=True)
def isolated_cache(tmp_path_factory, monkeypatch):
    """Every test gets its own basis cache, never ~/.cache."""
    cache = tmp_path_factory.mktemp("cache")
    monkeypatch.setenv("TERGODIC_CACHE_DIR", str(cache))
    return cache


@pytest.fixture
def reference() -> Path:
    """The paper's reference clouds; the test is skipped when they are not beside the repo."""
    if not (REFERENCE / "bun270_X.ply").exists():
        pytest.skip("reference data ../shared/data/reference is absent")
    return REFERENCE


@dataclass
class CliResult:
    code: int
    out: str
    err: str


def run_cli(*args: str) -> CliResult:
    """Run ``tergodic ARGS`` in-process and capture exit code, stdout and stderr."""
    from tergodic_cli.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in args])
    return CliResult(code, out.getvalue(), err.getvalue())


def run_cli_subprocess(*args: str, timeout: float = 600) -> CliResult:
    """Run the installed ``tergodic`` console script in a real subprocess."""
    exe = Path(sys.executable).with_name("tergodic")
    proc = subprocess.run([str(exe), *map(str, args)], capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "TERGODIC_NO_PROGRESS": "1"})
    return CliResult(proc.returncode, proc.stdout, proc.stderr)


def assert_one_line_error(res: CliResult, *needles: str) -> None:
    """Exit 2, a single 'tergodic: error:' line on stderr, no traceback, mentioning every needle."""
    assert res.code == 2, (res.code, res.out, res.err)
    lines = [ln for ln in res.err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, res.err
    assert lines[0].startswith("tergodic: error:"), res.err
    assert "Traceback" not in res.err
    for needle in needles:
        assert needle.lower() in lines[0].lower(), (needle, lines[0])


def fibonacci_sphere(n: int, radius: float = 1.0) -> np.ndarray:
    """(n, 3) nearly uniform points on a sphere."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    return radius * np.column_stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)])


def jittered_square(m: int, side: float = 1.0, seed: int = 0) -> np.ndarray:
    """(m*m, 3) cell-centred grid on [0, side]² in the z = 0 plane, jittered by ±10% of a cell."""
    g = (np.arange(m) + 0.5) / m * side
    x, y = np.meshgrid(g, g)
    pts = np.column_stack([x.ravel(), y.ravel(), np.zeros(m * m)])
    pts[:, :2] += np.random.default_rng(seed).uniform(-0.1, 0.1, (m * m, 2)) * side / m
    return pts


def default_signals() -> None:
    """``preexec_fn`` of a child whose test sends it SIGINT/SIGTERM: both at their default
    disposition, whatever the shell that started the suite ignores (Python then installs its
    Ctrl-C handler in the child)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
