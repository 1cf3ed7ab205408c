"""Recompute a run's summary from its log alone, and print it.

The numbers come from the logged series through the explorer's own ``summarize_run`` (and the
robot's ``summarize_robot``), so the replayed summary is the summary, not a re-implementation
of it; provenance keys come from the copy stored in the log at close (docs/logging.md).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from tergodic_cli.atomic import _json_default
from tergodic_cli.errors import TergodicError
from tergodic_cli.runlog import schema as S
from tergodic_cli.runlog.reader import RunLogData

def recompute_summary(data: RunLogData) -> dict[str, Any]:
    """The summary.json dict, recomputed from the log (without the ``truncated`` flag)."""
    from tergodic_cli.explore.summary import SERIES, summarize_run

    missing = [k for k in SERIES if k not in data.series]
    if missing:
        raise TergodicError(f"{data.path} has no series {', '.join(missing)}", "the log was not written by 'tergodic explore'")
    series = {k: data.series[k] for k in SERIES}
    robot = {}  # summarize_robot over the logged robot samples
    if data.robot:
        from tergodic_cli.robot import summarize_robot

        # a fault outside the explore phase leaves no sample: its stop reason is in the summary
        stop = (data.stored_summary or {}).get("stop_reason")
        robot = dict(summarize_robot(data.robot, **({"stop_reason": stop} if stop else {}), ticks=window_ticks(data)))
    own = set(summarize_run(series, data.config, None))
    static = {k: v for k, v in (data.stored_summary or {}).items() if k not in own and k not in robot}
    return summarize_run(series, data.config, {**static, **robot})


def window_ticks(data: RunLogData) -> dict[str, Any] | None:
    """The run's final 1 kHz figures from its force windows (/robot/force): the peak is the largest
    window max (every tick is in one window, the ticks after the last sample included), the rest the
    last window's cumulative figures. None for a log without windows (the last sample's are used)."""
    if not data.force_windows:
        return None
    last = data.force_windows[-1]
    ticks = {k: last.get(k) for k in ("tick_steady", "tick_force_rms_rel", "tick_tilt_median_deg", "tick_tilt_p95_deg")}
    ticks["tick_force_peak_N"] = max(w.get("force_max", 0.0) for w in data.force_windows)
    return ticks


def _robot_log_rows(data: RunLogData) -> list[tuple[str, str]]:
    """Rows for the robot's own records: its state transitions and the 1 kHz force windows."""
    rows = []
    if data.phases:
        seq = [data.phases[0].get("source", "?")] + [f"{p.get('target', '?')} {p.get('t', 0.0):.2f} s" for p in data.phases]
        if len(seq) > 13:  # a run with many move-overs: the start and the end
            seq = seq[:12] + [f"... {len(seq) - 13} more"] + seq[-1:]
        rows.append(("robot phases", f"{len(data.phases)} transitions: " + " -> ".join(seq)))
    if data.force_windows:
        w = max(data.force_windows, key=lambda r: r.get("force_max", 0.0))
        ticks = sum(int(r.get("ticks", 0)) for r in data.force_windows)
        rows.append(("force, 1 kHz windows", f"max {w.get('force_max', 0.0):.4g} N in {w.get('state', '?')} "
                     f"(t {w.get('t_start', 0.0):.3f}-{w.get('t_end', 0.0):.3f} s, step {w.get('step', 0)}); "
                     f"{len(data.force_windows)} windows, {ticks} ticks"))
    return rows


def canonical(obj: Any) -> str:
    """A JSON text for comparing summaries (key order ignored, NaN equal to NaN)."""
    return json.dumps(obj, sort_keys=True, default=_json_default)


def compare_with_file(summary: dict[str, Any], summary_path: Path) -> tuple[str, list[str]]:
    """Compare with a ``summary.json``: ("identical" | "differs" | "absent" | "unreadable", differing keys)."""
    if not summary_path.exists():
        return "absent", []
    try:
        stored = json.loads(summary_path.read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        return "unreadable", []
    mine = json.loads(canonical(summary))
    keys = sorted(k for k in set(mine) | set(stored) if canonical(mine.get(k)) != canonical(stored.get(k)))
    return ("identical" if not keys else "differs"), keys


def _fmt(x: Any, spec: str = ".6g") -> str:
    if x is None:
        return "n/a"
    if isinstance(x, bool):
        return str(x).lower()
    if isinstance(x, (int, float)):
        return format(x, spec)  # NaN formats as "nan"
    return str(x)


def _pct(x: Any) -> str:
    return "n/a" if x is None else f"{100 * x:.1f} %"


def _robot_rows(summary: dict[str, Any]) -> list[tuple[str, str]]:
    """Rows for the robot's summary keys that are present (summarize_robot's names)."""
    g = summary.get
    rows = []
    if "force_rms_error_rel" in summary:
        rows.append(("force (steady contact)", f"mean {_fmt(g('force_mean_N'), '.3g')} N against "
                     f"{_fmt(g('force_desired_N'), '.3g')} N desired, RMS error {_pct(g('force_rms_error_rel'))}, "
                     f"max {_fmt(g('force_max_N'), '.3g')} N"))
    if "contact_fraction" in summary:
        rows.append(("in contact", f"{_pct(g('contact_fraction'))} of explore steps"))
    for key, label, unit in (("tilt_deg", "tool tilt", "deg"), ("track_mm", "line tracking", "mm")):
        if f"{key}_median" in summary:
            rows.append((label, f"median {_fmt(g(f'{key}_median'), '.3g')} {unit}, p95 {_fmt(g(f'{key}_p95'), '.3g')} {unit}"))
    if "eps_sponge" in summary:
        rows.append(("ε / touched: sponge contacts", f"{_fmt(g('eps_sponge'))} / {_pct(g('touched_sponge'))}"))
        rows.append(("ε / touched: agent's own path", f"{_fmt(g('eps_agent'))} / {_pct(g('touched_agent'))}"))
    elif "contact_ergodicity" in summary:  # a log from before the sponge's own score: both are the agent's path
        rows.append(("contact ε / touched", f"{_fmt(g('contact_ergodicity'))} / {_pct(g('contact_touched_fraction'))}"))
    if "realtime_factor" in summary:
        rows.append(("real-time factor", f"{_fmt(g('realtime_factor'), '.3g')} x"))
    if "stop_reason" in summary:
        rows.append(("stop reason", str(g("stop_reason"))))
    return rows


def format_table(summary: dict[str, Any], data: RunLogData, comparison: tuple[str, list[str]] | None) -> str:
    """The human summary: steps, duration, ε at 200/500/end, touched, force statistics."""
    s = data.series
    lines = [f"{data.path}  (log schema {data.version}, {data.status if data.status == 'complete' else data.status.upper()})"]
    rows = [("steps", _fmt(summary.get("steps", data.steps), "d"))]
    if len(s["t"]):  # (a robot stopped before its first step logged none)
        t0, t1 = float(s["t"][0]), float(s["t"][-1])
        wall = float(s["step_ms"].sum()) / 1e3
        rows.append(("duration", f"{t1:.6g} s simulated (t = {t0:.6g} .. {t1:.6g}), {wall:.3g} s of explorer steps"))
    if summary.get("stop_reason") and not data.robot:
        rows.append(("stop reason", str(summary["stop_reason"])))
    rows += [(f"ε at step {k}", _fmt(v)) for k, v in (summary.get("ergodicity_at") or {}).items()
             if v is not None]
    source = f", {summary['eps_source']}" if summary.get("eps_source") else ""
    rows.append((f"ε at end (unit-mass, 0 best{source})", _fmt(summary.get("ergodicity"))))
    rows.append(("authors' residual at end", _fmt(summary.get("residual_ref"))))
    tf = summary.get("touched_fraction")
    rows.append(("target touched", "n/a" if tf is None else f"{100 * tf:.2f} %"))
    if summary.get("off_surface_fraction") is not None:
        rows.append(("off the surface (> 2h, or > h/2 off its sheet)",
                     f"{100 * summary['off_surface_fraction']:.2f} % of steps"))
    if summary.get("step_max_m") is not None:
        rows.append(("largest step", f"{1e3 * summary['step_max_m']:.3f} mm"))
    if summary.get("step_ms_median") is not None:
        rows.append(("step time median", f"{summary['step_ms_median']:.3g} ms"))
    if data.robot:
        rows += _robot_rows(summary)
        rows += _robot_log_rows(data)
        rs = data.robot_series()
        if "force_normal" in rs:
            f, contact = rs["force_normal"], rs.get("in_contact")
            some = contact is not None and contact.any()
            fc = f[contact.astype(bool)] if some else f
            rows.append(("normal force", f"mean {fc.mean():.3g} N, std {fc.std():.3g} N, max {f.max():.3g} N"
                         + (" (samples in contact)" if some else "")))
    if data.events:
        rows.append(("events", str(len(data.events))))
    rows.append(("clouds logged", str(data.topics.get(S.TOPIC_CLOUD, {}).get("count", 0))))
    if comparison is not None:
        state, keys = comparison
        rows.append(("summary.json", state if not keys else f"{state} in {', '.join(keys)}"))
    width = max(len(r[0]) for r in rows)
    lines += [f"  {k:<{width}}  {v}" for k, v in rows]
    if data.truncated:
        lines.append(f"  note: the log is truncated ({data.truncation_note}); read up to the last complete chunk")
    elif data.status == "interrupted":
        lines.append("  note: the run was interrupted (Ctrl-C or SIGTERM); the log holds the steps before it")
    return "\n".join(lines)


def to_json(obj: Any) -> str:
    """``obj`` (a summary or :func:`state_at` dict; numpy values allowed) as indented JSON."""
    return json.dumps(obj, indent=2, default=_json_default)


def state_at(data: RunLogData, step: int) -> dict[str, Any]:
    """The logged state after explorer step ``step``: its series values (agent vectors as nested
    lists), the robot sample, the ranges of the last cloud logged at or before it, and the events so far."""
    i = data.index_of(step)
    s = data.series
    state: dict = {"step": int(s["step"][i]), "t": float(s["t"][i]),
                   **{k: v[i].tolist() if isinstance(v[i], np.ndarray) else float(v[i])
                      for k, v in s.items() if k not in ("step", "t")}}
    if data.robot and i < len(data.robot):
        state["robot"] = {k: v for k, v in data.robot[i].items() if k != "step"}
    cloud = data.cloud_at(step)
    if cloud is not None:
        cov, tgt = cloud.fields.get("coverage"), cloud.fields.get("target")
        info = {"step": cloud.step, "n_points": len(cloud.points)}
        for name, values in cloud.fields.items():
            info[f"{name}_min"], info[f"{name}_max"] = float(values.min()), float(values.max())
        if cov is not None and tgt is not None:
            info["coverage_on_target_sum"] = float(cov[tgt > 0].sum())
        state["cloud"] = info
    state["events_so_far"] = [{"step": e[0], "text": e[2]} for e in data.events if e[0] <= step]
    return state


def format_state(state: dict[str, Any]) -> str:
    """:func:`state_at`'s dict as the text ``tergodic replay --step N`` prints."""
    lines = [f"step {state['step']}  (t = {state['t']:.6g} s)"]
    for k, v in state.items():
        if k in ("step", "t", "robot", "cloud", "events_so_far"):
            continue
        if isinstance(v, list):
            arr = np.asarray(v)
            lines.append(f"  {k:<18} " + "; ".join(np.array2string(r, precision=6, separator=", ", max_line_width=200) for r in arr.reshape(-1, 3)))
        else:
            lines.append(f"  {k:<18} {v:.9g}")
    if "robot" in state:
        lines.append("  robot:")
        for k, v in state["robot"].items():
            if k == "link_poses":
                lines.append(f"    {k:<16} {len(v)} links")
            elif isinstance(v, np.ndarray):
                lines.append(f"    {k:<16} {np.array2string(v, precision=5, separator=', ', max_line_width=200)}")
            else:
                lines.append(f"    {k:<16} {v}")
    if "cloud" in state:
        c = state["cloud"]
        extra = ", ".join(f"{k} {v:.4g}" for k, v in c.items() if k not in ("step", "n_points"))
        lines.append(f"  cloud (logged at step {c['step']}, {c['n_points']} points): {extra}")
    if ev := state["events_so_far"]:
        lines.append(f"  last event: step {ev[-1]['step']}: {ev[-1]['text']}")
    return "\n".join(lines)
