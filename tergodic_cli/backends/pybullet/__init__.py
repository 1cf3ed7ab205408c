"""The PyBullet backend: a simulated Franka Panda with a sponge and a wrist F/T sensor, and the
simulated camera; :func:`explore_with_robot` (``--robot pybullet``) and :func:`clean_with_robot`
(the closed loop through the camera, ``--recapture-every``)."""

from tergodic_cli.backends.pybullet.arm import RobotRun, SimArm, explore_with_robot
from tergodic_cli.backends.pybullet.closed_loop import (CleaningLoopConfig, clean_with_robot,
                                                      log_recapture, sim_scene_configs)
from tergodic_cli.backends.pybullet.devices import PyBulletArm, PyBulletWrenchSensor
from tergodic_cli.backends.pybullet.scene import PyBulletScene

__all__ = ["CleaningLoopConfig", "PyBulletArm", "PyBulletScene", "PyBulletWrenchSensor", "RobotRun", "SimArm",
           "clean_with_robot", "explore_with_robot", "log_recapture", "sim_scene_configs"]
