"""The PyBullet backend: a simulated Franka Panda with a sponge and a wrist F/T sensor."""

from tergodic_cli.robot.pybullet_backend.devices import PyBulletArm, PyBulletWrenchSensor
from tergodic_cli.robot.pybullet_backend.scene import PyBulletScene, SpongeSpec

__all__ = ["PyBulletArm", "PyBulletScene", "PyBulletWrenchSensor", "SpongeSpec"]
