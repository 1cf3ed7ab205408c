"""Run plots: ε and the authors' residual on their own axes, units on every colourbar, views that can be read."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from tergodic_cli.runlog import plots

BOWL = Path(__file__).resolve().parents[1] / "data" / "bowl"


@pytest.fixture
def figures(monkeypatch):
    """The figures plot_run makes, by file name, drawn and kept open for inspection."""
    kept = {}

    def keep(fig, path):
        fig.canvas.draw()
        kept[Path(path).name] = fig
        return Path(path)

    monkeypatch.setattr(plots, "_save", keep)
    yield kept
    import matplotlib.pyplot as plt

    for fig in kept.values():
        plt.close(fig)


@pytest.fixture(scope="module")
def bowl_log(tmp_path_factory):
    if not (BOWL / "cloud.npz").is_file():
        pytest.skip("data/bowl is missing")
    from tergodic_cli.explore import ExploreConfig
    from tergodic_cli.run import LogSpec, run_explore
    from tergodic_cli.runlog import read_run_log

    tmp = tmp_path_factory.mktemp("plots")
    run_explore(BOWL, ExploreConfig(steps=60, nk=30), tmp / "run", log=LogSpec(cloud_every=30), cache_dir=tmp / "cache")
    return read_run_log(tmp / "run" / "run.mcap")


@pytest.mark.parametrize("key", ["ergodicity_ref", "residual_ref"])
def test_epsilon_and_the_residual_each_have_their_own_axis(figures, key, tmp_path):
    t = np.arange(1.0, 51.0)
    s = {"ergodicity": 0.5 + 1 / t, key: np.linspace(1, 0.2, 50), "touched_fraction": np.linspace(0, 1, 50)}
    plots._plot_ergodicity(plots._pyplot(), t, "t (s)", s, "", tmp_path / "ergodicity.png")
    fig = figures["ergodicity.png"]
    axes = [ax for ax in fig.axes if ax.lines]
    assert len(axes) == 2
    (eps_line,), (ref_line,) = axes[0].lines, axes[1].lines
    np.testing.assert_array_equal(eps_line.get_ydata(), s["ergodicity"])
    np.testing.assert_array_equal(ref_line.get_ydata(), s[key])
    assert "ε" in axes[0].get_ylabel() and key in axes[1].get_ylabel()


def _colourbars(fig):
    return [ax for ax in fig.axes if getattr(ax, "_colorbar", None) is not None]


def _overlap(boxes) -> bool:
    boxes = sorted(boxes, key=lambda b: b.x0)
    return any(a.x1 > b.x0 for a, b in zip(boxes, boxes[1:]))


def test_cloud_views_have_units_and_readable_axes(figures, bowl_log, tmp_path):
    plots.plot_run(bowl_log, tmp_path)
    clouds = {name: fig for name, fig in figures.items() if name.startswith("cloud_")}
    assert set(clouds) == {"cloud_target.png", "cloud_coverage.png", "cloud_heat.png"}
    for name, fig in clouds.items():
        (cbar,) = _colourbars(fig)
        label = cbar.get_ylabel()
        assert re.search(r"\((.*[ ,])?(unitless|1/m²|1/m|m|mm|N|s)\)$", label.strip()), (name, label)  # unit in brackets
        renderer = fig.canvas.get_renderer()
        width_in, height_in = fig.get_size_inches()
        views = [ax for ax in fig.axes if ax.get_title().split(" ")[0] in ("front", "side", "top")]
        assert len(views) == 3
        for ax in views:
            box = ax.get_position()
            assert box.height * height_in >= 1.3 and box.width * width_in >= 1.3, (name, ax.get_title(), box)
            ticks = [t.get_window_extent(renderer) for t in ax.get_xticklabels() if t.get_visible() and t.get_text()]
            assert len(ticks) >= 3 and not _overlap(ticks), (name, ax.get_title(), [t.get_text() for t in ax.get_xticklabels()])
            lo, hi = ax.get_xlim(), ax.get_ylim()  # equal aspect: a mm is as long across as up
            ratio = ((lo[1] - lo[0]) / (box.width * width_in)) / ((hi[1] - hi[0]) / (box.height * height_in))
            assert ratio == pytest.approx(1.0, rel=0.02), (name, ax.get_title(), ratio)
