"""Universal Robots e-Series (``--robot ur``): :mod:`~tergodic_cli.backends.ur.rtde` (ur_rtde: force mode
with the paper's wrench, servoL, moveJ; the UR's own TCP force or an external F/T sensor) and
:mod:`~tergodic_cli.backends.ur.model` (the arm models, DH kinematics and datasheet limits)."""

from tergodic_cli.backends.ur.model import ur_model
from tergodic_cli.backends.ur.rtde import URArm, URConfig, URForceSensor

__all__ = ["URArm", "URConfig", "URForceSensor", "ur_model"]
