"""Lazy imports of the optional hardware SDKs, with a one-line install hint when one is missing.

Each SDK is an optional extra of the package (``pip install 'tergodic[franka]'`` and so on). The
import happens only when a backend connects, never at CLI start-up, so ``tergodic --help`` and
every simulated run work without any of them.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from tergodic_cli.errors import TergodicError

#: module name -> (extra, pip distribution, what it is)
SDKS: dict[str, tuple[str, str, str]] = {
    "franky": ("franka", "franky-control", "the Franka SDK"),
    "pylibfranka": ("libfranka", "pylibfranka", "Franka's official libfranka bindings"),
    "rtde_control": ("ur", "ur_rtde", "SDU's RTDE interface to Universal Robots"),
    "rtde_receive": ("ur", "ur_rtde", "SDU's RTDE interface to Universal Robots"),
    "bota_driver": ("bota", "bota-driver", "Bota Systems' F/T sensor driver"),
    "pyrealsense2": ("realsense", "pyrealsense2", "the Intel RealSense SDK"),
}


def import_sdk(module: str) -> ModuleType:
    """Import an optional SDK by its module name, or raise a one-line :class:`TergodicError`.

    A module that is absent gives "<module> is not installed; pip install 'tergodic[<extra>]'".
    A module that is present but fails to load (a missing shared library, a libfranka built for
    another robot generation) gives the loader's own message instead, since reinstalling the
    extra is then not the fix.
    """
    extra, dist, what = SDKS[module]
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name not in (None, module) and not str(exc.name).startswith(module + "."):
            raise TergodicError(f"{module} ({what}) failed to import: {exc}",
                                f"reinstall it with pip install --force-reinstall {dist}") from None
        raise TergodicError(f"{module} is not installed ({what}, pip package {dist})",
                            f"pip install 'tergodic[{extra}]'") from None
    except ImportError as exc:
        raise TergodicError(f"{module} ({what}) is installed but failed to load: {exc}",
                            f"reinstall it with pip install --force-reinstall {dist}, matching your robot or device firmware") from None


def one_line(exc: BaseException) -> str:
    """An SDK's exception as one line of at most 200 characters (its type when it says nothing)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."
