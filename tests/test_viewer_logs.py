"""Logs that viewers accept (issue 17 item 6): full cloud poses, wall-clock log times, Rerun's verifier."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import REPO, run_cli

from tergodic_cli.runlog import read_run_log
from tergodic_cli.runlog import schema as S

BOWL = REPO / "data" / "bowl"


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """A kinematic and a PyBullet run of the bowl, logged, with the wall clock before each."""
    root = tmp_path_factory.mktemp("viewer_logs")
    out = {}
    for robot, steps in (("kinematic", "60"), ("pybullet", "20")):
        before = time.time_ns()
        res = run_cli("explore", BOWL, "--robot", robot, "--steps", steps, "--nk", "60", "--seed", "1",
                      "--log-cloud-every", "10", "--out", root / robot)
        assert res.code == 0, res.err
        out[robot] = (root / robot, before)
    return out


def _messages(path: Path) -> list:
    """(topic, log_time, decoded message) of every protobuf message, decoded with the schemas in the file."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    factory, decoders, out = DecoderFactory(), {}, []
    with open(path, "rb") as fh:
        for schema, ch, m in make_reader(fh).iter_messages(log_time_order=False):
            if ch.message_encoding == "protobuf":
                if schema.id not in decoders:
                    decoders[schema.id] = factory.decoder_for("protobuf", schema)
                out.append((ch.topic, m.log_time, decoders[schema.id](m.data)))
    return out


@pytest.mark.parametrize("robot", ["kinematic", "pybullet"])
def test_every_cloud_has_a_full_pose_and_log_times_are_wall_clock(runs, robot):
    run, before = runs[robot]
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
    records = [(t, m) for topic, t, m in msgs if topic == S.TOPIC_METRICS]
    for t, rec in records:  # the simulated time stays in the message; the log time is start + it
        assert t == t0 + round(rec.t * 1e9)
    for t, cloud in clouds:
        assert cloud.timestamp.seconds * 10**9 + cloud.timestamp.nanos == t
    # the reader hands back simulated times: clouds land on their steps, events on theirs
    steps = data.series["step"].tolist()
    for c in data.clouds:
        assert c.t == data.series["t"][steps.index(c.step)]
    assert data.clouds[-1].step == int(data.series["step"][-1])
    assert all(0.0 <= t <= data.series["t"][-1] for _, t, _ in data.events)
    if robot == "pybullet":
        assert any(topic == S.TOPIC_TF for topic, _, _ in msgs)


def _rerun(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rerun", *args], capture_output=True, text=True, timeout=180)


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
