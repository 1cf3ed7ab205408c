"""Imported first by every benchmark script, before numpy.

- Moves this folder to the end of ``sys.path``: ``python benchmarks/x.py`` puts it first, and
  ``benchmarks/logging.py`` (the name issue 5 asks for) would shadow the standard library's
  ``logging`` for every library that imports it. At the end, benchmarks still import their
  shared modules (``import corpus``).
- Pins BLAS, OpenMP and numba to one thread (the machine has 2 cores; figures are medians).
- Turns progress bars off.
"""

import os
import sys

_here = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != _here] + [_here]

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"
os.environ.setdefault("TERGODIC_NO_PROGRESS", "1")
