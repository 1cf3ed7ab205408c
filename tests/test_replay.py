"""``tergodic replay``: the summary recomputed from the log equals summary.json; plots, export, --step, bad input."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli
from test_runlog import demo_inputs, write_demo_log

from tergodic_cli.atomic import write_json
from tergodic_cli.explore import summarize_run
from tergodic_cli.runlog import RunLog, read_run_log
from tergodic_cli.runlog import schema as S


def _summary_for(inp: dict, extra: dict | None = None) -> dict:
    """summary.json as the explore command builds it: summarize_run over the in-memory series."""
    series = {**inp["metrics"], "step_ms": inp["step_ms"]}
    return summarize_run(series, inp["config"], extra)


def _make_run(run_dir: Path, steps: int = 520, robot: bool = False, n_points: int = 600) -> dict:
    inp = demo_inputs(steps=steps, robot=robot, n_points=n_points, n_agents=1)
    summary = _summary_for(inp, {"versions": inp["versions"], "capture": "cap/", "basis_key": "abc123"})
    write_demo_log(run_dir / "run.mcap", inp, summary=summary)
    write_json(run_dir / "summary.json", summary)
    return inp


@pytest.fixture(scope="module")
def kin_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("kin")
    return run, _make_run(run)


@pytest.fixture(scope="module")
def robot_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("robot")
    return run, _make_run(run, steps=120, robot=True)


def test_replay_json_equals_summary_json(kin_run):
    run, inp = kin_run
    res = run_cli("replay", run, "--json")
    assert res.code == 0, res.err
    out = json.loads(res.out)
    stored = json.loads((run / "summary.json").read_text())
    assert out.pop("truncated") is False and out.pop("status") == "complete"
    assert out == stored
    # and the numbers are the series' own, not copies of the stored file
    assert out["ergodicity"] == inp["metrics"]["ergodicity"][-1]
    assert out["ergodicity_at"]["500"] == inp["metrics"]["ergodicity"][499]
    assert out["step_ms_median"] == float(np.median(inp["step_ms"]))


def test_replay_recomputes_from_the_series_not_from_the_stored_copy(tmp_path):
    """A log whose stored summary was tampered with still replays the true numbers, and says it differs."""
    inp = demo_inputs(steps=60, n_agents=1)
    true = _summary_for(inp)
    write_demo_log(tmp_path / "run.mcap", inp, summary={**true, "ergodicity": 123.0})
    write_json(tmp_path / "summary.json", {**true, "ergodicity": 123.0})
    res = run_cli("replay", tmp_path, "--json")
    assert json.loads(res.out)["ergodicity"] == inp["metrics"]["ergodicity"][-1]
    table = run_cli("replay", tmp_path)
    assert "differs in ergodicity" in table.out


def test_replay_table(kin_run):
    run, inp = kin_run
    res = run_cli("replay", run / "run.mcap")
    assert res.code == 0, res.err
    out = res.out
    e = inp["metrics"]["ergodicity"]
    assert "steps" in out and " 520" in out
    assert f"{e[199]:.6g}" in out and f"{e[499]:.6g}" in out and f"{e[-1]:.6g}" in out
    assert f"{100 * inp['metrics']['touched_fraction'][-1]:.2f} %" in out
    (row,) = [ln for ln in out.splitlines() if ln.strip().startswith("summary.json")]
    assert row.split()[-1] == "identical"
    assert "complete" in out.splitlines()[0]


def test_replay_robot_run_shows_force_and_plots_it(robot_run, tmp_path):
    run, inp = robot_run
    res = run_cli("replay", run)
    assert res.code == 0, res.err
    f = np.array([s["force_normal"] for s in inp["robot"]])
    contact = np.array([s["in_contact"] for s in inp["robot"]])
    assert f"mean {f[contact].mean():.3g} N" in res.out
    res = run_cli("replay", run, "--plot", tmp_path / "plots")
    assert res.code == 0, res.err
    assert _png_is_drawn(tmp_path / "plots" / "force.png")


def _png_is_drawn(path: Path, min_bytes: int = 8000) -> bool:
    import matplotlib.image as mpimg

    assert path.exists() and path.stat().st_size >= min_bytes, path
    img = mpimg.imread(path)[..., :3]
    non_white = (img < 0.95).any(axis=2).mean()
    return img.std() > 0.05 and non_white > 0.02


def test_plot_writes_non_blank_pngs(kin_run, tmp_path):
    run, _ = kin_run
    res = run_cli("replay", run, "--plot", tmp_path / "plots")
    assert res.code == 0, res.err
    names = sorted(p.name for p in (tmp_path / "plots").glob("*.png"))
    assert names == ["cloud_coverage.png", "cloud_heat.png", "cloud_target.png", "ergodicity.png", "touched.png"]
    for name in names:
        assert _png_is_drawn(tmp_path / "plots" / name), name
        assert f"wrote {tmp_path / 'plots' / name}" in res.out
    # the coverage figure is coloured by the data (viridis has green/yellow), not a flat single colour
    import matplotlib.image as mpimg

    img = mpimg.imread(tmp_path / "plots" / "cloud_coverage.png")[..., :3]
    colours = np.unique((img.reshape(-1, 3) * 16).astype(int), axis=0)
    assert len(colours) > 50


def test_export_npz_and_csv_round_trip(kin_run, tmp_path):
    run, inp = kin_run
    res = run_cli("replay", run, "--export", "npz", "--export-out", tmp_path / "s.npz")
    assert res.code == 0, res.err and f"wrote {tmp_path / 's.npz'}" in res.out
    with np.load(tmp_path / "s.npz", allow_pickle=False) as z:
        assert np.array_equal(z["ergodicity"], inp["metrics"]["ergodicity"])
        assert np.array_equal(z["positions"], inp["P"])
        assert np.array_equal(z["step"], np.arange(1, 521))
    res = run_cli("replay", run, "--export", "csv", "--export-out", tmp_path / "s.csv")
    assert res.code == 0, res.err
    with open(tmp_path / "s.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 520
    assert [float(r["touched_fraction"]) for r in rows] == inp["metrics"]["touched_fraction"].tolist()
    assert float(rows[7]["positions_0_y"]) == inp["P"][7, 0, 1]


def test_export_defaults_beside_the_log(tmp_path):
    inp = demo_inputs(steps=20, n_agents=1)
    write_demo_log(tmp_path / "run.mcap", inp)
    res = run_cli("replay", tmp_path, "--export", "npz")
    assert res.code == 0, res.err
    assert (tmp_path / "series.npz").exists() and f"wrote {tmp_path / 'series.npz'}" in res.out


def test_step_prints_the_state_at_that_step(kin_run):
    run, inp = kin_run
    res = run_cli("replay", run, "--step", "137", "--json")
    assert res.code == 0, res.err
    st = json.loads(res.out)
    assert st["step"] == 137 and st["t"] == 137.0
    assert st["ergodicity"] == inp["metrics"]["ergodicity"][136]
    assert st["positions"] == inp["P"][136].tolist()
    assert st["cloud"]["step"] == 100
    assert st["cloud"]["coverage_max"] == pytest.approx(inp["clouds"][100]["coverage"].max(), rel=1e-6)
    text = run_cli("replay", run, "--step", "137")
    assert text.code == 0 and text.out.startswith("step 137")
    assert_one_line_error(run_cli("replay", run, "--step", "9999"), "step 9999", "1..520")


# --- bad input -------------------------------------------------------------------------------
def test_not_an_mcap_file(tmp_path):
    f = tmp_path / "run.mcap"
    f.write_text("hello, I am a text file\n")
    assert_one_line_error(run_cli("replay", f), "not an MCAP file")


def test_truncated_header(tmp_path):
    inp = demo_inputs(steps=5)
    write_demo_log(tmp_path / "full.mcap", inp)
    data = (tmp_path / "full.mcap").read_bytes()
    for size in (4, 12, 25):
        f = tmp_path / f"cut{size}.mcap"
        f.write_bytes(data[:size])
        assert_one_line_error(run_cli("replay", f), "truncated header")


def test_unknown_schema_version(tmp_path, monkeypatch):
    inp = demo_inputs(steps=5)
    monkeypatch.setattr(S, "LOG_SCHEMA_VERSION", "99")
    write_demo_log(tmp_path / "run.mcap", inp)
    monkeypatch.undo()
    assert_one_line_error(run_cli("replay", tmp_path), "schema version '99'")


def test_empty_log(tmp_path):
    inp = demo_inputs(steps=5)
    RunLog(tmp_path / "run.mcap", config={}, seed=0, points=inp["points"]).close()
    assert_one_line_error(run_cli("replay", tmp_path), "empty log")
    (tmp_path / "zero.mcap").write_bytes(b"")
    assert_one_line_error(run_cli("replay", tmp_path / "zero.mcap"), "empty")


def test_other_bad_paths(tmp_path):
    assert_one_line_error(run_cli("replay", tmp_path / "nope"), "does not exist")
    assert_one_line_error(run_cli("replay", tmp_path), "no run.mcap")
    from mcap.writer import Writer  # a valid MCAP file that is not a tergodic log

    with open(tmp_path / "other.mcap", "wb") as fh:
        w = Writer(fh)
        w.start()
        w.finish()
    assert_one_line_error(run_cli("replay", tmp_path / "other.mcap"), "not a tergodic run log")
    inp = demo_inputs(steps=5)
    write_demo_log(tmp_path / "run.mcap", inp)
    assert_one_line_error(run_cli("replay", tmp_path, "--export", "xlsx"), "not a format", "--export csv")
    assert_one_line_error(run_cli("replay", tmp_path, "--rerun", tmp_path / "x.txt"), ".rrd")


def test_gui_without_display_says_so_in_one_line(tmp_path, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    inp = demo_inputs(steps=5, robot=True)
    write_demo_log(tmp_path / "run.mcap", inp)
    assert_one_line_error(run_cli("replay", tmp_path, "--gui"), "no display")


def test_gui_on_a_kinematic_run_needs_joint_states(tmp_path):
    from tergodic_cli.errors import TergodicError
    from tergodic_cli.runlog.viewers import joint_series

    inp = demo_inputs(steps=5)
    write_demo_log(tmp_path / "run.mcap", inp)
    with pytest.raises(TergodicError, match="no joint states"):
        joint_series(read_run_log(tmp_path))


def test_logged_joint_states_drive_the_arm(tmp_path):
    """The --gui path, in DIRECT mode: every logged configuration is what the arm ends up in."""
    import pybullet as p

    from tergodic_cli.runlog.viewers import joint_indices, joint_series, load_arm, set_joints

    inp = demo_inputs(steps=8, robot=True)
    for s in inp["robot"]:
        s["q"] = np.clip(s["q"], -1.5, 1.5)
    write_demo_log(tmp_path / "run.mcap", inp)
    q, names = joint_series(read_run_log(tmp_path))
    client = p.connect(p.DIRECT)
    try:
        body, movable = load_arm(client)
        idx = joint_indices(client, body, movable, names, q.shape[1])
        assert len(idx) == 7
        for row in q:
            set_joints(client, body, idx, row)
            got = [p.getJointState(body, j, physicsClientId=client)[0] for j in idx]
            np.testing.assert_allclose(got, row, atol=1e-12)
    finally:
        p.disconnect(client)


def test_rerun_export_or_install_hint(tmp_path):
    from tergodic_cli.runlog.viewers import rerun_available

    inp = demo_inputs(steps=60, n_agents=1)
    write_demo_log(tmp_path / "run.mcap", inp)
    res = run_cli("replay", tmp_path, "--rerun", tmp_path / "out.rrd")
    if not rerun_available():
        assert_one_line_error(res, "rerun-sdk is not installed", "pip install")
        return
    assert res.code == 0, res.err
    rrd = tmp_path / "out.rrd"
    assert rrd.read_bytes()[:3] == b"RRF" and rrd.stat().st_size > 1000
    import shutil
    import subprocess
    import sys

    cli = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    if Path(cli).exists():  # rerun's own reader: the file loads, and holds the metrics and the cloud
        assert subprocess.run([cli, "rrd", "verify", str(rrd)], capture_output=True, timeout=600).returncode == 0
        printed = subprocess.run([cli, "rrd", "print", str(rrd)], capture_output=True, text=True, timeout=600).stdout
        for entity in ("/metrics/ergodicity", "/object/cloud", "/object/agents"):
            assert entity in printed, entity


# --- end to end with the explore verb ------------------------------------------------------------
@pytest.fixture(scope="module")
def bowl_capture(tmp_path_factory):
    cap = tmp_path_factory.mktemp("e2e") / "cap"
    res = run_cli("capture", "--synthetic", "bowl", "--marking", "X", "--seed", "0", "--voxel", "0.005", "--out", cap)
    assert res.code == 0, res.err
    return cap


def test_explore_then_replay_equals_summary_json(bowl_capture, tmp_path):
    from mcap.reader import make_reader

    run = tmp_path / "run"
    res = run_cli("explore", bowl_capture, "--steps", "230", "--nk", "60", "--seed", "3", "--out", run,
                  "--log-cloud-every", "100")
    assert res.code == 0, res.err
    with open(run / "run.mcap", "rb") as fh:
        summary = make_reader(fh).get_summary()
    schemas = {summary.schemas[c.schema_id].name: summary.schemas[c.schema_id].encoding for c in summary.channels.values()}
    assert schemas["foxglove.PointCloud"] == "protobuf"
    replay = run_cli("replay", run, "--json")
    assert replay.code == 0, replay.err
    out = json.loads(replay.out)
    stored = json.loads((run / "summary.json").read_text())
    assert out.pop("truncated") is False and out.pop("status") == "complete"
    assert out == stored
    assert out["ergodicity_at"]["200"] is not None
    table = run_cli("replay", run)
    assert "identical" in table.out and f"{stored['ergodicity']:.6g}" in table.out
    d = read_run_log(run)
    assert [c.step for c in d.clouds] == [100, 200, 230]
    # the logged trajectory is the one in trajectory.npz
    with np.load(run / "trajectory.npz", allow_pickle=False) as z:
        assert np.array_equal(d.series["positions"], z["positions"])
        np.testing.assert_allclose(d.clouds[-1].coverage, z["coverage"], rtol=1e-6)  # float32 in the cloud
        # the heat, rebuilt by the writer child from Φ it read from the basis cache file
        np.testing.assert_allclose(d.clouds[-1].heat, z["heat"], rtol=1e-5, atol=1e-6 * np.abs(z["heat"]).max())
        np.testing.assert_allclose(d.clouds[-1].target, z["target"], rtol=1e-6)
    assert not any("not logged" in text for _, _, text in d.events)
    plots = run_cli("replay", run, "--plot", tmp_path / "plots")
    assert plots.code == 0, plots.err
    assert _png_is_drawn(tmp_path / "plots" / "cloud_coverage.png")


def test_sigkilled_explore_replays_as_truncated(bowl_capture, tmp_path):
    """Kill a real 'tergodic explore' with SIGKILL mid-run: the run folder is never published (it is built
    in a temporary sibling), and replay reads the sibling's log up to the last chunk, truncated."""
    import os
    import signal
    import subprocess
    import sys
    import time

    run = tmp_path / "run"
    exe = str(Path(sys.executable).with_name("tergodic"))
    proc = subprocess.Popen([exe, "explore", str(bowl_capture), "--steps", "1000000", "--nk", "60", "--out", str(run)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env={**os.environ, "TERGODIC_NO_PROGRESS": "1"})
    try:
        # the log grows by MBs a second: watch its size (a full read takes longer than the run)
        deadline, size = time.monotonic() + 600, 0  # event-based: a loaded machine takes long to start
        while size < (1 << 20) and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
            logs = list(tmp_path.glob(".run.tmp-*/run.mcap"))
            size = logs[0].stat().st_size if logs else 0
        assert size >= 1 << 20 and proc.poll() is None, (size, proc.poll())
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    assert not run.exists()
    res = run_cli("replay", logs[0].parent, "--json")
    assert res.code == 0, res.err
    out = json.loads(res.out)
    assert out["truncated"] is True and out["steps"] >= 160
    assert "truncated" in res.err


def test_rerun_missing_gives_the_install_hint(tmp_path, monkeypatch):
    import tergodic_cli.runlog.viewers as viewers

    monkeypatch.setattr(viewers, "rerun_available", lambda: False)
    inp = demo_inputs(steps=5, n_agents=1)
    write_demo_log(tmp_path / "run.mcap", inp)
    assert_one_line_error(run_cli("replay", tmp_path, "--rerun", tmp_path / "x.rrd"), "rerun-sdk is not installed",
                          "pip install rerun-sdk")
    assert not (tmp_path / "x.rrd").exists()


@pytest.mark.slow
def test_robot_run_replays_to_its_summary(bowl_capture, tmp_path):
    """A PyBullet robot run: the replayed summary (robot extras recomputed by summarize_robot) equals summary.json."""
    run = tmp_path / "robot"
    res = run_cli("explore", bowl_capture, "--robot", "pybullet", "--steps", "25", "--nk", "60", "--seed", "1",
                  "--out", run)
    assert res.code == 0, res.err
    out = json.loads(run_cli("replay", run, "--json").out)
    assert out.pop("truncated") is False and out.pop("status") == "complete"
    assert out == json.loads((run / "summary.json").read_text())
    d = read_run_log(run)
    assert len(d.robot) == 25 and d.topics[S.TOPIC_TF]["count"] >= 25 and d.topics[S.TOPIC_JOINTS]["count"] == 25
    res = run_cli("replay", run, "--plot", tmp_path / "plots")
    assert res.code == 0, res.err
    assert _png_is_drawn(tmp_path / "plots" / "force.png")
