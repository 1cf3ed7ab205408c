"""A self-contained, interactive HTML report of a run, from its log alone (plotly, offline).

The page holds plotly.js itself (no CDN, no network) and two figures:

- the cloud in 3-D, coloured by target p, coverage c̃, heat u or source s (buttons), with a
  slider over the logged clouds, the agents' trajectories as 3-D lines and their positions at
  the cloud's step;
- the time series: ε(t), the authors' residual on its own axis, touched(t), and for robot
  runs the normal force against the desired one and the tool tilt.

The numbers behind the figures are also embedded as JSON in
``<script type="application/json" id="tergodic-data">``, for scripts and tests.
"""

from __future__ import annotations

import html
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from tergodic_cli.atomic import atomic_path, check_output_file
from tergodic_cli.errors import TergodicError
from tergodic_cli.runlog.plots import RESIDUAL_KEYS, broken_at, colour_range, log_scale, timeline
from tergodic_cli.runlog.reader import RunLogData

#: More points than this are subsampled on the page (evenly, deterministic); the page says so.
MAX_POINTS = 40_000
#: Budget of per-point values over all slider frames (float32: 4 bytes each, before base64).
MAX_FRAME_VALUES = 6_000_000
#: Longer trajectories are drawn through an even subset of their steps (each frame carries its path so
#: far, so the page grows with frames x steps); the page says so.
MAX_TRAJ_ROWS = 4_000

#: field -> (colour scale, colour bar title with units, button label)
_FIELDS = {
    "target": ("Cividis", "target p<br>(0-1, unitless)", "target p"),
    "coverage": ("Viridis", "coverage c̃<br>(unitless)", "coverage c̃"),
    "heat": ("Inferno", "heat u<br>(1/m²)", "heat u"),
    "source": ("Magma", "source s<br>(1/m⁴)", "source s"),
}
_AGENT_COLOURS = ("#d62728", "#1f77b4", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b")
_FIX = "choose another --html path"


def write_html_report(data: RunLogData, path: str | os.PathLike) -> Path:
    """Write an interactive, offline HTML report of a run.

    Parameters
    ----------
    data : RunLogData
        The run log, as :func:`tergodic_cli.runlog.read_run_log` returns it (with its clouds).
    path : path-like
        The ``.html`` file to write; written atomically (a temporary file renamed over it),
        its folder created when missing.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    TergodicError
        The file cannot be written (one line, exit 2 in the CLI).

    Notes
    -----
    Clouds of more than :data:`MAX_POINTS` points are subsampled evenly, and the slider keeps
    an even subset of the clouds when all of them would exceed :data:`MAX_FRAME_VALUES`
    values; the page says when either happens. Otherwise the page's numbers are the log's:
    positions and series in float64, cloud points and fields in float32, as logged.
    """
    import plotly.io as pio
    from plotly.offline import get_plotlyjs

    path = Path(path)
    check_output_file(path, True, "--html")  # the verb asked for --overwrite already
    notes: list[str] = []
    cloud_fig, embedded = _cloud_figure(data, notes)
    series_fig, series_rows = _series_figure(data, embedded.get("frames", []))
    embedded.update(series_rows)
    config = {"displaylogo": False, "responsive": True,
              "toImageButtonOptions": {"format": "png", "filename": "tergodic_report"}}
    parts = [pio.to_html(fig, include_plotlyjs=False, full_html=False, config=config, div_id=div_id, auto_play=False)
             for fig, div_id in ((cloud_fig, "tergodic-cloud"), (series_fig, "tergodic-series"))
             if fig is not None]
    log = data.path.resolve()  # "." has no name
    page = _PAGE.format(
        title=html.escape(f"tergodic report: {log.parent.name}"),
        plotlyjs=get_plotlyjs(),
        heading=html.escape(f"Run {log.parent.name}/{log.name}"),
        meta=_meta_line(data),
        notes="".join(f"<p class='note'>{html.escape(n)}</p>" for n in notes),
        figures="\n".join(f"<section>{p}</section>" for p in parts),
        data=_script_json(embedded),
    )
    try:
        with atomic_path(path, suffix=".html") as tmp:
            tmp.write_text(page, encoding="utf-8")
    except TergodicError as exc:  # atomic_path's own line: keep its cause, say which option to change
        raise TergodicError(exc.problem, f"{exc.fix}; or {_FIX}" if exc.fix else _FIX) from None
    return path


def _meta_line(data: RunLogData) -> str:
    s = data.series
    bits = [f"{data.steps} steps"]
    pos = s.get("positions")
    if pos is not None and pos.dtype != object and pos.ndim == 3:
        bits.append(f"{pos.shape[1]} agent{'s' if pos.shape[1] != 1 else ''}")
    if data.clouds:
        bits.append(f"{len(data.clouds[-1].points)} points, {len(data.clouds)} logged clouds")
    if len(s.get("ergodicity", ())):
        sponge = " (sponge contacts)" if "ergodicity_agent" in s else ""  # a robot run's ε is its real contacts'
        bits.append(f"final ε{sponge} {s['ergodicity'][-1]:.4g}")
    if len(s.get("touched_fraction", ())):
        bits.append(f"touched {100 * s['touched_fraction'][-1]:.1f} %")
    bits.append("robot run" if data.robot else "kinematic run")
    if data.truncated:
        bits.append("TRUNCATED log (the run was cut short)")
    return html.escape(" · ".join(bits))


def _positions(data: RunLogData) -> np.ndarray | None:
    """(T, N, 3) agent positions; NaN-padded when the agent count changed mid-run."""
    pos = data.series.get("positions")
    if pos is None or len(pos) == 0:
        return None
    if pos.dtype == object:
        n = max(len(p) for p in pos)
        out = np.full((len(pos), n, 3), np.nan)
        for i, p in enumerate(pos):
            out[i, :len(p)] = p
        return out
    return pos


def _cloud_figure(data: RunLogData, notes: list[str]) -> tuple[Any, dict]:
    import plotly.graph_objects as go

    embedded: dict[str, Any] = {}
    pos = _positions(data)
    steps = data.series["step"]
    clouds = data.clouds
    if not clouds and pos is None:
        return None, embedded
    fig, idx, fields, shown = go.Figure(), slice(None), [], []  # idx: the points shown
    if clouds:
        last = clouds[-1]
        n = len(last.points)
        if n > MAX_POINTS:
            idx = np.linspace(0, n - 1, MAX_POINTS).round().astype(np.int64)
            notes.append(f"The cloud has {n} points; the page shows {MAX_POINTS} of them, evenly subsampled.")
            embedded["point_index"] = idx.tolist()
        fields = [f for f in _FIELDS if f in last.fields] + [f for f in last.fields if f not in _FIELDS]
        # which clouds get a slider frame: all of them, unless that exceeds the size budget
        per_frame = max(1, len(fields) * len(last.points[idx]))
        keep = max(2, MAX_FRAME_VALUES // per_frame)
        # two clouds at one step (a re-capture's and the periodic one): the slider shows the later
        last_at = {c.step: i for i, c in enumerate(clouds)}
        shown = sorted(last_at.values())
        if len(shown) > keep:
            pick = np.linspace(0, len(shown) - 1, keep).round().astype(int)
            shown = sorted({shown[i] for i in pick.tolist()})
            notes.append(f"{len(clouds)} clouds were logged; the slider shows {len(shown)} of them, evenly spaced.")
        pts = _f32(last.points[idx])
        for j, f in enumerate(fields):
            cmap, cbar, label = _FIELDS.get(f, ("Viridis", f, f))
            vmin, vmax = colour_range(f, last.fields[f][idx])  # each frame carries its own limits
            fig.add_trace(go.Scatter3d(
                x=pts[:, 0], y=pts[:, 1], z=pts[:, 2], mode="markers", name=label,
                visible=(j == min(1, len(fields) - 1)),  # coverage first: what the run did
                marker=dict(size=2.6, color=_f32(last.fields[f][idx]), colorscale=cmap, cmin=vmin, cmax=vmax,
                            colorbar=dict(title=dict(text=cbar), thickness=14, len=0.75, x=0.98)),
                hovertemplate="x %{x:.4f} m<br>y %{y:.4f} m<br>z %{z:.4f} m<br>" + f + " %{marker.color:.4g}"
                              "<extra></extra>",
                showlegend=False))
        embedded["points"] = _nested(pts)
        # a cloud repeats its points only when they differ from the last cloud's
        embedded["clouds"] = [{"step": int(clouds[i].step),
                               **({} if np.array_equal(clouds[i].points, last.points)
                                  else {"points": _nested(_f32(clouds[i].points[idx]))}),
                               **{f: _nested(_f32(clouds[i].fields[f][idx])) for f in fields if f in clouds[i].fields}}
                              for i in shown]
    traj_traces: list[int] = []
    if pos is not None:
        upto = len(pos) if not clouds else _row_of(steps, clouds[shown[-1]].step) + 1  # the slider's start
        stride = -(-len(pos) // MAX_TRAJ_ROWS)
        if stride > 1:
            notes.append(f"The trajectory has {len(pos)} steps; the page draws every {stride}th of them.")

        def path(k: int, upto: int) -> dict:
            """Agent k's path through steps 0..upto-1 (every ``stride``th, and the last)."""
            rows = np.unique(np.r_[np.arange(0, upto, stride), upto - 1])
            return dict(x=pos[rows, k, 0], y=pos[rows, k, 1], z=pos[rows, k, 2])

        for k in range(pos.shape[1]):
            traj_traces.append(len(fig.data))
            fig.add_trace(go.Scatter3d(**path(k, upto), mode="lines",
                                       name=f"agent {k} trajectory", hoverinfo="skip",
                                       line=dict(color=_AGENT_COLOURS[k % len(_AGENT_COLOURS)],
                                                 width=3)))
        at = pos[upto - 1]
        fig.add_trace(go.Scatter3d(x=at[:, 0], y=at[:, 1], z=at[:, 2], mode="markers", name="agents at the cloud's step",
                                   marker=dict(size=8, color="white", line=dict(color="black", width=3), symbol="diamond")))
        embedded["positions"] = _nested(pos)
    agent_trace = len(fig.data) - 1

    if clouds:
        moved = any(not np.array_equal(clouds[i].points, last.points) for i in shown)  # a re-capture moved them
        varying = [j for j, f in enumerate(fields)
                   if moved or any(f in clouds[i].fields and not np.array_equal(clouds[i].fields[f], last.fields[f])
                                   for i in shown)]
        frames, slider_steps = [], []
        # every frame: the fields that change (colours, and points when a re-capture moved them), the
        # colour limits of every field but the fixed 0-1 target, the trajectory up to the cloud's step
        # and the agents there
        framed = [j for j, f in enumerate(fields) if j in varying or f != "target"]
        p = None
        for i in shown:
            c = clouds[i]
            fdata, traces = [], []
            if moved:
                p = _f32(c.points[idx])
            for j in framed:
                f = fields[j]
                vals = c.fields[f][idx] if f in c.fields else last.fields[f][idx]
                lo, hi = colour_range(f, vals)
                marker = dict(cmin=lo, cmax=hi, **({"color": _f32(vals)} if j in varying else {}))
                d = go.Scatter3d(marker=marker)
                if moved:
                    d.update(x=p[:, 0], y=p[:, 1], z=p[:, 2])
                fdata.append(d)
                traces.append(j)
            if pos is not None:
                row = _row_of(steps, c.step)
                for k, tr in enumerate(traj_traces):
                    fdata.append(go.Scatter3d(**path(k, row + 1)))
                    traces.append(tr)
                a = pos[row]
                fdata.append(go.Scatter3d(x=a[:, 0], y=a[:, 1], z=a[:, 2]))
                traces.append(agent_trace)
            frames.append(go.Frame(name=str(i), data=fdata, traces=traces))
            slider_steps.append(dict(method="animate", label=f"{c.step}",
                                     args=[[str(i)], dict(mode="immediate", frame=dict(duration=0, redraw=True),
                                                        transition=dict(duration=0))]))
        fig.frames = frames
        nf = len(fields)
        vis = lambda j: [t == j for t in range(nf)] + [True] * (len(fig.data) - nf)  # noqa: E731
        fig.add_annotation(text="colour by", x=0.0, y=0.985, xref="paper", yref="paper", xanchor="left",
                           yanchor="top", showarrow=False, font=dict(size=13))
        fig.update_layout(
            sliders=[dict(active=len(shown) - 1, steps=slider_steps, x=0.04, len=0.92, y=0.0, pad=dict(t=10, b=4),
                          transition=dict(duration=0),
                          currentvalue=dict(prefix="cloud logged at explorer step ", font=dict(size=13)))],
            updatemenus=[
                dict(type="buttons", direction="right", x=0.09, y=1.0, xanchor="left", yanchor="top", showactive=True,
                     active=min(1, len(fields) - 1), pad=dict(r=4, t=4), bgcolor="#f4f4f4",
                     buttons=[dict(label=fig.data[j].name, method="restyle",
                                   args=[{"visible": vis(j)}])
                              for j in range(len(fields))]),
                dict(type="buttons", direction="right", x=0.0, y=0.06, xanchor="left", yanchor="bottom",
                     pad=dict(r=4), showactive=False, bgcolor="#f4f4f4",
                     buttons=[dict(label="▶ play", method="animate",
                                   args=[None, dict(frame=dict(duration=400, redraw=True), fromcurrent=True,
                                                    transition=dict(duration=0), mode="immediate")]),
                              dict(label="❚❚ pause", method="animate",
                                   args=[[None], dict(frame=dict(duration=0, redraw=False), mode="immediate")])]),
            ])
    axis = dict(showbackground=True, backgroundcolor="#f7f7f7", gridcolor="#d0d0d0", tickformat=".3f")
    fig.update_layout(
        title=dict(text="Cloud and trajectory (object frame)", x=0.02, y=0.985, font=dict(size=16)),
        height=820, margin=dict(l=0, r=0, t=40, b=10), paper_bgcolor="white",
        scene=dict(aspectmode="data",
                   **{f"{c}axis": dict(title=dict(text=f"{c} (m)"), **axis) for c in "xyz"},
                   camera=dict(eye=dict(x=1.3, y=-1.3, z=1.0)), domain=dict(x=[0, 0.9], y=[0.1, 0.93])),
        legend=dict(x=0.01, y=0.1, yanchor="bottom", bgcolor="rgba(255,255,255,0.7)"),
    )
    embedded["frames"] = [{"name": str(i), "step": int(clouds[i].step)} for i in shown]
    return fig, embedded


def _series_figure(data: RunLogData, frames: list[dict]) -> tuple[Any, dict]:
    """The time plots on one simulated-time axis, a cursor on each, the re-captures marked.

    ``frames`` (the cloud figure's slider frames: name, step) become this figure's frames of the
    same names, each moving the cursors to its step's time; the page's script plays them with the
    cloud's slider.
    """
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    s, t = data.series, data.series["t"]
    x, gaps = timeline(data)
    embedded: dict[str, Any] = {"step": s["step"].tolist(), "t": t.tolist(), "time": x.tolist(),
                                "recapture_rows": gaps}

    def line(into: dict, key: str, xs, y, name: str, colour: str, dash: str | None = None,
             **kw) -> Any:
        into[key] = _nested(y)  # the numbers drawn (unbroken), also in the page's JSON block
        xs, y = broken_at(xs, y, gaps) if len(xs) == len(x) else (xs, y)
        return go.Scatter(x=xs, y=y, name=name, line=dict(color=colour, dash=dash), **kw)

    eps = np.asarray(s["ergodicity"], dtype=np.float64)
    solo = dict(showlegend=False)
    # (title, y title, traces, y axis options)
    rows = [("Ergodicity ε over time", "ε (dimensionless)",
             [line(embedded, "ergodicity", x, eps, "ε of the sponge's contacts (eq. 48)" if "ergodicity_agent" in s
                   else "ε (eq. 48)", "#1f77b4", **solo)],
             dict(type="log") if log_scale(eps) else dict(rangemode="tozero"))]
    if ref := next((k for k in RESIDUAL_KEYS if k in s), None):
        rows.append(("Authors' residual: share of the target's heat not yet touched", f"{ref} (unitless)",
                     [line(embedded, ref, x, s[ref], ref, "#ff7f0e", **solo)],
                     dict(rangemode="tozero")))
    if "touched_fraction" in s:
        rows.append(("Target touched over time", "touched (% of target)",
                     [line(embedded, "touched_fraction", x, s["touched_fraction"], "touched",
                           "#2ca02c", **solo)],
                     dict(range=[0, 1.05], tickformat=".0%")))
    n_explorer = len(rows)

    if rs := data.robot_series():
        rt = rs["t_sim"] if "t_sim" in rs else t[:len(data.robot)]
        robot = embedded["robot"] = {"t_sim": _nested(rt)}
        force = []
        if "force_normal" in rs:
            force.append(line(robot, "force_normal", rt, rs["force_normal"],
                              "measured normal force", "#d62728"))
        if "wrench_desired" in rs and rs["wrench_desired"].ndim == 2:  # along the tool axis
            force.append(line(robot, "force_desired", rt, rs["wrench_desired"][:, 2],
                              "desired force", "black", dash="dash"))
        if force:
            rows.append(("Contact force against desired", "force (N)", force, {}))
        if "tilt_deg" in rs:
            rows.append(("Tool tilt from the surface normal", "tilt (°)",
                         [line(robot, "tilt_deg", rt, rs["tilt_deg"], "tilt", "#9467bd", **solo)],
                         dict(rangemode="tozero")))
        if gaps:  # the closed loop: the ink left at each re-capture, capture 0 being all of it
            ink = []
            for key, name, colour in (("marking_remaining", "marking seen by the camera", "#8c564b"),
                                      ("marking_remaining_true", "ink left in the texture", "#e377c2")):
                rows_k = [i for i in gaps if data.robot[i].get(key) is not None]
                if rows_k:
                    tk = np.r_[0.0, rt[rows_k]]
                    vk = np.r_[1.0, [float(data.robot[i][key]) for i in rows_k]]
                    robot[key] = {"t_sim": _nested(tk), "share": _nested(vk)}
                    ink.append(go.Scatter(x=tk, y=vk, name=name, mode="lines+markers",
                                          line=dict(color=colour, shape="hv")))
            if ink:
                rows.append(("Marking left (capture 0 = 100 %, then each re-capture)", "left (% of capture 0)",
                             ink, dict(range=[0, 1.05], tickformat=".0%")))
    one_axis = not data.robot or len(data.robot) == len(x)  # every step has its physics time

    fig = make_subplots(rows=len(rows), cols=1, subplot_titles=[r[0] for r in rows], vertical_spacing=0.42 / len(rows))
    for r, (_, ytitle, traces, yopts) in enumerate(rows, start=1):
        for tr in traces:
            fig.add_trace(tr, row=r, col=1)
        fig.update_yaxes(title_text=ytitle, row=r, col=1, gridcolor="#e5e5e5", **yopts)
        # one time axis; a robot log with fewer samples than steps keeps the physics clock apart
        fig.update_xaxes(matches="x" if one_axis or r <= n_explorer else f"x{n_explorer + 1}", row=r, col=1,
                         showticklabels=True, gridcolor="#e5e5e5")
    fig.update_xaxes(title_text="simulated time (s)", row=len(rows), col=1)
    if not one_axis:
        fig.update_xaxes(title_text="simulated time t (s)", row=n_explorer, col=1)
        fig.update_xaxes(title_text="robot simulated time (s)", row=len(rows), col=1)

    # re-captures: a grey band over each pause (retreat, picture, hover, approach) and a line at its start
    marks = []
    for g in gaps:
        end = x[g + 1] if g + 1 < len(x) else x[g]
        marks.append(dict(type="rect", name="recapture", xref="x", yref="paper", x0=x[g], x1=end, y0=0, y1=1,
                          fillcolor="#bbbbbb", opacity=0.25, line=dict(width=0), layer="below"))
        marks.append(dict(type="line", name="recapture", xref="x", yref="paper", x0=x[g], x1=x[g], y0=0, y1=1,
                          line=dict(color="#8c564b", width=1, dash="dash"), layer="below"))
    if gaps:
        fig.add_annotation(text="grey bands: re-capture pauses", xref="paper", yref="paper", x=1, y=1.0,
                           xanchor="right", yanchor="bottom", showarrow=False, font=dict(size=11, color="#555"))

    def cursors(at: float) -> list[dict]:
        return [dict(type="line", name="cursor", xref=f"x{r if r > 1 else ''}", yref=f"y{r if r > 1 else ''} domain",
                     x0=at, x1=at, y0=0, y1=1, line=dict(color="#333", width=1.5, dash="dot"))
                for r in range(1, len(rows) + 1)]

    steps = np.asarray(s["step"])
    frame_time = [float(x[_row_of(steps, f["step"])]) for f in frames]
    fig.update_layout(shapes=marks + cursors(frame_time[-1] if frames else float(x[-1])))
    fig.frames = [go.Frame(name=f["name"], layout=dict(shapes=marks + cursors(at)))
                  for f, at in zip(frames, frame_time)]
    embedded["frame_time"] = frame_time
    fig.update_annotations(font_size=13)
    fig.update_layout(height=max(820, 250 * len(rows)), margin=dict(l=70, r=20, t=40, b=50),
                      paper_bgcolor="white", plot_bgcolor="white", hovermode="x unified",
                      legend=dict(orientation="h", x=0, y=-0.08 if len(rows) < 4 else -0.05))
    return fig, embedded


def _row_of(steps: np.ndarray, step: int) -> int:
    """Row of the last logged step at or before ``step`` (the cloud's step)."""
    return max(0, int(np.searchsorted(steps, step, side="right")) - 1)


def _f32(a: np.ndarray) -> np.ndarray:
    # Cloud points and fields are float32 in the log: float32 on the page is exact and half the size.
    return np.ascontiguousarray(a, dtype=np.float32)


def _nested(a: np.ndarray) -> list:
    """(Nested) lists of floats for JSON, NaN as null (JSON has no NaN)."""
    a = np.asarray(a, dtype=np.float64)
    return np.where(np.isfinite(a), a, None).tolist()


def _script_json(obj: Any) -> str:
    """JSON safe inside <script>: '</' cannot close the element early."""
    return json.dumps(obj, allow_nan=False, separators=(",", ":")).replace("</", "<\\/")


_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<meta name="generator" content="tergodic replay --html">
<title>{title}</title>
<style>
  body {{ font-family: system-ui, -apple-system, "Segoe UI", Roboto, "DejaVu Sans", sans-serif; margin: 0;
         color: #222; background: #fafafa; }}
  header {{ padding: 10px 18px 6px; border-bottom: 1px solid #e2e2e2; background: white; }}
  h1 {{ font-size: 19px; margin: 0 0 2px; }}
  .meta {{ font-size: 13px; color: #555; margin: 0; }}
  .note {{ font-size: 13px; color: #8a5a00; margin: 2px 0 0; }}
  main {{ display: grid; grid-template-columns: minmax(0, 58fr) minmax(0, 42fr); gap: 8px; padding: 8px;
          align-items: start; }}
  section {{ background: white; border: 1px solid #e2e2e2; border-radius: 4px; min-width: 0; }}
  @media (max-width: 1000px) {{ main {{ grid-template-columns: 1fr; }} }}
</style>
<script type="text/javascript">{plotlyjs}</script>
</head>
<body>
<header>
<h1>{heading}</h1>
<p class="meta">{meta}</p>
{notes}
</header>
<main>
{figures}
</main>
<script type="application/json" id="tergodic-data">{data}</script>
<script type="text/javascript">
  // The cloud's slider (and its play button) drives the time plots: each cloud frame has a time-plot
  // frame of the same name that moves the cursors to that step's time.
  window.addEventListener("load", function () {{
    var cloud = document.getElementById("tergodic-cloud"), series = document.getElementById("tergodic-series");
    if (!cloud || !series || !cloud.on) return;
    cloud.on("plotly_animatingframe", function (ev) {{
      if (ev && ev.name != null) {{
        Plotly.animate(series, [ev.name], {{mode: "immediate", frame: {{duration: 0, redraw: true}},
                                           transition: {{duration: 0}}}});
      }}
    }});
  }});
</script>
</body>
</html>
"""
