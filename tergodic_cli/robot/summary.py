"""Robot metrics for summary.json, as a pure function of the per-step robot samples.

The replay verb reads the samples back from the run log (topic /robot/sample) and calls
:func:`summarize_robot` again, so these numbers are recomputed exactly from the log.
"""

from __future__ import annotations

import math
from typing import Iterable, Mapping

import numpy as np

#: Contact younger than this (s, simulated) is a transient, not "steady contact".
SETTLE_S = 0.5


def _num(x) -> float | None:
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _columns(samples) -> tuple[dict[str, list], int]:
    if isinstance(samples, Mapping):
        n = len(next(iter(samples.values()))) if samples else 0
        return {k: list(v) for k, v in samples.items()}, n
    rows = list(samples)
    keys = set().union(*(r.keys() for r in rows))
    return {k: [r.get(k) for r in rows] for k in keys}, len(rows)


#: The coverage figures the samples carry (their last value is the run's): the unit-mass ε and the
#: touched share of the sponge's contact points and of the virtual agent's own path.
EPS_KEYS = ("eps_sponge", "touched_sponge", "eps_agent", "touched_agent")
#: The names of older logs (before the sponge's own score: their "contact" figures were the agent's path).
LEGACY_EPS_KEYS = ("contact_ergodicity", "contact_touched_fraction", "agent_ergodicity", "agent_touched_fraction")

#: The 1 kHz figures (from every control tick) and the 5 Hz ones (from the samples) they replace.
TICK_KEYS = {"force_rms_error_rel": "tick_force_rms_rel", "tilt_deg_median": "tick_tilt_median_deg",
             "tilt_deg_p95": "tick_tilt_p95_deg", "force_peak_N": "tick_force_peak_N"}


def summarize_robot(samples: Iterable[Mapping] | Mapping[str, Iterable], settle_s: float = SETTLE_S,
                    stop_reason: str | None = None, ticks: Mapping | None = None) -> dict:
    """Robot extras of summary.json.

    Parameters
    ----------
    samples : the robot sample dicts, one per explorer step (CONTRACTS.md robot_sample_dict plus
        the keys listed below), or the same as columns {key: sequence}. Keys used: t_sim, t_wall,
        state, in_contact, force_normal, wrench_desired, tilt_deg, track_mm, and when present
        eps_sponge, touched_sponge, eps_agent, touched_agent (:data:`EPS_KEYS`), stop_reason.
    settle_s : contact younger than this many simulated seconds is excluded from the force error.
    stop_reason : overrides the reason found in the samples (a fault outside the explore phase
        leaves no sample behind; the run log's last robot event carries it).
    ticks : the run's final 1 kHz figures (:func:`~tergodic_cli.robot.kernels.tick_figures`); without
        them the last sample's (cumulative) ones are used: the same up to the ticks after it.

    Returns
    -------
    dict: force_rms_error_rel (RMS of |F_n - F_d| / F_d over the 1 kHz ticks in steady contact),
    tilt_deg_median and tilt_deg_p95 (the same ticks), force_peak_N (largest |F| of the contact wrench
    over every tick), each also over the 5 Hz samples as ``*_5hz`` (the samples only: the figure
    itself when the samples carry no tick figures), force_max_N (force_peak_N, else the 5 Hz one),
    track_mm_median (tool contact point to the agent line), contact_fraction (share of explore
    samples in contact), realtime_factor (simulated / wall time), eps_sponge and touched_sponge
    (the unit-mass ε and touched share of the sponge's logged contact points: the run's headline),
    eps_agent and touched_agent (the same score of the virtual agent's own path), and supporting
    figures. Numbers that cannot be computed are None. A log written before the sponge's score
    (samples with contact_ergodicity etc., :data:`LEGACY_EPS_KEYS`) keeps those keys as they were.
    """
    cols, n = _columns(samples)
    out: dict = {"robot_samples": n}
    if n == 0:
        out.update({k: None for k in ("force_rms_error_rel", "force_rms_error_rel_filtered", "force_desired_N",
                                      "force_mean_N", "force_max_N", "tilt_deg_median", "tilt_deg_p95",
                                      "force_rms_error_rel_5hz", "tilt_deg_median_5hz", "tilt_deg_p95_5hz",
                                      "force_peak_5hz_N", "tick_steady",
                                      "track_mm_median", "track_mm_p95", "contact_fraction", "realtime_factor",
                                      *EPS_KEYS)})
        out.update(explore_samples=0, steady_samples=0)
        for key, tk in TICK_KEYS.items():
            out[key] = _num((ticks or {}).get(tk))
        out["stop_reason"] = stop_reason
        return out
    state = np.array([str(s) for s in cols.get("state", ["explore"] * n)])
    explore = state == "explore"
    t = np.array([float(x) for x in cols["t_sim"]])
    contact = np.array([bool(x) for x in cols.get("in_contact", [False] * n)])
    fn = np.array([np.nan if x is None else float(x) for x in cols.get("force_normal", [None] * n)])
    fd = np.array([float(w[2]) if w is not None else np.nan for w in cols.get("wrench_desired", [None] * n)])
    tilt = np.array([np.nan if x is None else float(x) for x in cols.get("tilt_deg", [None] * n)])
    track = np.array([np.nan if x is None else float(x) for x in cols.get("track_mm", [None] * n)])

    # Steady contact: explore samples inside a contact run that started at least settle_s earlier.
    steady = np.zeros(n, bool)
    onset = None
    for i in range(n):
        if explore[i] and contact[i]:
            if onset is None:
                onset = t[i]
            steady[i] = t[i] - onset >= settle_s
        else:
            onset = None
    ec = explore & contact
    rel = np.abs(fn - fd) / fd
    good = steady & np.isfinite(rel)
    out["force_rms_error_rel"] = _num(np.sqrt(np.mean(rel[good] ** 2))) if good.any() else None
    # The same on the force the PID sees (the F/T reading low-passed at force_filter_hz): without the
    # solver's 1 kHz contact jitter, closer to what a real (filtered) F/T sensor reports.
    ff = np.array([np.nan if x is None else float(x) for x in cols.get("force_filtered", [None] * n)])
    relf = np.abs(ff - fd) / fd
    goodf = steady & np.isfinite(relf)
    out["force_rms_error_rel_filtered"] = _num(np.sqrt(np.mean(relf[goodf] ** 2))) if goodf.any() else None
    out["force_desired_N"] = _num(np.nanmedian(fd[explore])) if explore.any() else None
    out["force_mean_N"] = _num(np.mean(fn[good])) if good.any() else None
    out["force_max_N"] = _num(np.nanmax(fn[explore])) if explore.any() and np.isfinite(fn[explore]).any() else None
    for name, arr in (("tilt_deg", tilt), ("track_mm", track)):
        vals = arr[ec & np.isfinite(arr)]
        out[f"{name}_median"] = _num(np.median(vals)) if len(vals) else None
        out[f"{name}_p95"] = _num(np.percentile(vals, 95)) if len(vals) else None
    out["contact_fraction"] = _num(contact[explore].mean()) if explore.any() else None
    out["explore_samples"] = int(explore.sum())
    out["steady_samples"] = int(good.sum())
    wall = cols.get("t_wall")
    ran = wall is not None and wall[-1] is not None and float(wall[-1]) > 0
    out["realtime_factor"] = _num(t[-1] / float(wall[-1])) if ran else None
    legacy = not any(k in cols for k in EPS_KEYS) and any(k in cols for k in LEGACY_EPS_KEYS)
    for key in LEGACY_EPS_KEYS if legacy else EPS_KEYS:
        vals = [v for v in cols.get(key, []) if v is not None]
        out[key] = _num(vals[-1]) if vals else None
    # Every tick counts: the 1 kHz figures replace the 5 Hz ones, which stay as *_5hz.
    for key in ("force_rms_error_rel", "tilt_deg_median", "tilt_deg_p95"):
        out[f"{key}_5hz"] = out[key]
    out["force_peak_5hz_N"] = out["force_max_N"]
    if ticks is None:
        last = [v for v in cols.get("tick_steady", []) if v is not None]
        ticks = {tk: cols[tk][-1] for tk in (*TICK_KEYS.values(), "tick_steady") if tk in cols} if last else None
    out["force_peak_N"] = None
    out["tick_steady"] = None
    if ticks:
        out["tick_steady"] = int(ticks.get("tick_steady") or 0)
        for key, tk in TICK_KEYS.items():
            out[key] = _num(ticks.get(tk))
        if out["force_peak_N"] is not None:
            out["force_max_N"] = out["force_peak_N"]
    reasons = [r for r in cols.get("stop_reason", []) if r]
    out["stop_reason"] = stop_reason or (reasons[-1] if reasons else "completed")
    return out
