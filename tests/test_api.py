"""The public API: docs/api.md's example runs as written, and every public name resolves lazily."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

import tergodic_cli

DOC = Path(__file__).resolve().parents[1] / "docs" / "api.md"


def test_api_doc_example_runs(tmp_path):
    code = re.findall(r"```python\n(.*?)```", DOC.read_text(), re.S)
    assert len(code) == 1, "docs/api.md should hold one runnable python block"
    # Its own asserts check the stages against each other (the run's ε equals the path's score).
    done = subprocess.run([sys.executable, "-c", code[0]], cwd=tmp_path, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    lines = done.stdout.splitlines()
    assert re.fullmatch(r"\d+ points, \d+ marked", lines[0])
    eps = float(re.search(r"eps ([0-9.]+)", lines[1]).group(1))
    assert 0.0 < eps < 1.0
    assert "summary.json" in lines[2] and "run.mcap" in lines[2] and "config.json" in lines[2]


@pytest.mark.parametrize("name", [n for n in tergodic_cli.__all__ if not n.startswith("_") and n != "FORMAT_VERSION"])
def test_public_name_resolves_with_a_docstring(name):
    obj = getattr(tergodic_cli, name)
    assert obj.__doc__ and obj.__doc__.strip(), f"{name} has no docstring"
    assert name in dir(tergodic_cli)


def test_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError):
        tergodic_cli.no_such_name  # noqa: B018


def test_import_stays_cheap():
    # The heavy libraries load inside the functions that need them, not on import.
    code = ("import sys, tergodic_cli; heavy = [m for m in ('open3d', 'pybullet', 'robust_laplacian', 'numba') "
            "if m in sys.modules]; print(','.join(heavy))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and done.stdout.strip() == "", done.stdout + done.stderr
