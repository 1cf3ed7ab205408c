"""Intel RealSense RGB-D cameras through ``pyrealsense2`` (optional extra ``tergodic[realsense]``)."""

from tergodic_cli.backends.realsense.camera import RealSenseCamera, RealSenseConfig

__all__ = ["RealSenseCamera", "RealSenseConfig"]
