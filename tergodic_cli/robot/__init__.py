"""Robot: a force-controlled arm follows the explorer (paper sections IV-B and V-A3).

Entry points: :class:`RobotConfig`, :class:`ContactRun` (the one contact loop: state machine and
safety guard), :func:`summarize_robot` (summary extras from the per-step samples, pure), and
:func:`robot_explore_config` (the explorer's time scaling for robot mode).

The backends implement :class:`Arm` and :class:`WrenchSensor` (Protocols) in
:mod:`tergodic_cli.backends` (``pybullet``: the simulation and its camera; ``streamed``: a
Franka through franky with a Bota or Net F/T sensor).
"""

from tergodic_cli.robot.config import RobotConfig, validate_robot_config
from tergodic_cli.robot.controller import PAPER_GAINS, ControllerGains, LineForceController
from tergodic_cli.robot.interfaces import Arm, ArmState, LineTarget, Observation, ToolLoad, WrenchReading, WrenchSensor
from tergodic_cli.robot.safety import Fault, SafetyConfig, SafetyGuard
from tergodic_cli.robot.summary import summarize_robot


def __getattr__(name):  # the run pulls in scipy; load on first use
    if name in ("ContactRun", "robot_explore_config"):
        from tergodic_cli.robot import run

        return getattr(run, name)
    raise AttributeError(name)


__all__ = [
    "Arm", "ArmState", "ContactRun", "ControllerGains", "Fault", "LineForceController", "LineTarget", "Observation",
    "PAPER_GAINS", "RobotConfig", "SafetyConfig", "SafetyGuard", "ToolLoad", "WrenchReading", "WrenchSensor",
    "robot_explore_config", "summarize_robot", "validate_robot_config",
]
