"""The explorer's numba kernels into numba's disk cache (``make setup``), and the one line a
cold cache says first. ``tergodic_cli.warm`` is the command; this is the explore stage's part."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np

#: Measured cold compile of the explorer's kernels (a plain `pip install`, 2026-11: 15-25 s).
COMPILE_S = 25

COLD_LINE = f"compiling the explorer's kernels (first run only, ~{COMPILE_S} s)"


def _cached(dispatcher) -> bool:
    """Whether numba's disk cache holds a compiled version of ``dispatcher`` for its current source."""
    if getattr(dispatcher, "signatures", None):
        return True  # compiled (or loaded) in this process already
    try:
        # numba's own index reader: empty when the index is missing, from another numba, or
        # stale (the kernels' source changed since). Private API, hence the fallback below.
        return bool(dispatcher._cache._cache_file._load_index())
    except Exception:
        name = getattr(dispatcher, "__qualname__", getattr(dispatcher, "__name__", ""))
        module = sys.modules.get(getattr(dispatcher, "__module__", ""), None)
        folder = Path(getattr(module, "__file__", "") or ".").parent / "__pycache__"
        return any(folder.glob(f"*.{name}-*.nbi"))


def explorer_kernels_cached() -> bool:
    """Whether the explorer's step kernel (the bulk of the compile) is in numba's disk cache.

    Returns
    -------
    bool
    """
    from tergodic_cli.explore import kernels

    return _cached(kernels.step_kernel)


def _compiled_here() -> bool:
    """Whether this process has compiled (or loaded) the explorer's step kernel already."""
    from tergodic_cli.explore import kernels

    return bool(kernels.step_kernel.signatures)


def _tiny_basis(n: int = 300, nk: int = 10):
    """A stand-in basis of a small sphere (5 cm, Fibonacci points) with the real one's types: a kNN
    graph Laplacian and random orthonormal modes. Values do not matter here, and it takes ~5 ms
    where the real basis (robust Laplacian + eigensolver) takes ~250 ms on every run."""
    import scipy.sparse as sp
    from scipy.spatial import cKDTree

    from tergodic_cli.basis import Basis

    i = np.arange(n) + 0.5
    phi, theta = np.arccos(1 - 2 * i / n), np.pi * (1 + 5**0.5) * i
    pts = 0.05 * np.column_stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)])
    d, j = cKDTree(pts).query(pts, 7)
    W = sp.csr_matrix((np.ones(6 * n), (np.repeat(np.arange(n), 6), j[:, 1:].ravel())), shape=(n, n))
    W = W.maximum(W.T)
    L = (sp.diags(np.asarray(W.sum(axis=1)).ravel()) - W).tocsr()
    mass = np.full(n, 4 * np.pi * 0.05**2 / n)
    evecs = np.linalg.qr(np.random.default_rng(0).standard_normal((n, nk)))[0] / np.sqrt(mass[:, None])
    return Basis(points=pts, L=L, mass=mass, evals=np.linspace(0.0, 1e4, nk), evecs=np.ascontiguousarray(evecs),
                 h=float(d[:, 1:4].mean()))


def compile_explorer(say: Callable[[str], None] | None = None) -> float:
    """Compile (cold disk cache) or load (warm) every explorer kernel in this process; returns seconds.

    A few steps of a tiny explorer take every kernel through the paths a run uses: the spectral and
    the implicit step, the robot's deposits and resets, and the logged heat and source.

    Parameters
    ----------
    say : callable, optional
        Gets :data:`COLD_LINE` first when the disk cache is cold.

    Returns
    -------
    float
        Seconds spent.
    """
    from tergodic_cli.explore import ExploreConfig, Explorer

    if _compiled_here():
        return 0.0
    if say is not None and not explorer_kernels_cached():
        say(COLD_LINE)
    t0 = time.perf_counter()
    basis = _tiny_basis()
    pts = basis.points
    target = np.zeros(len(pts))
    target[: len(pts) // 2] = 1.0
    for integrator in ("resolvent", "implicit"):
        ex = Explorer(basis, target, ExploreConfig(nk=10, agent_radius=0.02, integrator=integrator), pts[:1],
                      on_event=lambda msg: None)
        ex.step()
        ex.step(deposit_at=pts[:2], agent_at=pts[1:2])
        ex.step(deposit_at=pts[:0])
        _ = ex.heat, ex.source, ex.metrics()
    return time.perf_counter() - t0
