"""Capture: a coloured point cloud in metres plus a per-point target weight p.

Entry points: :func:`capture_cloud` (run a :class:`CaptureConfig`),
:func:`load_capture` / :func:`save_capture` (the on-disk artefact).
"""

from tergodic_cli.capture.config import CaptureConfig


def __getattr__(name):  # the readers and filters pull in numpy and open3d: load on first use
    if name in ("Capture", "load_capture", "save_capture"):
        from tergodic_cli.capture import artefact

        return getattr(artefact, name)
    if name == "capture_cloud":
        from tergodic_cli.capture.pipeline import capture_cloud

        return capture_cloud
    raise AttributeError(name)


__all__ = ["Capture", "CaptureConfig", "capture_cloud", "load_capture", "save_capture"]
