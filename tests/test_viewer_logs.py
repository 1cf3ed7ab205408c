"""Logs that viewers accept (issue 17 item 6, issue 26 items 4-5): full cloud poses, log times that are the wall
clock when written with the simulated time in the messages, every channel protobuf, Rerun's verifier."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO, run_cli

from tergodic_cli.runlog import read_run_log
from tergodic_cli.runlog import schema as S

BOWL = REPO / "data" / "bowl"


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, tuple[Path, int, int]]:
    """A kinematic and a PyBullet run of the bowl, logged, with the wall clock (ns) before and after each."""
    root = tmp_path_factory.mktemp("viewer_logs")
    out = {}
    for robot, steps in (("kinematic", "60"), ("pybullet", "20")):
        before = time.time_ns()
        res = run_cli("explore", BOWL, "--robot", robot, "--steps", steps, "--nk", "60", "--seed", "1",
                      "--log-cloud-every", "10", "--out", root / robot)
        after = time.time_ns()
        assert res.code == 0, res.err
        out[robot] = (root / robot, before, after)
    return out


def _messages(path: Path) -> list:
    """(topic, log_time, decoded message) of every message in file order, decoded by mcap's reader with the
    protobuf decoder factory alone and the schemas in the file (any other encoding raises DecoderNotFoundError)."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        return [(ch.topic, m.log_time, msg) for _, ch, m, msg in reader.iter_decoded_messages(log_time_order=False)]


def _ns(stamp) -> int:
    return stamp.seconds * 10**9 + stamp.nanos


@pytest.mark.parametrize("robot", ["kinematic", "pybullet"])
def test_every_cloud_has_a_full_pose_and_log_times_are_wall_clock(runs, robot):
    run, before, after = runs[robot]
    msgs = _messages(run / "run.mcap")
    clouds = [(t, m) for topic, t, m in msgs if topic == S.TOPIC_CLOUD]
    assert len(clouds) >= 2
    for _, cloud in clouds:
        assert cloud.HasField("pose") and cloud.pose.HasField("position") and cloud.pose.HasField("orientation")
        p, o = cloud.pose.position, cloud.pose.orientation
        assert (p.x, p.y, p.z) == (0.0, 0.0, 0.0) and (o.x, o.y, o.z, o.w) == (0.0, 0.0, 0.0, 1.0)

    data = read_run_log(run)
    t0 = int(data.info["time_origin_ns"])
    assert before <= t0 <= time.time_ns()  # the run's start, wall clock
    log_times = [t for _, t, _ in msgs]  # file order = the order of writing
    assert log_times == sorted(log_times) and before <= log_times[0] and log_times[-1] <= after
    # the simulated time is in the messages: the step's t, and the stamps = the run's start + t
    t_of_step = dict(zip(data.series["step"].tolist(), data.series["t"].tolist()))
    records = [m for topic, _, m in msgs if topic == S.TOPIC_METRICS]
    poses = [m for topic, _, m in msgs if topic == S.TOPIC_AGENT_POSES]
    assert [rec.t for rec in records] == list(t_of_step.values())
    assert [_ns(p.timestamp) for p in poses] == [t0 + round(rec.t * 1e9) for rec in records]
    assert {_ns(c.timestamp) for _, c in clouds} <= {t0 + round(t * 1e9) for t in t_of_step.values()}
    # the reader hands back simulated times: clouds land on their steps, events on theirs
    steps = data.series["step"].tolist()
    for c in data.clouds:
        assert c.t == data.series["t"][steps.index(c.step)]
    assert data.clouds[-1].step == int(data.series["step"][-1])
    assert all(0.0 <= t <= data.series["t"][-1] for _, t, _ in data.events)
    if robot == "pybullet":
        assert any(topic == S.TOPIC_TF for topic, _, _ in msgs)


def _rerun(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rerun", *args], capture_output=True, text=True, timeout=600)


@pytest.mark.parametrize("robot", ["kinematic", "pybullet"])
def test_rerun_converts_and_verifies_the_logs(runs, robot, tmp_path):
    if importlib.util.find_spec("rerun") is None:
        pytest.skip("rerun-sdk is not installed (the [rerun] extra): rerun mcap convert / rrd verify not run")
    run, _ = runs[robot]
    rrd = tmp_path / "converted.rrd"
    conv = _rerun("mcap", "convert", str(run / "run.mcap"), "-o", str(rrd))
    assert conv.returncode == 0 and rrd.is_file(), conv.stderr[-2000:]
    ver = _rerun("rrd", "verify", str(rrd))
    text = ver.stdout + ver.stderr
    assert ver.returncode == 0 and "without error" in text and "Expected non-nullable" not in text, text[-2000:]

    # tergodic's own export: for robot runs the arm's transforms and the wrench arrows, and it verifies too
    own = tmp_path / "replay.rrd"
    res = run_cli("replay", run, "--rerun", own)
    assert res.code == 0, res.err
    ver = _rerun("rrd", "verify", str(own))
    assert ver.returncode == 0 and "without error" in ver.stdout + ver.stderr, (ver.stdout + ver.stderr)[-2000:]
    if robot == "pybullet":
        printed = _rerun("rrd", "print", str(own)).stdout
        for entity in ("/arm/panda_link0", "/arm/ee", "/arm/ee/wrench_measured", "/arm/ee/wrench_desired", "/object"):
            assert entity in printed, entity


def test_log_times_span_the_wall_time_and_stamps_the_simulated_time(runs):
    """A 60-step kinematic run at dt = 1 s: the messages' simulated times span 60 s of the run's own clock,
    their log times lie inside the wall time the run took (they used to be start + simulated time, 60 s on)."""
    run, before, after = runs["kinematic"]
    msgs = _messages(run / "run.mcap")
    data = read_run_log(run)
    t0 = int(data.info["time_origin_ns"])
    dt = float(data.config["dt"])
    records = [m for topic, _, m in msgs if topic == S.TOPIC_METRICS]
    assert [(r.step, r.t) for r in records] == [(k, k * dt) for k in range(1, 61)]  # steps × dt
    stamps = [_ns(m.timestamp) for topic, _, m in msgs if topic == S.TOPIC_AGENT_POSES]
    assert stamps[0] == t0 + round(dt * 1e9) and stamps[-1] - t0 == round(60 * dt * 1e9)
    log_times = [t for _, t, _ in msgs]
    assert log_times[-1] - log_times[0] <= after - before  # bounded by the measured wall time of the run
    assert before <= t0 <= log_times[0] and log_times[-1] <= after
    # the reader's times are simulated seconds, and its figures are the run's summary.json
    assert np.array_equal(data.series["t"], dt * np.arange(1, 61))
    assert [c.t for c in data.clouds] == [dt * c.step for c in data.clouds] and data.clouds[-1].step == 60
    from tergodic_cli.runlog.summary import canonical, recompute_summary

    stored = json.loads((run / "summary.json").read_text())
    assert canonical(recompute_summary(data)) == canonical(stored)


def test_a_robot_log_decodes_with_the_protobuf_decoder_alone(runs):
    """Every channel of a PyBullet run is protobuf: mcap's reader with only mcap_protobuf's DecoderFactory
    decodes every message, and the decoded robot samples and wrenches give the figures of summary.json."""
    run, _, _ = runs["pybullet"]
    msgs = _messages(run / "run.mcap")  # DecoderNotFoundError on any non-protobuf channel
    stored = json.loads((run / "summary.json").read_text())
    data = read_run_log(run)
    by_topic: dict[str, list] = {}
    for topic, _, m in msgs:
        by_topic.setdefault(topic, []).append(m)
    assert {S.TOPIC_ROBOT_SAMPLE, S.TOPIC_WRENCH, S.TOPIC_TF, S.TOPIC_JOINTS, S.TOPIC_ROBOT_FORCE} <= set(by_topic)
    samples, wrenches = by_topic[S.TOPIC_ROBOT_SAMPLE], by_topic[S.TOPIC_WRENCH]
    assert len(samples) == len(wrenches) == stored["robot_samples"] == stored["steps"]
    last = samples[-1]
    assert (last.eps_sponge, last.touched_sponge) == (stored["eps_sponge"], stored["touched_sponge"])
    assert (last.eps_agent, last.touched_agent) == (stored["eps_agent"], stored["touched_agent"])
    explore = [s for s in samples if s.state == "explore"]
    assert len(explore) == stored["explore_samples"]
    assert max(s.force_normal for s in explore) == stored["force_peak_5hz_N"]
    assert np.mean([s.in_contact for s in explore]) == stored["contact_fraction"]
    assert last.t_sim / last.t_wall == stored["realtime_factor"]
    assert last.tick_steady == stored["tick_steady"] and last.tick_force_peak_N <= stored["force_peak_N"]
    for s, w in zip(samples, wrenches):  # the wrench channel says what the sample says
        assert [w.measured.fx, w.measured.fy, w.measured.fz, w.measured.tx, w.measured.ty, w.measured.tz] \
            == list(s.wrench_measured)
        assert (w.desired.fz, w.force_normal, w.in_contact, _ns(w.timestamp)) \
            == (s.wrench_desired[2], s.force_normal, s.in_contact, _ns(s.timestamp))
    # the reader hands back the samples the robot produced, and the summary it recomputes is summary.json
    assert [r["step"] for r in data.robot] == [s.step for s in samples]
    np.testing.assert_array_equal(data.robot_series()["q"], [list(s.q) for s in samples])
    from tergodic_cli.runlog.summary import canonical, recompute_summary

    assert canonical(recompute_summary(data)) == canonical(stored)
