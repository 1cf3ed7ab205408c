"""Real-hardware backends behind the robot Protocols; each SDK is an optional extra, imported lazily.

- :mod:`~tergodic_cli.hardware.franka`: Franka arms through franky (``tergodic[franka]``);
- :mod:`~tergodic_cli.hardware.bota`: Bota F/T sensors through bota_driver (``tergodic[bota]``);
- :mod:`~tergodic_cli.hardware.netft`: ATI Net F/T over UDP (standard library, no extra);
- :mod:`~tergodic_cli.hardware.realsense`: RealSense cameras through pyrealsense2 (``tergodic[realsense]``);
- :mod:`~tergodic_cli.hardware.camera`: the :class:`Camera` protocol and back-projection;
- :mod:`~tergodic_cli.hardware.impedance`: how the line controller becomes an SDK impedance reference;
- :mod:`~tergodic_cli.hardware.run`: the exploration loop on hardware, and :func:`dry_run`.

Entry points: :func:`make_hardware`, :func:`make_camera`, :func:`explore_with_hardware`, :func:`dry_run`.
"""

from tergodic_cli.hardware.camera import Camera, Intrinsics, RGBDFrame, capture_with_camera, deproject, frame_to_cloud
from tergodic_cli.hardware.extras import import_sdk, install_hint
from tergodic_cli.hardware.factory import make_camera, make_hardware
from tergodic_cli.hardware.impedance import ImpedanceArm, ImpedanceTarget, LineImpedanceGains, line_impedance_target
from tergodic_cli.hardware.run import DryRunPlan, HardwareRun, HardwareRunConfig, dry_run, explore_with_hardware

__all__ = [
    "Camera", "DryRunPlan", "HardwareRun", "HardwareRunConfig", "ImpedanceArm", "ImpedanceTarget", "Intrinsics",
    "LineImpedanceGains", "RGBDFrame", "capture_with_camera", "deproject", "dry_run", "explore_with_hardware",
    "frame_to_cloud", "import_sdk", "install_hint", "line_impedance_target", "make_camera", "make_hardware",
]
