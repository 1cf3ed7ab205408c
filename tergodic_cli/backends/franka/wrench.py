"""The Franka's own estimate of the external wrench, as a :class:`WrenchSensor` (no extra hardware).

libfranka estimates the wrench the environment applies to the robot from its joint torque sensors,
``K_F_ext_hat_K`` (stiffness frame K, which is the end-effector frame unless ``set_k`` moved it).
The sensor convention of :mod:`tergodic_cli.robot.interfaces` is the wrench the arm applies to the
tool, so the reading is its negative. Far noisier than a wrist sensor (about ±1-2 N at the TCP
from joint friction and model error): fine for a first test, not for measured force tracking.
"""

from __future__ import annotations

import numpy as np

from tergodic_cli.robot.interfaces import WrenchSensor


class FrankaWrenchEstimate(WrenchSensor):
    """``-K_F_ext_hat_K`` of a connected :class:`~tergodic_cli.backends.franka.FrankyArm`, minus the tare."""

    def __init__(self, arm, tare_samples: int = 20):
        super().__init__(None, tare_samples)
        self.arm = arm

    def connect(self) -> None:
        self.arm.connect()

    def _sample(self) -> tuple[float, np.ndarray]:
        s = self.arm._require().state
        return float(s.time.to_sec()), -np.asarray(s.K_F_ext_hat_K, dtype=float).reshape(6)

    def disconnect(self) -> None:
        """The arm owns the connection."""
