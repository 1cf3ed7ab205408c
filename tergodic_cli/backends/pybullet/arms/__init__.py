"""The simulated arms: one module per arm, one line each in :data:`ARMS` (``--arm``).

An arm module defines one :class:`ArmSpec`: where its URDF lives in pybullet_data, its joints, the
link the tool is fixed to (the flange), its picture posture, and whatever it knows better than its
URDF (datasheet limits, gains tuned for it). The scene loads the URDF with the sponge tool on the
flange (:func:`flange_tool_urdf`: a fixed joint that is the wrist F/T sensor, then the holder and the
sponge ball); :meth:`PyBulletScene.arm_model <tergodic_cli.backends.pybullet.scene.PyBulletScene.arm_model>`
reads the :class:`~tergodic_cli.robot.model.ArmModel` (DoF, limits, chain) back from what PyBullet
loaded. Adding an arm: a module beside these and one line in :data:`ARMS` (docs/robot.md).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from tergodic_cli.errors import require

#: Joint name of the wrist F/T sensor and link name of the sponge tool on a flange (generic arms).
SENSOR_JOINT, TOOL_LINK = "tool_ft_joint", "sponge_tool"
#: The generic tool beyond the flange: F/T sensor and holder, a cylinder (m) of this radius and length
#: along the flange's z, this mass (kg); the sponge ball's centre sits SpongeSpec.offset beyond the flange.
HOLDER_RADIUS, HOLDER_LENGTH, HOLDER_MASS = 0.03, 0.09, 0.35


@dataclass(frozen=True)
class ArmSpec:
    """One simulated arm.

    name : the registry name (``--arm``).
    urdf : its URDF, relative to pybullet_data.
    joints : (n,) its movable joints, base to tip (every non-fixed joint of the URDF).
    flange : the link the tool is fixed to.
    home : (n,) the picture posture, rad (the tool points down over the table in front of the base).
    limits : datasheet limits that replace the URDF's, {"q_min"|"q_max"|"dq_max"|"tau_max": (n,)};
        the others are read from the URDF.
    joint_gains : ((n,) N m/rad, (n,) N m s/rad): the joint impedance of the set-up moves and holds.
    reach_bound : (n,) m, an upper bound on the distance of any point of the arm and tool from joint
        i's axis (the set-up planner's conservative advancement).
    gains : :class:`~tergodic_cli.robot.controller.ControllerGains` fields tuned for this arm (used when
        the run keeps the default gains).
    build : (pybullet_data folder, SpongeSpec, arm_collision) -> URDF text with the tool; None:
        :func:`flange_tool_urdf`.
    armature : (n,) kg m², each joint's reflected rotor inertia (motor and gearbox), added to its child
        link about the joint axis. The controller's gains assume the Panda's wrist: pybullet_data's Panda
        gives every link 0.1 kg m² (its wrist responds like that), where a bare 6-DoF wrist with a 0.4 kg tool
        has ~3e-4 kg m² about its last axis, and the 1 kHz loop's damping (joint impedance 6 N m s/rad,
        task 2 N m s/rad) then exceeds the explicit step's stability bound (I > D dt / 2).
    tool_link, sensor_joint : the link carrying the sponge ball (the F/T sensor reports in its inertial
        frame) and the fixed joint flange -> tool that is the sensor.
    reach : ((3,) m, m) the shoulder and the distance from it the tool works at (datasheet); None: not checked.
    parts : (pybullet_data folder) -> [(part name, link name or None for the base, mesh file, pos (3,),
        rpy (3,))]: the convex pieces the whole-arm checks watch, the base's first (the table's hole is
        its footprint); None: every collision mesh of the URDF.
    """

    name: str
    urdf: str
    joints: tuple[str, ...]
    flange: str
    home: tuple[float, ...]
    joint_gains: tuple[tuple[float, ...], tuple[float, ...]]
    reach_bound: tuple[float, ...]
    limits: dict = field(default_factory=dict)
    gains: dict = field(default_factory=dict)
    armature: tuple[float, ...] = ()
    build: Callable | None = None
    tool_link: str = TOOL_LINK
    sensor_joint: str = SENSOR_JOINT
    parts: Callable | None = None
    #: ((3,) shoulder in the base frame, m; distance from it the tool works at, m), from the datasheet:
    #: the rough check that refuses an object out of reach before the reach map (surface.check_reachable).
    reach: tuple | None = None

    def urdf_text(self, data: str, sponge, arm_collision: bool = False) -> str:
        """The arm's URDF with the sponge tool (collision shapes on the arm's links with ``arm_collision``)."""
        if self.build is not None:
            return self.build(data, sponge, arm_collision)
        return flange_tool_urdf(os.path.join(data, self.urdf), self.flange, sponge, arm_collision,
                                dict(zip(self.joints, self.armature)) if self.armature else None)

    def collision_parts(self, data: str) -> list[tuple]:
        if self.parts is not None:
            return self.parts(data)
        return urdf_collision_parts(self.urdf_text(data, _Sponge0(), True))


@dataclass
class _Sponge0:  # a placeholder sponge for reading the arm's own collision meshes
    offset: float = 0.1
    radius: float = 0.01
    mass: float = 0.0


def tool_inertial(mass: float, com_z: float, inertia: float, sponge) -> str:
    """URDF ``<inertial>`` of a link (``mass`` kg, centre of mass ``com_z`` m along its z, inertia
    ``inertia`` kg m² about each axis) carrying the sponge ball ``sponge.offset`` along its z: the two
    bodies combined (parallel axes)."""
    m = mass + sponge.mass
    cz = (mass * com_z + sponge.mass * sponge.offset) / m
    i_s = 0.4 * sponge.mass * sponge.radius ** 2  # solid ball
    ixx = inertia + mass * (com_z - cz) ** 2 + i_s + sponge.mass * (sponge.offset - cz) ** 2
    izz = inertia + i_s
    return (f'<inertial><origin rpy="0 0 0" xyz="0 0 {cz:.9f}"/><mass value="{m:.9f}"/>'
            f'<inertia ixx="{ixx:.9f}" ixy="0" ixz="0" iyy="{ixx:.9f}" iyz="0" izz="{izz:.9f}"/></inertial>')


def sponge_ball(sponge) -> tuple[str, str]:
    """(visual, collision) URDF of the sponge ball on its link."""
    ball = f'<origin rpy="0 0 0" xyz="0 0 {sponge.offset}"/><geometry><sphere radius="{sponge.radius}"/></geometry>'
    return (f'<visual>{ball}<material name="sponge_yellow"><color rgba="0.95 0.8 0.2 1"/></material></visual>',
            f"<collision>{ball}</collision>")


def absolute_meshes(text: str, folder: str) -> str:
    """Mesh file names of a URDF made absolute: ``package://x/...`` and relative names from ``folder``."""
    def fix(m):
        name = m.group(1)
        name = name[len("package://"):] if name.startswith("package://") else name
        return f'filename="{name if os.path.isabs(name) else os.path.join(folder, name)}"'

    return re.sub(r'filename="([^"]+)"', fix, text)


def physical_inertias(text: str) -> str:
    """Every ``<inertia>`` of a URDF that breaks the triangle inequality of principal moments (I1 + I2 >= I3,
    which PyBullet enforces by zeroing the link's inertia: the xArm 6's link2 and link3) raised by the
    smallest isotropic term that meets it; its principal axes are kept."""
    def fix(m):
        vals = {k: float(v) for k, v in re.findall(r'(i[xyz]{2})="([^"]+)"', m.group(0))}
        I = np.array([[vals["ixx"], vals["ixy"], vals["ixz"]], [vals["ixy"], vals["iyy"], vals["iyz"]],
                      [vals["ixz"], vals["iyz"], vals["izz"]]])
        lam = np.linalg.eigvalsh(I)
        add = max(0.0, lam[2] - lam[0] - lam[1]) * 1.01
        if add == 0.0:
            return m.group(0)
        I = I + add * np.eye(3)
        return (f'<inertia ixx="{I[0, 0]:.9g}" ixy="{I[0, 1]:.9g}" ixz="{I[0, 2]:.9g}" iyy="{I[1, 1]:.9g}" '
                f'iyz="{I[1, 2]:.9g}" izz="{I[2, 2]:.9g}"/>')

    return re.sub(r"<inertia\s[^>]*/>", fix, text)


def add_armature(text: str, armature: dict) -> str:
    """The URDF with each joint's reflected rotor inertia ``armature[joint]`` (kg m²) added to its child link
    (PyBullet has no armature of its own), as an isotropic inertia: a term about the joint axis alone would
    break the principal moments' triangle inequality, and PyBullet zeroes such a link's inertia."""
    # each joint's child link, then that link's inertia
    child = dict(re.findall(r'<joint name="([^"]+)"[^>]*>.*?<child link="([^"]+)"', text, flags=re.S))
    by_link = {child[j]: a for j, a in armature.items() if j in child}

    def link(m):
        a = by_link.get(m.group(1), 0.0)
        if not a:
            return m.group(0)
        return re.sub(r"<inertia\s[^>]*/>", lambda k: re.sub(
            r'(i(?:xx|yy|zz))="([^"]+)"', lambda v: f'{v.group(1)}="{float(v.group(2)) + a:.9g}"', k.group(0)),
            m.group(0))

    return re.sub(r'<link name="([^"]+)">.*?</link>', link, text, flags=re.S)


def flange_tool_urdf(path: str, flange: str, sponge, arm_collision: bool = False, armature: dict | None = None) -> str:
    """The URDF at ``path`` with the sponge tool fixed to ``flange``: a fixed joint (the wrist F/T
    sensor, :data:`SENSOR_JOINT`), then one link (:data:`TOOL_LINK`) carrying the holder (a cylinder,
    :data:`HOLDER_RADIUS` × :data:`HOLDER_LENGTH`, :data:`HOLDER_MASS`) and the sponge ball, its only
    collision shape in the physics (the holder is checked, collision.py). Without ``arm_collision`` the
    arm's links have no collision shapes (every contact but the sponge's is checked, not simulated).
    ``armature`` {joint: kg m²}: reflected rotor inertias (:func:`add_armature`)."""
    with open(path) as fh:
        text = physical_inertias(absolute_meshes(fh.read(), os.path.dirname(path)))
    if armature:
        text = add_armature(text, armature)
    require(f'<link name="{flange}"' in text, f"{os.path.basename(path)} has no link '{flange}'", "check the arm's flange")
    if not arm_collision:
        text = re.sub(r"<collision>.*?</collision>", "", text, flags=re.S)
    L = HOLDER_LENGTH
    inertia = HOLDER_MASS * (3 * HOLDER_RADIUS ** 2 + L ** 2) / 12
    visual, collision = sponge_ball(sponge)
    holder = (f'<origin rpy="0 0 0" xyz="0 0 {L / 2}"/><geometry><cylinder radius="{HOLDER_RADIUS}" length="{L}"/>'
              '</geometry>')
    tool = (f'<link name="{TOOL_LINK}">{tool_inertial(HOLDER_MASS, L / 2, inertia, sponge)}'
            f'<visual>{holder}<material name="holder_grey"><color rgba="0.3 0.3 0.32 1"/></material></visual>'
            f'{visual}{collision}</link>'
            f'<joint name="{SENSOR_JOINT}" type="fixed"><parent link="{flange}"/><child link="{TOOL_LINK}"/>'
            '<origin rpy="0 0 0" xyz="0 0 0"/></joint>')
    return text.replace("</robot>", tool + "</robot>")


def urdf_collision_parts(text: str) -> list[tuple]:
    """[(part name, link name, mesh file, pos (3,), rpy (3,))] of every mesh collision shape of a URDF, in
    the file's order (the base's first; the root link, no joint's child, with link name None)."""
    import xml.etree.ElementTree as ET

    root = ET.fromstring(text)
    children = {j.find("child").get("link") for j in root.findall("joint")}
    out = []
    for link in root.findall("link"):
        name = link.get("name")
        for k, col in enumerate(link.findall("collision")):
            mesh = col.find("geometry/mesh")
            if mesh is None:
                continue
            o = col.find("origin")
            xyz = [float(x) for x in (o.get("xyz", "0 0 0") if o is not None else "0 0 0").split()]
            rpy = [float(x) for x in (o.get("rpy", "0 0 0") if o is not None else "0 0 0").split()]
            out.append((name if k == 0 else f"{name}_{k}", None if name not in children else name,
                        mesh.get("filename"), tuple(xyz), tuple(rpy)))
    return out


def mesh_vertices(path: str) -> np.ndarray:
    """(k, 3) the vertices of a mesh file (.obj read directly; other formats through open3d)."""
    if path.endswith(".obj"):
        with open(path) as fh:
            return np.array([[float(v) for v in ln.split()[1:4]] for ln in fh if ln.startswith("v ")])
    import open3d as o3d

    return np.asarray(o3d.io.read_triangle_mesh(path).vertices, dtype=float)


from tergodic_cli.backends.pybullet.arms import iiwa, panda, xarm6  # noqa: E402  (the arms register below)

#: Every simulated arm, by name: one line each.
ARMS: dict[str, ArmSpec] = {
    "panda": panda.ARM,
    "xarm6": xarm6.ARM,
    "iiwa": iiwa.ARM,
}


def get_arm(name: str) -> ArmSpec:
    """The arm called ``name``; an unknown name is refused in one line naming the choices (exit 2)."""
    require(name in ARMS, f"unknown arm '{name}'", f"use --arm {' or '.join(ARMS)}")
    return ARMS[name]


__all__ = ["ARMS", "ArmSpec", "get_arm", "flange_tool_urdf", "tool_inertial", "urdf_collision_parts"]
