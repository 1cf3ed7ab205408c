"""PNG figures of a run, from its log alone (matplotlib, Agg backend: no display needed).

The files (ε, touched, force, cleaning and three cloud views) are listed in docs/logging.md.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from tergodic_cli.atomic import atomic_path
from tergodic_cli.runlog.reader import RunLogData

#: (name, horizontal axis, vertical axis, depth axis towards the viewer, sign of depth)
_VIEWS = (("front (x-z)", 0, 2, 1, -1), ("side (y-z)", 1, 2, 0, 1), ("top (x-y)", 0, 1, 2, 1))


def _pyplot():
    import logging

    import matplotlib

    matplotlib.use("Agg", force=True)
    logging.getLogger("matplotlib").setLevel(logging.ERROR)  # its layout notes are not the user's problem
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    """Write ``fig`` as a PNG atomically, then close it."""
    import matplotlib.pyplot as plt

    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path


def _single(plt, path: Path, title: str, xlabel: str, ylabel: str, draw) -> Path:
    """One axes: ``draw(ax)`` plots, then the labels, a grid and a legend of the labelled lines."""
    fig, ax = plt.subplots(figsize=(7, 4))
    draw(ax)
    ax.set(xlabel=xlabel, ylabel=ylabel, title=title)
    ax.grid(True, alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend()
    fig.tight_layout()
    return _save(fig, path)


def plot_run(data: RunLogData, out_dir: str | os.PathLike) -> list[Path]:
    """Write the figures into ``out_dir`` (created); returns the paths written."""
    plt = _pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    s = data.series
    t, gaps = timeline(data)  # the force plot's clock too; lines break at re-capture pauses
    tlabel = "simulated time (s)"
    note = " (truncated log)" if data.truncated else ""

    written = [_plot_ergodicity(plt, t, tlabel, s, note, out / "ergodicity.png", gaps)]

    def touched(ax) -> None:
        ax.plot(*broken_at(t, 100 * s["touched_fraction"], gaps), color="C2", clip_on=False)
        ax.set_ylim(0, 103)  # a curve at 100 % stays above the frame's top edge

    written.append(_single(plt, out / "touched.png", f"Target touched over time{note}", tlabel,
                           "target touched (%)", touched))

    written += _plot_force(plt, data, data.robot_series(), out, note)
    written += _plot_cleaning(plt, data, out, note)
    if data.clouds:
        cloud, traj = data.clouds[-1], data.series.get("positions")
        for field, cmap, label, line in (("target", "cividis", "target weight p (0-1, unitless)", "red"),
                                         ("coverage", "viridis", "coverage c̃ (summed footprint, unitless)", "red"),
                                         ("heat", "inferno", "heat u (1/m²)", "cyan")):
            if field in cloud.fields:
                written.append(_plot_cloud(plt, cloud, field, cmap, label, traj, out / f"cloud_{field}.png", note, line))
    return written


#: The authors' residual, under its old and its new name (the first one present is plotted).
RESIDUAL_KEYS = ("residual_ref", "ergodicity_ref")


def log_scale(eps: np.ndarray) -> bool:
    """A log axis for ε only when its finite values are positive and span more than a decade."""
    fin = eps[np.isfinite(eps)]
    return bool(fin.size and np.all(fin > 0) and fin.max() > 10 * fin.min())


def _plot_ergodicity(plt, t, tlabel: str, s: dict, note: str, path: Path, gaps: list[int] = ()) -> Path:
    """ε (eq. 48) and the authors' residual, each on its own axis: they are different quantities; no line
    after the rows in ``gaps`` (re-capture pauses)."""
    ref = next((k for k in RESIDUAL_KEYS if k in s), None)
    fig, axes = plt.subplots(2 if ref else 1, 1, figsize=(7, 5.6 if ref else 3.6), sharex=True, squeeze=False)
    ax = axes[0, 0]
    eps = np.asarray(s["ergodicity"], dtype=np.float64)
    ax.plot(*broken_at(t, eps, list(gaps)), color="C0")
    if log_scale(eps):
        ax.set_yscale("log")
    ax.set(ylabel="ε (eq. 48)", title=f"Ergodicity ε over time{note}")
    if ref:
        ax2 = axes[1, 0]
        ax2.plot(*broken_at(t, s[ref], list(gaps)), color="C1")
        ax2.set_ylim(0, max(1.0, float(np.nanmax(s[ref])) if len(s[ref]) else 1.0) * 1.02)
        ax2.set_ylabel(f"{ref} (unitless)")
        ax2.set_title("Residual of the authors' code: share of the target's heat not yet touched", fontsize=10)
    for a in axes[:, 0]:
        a.grid(True, alpha=0.3)
    axes[-1, 0].set_xlabel(tlabel)
    fig.tight_layout()
    return _save(fig, path)


def timeline(data: RunLogData) -> tuple[np.ndarray, list[int]]:
    """One simulated-time axis for every plot, and the rows after which the run paused for a re-capture.

    Parameters
    ----------
    data : RunLogData
        The run log.

    Returns
    -------
    x : (T,) array, s
        Per logged step: the robot's simulated time ``t_sim`` when every step has a robot sample (the
        physics clock, which also runs through approaches, retreats and re-capture moves), else the
        explorer's ``t``.
    gaps : list of int
        Rows (increasing) of the cycle's last step before each re-capture: its sample carries
        ``marking_remaining`` (the closed loop, docs/closed_loop.md). Lines break after them. Empty
        unless there is one robot sample per step.
    """
    t = np.asarray(data.series["t"], dtype=np.float64)
    robot = data.robot or []
    if len(robot) != len(t):  # samples not one per step: their rows are not the steps' rows
        return t, []
    if all(isinstance(r.get("t_sim"), (int, float)) for r in robot):
        t = np.array([float(r["t_sim"]) for r in robot])
    return t, [i for i, r in enumerate(robot) if r.get("marking_remaining") is not None]


def broken_at(x: np.ndarray, y: np.ndarray, gaps: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """``x``, ``y`` (n,) with a NaN point after each row in ``gaps`` (plotly and matplotlib draw no line
    across it): (n + number of gaps before the last row,) each."""
    gaps = [g for g in gaps if g < len(x) - 1]
    if not gaps:
        return x, y
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    return np.insert(x, np.array(gaps) + 1, np.nan), np.insert(y, np.array(gaps) + 1, np.nan)


def _plot_force(plt, data: RunLogData, rs: dict, out: Path, note: str) -> list[Path]:
    """Measured normal force against the desired one (wrench_desired's z, the tool axis), per explorer step."""
    if "force_normal" not in rs and "wrench_measured" not in rs:
        return []
    t = rs["t_sim"] if "t_sim" in rs else data.series["t"][:len(data.robot)]
    measured = rs["force_normal"] if "force_normal" in rs else np.linalg.norm(rs["wrench_measured"][:, :3], axis=1)
    gaps = timeline(data)[1]  # closed loop: no line across a re-capture pause

    def draw(ax) -> None:
        ax.plot(*broken_at(t, measured, gaps), label="measured normal force", color="C3", lw=1)
        if "wrench_desired" in rs and rs["wrench_desired"].ndim == 2:
            ax.plot(*broken_at(t, rs["wrench_desired"][:, 2], gaps), label="desired normal force", color="k",
                    ls="--", lw=1)
        off = ~rs["in_contact"].astype(bool) if "in_contact" in rs else np.zeros(0, bool)
        if off.any():
            ax.fill_between(t, 0, 1, where=off, transform=ax.get_xaxis_transform(), color="0.85", lw=0,
                            label="not in contact")
        ax.set_ylim(bottom=0)

    return [_single(plt, out / "force.png", f"Contact force against desired{note}",
                    "simulated time (s)", "force (N)", draw)]


def _plot_cleaning(plt, data: RunLogData, out: Path, note: str) -> list[Path]:
    """Closed-loop runs: the share of the initial marking left after each re-capture, against steps.

    The robot sample of each cycle's last step carries ``marking_remaining`` (what the camera sees)
    and ``marking_remaining_true`` (the texture's ink), see :mod:`tergodic_cli.backends.pybullet.closed_loop`.
    """
    rows = [s for s in (data.robot or []) if s.get("marking_remaining") is not None]
    if not rows:
        return []
    steps = np.array([0] + [int(s["step"]) for s in rows])
    seen = np.array([1.0] + [float(s["marking_remaining"]) for s in rows])
    true = [s.get("marking_remaining_true") for s in rows]

    def draw(ax) -> None:
        ax.plot(steps, 100 * seen, "o-", color="C3", label="seen by the camera (marking_remaining)")
        if all(v is not None for v in true):
            ax.plot(steps, 100 * np.array([1.0] + [float(v) for v in true]), "s--", color="0.4",
                    ms=4, label="ink left in the texture (true)")
        ax.set_ylim(0, 105)

    return [_single(plt, out / "cleaning.png", f"Cleaning: marking left at each re-capture{note}",
                    "explorer step", "marking left (% of the initial)", draw)]


#: Colour limits of the fields that are not already on a fixed 0-1 scale: these percentiles of the
#: frame's own values (the upper one among the values above the lower), so that a few extreme points
#: (or an offset: heat spans 1.8e4-2.4e4) do not wash out the rest.
ROBUST_PERCENTILES = (2.0, 98.0)


def colour_range(field: str, vals: np.ndarray) -> tuple[float, float]:
    """Colour limits of one field's values on one frame.

    Parameters
    ----------
    field : str
        The field's name; ``target`` (p in 0-1) keeps the fixed range 0-1.
    vals : (n,) array
        The values shown.

    Returns
    -------
    (float, float)
        ``(cmin, cmax)``: the lower :data:`ROBUST_PERCENTILES` of the finite values, and the upper one
        of the values above that (a sparse field, coverage after a few steps, is mostly at its floor:
        the covered points keep their shades instead of all saturating); widened to a non-empty
        interval when they are equal (a constant field).
    """
    if field == "target":
        return 0.0, 1.0
    finite = np.asarray(vals, dtype=np.float64)
    finite = finite[np.isfinite(finite)]
    if finite.size == 0:
        return 0.0, 1.0
    lo = float(np.percentile(finite, ROBUST_PERCENTILES[0]))
    above = finite[finite > lo]
    hi = float(np.percentile(above, ROBUST_PERCENTILES[1])) if above.size else lo
    if hi <= lo:
        pad = max(abs(lo) * 1e-6, 1e-12)
        lo, hi = lo - pad, hi + pad
    return lo, hi


def _plot_cloud(plt, cloud, field: str, cmap: str, label: str, traj, path: Path, note: str, line: str) -> Path:
    """Front and side views above the top view, as in a technical drawing, sized by the object's
    extents, in millimetres; a flat view keeps a readable height (its axis limits widen instead)."""
    from matplotlib.ticker import MaxNLocator

    pts = cloud.points
    vals = cloud.fields[field]
    vmin, vmax = colour_range(field, vals)
    span = pts.max(0) - pts.min(0)
    big = float(span.max()) or 1.0
    sx, sy, sz = np.maximum(span, 0.35 * big)  # no strip thinner than about a third of the largest extent
    width = 11.0
    height = float(np.clip(0.85 * width * (sz + sy) / (sx + sy) + 1.3, 5.0, 11.0))
    fig = plt.figure(figsize=(width, height))
    gs = fig.add_gridspec(2, 3, width_ratios=(sx, sy, 0.05 * (sx + sy)), height_ratios=(sz, sy),
                          left=0.08, right=0.9, bottom=0.08, top=0.9, wspace=0.3, hspace=0.3)
    cells = {"front (x-z)": gs[0, 0], "side (y-z)": gs[0, 1], "top (x-y)": gs[1, 0]}
    size = max(0.5, min(12.0, 2.0e4 / max(len(pts), 1)))
    sc = None
    for name, h, v, d, sign in _VIEWS:
        ax = fig.add_subplot(cells[name])
        order = np.argsort(sign * pts[:, d])  # painter's order: far points first, near ones on top
        sc = ax.scatter(1e3 * pts[order, h], 1e3 * pts[order, v], c=vals[order], cmap=cmap, vmin=vmin, vmax=vmax,
                        s=size, linewidths=0)
        if traj is not None and traj.dtype != object and traj.ndim == 3 and len(traj):
            for k in range(traj.shape[1]):
                ax.plot(1e3 * traj[:, k, h], 1e3 * traj[:, k, v], color=line, lw=0.6, alpha=0.6)
                ax.plot(1e3 * traj[-1, k, h], 1e3 * traj[-1, k, v], "o", color=line, ms=4, mec="k", mew=0.5)
        pad = 30.0 * big  # 3% of the largest extent, in mm
        ax.set_xlim(1e3 * pts[:, h].min() - pad, 1e3 * pts[:, h].max() + pad)
        ax.set_ylim(1e3 * pts[:, v].min() - pad, 1e3 * pts[:, v].max() + pad)
        ax.set_aspect("equal", adjustable="datalim")  # true proportions; the limits widen to fill the cell
        ax.xaxis.set_major_locator(MaxNLocator(5))
        ax.yaxis.set_major_locator(MaxNLocator(5))
        ax.set_title(name, fontsize=10)
        ax.set(xlabel="xyz"[h] + " (mm)", ylabel="xyz"[v] + " (mm)")
        ax.grid(True, alpha=0.2)
    cax = fig.add_subplot(gs[:, 2])
    below, above = vmin > np.nanmin(vals), vmax < np.nanmax(vals)  # arrows where colours saturate
    extend = {(True, True): "both", (True, False): "min", (False, True): "max"}.get((below, above), "neither")
    fig.colorbar(sc, cax=cax, label=label, extend=extend)
    fig.text(0.54, 0.3, f"step {cloud.step}\n\nagent trajectory: {line} line\ndot: last position", fontsize=10,
             va="center")
    fig.suptitle(f"{label} at step {cloud.step}{note}")
    return _save(fig, path)
