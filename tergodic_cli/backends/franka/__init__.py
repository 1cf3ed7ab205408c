"""Franka Emika Panda / FR3: two paths to the same arm (docs/hardware.md).

- :mod:`~tergodic_cli.backends.franka.franky` (``--robot franka``, ``tergodic[franka]``): franky's
  Cartesian impedance, references streamed from Python at ``stream_hz``;
- :mod:`~tergodic_cli.backends.franka.libfranka` (``--robot franka-torque``, ``tergodic[libfranka]``):
  the official ``pylibfranka`` bindings, 1 kHz torque control running the paper's line impedance
  and wrench PID (:class:`~tergodic_cli.robot.controller.LineForceController`) in a process of its
  own (:mod:`~tergodic_cli.backends.torque`).
"""

from tergodic_cli.backends.franka.franky import (LIMITS, FrankaConfig, FrankaWrenchEstimate, FrankyArm,
                                                 _connect_fix)

__all__ = ["LIMITS", "FrankaConfig", "FrankaWrenchEstimate", "FrankyArm", "_connect_fix"]
