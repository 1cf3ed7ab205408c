"""Versions and environment recorded beside every artefact, for reproducibility."""

from __future__ import annotations

import functools
import platform
import sys
from importlib import metadata

_PACKAGES = ("tergodic", "numpy", "scipy", "open3d", "robust-laplacian", "pybullet", "pygafro", "mcap")


@functools.lru_cache(maxsize=1)
def _versions() -> tuple[tuple[str, str], ...]:
    out = {"python": sys.version.split()[0], "platform": platform.platform()}
    for name in _PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "absent"
    return tuple(out.items())


def library_versions() -> dict[str, str]:
    """Installed versions of the libraries that shape results (``"absent"`` when missing)."""
    return dict(_versions())
