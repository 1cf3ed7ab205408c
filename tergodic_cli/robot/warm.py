"""The robot's numba kernels: whether numba's disk cache holds them (the line a cold cache says)."""

from __future__ import annotations

from tergodic_cli.explore.warm import _cached

#: The same for the robot's kernels (a PyBullet run).
ROBOT_COMPILE_S = 8

def robot_kernels_line() -> str | None:
    """The line to say before a robot run whose kernels are not in numba's disk cache, else None."""
    try:
        from tergodic_cli.robot import kernels
    except ImportError:
        return None  # the run says what is missing
    if _cached(kernels.pybullet_tick):
        return None
    return f"compiling the robot's kernels (first run only, ~{ROBOT_COMPILE_S} s)"
