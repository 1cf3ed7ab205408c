"""Imported first by every benchmark script, before numpy.

- Takes this folder off ``sys.path``: ``python benchmarks/x.py`` puts it first, and
  ``benchmarks/logging.py`` (the name issue 5 asks for) would shadow the standard library's
  ``logging``, and ``benchmarks/coverage.py`` the ``coverage`` package numba looks for, for every
  library that imports them (anywhere on the path, even last). Benchmarks still import their
  shared modules (``SHARED``: ``import corpus``) through a finder that knows only those names.
- Pins BLAS, OpenMP and numba to one thread (the machine has 2 cores; figures are medians).
- Turns progress bars off.
"""

import importlib.abc
import importlib.util
import os
import sys

_here = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != _here]
#: The benchmark modules other benchmarks import.
SHARED = ("corpus", "explore_reference")


class _SharedFinder(importlib.abc.MetaPathFinder):
    """Finds the SHARED modules in this folder, and nothing else."""

    def find_spec(self, name, path=None, target=None):
        if path is None and name in SHARED:
            return importlib.util.spec_from_file_location(name, os.path.join(_here, f"{name}.py"))
        return None


if not any(isinstance(f, _SharedFinder) for f in sys.meta_path):
    sys.meta_path.append(_SharedFinder())

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"
os.environ.setdefault("TERGODIC_NO_PROGRESS", "1")
