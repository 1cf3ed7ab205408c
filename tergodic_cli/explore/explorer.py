"""The HEDAC explorer on a point cloud (paper section IV-A).

One :meth:`Explorer.step`:

1. deposit the footprint φ(r) = exp(-ε² r²) (eq. 30) on the cloud points within r_a of each
   agent, r measured in the agent's tangent plane (eq. 31), into the raw coverage c̃ shared
   by all agents (eq. 3) - or, in robot mode, at the given contact points;
2. source s = max(p̄ - c̄, 0)² (eq. 1) with p̄ and c̄ = c̃ / ∫c̃ normalised to unit mass with M
   (eq. 2); it is injected as s / ∫s, so every step adds unit mass whatever the residual;
3. diffuse with δt = α h² (eq. 21): ``carry`` u <- D u + s/∫s from u₀ = p̄ (eq. 5), or
   ``source`` u = D s/∫s, where D is, by ``integrator``: ``resolvent`` Φ (1 + λδt)⁻¹ Φᵀ M
   (eq. 4, the stationary HEDAC equation, in the eigenbasis), ``spectral`` Φ e^{-λδt} Φᵀ M
   (eq. 19) or ``implicit`` (M + δt L)⁻¹ M (sparse, exact);
4. for each agent: ∇u at its projected position from a weighted cubic fit (eqs. 32-33; a plane
   when the agent is off the sampled surface), acceleration a = a_max ∇u/|∇u| (eq. 6
   saturated: u has no physical scale), semi-implicit Euler v <- clip(v + a δt, v_max),
   x <- x + v δt; then x is projected onto the CGA plane/sphere fitted to its n_N nearest
   points (eqs. 23-27) and v is turned into the new tangent plane keeping its speed. An agent
   that slid off the object (farther from its nearest point than r_a or that point's longest
   Laplacian edge) is put back at that distance and its velocity reflected.

Per-step cost is independent of the number of cloud points except through the target:
the source and its spectral projection live on the target points only, the heat is
evaluated only at the agents' neighbours, and the metrics are updated incrementally.
(The ``implicit`` integrator solves with the sparse factor: O(n) or so per step.)
"""

from __future__ import annotations

import math
import time
import warnings
from typing import Callable

import numpy as np

from tergodic_cli.errors import TergodicError, require
from tergodic_cli.explore.config import ExploreConfig, parse_alpha, validate_config
from tergodic_cli.explore.diffusion import ImplicitDiffusion, time_step
from tergodic_cli.explore.geometry import fit_primitive, orient, project_onto, tangent_basis
from tergodic_cli.explore.gradient import fit_cubic

#: Iterations of "fit, project, re-query" that bring a start point onto the surface.
START_ITERATIONS = 8


class Explorer:
    """HEDAC exploration state on one cloud; see the module docstring for one step.

    Parameters
    ----------
    basis : :class:`tergodic_cli.basis.Basis` of the cloud (truncated to ``cfg.nk``).
    target : (n,) target weight p >= 0 per cloud point (any scale; normalised internally).
    cfg : :class:`ExploreConfig`.
    starts : (N, 3) start positions, metres, N = cfg.n_agents; projected onto the surface.
    on_event : callable(str) for warnings (default: :func:`warnings.warn`).

    Attributes (read-only, updated by every step)
    ----------
    positions : (N, 3) projected agent positions, metres.
    velocities : (N, 3) m/s, tangent to the surface.
    accelerations : (N, 3) commanded accelerations of the last step, m/s².
    normals : (N, 3) unit surface normals at ``positions``; the line L_a⊥ is positions + s·normals.
    coverage : (n,) raw accumulated footprint c̃.
    heat : (n,) the potential u (evaluated on access).
    source : (n,) s = max(p̄ - c̄, 0)² (eq. 1), 1/m⁴.
    step_index : steps done.
    last_step_ms : wall time of the last :meth:`step`, metrics included.
    edge_events : how many times an agent was pulled back onto the cloud.
    """

    def __init__(self, basis, target: np.ndarray, cfg: ExploreConfig, starts: np.ndarray,
                 on_event: Callable[[str], None] | None = None):
        validate_config(cfg)
        self.cfg = cfg
        self._say = on_event or (lambda msg: warnings.warn(msg, stacklevel=3))
        n = len(basis.points)
        require(basis.nk >= cfg.nk, f"nK = {cfg.nk} is larger than the basis ({basis.nk} eigenpairs)",
                f"compute a basis with --nk {cfg.nk} or use --nk <= {basis.nk}")
        require(int(cfg.n_neighbors) <= n, f"--fit-neighbors {cfg.n_neighbors} exceeds the {n} cloud points",
                "use fewer neighbours")
        self.points = basis.points
        self.mass = basis.mass
        self.h = float(basis.h)
        self.kdtree = basis.kdtree
        self.evecs = np.ascontiguousarray(basis.evecs[:, : cfg.nk])
        self.evals = basis.evals[: cfg.nk]
        self._L = basis.L
        self.eps = cfg.footprint_epsilon
        self.r_a = float(cfg.agent_radius)
        # Off-cloud guard: the fitted plane of an open sheet extends past its last points, so an
        # agent may slide off the object. It may stray from its nearest point j by at most
        # max(r_a, ℓ_j), ℓ_j the longest Laplacian edge at j: gaps the Laplacian bridges (and
        # the heat flows across) stay crossable, as in the paper's bunny ear; beyond, it is pulled back.
        Lc = basis.L.tocoo()
        off = Lc.row != Lc.col
        lengths = np.linalg.norm(self.points[Lc.row[off]] - self.points[Lc.col[off]], axis=1)
        self._reach = np.full(len(self.points), self.r_a)
        np.maximum.at(self._reach, Lc.row[off], lengths)
        if self.r_a < self.h:
            self._say(f"warning: agent radius {self.r_a * 1e3:.2f} mm is below the point spacing h = "
                      f"{self.h * 1e3:.2f} mm; the footprint may miss points (use --agent-radius >= h)")
        self._spectral = cfg.integrator in ("spectral", "resolvent")
        self._schedule = parse_alpha(cfg.alpha)
        self._alpha = None
        self._implicit: dict[float, ImplicitDiffusion] = {}

        self.coverage = np.zeros(n)
        self._cov_mass = 0.0  # ∫c̃ = Σ M c̃
        self.step_index = 0
        self.last_step_ms = 0.0
        self.edge_events = 0
        self._heat_cache: tuple[int, np.ndarray] | None = None
        self.set_target(target)

        starts = np.asarray(starts, dtype=np.float64)
        require(starts.ndim == 2 and starts.shape[1] == 3, f"starts must be an (N, 3) array, got shape {starts.shape}",
                "give one x,y,z start per agent")
        require(len(starts) == cfg.n_agents, f"{len(starts)} start positions for {cfg.n_agents} agents",
                "give one start per agent")
        require(bool(np.all(np.isfinite(starts))), "a start position is not finite", "give finite x,y,z in metres")
        N = cfg.n_agents
        self.positions = np.zeros((N, 3))
        self.velocities = np.zeros((N, 3))
        self.accelerations = np.zeros((N, 3))
        self.normals = np.zeros((N, 3))
        self._nbrs: list[np.ndarray] = [np.zeros(0, dtype=np.intp)] * N
        self._frames: list[np.ndarray] = [np.zeros((3, 2))] * N
        hint = np.asarray(cfg.normal_hint, dtype=float)
        hint = hint / np.linalg.norm(hint)
        for i, x0 in enumerate(starts):
            self._place(i, x0, hint)

    # ------------------------------------------------------------------ target and state
    def set_target(self, target: np.ndarray, reset_coverage: bool = False) -> None:
        """Use a new target p (n,) from a re-capture; the basis is unchanged.

        Coverage is kept unless ``reset_coverage``; the heat restarts from the new p̄ (eq. 5) and
        the reference heat p̂ of ``ergodicity_ref`` is re-taken after the next step.
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
            self.coverage[:] = 0.0
            self._cov_mass = 0.0
        self.p = p
        self._T = np.flatnonzero(p > 0)
        self._is_target = p > 0
        self._pT = p[self._T] / total  # p̄ on the target points
        self._mT = self.mass[self._T]
        # Φᵀ M restricted to the target columns: the source lives there only.
        self._PhiTM_T = np.ascontiguousarray((self.evecs[self._T] * self._mT[:, None]).T)
        self._touched_T = int(np.count_nonzero(self.coverage[self._T] > 0))
        self._s = np.zeros(len(self._T))  # s = max(p̄ - c̄, 0)² on the target
        self._sbar_full = np.zeros(n)  # s / ∫s, the injected source, on all points
        self._residual_mass = float(self._mT @ (self._pT * self._pT))
        self._phat = None  # set after the next step
        self._ref_untouched = 0.0
        self._ref_norm2 = 1.0
        if self._spectral:
            self._a = np.zeros(len(self.evals))  # spectral part of u
            self._b = self._PhiTM_T @ self._pT  # Φᵀ M of u's non-spectral part (u₀ = p̄)
        else:
            self._u = np.zeros(n)
            self._u[self._T] = self._pT
        self._heat_cache = None
        self._metrics = {"ergodicity": float(math.sqrt(self._residual_mass)), "ergodicity_ref": float("nan"),
                         "touched_fraction": self._touched_T / len(self._T)}

    @property
    def source(self) -> np.ndarray:
        s = np.zeros(len(self.points))
        s[self._T] = self._s
        return s

    @property
    def heat(self) -> np.ndarray:
        if self._heat_cache is not None and self._heat_cache[0] == self.step_index:
            return self._heat_cache[1]
        if self._spectral:
            u = self.evecs @ self._a
            if self.cfg.diffusion == "carry":
                u += self._sbar_full
        else:
            u = self._u.copy()
        self._heat_cache = (self.step_index, u)
        return u

    def metrics(self) -> dict:
        """{"ergodicity", "ergodicity_ref", "touched_fraction"} after the last step (see docs/explore.md)."""
        return dict(self._metrics)

    @property
    def alpha(self) -> float:
        """α in effect for the next step."""
        return [a for s, a in self._schedule if s <= self.step_index][-1]

    # ------------------------------------------------------------------ geometry
    def _locate(self, x: np.ndarray, ref_normal: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Project ``x`` onto the surface fitted to its n_N nearest points.

        Returns the projected point, its unit normal (oriented like ``ref_normal``), and the
        neighbour indices (sorted by distance to ``x``).
        """
        _, nb = self.kdtree.query(x, k=self.cfg.n_neighbors)
        nbp = self.points[nb]
        try:
            prim = fit_primitive(nbp)
            xp, n = project_onto(prim, x)
        except ValueError:  # degenerate patch or sphere centre: fall back to the nearest point's plane
            xp, n = nbp[0].copy(), ref_normal.copy()
        return xp, orient(n, ref_normal), nb

    def _place(self, i: int, x0: np.ndarray, hint: np.ndarray, start: bool = True) -> None:
        """Project a start (or, with ``start=False``, a reset position) onto the surface.

        A start farther than ``max_start_distance`` from the cloud is refused; a reset that
        far is ignored (the agent keeps its state) and reported.
        """
        d0, _ = self.kdtree.query(x0)
        if not start and d0 > self.cfg.max_start_distance:
            self._say(f"warning: step {self.step_index}: agent {i} reset point is {d0 * 1e3:.1f} mm off the cloud; ignored")
            return
        require(d0 <= self.cfg.max_start_distance,
                f"start {np.array2string(x0, precision=4)} is {d0 * 1e3:.1f} mm from the cloud "
                f"(limit {self.cfg.max_start_distance * 1e3:.0f} mm)",
                "give a start on the object (x,y,z in metres, a point index, or 'random')")
        x, ref = np.asarray(x0, dtype=float), hint
        for _ in range(START_ITERATIONS):
            xp, n, nb = self._locate(x, ref)
            moved = float(np.linalg.norm(xp - x))
            x, ref = xp, n
            if moved < 1e-9:
                break
        if start and d0 > self.h:
            self._say(f"warning: start {np.array2string(x0, precision=4)} is {d0 * 1e3:.1f} mm off the cloud; "
                      f"projected onto the surface at {np.array2string(x, precision=4)}")
        self.positions[i] = x
        self.normals[i] = ref
        self._nbrs[i] = nb
        self._frames[i] = np.column_stack(tangent_basis(ref))
        v = self.velocities[i]
        self.velocities[i] = self._tangential(v, ref)

    @staticmethod
    def _tangential(v: np.ndarray, n: np.ndarray) -> np.ndarray:
        """``v`` turned into the plane normal to ``n`` with its speed kept."""
        speed = math.sqrt(float(v @ v))
        vt = v - (v @ n) * n
        norm = math.sqrt(float(vt @ vt))
        return vt * (speed / norm) if norm > 0 else np.zeros(3)

    # ------------------------------------------------------------------ coverage
    def _deposit(self, x: np.ndarray, n: np.ndarray) -> None:
        idx = np.asarray(self.kdtree.query_ball_point(x, self.r_a), dtype=np.intp)
        if len(idx) == 0:
            return
        d = self.points[idx] - x
        off = d @ n
        r2 = np.maximum(np.einsum("ij,ij->i", d, d) - off * off, 0.0)  # tangent-plane distance² (eq. 31)
        phi = np.exp(-(self.eps * self.eps) * r2)
        fresh = idx[self.coverage[idx] == 0]
        self.coverage[idx] += phi
        self._cov_mass += float(self.mass[idx] @ phi)
        if len(fresh):
            self._touched_T += int(np.count_nonzero(self._is_target[fresh]))
            if self._phat is not None:
                ph = self._phat[fresh]
                self._ref_untouched -= float(ph @ ph)

    # ------------------------------------------------------------------ diffusion
    def _update_source(self) -> None:
        T = self._T
        e = self._pT - self.coverage[T] / self._cov_mass if self._cov_mass > 0 else self._pT.copy()
        np.maximum(e, 0.0, out=e)
        s = e * e
        self._s = s
        z = float(self._mT @ s)  # ∫s = ‖max(p̄ - c̄, 0)‖² in L2(M)
        self._residual_mass = z
        self._sbar_full[T] = s / z if z > 0 else 0.0

    def _set_alpha(self) -> float:
        alpha = self.alpha
        if alpha != self._alpha:
            self._alpha = alpha
            dt = time_step(alpha, self.h)
            if self.cfg.integrator == "spectral":
                self._decay = np.exp(-self.evals * dt)  # eq. 19
            elif self.cfg.integrator == "resolvent":
                self._decay = 1.0 / (1.0 + self.evals * dt)  # eq. 4: (M + δt L)⁻¹ M in the eigenbasis
            elif alpha not in self._implicit:
                self._implicit[alpha] = ImplicitDiffusion(self._L, self.mass, dt)
        return alpha

    def _diffuse(self) -> None:
        alpha = self._set_alpha()
        carry = self.cfg.diffusion == "carry"
        if self._spectral:
            sbar_coef = self._PhiTM_T @ self._sbar_full[self._T]
            if carry:
                # u_{t-1} = Φ a + r with Φᵀ M r = b, so Φᵀ M u_{t-1} = a + b; then u_t = Φ a' + s̄.
                self._a = self._decay * (self._a + self._b)
                self._b = sbar_coef
            else:
                self._a = self._decay * sbar_coef
        else:
            op = self._implicit[alpha]
            self._u = op.apply(self._u) + self._sbar_full if carry else op.apply(self._sbar_full)

    def _heat_at(self, idx: np.ndarray) -> np.ndarray:
        if self._spectral:
            u = self.evecs[idx] @ self._a
            return u + self._sbar_full[idx] if self.cfg.diffusion == "carry" else u
        return self._u[idx]

    # ------------------------------------------------------------------ agents
    def _gradient(self, i: int) -> np.ndarray:
        """∇u (3,) at agent i's projected position, in its tangent plane (eqs. 32-33)."""
        nb = self._nbrs[i]
        frame = self._frames[i]  # (3, 2): t1, t2 as columns
        uv = (self.points[nb] - self.positions[i]) @ frame
        r2 = np.einsum("ij,ij->i", uv, uv)
        w = np.exp(-(self.eps * self.eps) * r2)
        # Off the sampled surface (past an open edge, across a gap) the neighbours lie on one
        # side and a cubic would be extrapolated: fit a plane there.
        degree = 3 if float(r2.min()) <= self.h * self.h else 1
        coef = fit_cubic(uv, self._heat_at(nb), w, degree)
        return frame @ coef[1:3]

    def _move(self, i: int) -> None:
        cfg = self.cfg
        g = self._gradient(i)
        gn = math.sqrt(float(g @ g))
        a = g * (cfg.a_max / gn) if gn > 0 and math.isfinite(gn) else np.zeros(3)
        # Semi-implicit Euler: the step's displacement is v_new δt, so |Δx| <= v_max δt exactly.
        v = self.velocities[i] + a * cfg.dt
        speed = math.sqrt(float(v @ v))
        if speed > cfg.v_max:
            v *= cfg.v_max / speed
        x_new = self.positions[i] + v * cfg.dt
        xp, n, nb = self._locate(x_new, self.normals[i])
        # Edge guard: an open sheet's fitted plane extends past its last points.
        diff = self.points[nb] - xp
        d2 = np.einsum("ij,ij->i", diff, diff)
        j = int(np.argmin(d2))
        reach = self._reach[nb[j]]
        if d2[j] > reach * reach:
            self.edge_events += 1
            q = self.points[nb[j]]
            out = (xp - q) / math.sqrt(float(d2[j]))
            xp, n, nb = self._locate(q + out * reach, n)
            v = v - 2.0 * max(float(v @ out), 0.0) * out  # reflect off the edge: keep moving, never stall
        self.accelerations[i] = a
        self.positions[i] = xp
        self.normals[i] = n
        self.velocities[i] = self._tangential(v, n)
        self._nbrs[i] = nb
        self._frames[i] = np.column_stack(tangent_basis(n))

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
        if deposit_at is None:
            for i in range(len(self.positions)):
                self._deposit(self.positions[i], self.normals[i])
        else:
            pts = np.asarray(deposit_at, dtype=np.float64).reshape(-1, 3)
            ref = self.normals[0]
            for q in pts:
                if self.kdtree.query(q)[0] > self.r_a:
                    continue  # a contact off the cloud covers no cloud point
                xp, n, _ = self._locate(q, ref)
                self._deposit(xp, n)
        self._update_source()
        self._diffuse()
        if agent_at is not None:
            at = np.asarray(agent_at, dtype=np.float64).reshape(-1, 3)
            require(len(at) == len(self.positions), f"agent_at has {len(at)} rows for {len(self.positions)} agents",
                    "give one position per agent")
            for i, x in enumerate(at):
                self._place(i, x, self.normals[i], start=False)
        for i in range(len(self.positions)):
            self._move(i)
        self.step_index += 1
        if self._phat is None:
            self._take_reference_heat()
        self._metrics = {
            "ergodicity": math.sqrt(self._residual_mass),
            "ergodicity_ref": math.sqrt(max(self._ref_untouched, 0.0) / self._ref_norm2),
            "touched_fraction": self._touched_T / len(self._T),
        }
        self.last_step_ms = 1e3 * (time.perf_counter() - t0)

    def _take_reference_heat(self) -> None:
        """p̂ of ``ergodicity_ref``: the heat after the first step of the carry-over scheme,
        e^{-δtL} p̄ + s̄₁ (the published code's), whichever diffusion drives the agents, so
        that the metric compares runs and variants on the same footing."""
        decay = np.exp(-self.evals * time_step(self._alpha, self.h))
        u = self.evecs @ (decay * (self._PhiTM_T @ self._pT)) + self._sbar_full
        total = float(u.sum())
        if not (total > 0 and math.isfinite(total)):
            raise TergodicError("the heat after the first step has no positive mass",
                                "check the target and the basis (non-finite eigenvectors?)")
        self._phat = u / total
        self._ref_norm2 = float(self._phat @ self._phat)
        untouched = self._phat[self.coverage == 0]
        self._ref_untouched = float(untouched @ untouched)
