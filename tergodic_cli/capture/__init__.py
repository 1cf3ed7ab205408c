"""Capture: a coloured point cloud in metres plus a per-point target weight p.

Entry points: :func:`capture_cloud` (run a :class:`CaptureConfig`),
:func:`load_capture` / :func:`save_capture` (the on-disk artefact).
"""

from tergodic_cli.capture.artefact import Capture, load_capture, save_capture
from tergodic_cli.capture.pipeline import CaptureConfig, capture_cloud

__all__ = ["Capture", "CaptureConfig", "capture_cloud", "load_capture", "save_capture"]
