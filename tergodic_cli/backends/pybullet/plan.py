"""Collision-free set-up moves: a checking world beside the physics and an OMPL joint-space planner.

The set-up moves (picture -> hover, move-over transits, back to the picture pose) are joint-space
moves through free space. A straight joint-space line between two postures can sweep the arm or
the sponge through the object (issue 24: 42 N on a duck, 103 N on a bowl placed high), so every
such move is planned and checked before it starts:

- :class:`CollisionWorld`: a second PyBullet client (DIRECT) holding the arm with a collision
  shape on every link (the tool link's pieces, the sponge ball as a link of its own) and a
  copy of **every body of the physics scene but the arm** (the object; a table or stand as soon
  as the scene has one), their poses synchronised before each plan. The physics scene is never
  touched: no state to save or restore, nothing a run could notice.
- A posture is *clear* when every arm link stays :data:`LINK_MARGIN` from every obstacle and the
  sponge ball :data:`SPONGE_MARGIN` (the ball's only business near the object is the final approach,
  which runs along the surface normal and is not planned here), and the hand and the ball stay
  :data:`SELF_MARGIN` off the base and the first moving link (self-collision).
- :func:`plan_path`: the straight joint-space line when it is clear, else OMPL's RRTConnect in the
  n-D joint box (the guard's limits) with the margins + :data:`PLAN_SLACK` as the state validity
  checker (motions checked every :data:`CHECK_STEP` rad), OMPL's path simplifier (shortcuts, B-spline
  smoothing). Lines and planned paths are then certified by conservative advancement
  (:meth:`CollisionWorld.segment_slack`): from a posture whose clearance beats the margin by e, the
  next check is e / sum_i |dq_i| R_i further on (the arm module's ``reach_bound``), so no point of the arm can
  come nearer than the margin between two checks (steps never below :data:`DENSE_STEP`).
- :func:`retreat_clear`: a retreat (the tool backing off along its axis) stops where an arm link would
  come closer to a body than it started.

The joint impedance follows its min-jerk reference to ~1 mm in free space, well inside the margins.
"""

from __future__ import annotations

import math
import os
import re
import tempfile
from contextlib import suppress
from dataclasses import dataclass

import numpy as np

#: Metres every arm link (hand, fingers included) keeps from every obstacle during a set-up move.
LINK_MARGIN = 0.015
#: Metres the sponge ball keeps from every obstacle during a set-up move (it ends at the hover pose,
#: hover_height = 40 mm above the start along the normal; the approach is the only way in).
SPONGE_MARGIN = 0.010
#: Metres the hand and the ball keep from the base and link 1 (self-collision).
SELF_MARGIN = 0.005
#: Extra metres the planner demands, so the dense re-check (finer steps) still finds the margins.
PLAN_SLACK = 0.005
#: Radians (largest joint's change) between checked postures while planning.
CHECK_STEP = 0.01
#: Radians between postures of the dense re-check of a planned path (the shortest certified step).
DENSE_STEP = 0.0025
#: Metres beyond the margins the checks measure the clearance. The certified step grows with it, but a
#: link's hull against a trimesh costs more the more triangles lie within reach: the duck's move to
#: hover, certified, took 32 ms at 0.02 (147 checks), 246 ms at 0.05 (64), 1.8 s at 0.08 (51).
PROBE = 0.02
#: Seconds OMPL may search for one move (the bowl at z = 0.6 m: 1.7 s in all, simplification and
#: certification included, on a loaded machine; a straight line is certified in tens of ms).
PLAN_TIME_S = 1.5
#: Seconds OMPL's simplifier may shorten and smooth a found path.
SIMPLIFY_TIME_S = 0.3
#: Metres between the checked postures of a retreat (the tool backs off along its axis).
RETREAT_STEP = 0.005
#: Metres a retreat always goes, whatever the check says: the sponge leaves the surface.
RETREAT_LEAST = 0.02
#: Metres: when an end of a move is itself closer than the margins (a retreat that ended near a rim),
#: the move is held to that end's own clearance; an end with the ball within END_FLOOR of a body (a
#: link within LINK_MARGIN - SPONGE_MARGIN + END_FLOOR = 8 mm) is refused.
END_FLOOR = 0.003

_GEOM_SPHERE, _GEOM_BOX, _GEOM_CYLINDER, _GEOM_MESH, _GEOM_PLANE, _GEOM_CAPSULE = 2, 3, 4, 5, 6, 7


def hull_meshes(text: str, out: str) -> str:
    """The URDF ``text`` with every collision mesh replaced by its convex hull's vertices only, written to
    ``out``: PyBullet hulls a mesh's every vertex (the Panda's links 4-7: 600-966), and its distance
    queries walk them all; the hull's own vertices (102-260) give the same shape at 3-4 times less cost
    per query."""
    from scipy.spatial import ConvexHull

    from tergodic_cli.backends.pybullet.arms import mesh_vertices

    done: dict[str, str] = {}

    def hull(m):
        src = m.group(1)
        if src not in done:
            V = mesh_vertices(src)
            h = ConvexHull(V)
            keep = np.sort(h.vertices)
            faces = np.searchsorted(keep, h.simplices) + 1  # 1-based, into the kept vertices
            dst = os.path.join(out, f"{len(done)}_{os.path.splitext(os.path.basename(src))[0]}.obj")
            with open(dst, "w") as fh:
                fh.writelines(f"v {x:.7f} {y:.7f} {z:.7f}\n" for x, y, z in V[keep])
                fh.writelines(f"f {a} {b} {c}\n" for a, b, c in faces)
            done[src] = dst
        return f'<mesh filename="{done[src]}"'

    def per_collision(m):
        return re.sub(r'<mesh filename="([^"]+)"', hull, m.group(0))

    return re.sub(r"<collision>.*?</collision>", per_collision, text, flags=re.S)


def checking_urdf(spec, data: str, sponge, meshes: str) -> str:
    """The simulated arm (``spec``: :class:`~tergodic_cli.backends.pybullet.arms.ArmSpec`, its URDF with
    the sponge tool) with a collision shape on every link: the arm's own collision meshes as their hulls
    (written to ``meshes``, :func:`hull_meshes`), the tool link's pieces (the Panda's hand and fingers, a
    generic tool's holder), and the sponge ball as a link of its own (``sponge_ball``, fixed to the tool
    link) so it keeps its own margin. Kinematics unchanged."""
    from tergodic_cli.backends.pybullet.arms import HOLDER_LENGTH, HOLDER_RADIUS

    text = spec.urdf_text(data, sponge, arm_collision=True)
    tool = spec.tool_link
    i0 = text.index(f'<link name="{tool}">')
    i1 = text.index("</link>", i0)
    pieces = []
    for _name, link, path, pos, rpy in spec.collision_parts(data):
        if link == tool:
            pieces.append(f'<collision><origin rpy="{rpy[0]} {rpy[1]} {rpy[2]}" xyz="{pos[0]} {pos[1]} {pos[2]}"/>'
                          f'<geometry><mesh filename="{path}"/></geometry></collision>')
    if spec.build is None:  # the generic tool's holder (arms.flange_tool_urdf)
        pieces.append(f'<collision><origin rpy="0 0 0" xyz="0 0 {HOLDER_LENGTH / 2}"/><geometry><cylinder '
                      f'radius="{HOLDER_RADIUS}" length="{HOLDER_LENGTH}"/></geometry></collision>')
    hand = re.sub(r"<collision>.*?</collision>", "", text[i0:i1], flags=re.S) + "".join(pieces)
    ball = (f'<link name="sponge_ball"><inertial><origin rpy="0 0 0" xyz="0 0 0"/><mass value="0.01"/>'
            f'<inertia ixx="1e-6" ixy="0" ixz="0" iyy="1e-6" iyz="0" izz="1e-6"/></inertial>'
            f'<collision><origin rpy="0 0 0" xyz="0 0 {sponge.offset}"/><geometry><sphere radius="{sponge.radius}"/>'
            '</geometry></collision></link>'
            f'<joint name="sponge_ball_joint" type="fixed"><parent link="{tool}"/><child link="sponge_ball"/>'
            '<origin rpy="0 0 0" xyz="0 0 0"/></joint>')
    text = text[:i0] + hand + text[i1:]
    return hull_meshes(text.replace("</robot>", ball + "</robot>"), meshes)


@dataclass
class Plan:
    """A checked joint-space path.

    path : (m, n) postures (rad), first the start, last the goal; straight lines between them.
    clearance : m, the smallest obstacle distance minus its margin over the dense re-check (>= 0 when
        the margins hold; a relaxed end, see :data:`END_FLOOR`, can make it negative down to its floor).
    planner : "straight" or "RRTConnect". seconds : wall time spent planning.
    """

    path: np.ndarray
    clearance: float
    planner: str
    seconds: float


class CollisionWorld:
    """The arm and copies of the physics scene's other bodies, in a PyBullet client of their own.

    Parameters
    ----------
    scene : the :class:`~tergodic_cli.backends.pybullet.scene.PyBulletScene` whose non-arm bodies are
        the obstacles (None: an empty world, add obstacles with :meth:`add_box`).
    sponge : the tool's :class:`SpongeSpec` (default: the scene's). arm : the arm's name or spec (default:
        the scene's, else "panda").

    ``reach_bound`` (n,), m: an upper bound on the distance of any point of the arm and tool from joint
    i's axis (the arm's module): a joint step dq moves no point further than sum_i |dq_i| R_i.
    """

    def __init__(self, scene=None, sponge=None, arm=None):
        from tergodic_cli.backends.pybullet.arms import ArmSpec, get_arm
        from tergodic_cli.backends.pybullet.camera import quiet_native_output
        from tergodic_cli.robot.config import SpongeSpec

        with quiet_native_output():
            import pybullet as p
            import pybullet_data

        self.p = p
        self.cid = p.connect(p.DIRECT)
        self.sponge = sponge or (scene.sponge if scene is not None else SpongeSpec())
        spec = arm if isinstance(arm, ArmSpec) else get_arm(arm) if arm else scene.spec if scene is not None \
            else get_arm("panda")
        self.spec = spec
        self.reach_bound = np.asarray(spec.reach_bound, dtype=float)
        with tempfile.TemporaryDirectory(prefix="tergodic_check_") as tmp:
            path = os.path.join(tmp, "arm.urdf")
            with open(path, "w") as fh:
                fh.write(checking_urdf(spec, pybullet_data.getDataPath(), self.sponge, tmp))
            self.robot = p.loadURDF(path, useFixedBase=True, physicsClientId=self.cid)
        n = p.getNumJoints(self.robot, physicsClientId=self.cid)
        infos = [p.getJointInfo(self.robot, j, physicsClientId=self.cid) for j in range(n)]
        names = {info[1].decode(): j for j, info in enumerate(infos)}
        links = {info[12].decode(): j for j, info in enumerate(infos)}
        self.joints = [names[j] for j in spec.joints]
        self.ball = links["sponge_ball"]
        #: (n_links + 1,) margin per link index + 1 (index 0: the base, link0, which never moves: not checked).
        self.margin = np.full(n + 1, LINK_MARGIN)
        self.margin[self.ball + 1] = SPONGE_MARGIN
        # Links fixed to the base (the xArm's link_base behind its world joint) never move: like the base
        # itself (index -1), not checked (the table's hole is their footprint).
        self.margin[[j + 1 for j in range(n) if not set(self._chain(j, infos)) & set(self.joints)]] = -np.inf
        distal = [links[spec.tool_link], self.ball]
        proximal = [-1, self.joints[0]]  # the base and the first moving link
        self.self_pairs = [(a, b) for a in distal for b in proximal]
        self.obstacles: dict[tuple[int, int], int] = {}  # (scene body, link) -> our body
        self.extra: list[int] = []  # bodies added here only (tests, a planning table)
        self.scene = scene
        self.checks = 0
        if scene is not None:
            self.sync()

    @staticmethod
    def _chain(j: int, infos) -> list[int]:
        """Link ``j`` and its ancestors (joint infos' parent indices)."""
        out = []
        while j >= 0:
            out.append(j)
            j = infos[j][16]
        return out

    # ------------------------------------------------------------------ obstacles
    def sync(self) -> None:
        """Copy every body of the scene but the arm (new ones), and move the copies to their bodies' poses."""
        sp, scid = self.scene.p, self.scene.cid
        for i in range(sp.getNumBodies(physicsClientId=scid)):
            body = sp.getBodyUniqueId(i, physicsClientId=scid)
            if body == self.scene.robot:
                continue
            for link in range(-1, sp.getNumJoints(body, physicsClientId=scid)):
                if link < 0:
                    pos, orn = sp.getBasePositionAndOrientation(body, physicsClientId=scid)
                else:
                    st = sp.getLinkState(body, link, computeForwardKinematics=True, physicsClientId=scid)
                    pos, orn = st[0], st[1]
                key = (body, link)
                if key not in self.obstacles:
                    shapes = sp.getCollisionShapeData(body, link, physicsClientId=scid)
                    if not shapes:
                        continue
                    self.obstacles[key] = self._copy(body, shapes)
                self.p.resetBasePositionAndOrientation(self.obstacles[key], pos, orn, physicsClientId=self.cid)

    def _copy(self, body: int, shapes) -> int:
        """A static body here with the collision shapes ``shapes`` (getCollisionShapeData rows)."""
        from tergodic_cli.errors import TergodicError

        p, cid = self.p, self.cid
        cols, poss, orns = [], [], []
        for s in shapes:
            geom, dims, fname, lpos, lorn = s[2], s[3], s[4], s[5], s[6]
            fname = fname.decode() if isinstance(fname, bytes) else fname
            if geom == _GEOM_BOX:
                c = p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.5 * x for x in dims], physicsClientId=cid)
            elif geom == _GEOM_SPHERE:
                c = p.createCollisionShape(p.GEOM_SPHERE, radius=dims[0], physicsClientId=cid)
            elif geom in (_GEOM_CYLINDER, _GEOM_CAPSULE):
                c = p.createCollisionShape(p.GEOM_CYLINDER if geom == _GEOM_CYLINDER else p.GEOM_CAPSULE,
                                           radius=dims[1], height=dims[0], physicsClientId=cid)
            elif geom == _GEOM_PLANE:
                c = p.createCollisionShape(p.GEOM_PLANE, planeNormal=list(dims), physicsClientId=cid)
            elif geom == _GEOM_MESH and fname and fname != "unknown_file":
                c = p.createCollisionShape(p.GEOM_MESH, fileName=fname, meshScale=list(dims), physicsClientId=cid)
            elif geom == _GEOM_MESH and body in getattr(self.scene, "mesh_data", {}):
                V, F = self.scene.mesh_data[body]
                c = p.createCollisionShape(p.GEOM_MESH, vertices=np.asarray(V, float).tolist(),
                                           indices=np.asarray(F, np.int64).ravel().tolist(),
                                           flags=p.GEOM_FORCE_CONCAVE_TRIMESH, physicsClientId=cid)
            else:  # a body the set-up moves could not avoid: refuse rather than plan blind
                raise TergodicError(f"the collision check cannot copy body {body} of the scene (shape type {geom})",
                                    "add its vertices to the scene's mesh_data when creating it")
            cols.append(c)
            poss.append(list(lpos))
            orns.append(list(lorn))
        if len(cols) == 1 and not any(poss[0]) and list(orns[0]) == [0.0, 0.0, 0.0, 1.0]:
            return p.createMultiBody(0.0, cols[0], -1, physicsClientId=cid)
        # Shapes offset in their body: a massless base with each shape on a fixed link at its local frame.
        n = len(cols)
        b = p.createMultiBody(0.0, -1, -1, linkMasses=[0.0] * n, linkCollisionShapeIndices=cols,
                              linkVisualShapeIndices=[-1] * n, linkPositions=poss, linkOrientations=orns,
                              linkInertialFramePositions=[[0, 0, 0]] * n, linkInertialFrameOrientations=[[0, 0, 0, 1]] * n,
                              linkParentIndices=[0] * n, linkJointTypes=[p.JOINT_FIXED] * n,
                              linkJointAxis=[[0, 0, 1]] * n, physicsClientId=cid)
        return b

    def add_box(self, half_extents, pose: np.ndarray) -> int:
        """A box obstacle (half extents (3,) m) at ``pose`` (4, 4), here only (tests, a planning table)."""
        from tergodic_cli.robot.ga import matrix_to_quat

        p, cid = self.p, self.cid
        c = p.createCollisionShape(p.GEOM_BOX, halfExtents=list(map(float, half_extents)), physicsClientId=cid)
        b = p.createMultiBody(0.0, c, -1, basePosition=pose[:3, 3].tolist(),
                              baseOrientation=matrix_to_quat(pose[:3, :3]).tolist(), physicsClientId=cid)
        self.extra.append(b)
        return b

    def bodies(self) -> list[int]:
        return list(self.obstacles.values()) + self.extra

    # ------------------------------------------------------------------ checks
    def set_q(self, q: np.ndarray) -> None:
        self.p.resetJointStatesMultiDof(self.robot, self.joints, [[float(x)] for x in q], physicsClientId=self.cid)

    def slack(self, q: np.ndarray, reach: float = 0.0, ball: bool = True) -> float:
        """Metres: the smallest (distance - margin) over every arm link against every obstacle, and the
        self-collision pairs against :data:`SELF_MARGIN`, at the posture ``q`` (n,). Only distances up to
        the margins + ``reach`` are looked at; beyond that it returns ``reach`` (clear by at least that).
        ``ball`` False: the sponge ball against the obstacles is left out."""
        p, cid, rob = self.p, self.cid, self.robot
        self.checks += 1
        self.set_q(q)
        best = reach
        far = float(LINK_MARGIN + reach)
        skip = -1 if ball else self.ball  # without the ball: a retreat starts with it touching
        for b in self.bodies():
            for c in p.getClosestPoints(rob, b, far, physicsClientId=cid):
                la = c[3]
                if la >= 0 and la != skip:
                    best = min(best, c[8] - self.margin[la + 1])
        for a, b in self.self_pairs:
            for c in p.getClosestPoints(rob, rob, SELF_MARGIN + reach, a, b, physicsClientId=cid):
                best = min(best, c[8] - SELF_MARGIN)
        return best

    def clearance(self, q: np.ndarray, upto: float = 0.06) -> tuple[float, str]:
        """(m, which link): the smallest distance of any arm link to any obstacle at ``q`` (n,), up to ``upto``
        (beyond: (upto, "")). A far reach costs: a hull against a trimesh walks every triangle in reach."""
        p, cid, rob = self.p, self.cid, self.robot
        self.set_q(q)
        best, which = upto, ""
        for b in self.bodies():
            for c in p.getClosestPoints(rob, b, upto, physicsClientId=cid):
                if c[3] >= 0 and np.isfinite(self.margin[c[3] + 1]) and c[8] < best:
                    best, which = c[8], p.getJointInfo(rob, c[3], physicsClientId=cid)[12].decode()
        return best, which

    def segment_slack(self, q0: np.ndarray, q1: np.ndarray, need: float = 0.0, step: float | None = None) -> float:
        """The smallest :meth:`slack` along the straight joint-space segment ``q0`` -> ``q1`` (n,), or a value
        below ``need`` as soon as one posture falls below it.

        ``step`` (rad, largest joint): check postures that far apart, ends included. None: certified
        steps (conservative advancement): from a posture whose slack exceeds ``need`` by e, the next is
        e / sum_i |dq_i| R_i further on (the arm module's ``reach_bound``), so no point of the arm can have come
        closer than ``need`` in between; never shorter than :data:`DENSE_STEP`.
        """
        q0, q1 = np.asarray(q0, float), np.asarray(q1, float)
        dq = q1 - q0
        span = float(np.max(np.abs(dq)))
        if step is not None:
            n = max(1, int(math.ceil(span / step)))
            worst = math.inf
            for s in np.linspace(0.0, 1.0, n + 1):
                worst = min(worst, self.slack(q0 + s * dq, PROBE))
                if worst < need:
                    break
            return worst
        rate = float(np.abs(dq) @ self.reach_bound)  # m of arm motion per unit of the segment's parameter, at most
        t_min = DENSE_STEP / span if span > 0 else 1.0
        t, worst = 0.0, math.inf
        while True:
            sl = self.slack(q0 + t * dq, PROBE)
            worst = min(worst, sl)
            if sl < need or t >= 1.0:
                return worst
            t = min(1.0, t + max(t_min, (sl - need) / rate if rate > 0 else 1.0))

    def path_slack(self, path: np.ndarray, need: float = 0.0, step: float | None = None) -> float:
        """The smallest :meth:`segment_slack` over the straight joint-space segments of ``path`` (m, n)."""
        return min(self.segment_slack(a, b, need, step) for a, b in zip(path[:-1], path[1:]))

    def close(self) -> None:
        if self.cid >= 0:
            with suppress(self.p.error):
                self.p.disconnect(physicsClientId=self.cid)
            self.cid = -1


def plan_path(world: CollisionWorld, q0: np.ndarray, q1: np.ndarray, q_lo: np.ndarray, q_hi: np.ndarray,
              seed: int = 0, time_s: float = PLAN_TIME_S, inside=None) -> tuple[Plan | None, str | None]:
    """A checked joint-space path from ``q0`` to ``q1`` (n,) inside the joint box [q_lo, q_hi] (n,).

    The straight line when it keeps the margins (certified, :meth:`CollisionWorld.segment_slack`); else
    OMPL's RRTConnect with the margins + :data:`PLAN_SLACK` as its validity check (every
    :data:`CHECK_STEP` rad), simplified, then certified like the line. When an end itself is closer
    than the margins (but at least :data:`END_FLOOR` clear), the whole move is held to that end's
    clearance instead. ``inside(q) -> bool``, when given, must hold at every posture of the path too
    (checked every :data:`CHECK_STEP` rad: the TCP in the guard's workspace box, which a move that
    leaves it would fault on). Returns (plan, None) or (None, the reason in a few words).
    """
    import time

    t0 = time.perf_counter()
    q0, q1 = np.asarray(q0, float), np.asarray(q1, float)
    s0, s1 = world.slack(q0, PLAN_SLACK), world.slack(q1, PLAN_SLACK)
    need = min(0.0, s0, s1)  # relaxed to the ends' own clearance
    if need < END_FLOOR - SPONGE_MARGIN:
        which, q = ("goal", q1) if s1 <= s0 else ("start", q0)
        d, link = world.clearance(q)
        return None, f"the {which} posture has its {link} {1e3 * d:.0f} mm from an obstacle"
    if inside is not None and not (inside(q0) and inside(q1)):
        return None, f"the {'start' if not inside(q0) else 'goal'} posture has the tool outside the workspace box"
    line = world.segment_slack(q0, q1, need)
    if line >= need and _stays_inside(inside, np.array([q0, q1])):
        return Plan(np.array([q0, q1]), line, "straight", time.perf_counter() - t0), None
    if not (np.all(q0 >= q_lo) and np.all(q0 <= q_hi) and np.all(q1 >= q_lo) and np.all(q1 <= q_hi)):
        return None, "an end of the move is outside the joint limits"
    path = _rrt_connect(world, q0, q1, np.asarray(q_lo, float), np.asarray(q_hi, float),
                        lambda q: world.slack(q, PLAN_SLACK) >= need + PLAN_SLACK and (inside is None or inside(q)),
                        seed, time_s)
    if path is None:
        return None, f"no collision-free path found in {time_s:g} s"
    s = world.path_slack(path, need)
    if s < need:
        return None, f"the planned path comes within {1e3 * max(0.0, s + SPONGE_MARGIN):.0f} mm of an obstacle"
    if not _stays_inside(inside, path):
        return None, "the planned path takes the tool outside the workspace box"
    return Plan(path, s, "RRTConnect", time.perf_counter() - t0), None


def _stays_inside(inside, path: np.ndarray) -> bool:
    """Whether ``inside(q)`` holds every :data:`CHECK_STEP` rad along the straight segments of ``path`` (m, n)."""
    if inside is None:
        return True
    for a, b in zip(path[:-1], path[1:]):
        k = max(1, int(np.ceil(np.max(np.abs(b - a)) / CHECK_STEP)))
        if not all(inside(a + s * (b - a)) for s in np.linspace(0.0, 1.0, k + 1)):
            return False
    return True


def _rrt_connect(world, q0, q1, lo, hi, valid, seed: int, time_s: float):
    """OMPL RRTConnect in the joint box [lo, hi] (n,) with ``valid(q)`` as its state validity checker.
    Returns the simplified path (m, n) or None."""
    from ompl import base as ob, geometric as og, util as ou

    ou.setLogLevel(ou.LOG_NONE)
    with suppress(Exception):
        ou.RNG.setSeed(int(seed) + 1)  # OMPL takes the global seed once per process, before its first use
    n = len(q0)
    space = ob.RealVectorStateSpace(n)
    bounds = ob.RealVectorBounds(n)
    for i in range(n):
        bounds.setLow(i, float(lo[i]))
        bounds.setHigh(i, float(hi[i]))
    space.setBounds(bounds)
    ss = og.SimpleSetup(space)
    ss.setStateValidityChecker(lambda st: bool(valid(np.array([st[i] for i in range(n)]))))
    si = ss.getSpaceInformation()
    # OMPL checks motions every fraction × the space's extent: make that CHECK_STEP rad.
    si.setStateValidityCheckingResolution(CHECK_STEP / space.getMaximumExtent())
    start, goal = space.allocState(), space.allocState()
    for i in range(n):
        start[i], goal[i] = float(q0[i]), float(q1[i])
    ss.setStartAndGoalStates(start, goal)
    ss.setPlanner(og.RRTConnect(si))
    try:
        ss.solve(time_s)
        if not ss.haveExactSolutionPath():
            return None
        ss.simplifySolution(SIMPLIFY_TIME_S)
        sol = ss.getSolutionPath()
        return np.array([[sol.getState(k)[i] for i in range(n)] for k in range(sol.getStateCount())])
    finally:
        del ss, si, space, bounds, start, goal  # nanobind: release OMPL's objects before interpreter exit


def retreat_postures(chain, q0: np.ndarray, d: np.ndarray, distance: float, step: float = RETREAT_STEP) -> np.ndarray:
    """(k + 1, n) postures backing the TCP off along ``-d`` (unit (3,), the tool axis) by up to ``distance``
    m from ``q0`` (n,), orientation held, every ``step`` m: resolved-rate steps on the compiled chain
    (:func:`~tergodic_cli.robot.kernels.fk_jacobian`; a few µs each), one posture per step."""
    from tergodic_cli.robot.kernels import fk_jacobian

    F, axis, qidx, off = chain
    q = np.asarray(q0, dtype=float).copy()
    T, J = np.empty((4, 4)), np.empty((6, len(q)))
    fk_jacobian(q, F, axis, qidx, off, T, J)
    p0, R0 = T[:3, 3].copy(), T[:3, :3].copy()
    out = [q.copy()]
    n = max(1, int(math.ceil(distance / step)))
    for k in range(1, n + 1):
        goal = p0 - d * (distance * k / n)
        for _ in range(3):  # a few Newton steps per posture: the line is held to well under a mm
            fk_jacobian(q, F, axis, qidx, off, T, J)
            Re = R0 @ T[:3, :3].T
            w = 0.5 * np.array([Re[2, 1] - Re[1, 2], Re[0, 2] - Re[2, 0], Re[1, 0] - Re[0, 1]])
            e = np.concatenate([goal - T[:3, 3], w])
            q = q + J.T @ np.linalg.solve(J @ J.T + 1e-6 * np.eye(6), e)
        out.append(q.copy())
    return np.array(out)


def retreat_clear(world: CollisionWorld, chain, q0: np.ndarray, d: np.ndarray, distance: float,
                  least: float = RETREAT_LEAST) -> tuple[float, float]:
    """How far (m, at most ``distance``) the tool can back off along its axis ``d`` from ``q0`` without an arm
    link coming closer to a body than it started (or than the margins, when it started beyond them); the
    ball is left out (it leaves the surface along the line). Never less than ``least``: the tool leaves
    the surface whatever. Returns (that distance, the smallest link slack (m) met on it)."""
    Q = retreat_postures(chain, q0, d, distance)
    start = world.slack(Q[0], PROBE, ball=False)
    floor = min(0.0, start) - 1e-3
    ok, worst = 0.0, start
    for k, q in enumerate(Q[1:], 1):
        s = world.slack(q, PROBE, ball=False)
        if s < floor and distance * k / (len(Q) - 1) > least:
            break
        ok, worst = distance * k / (len(Q) - 1), min(worst, s)
    return ok, worst
