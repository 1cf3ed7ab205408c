"""Franka arms through franky (optional extra ``tergodic[franka]``)."""

from tergodic_cli.backends.franka.arm import LIMITS, FrankaConfig, FrankyArm
from tergodic_cli.backends.franka.wrench import FrankaWrenchEstimate

__all__ = ["FrankaConfig", "FrankaWrenchEstimate", "FrankyArm", "LIMITS"]
