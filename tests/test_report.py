"""``tergodic replay RUN --html``: the page's embedded data equals the log's, it works offline, bad paths are one line."""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO, assert_one_line_error, run_cli
from test_replay import _make_run

from tergodic_cli.runlog import read_run_log

pytest.importorskip("plotly")


@pytest.fixture(scope="module")
def bowl_run(tmp_path_factory):
    """A short kinematic explore on data/bowl, its log and its HTML report."""
    root = tmp_path_factory.mktemp("report")
    with pytest.MonkeyPatch.context() as mp:  # a module fixture runs before the per-test cache fixture
        mp.setenv("TERGODIC_CACHE_DIR", str(root / "cache"))
        res = run_cli("explore", REPO / "data" / "bowl", "--out", root / "run", "--steps", "60",
                      "--log-cloud-every", "20", "--seed", "2")
        assert res.code == 0, res.err
        page = root / "out" / "report.html"  # a missing folder is created
        res = run_cli("replay", root / "run", "--html", page)
    assert res.code == 0, res.err
    assert f"wrote {page}" in res.out
    return root / "run", page, read_run_log(root / "run")


def _decode(v):
    """plotly's JSON array: a plain list or a base64 typed array {"dtype", "bdata", "shape"}."""
    if isinstance(v, dict) and "bdata" in v:
        a = np.frombuffer(base64.b64decode(v["bdata"]), dtype=np.dtype(v["dtype"]))
        if "shape" in v:
            a = a.reshape([int(n) for n in str(v["shape"]).split(",")])
        return a.astype(np.float64)
    return np.array([np.nan if x is None else x for x in v], dtype=np.float64)


def _plotly_calls(html: str) -> dict[str, dict]:
    """{div id: {"data": [...], "layout": {...}, "frames": [...]}} from the page's Plotly.newPlot/addFrames calls."""
    dec = json.JSONDecoder()

    def args(start: int, n: int) -> list:
        out, i = [], start
        while len(out) < n:
            while html[i] in " \n\t,":
                i += 1
            obj, i = dec.raw_decode(html, i)
            out.append(obj)
        return out

    figs: dict[str, dict] = {}
    for m in re.finditer(r"Plotly\.newPlot\(", html):
        div, data, layout = args(m.end(), 3)
        figs[div] = {"data": data, "layout": layout, "frames": []}
    for m in re.finditer(r"Plotly\.addFrames\('([^']+)',", html):
        figs[m.group(1)]["frames"] = args(m.end(), 1)[0]
    return figs


def test_page_data_equals_the_log(bowl_run):
    _, page, data = bowl_run
    html = page.read_text(encoding="utf-8")
    figs = _plotly_calls(html)
    assert set(figs) == {"tergodic-cloud", "tergodic-series"}
    s = data.series
    pos = s["positions"]
    assert pos.shape[1] == 1 and len(data.clouds) == 3  # steps 20, 40, 60

    # the trajectory drawn in 3-D is the logged positions
    cloud_fig = figs["tergodic-cloud"]
    (traj,) = [t for t in cloud_fig["data"] if t.get("name") == "agent 0 trajectory"]
    for k, axis in enumerate("xyz"):
        np.testing.assert_allclose(_decode(traj[axis]), pos[:, 0, k], rtol=0, atol=1e-12)

    # the cloud shown first is the last logged one: its points and its coverage, as logged (float32)
    last = data.clouds[-1]
    by_name = {t.get("name"): t for t in cloud_fig["data"]}
    cov = by_name["coverage c̃"]
    assert cov["visible"] is True and by_name["heat u"]["visible"] is False
    np.testing.assert_allclose(_decode(cov["marker"]["color"]), last.fields["coverage"], rtol=1e-7, atol=0)
    np.testing.assert_allclose(np.column_stack([_decode(cov[a]) for a in "xyz"]), last.points, rtol=1e-7, atol=0)
    for f in ("target", "heat", "source"):
        (tr,) = [t for t in cloud_fig["data"] if t.get("name", "").startswith(f)]
        np.testing.assert_allclose(_decode(tr["marker"]["color"]), last.fields[f], rtol=1e-7, atol=0)

    # one slider frame per logged cloud, each with that cloud's coverage and the agent at its step
    frames = cloud_fig["frames"]
    assert len(frames) == len(data.clouds)
    steps = [st["label"] for st in cloud_fig["layout"]["sliders"][0]["steps"]]
    assert steps == [str(c.step) for c in data.clouds]
    cov_index = [t.get("name") for t in cloud_fig["data"]].index("coverage c̃")
    for fr, c in zip(frames, data.clouds):
        tr = fr["data"][fr["traces"].index(cov_index)]
        np.testing.assert_allclose(_decode(tr["marker"]["color"]), c.fields["coverage"], rtol=1e-7, atol=0)
        agent = fr["data"][-1]
        np.testing.assert_allclose(_decode(agent["x"]), pos[data.index_of(c.step), :, 0], rtol=0, atol=1e-12)

    # ε, the residual and touched against time
    series = {t["name"]: t for t in figs["tergodic-series"]["data"]}
    for name, key in (("ε (eq. 48)", "ergodicity"), ("residual_ref", "residual_ref"), ("touched", "touched_fraction")):
        np.testing.assert_allclose(_decode(series[name]["y"]), s[key], rtol=0, atol=1e-15)
        np.testing.assert_allclose(_decode(series[name]["x"]), s["t"], rtol=0, atol=1e-15)

    # and the plain JSON block for scripts holds the same numbers
    m = re.search(r'<script type="application/json" id="tergodic-data">(.*?)</script>', html, re.S)
    block = json.loads(m.group(1))
    np.testing.assert_allclose(np.array(block["positions"]), pos, rtol=0, atol=1e-15)
    np.testing.assert_allclose(block["ergodicity"], s["ergodicity"], rtol=0, atol=1e-15)
    np.testing.assert_allclose(block["touched_fraction"], s["touched_fraction"], rtol=0, atol=1e-15)
    assert [c["step"] for c in block["clouds"]] == [c.step for c in data.clouds]
    np.testing.assert_allclose(block["clouds"][-1]["coverage"], last.fields["coverage"], rtol=1e-7, atol=0)
    np.testing.assert_allclose(np.array(block["points"]), last.points, rtol=1e-7, atol=0)


def test_page_works_offline(bowl_run):
    _, page, _ = bowl_run
    html = page.read_text(encoding="utf-8")
    tags = re.findall(r"<script\b[^>]*>", html, re.I)
    assert tags and not [t for t in tags if "src=" in t.lower()], tags  # plotly.js is inline, nothing is fetched
    assert not re.search(r"""<(script|link|img|iframe)\b[^>]*(src|href)\s*=\s*["']?(https?:)?//""", html, re.I)
    assert "Plotly.newPlot" in html and len(html) > 1_000_000  # plotly.js itself is embedded
    assert not list(page.parent.glob(".*.tmp"))  # written atomically: no temporary file left


def test_robot_run_shows_force_and_tilt(tmp_path):
    inp = _make_run(tmp_path / "run", steps=60, robot=True, n_points=300)
    res = run_cli("replay", tmp_path / "run", "--html", tmp_path / "r.html")
    assert res.code == 0, res.err
    figs = _plotly_calls((tmp_path / "r.html").read_text(encoding="utf-8"))
    series = {t["name"]: t for t in figs["tergodic-series"]["data"]}
    f = np.array([s["force_normal"] for s in inp["robot"]])
    fd = np.array([s["wrench_desired"][2] for s in inp["robot"]])
    tilt = np.array([s["tilt_deg"] for s in inp["robot"]])
    np.testing.assert_allclose(_decode(series["measured normal force"]["y"]), f, rtol=0, atol=1e-15)
    np.testing.assert_allclose(_decode(series["desired force"]["y"]), fd, rtol=0, atol=1e-15)
    np.testing.assert_allclose(_decode(series["tilt"]["y"]), tilt, rtol=0, atol=1e-15)
    titles = [a["text"] for a in figs["tergodic-series"]["layout"]["annotations"]]
    assert "Contact force against desired" in titles and "Tool tilt from the surface normal" in titles


def test_big_clouds_are_subsampled_and_say_so(tmp_path, monkeypatch):
    from tergodic_cli.runlog import report

    _make_run(tmp_path / "run", steps=60, n_points=500)
    monkeypatch.setattr(report, "MAX_POINTS", 200)
    data = read_run_log(tmp_path / "run")
    report.write_html_report(data, tmp_path / "r.html")
    html = (tmp_path / "r.html").read_text(encoding="utf-8")
    assert "the page shows 200 of them" in html
    cov = [t for t in _plotly_calls(html)["tergodic-cloud"]["data"] if t.get("name") == "coverage c̃"][0]
    idx = np.linspace(0, 499, 200).round().astype(int)
    np.testing.assert_allclose(_decode(cov["marker"]["color"]), data.clouds[-1].fields["coverage"][idx], rtol=1e-7)


@pytest.mark.parametrize("where, needle", [("folder", "is a folder"), ("under_file", "is a file")])
def test_unwritable_html_path_is_one_line(bowl_run, tmp_path, where, needle):
    run, _, _ = bowl_run
    (tmp_path / "afile").write_text("x")
    target = tmp_path if where == "folder" else tmp_path / "afile" / "r.html"
    res = run_cli("replay", run, "--html", target)
    assert_one_line_error(res, needle, "--html")


def test_read_only_folder_is_one_line(bowl_run, tmp_path):
    import os

    run, _, _ = bowl_run
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        if os.access(ro, os.W_OK):
            pytest.skip("running as a user who may write anywhere (root)")
        assert_one_line_error(run_cli("replay", run, "--html", ro / "r.html"), "permission denied", "--html")
        assert not list(ro.iterdir())
    finally:
        ro.chmod(0o700)


def test_write_error_is_one_line(bowl_run, tmp_path, monkeypatch):
    """An OS error while writing (disk full) is one line and leaves nothing behind."""
    import errno

    run, _, _ = bowl_run

    def full(self, *a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_text", full)
    res = run_cli("replay", run, "--html", tmp_path / "r.html")
    assert_one_line_error(res, "no space left on device", "--html")
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------------ a page that follows the run (issue 26)
def _robust(vals: np.ndarray) -> tuple[float, float]:
    """The page's colour limits, written out: the 2nd percentile, and the 98th of the values above it."""
    lo = np.percentile(vals, 2)
    above = vals[vals > lo]
    return lo, (np.percentile(above, 98) if above.size else lo)


def _cursor_x(layout: dict) -> dict[str, float]:
    """{x axis ref: cursor x} of a layout's cursor shapes (x0 == x1: a vertical line)."""
    out = {}
    for sh in layout.get("shapes", []):
        if sh.get("name") == "cursor":
            assert sh["x0"] == sh["x1"] and sh["type"] == "line"
            assert sh["yref"].endswith(" domain") and (sh["y0"], sh["y1"]) == (0, 1)
            out[sh["xref"]] = sh["x0"]
    return out


def _x_axes(layout: dict) -> list[str]:
    """The series figure's x axes as shape refs: "x", "x2", ..."""
    return sorted(("x" + k[len("xaxis"):]) for k in layout if re.fullmatch(r"xaxis\d*", k))


def test_colour_limits_are_each_frames_percentiles(bowl_run):
    """Every field but the target is coloured between the 2nd percentile of the frame's own values and the 98th
    of those above it
    (heat's offset no longer washes it out); the target stays 0-1; each field has its colour bar."""
    _, page, data = bowl_run
    cloud_fig = _plotly_calls(page.read_text(encoding="utf-8"))["tergodic-cloud"]
    names = [t.get("name") for t in cloud_fig["data"]]
    field_of = {"target p": "target", "coverage c̃": "coverage", "heat u": "heat", "source s": "source"}
    for label, f in field_of.items():
        tr = cloud_fig["data"][names.index(label)]
        assert tr["marker"]["colorbar"]["title"]["text"].startswith(f)  # a legend per field
        vals = data.clouds[-1].fields[f].astype(np.float32).astype(np.float64)
        lo, hi = (0.0, 1.0) if f == "target" else _robust(vals)
        assert (tr["marker"]["cmin"], tr["marker"]["cmax"]) == pytest.approx((lo, hi), rel=1e-9, abs=1e-12)
    heat = data.clouds[-1].fields["heat"]
    assert np.ptp(heat) > 0  # the test means something: the heat varies over the cloud
    for fr, c in zip(cloud_fig["frames"], data.clouds):
        for f in ("coverage", "heat", "source"):
            d = fr["data"][fr["traces"].index(names.index(next(k for k, v in field_of.items() if v == f)))]
            vals = c.fields[f].astype(np.float32).astype(np.float64)
            lo, hi = _robust(vals)
            if hi > lo:
                assert (d["marker"]["cmin"], d["marker"]["cmax"]) == pytest.approx((lo, hi), rel=1e-9, abs=1e-12)
            else:  # a constant field (coverage before the agent moved): a small interval around it
                assert d["marker"]["cmin"] < lo <= hi < d["marker"]["cmax"]
        assert names.index("target p") not in fr["traces"]  # unchanged target: its 0-1 scale stays


def test_colour_range_of_an_offset_field():
    """Heat spanning 1.8e4-2.4e4 gets limits inside that span, not from 0; a constant field a non-empty one."""
    from tergodic_cli.runlog.plots import colour_range

    rng = np.random.default_rng(3)
    heat = 1.8e4 + 6e3 * rng.random(1000)
    lo, hi = colour_range("heat", heat)
    assert 1.8e4 < lo < 1.82e4 and 2.38e4 < hi < 2.4e4
    assert np.mean((heat >= lo) & (heat <= hi)) == pytest.approx(0.96, abs=0.003)
    # sparse coverage (3 % of the points covered): the covered points keep their shades, not all saturated
    cov = np.zeros(1000)
    cov[:30] = np.linspace(1, 30, 30)
    lo, hi = colour_range("coverage", cov)
    assert lo == 0 and 29 < hi < 30
    assert colour_range("target", heat) == (0.0, 1.0)
    lo, hi = colour_range("coverage", np.zeros(50))
    assert lo < 0 < hi
    assert colour_range("heat", np.full(4, np.nan)) == (0.0, 1.0)


def test_trajectory_and_cursors_follow_the_slider(bowl_run):
    """Frame k draws the trajectory up to its cloud's step, and moves a cursor on every time plot to that
    step's time; the time plots' frames have the cloud frames' names (the page's script plays them together)."""
    _, page, data = bowl_run
    html = page.read_text(encoding="utf-8")
    figs = _plotly_calls(html)
    cloud_fig, series_fig = figs["tergodic-cloud"], figs["tergodic-series"]
    pos, t = data.series["positions"], data.series["t"]
    names = [tr.get("name") for tr in cloud_fig["data"]]
    traj = names.index("agent 0 trajectory")
    assert len(cloud_fig["frames"]) == 3
    axes = _x_axes(series_fig["layout"])
    assert len(axes) >= 3  # ε, residual, touched
    seen = []
    sframes = {fr["name"]: fr for fr in series_fig["frames"]}
    assert list(sframes) == [fr["name"] for fr in cloud_fig["frames"]]
    for fr, c in zip(cloud_fig["frames"], data.clouds):
        row = data.index_of(c.step)
        d = fr["data"][fr["traces"].index(traj)]
        xyz = np.column_stack([_decode(d[a]) for a in "xyz"])
        assert len(xyz) == row + 1 == c.step  # one row per step, from step 1
        np.testing.assert_allclose(xyz, pos[:row + 1, 0], rtol=0, atol=1e-12)
        cur = _cursor_x(sframes[fr["name"]]["layout"])
        assert sorted(cur) == axes  # a cursor on every time plot
        np.testing.assert_allclose(list(cur.values()), t[row], rtol=0, atol=1e-12)
        seen.append(cur["x"])
    assert seen == sorted(seen) and len(set(seen)) == 3  # the cursor moves with the slider
    assert _cursor_x(series_fig["layout"])["x"] == pytest.approx(seen[-1])  # the page opens at the last frame
    assert 'cloud.on("plotly_animatingframe"' in html


def test_the_pages_script_plays_the_time_plots_with_the_slider(bowl_run, tmp_path):
    """The bridge script, run in node with the two plot divs stubbed: a cloud frame animates the same-named
    time-plot frame."""
    import shutil
    import subprocess

    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed")
    _, page, _ = bowl_run
    html = page.read_text(encoding="utf-8")
    scripts = re.findall(r'<script type="text/javascript">(.*?)</script>', html, re.S)
    (bridge,) = [s for s in scripts if "plotly_animatingframe" in s and len(s) < 5000]
    harness = """
    const calls = [], handlers = {};
    const cloud = {id: "tergodic-cloud", on: (ev, f) => { handlers[ev] = f; }};
    const series = {id: "tergodic-series"};
    let onload = null;
    global.window = {addEventListener: (ev, f) => { if (ev === "load") onload = f; }};
    global.document = {getElementById: (id) => ({"tergodic-cloud": cloud, "tergodic-series": series})[id]};
    global.Plotly = {animate: (gd, names, opts) => { calls.push([gd.id, names, opts.mode]); }};
    """ + bridge + """
    onload();
    handlers["plotly_animatingframe"]({name: "1", frame: {}});
    handlers["plotly_animatingframe"]({name: "2", frame: {}});
    console.log(JSON.stringify(calls));
    """
    (tmp_path / "h.js").write_text(harness)
    out = subprocess.run([node, str(tmp_path / "h.js")], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout) == [["tergodic-series", ["1"], "immediate"], ["tergodic-series", ["2"], "immediate"]]


@pytest.fixture(scope="module")
def loop_run(tmp_path_factory):
    """A closed-loop-shaped log of 60 steps in 3 cycles of 20, written as the CLI writes one: the robot's
    clock jumps 4 s over each re-capture pause, each cycle's last sample carries the marking left, and the
    re-capture cloud (log_recapture) and the periodic cloud share a step. Heat sits at 1.8e4-2.4e4."""
    from types import SimpleNamespace

    from test_runlog import demo_inputs

    from tergodic_cli.backends.pybullet.closed_loop import log_recapture
    from tergodic_cli.runlog import RunLog

    root = tmp_path_factory.mktemp("loop")
    inp = demo_inputs(steps=60, robot=True, n_points=300, n_agents=1)
    rng = np.random.default_rng(5)
    dt, pause, K = 0.2, 4.0, 20
    shares = {20: (0.6, 0.7), 40: (0.2, 0.3), 60: (0.04, 0.07)}
    for k, smp in enumerate(inp["robot"]):
        step = k + 1
        smp["t_sim"] = 0.5 + step * dt + pause * (k // K)  # the physics clock, with a pause per re-capture
        if step in shares:
            smp["marking_remaining"], smp["marking_remaining_true"] = shares[step]
            smp["recapture_ms"] = 150.0
    n = len(inp["points"])
    with RunLog(root / "run" / "run.mcap", config=inp["config"], seed=1, versions=inp["versions"],
                capture_sidecar=inp["sidecar"], points=inp["points"], target=inp["target"], cloud_every=K) as log:
        for k in range(60):
            step = k + 1
            log.log_step(step, step * dt, positions=inp["P"][k], velocities=inp["V"][k], normals=inp["N"][k],
                         metrics={m: v[k] for m, v in inp["metrics"].items()}, step_ms=1.0, robot=inp["robot"][k])
            if step % K == 0:
                ex = SimpleNamespace(coverage=rng.random(n) * step, heat=1.8e4 + 6e3 * rng.random(n),
                                     source=rng.standard_normal(n))
                rec = {"target": (rng.random(n) > 0.5).astype(float), "marking_remaining": shares[step][0],
                       "marking_remaining_true": shares[step][1], "ms": 150.0, "basis_cache_hit": True,
                       "applied": step < 60}
                log_recapture(log, ex, step, step * dt, rec)
                log.log_cloud(step, coverage=ex.coverage, heat=ex.heat, source=ex.source)
    res = run_cli("replay", root / "run", "--html", root / "r.html")
    assert res.code == 0, res.err
    return inp, (root / "r.html").read_text(encoding="utf-8"), read_run_log(root / "run")


def test_closed_loop_page_has_one_time_axis_breaks_marks_and_the_ink_left(loop_run):
    inp, html, data = loop_run
    figs = _plotly_calls(html)
    cloud_fig, series_fig = figs["tergodic-cloud"], figs["tergodic-series"]
    lay = series_fig["layout"]
    t_sim = np.array([s["t_sim"] for s in inp["robot"]])
    # one time axis: every plot's x axis follows the first, whose data is the robot's simulated time
    axes = _x_axes(lay)
    assert len(axes) >= 6  # ε, residual, touched, force, tilt, marking left
    assert all(lay["xaxis" + a[1:]].get("matches") == "x" for a in axes if a != "x")
    series = {tr["name"]: tr for tr in series_fig["data"]}
    gap_rows = [19, 39]  # the last step of each cycle that the run went on after
    for name in ("ε (eq. 48)", "touched", "measured normal force", "tilt"):
        x, y = _decode(series[name]["x"]), _decode(series[name]["y"])
        # a break (no line) after each cycle's last step: the pause is not drawn as a ramp
        assert len(x) == 60 + len(gap_rows)
        breaks = np.flatnonzero(np.isnan(y))
        np.testing.assert_array_equal(breaks, [g + 1 + i for i, g in enumerate(gap_rows)])
        np.testing.assert_allclose(x[np.isfinite(x)], t_sim, rtol=0, atol=1e-12)
    np.testing.assert_allclose(_decode(series["tilt"]["y"])[:20], [s["tilt_deg"] for s in inp["robot"][:20]])
    # the ink left: capture 0 (100 % at t 0), then each re-capture, camera-seen and true
    seen, true = series["marking seen by the camera"], series["ink left in the texture"]
    np.testing.assert_allclose(_decode(seen["x"]), [0, t_sim[19], t_sim[39], t_sim[59]])
    np.testing.assert_allclose(_decode(seen["y"]), [1, 0.6, 0.2, 0.04])
    np.testing.assert_allclose(_decode(true["y"]), [1, 0.7, 0.3, 0.07])
    # re-capture marks: a band over each pause and a line at its start
    bands = [(sh["x0"], sh["x1"]) for sh in lay["shapes"] if sh.get("name") == "recapture" and sh["type"] == "rect"]
    lines = [sh["x0"] for sh in lay["shapes"] if sh.get("name") == "recapture" and sh["type"] == "line"]
    np.testing.assert_allclose(bands, [(t_sim[19], t_sim[20]), (t_sim[39], t_sim[40]), (t_sim[59], t_sim[59])])
    np.testing.assert_allclose(lines, t_sim[[19, 39, 59]])
    # the slider: one frame per step (the re-capture's cloud and the periodic one share it), unique labels
    labels = [st["label"] for st in cloud_fig["layout"]["sliders"][0]["steps"]]
    assert len(data.clouds) == 6 and labels == ["20", "40", "60"]
    # the cursors sit at the physics time of each frame's step, on every plot
    for fr, row in zip(series_fig["frames"], (19, 39, 59)):
        cur = _cursor_x(fr["layout"])
        assert sorted(cur) == axes
        np.testing.assert_allclose(list(cur.values()), t_sim[row], rtol=0, atol=1e-12)
    # the offset heat is coloured between its own percentiles, per frame
    names = [tr.get("name") for tr in cloud_fig["data"]]
    last_at = {c.step: c for c in data.clouds}
    for fr, step in zip(cloud_fig["frames"], (20, 40, 60)):
        d = fr["data"][fr["traces"].index(names.index("heat u"))]
        vals = last_at[step].fields["heat"].astype(np.float32).astype(np.float64)
        lo, hi = _robust(vals)
        assert d["marker"]["cmin"] == pytest.approx(lo, rel=1e-9) and d["marker"]["cmax"] == pytest.approx(hi, rel=1e-9)
        assert 1.8e4 < lo < hi < 2.4e4


def test_a_long_trajectory_is_drawn_through_a_subset_and_says_so(tmp_path, monkeypatch):
    from tergodic_cli.runlog import report

    inp = _make_run(tmp_path / "run", steps=120, n_points=200)
    monkeypatch.setattr(report, "MAX_TRAJ_ROWS", 25)
    data = read_run_log(tmp_path / "run")
    report.write_html_report(data, tmp_path / "r.html")
    html = (tmp_path / "r.html").read_text(encoding="utf-8")
    assert "The trajectory has 120 steps; the page draws every 5th of them." in html
    cloud_fig = _plotly_calls(html)["tergodic-cloud"]
    traj = [t.get("name") for t in cloud_fig["data"]].index("agent 0 trajectory")
    for fr, c in zip(cloud_fig["frames"], data.clouds):  # steps 50, 100, 120
        d = fr["data"][fr["traces"].index(traj)]
        rows = sorted(set(range(0, c.step, 5)) | {c.step - 1})  # every 5th row, and the cloud's step
        np.testing.assert_allclose(_decode(d["x"]), inp["P"][rows, 0, 0], rtol=0, atol=1e-12)


def test_closed_loop_pngs_share_the_clock_and_break_at_re_captures(loop_run, monkeypatch, tmp_path):
    """ε, touched and force PNGs: x is the robot's simulated time, and each line breaks after a cycle's last step."""
    from tergodic_cli.runlog import plots

    inp, _, data = loop_run
    kept = {}
    monkeypatch.setattr(plots, "_save", lambda fig, path: kept.setdefault(Path(path).name, fig) and Path(path))
    plots.plot_run(data, tmp_path)
    t_sim = np.array([s["t_sim"] for s in inp["robot"]])
    try:
        for name in ("ergodicity.png", "touched.png", "force.png"):
            line = [ln for ax in kept[name].axes for ln in ax.lines][0]
            x, y = np.asarray(line.get_xdata(), float), np.asarray(line.get_ydata(), float)
            np.testing.assert_array_equal(np.flatnonzero(np.isnan(y)), [20, 41])
            np.testing.assert_allclose(x[np.isfinite(x)], t_sim, rtol=0, atol=1e-12)
    finally:
        import matplotlib.pyplot as plt

        for fig in kept.values():
            plt.close(fig)
