"""The exploration stage's configuration and its validation."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from tergodic_cli.config import Config, option
from tergodic_cli.errors import TergodicError, check_seed, require

DIFFUSIONS = ("carry", "source")
INTEGRATORS = ("resolvent", "spectral", "implicit")
COVERAGE_NORMS = ("target", "cloud")
SHEETS = ("mixed", "separate")
#: The paper's n_N (Table II, "M = 20"): neighbours for the tangent fit and the gradient fit.
DEFAULT_NEIGHBORS = 20
#: Default footprint shape: ε r_a = 2, so the disc of radius r_a holds 1 - e^-4 = 98 % of the
#: Gaussian's mass (truncating it at r_a changes almost nothing) and φ(r_a) = e^-4 ≈ 0.02.
FOOTPRINT_EPS_RA = 2.0
#: A cubic in two variables has 10 coefficients; fewer neighbours cannot determine it.
MIN_NEIGHBORS = 10


@dataclass
class ExploreConfig(Config):
    """Everything that determines an exploration run; saved in ``summary.json["config"]`` and a run's ``config.json``.

    Attributes
    ----------
    steps : number of explorer steps (one step = ``dt`` seconds).
    alpha : diffusion scalar α of δt = α h₀² (eq. 21, h₀ = 2.5 mm fixed): a number ("10"), or a schedule
        "A0:A1@S1[:A2@S2...]": α = A0 for the first S1 steps, then A1, then A2 from step S2 on
        (e.g. "50:10@200", high first for reach, low later for local detail; paper VI-E).
    nk : eigenpairs used by the spectral diffusion (the basis is truncated to this).
    agent_radius : footprint radius r_a, metres.
    n_agents : agents sharing one coverage field (eq. 3).
    v_max, a_max : speed (m/s) and acceleration (m/s²) limits (paper Table II: 3 mm/s, 3 mm/s²).
    dt : seconds per step (paper: 1 s).
    diffusion : "carry" (u <- D u + s, heat carried over between steps, as the published code; the
        default) or "source" (u = D s, the current source only). See docs/explore.md for the measurements.
    integrator : the one-step operator D: "resolvent" (Φ (1 + λδt)⁻¹ Φᵀ M: the stationary HEDAC
        equation 4 in the eigenbasis; the default: its potential has no maxima away from the
        source, so agents do not get stuck in a region they have cleared), "spectral" (eq. 19,
        Φ e^{-λδt} Φᵀ M) or "implicit" ((M + δt L)⁻¹ M, sparse, factorised once per α: the
        exact baseline).
    coverage_norm : what the source's coverage is normalised over, c̄ = c̃ / ∫c̃: "cloud" (the
        whole cloud, eq. 2 as printed; the default) or "target" (the target's support {p > 0}).
    sheets : a wall's two sides: "mixed" (the tangent fit, the gradient and the projection use all
        n_N nearest, the footprint and the gains their 3-D balls: the paper's; the default) or
        "separate" (all of them only the agent's own sheet: never inside a wall whose two sides are
        sampled, and nothing deposited on, or sought through, its other side). Separate keeps the agent
        within 1.5 mm of the mesh on 97 % of its steps against 70 %, but it must now cover each side of
        a wall in turn, and its median ε on the household corpus is 1.3x the mixed one
        (docs/explore.md, "Sheet separation"). The run's off-surface figure tests one sheet either way.
    seed : seed of everything random in the run (random starts).
    resync_every : K: the incrementally kept spectral source (docs/speed.md) is recomputed in
        full every K steps to bound round-off; 1 recomputes every step (the O(n_target nK)
        reference), 0 never.
    n_neighbors : n_N, neighbours of the agent for the CGA tangent fit and the gradient cubic.
    epsilon : footprint shape ε of φ(r) = exp(-ε² r²), 1/m; None means 2/agent_radius (the
        disc r <= r_a holds 98 % of the Gaussian's mass, so the cut at r_a changes almost nothing).
    basis_neighbors : neighbours of the robust Laplacian (recorded; chosen by the command).
    max_start_distance : a start farther than this (metres) from the cloud is refused; one
        farther than the spacing h is projected onto the surface with a warning.
    normal_hint : initial orientation of the surface normals (they then stay continuous).
    heat_weight, gain_weight : weights of the heat's gradient and of the footprint gain's in the
        agent's drive (docs/explore.md, "How the agent is driven": measured on the reference clouds).
    gain_width : the gain's kernel width as a multiple of the footprint's (1/ε).
    """

    steps: int = field(default=1000, metadata=option("--steps", "Explorer steps (one step = --dt seconds)."))
    alpha: str = field(default="10", metadata=option(
        "--alpha", "α of δt = α h₀² (eq. 21, h₀ = 2.5 mm fixed), or a schedule A0:A1@S1, e.g. 50:10@200 (50 for 200 "
        "steps, then 10)."))
    nk: int = field(default=200, metadata=option(
        "--nk", "Eigenpairs used by the spectral diffusion (a larger cached basis is truncated)."))
    agent_radius: float = field(default=0.0075, metadata=option(
        "--agent-radius", "Footprint radius r_a (paper: 0.0075 bunny/cup, 0.015 plate)", unit="METRES"))
    n_agents: int = field(default=1, metadata=option("--agents", "Agents sharing one coverage field (eq. 3)."))
    v_max: float = field(default=0.003, metadata=option("--v-max", "Speed limit (paper: 0.003)", unit="m/s"))
    a_max: float = field(default=0.003, metadata=option("--a-max", "Acceleration limit (paper: 0.003)", unit="m/s²"))
    dt: float = field(default=1.0, metadata=option("--dt", "Seconds per explorer step (paper: 1)."))
    diffusion: str = field(default="carry", metadata=option(
        "--diffusion", "'carry': u <- e^{-δtL}u + s (default, measured best); 'source': eq. 19 on the current "
        "source only."))
    integrator: str = field(default="resolvent", metadata=option(
        "--integrator", "'resolvent' (eq. 4 in the eigenbasis, 1/(1+λδt); default, measured most robust), 'spectral' "
        "(eq. 19, e^{-λδt}) or 'implicit' (sparse (M + δt L)^-1 M, the exact baseline)."))
    coverage_norm: str = field(default="cloud", metadata=option(
        "--coverage-norm", "What the source's coverage is normalised over: 'cloud' (default: the whole cloud, eq. 2 "
        "as printed) or 'target' (the marked points only; tuned in wave 1 to the touched share, which the neutral "
        "ε does not reward: docs/explore.md)."))
    sheets: str = field(default="mixed", metadata=option(
        "--sheets", "Sheets of a wall's two sides: 'mixed' (the fit, gradient, footprint and gain use all n_N "
        "nearest / 3-D balls, the paper's; default) or 'separate' (only the agent's own sheet: never inside a wall "
        "whose two sides are sampled, and nothing deposited or sought through it; within 1.5 mm of the mesh on 97 % "
        "of steps against 70 %, but a median ε 1.3x the mixed one on household meshes: docs/explore.md)."))
    seed: int = field(default=0, metadata=option("--seed", "Seed for random starts."))
    resync_every: int = 1000
    n_neighbors: int = field(default=DEFAULT_NEIGHBORS, metadata=option(
        "--fit-neighbors", "n_N: neighbours of the tangent-plane and gradient fits (paper Table II: 20)."))
    epsilon: float | None = field(default=None, metadata=option(
        "--epsilon", "Footprint φ = exp(-ε² r²), ε in 1/m", default="2/agent-radius: 98% of the Gaussian inside r_a"))
    basis_neighbors: int = field(default=30, metadata=option(
        "--neighbors", "Neighbours of the robust Laplacian (must match 'tergodic precompute'; the authors used 40)."))
    max_start_distance: float = field(default=0.02, metadata=option(
        "--max-start-distance", "Refuse a start farther than this from the cloud; closer ones are projected",
        unit="m"))
    normal_hint: tuple[float, float, float] = field(default=(0.0, 0.0, 1.0))
    heat_weight: float = 0.02
    gain_weight: float = 1.0
    gain_width: float = 1.5

    @property
    def footprint_epsilon(self) -> float:
        """ε in 1/m actually used."""
        return footprint_epsilon(self.agent_radius, self.epsilon)


def footprint_epsilon(agent_radius: float, epsilon: float | None = None) -> float:
    """The footprint's ε (eq. 30, φ = exp(-ε² r²)): ``epsilon`` when given, else FOOTPRINT_EPS_RA / r_a.

    Parameters
    ----------
    agent_radius : float
        r_a, metres.
    epsilon : float, optional
        An explicit ε, 1/m.

    Returns
    -------
    float
        ε, 1/m.
    """
    return float(epsilon) if epsilon is not None else FOOTPRINT_EPS_RA / float(agent_radius)


def parse_alpha(text: str | float) -> list[tuple[int, float]]:
    """Parse an α value or schedule into [(first_step, alpha), ...], first_step ascending from 0.

    "10" -> [(0, 10.0)]; "50:10@200" -> [(0, 50.0), (200, 10.0)];
    "100:50@100:10@300" -> [(0, 100.0), (100, 50.0), (300, 10.0)].
    Steps count from 0, so "@200" takes effect for the 201st step.

    Parameters
    ----------
    text : str or float
        α, or a schedule "A0:A1@S1[:A2@S2...]".

    Returns
    -------
    list of (int, float)
        (first step, α), first steps ascending from 0.
    """
    fix = "use a positive number, or a schedule like 50:10@200 (α = 50 for 200 steps, then 10)"
    parts = str(text).strip().split(":")
    stages: list[tuple[int, float]] = []
    for i, part in enumerate(parts):
        value, _, at = part.partition("@")
        try:
            alpha = float(value)
            start = 0 if i == 0 else int(at)
        except ValueError:
            raise TergodicError(f"--alpha '{text}' is not a number or schedule", fix) from None
        require(i > 0 or not at, f"--alpha '{text}': the first α applies from step 0 and takes no @STEP", fix)
        require(math.isfinite(alpha) and alpha > 0, f"--alpha must be > 0, got {value!r}", fix)
        if stages:
            require(start > stages[-1][0], f"--alpha '{text}': switch steps must increase and be > 0", fix)
        stages.append((start, alpha))
    return stages


#: Largest accepted lengths and rates (SI): above these a value is almost surely millimetres typed as
#: metres (a 0.5 m footprint, 1 m/s or 10 m/s² on a surface being polished).
UNIT_GUARD = {"--agent-radius": 0.5, "--v-max": 1.0, "--a-max": 10.0}


def validate_config(cfg: ExploreConfig) -> None:
    """Refuse impossible settings with a one-line problem; fix message.

    Parameters
    ----------
    cfg : ExploreConfig
    """
    for opt, v, eg in (("--steps", cfg.steps, 1000), ("--nk", cfg.nk, 200), ("--agents", cfg.n_agents, 1)):
        require(int(v) >= 1, f"{opt} must be >= 1, got {v}", f"e.g. {opt} {eg}")
    parse_alpha(cfg.alpha)
    check_seed(cfg.seed)
    for opt, v, unit, eg in (("--agent-radius", cfg.agent_radius, "metres", "0.0075 (7.5 mm)"),
                             ("--v-max", cfg.v_max, "m/s", "0.003"),
                             ("--a-max", cfg.a_max, "m/s²", "0.003"), ("--dt", cfg.dt, "s", "1")):
        require(math.isfinite(v) and v > 0, f"{opt} must be > 0 {unit}, got {v}",
                f"e.g. {opt} {eg}")
        # the lengths are SI: a value this large is millimetres typed as metres (7.5 for 7.5 mm)
        require(opt not in UNIT_GUARD or v <= UNIT_GUARD[opt], f"{opt} {v:g} {unit} is far too large for a "
                f"contact tool (limit {UNIT_GUARD.get(opt, 0):g} {unit}): the value looks like millimetres",
                f"give it in SI units, e.g. {opt} {eg}")
    for opt, v, choices in (("--diffusion", cfg.diffusion, DIFFUSIONS),
                            ("--coverage-norm", cfg.coverage_norm, COVERAGE_NORMS),
                            ("--sheets", cfg.sheets, SHEETS),
                            ("--integrator", cfg.integrator, INTEGRATORS)):
        require(v in choices, f"{opt} '{v}' is unknown", f"use one of {', '.join(choices)}")
    require(int(cfg.resync_every) >= 0, f"resync_every must be >= 0 steps, got {cfg.resync_every}",
            "e.g. 1000 (0: never, 1: a full recompute every step)")
    require(int(cfg.n_neighbors) >= MIN_NEIGHBORS, f"--fit-neighbors {cfg.n_neighbors} is too few for a cubic fit",
            f"use at least {MIN_NEIGHBORS} (paper: {DEFAULT_NEIGHBORS})")
    if cfg.epsilon is not None:
        require(math.isfinite(cfg.epsilon) and cfg.epsilon > 0, f"--epsilon must be > 0 (1/m), got {cfg.epsilon}",
                "omit it for the default 1/agent-radius")
    require(cfg.max_start_distance > 0, "max_start_distance must be > 0 metres", "e.g. 0.02")
    for name in ("heat_weight", "gain_weight"):
        w = getattr(cfg, name)
        require(math.isfinite(w) and w >= 0, f"{name} must be >= 0, got {w}", "e.g. heat_weight 0.01, gain_weight 1")
    require(cfg.heat_weight > 0 or cfg.gain_weight > 0, "heat_weight and gain_weight are both 0: nothing drives the agent",
            "give one of them a positive weight")
    require(math.isfinite(cfg.gain_width) and cfg.gain_width > 0, f"gain_width must be > 0, got {cfg.gain_width}",
            "e.g. 1.5 (the footprint's width times 1.5)")
    require(len(cfg.normal_hint) == 3 and any(abs(float(x)) > 0 for x in cfg.normal_hint),
            "normal_hint must be a non-zero 3-vector", "e.g. (0, 0, 1)")
