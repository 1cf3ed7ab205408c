"""``python -m tergodic_cli.basis._laplacian_child DIR``: robust_laplacian in a child process.

robust_laplacian holds the GIL for the whole call (70 s on 150k points), so a parent that runs it
itself cannot answer Ctrl-C; the parent runs it here and kills this process instead. The points come
in and the matrices go out as ``.npy`` files (never pickles): ``points.npy`` and ``k.npy`` in DIR,
``data.npy``/``indices.npy``/``indptr.npy``/``mass.npy`` out, or ``error.txt`` with one line.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np


def main(folder: str) -> int:
    import signal

    from tergodic_cli.basis.core import HELD_SIGNALS

    if hasattr(signal, "pthread_sigmask"):  # the parent held Ctrl-C and SIGTERM over the start: take them again
        signal.pthread_sigmask(signal.SIG_UNBLOCK, HELD_SIGNALS)
    d = Path(folder)
    import robust_laplacian
    import scipy.sparse as sp

    points = np.load(d / "points.npy", allow_pickle=False)
    k = int(np.load(d / "k.npy", allow_pickle=False))
    try:
        L, M = robust_laplacian.point_cloud_laplacian(points, n_neighbors=k)
    except (RuntimeError, ValueError, AssertionError) as exc:
        (d / "error.txt").write_text(str(exc).splitlines()[0][:80] if str(exc) else type(exc).__name__)
        return 1
    L = sp.csr_matrix(L, dtype=np.float64)
    for name, arr in (("data", L.data), ("indices", L.indices), ("indptr", L.indptr),
                      ("mass", np.asarray(M.diagonal(), dtype=np.float64))):
        np.save(d / f"{name}.npy", arr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
