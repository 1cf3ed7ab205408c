"""Versions and environment recorded beside every artefact, for reproducibility."""

from __future__ import annotations

import contextlib
import functools
import platform
import sys
from importlib import metadata

#: Other distributions of the same module: open3d-cpu installs ``open3d`` (pyproject.toml).
_ALIASES = {"open3d": ("open3d-cpu",)}

_PACKAGES = ("tergodic", "numpy", "scipy", "open3d", "robust-laplacian", "pybullet", "pygafro", "mcap")


@functools.lru_cache(maxsize=1)
def _versions() -> tuple[tuple[str, str], ...]:
    out = {"python": sys.version.split()[0], "platform": platform.platform()}
    for name in _PACKAGES:
        found = []
        for dist in (name,) + _ALIASES.get(name, ()):
            with contextlib.suppress(metadata.PackageNotFoundError):
                found.append(metadata.version(dist))
        out[name] = (found or ["absent"])[0]
    return tuple(out.items())


def library_versions() -> dict[str, str]:
    """Installed versions of the libraries that shape results (``"absent"`` when missing)."""
    return dict(_versions())
