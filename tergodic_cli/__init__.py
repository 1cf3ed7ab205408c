"""tergodic: tactile ergodic control on coloured point clouds.

Data flows one way: cloud -> basis -> explorer -> robot -> log. The names below are the public API
for notebooks and scripts (docs/api.md has a runnable example); each stage's package holds the rest.

Capture
    :class:`CaptureConfig`, :func:`capture_cloud`, :func:`load_capture`, :func:`save_capture`,
    :class:`Capture`.
Precompute
    :class:`BasisConfig`, :func:`get_basis` (cached by geometry content), :class:`Basis`.
Explore
    :class:`ExploreConfig`, :class:`Explorer` (one object per run, ``step()`` per step),
    :func:`coverage_score` (the unit-mass ε of a trajectory).
Run
    :func:`run_explore` (a whole ``tergodic explore`` run into a folder, log included),
    :func:`make_backend` ("kinematic", "pybullet", "franka"), :class:`StartSpec`, :class:`LogSpec`.

Heavy libraries (open3d, pybullet, robust_laplacian) are imported only inside the functions that
need them, and these names are resolved on first use, so ``import tergodic_cli`` stays cheap.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

#: Version of the basis-cache layout and solver; part of every cache key, bumped when either changes.
FORMAT_VERSION = 2

#: public name -> the module that defines it (resolved lazily, PEP 562)
_PUBLIC = {
    "Capture": "tergodic_cli.capture.artefact",
    "CaptureConfig": "tergodic_cli.capture.pipeline",
    "capture_cloud": "tergodic_cli.capture.pipeline",
    "load_capture": "tergodic_cli.capture.artefact",
    "save_capture": "tergodic_cli.capture.artefact",
    "Basis": "tergodic_cli.basis.core",
    "BasisConfig": "tergodic_cli.basis.cache",
    "get_basis": "tergodic_cli.basis.cache",
    "ExploreConfig": "tergodic_cli.explore.config",
    "Explorer": "tergodic_cli.explore.explorer",
    "coverage_score": "tergodic_cli.explore.metrics",
    "run_explore": "tergodic_cli.run",
    "make_backend": "tergodic_cli.run",
    "StartSpec": "tergodic_cli.runspec",
    "LogSpec": "tergodic_cli.runspec",
}

__all__ = ["FORMAT_VERSION", "__version__", *_PUBLIC]


def __getattr__(name: str):
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'tergodic_cli' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # resolve once
    return value


def __dir__():
    return sorted(set(globals()) | set(_PUBLIC))
