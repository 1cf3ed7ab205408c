"""Robot: a force-controlled arm follows the explorer (paper sections IV-B and V-A3).

Entry points: :class:`RobotConfig`, :class:`ContactRun` (the one contact loop: state machine and
safety guard), :func:`summarize_robot` (summary extras from the per-step samples, pure), and
:func:`robot_explore_config` (the explorer's time scaling for robot mode).

The backends implement :class:`Arm` and :class:`WrenchSensor` (Protocols) in
:mod:`tergodic_cli.backends` (``pybullet``: the simulation and its camera; ``streamed``: a
Franka through franky with a Bota or Net F/T sensor).
"""

from tergodic_cli.robot.config import PAPER_GAINS, ControllerGains, RobotConfig, SafetyConfig, validate_robot_config

#: name -> the module that defines it, loaded on first use (numpy, scipy: the CLI reads only the config at start-up)
_LAZY = {"LineForceController": "controller", "Arm": "interfaces", "ArmState": "interfaces", "LineTarget": "interfaces",
         "Observation": "interfaces", "ToolLoad": "interfaces", "WrenchReading": "interfaces",
         "WrenchSensor": "interfaces", "Fault": "safety", "SafetyGuard": "safety", "summarize_robot": "summary",
         "ContactRun": "run", "robot_explore_config": "run"}


def __getattr__(name):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(name)
    import importlib

    return getattr(importlib.import_module(f"tergodic_cli.robot.{module}"), name)


__all__ = [
    "Arm", "ArmState", "ContactRun", "ControllerGains", "Fault", "LineForceController", "LineTarget", "Observation",
    "PAPER_GAINS", "RobotConfig", "SafetyConfig", "SafetyGuard", "ToolLoad", "WrenchReading", "WrenchSensor",
    "robot_explore_config", "summarize_robot", "validate_robot_config",
]
