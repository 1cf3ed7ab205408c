"""Robot: a force-controlled arm follows the explorer (paper sections IV-B and V-A3).

Entry points: :class:`RobotConfig`, :func:`explore_with_robot` (the ``--robot pybullet`` run),
:func:`clean_with_robot` (the closed outer loop through the simulated camera, ``--recapture-every``),
:func:`summarize_robot` (summary extras from the per-step samples, pure), and
:func:`robot_explore_config` (the explorer's time scaling for robot mode).

Hardware-shaped interfaces: :class:`Arm`, :class:`WrenchSensor` (Protocols); the PyBullet
backend lives in :mod:`tergodic_cli.robot.pybullet_backend`. One :class:`SafetyGuard`
serves every backend.
"""

from tergodic_cli.robot.config import RobotConfig, validate_robot_config
from tergodic_cli.robot.controller import PAPER_GAINS, ControllerGains, LineForceController
from tergodic_cli.robot.interfaces import Arm, ArmState, ToolLoad, WrenchReading, WrenchSensor
from tergodic_cli.robot.safety import Fault, SafetyConfig, SafetyGuard
from tergodic_cli.robot.summary import summarize_robot


def __getattr__(name):  # the run pulls in open3d, scipy and pybullet; load on first use
    if name in ("explore_with_robot", "robot_explore_config", "RobotRun"):
        from tergodic_cli.robot import run

        return getattr(run, name)
    if name in ("clean_with_robot", "CleaningLoopConfig", "log_recapture", "sim_scene_configs"):
        from tergodic_cli.robot import closed_loop

        return getattr(closed_loop, name)
    raise AttributeError(name)


__all__ = [
    "Arm", "ArmState", "CleaningLoopConfig", "ControllerGains", "Fault", "LineForceController", "PAPER_GAINS",
    "RobotConfig", "RobotRun", "SafetyConfig", "SafetyGuard", "ToolLoad", "WrenchReading", "WrenchSensor",
    "clean_with_robot", "explore_with_robot", "log_recapture", "robot_explore_config", "sim_scene_configs",
    "summarize_robot", "validate_robot_config",
]
