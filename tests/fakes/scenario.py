"""One exploration scenario shared by the hardware tests: a synthetic plate in front of a fake Panda.

The plate (capture frame) is placed with its footprint centre 0.5 m in front of the base; the fake
world's surface is the same cloud in the base frame, so the run's geometry and the "real" one agree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fakes import franky as fake_franky
from fakes.world import FakeWorld

ROBOT_IP = "172.16.0.2"


@dataclass
class Plate:
    capture: object
    basis: object
    T_obj: np.ndarray


def make_plate() -> Plate:
    from tergodic_cli.basis import compute_basis
    from tergodic_cli.capture import CaptureConfig, capture_cloud
    from tergodic_cli.robot.surface import default_object_pose

    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic="plate", voxel=0.005))
    return Plate(cap, compute_basis(cap.points, 40, 30), default_object_pose(cap.points))


def robot_config(plate: Plate, **kw):
    from tergodic_cli.robot import RobotConfig

    return RobotConfig(force=kw.pop("force", 5.0), object_pose=tuple(float(x) for x in plate.T_obj[:3, 3]),
                       hover_height=0.02, **kw)


def explorer(plate: Plate, cfg, seed: int = 0):
    from tergodic_cli.explore import ExploreConfig, Explorer
    from tergodic_cli.robot import robot_explore_config

    ec = robot_explore_config(ExploreConfig(nk=40, seed=seed, agent_radius=0.008), cfg.explore_dt)
    pts = plate.capture.points
    start = pts[np.argmin(np.linalg.norm(pts[:, :2] - [0.03, 0.02], axis=1))][None]
    return Explorer(plate.basis, plate.capture.target, ec, start, on_event=lambda msg: None)


def world(plate: Plate, monkeypatch, **kw) -> FakeWorld:
    """A fake world holding the plate, registered as the robot at ROBOT_IP."""
    from tergodic_cli.backends.pybullet.arms.panda import HOME as PICTURE_Q
    from tergodic_cli.robot.surface import oriented_normals, transform_points

    w = FakeWorld(transform_points(plate.T_obj, plate.capture.points), oriented_normals(plate.capture.points, "up"),
                  np.array(PICTURE_Q), **kw)
    monkeypatch.setattr(fake_franky, "_NETWORK", {ROBOT_IP: w})
    return w
