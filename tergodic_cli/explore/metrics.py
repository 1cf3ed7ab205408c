"""Coverage, source and the three exploration metrics as pure functions of full arrays.

The :class:`~tergodic_cli.explore.explorer.Explorer` keeps incremental versions of these for
speed; these reference forms define them (and the tests check the two agree).

All per-point arrays are (n,) float64 over the cloud; ``mass`` is the lumped mass M (m²).
"""

from __future__ import annotations

import numpy as np


def footprint(r: np.ndarray, epsilon: float) -> np.ndarray:
    """Gaussian RBF footprint φ(r) = exp(-ε² r²) (eq. 30); ``r`` in metres, ε in 1/m."""
    r = np.asarray(r, dtype=float)
    return np.exp(-(epsilon * epsilon) * (r * r))


def normalise(f: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """``f`` scaled to unit mass, f / ∫f with ∫f = Σ M_i f_i (eq. 2); zeros stay zeros."""
    total = float(mass @ f)
    return f / total if total > 0 else np.zeros_like(f, dtype=float)


def source_term(p: np.ndarray, coverage: np.ndarray, mass: np.ndarray, norm: str = "cloud") -> np.ndarray:
    """s = max(p̄ - c̄, 0)² (eq. 1) with p̄ the target normalised to unit mass.

    ``norm`` "cloud": c̄ = c̃ / ∫_Ω c̃, the raw coverage normalised over the whole cloud (eq. 2);
    "target": c̄ = c̃ / ∫_T c̃ over the target's support T = {p > 0} (the explorer's default, see
    docs/explore.md), so that coverage falling beside the target does not count towards it.
    """
    if norm == "target":
        on_target = np.where(np.asarray(p) > 0, coverage, 0.0)
        total = float(mass @ on_target)
        cbar = coverage / total if total > 0 else np.zeros_like(coverage, dtype=float)
    else:
        cbar = normalise(coverage, mass)
    return np.maximum(normalise(p, mass) - cbar, 0.0) ** 2


def ergodicity(p: np.ndarray, coverage: np.ndarray, mass: np.ndarray) -> float:
    """Eq. 48: ε = ‖max(p̄ - c̄, 0)‖₂ / ∫p̄ with ‖f‖₂ = (Σ M_i f_i²)^½ and ∫p̄ = 1.

    Units 1/m (a density difference in L2 on the surface). At zero coverage it is ‖p̄‖₂.
    """
    e = np.maximum(normalise(p, mass) - normalise(coverage, mass), 0.0)
    return float(np.sqrt(mass @ (e * e)))


def ergodicity_ref(first_heat: np.ndarray, coverage: np.ndarray) -> float:
    """The authors' residual: ‖p̂ · [c̃ = 0]‖₂ / ‖p̂‖₂ with p̂ = u₁ / Σu₁ (plain sums and norms).

    ``first_heat`` is the heat u after the first step; [c̃ = 0] marks points the footprint
    never reached. Raw, unnormalised coverage makes any touched point count as done.
    """
    p_hat = first_heat / first_heat.sum()
    untouched = coverage == 0
    return float(np.linalg.norm(p_hat[untouched]) / np.linalg.norm(p_hat))


def touched_fraction(p: np.ndarray, coverage: np.ndarray) -> float:
    """Share of target points (p > 0) whose coverage is > 0."""
    target = p > 0
    return float(np.count_nonzero(coverage[target] > 0) / max(np.count_nonzero(target), 1))
