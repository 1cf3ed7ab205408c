"""numba's disk cache: the cold-cache line, and no compile inside a timed explorer step."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tergodic_cli.explore import warm as explore_warm

numba = pytest.importorskip("numba")

KERNEL = """
import numba

@numba.njit(cache=True)
def double(x):
    return {body}
"""


def _import_fresh(folder: Path, name: str):
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, folder / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def test_cached_follows_numbas_index(tmp_path):
    """Cold before the first compile, warm in a new process after it, cold again once the source changes."""
    src = tmp_path / "warm_probe.py"
    src.write_text(KERNEL.format(body="2 * x"))
    try:
        assert not explore_warm._cached(_import_fresh(tmp_path, "warm_probe").double)
        run = [sys.executable, "-c", "import sys; sys.path.insert(0, sys.argv[1]); import warm_probe; warm_probe.double(1.0)",
               str(tmp_path)]
        subprocess.run(run, check=True, timeout=600)
        assert explore_warm._cached(_import_fresh(tmp_path, "warm_probe").double)
        src.write_text(KERNEL.format(body="3 * x"))  # a new source stamp: numba's index is stale
        assert not explore_warm._cached(_import_fresh(tmp_path, "warm_probe").double)
    finally:
        sys.modules.pop("warm_probe", None)


def test_cold_line_is_said_once_and_only_when_cold(monkeypatch):
    said: list[str] = []
    for cold in (True, False):
        monkeypatch.setattr(explore_warm, "explorer_kernels_cached", lambda cold=cold: not cold)
        monkeypatch.setattr(explore_warm, "_compiled_here", lambda: False)  # as at the start of a run
        said.clear()
        explore_warm.compile_explorer(said.append)
        assert said == ([explore_warm.COLD_LINE] if cold else [])
    assert "first run only" in explore_warm.COLD_LINE and "compiling the explorer's kernels" in explore_warm.COLD_LINE


def test_no_compile_inside_a_timed_step(tmp_path):
    """In a fresh process the step kernel is compiled (or loaded) before the first timed step, and
    the run's own arguments need no further compile."""
    cap = Path(__file__).resolve().parents[1] / "data" / "bowl"
    if not (cap / "cloud.npz").is_file():
        pytest.skip("data/bowl is missing")
    script = textwrap.dedent(f"""
        import json
        from tergodic_cli.explore import ExploreConfig, kernels
        from tergodic_cli.explore.explorer import Explorer
        from tergodic_cli.run import run_explore

        import numpy as np
        seen = []
        n_points = len(np.load({str(cap / 'cloud.npz')!r})["points"])
        step = Explorer.step
        def probe(self, *a, **k):
            if len(self.points) == n_points:  # the run's explorer, not the warm-up's
                seen.append(len(kernels.step_kernel.signatures))
            return step(self, *a, **k)
        Explorer.step = probe
        run_explore({str(cap)!r}, ExploreConfig(steps=5, nk=20), {str(tmp_path / 'run')!r}, log=None,
                    cache_dir={str(tmp_path / 'cache')!r})
        print(json.dumps({{"seen": seen, "after": len(kernels.step_kernel.signatures)}}))
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600,
                         env={**__import__("os").environ, "TERGODIC_NO_PROGRESS": "1"})
    assert out.returncode == 0, out.stderr
    import json

    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert len(res["seen"]) == 5 and res["seen"][0] >= 1, "the first timed step compiled the step kernel"
    assert res["after"] == res["seen"][0], "the run's arguments needed a new specialisation inside a step"
