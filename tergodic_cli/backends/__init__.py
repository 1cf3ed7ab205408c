"""The backends behind the robot layer's interfaces: one folder per device family, one registry.

:mod:`~tergodic_cli.backends.registry` lists every backend (name -> config dataclass -> factory):

- robots: ``kinematic`` (the agent alone), ``pybullet`` (:mod:`~tergodic_cli.backends.pybullet`: simulated
  arms, one module each under ``pybullet/arms/``), ``franka`` and ``franka-torque``
  (:mod:`~tergodic_cli.backends.franka`: franky, ``tergodic[franka]``; pylibfranka, ``tergodic[libfranka]``),
  ``ur`` (:mod:`~tergodic_cli.backends.ur`: ur_rtde, ``tergodic[ur]``);
- F/T sensors: ``bota`` (:mod:`~tergodic_cli.backends.bota`, ``tergodic[bota]``), ``netft``
  (:mod:`~tergodic_cli.backends.netft`, standard library), ``franka`` and ``ur`` (the arms' own);
- cameras: ``realsense`` (:mod:`~tergodic_cli.backends.realsense`, ``tergodic[realsense]``).

Shared by the hardware backends: :mod:`~tergodic_cli.backends.camera` (the Camera protocol,
back-projection), :mod:`~tergodic_cli.backends.impedance` (impedance references),
:mod:`~tergodic_cli.backends.streamed` (a device and a sensor as the contact loop's Arm, the dry run),
:mod:`~tergodic_cli.backends.torque` (a 1 kHz torque loop in a process of its own),
:mod:`~tergodic_cli.backends.factory` (building them from the registry), :mod:`~tergodic_cli.backends.extras`
(optional SDKs, imported lazily).

Entry points: :func:`make_hardware`, :func:`make_camera`, :func:`explore_with_hardware`, :func:`dry_run`
(attributes resolved on first use, so importing the registry loads no SDK, numba or PyBullet).
"""

import importlib

_EXPORTS = {
    "Camera": "camera", "Intrinsics": "camera", "deproject": "camera",
    "make_camera": "factory", "make_hardware": "factory",
    "LineImpedanceGains": "impedance", "line_impedance_target": "impedance",
    "DryRunPlan": "streamed", "HardwareRunConfig": "streamed", "dry_run": "streamed", "explore_with_hardware": "streamed",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"tergodic_cli.backends.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'tergodic_cli.backends' has no attribute {name!r}")
