"""Fake hardware SDKs for tests, shaped like the real modules (``franky``, ``bota_driver``, ``pyrealsense2``)
and a loopback Net F/T (RDT over UDP) server. Each fake is installed under the real module's name with
``monkeypatch.setitem(sys.modules, ...)``; the tergodic code under test is never replaced.

The call signatures follow the installed SDKs (franky-control 2.0.0 ``_franky.pyi``, bota-driver 1.1.16,
pyrealsense2 2.59.1), including the refusals the real bindings make (franky's JointMotion refuses a
plain list; Bota's tare() refuses to run while streaming; a pipeline that was never started refuses
stop()). What a real device would do physically comes from :class:`fakes.world.FakeWorld`.
"""

import sys
from types import ModuleType


def install(monkeypatch, name: str) -> ModuleType:
    """Put the fake SDK ``name`` (franky, bota_driver, pyrealsense2) into sys.modules for one test."""
    import importlib

    module = importlib.import_module(f"fakes.{name}")
    monkeypatch.setitem(sys.modules, name, module)
    return module


def uninstall(monkeypatch, name: str) -> None:
    """Make ``import name`` fail as if the SDK were not installed."""
    monkeypatch.setitem(sys.modules, name, None)
