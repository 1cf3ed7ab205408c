"""Intel RealSense RGB-D cameras through ``pyrealsense2`` (optional extra ``tergodic[realsense]``)."""

from tergodic_cli.backends.realsense.camera import RealSenseCamera, RealSenseConfig



def make_camera(cfg: RealSenseConfig) -> RealSenseCamera:
    """The registry's factory (backends/registry.py): a RealSense camera, not yet connected."""
    return RealSenseCamera(cfg)


__all__ = ["RealSenseCamera", "RealSenseConfig", "make_camera"]
