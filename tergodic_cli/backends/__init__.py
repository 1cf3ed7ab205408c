"""The backends behind the robot Protocols, one folder each; each SDK is an optional extra, imported lazily.

- :mod:`~tergodic_cli.backends.pybullet`: the simulated Panda, sponge, F/T sensor and camera (PyBullet);
- :mod:`~tergodic_cli.backends.franka`: Franka arms through franky (``tergodic[franka]``);
- :mod:`~tergodic_cli.backends.bota`: Bota F/T sensors through bota_driver (``tergodic[bota]``);
- :mod:`~tergodic_cli.backends.netft`: ATI Net F/T over UDP (standard library, no extra);
- :mod:`~tergodic_cli.backends.realsense`: RealSense cameras through pyrealsense2 (``tergodic[realsense]``);
- :mod:`~tergodic_cli.backends.camera`: the :class:`Camera` protocol and back-projection;
- :mod:`~tergodic_cli.backends.impedance`: how the line controller becomes an SDK impedance reference;
- :mod:`~tergodic_cli.backends.streamed`: an ImpedanceArm and a WrenchSensor as the contact loop's Arm, and :func:`dry_run`.

Entry points: :func:`make_hardware`, :func:`make_camera`, :func:`explore_with_hardware`, :func:`dry_run`.
"""

from tergodic_cli.backends.camera import Camera, Intrinsics, deproject
from tergodic_cli.backends.factory import make_camera, make_hardware
from tergodic_cli.backends.impedance import LineImpedanceGains, line_impedance_target
from tergodic_cli.backends.streamed import (DryRunPlan, HardwareRunConfig, dry_run,
                                            explore_with_hardware)

__all__ = ["Camera", "DryRunPlan", "HardwareRunConfig", "Intrinsics", "LineImpedanceGains",
           "deproject", "dry_run", "explore_with_hardware", "line_impedance_target", "make_camera",
           "make_hardware"]
