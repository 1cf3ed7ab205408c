"""Whole-arm collision in the PyBullet scene: every arm link, the hand and its fingers, and the sponge
against the object, the table and the stand.

The physics step keeps one contact pair only, the sponge ball on the object (the tuned contact, and a
hand hull against the concave trimesh costs 5-10 × a physics step, docs/robot.md). Every other pair is
*checked*: each part's convex hull (the arm's own collision meshes, arms/; the ball for the sponge), at
its link's pose, against each obstacle body with ``getClosestPoints`` (exact convex-hull distances,
hulls with Bullet's 1 mm collision margin). A check costs ~20 µs per queried pair, so it is culled and
paced:

- *culled*: a part is queried against a body only when its bounding ball comes within ``QUERY_M``
  of it (the table's plane, the stand's box, the object's vertices less its longest triangle edge);
- *paced by the fastest part* (conservative advancement): after a check, the next one comes when the
  fastest part could have closed its gap to the nearest obstacle plus ``DEPTH_M``, moving at its
  present speed ``v`` = |v| + |ω| · (reach of the part from its link's centre of mass) and
  accelerating at ``A_MAX``: ``v t + A_MAX t² / 2 = gap + DEPTH_M``; at least every ``MAX_TICKS``
  physics steps and at most every tick. A contact is therefore found before it is deeper than
  ``DEPTH_M`` + the 1 mm hull margin.

The sponge's ball against the object is the tool's contact, never an arm contact; the ball against the
table or the stand is one once it sinks deeper than the foam does at the force limit (a captured
surface has no thickness: a plate's sheet lies on the stand's top, and pressing it presses the stand).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

#: Metres a contact may deepen between two checks (with the hulls' 1 mm margin: found within ~3 mm).
DEPTH_M = 0.002
#: Metres within which a part's bounding ball must come of a body to be queried exactly (the query's
#: cost grows with it: the trimesh's triangles within it are tested).
QUERY_M = 0.01
#: Metres: a pressed point this close to the table or the stand (beyond the sponge's sink) lies on it.
SUPPORT_TOL = 0.002
#: ... and the tool axis within 30 degrees of straight down (a sloped face by the stand is not on it: the
#: corpus prism's side, 2 mm above its stand, let the ball sink 3 mm into the stand).
SUPPORT_COS = 0.866
#: Physics steps between checks at most (0.1 s), m/s below which a part counts as that slow, and the
#: acceleration (m/s²) a part's point is assumed to reach at most between checks (a set-up move's
#: min-jerk peak, at the TCP speed it is planned for, is 0.1 m²/s² / its length: 2 m/s² for 5 cm).
MAX_TICKS, V_FLOOR, A_MAX = 100, 0.02, 5.0
#: Metres kept free around the robot's base in the table (the base stands in a hole).
BASE_MARGIN = 0.01
#: The table: a slab, top face at z = 0, this half-size (m) about the base and thick.
TABLE_HALF, TABLE_THICK = 1.2, 0.04
#: A stand is made when the object's lowest point is this high (m) above the table; its footprint is
#: the object's foot (the vertices within STAND_FOOT of the lowest), grown by STAND_PAD, at least
#: STAND_MIN on a side.
STAND_MIN_HEIGHT, STAND_FOOT, STAND_PAD, STAND_MIN = 0.005, 0.01, 0.0, 0.04


def _obj_vertices(path: str) -> np.ndarray:
    with open(path) as fh:
        return np.array([[float(v) for v in ln.split()[1:4]] for ln in fh if ln.startswith("v ")])


def _quat_matrix(q) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


@dataclass
class Part:
    """One convex piece of the arm: ``name``, the robot ``link`` it rides on (-1: the base), its collision
    ``shape`` (a PyBullet shape id), its pose in the link frame (``pos`` (3,), ``orn`` xyzw) and its
    bounding ball (``centre`` (3,) in the link frame, ``radius`` m)."""

    name: str
    link: int
    shape: int
    pos: np.ndarray
    orn: tuple
    centre: np.ndarray
    radius: float
    sponge: bool = False


@dataclass
class ArmContacts:
    """What the checks found over a run: ``count`` (checks × parts found touching a body other than
    the sponge on the object), ``deepest_mm`` (largest penetration, hull margin included), ``first``
    ({part, body, step, t, depth_mm}) and ``checks`` (how many checks ran)."""

    count: int = 0
    deepest_mm: float = 0.0
    first: dict | None = None
    checks: int = 0
    pairs: int = 0
    bodies: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"count": self.count, "deepest_mm": round(self.deepest_mm, 2), "first": self.first,
                "checks": self.checks, "pairs_queried": self.pairs, "by_body": dict(self.bodies)}


class ArmCollision:
    """The arm's parts and the obstacle bodies of a :class:`~tergodic_cli.backends.pybullet.scene.PyBulletScene`.

    Parameters
    ----------
    scene : the scene (its client, robot, arm spec, sponge and link names).
    data : pybullet_data's folder (the arm's collision meshes: ``scene.spec.collision_parts``).
    """

    def __init__(self, scene, data: str):
        from tergodic_cli.backends.pybullet.arms import mesh_vertices

        self.scene = scene
        p, cid = scene.p, scene.cid
        self.parts: list[Part] = []

        def add(name, link, shape, verts, pos=(0.0, 0.0, 0.0), rpy=(0.0, 0.0, 0.0), sponge=False):
            orn = p.getQuaternionFromEuler(rpy)
            R = _quat_matrix(orn)
            v = verts @ R.T + np.asarray(pos)
            lo, hi = v.min(axis=0), v.max(axis=0)
            c = 0.5 * (lo + hi)
            self.parts.append(Part(name, link, shape, np.asarray(pos, float), orn, c,
                                   float(np.max(np.linalg.norm(v - c, axis=1))), sponge))

        base_v = None
        for name, link, path, pos, rpy in scene.spec.collision_parts(data):
            V = mesh_vertices(path)
            j = -1 if link is None else scene.link_index[link]
            add(name, j, p.createCollisionShape(p.GEOM_MESH, fileName=path, physicsClientId=cid), V, pos=pos, rpy=rpy)
            if base_v is None:  # the base's piece comes first: its footprint, base frame (it never moves)
                T = np.eye(4) if j < 0 else scene.link_pose(j)
                base_v = (V @ _quat_matrix(p.getQuaternionFromEuler(rpy)).T + np.asarray(pos)) @ T[:3, :3].T + T[:3, 3]
        tool = scene.sponge_link
        if scene.spec.build is None:  # the generic tool's holder (arms.flange_tool_urdf), on the tool link
            from tergodic_cli.backends.pybullet.arms import HOLDER_LENGTH, HOLDER_RADIUS

            cyl = p.createCollisionShape(p.GEOM_CYLINDER, radius=HOLDER_RADIUS, height=HOLDER_LENGTH, physicsClientId=cid)
            r, h = HOLDER_RADIUS, HOLDER_LENGTH / 2
            add("holder", tool, cyl, np.array([[x, y, z] for x in (-r, r) for y in (-r, r) for z in (-h, h)]),
                pos=(0.0, 0.0, h))
        s = scene.sponge
        ball = p.createCollisionShape(p.GEOM_SPHERE, radius=s.radius, physicsClientId=cid)
        add("sponge", tool, ball, s.radius * np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]),
            pos=(0.0, 0.0, s.offset), sponge=True)
        self._links = sorted({pt.link for pt in self.parts if pt.link >= 0})
        # Per part: its row in link_states (0: the base), bounding ball, and its link's centre of mass
        # in the link frame (getLinkStates' velocities are the centre of mass's).
        self._rows = np.array([0 if pt.link < 0 else 1 + self._links.index(pt.link) for pt in self.parts])
        com = {-1: np.zeros(3), **{j: np.array(p.getDynamicsInfo(scene.robot, j, physicsClientId=cid)[3]) for j in self._links}}
        self._com_rows = np.array([com[pt.link] for pt in self.parts])
        self._centre = np.array([pt.centre for pt in self.parts])
        self._radius = np.array([pt.radius for pt in self.parts])
        self._sponge = np.array([pt.sponge for pt in self.parts])
        #: The hole in the table around the base: link0's footprint + BASE_MARGIN.
        self.hole = (base_v[:, :2].min(axis=0) - BASE_MARGIN, base_v[:, :2].max(axis=0) + BASE_MARGIN)
        self.bodies: dict[str, int] = {}
        self.stand_box: tuple[np.ndarray, np.ndarray] | None = None
        self._obj_tree: cKDTree | None = None
        self._obj_edge = 0.0
        self.stats = ArmContacts()
        #: Metres the sponge ball may sink into the table or stand: the foam pressed at the force limit
        #: (limit / contact stiffness) where the object's pressed surface lies on its support (a plate's
        #: sheet on the stand's top); the run sets it from its force limit.
        self.sponge_sink = 15.0 / scene.sponge.stiffness
        self.countdown = 0
        #: The contacts found by the last check: [(part, body, depth m, point on the body (3,))].
        self.last: list[tuple[str, str, float, np.ndarray]] = []

    # ------------------------------------------------------------------ bodies
    def add_table(self) -> int:
        """The table: a slab whose top is the base plane z = 0, with a hole for the base (four boxes)."""
        p, cid = self.scene.p, self.scene.cid
        (x0, y0), (x1, y1) = self.hole
        H, t = TABLE_HALF, TABLE_THICK
        boxes = [((x0 - (-H)) / 2, H, (-H + x0) / 2, 0.0),  # behind the hole: (half x, half y, centre x, centre y)
                 ((H - x1) / 2, H, (x1 + H) / 2, 0.0),  # in front
                 ((x1 - x0) / 2, (y0 + H) / 2, (x0 + x1) / 2, (-H + y0) / 2),  # right
                 ((x1 - x0) / 2, (H - y1) / 2, (x0 + x1) / 2, (y1 + H) / 2)]  # left
        shape = p.createCollisionShapeArray([p.GEOM_BOX] * 4, halfExtents=[[hx, hy, t / 2] for hx, hy, _, _ in boxes],
                                            collisionFramePositions=[[cx, cy, -t / 2] for _, _, cx, cy in boxes],
                                            physicsClientId=cid)
        vis = -1
        if self.scene.gui:
            vis = p.createVisualShapeArray([p.GEOM_BOX] * 4, halfExtents=[[hx, hy, t / 2] for hx, hy, _, _ in boxes],
                                           visualFramePositions=[[cx, cy, -t / 2] for _, _, cx, cy in boxes],
                                           rgbaColors=[[0.6, 0.5, 0.4, 1.0]] * 4, physicsClientId=cid)
        body = p.createMultiBody(0.0, shape, vis, physicsClientId=cid)
        p.setCollisionFilterGroupMask(body, -1, 0, 0, physicsClientId=cid)  # checked, never simulated
        self.bodies["table"] = body
        return body

    def set_object(self, body: int, vertices_base: np.ndarray, triangles: np.ndarray) -> None:
        """The object (``body``) with its collision mesh's vertices (V, 3) in the base frame, and the stand
        under it (made, moved or removed to fit)."""
        self.bodies["object"] = body
        v = np.asarray(vertices_base, dtype=float)
        self._obj_tree = cKDTree(v)
        tri = np.asarray(triangles)
        e = np.linalg.norm(v[tri] - v[np.roll(tri, 1, axis=1)], axis=2)
        self._obj_edge = float(e.max()) if e.size else 0.0
        self._set_stand(v)

    def _set_stand(self, v: np.ndarray) -> None:
        p, cid = self.scene.p, self.scene.cid
        if "stand" in self.bodies:
            p.removeBody(self.bodies.pop("stand"), physicsClientId=cid)
            self.stand_box = None
        box = stand_box(v)
        if box is None:
            return
        lo, hi = box
        half, centre = (0.5 * (hi - lo)).tolist(), (0.5 * (hi + lo)).tolist()
        shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=cid)
        vis = p.createVisualShape(p.GEOM_BOX, halfExtents=half, rgbaColor=[0.45, 0.45, 0.5, 1.0],
                                  physicsClientId=cid) if self.scene.gui else -1
        body = p.createMultiBody(0.0, shape, vis, basePosition=centre, physicsClientId=cid)
        p.setCollisionFilterGroupMask(body, -1, 0, 0, physicsClientId=cid)
        self.bodies["stand"] = body
        self.stand_box = (lo, hi)

    # ------------------------------------------------------------------ the check
    def link_states(self):
        """The parts' links now: (positions (L, 3), rotations (L, 3, 3), quaternions [xyzw] * L, linear
        velocities of their centres of mass (L, 3), angular velocities (L, 3)), rows as :attr:`_rows`."""
        sc = self.scene
        states = sc.p.getLinkStates(sc.robot, self._links, computeLinkVelocity=1, computeForwardKinematics=1,
                                    physicsClientId=sc.cid)
        quats = [(0.0, 0.0, 0.0, 1.0)] + [s[5] for s in states]
        X = np.array([(0.0, 0.0, 0.0)] + [s[4] for s in states])
        V = np.array([(0.0, 0.0, 0.0)] + [s[6] for s in states])
        W = np.array([(0.0, 0.0, 0.0)] + [s[7] for s in states])
        return X, _quats_matrices(np.array(quats)), quats, V, W

    def _lower_bounds(self, c: np.ndarray, r: np.ndarray) -> dict[str, np.ndarray]:
        """Lower bounds (m) on each part's distance to each body, from bounding balls (centres (k, 3), radii (k,))."""
        out = {}
        if "table" in self.bodies:
            (x0, y0), (x1, y1) = self.hole
            inside = (c[:, 0] - r > x0) & (c[:, 0] + r < x1) & (c[:, 1] - r > y0) & (c[:, 1] + r < y1)
            out["table"] = np.where(inside, np.inf, c[:, 2] - r)
        if self.stand_box is not None:
            lo, hi = self.stand_box
            out["stand"] = np.linalg.norm(np.maximum(np.maximum(lo - c, c - hi), 0.0), axis=1) - r
        if self._obj_tree is not None:
            # a point's distance to the surface is at least its distance to the nearest vertex less the longest edge
            out["object"] = self._obj_tree.query(c)[0] - self._obj_edge - r
        return out

    def check(self, step: int = -1, states=None) -> list[tuple[str, str, float, np.ndarray]]:
        """One check at the arm's present pose. Returns the contacts [(part, body, depth m, point (3,))] and
        sets :attr:`countdown`, the physics steps until the next check is due."""
        sc = self.scene
        p, cid = sc.p, sc.cid
        X, R, quats, V, W = states or self.link_states()
        rows = self._rows
        Rp = R[rows]
        C = X[rows] + np.einsum("kij,kj->ki", Rp, self._centre)
        com = X[rows] + np.einsum("kij,kj->ki", Rp, self._com_rows)
        speed = np.linalg.norm(V[rows], axis=1) + np.linalg.norm(W[rows], axis=1) * (
            np.linalg.norm(C - com, axis=1) + self._radius)
        bounds = self._lower_bounds(C, self._radius)
        gap = np.full(len(self.parts), np.inf)  # per part, a lower bound of its distance to every body
        found = []
        for name, lb in bounds.items():
            body = self.bodies[name]
            near = lb < QUERY_M
            if name == "object":
                near &= ~self._sponge
                lb = np.where(self._sponge, np.inf, lb)  # the ball on the object: the tool's own contact
            gap_q = gap.copy()  # the queried parts' gap to this body comes from the query, not the bound
            gap = np.minimum(gap, np.where(near, np.inf, lb))
            for i in np.flatnonzero(near):
                pt = self.parts[i]
                pos, orn = p.multiplyTransforms(X[rows[i]].tolist(), quats[rows[i]], pt.pos.tolist(), pt.orn,
                                                physicsClientId=cid)
                self.stats.pairs += 1
                res = p.getClosestPoints(-1, body, QUERY_M, collisionShapeA=pt.shape, collisionShapePositionA=pos,
                                         collisionShapeOrientationA=orn, physicsClientId=cid)
                d = min((r[8] for r in res), default=QUERY_M)  # nothing within QUERY_M: at least that far
                gap[i] = min(gap_q[i], d + (self.sponge_sink if pt.sponge else 0.0))  # the gap to a fault
                gap_q[i] = gap[i]
                if d < (-self.sponge_sink if pt.sponge else 0.0):
                    hit = min(res, key=lambda r: r[8])
                    found.append((pt.name, name, -float(d), np.array(hit[6])))
        # Conservative advancement: no part can close its gap (+ DEPTH_M) before the next check, moving at
        # its speed now and accelerating at A_MAX: v t + A_MAX t² / 2 = gap + DEPTH_M.
        v = np.maximum(speed, V_FLOOR)
        reach = np.maximum(gap, 0.0) + DEPTH_M
        t = (np.sqrt(v * v + 2.0 * A_MAX * reach) - v) / A_MAX
        self.countdown = int(max(1, min(MAX_TICKS, float(np.min(np.floor(t / sc.dt))))))
        st = self.stats
        st.checks += 1
        for part, body, depth, _ in found:
            st.count += 1
            st.bodies[body] = st.bodies.get(body, 0) + 1
            st.deepest_mm = max(st.deepest_mm, 1e3 * depth)
            if st.first is None:
                st.first = {"part": part, "body": body, "step": int(step), "t": round(sc.t, 4),
                            "depth_mm": round(1e3 * depth, 2)}
        self.last = found
        return found


    def tool_clearance(self, T_tcp: np.ndarray, clear: float = 0.01) -> np.ndarray:
        """(n,) whether the tool link's parts (the hand and its fingers, or the holder) and the sponge, with
        the TCP at each pose ``T_tcp`` (n, 4, 4) base frame, stay ``clear`` m from every body (the sponge's own
        contact with the object aside). The sponge keeps ``clear`` from the table and the stand too, except
        where the pressed point itself lies on that support with the tool pointing down (a plate's sheet on
        the stand's top): there it may sink into it as into the object (:attr:`sponge_sink`). A ball pressed on a face just above its
        support (a prism's side by the stand) touched the stand mid-run."""
        p, cid = self.scene.p, self.scene.cid
        hand = self.scene.sponge_link
        idx = [i for i, pt in enumerate(self.parts) if pt.link == hand]
        off = np.asarray(self.scene.tcp_offset, dtype=float)
        T_tcp = np.asarray(T_tcp, dtype=float)
        R = T_tcp[:, :3, :3]
        O = T_tcp[:, :3, 3] - R @ off  # the hand's origin
        ok = np.ones(len(T_tcp), dtype=bool)
        # pressed on a surface that lies on the support and faces up as its top does: the tool points down
        down = T_tcp[:, 2, 2] <= -SUPPORT_COS
        on_support = {name: (lb <= self.sponge_sink + SUPPORT_TOL) & down
                      for name, lb in self._lower_bounds(T_tcp[:, :3, 3], np.zeros(len(T_tcp))).items()}
        for i in idx:
            pt = self.parts[i]
            C = O + R @ pt.centre
            bounds = self._lower_bounds(C, np.full(len(C), pt.radius))
            for name, lb in bounds.items():
                if pt.sponge and name == "object":
                    continue
                limits = np.where(on_support[name], -self.sponge_sink, clear) if pt.sponge else np.full(len(C), clear)
                for k in np.flatnonzero(ok & (lb < limits + QUERY_M)):
                    limit = float(limits[k])
                    Rk = R[k] @ _quat_matrix(pt.orn)
                    res = p.getClosestPoints(-1, self.bodies[name], max(limit, 0.0) + QUERY_M, collisionShapeA=pt.shape,
                                             collisionShapePositionA=(O[k] + R[k] @ pt.pos).tolist(),
                                             collisionShapeOrientationA=_matrix_quat(Rk), physicsClientId=cid)
                    if min((r[8] for r in res), default=np.inf) < limit:
                        ok[k] = False
        return ok


def _matrix_quat(R: np.ndarray) -> list[float]:
    from tergodic_cli.robot.ga import matrix_to_quat

    return [float(v) for v in matrix_to_quat(R)]


def _quats_matrices(q: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotation matrices of quaternions (n, 4) xyzw."""
    x, y, z, w = q.T
    return np.column_stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]).reshape(-1, 3, 3)


def stand_box(vertices_base: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The stand under an object lifted off the table: (lo (3,), hi (3,)) of a box from the table (z = 0)
    to the object's lowest point, its footprint the object's foot (the vertices within STAND_FOOT of the
    lowest, (V, 3) base frame) grown by STAND_PAD, at least STAND_MIN on a side; None when the object
    stands on the table (lowest point under STAND_MIN_HEIGHT)."""
    v = np.asarray(vertices_base, dtype=float)
    z = float(v[:, 2].min())
    if z < STAND_MIN_HEIGHT:
        return None
    foot = v[v[:, 2] <= z + STAND_FOOT, :2]
    lo, hi = foot.min(axis=0) - STAND_PAD, foot.max(axis=0) + STAND_PAD
    mid, half = 0.5 * (lo + hi), np.maximum(0.5 * (hi - lo), 0.5 * STAND_MIN)
    return np.array([*(mid - half), 0.0]), np.array([*(mid + half), z])


def replay_contacts(scene, Q: np.ndarray) -> ArmContacts:
    """Joint states ``Q`` (n, 7) replayed at rest through ``scene``'s checks (a logged run's arm against its
    object, table and stand). Returns the contacts found (a fresh :class:`ArmContacts`); the arm is left at Q[-1]."""
    col = scene.collision
    saved, col.stats = col.stats, ArmContacts()
    try:
        for k, q in enumerate(np.asarray(Q, dtype=float)):
            scene.set_arm(q)
            col.check(step=k)
        return col.stats
    finally:
        col.stats = saved
