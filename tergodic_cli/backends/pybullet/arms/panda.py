"""The Franka Emika Panda (pybullet_data's ``franka_panda/panda.urdf``), its gripper replaced by the sponge.

The paper's sponge sits on the F/T sensor at the flange (V): the fingers become visuals of the hand,
and the massless helper links (panda_link8, panda_grasptarget) are folded into the fixed hand joint,
which stays as the F/T sensor (flange -> hand, rotated -45° about z). Five fewer links make each
physics step ~15 % cheaper; the kinematics to the flange are untouched (checked against pygafro's
Franka to 1e-7 m). Every Panda constant lives here.
"""

from __future__ import annotations

import math
import os
import re

import numpy as np

from tergodic_cli.backends.pybullet.arms import ArmSpec, sponge_ball, tool_inertial
from tergodic_cli.errors import require

JOINTS = tuple(f"panda_joint{i}" for i in range(1, 8))
#: Franka Emika datasheet limits (stricter than the pybullet URDF's).
Q_MIN = np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973])
Q_MAX = np.array([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])
DQ_MAX = np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])
TAU_MAX = np.array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0])
#: The Panda's "ready" pose, from which a wrist camera sees the table in front of the robot.
HOME = (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785)
#: The joint impedance of the set-up moves: stiffness N m/rad, damping N m s/rad.
JOINT_K = (600.0, 600.0, 600.0, 600.0, 250.0, 150.0, 50.0)
JOINT_D = (50.0, 50.0, 50.0, 50.0, 20.0, 15.0, 6.0)
#: Metres, the set-up planner's reach bound per joint (link lengths from the datasheet, + the hand's
#: and hulls' half widths, + the tool).
REACH_BOUND = (1.2, 1.2, 0.9, 0.9, 0.5, 0.5, 0.2)

#: The stock hand's inertial (panda.urdf): 0.81 kg, centre of mass 40 mm along the hand's z.
_HAND_MASS, _HAND_COM_Z, _HAND_INERTIA = 0.81, 0.04, 0.1
_HAND_INERTIAL = r'<inertial>\s*<origin rpy="0 0 0" xyz="0 0 0.04"/>\s*<mass value=".81"/>\s*' \
                 r'<inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/>\s*</inertial>'

_FINGER_VISUALS = """
    <visual><origin rpy="0 0 0" xyz="0 0 0.0584"/><geometry><mesh filename="{m}/visual/finger.obj"/></geometry>
      <material name="panda_white"/></visual>
    <visual><origin rpy="0 0 3.14159265359" xyz="0 0 0.0584"/><geometry><mesh filename="{m}/visual/finger.obj"/></geometry>
      <material name="panda_white"/></visual>
"""


def panda_sponge_urdf(data: str, sponge, arm_collision: bool = True) -> str:
    """The stock ``franka_panda/panda.urdf`` with the gripper replaced by the sponge tool.

    The ball is part of the hand link, not a link of its own behind a fixed joint: PyBullet's
    Featherstone solver walks every link of the chain for each contact row and in the
    articulated-body passes, fixed links included: one link fewer saves a few per cent of a tick
    in contact (docs/robot.md, "Timing"). Mass, centre of mass and inertia are the two bodies combined;
    the only collision shape of the hand is the ball (only the sponge may touch the object).
    """
    meshes = os.path.join(data, "franka_panda", "meshes")
    with open(os.path.join(data, "franka_panda", "panda.urdf")) as fh:
        text = fh.read()
    text = text.replace("package://meshes/", meshes + "/")
    for pattern in (r'<link name="panda_leftfinger">.*?</link>', r'<link name="panda_rightfinger">.*?</link>',
                    r'<joint name="panda_finger_joint1".*?</joint>', r'<joint name="panda_finger_joint2".*?</joint>',
                    r'<link name="panda_grasptarget">.*?</link>', r'<joint name="panda_grasptarget_hand".*?</joint>',
                    r'<joint name="panda_joint8".*?</joint>', r'<link name="panda_link8"\s*/>',
                    r'<link name="panda_link8">.*?</link>'):
        text = re.sub(pattern, "", text, flags=re.S)
    hand = ('<parent link="panda_link8"/>\n    <child link="panda_hand"/>\n'
            '    <origin rpy="0 0 -0.785398163397" xyz="0 0 0"/>')
    require(hand in text and "panda_leftfinger" not in text, "pybullet_data's panda.urdf is not the expected file", "use pybullet 3.2.7")
    text = text.replace(hand, '<parent link="panda_link7"/>\n    <child link="panda_hand"/>\n'
                              '    <origin rpy="0 0 -0.785398163397" xyz="0 0 0.107"/>')
    i0, i1 = text.index('<link name="panda_hand">'), text.index("</link>", text.index('<link name="panda_hand">'))
    hand_link = text[i0:i1]
    inertial = tool_inertial(_HAND_MASS, _HAND_COM_Z, _HAND_INERTIA, sponge)
    sponge_visual, sponge_collision = sponge_ball(sponge)
    hand_link, n_in = re.subn(_HAND_INERTIAL, inertial, hand_link)
    hand_link, n_col = re.subn(r"<collision>.*?</collision>", sponge_collision, hand_link, flags=re.S)
    require(n_in == 1 and n_col == 1, "pybullet_data's panda.urdf is not the expected file", "use pybullet 3.2.7")
    hand_link = re.sub(r"(</visual>)", lambda m: m.group(1) + _FINGER_VISUALS.format(m=meshes) + sponge_visual,
                       hand_link, count=1)
    text = text[:i0] + hand_link + text[i1:]
    if not arm_collision:  # only the sponge has a collision shape
        text = re.sub(r"<collision>.*?</collision>", "", text[:i0], flags=re.S) + text[i0:]
    return text


def collision_parts(data: str) -> list[tuple]:
    """The stock collision hulls of links 0-7 and the hand, and the two closed fingers drawn on the hand
    (they stand 18 mm short of the sponge ball)."""
    mesh = os.path.join(data, "franka_panda", "meshes", "collision")
    z = (0.0, 0.0, 0.0)
    parts = [("panda_link0", None, os.path.join(mesh, "link0.obj"), z, z)]
    parts += [(f"panda_link{i}", f"panda_link{i}", os.path.join(mesh, f"link{i}.obj"), z, z) for i in range(1, 8)]
    parts += [("panda_hand", "panda_hand", os.path.join(mesh, "hand.obj"), z, z),
              ("panda_leftfinger", "panda_hand", os.path.join(mesh, "finger.obj"), (0.0, 0.0, 0.0584), z),
              ("panda_rightfinger", "panda_hand", os.path.join(mesh, "finger.obj"), (0.0, 0.0, 0.0584), (0.0, 0.0, math.pi))]
    return parts


ARM = ArmSpec(name="panda", urdf="franka_panda/panda.urdf", joints=JOINTS, flange="panda_link7", home=HOME,
              joint_gains=(JOINT_K, JOINT_D),
              reach_bound=REACH_BOUND, limits={"q_min": Q_MIN, "q_max": Q_MAX, "dq_max": DQ_MAX, "tau_max": TAU_MAX},
              build=panda_sponge_urdf, tool_link="panda_hand", sensor_joint="panda_hand_joint", parts=collision_parts,
              # the shoulder (joint 2) 0.333 m up; 0.855 m reach to the flange, 0.8 m with the tool on a normal
              reach=((0.0, 0.0, 0.333), 0.8))
