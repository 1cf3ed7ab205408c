"""Where the tool can follow the surface normal: tool orientation, spin choice and reachability.

The sponge is a ball on the tool axis, so only the axis is set by the task (it points into the
surface, along -n); the rotation about it (the spin) is free. :func:`tool_rotation` picks it as a
continuous function of the axis: the spin the arm has pointing straight down, carried along the
shortest rotation to the axis. It is smooth everywhere but for a tool pointing straight up (never
used on a sheet worked from outside), so the wrist never flips between neighbouring normals, and
on the Panda it keeps joint 6 and 7 well inside their limits on vertical walls (horizontal
axes: the hand's x-axis turns to ±z, the wrist folds in its middle range).

:func:`reach_map` runs inverse kinematics (damped least squares on the compiled chain, a few ms
each) for a sample of the cloud's normals and marks every point by its nearest sample: a point is
reachable when the arm holds the tool along its normal, at the point and ``hover`` back along the
normal, with every joint ``margin`` rad inside its limits, and the object does not block the tool's
axis behind it (:func:`occluded`). The robot run drops the unreachable
part from the explorer's target before it starts and says so (issue 15, item 1).
:func:`plan_reach` also places an object whose pose the capture does not give (0.5 or 0.4 m in
front of the base, turned about the vertical) where the arm reaches the most of its target, and
:func:`posture` picks the arm's start posture (the line controller's null-space rest posture).
"""

from __future__ import annotations

import math

import numpy as np

#: Radians every joint keeps from its limits for a normal to count as reachable.
REACH_MARGIN = 0.15
#: Surface samples the reach map solves inverse kinematics for.
REACH_SAMPLES = 96


def tool_rotation(d: np.ndarray, x_down: np.ndarray) -> np.ndarray:
    """(3, 3) tool orientation with z along the unit axis ``d`` (3,), spin from ``x_down``.

    ``x_down`` (3,) is the tool's x-axis when it points straight down; it is carried to ``d`` by the
    shortest rotation from -z to ``d`` (continuous in ``d`` except at +z). One row of :func:`tool_rotations`.
    """
    return tool_rotations(np.asarray(d, dtype=float)[None], x_down)[0]


def tool_rotations(d: np.ndarray, x_down: np.ndarray) -> np.ndarray:
    """(n, 3, 3) tool orientations of :func:`tool_rotation` for the axes ``d`` (n, 3), in one pass."""
    d = np.asarray(d, dtype=float)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    axis = np.cross([0.0, 0.0, -1.0], d)
    s, c = np.linalg.norm(axis, axis=1), -d[:, 2]
    x = np.tile(np.asarray(x_down, dtype=float), (len(d), 1))
    turn = s > 1e-9
    k, st, ct, xt = axis[turn] / s[turn, None], s[turn, None], c[turn, None], x[turn]
    x[turn] = xt * ct + np.cross(k, xt) * st + k * np.sum(k * xt, axis=1, keepdims=True) * (1.0 - ct)
    x[~turn & (c < 0)] = (1.0, 0.0, 0.0)  # pointing straight up: any spin (the one discontinuity)
    x = x - np.sum(x * d, axis=1, keepdims=True) * d
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return np.stack([x, np.cross(d, x), d], axis=2)


def ik(chain, T: np.ndarray, q0: np.ndarray, q_min: np.ndarray, q_max: np.ndarray, q_rest: np.ndarray | None = None,
       iters: int = 150, margin: float = 0.02) -> tuple[np.ndarray, float, float]:
    """Damped least squares inverse kinematics of the TCP pose ``T`` (4, 4) on the compiled ``chain``.

    Returns (q (n,), position error m, orientation error rad); the posture ``q_rest`` is favoured
    in the null space, the joints are kept ``margin`` rad inside their limits.
    """
    from tergodic_cli.robot.kernels import ik_dls

    F, axis, qidx, off = chain
    lo, hi = q_min + margin, q_max - margin
    q = np.clip(np.asarray(q0, dtype=float), lo, hi)
    q_rest = q.copy() if q_rest is None else np.asarray(q_rest, dtype=float)
    # compiled (numba): the reach map solves a few hundred of these per robot run
    q, pe, oe = ik_dls(np.ascontiguousarray(T, dtype=float), q, lo, hi, q_rest, F, axis, qidx, off, int(iters))
    return q, float(pe), float(oe)


def posture(chain, T: np.ndarray, q_ref: np.ndarray, q_min: np.ndarray, q_max: np.ndarray,
            valid=None) -> tuple[np.ndarray, float, float]:
    """Inverse kinematics of ``T`` (4, 4) from a few seeds, the best posture of those that converge.

    Seeds: ``q_ref`` (n,) and ``q_ref`` with the base turned towards the target, each also with the
    wrist rolled either way (joints n - 2 and n: the Panda's and iiwa's 5 and 7, the xArm 6's 4 and 6). One seed alone can settle in a twisted elbow (joints 1
    and 3 counter-rotated, joint 4 and 6 near their limits: measured on the bowl's far wall), where
    the line controller's null-space spring would then hold the arm. Best: the widest joint margin
    (up to 0.5 rad), then the nearest to ``q_ref``; with ``valid`` (q (n,) -> bool, e.g. clear of the
    object) a posture it refuses only wins when no converged one passes. Returns (q (n,), position
    error m, orientation error rad).
    """
    q_ref = np.asarray(q_ref, dtype=float)
    turned = q_ref.copy()
    turned[0] = math.atan2(T[1, 3], T[0, 3])
    roll = np.zeros(len(q_ref))
    roll[-3], roll[-1] = 1.2, -1.0
    best, best_score = None, -math.inf
    for seed in (q_ref, turned, q_ref + roll, q_ref - roll, turned + roll, turned - roll):
        q, pe, oe = ik(chain, T, seed, q_min, q_max, q_rest=seed)
        ok = pe <= 1e-3 and oe <= 1e-2
        score = (0.0 if ok else -10.0) + min(0.5, float(np.min(np.minimum(q - q_min, q_max - q)))) \
            - 0.1 * float(np.linalg.norm(q - q_ref))
        if ok and valid is not None and not valid(q):
            score -= 5.0
        if score > best_score:
            best, best_score = (q, pe, oe), score
    return best


def pose_ok(chain, a: np.ndarray, d: np.ndarray, x_down: np.ndarray, q0: np.ndarray, q_min: np.ndarray,
            q_max: np.ndarray, hover: float = 0.04, margin: float = REACH_MARGIN) -> tuple[bool, np.ndarray]:
    """Whether the arm holds the tool along ``d`` at ``a`` and ``hover`` m back, ``margin`` rad inside the limits.

    Returns (reachable, joints (n,) at ``a``).
    """
    from tergodic_cli.robot.ga import pose_matrix

    R = tool_rotation(d, x_down)
    q = np.asarray(q0, dtype=float)
    ok = True
    for back in (hover, 0.0):
        q, pe, oe = ik(chain, pose_matrix(R, a - back * d), q, q_min, q_max, q_rest=q0)
        ok = ok and pe < 1e-3 and oe < 1e-2 and bool(np.all(q - q_min >= margin) and np.all(q_max - q >= margin))
    return ok, q


def reach_map(chain, points: np.ndarray, normals: np.ndarray, x_down: np.ndarray, q0: np.ndarray,
              q_min: np.ndarray, q_max: np.ndarray, hover: float = 0.04, samples: int = REACH_SAMPLES,
              seed: int = 0) -> np.ndarray:
    """Reachable mask (n,) bool of the cloud ``points`` (n, 3) with unit ``normals`` (n, 3), base frame.

    ``samples`` points (farthest-point spread, from a seeded start) are solved with :func:`pose_ok`
    (tool along -n, from the posture ``q0``); every point takes its nearest sample's answer.
    """
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=float)
    n = len(pts)
    k = min(int(samples), n)
    rng = np.random.default_rng(seed)
    idx = [int(rng.integers(n))]
    dist = np.linalg.norm(pts - pts[idx[0]], axis=1)
    for _ in range(k - 1):
        j = int(np.argmax(dist))
        idx.append(j)
        dist = np.minimum(dist, np.linalg.norm(pts - pts[j], axis=1))
    ok = np.array([pose_ok(chain, pts[j], -normals[j], x_down, q0, q_min, q_max, hover)[0] for j in idx])
    _, near = cKDTree(pts[idx]).query(pts)
    return ok[near] & ~occluded(pts, normals)


def occluded(points: np.ndarray, normals: np.ndarray, reach: float = 0.16, clearance: float = 0.025) -> np.ndarray:
    """(n,) bool: the object (the cloud ``points`` (n, 3)) lies within ``clearance`` m of the tool's
    axis over the ``reach`` m behind a point along its unit normal (``normals`` (n, 3)): the sponge's
    holder and the hand there would hit it (the inside of a torus's hole, a narrow gap), whatever the
    joints allow. (The torus's inner wall, 8 % of its surface, is the only built-in part it marks.)"""
    from scipy.spatial import cKDTree

    tree = cKDTree(points)
    hit = np.zeros(len(points), dtype=bool)
    for s in np.linspace(0.03, reach, 15):
        d, _ = tree.query(points + s * normals, distance_upper_bound=clearance)
        hit |= np.isfinite(d)
    return hit


#: Object placements tried when the capture does not say where the object stands: (reach m, yaw deg)
#: about the vertical through its footprint centre, in order; the first that reaches the whole
#: target wins, else the one reaching the most of it.
PLACEMENTS = ((0.5, 0.0), (0.5, 90.0), (0.5, -90.0), (0.5, 180.0), (0.4, 0.0), (0.4, 90.0), (0.4, -90.0), (0.4, 180.0))


def plan_reach(chain, points: np.ndarray, normals: np.ndarray, target: np.ndarray, x_down: np.ndarray, q0: np.ndarray,
               q_min: np.ndarray, q_max: np.ndarray, T_obj: np.ndarray | None, hover: float = 0.04,
               seed: int = 0, reach: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The object pose and the reachable mask of its cloud.

    Parameters
    ----------
    points, normals : (n, 3) cloud and oriented unit normals, capture frame. target : (n,) p >= 0.
    T_obj : (4, 4) the capture frame in the base frame when it is given (calibrated camera,
        ``--object-pose``); None: try :data:`PLACEMENTS` (stand of :func:`default_object_pose`).
    reach : ((3,) m, m) or None
        The arm's shoulder and working distance (:func:`~tergodic_cli.robot.surface.check_reachable`),
        which a placement after the first must pass.

    Returns
    -------
    (T_obj (4, 4), reachable (n,) bool).
    """
    from tergodic_cli.errors import TergodicError
    from tergodic_cli.robot.surface import check_reachable, default_object_pose, transform_points

    def mask_at(T, samples=REACH_SAMPLES):
        return reach_map(chain, transform_points(T, points), normals @ T[:3, :3].T, x_down, q0, q_min, q_max, hover,
                         samples, seed)

    if T_obj is not None:
        return T_obj, mask_at(T_obj)
    p = np.asarray(target, dtype=float)
    best = None
    for distance, yaw in PLACEMENTS:
        T = default_object_pose(points, distance, yaw)
        if best is not None:  # the first (the usual stand) is checked by the caller; others must fit too
            try:
                check_reachable(transform_points(T, points), reach)
            except TergodicError:
                continue
        m = mask_at(T, REACH_SAMPLES // 2)
        share = float(p @ m) / float(p.sum())
        if best is None or share > best[0] + 1e-9:
            best = (share, T)
        if share >= 0.999:
            break
    return best[1], mask_at(best[1])
