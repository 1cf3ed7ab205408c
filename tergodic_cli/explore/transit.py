"""Never trapped: the explorer's stagnation check and its recovery, a transit along the surface.

The drive (docs/explore.md, "How the agent is driven") is local: the footprint gain sees residual
within a few footprints, and the heat, truncated to nK modes, can be flat between a cleared region
and a far one. An agent can then circle a cleared area for ever while target residual remains
elsewhere (issue 25: the bunny with a band, 4 of 5 starts). Every ``STALL_WINDOW`` steps the
explorer compares the residual ∫s with the last check's; when it has not fallen by ``STALL_FALL``
and the footprint gain G where the agent stands is below ``STALL_GAIN`` of the best G on the
target it can reach, the agent makes a *transit*: it follows the shortest path on the cloud's
neighbour graph to the nearest point where G is at least ``GOAL_SHARE`` of that best, under the same v_max / a_max limits (docs/explore.md,
"Never trapped", gives the argument).
"""

from __future__ import annotations

import math

import numpy as np

#: Steps between stagnation checks (the check costs O(|T|) numpy work; nothing on the other steps).
STALL_WINDOW = 50
#: ∫s must fall by at least this share over a window, or the explorer looks for a better place.
STALL_FALL = 0.02
#: ... and the agent moves there when the gain where it stands is below this share of the best.
STALL_GAIN = 0.1
#: The surface graph's normals come from this many nearest points; an edge whose direction has a
#: component above EDGE_MAX_NORMAL along either end's normal (more than ~45° out of the tangent
#: plane) crosses between sheets and is left out.
NORMAL_NEIGHBORS, EDGE_MAX_NORMAL = 6, 0.7
#: A goal the agent could not reach (a transit that gave up) is not chosen again within this many
#: r_a of it (the same target, seen through a wall).
BAN_RA = 1.0
#: The goal: the nearest point (along the surface) where G is at least this share of the best reachable.
GOAL_SHARE = 0.5
#: The transit aims this many v_max dt ahead along its path (pure pursuit).
LOOKAHEAD_STEPS = 2.0
#: A transit ends within this share of r_a of its goal, or gives up after SLACK x the path's
#: length in steps (plus SLACK_STEPS): a path the agent cannot follow (a move refused at an edge).
ARRIVE_RA = 0.5
SLACK, SLACK_STEPS = 2.0, 20


def stalled(s_then: float, s_now: float, gain_here: float, gain_best: float, fall: float = STALL_FALL,
            ratio: float = STALL_GAIN) -> bool:
    """The stagnation test: the residual did not fall over the window, and a better place exists.

    Parameters
    ----------
    s_then, s_now : ∫s at the last check and now (1/m², any consistent scale).
    gain_here : footprint gain G at the agent (what a deposit there would remove).
    gain_best : the largest G on the target the agent can reach.
    fall : share ∫s must fall by over the window to count as progress.
    ratio : G here below this share of the best means the agent is where little is left.

    Returns
    -------
    bool
    """
    if not (gain_best > 0.0 and math.isfinite(s_now)):
        return False  # nothing left to remove anywhere: done, not stuck
    return s_now > (1.0 - fall) * s_then and gain_here < ratio * gain_best


def surface_graph(points: np.ndarray, reach: float, normal_neighbors: int = NORMAL_NEIGHBORS,
                  max_normal: float = EDGE_MAX_NORMAL, normals: np.ndarray | None = None):
    """The cloud's neighbour graph along its surface: an edge between points closer than ``reach``
    that runs along the surface at both ends, weighted by its length.

    An edge runs along the surface when its direction's component along the local normal (PCA of
    the ``normal_neighbors`` nearest points, open3d) is below ``max_normal`` at both ends: an edge
    across a thin wall, from one sheet to the other, runs along the normal and is left out, so a
    path never goes through the material.

    Parameters
    ----------
    points : (m, 3) metres.
    reach : metres (the explorer's 2 x SURFACE_REACH h: what an agent on the data can cross).
    normals : (m, 3) or None
        Oriented unit normals (``index.sheet_normals``, ``--sheets separate``): used instead of the
        PCA lines, and an edge whose ends' normals are more than 120 degrees apart (a wall's two
        sides, where the edge test is blind) is left out too.

    Returns
    -------
    scipy.sparse.csr_matrix (m, m), symmetric, metres.
    """
    import open3d as o3d
    from scipy.sparse import coo_matrix
    from scipy.spatial import cKDTree

    m = len(points)
    oriented = normals is not None
    if not oriented:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(normal_neighbors))
        normals = np.asarray(pcd.normals)
    pairs = cKDTree(points).query_pairs(reach, output_type="ndarray")
    d = points[pairs[:, 1]] - points[pairs[:, 0]]
    w = np.linalg.norm(d, axis=1)
    d /= np.where(w > 0, w, 1.0)[:, None]
    along = (np.abs(np.sum(d * normals[pairs[:, 0]], axis=1)) < max_normal) & \
        (np.abs(np.sum(d * normals[pairs[:, 1]], axis=1)) < max_normal)
    if oriented:  # a wall's two sides, joined where the edge test is blind (a rim), point opposite ways
        along &= np.sum(normals[pairs[:, 0]] * normals[pairs[:, 1]], axis=1) > -0.5
    pairs, w = pairs[along], w[along]
    i, j = np.concatenate([pairs[:, 0], pairs[:, 1]]), np.concatenate([pairs[:, 1], pairs[:, 0]])
    return coo_matrix((np.concatenate([w, w]), (i, j)), shape=(m, m)).tocsr()


def paths_from(graph, source: int) -> tuple[np.ndarray, np.ndarray]:
    """Shortest paths on :func:`surface_graph` from ``source`` to every point (Dijkstra).

    Parameters
    ----------
    graph : the (m, m) sparse graph of :func:`surface_graph`.
    source : the start point's index.

    Returns
    -------
    dist : (m,) metres along the graph (inf where unreachable).
    pred : (m,) each point's predecessor on its path (-9999 for the source and unreachable points).
    """
    from scipy.sparse.csgraph import dijkstra

    return dijkstra(graph, directed=False, indices=source, return_predecessors=True)


def path_to(pred: np.ndarray, source: int, goal: int) -> np.ndarray:
    """The path source -> goal from :func:`paths_from`'s predecessors.

    Parameters
    ----------
    pred : (m,) predecessors from :func:`paths_from` (``source``'s).
    source, goal : point indices; ``goal`` must be reachable (finite distance).

    Returns
    -------
    (k,) int64 point indices from source to goal.
    """
    path = [goal]
    while path[-1] != source:
        path.append(int(pred[path[-1]]))
    return np.array(path[::-1], dtype=np.int64)


def choose_goal(dist: np.ndarray, gain: np.ndarray, share: float = GOAL_SHARE, banned: np.ndarray | None = None) -> int:
    """The transit's goal: of the reachable points whose gain is at least ``share`` of the best
    reachable gain, the nearest along the surface (-1 when none is reachable or no gain is left).

    Parameters
    ----------
    dist : (k,) path lengths to k candidate points, metres (inf: unreachable).
    gain : (k,) their footprint gain G.
    share : in (0, 1].
    banned : (k,) bool, points not to choose (goals a transit could not reach), or None.

    Returns
    -------
    int: the index into the k candidates, or -1.
    """
    ok = np.isfinite(dist) if banned is None else np.isfinite(dist) & ~banned
    if not np.any(ok) or not np.max(gain[ok]) > 0.0:
        return -1
    good = np.flatnonzero(ok & (gain >= share * np.max(gain[ok])))
    return int(good[np.argmin(dist[good])])


class Transit:
    """One agent's transit along a path of surface points.

    Parameters
    ----------
    points : (k, 3) the path's points, metres (from the agent's nearest point to the goal).
    step_length : v_max dt, metres.
    arrive : distance to the goal at which the transit ends, metres.
    """

    def __init__(self, points: np.ndarray, step_length: float, arrive: float):
        self.points = points
        seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
        self.arc = np.concatenate([[0.0], np.cumsum(seg)])
        self.length = float(self.arc[-1])
        self.step_length, self.arrive = step_length, arrive
        self.at = 0  # the path point the agent passed last
        self.steps = 0
        self.limit = int(SLACK * self.length / step_length) + SLACK_STEPS

    def velocity(self, x: np.ndarray, normal: np.ndarray, v_max: float) -> np.ndarray | None:
        """The velocity to track from ``x`` (3,), tangent to ``normal``; None when the transit is over.

        Pure pursuit: the aim is the path point LOOKAHEAD_STEPS v_max dt beyond the path point
        nearest the agent (searched forward from the last one, so the agent never turns back).

        Parameters
        ----------
        x : (3,) the agent's position, metres.
        normal : (3,) unit surface normal there.
        v_max : m/s.

        Returns
        -------
        (3,) m/s, tangent, of length v_max; or None when the agent has arrived or given up.
        """
        self.steps += 1
        if np.linalg.norm(self.points[-1] - x) <= self.arrive or self.steps > self.limit:
            return None
        ahead = self.points[self.at: self.at + 16]
        self.at += int(np.argmin(np.linalg.norm(ahead - x, axis=1)))
        reach = self.arc[self.at] + LOOKAHEAD_STEPS * self.step_length
        aim = self.points[min(int(np.searchsorted(self.arc, reach)), len(self.points) - 1)]
        d = aim - x
        d -= (d @ normal) * normal
        n = float(np.linalg.norm(d))
        if n == 0.0:
            return None
        return d * (v_max / n)

    @property
    def arrived(self) -> bool:
        return self.steps <= self.limit
