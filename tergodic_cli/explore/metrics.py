"""Coverage, source and the three exploration metrics as pure functions of full arrays.

The :class:`~tergodic_cli.explore.explorer.Explorer` keeps incremental versions of these for
speed; these forms define them (and the tests check the two agree). The neutral score of a
trajectory is kept step by step (:class:`CoverageScore`); its full-array definition is in
``tests/reference_geometry.py``.

All per-point arrays are (n,) float64 over the cloud; ``mass`` is the lumped mass M (m²).
"""

from __future__ import annotations

import numpy as np

from tergodic_cli.explore import kernels as K
from tergodic_cli.explore.config import footprint_epsilon
from tergodic_cli.explore.footprint import source
from tergodic_cli.explore.index import cloud_index, sheet_normals


def source_term(p: np.ndarray, coverage: np.ndarray, mass: np.ndarray, norm: str = "cloud") -> np.ndarray:
    """s = max(p̄ - c̄, 0)² (eq. 1) with p̄ the target normalised to unit mass.

    ``norm`` "cloud": c̄ = c̃ / ∫_Ω c̃, the raw coverage normalised over the whole cloud (eq. 2);
    "target": c̄ = c̃ / ∫_T c̃ over the target's support T = {p > 0}, so that coverage falling
    beside the target does not count towards it (docs/explore.md).

    Parameters
    ----------
    p : (n,) float
        Target weight in [0, 1].
    coverage : (n,) float
        Raw coverage c̃.
    mass : (n,) float
        Lumped mass, m².
    norm : str
        "cloud" or "target".

    Returns
    -------
    (n,) float
        s, 1/m⁴.
    """
    # each to unit mass, f / ∫f with ∫f = Σ M_i f_i (eq. 2); zeros stay zeros
    p_total = float(mass @ p)
    pbar = p / p_total if p_total > 0 else np.zeros_like(p, dtype=float)
    counted = np.where(np.asarray(p) > 0, coverage, 0.0) if norm == "target" else coverage
    total = float(mass @ counted)
    cbar = coverage / total if total > 0 else np.zeros_like(coverage, dtype=float)
    return source(np.asarray(pbar, dtype=np.float64), np.asarray(cbar, dtype=np.float64))


def ergodicity(p: np.ndarray, coverage: np.ndarray, mass: np.ndarray) -> float:
    """Eq. 48 in the surface's measure: ‖max(p̄ - c̄, 0)‖₂ with ‖f‖₂ = (Σ M_i f_i²)^½, ∫p̄ = 1.

    Units 1/m (a density difference in L2 on the surface); it is √∫s of the source with the
    cloud's normalisation. Not the reported score: that is :func:`coverage_score` (unit masses in
    plain sums, dimensionless), which compares any trajectory with any other.

    Parameters
    ----------
    p : (n,) float
        Target weight.
    coverage : (n,) float
        Raw coverage c̃.
    mass : (n,) float
        Lumped mass, m².

    Returns
    -------
    float
        1/m.
    """
    return float(np.sqrt(mass @ source_term(p, coverage, mass)))


def touched_fraction(p: np.ndarray, coverage: np.ndarray) -> float:
    """Share of target points (p > 0) whose coverage is > 0.

    Parameters
    ----------
    p : (n,) float
        Target weight.
    coverage : (n,) float

    Returns
    -------
    float
        In [0, 1].
    """
    target = p > 0
    return float(np.count_nonzero(coverage[target] > 0) / max(np.count_nonzero(target), 1))


#: The score's footprint is summed over the points within this many r_a (exp(-4 · 2.5²) = 1e-11).
SCORE_CUT = 2.5
#: A position farther than this many mean spacings h from every cloud point is off the surface ...
OFF_SURFACE_H = 2.0
#: ... and so is one farther than this many h (or than the cloud's sheet gap, if wider: a noisy cloud)
#: from the surface fitted to its nearest points on one sheet, when they hold more than one
#: (kernels.sheet_distance): between a wall's two sides (docs/explore.md, sheet separation).
OFF_SHEET_H = 0.5


def coverage_score(points: np.ndarray, target: np.ndarray, positions: np.ndarray, agent_radius: float,
                   h: float) -> dict:
    """The neutral coverage score of a whole trajectory: :class:`CoverageScore` over its steps.

    Parameters
    ----------
    points : (n, 3) cloud points P, metres.
    target : (n,) target weight p >= 0.
    positions : (T, 3) or (T, N, 3) agent positions X_t, metres (all agents' count).
    agent_radius : r_a, metres; the footprint is exp(-(2/r_a)² d²), d the 3-D distance.
    h : mean point spacing, metres.

    Returns
    -------
    dict: ``ergodicity`` ε = ‖max(p̄ - c̄, 0)‖₂ / ‖p̄‖₂ with c_i = Σ_t exp(-(2/r_a)² |P_i - X_t|²) and
    p̄ = p/Σp, c̄ = c/Σc (dimensionless, 0 is perfect, 1 untouched); ``touched_fraction`` (share of
    target points within r_a of some X_t); ``off_surface_fraction`` (share of positions more than
    2h from every point, or, among points of more than one sheet, more than h/2 (or the sheet gap, if
    wider) from the local surface of the
    sheet they are nearest to, fitted to its points among their n_N nearest); ``step_max_m`` (largest |X_{t+1} - X_t| of one agent).
    """
    X = np.asarray(positions, dtype=np.float64).reshape(len(positions), -1, 3)
    index = cloud_index(np.ascontiguousarray(points, dtype=np.float64))
    score = CoverageScore(index, target, agent_radius, h, X.shape[1])
    for x in X:
        score.add(x)
    return score.metrics()


class CoverageScore:
    """:func:`coverage_score`, kept up to date one step at a time (O(points near X_t + |T|) a step).

    Parameters
    ----------
    index : the cloud's :class:`~tergodic_cli.explore.index.CloudIndex` (its tree and order).
    target : (n,) target weight p in the cloud's order.
    agent_radius : r_a, metres.
    h : mean point spacing, metres.
    n_agents : agents whose positions are added each step.
    """

    def __init__(self, index, target: np.ndarray, agent_radius: float, h: float, n_agents: int = 1):
        self._tree = index.tree
        n = len(index.order)
        self._nrm, gap = sheet_normals(index, h)
        self._cov = np.zeros(n)
        self._touched = np.zeros(n, dtype=np.int8)
        self._ss = np.zeros(5)
        nb = min(K.NORMAL_NEIGHBOURS, n)
        self._target = np.zeros(n, dtype=np.int8)
        self._sc = K.Score(self._cov, self._touched, self._target, self._ss, np.zeros(n, dtype=np.int64),
                           np.zeros(nb, dtype=np.int64), np.zeros(nb))
        self._args = (K.plain(self._tree), K.plain(self._sc))
        self._prm = np.zeros(K.N_SC)
        # the paper's footprint at ε = 2/r_a, whatever ε the explorer ran with: a neutral score
        self._prm[[K.SC_EPS2, K.SC_CUT, K.SC_RA, K.SC_OFFDIST]] = (footprint_epsilon(agent_radius) ** 2,
                                                                 SCORE_CUT * agent_radius, agent_radius, OFF_SURFACE_H * h)
        self._prm[K.SC_GAP] = gap
        self._prm[K.SC_OFFSHEET] = max(OFF_SHEET_H * h, gap)
        self._prev = np.zeros((n_agents, 3))
        self.set_target(target, index)

    def set_target(self, target: np.ndarray, index) -> None:
        """A new target p (a re-capture): the coverage so far is kept, touched is re-counted.

        Parameters
        ----------
        target : (n,) float
            p in [0, 1].
        index : CloudIndex
            The cloud's index (:func:`~tergodic_cli.explore.index.cloud_index`).
        """
        p = np.asarray(target, dtype=np.float64)[index.order]
        self._tlist = np.flatnonzero(p > 0)
        self._target[:] = p > 0
        self._pplain = p / p.sum()
        self._ss[K.SS_TOUCHED] = float(np.count_nonzero(self._touched[self._tlist]))

    def add(self, positions: np.ndarray) -> None:
        """Score one step.

        Parameters
        ----------
        positions : (N, 3) float
            The agents' positions, metres.
        """
        K.score_step(self._args[0], self._nrm, self._args[1], self._prm,
                     np.ascontiguousarray(positions, dtype=np.float64), self._prev)

    def epsilon_for(self, target: np.ndarray, index) -> float:
        """ε of the coverage so far against another target, e.g. the captured per-point p of a cloud
        whose score uses its target at the fields' resolution.

        Parameters
        ----------
        target : (n,) float
            p >= 0, cloud order.
        index : CloudIndex
            The cloud's index (:func:`~tergodic_cli.explore.index.cloud_index`).

        Returns
        -------
        float
            ε (dimensionless; 1 before any step).
        """
        p = np.asarray(target, dtype=np.float64)[index.order]
        ss = self._ss
        return float(K.score_epsilon(self._cov, np.flatnonzero(p > 0), p / p.sum(), ss)) if ss[K.SS_N] else 1.0

    def metrics(self) -> dict:
        """The score so far.

        Returns
        -------
        dict
            ``ergodicity`` (dimensionless), ``touched_fraction``, ``off_surface_fraction``, ``step_max_m`` (metres).
        """
        ss = self._ss
        n = max(ss[K.SS_N], 1.0)
        return {"ergodicity": K.score_epsilon(self._cov, self._tlist, self._pplain, ss) if ss[K.SS_N] else 1.0,
                "touched_fraction": float(ss[K.SS_TOUCHED] / len(self._tlist)),
                "off_surface_fraction": float(ss[K.SS_OFF] / n), "step_max_m": float(ss[K.SS_STEPMAX])}
