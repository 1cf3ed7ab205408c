"""numba's kernels, compiled once into its on-disk cache: ``python -m tergodic_cli.warm`` (``make setup`` runs it).

The explorer's and the robot's kernels are ``numba.njit(cache=True)``: the first process that
calls them compiles them (about 25 s), later ones load the machine code (about 0.1 s). Without
a warm cache a first ``tergodic explore`` would sit silent for that long, and the compile would
land inside its first step. So ``run_explore`` calls :func:`compile_explorer` before its loop,
which says one line when the disk cache is cold, and ``make setup`` fills the cache up front.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

from tergodic_cli.explore.warm import compile_explorer, explorer_kernels_cached


def compile_robot() -> float:
    """Compile or load the robot's kernels: a two-step simulated (PyBullet) run on a tiny capture; returns seconds."""
    from tergodic_cli.capture import CaptureConfig, capture_cloud, save_capture
    from tergodic_cli.explore import ExploreConfig
    from tergodic_cli.run import make_backend, run_explore

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="tergodic-warm-") as tmp:
        cap = capture_cloud(CaptureConfig(source="synthetic", synthetic="bowl", marking="X", seed=0))
        save_capture(cap, Path(tmp) / "cap")
        run_explore(Path(tmp) / "cap", ExploreConfig(steps=2, nk=10), Path(tmp) / "run", make_backend("pybullet"),
                    log=None, cache_dir=Path(tmp) / "cache")
    return time.perf_counter() - t0


def main() -> int:
    os.environ.setdefault("TERGODIC_NO_PROGRESS", "1")
    cold = not explorer_kernels_cached()
    t = compile_explorer()
    print(f"warm: explorer kernels {'compiled' if cold else 'loaded from the cache'} in {t:.1f} s")
    try:
        t = compile_robot()
    except Exception as exc:  # the explorer works without the robot stack; say so and go on
        print(f"warm: robot kernels not compiled ({type(exc).__name__}: {str(exc).splitlines()[0][:100]})")
        return 0
    print(f"warm: robot kernels ready in {t:.1f} s")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
