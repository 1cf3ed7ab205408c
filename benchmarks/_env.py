"""Imported first by every benchmark script, before numpy.

- Takes this folder off ``sys.path``: ``python benchmarks/x.py`` puts it first, and
  ``benchmarks/logging.py`` (the name issue 5 asks for) would shadow the standard library's
  ``logging`` for every library that imports it.
- Pins BLAS, OpenMP and numba to one thread (the machine has 2 cores; figures are medians).
- Turns progress bars off.

Shared benchmark modules are loaded by path, not by name: ``corpus = _env.load("corpus")``
(with this folder on ``sys.path``, ``benchmarks/coverage.py`` would also shadow the ``coverage``
package numba probes for).
"""

import os
import sys

_here = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != _here]

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"
os.environ.setdefault("TERGODIC_NO_PROGRESS", "1")


def load(name: str):
    """The benchmark module ``benchmarks/<name>.py``, imported by path (once; kept in ``sys.modules``)."""
    import importlib.util

    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, os.path.join(_here, f"{name}.py"))
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]
