"""UFactory xArm 6 (pybullet_data's ``xarm/xarm6_robot.urdf``): 6 DoF, the sponge tool on link6 (the flange).

Limits: the URDF's (positions, 3.14 rad/s, 50/50/32/32/32/20 N m: the datasheet's). Its joints carry
``<dynamics damping="1.0" friction="1.0">``, which PyBullet does not apply to torque-controlled joints;
the scene sets the joint damping to 0 like every arm's.
"""

from __future__ import annotations

from tergodic_cli.backends.pybullet.arms import ArmSpec

ARM = ArmSpec(
    name="xarm6", urdf="xarm/xarm6_robot.urdf", joints=tuple(f"joint{i}" for i in range(1, 7)), flange="link6",
    # The tool straight down at (0.307, 0, 0.448) m, its x-axis along the base's x: the Panda's ready pose.
    home=(0.0, -0.4985, -1.274, 0.0, 1.7725, 0.0),
    # The Panda's joint impedance without its third joint (the xArm's joints 1-3 take 50/50/32 N m).
    joint_gains=((600.0, 600.0, 400.0, 250.0, 150.0, 50.0), (50.0, 50.0, 40.0, 20.0, 15.0, 6.0)),
    # Upper arm 0.29 m, forearm 0.35 m, wrist 0.1 m + the tool 0.14 m, + 0.06 m of hull half widths.
    # Reflected rotor inertias (ArmSpec.armature): the Panda's 0.1 kg m² per link, which the gains assume.
    armature=(0.1, 0.1, 0.1, 0.1, 0.1, 0.1),
    reach_bound=(1.0, 1.0, 0.7, 0.4, 0.35, 0.2),
    # datasheet: the shoulder (joint 2) 0.267 m up, 0.7 m reach
    reach=((0.0, 0.0, 0.267), 0.7),
)
