"""``summary.json`` as a pure function of the per-step series (the replay verb recomputes it)."""

from __future__ import annotations

import math

import numpy as np

#: Steps at which ``ergodicity_at`` (and the other ``*_at`` keys) report values (paper VI-B: 200 and 500).
MILESTONES = (200, 500, 1000)
SERIES = ("ergodicity", "residual_ref", "touched_fraction", "step_ms")


def _num(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def summarize_run(series: dict[str, np.ndarray], config: dict, extra: dict | None = None) -> dict:
    """The run summary.

    Parameters
    ----------
    series : "ergodicity", "residual_ref", "touched_fraction", "step_ms", each (T,) float64,
        entry k being the value after step k + 1.
    config : the run configuration (``ExploreConfig.to_dict()``, including the seed).
    extra : merged in last (versions, robot metrics, capture/basis provenance, ...).

    Returns
    -------
    dict with steps, ergodicity (the neutral unit-mass ε of ``metrics.coverage_score``),
    residual_ref (the authors' residual), touched_fraction (final values), ergodicity_at /
    residual_ref_at / touched_fraction_at {"200": .., "500": .., "1000": ..} (None when the run is
    shorter), step_ms_median, seed and config; ``extra`` adds off_surface_fraction and step_max_m
    (``Explorer.score()``). Non-finite numbers become None (valid JSON).
    """
    arrays = {k: np.asarray(series[k], dtype=np.float64) for k in SERIES}
    steps = len(arrays["ergodicity"])
    if any(len(a) != steps for a in arrays.values()):
        raise ValueError("all series must have one value per step")

    def at(name: str) -> dict[str, float | None]:
        return {str(m): (_num(arrays[name][m - 1]) if steps >= m else None) for m in MILESTONES}

    metrics = ("ergodicity", "residual_ref", "touched_fraction")  # final values, then at the milestones
    return {"steps": steps, **{k: _num(arrays[k][-1]) if steps else None for k in metrics},
            **{f"{k}_at": at(k) for k in metrics},
            "step_ms_median": _num(np.median(arrays["step_ms"])) if steps else None,
            "seed": config.get("seed"), "config": dict(config), **(extra or {})}
