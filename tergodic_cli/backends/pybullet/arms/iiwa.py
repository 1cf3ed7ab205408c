"""KUKA LBR iiwa (pybullet_data's ``kuka_iiwa/model.urdf``): 7 DoF, the sponge tool on lbr_iiwa_link_7.

Limits: positions and torques from the URDF; its 10 rad/s joint speed is a placeholder, replaced by
the LBR iiwa 14 R820 datasheet's (85, 85, 100, 75, 130, 135, 135 deg/s).
"""

from __future__ import annotations

import numpy as np

from tergodic_cli.backends.pybullet.arms import ArmSpec

ARM = ArmSpec(
    name="iiwa", urdf="kuka_iiwa/model.urdf", joints=tuple(f"lbr_iiwa_joint_{i}" for i in range(1, 8)),
    flange="lbr_iiwa_link_7",
    # The tool straight down at (0.38, 0, 0.5) m, its x-axis along the base's -x (along +x joint 7 would sit
    # at its limit); nearer the base the elbow (joint 4) comes within 0.3 rad of its limit.
    home=(0.0, -0.038, 0.0, -1.751, 0.0, 1.4286, 0.0),
    limits={"dq_max": np.radians([85.0, 85.0, 100.0, 75.0, 130.0, 135.0, 135.0])},
    joint_gains=((600.0, 600.0, 600.0, 600.0, 250.0, 150.0, 50.0), (50.0, 50.0, 50.0, 50.0, 20.0, 15.0, 6.0)),
    # Shoulder to wrist 0.42 + 0.4 m, wrist to flange 0.126 m + the tool 0.14 m, + hull half widths.
    # Reflected rotor inertias (ArmSpec.armature): the Panda's 0.1 kg m² per link, which the gains assume.
    armature=(0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1),
    reach_bound=(1.2, 1.2, 0.9, 0.9, 0.45, 0.45, 0.2),
    # pybullet_data's model has the LBR iiwa 14 R820's geometry (datasheet: A2 0.36 m up, 0.82 m reach
    # to the flange); 0.8 m with the tool on a normal
    reach=((0.0, 0.0, 0.36), 0.8),
)
