"""Sweep figures in the style of the paper's Figs. 6-7 and 9-11 (the files: docs/speed.md).

Columns are objects; the top row is ``ergodicity`` (the neutral unit-mass ε), the bottom row
``residual_ref`` (the published code's residual). When the grid varies other options too, each
combination of them gets its own set of files (suffix ``__key=value``).
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np

from tergodic_cli.sweep.grid import Grid, alpha_key

METRICS = (("ergodicity", "ε (unit-mass eq. 48, dimensionless)"),
           ("residual_ref", "residual of the published code (unitless)"))


def plot_sweep(out: Path, grid: Grid, rows: list[dict], series: dict) -> list[str]:
    """Write the figures into ``out`` (the sweep's staging folder, renamed into place whole);
    returns their paths relative to ``out``."""
    from tergodic_cli.runlog.plots import _pyplot, _save

    plt = _pyplot()
    objects = [o.name for o in grid.objects]
    varied = grid.varied
    variants = list(itertools.product(*(grid.options[k] for k in varied))) if varied else [()]
    index = {rid: i for i, rid in enumerate(series["run_id"].tolist())}
    files = []
    for variant in variants:
        sel = [r for r in rows if all(str(r.get(k)) == str(v) for k, v in zip(varied, variant))]
        if not sel:
            continue
        suffix = "".join(f"__{k}={v}" for k, v in zip(varied, variant))
        nks = sorted({int(r["nk"]) for r in sel})
        alphas = sorted({str(r["alpha"]) for r in sel}, key=alpha_key)
        numeric = [a for a in alphas if alpha_key(a)[0] == 0]
        best_alpha = (min(numeric, key=lambda a: abs(math.log(float(a) / 10.0))) if numeric
                      else alphas[0])
        figs = {
            f"eps_vs_nk{suffix}.png": _final_plot(plt, sel, objects, "nk", nks, "alpha", alphas, "nK", log2=True),
            f"eps_vs_alpha{suffix}.png": (_final_plot(plt, sel, objects, "alpha", numeric, "nk", nks, "α", log10=True)
                                          if len(numeric) > 1 else None),
            f"eps_t{suffix}.png": _time_plot(plt, sel, objects, series, index, "nk", nks, {"alpha": best_alpha},
                                             f"α = {best_alpha}", "nK"),
            f"eps_t_alpha{suffix}.png": _time_plot(plt, sel, objects, series, index, "alpha", alphas,
                                                   {"nk": max(nks)}, f"nK = {max(nks)}", "α"),
        }
        files += [_save(fig, out / name).name for name, fig in figs.items() if fig is not None]
    return files


def _panels(plt, objects, draw, title, **title_kw):
    """Objects across, ε and the residual down (each on its own axes); ``draw(ax, obj, metric)``
    fills a panel."""
    fig, axes = plt.subplots(2, len(objects), figsize=(4.2 * len(objects), 6.4), squeeze=False)
    for col, obj in enumerate(objects):
        for row, (metric, label) in enumerate(METRICS):
            ax = axes[row, col]
            draw(ax, obj, metric)
            ax.grid(alpha=0.3)
            if row == 0:
                ax.set_title(title(obj), **title_kw)
            if col == 0:
                ax.set_ylabel(label)
    axes[0, -1].legend(fontsize=7, loc="best")
    fig.tight_layout()
    return fig


def _final_plot(plt, rows, objects, xkey, xs, lkey, lines, xlabel, log2=False, log10=False):
    def draw(ax, obj, metric):
        for line in lines:
            xv, mean, std = [], [], []
            for x in xs:
                vals = [r[metric] for r in rows if r["object"] == obj and str(r[xkey]) == str(x)
                        and str(r[lkey]) == str(line) and r[metric] is not None]
                if vals:
                    xv.append(float(x))
                    mean.append(np.mean(vals))
                    std.append(np.std(vals))
            if xv:
                mean, std = np.array(mean), np.array(std)
                name = "α" if lkey == "alpha" else "nK"
                ax.plot(xv, mean, marker="o", ms=3, label=f"{name} = {line}")
                ax.fill_between(xv, mean - std, mean + std, alpha=0.15)
        if log2:
            ax.set_xscale("log", base=2)
            ax.set_xticks([float(x) for x in xs], [str(x) for x in xs])
        if log10:
            ax.set_xscale("log")
        ax.set_xlabel(xlabel)

    return _panels(plt, objects, draw, str)


def _time_plot(plt, rows, objects, series, index, lkey, lines, fixed: dict, fixed_label: str, llabel: str):
    if not index:
        return None

    def draw(ax, obj, metric):
        for line in lines:
            ids = [r["run_id"] for r in rows if r["object"] == obj and str(r[lkey]) == str(line)
                   and all(str(r[k]) == str(v) for k, v in fixed.items())]
            if not ids:
                continue
            Y = np.stack([series[metric][index[i]] for i in ids]).astype(np.float64)
            t = np.arange(1, Y.shape[1] + 1)
            mean, std = np.nanmean(Y, axis=0), np.nanstd(Y, axis=0)
            ax.plot(t, mean, lw=1.2, label=f"{llabel} = {line}")
            ax.fill_between(t, mean - std, mean + std, alpha=0.2)
        ax.set_xlabel("step")

    return _panels(plt, objects, draw, lambda obj: f"{obj} ({fixed_label}, mean ± std over starts)",
                   fontsize=9)
