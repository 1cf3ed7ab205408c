"""The HEDAC explorer on a point cloud (paper section IV-A).

One :meth:`Explorer.step` deposits the footprint (eqs. 3, 30-31), updates the source (eqs. 1-2),
diffuses (eq. 4, 19 or the implicit baseline, ``integrator``) and moves each agent along the heat
gradient of a weighted cubic fit (eqs. 32-33) plus the footprint gain's, projected onto the CGA
primitive fitted to its neighbours (eqs. 23-27) and kept on the data; docs/explore.md, "One step".
With the spectral integrators the source's coefficients are kept incrementally, so a step costs
the points under the footprint and nK, not the cloud's size (docs/speed.md); the whole step is one
compiled call (:func:`kernels.step_kernel`).
"""

from __future__ import annotations

import math
import time
import warnings
from typing import Callable

import numpy as np

from tergodic_cli.capture.filters import FIELD_VOXEL, mean_spacing, thins, voxel_standins
from tergodic_cli.errors import require
from tergodic_cli.explore import kernels as K
from tergodic_cli.explore.config import ExploreConfig, parse_alpha, validate_config
from tergodic_cli.explore.diffusion import ImplicitDiffusion, time_step
from tergodic_cli.explore.footprint import footprint, residual, source
from tergodic_cli.explore.index import cached, cloud_index, sheet_normals
from tergodic_cli.explore.metrics import CoverageScore, source_term
from tergodic_cli.explore.transit import (ARRIVE_RA, BAN_RA, STALL_FALL, STALL_WINDOW, Transit, choose_goal, path_to, paths_from,
                                          stalled, surface_graph)

class FieldSet:
    """The points that carry the explorer's fields: ``sel`` (m,) cloud indices, ``rep`` (n,) the
    position in ``sel`` that stands for each cloud point, ``mass`` (m,) the summed lumped mass of
    the points each stands for (m²), ``points`` (m, 3), ``h`` their mean spacing (metres),
    ``rows`` (m,) each one's row of the basis' eigenvectors.

    A basis on stand-ins (:attr:`Basis.thinned <tergodic_cli.basis.Basis.thinned>`) gives them; a
    basis on every point of a cloud much denser than a 3 mm capture is thinned here by the same
    rule (:func:`~tergodic_cli.capture.filters.voxel_standins` at
    :data:`~tergodic_cli.capture.filters.FIELD_VOXEL`), unless ``whole``.
    """

    def __init__(self, basis, whole: bool = False):
        points, mass, h = basis.points, basis.point_mass, basis.h
        n = len(points)
        self.from_basis = basis.thinned
        self.thinned = basis.thinned or (thins(h) and not whole)
        if basis.thinned:
            self.sel, self.rep, self.mass = basis.sel, basis.rep, basis.mass
            self.rows = np.arange(len(basis.sel))
        elif not self.thinned:
            self.sel, self.rep, self.mass, self.points, self.h = np.arange(n), np.arange(n), mass, points, h
            self.rows = self.sel
            return
        else:
            self.sel, self.rep = voxel_standins(points, FIELD_VOXEL)
            self.mass = np.bincount(self.rep, weights=mass, minlength=len(self.sel))
            self.rows = self.sel
        self.points = np.ascontiguousarray(points[self.sel])
        self.h = mean_spacing(self.points)


class Explorer:
    """HEDAC exploration state on one cloud; see the module docstring for one step.

    Parameters
    ----------
    basis : :class:`tergodic_cli.basis.Basis` of the cloud (truncated to ``cfg.nk``).
    target : (n,) target weight p >= 0 per cloud point (any scale; normalised internally).
    cfg : :class:`ExploreConfig`.
    starts : (N, 3) start positions, metres, N = cfg.n_agents; projected onto the surface.
    on_event : callable(str) for warnings (default: :func:`warnings.warn`); a public attribute, so a
        run may route them to its log once it has one.

    Attributes (read-only, updated by every step)
    ----------
    positions : (N, 3) projected agent positions, metres.
    velocities : (N, 3) m/s, tangent to the surface.
    accelerations : (N, 3) commanded accelerations of the last step, m/s².
    normals : (N, 3) unit surface normals at ``positions``; the line L_a⊥ is positions + s·normals.
    neighbours : (N, n_N) indices of each agent's n_N nearest cloud points (its fit patch).
    coverage : (n,) raw accumulated footprint c̃.
    heat : (n,) the potential u (reconstructed on access, O(n nK)).
    source : (n,) s = max(p̄ - c̄, 0)² (eq. 1), 1/m⁴ (computed on access).
    step_index : steps done.
    last_step_ms : wall time of the last :meth:`step`, metrics included.
    edge_events : how many moves were refused because they left the data (edge, hole, gap).
    resync_drift : largest relative correction a periodic full recompute has made to the
        incrementally kept ∫s and Φᵀ M s (round-off; 0 before the second recompute).
    transits : how many transits along the surface the stagnation check has started (transit.py;
        each is announced through ``on_event``, "transit: ...").
    """

    def __init__(self, basis, target: np.ndarray, cfg: ExploreConfig, starts: np.ndarray,
                 on_event: Callable[[str], None] | None = None):
        validate_config(cfg)
        self.cfg = cfg
        self.on_event = on_event or (lambda msg: warnings.warn(msg, stacklevel=3))
        n = len(basis.points)
        require(basis.nk >= cfg.nk, f"nK = {cfg.nk} is larger than the basis ({basis.nk} eigenpairs)",
                f"compute a basis with --nk {cfg.nk} or use --nk <= {basis.nk}")
        require(int(cfg.n_neighbors) <= n, f"--fit-neighbors {cfg.n_neighbors} exceeds the {n} cloud points",
                "use fewer neighbours")
        self._basis = basis
        self.points = np.ascontiguousarray(basis.points, dtype=np.float64)
        self.mass = basis.point_mass  # (n,) per cloud point, m²
        self.h = float(basis.h)
        self.evals = basis.evals[: cfg.nk]
        self.eps = cfg.footprint_epsilon
        self.r_a = float(cfg.agent_radius)
        self._k = int(cfg.n_neighbors)
        self._full = cloud_index(self.points)  # what lies on the data, the score, the starts
        # The fields live on the cloud, or on its stand-ins when the cloud is much denser than a 3 mm
        # capture (the implicit integrator needs L where the fields are: the basis' stand-ins, or all);
        # built once per cloud, or per stand-in map (the basis' own, whichever cache entry it came from).
        fset = cached("fields", basis.rep if basis.thinned else self.points, lambda: FieldSet(basis))
        if fset.thinned and not fset.from_basis and cfg.integrator == "implicit":
            fset = FieldSet(basis, whole=True)
        self._field = fset
        index = cloud_index(fset.points)
        self._order, self._rank, self._P, self._tree = index.order, index.rank, index.points, index.tree
        # each field point's normal line, fitted to its own sheet: once per cloud (docs/explore.md)
        self._nrm, gap = sheet_normals(index, fset.h, oriented=cfg.sheets == "separate")
        phis = cached("phi", basis.evecs, dict)  # Φ[:, :nK], rows in internal order: once per nK and point set
        key = (cfg.nk, len(fset.sel))  # the whole cloud, or its field set (one per cloud)
        if key not in phis:
            phis[key] = np.ascontiguousarray(basis.evecs[fset.rows[self._order], : cfg.nk], dtype=np.float64)
        self._phi = phis[key]
        n = len(fset.sel)
        if self.r_a < self.h:
            self.on_event(f"warning: agent radius {self.r_a * 1e3:.2f} mm is below the point spacing h = "
                      f"{self.h * 1e3:.2f} mm; the footprint may miss points (use --agent-radius >= h)")
        self._spectral = cfg.integrator in ("spectral", "resolvent")
        self._mode = (K.HEAT_FULL if not self._spectral else
                      K.HEAT_CARRY if cfg.diffusion == "carry" else K.HEAT_SOURCE)
        self._schedule = parse_alpha(cfg.alpha)
        self._alpha = None
        self._implicit: dict[float, ImplicitDiffusion] = {}

        # Per-point state, packed for the compiled step (kernels.PF_*, PB_*, PI_* rows).
        self._pf = np.zeros((K.N_PF, n))
        self._pf[K.PF_MASS] = fset.mass[self._order]
        self._pb = np.zeros((K.N_PB, n), dtype=np.int8)
        self._pi = np.zeros((K.N_PI, n), dtype=np.int64)
        self._sp = np.zeros((K.N_SP, cfg.nk))
        self._fs = np.zeros(K.N_FS)
        self._is = np.zeros(K.N_IS, dtype=np.int64)
        self._prm = np.zeros(K.N_PR)
        self._prm[K.PR_EPS2] = self.eps * self.eps
        self._prm[K.PR_RA] = self.r_a
        self._prm[K.PR_H2] = fset.h * fset.h
        self._prm[K.PR_AMAX] = cfg.a_max
        self._prm[K.PR_VMAX] = cfg.v_max
        self._prm[K.PR_DT] = cfg.dt
        self._prm[K.PR_MAXSTART] = cfg.max_start_distance
        self._prm[K.PR_REACH] = K.SURFACE_REACH * self.h
        self._prm[K.PR_HEAT] = cfg.heat_weight
        # "mixed": no gap splits the neighbours (inf), the fit takes all n_N as the paper does
        self._prm[K.PR_SHEET_GAP] = gap if cfg.sheets == "separate" else math.inf
        # The gain is a footprint integral (∫φ = π/ε²): per unit area it weighs like the heat.
        geps = self.eps / cfg.gain_width
        self._prm[K.PR_GAIN_EPS2] = geps * geps
        self._prm[K.PR_GAIN] = cfg.gain_weight * geps * geps / math.pi
        self._cov = self._pf[K.PF_COV]
        self._u_full = np.zeros(n if not self._spectral else 0)  # implicit: u in internal order
        self._u_orig = np.zeros(n if not self._spectral else 0)  # ... and in the order of L's rows
        self.step_index, self.last_step_ms = 0, 0.0
        self._score = None
        starts = np.asarray(starts, dtype=np.float64)
        require(starts.ndim == 2 and starts.shape[1] == 3, f"starts must be an (N, 3) array, got shape {starts.shape}",
                "give one x,y,z start per agent")
        require(len(starts) == cfg.n_agents, f"{len(starts)} start positions for {cfg.n_agents} agents",
                "give one start per agent")
        require(bool(np.all(np.isfinite(starts))), "a start position is not finite", "give finite x,y,z in metres")
        N = cfg.n_agents
        self._ag = np.zeros((N, K.N_AG))
        self._nbrs = np.zeros((N, self._k), dtype=np.int64)
        self.positions = self._ag[:, K.AG_POS:K.AG_POS + 3]
        self.velocities = self._ag[:, K.AG_VEL:K.AG_VEL + 3]
        self.accelerations = self._ag[:, K.AG_ACC:K.AG_ACC + 3]
        self.normals = self._ag[:, K.AG_NRM:K.AG_NRM + 3]
        self._resets = np.zeros((N, 3))
        self._reset_status = np.full(N, -1, dtype=np.int64)
        self._no_deposits = np.zeros((0, 3))
        self._resync = int(cfg.resync_every)
        self._ball = np.empty(n + 1, dtype=np.int64)  # the stall check's gain: its points, one more for the anchor
        self._transit: list[Transit | None] = [None] * N
        self._moving = False  # some agent is on a transit
        self.transits = 0
        self.set_target(target)
        hint = np.asarray(cfg.normal_hint, dtype=float)
        hint = hint / np.linalg.norm(hint)
        for i, x0 in enumerate(starts):
            d0 = K.nearest_distance(*self._full.tree, x0)
            require(d0 <= cfg.max_start_distance,
                    f"start {np.array2string(x0, precision=4)} is {d0 * 1e3:.1f} mm from the cloud "
                    f"(limit {cfg.max_start_distance * 1e3:.0f} mm)",
                    "give a start on the object (x,y,z in metres, a point index, or 'random')")
            K.place_agent(self._surface, self._st, i, x0, hint, self._prm[K.PR_REACH], self._prm[K.PR_SHEET_GAP])
            if d0 > self.h:
                self.on_event(f"warning: start {np.array2string(x0, precision=4)} is {d0 * 1e3:.1f} mm off the cloud; "
                          f"projected onto the surface at {np.array2string(self.positions[i], precision=4)}")
            self._to_target_part(i, hint)
        parts = self._parts()
        left = (self.p > 0) & ~np.isin(parts, [self._part_of(i) for i in range(N)])
        share = float(self.mass[left] @ self.p[left]) / float(self.mass @ self.p)
        if share > 0.01:  # an agent never crosses a gap: that share stays untouched
            self.on_event(f"warning: {100 * share:.0f} % of the target lies on parts of the cloud no agent starts "
                          f"on (gaps wider than {2 * K.SURFACE_REACH * self.h * 1e3:.1f} mm, which an agent never "
                          "crosses); give more --agents, or capture those parts separately")

    def _to_target_part(self, i: int, hint: np.ndarray) -> None:
        """Move agent i to the target's part of the cloud when its start is on a part the agent
        cannot leave without leaving the data (a gap wider than 2 x SURFACE_REACH h).

        The parts (built once per cloud) join the points closer than 2 x SURFACE_REACH h, so an
        agent that stays within SURFACE_REACH h of the data can cross between any two points of
        one part and no others."""
        parts, here = self._parts(), self._part_of(i)
        if np.any(self.p[parts == here] > 0):
            return
        reachable = np.flatnonzero(np.isin(parts, np.unique(parts[self.p > 0])))
        x = self.positions[i].copy()
        j = reachable[np.argmin(np.linalg.norm(self.points[reachable] - x, axis=1))]
        K.place_agent(self._surface, self._st, i, self.points[j].copy(), hint, self._prm[K.PR_REACH],
                      self._prm[K.PR_SHEET_GAP])
        self.on_event(f"warning: start {np.array2string(x, precision=4)} is on a part of the cloud the target is not on "
                  f"(a gap wider than {2 * K.SURFACE_REACH * self.h * 1e3:.1f} mm); starting at the nearest point "
                  f"of the target's part, {np.linalg.norm(self.points[j] - x) * 1e3:.1f} mm away")

    def _parts(self) -> np.ndarray:
        """(n,) the cloud's parts (built once per cloud): its points joined closer than 2 x SURFACE_REACH h."""

        def parts_of_cloud():
            from scipy.sparse import coo_matrix
            from scipy.sparse.csgraph import connected_components
            from scipy.spatial import cKDTree

            n, reach = len(self.points), 2.0 * K.SURFACE_REACH * self.h
            pairs = cKDTree(self.points).query_pairs(reach, output_type="ndarray")
            graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
            return connected_components(graph, directed=False)[1]

        return cached("parts", self.points, parts_of_cloud)

    def _part_of(self, i: int) -> int:
        """The part of the cloud agent i stands on."""
        return int(self._parts()[self._field.sel[self._order[self._nbrs[i, 0]]]])

    # ------------------------------------------------------------------ target and state
    def set_target(self, target: np.ndarray, reset_coverage: bool = False) -> None:
        """Use a new target p (n,) from a re-capture; the basis is unchanged.

        The heat restarts from the new p̄ (eq. 5) and the reference heat p̂ of ``residual_ref``
        is re-taken after the next step.

        Parameters
        ----------
        target : (n,) float
            p in [0, 1], in the cloud's order.
        reset_coverage : bool
            Start the coverage from zero (else it is kept).
        """
        p = np.asarray(target, dtype=np.float64)
        n = len(self.points)
        require(p.shape == (n,), f"the target has {p.shape[0] if p.ndim else 0} values but the basis has {n} points",
                "the basis does not match this capture; recompute it with 'tergodic precompute CAPTURE'")
        require(bool(np.all(np.isfinite(p))) and bool(np.all(p >= 0)), "the target has negative or non-finite values",
                "re-capture: p must be >= 0")
        total = float(self.mass @ p)
        require(total > 0, "the target is empty (no point has p > 0)",
                "check the capture's --target colour, or use --target all for uniform coverage")
        if reset_coverage:
            self._cov[:] = 0.0
        self.p = p
        fset = self._field
        n = len(fset.sel)
        # p̄ on the field set: each field point carries the mass-weighted mean of the points it stands for
        held = np.bincount(fset.rep, weights=self.mass * p, minlength=n)
        pbar = (np.divide(held, fset.mass, out=np.zeros(n), where=fset.mass > 0) / total)[self._order]  # internal order
        T = np.flatnonzero(pbar > 0)
        self._T = T
        self._pf[K.PF_PBAR] = pbar
        self._pf[K.PF_PHAT] = 0.0
        self._pb[:] = 0
        self._pb[K.PB_TARGET, T] = 1
        self._pi[K.PI_TARGET, : len(T)] = T
        tgt = K.Tree(*K.tree_build(np.ascontiguousarray(self._P[T])))  # the broad gain's
        # The source's c̄ = c̃/Z: Z over the target (cfg.coverage_norm "target") or the cloud (eq. 2).
        self._prm[K.PR_ZTARGET] = 1.0 if self.cfg.coverage_norm == "target" and len(T) < n else 0.0
        self._heap_keys, self._heap_idx = np.zeros(len(T)), np.zeros(len(T), dtype=np.int64)
        # the state restarts; the run's diagnostics (edge events, work counters, resync drift) survive a new target
        self._is[np.isin(np.arange(K.N_IS), [K.IS_EDGE, K.IS_FOOTPRINT, K.IS_ROWS, K.IS_POPS], invert=True)] = 0
        self._is[K.IS_NTARGET] = len(T)
        self._is[K.IS_TOUCHED] = int(np.count_nonzero(self._cov[T] > 0))
        self._fs[np.arange(K.N_FS) != K.FS_DRIFT] = 0.0
        # the step kernel's arguments, bound once per target (the target's tree and the heap change with it)
        self._surface = K.Surface(self._P, self._nrm, self._tree, self._full.tree, tgt, T.astype(np.int64), self._phi)
        self._st = K.State(self._pf, self._pb, self._pi, self._sp, self._heap_keys, self._heap_idx, self._fs, self._is,
                           self._ag, self._nbrs, self._u_full)
        self._state = (K.plain(self._surface), K.plain(self._st), self._prm)
        K.resync(self._phi, self._st, self._prm[K.PR_ZTARGET])
        self._ref_norm2 = 1.0
        # Φᵀ M p̄: the spectral part of u₀ = p̄ (eq. 5) and of the reference heat p̂.
        pbar_coef = K.project_rows(self._phi, self._pf[K.PF_MASS] * pbar)
        self._sp[K.SP_PBARCOEF] = pbar_coef
        self._sp[K.SP_A] = 0.0
        self._sp[K.SP_B] = pbar_coef  # u₀ = Φ a + r with Φᵀ M r = b: a = 0, r = p̄
        if not self._spectral:
            self._u_full[:] = pbar
            self._u_orig[:] = pbar[self._rank]
        # The score's target: p itself, or, on a field set thinned to 3 mm stand-ins (a cloud much denser
        # than a 3 mm capture), each point's stand-in mean, which the explorer seeks (p̄ above): the 3 mm
        # capture's own rule, so a 1M-point scan and its 3 mm capture score alike (issue 27; the per-point
        # p is scored too, score()["ergodicity_point_target"]).
        self._p_score = p
        if fset.thinned:
            self._p_score = np.divide(held, fset.mass, out=np.zeros(n), where=fset.mass > 0)[fset.rep]
        if self._score is None:
            self._score = CoverageScore(self._full, self._p_score, self.r_a, self.h, self.cfg.n_agents)
        else:
            self._score.set_target(self._p_score, self._full)
        self._set_metrics(float("nan"))
        self._gain_of_target = None  # the gain's kernel over T, built at the first stall check
        self._banned = np.zeros(len(T), dtype=bool)  # target points a transit could not reach
        self._s_then, self._next_check = math.inf, STALL_WINDOW

    def _set_metrics(self, residual_ref: float) -> None:
        sc = self._score.metrics()
        self._metrics = {"ergodicity": sc["ergodicity"], "residual_ref": residual_ref,
                         "touched_fraction": sc["touched_fraction"]}

    @property
    def edge_events(self) -> int:
        return int(self._is[K.IS_EDGE])

    @property
    def resync_drift(self) -> float:
        return float(self._fs[K.FS_DRIFT])

    @property
    def work(self) -> dict:
        """Work counters since the start: footprint points visited, rows of Φ added into the
        source accumulators (deposits and threshold crossings), full recomputes."""
        return {"footprint_points": int(self._is[K.IS_FOOTPRINT]), "spectral_rows": int(self._is[K.IS_ROWS]),
                "heap_pops": int(self._is[K.IS_POPS]), "resyncs": int(self._is[K.IS_RESYNCS])}

    @property
    def kdtree(self):
        """scipy cKDTree of the cloud (the basis'; built on first use)."""
        return self._basis.kdtree

    @property
    def coverage(self) -> np.ndarray:
        """(n,) raw coverage c̃ in the cloud's order (a copy; on a thinned cloud, each point's field point's)."""
        return self._cov[self._rank][self._field.rep]

    @property
    def neighbours(self) -> np.ndarray:
        """(N, n_N) each agent's n_N nearest cloud points (a copy): those on its sheet, its fit
        patch, first (:attr:`sheet_neighbours` of them), each group nearest first."""
        return self._field.sel[self._order[self._nbrs]]

    @property
    def sheet_neighbours(self) -> np.ndarray:
        """(N,) how many of each agent's :attr:`neighbours` lie on its sheet (its fit patch)."""
        return self._ag[:, K.AG_NKEEP].astype(np.int64)

    @property
    def source(self) -> np.ndarray:
        return source_term(self.p, self.coverage, self.mass, norm=self.cfg.coverage_norm)

    def _s_target(self, Z: float) -> np.ndarray:
        """s = max(p̄ - c̃/Z, 0)² on the target's points ``self._T`` (internal order)."""
        T = self._T
        return source(self._pf[K.PF_PBAR, T], self._cov[T] / Z if Z > 0 else 0.0)

    def _sbar(self, Z: float | None = None) -> np.ndarray:
        """(m,) the injected source s/∫s in internal order: as the step used it (running Z and ∫s), or
        with coverage normaliser ``Z`` and ∫s summed afresh."""
        out = np.zeros(len(self._field.sel))
        s = self._s_target(self._fs[K.FS_Z] if Z is None else Z)
        total = self._fs[K.FS_MASS_S] if Z is None else float(self._pf[K.PF_MASS, self._T] @ s)
        if total > 0:
            out[self._T] = s / total
        return out

    @property
    def heat(self) -> np.ndarray:
        """(n,) the potential u in the cloud's order (reconstructed: O(n nK))."""
        f = self._field
        if not self._spectral:
            return self._u_orig[f.rep] if f.from_basis else self._u_orig.copy()
        if f.from_basis:  # every point takes its stand-in's
            u = K.expand_rows(self._phi, self._sp[K.SP_A])[self._rank]
            if self._mode == K.HEAT_CARRY:
                u += self._sbar()[self._rank]
            return u[f.rep]
        if f.thinned:  # the spectral part on every point; the residual from each one's field point
            u = K.expand_rows(np.ascontiguousarray(self._basis.evecs[:, : self.cfg.nk]), self._sp[K.SP_A])
        else:
            u = K.expand_rows(self._phi, self._sp[K.SP_A])[self._rank]
        if self._mode == K.HEAT_CARRY:
            u += self._sbar()[self._rank][f.rep]
        return u

    def metrics(self) -> dict:
        """The metrics after the last step (see docs/explore.md).

        Returns
        -------
        dict
            ``ergodicity`` and ``touched_fraction`` (the neutral score of
            :func:`metrics.coverage_score`) and ``residual_ref`` (the authors' residual), floats.
        """
        return dict(self._metrics)

    def score(self) -> dict:
        """The neutral score so far.

        Returns
        -------
        dict
            ``ergodicity``, ``touched_fraction``, ``off_surface_fraction`` and ``step_max_m`` (metres); on
            a field set thinned to 3 mm stand-ins, whose ε scores the target at that resolution, also
            ``ergodicity_point_target``: ε of the same coverage against the captured per-point p.
        """
        out = self._score.metrics()
        if self._field.thinned:
            out["ergodicity_point_target"] = self._score.epsilon_for(self.p, self._full)
        return out

    @property
    def score_target(self) -> np.ndarray:
        """(n,) the target p the score's ε is measured against, cloud order: :attr:`p`, or on a field
        set thinned to 3 mm stand-ins each point's stand-in mean of p."""
        return self._p_score

    @property
    def alpha(self) -> float:
        """α in effect for the next step."""
        return [a for s, a in self._schedule if s <= self.step_index][-1]

    def _set_alpha(self) -> None:
        alpha = self.alpha
        if alpha != self._alpha:
            self._alpha = alpha
            dt = time_step(alpha)
            if self.cfg.integrator == "spectral":
                self._sp[K.SP_DECAY] = np.exp(-self.evals * dt)  # eq. 19
            elif self.cfg.integrator == "resolvent":
                self._sp[K.SP_DECAY] = 1.0 / (1.0 + self.evals * dt)  # eq. 4: (M + δt L)⁻¹ M in the eigenbasis
            elif alpha not in self._implicit:
                self._implicit[alpha] = ImplicitDiffusion(self._basis.L, self._basis.mass, dt)

    # ------------------------------------------------------------------ the step
    def step(self, deposit_at: np.ndarray | None = None, agent_at: np.ndarray | None = None) -> None:
        """One explorer step (see the module docstring).

        Parameters
        ----------
        deposit_at : None (kinematic: deposit at the agents' projected positions) or (m, 3)
            tool contact points in force, metres (m may be 0: no contact, no coverage).
        agent_at : None, or (N, 3) positions the agents are reset to (projected) before the
            gradient step, e.g. the measured tool tip (eq. 22).
        """
        t0 = time.perf_counter()
        if self._alpha is None or len(self._schedule) > 1:  # a constant α is set once, not every step
            self._set_alpha()
        if deposit_at is None:
            deposits, n_dep = self._no_deposits, -1
        else:
            deposits = np.ascontiguousarray(deposit_at, dtype=np.float64).reshape(-1, 3)
            n_dep = len(deposits)
        status = self._reset_status
        status[:] = -1  # no reset; 0: reset to self._resets, which the kernel turns to -2 when it is refused
        if agent_at is not None:
            at = np.asarray(agent_at, dtype=np.float64).reshape(-1, 3)
            require(len(at) == len(self.positions), f"agent_at has {len(at)} rows for {len(self.positions)} agents",
                    "give one position per agent")
            self._resets[:] = at
            status[:] = 0
        if self._moving:
            self._steer()
        args = (*self._state, deposits, n_dep, self._resets, status, self._mode, self._resync)
        if self._spectral:
            K.step_kernel(*args, 0)
        else:  # coverage and source, the full field's diffusion, the agents
            K.step_kernel(*args, 1)
            self._diffuse_full()
            K.step_kernel(*args, 2)
        for i in np.flatnonzero(status == -2) if agent_at is not None else ():  # no search on a plain step
            self.on_event(f"warning: step {self.step_index}: agent {i} reset point is "
                          f"{self._resets[i, 0] * 1e3:.1f} mm off the cloud; ignored")
        self.step_index += 1
        if self._is[K.IS_PHAT] == 0:
            self._take_reference_heat()
        if self.step_index >= self._next_check:  # every STALL_WINDOW steps, not on the others
            self._check_stall()
        self.last_step_ms = 1e3 * (time.perf_counter() - t0)
        # The neutral score (metrics.coverage_score) is instrumentation: outside the step's time.
        self._score.add(self.positions)
        untouched = max(float(self._fs[K.FS_REF_UNTOUCHED]), 0.0)
        self._set_metrics(math.sqrt(untouched / self._ref_norm2))

    def _diffuse_full(self) -> None:
        """The implicit integrator on the whole field: u <- (M + δt L)⁻¹ M u + s̄ (carry) or u = ... s̄."""
        sbar = self._sbar(self._fs[K.FS_Z])[self._rank]  # the sparse operator works in the cloud's order
        op = self._implicit[self._alpha]
        if self.cfg.diffusion == "carry":
            self._u_orig[:] = op.apply(self._u_orig) + sbar
        else:
            self._u_orig[:] = op.apply(sbar)
        self._u_full[:] = self._u_orig[self._order]

    def _take_reference_heat(self) -> None:
        """p̂ of ``residual_ref``: the heat after the first step of the carry-over scheme,
        e^{-δtL} p̄ + s̄₁ (the published code's), whichever diffusion drives the agents, so
        that the metric compares runs and variants on the same footing. O(n nK), once."""
        decay = np.exp(-self.evals * time_step(self._alpha))
        u = K.expand_rows(self._phi, decay * self._sp[K.SP_PBARCOEF])  # internal order
        if self._prm[K.PR_ZTARGET] == 0.0:
            u += self._sbar()
        else:  # the published code's s̄₁ has the cloud-normalised coverage (eq. 2), whatever drives the agents
            u += self._sbar(self._fs[K.FS_ZC])
        total = float(u.sum())
        require(total > 0 and math.isfinite(total), "the heat after the first step has no positive mass",
                "check the target and the basis (non-finite eigenvectors?)")
        phat = u / total
        self._pf[K.PF_PHAT] = phat
        self._ref_norm2 = float(phat @ phat)
        untouched = phat[self._cov == 0]
        self._fs[K.FS_REF_UNTOUCHED] = float(untouched @ untouched)
        self._is[K.IS_PHAT] = 1

    # ------------------------------------------------------------------ never trapped (transit.py)
    def _check_stall(self) -> None:
        """The stagnation check (every STALL_WINDOW steps): when ∫s has not fallen by STALL_FALL since
        the last check and an agent stands where the footprint gain is below STALL_GAIN of the best
        it can reach, that agent (the lowest such) starts a transit (transit.choose_goal)."""
        self._next_check = self.step_index + STALL_WINDOW
        s_now = float(self._fs[K.FS_MASS_S])
        s_then, self._s_then = self._s_then, s_now
        if not s_now > (1.0 - STALL_FALL) * s_then:
            return  # progress (or the first window): no further work
        T = self._T
        zc = float(self._fs[K.FS_ZC])
        e = residual(self._pf[K.PF_PBAR, T], self._cov[T] / zc if zc > 0 else 0.0)
        w = self._pf[K.PF_MASS, T] * e
        gain = self._target_kernel() @ w  # G at every target point: what a deposit there would remove
        separate = self.cfg.sheets == "separate"  # then along the explorer's own oriented sheet normals
        graph = cached(f"surface_graph {separate}", self._P, lambda: surface_graph(
            self._P, 2.0 * K.SURFACE_REACH * self._field.h, normals=self._nrm if separate else None))
        worst = None
        for i in range(len(self.positions)):
            src = int(self._nbrs[i, 0])
            dist, pred = paths_from(graph, src)
            ok = np.isfinite(dist[T]) & ~self._banned
            if not np.any(ok):
                continue
            best = float(np.max(gain[ok]))
            # G where the agent stands, over its own sheet (kernels.sheet_of): residual seen through a
            # wall is nothing a deposit here would remove, so an agent parked under it is stalled
            here = K.gain_gradient(self._surface, self._st, self._prm, self.positions[i],
                                   self._ag[i, K.AG_T1:K.AG_T1 + 3], self._ag[i, K.AG_T2:K.AG_T2 + 3], self._ball, src,
                                   self._prm[K.PR_SHEET_GAP], False)[1]
            if stalled(s_then, s_now, here, best) and (worst is None or here / best < worst[0]):
                worst = (here / best, i, src, dist, pred, gain)
        if worst is not None:
            ratio, i, src, dist, pred, gain = worst
            j = choose_goal(dist[T], gain, banned=self._banned)
            if j >= 0:
                self._start_transit(i, path_to(pred, src, int(T[j])), s_then, s_now, ratio)

    def _target_kernel(self):
        """(|T|, |T|) sparse footprint-gain kernel over the target's points, G = K (M e); once per target."""
        if self._gain_of_target is None:
            from scipy.sparse import coo_matrix
            from scipy.spatial import cKDTree

            T = self._T
            eps2 = self._prm[K.PR_GAIN_EPS2]
            pts = self._P[T]
            pairs = cKDTree(pts).query_pairs(K.GAIN_REACH / math.sqrt(eps2), output_type="ndarray")
            k = footprint(eps2, np.sum((pts[pairs[:, 0]] - pts[pairs[:, 1]]) ** 2, axis=1))
            m = len(T)
            i = np.concatenate([pairs[:, 0], pairs[:, 1], np.arange(m)])
            j = np.concatenate([pairs[:, 1], pairs[:, 0], np.arange(m)])
            self._gain_of_target = coo_matrix((np.concatenate([k, k, np.ones(m)]), (i, j)), shape=(m, m)).tocsr()
        return self._gain_of_target

    def _start_transit(self, i: int, path: np.ndarray, s_then: float, s_now: float, ratio: float) -> None:
        """Agent i follows ``path`` (field point indices, from its nearest point to the goal)."""
        if len(path) < 2:
            return
        tr = Transit(self._P[path], self.cfg.v_max * self.cfg.dt, ARRIVE_RA * self.r_a)
        self._transit[i] = tr
        self._moving = True
        self.transits += 1
        self._next_check = math.inf  # no check while a transit runs; the window restarts on arrival
        self.on_event(f"transit: step {self.step_index}: agent {i} stalled (∫s {s_then:.4g} -> {s_now:.4g} over "
                      f"{STALL_WINDOW} steps, the gain where it stands {100 * ratio:.1f} % of the best it can "
                      f"reach); moving {tr.length * 1e3:.0f} mm along the surface to "
                      f"{np.array2string(tr.points[-1], precision=4)}")

    def _steer(self) -> None:
        """Set each transiting agent's velocity to track (kernels.AG_VD); end the transits that are over."""
        for i, tr in enumerate(self._transit):
            if tr is None:
                continue
            v = tr.velocity(self.positions[i], self.normals[i], self.cfg.v_max)
            if v is not None:
                self._ag[i, K.AG_VD:K.AG_VD + 3] = v
                self._ag[i, K.AG_TRANSIT] = 1.0
                continue
            self._ag[i, K.AG_TRANSIT] = 0.0
            self._transit[i] = None
            if not tr.arrived:  # not chosen again: the goal may lie beyond what the agent can follow
                self._banned |= np.linalg.norm(self._P[self._T] - tr.points[-1], axis=1) <= BAN_RA * self.r_a
            self.on_event(f"transit: step {self.step_index}: agent {i} "
                          + (f"arrived after {tr.steps - 1} steps" if tr.arrived else
                             f"gave up after {tr.steps - 1} steps, {np.linalg.norm(tr.points[-1] - self.positions[i]) * 1e3:.0f} mm short"))
        self._moving = any(tr is not None for tr in self._transit)
        if not self._moving:
            self._s_then, self._next_check = float(self._fs[K.FS_MASS_S]), self.step_index + STALL_WINDOW

