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


def installed(name: str) -> tuple[str, str] | None:
    """(version, distribution) of ``name`` or of another distribution of its module; None when absent."""
    for dist in (name,) + _ALIASES.get(name, ()):
        with contextlib.suppress(metadata.PackageNotFoundError):
            return metadata.version(dist), dist
    return None


@functools.lru_cache(maxsize=1)
def _versions() -> tuple[tuple[str, str], ...]:
    out = {"python": sys.version.split()[0], "platform": platform.platform()}
    out.update({name: (installed(name) or ("absent",))[0] for name in _PACKAGES})
    return tuple(out.items())


def library_versions() -> dict[str, str]:
    """Installed versions of the libraries that shape results (``"absent"`` when missing)."""
    return dict(_versions())
