"""Franka arms through franky (optional extra ``tergodic[franka]``)."""

from tergodic_cli.hardware.franka.arm import LIMITS, FrankaConfig, FrankyArm
from tergodic_cli.hardware.franka.wrench import FrankaWrenchEstimate

__all__ = ["FrankaConfig", "FrankaWrenchEstimate", "FrankyArm", "LIMITS"]
