"""Run log: every channel round-trips through a real MCAP file, schemas are Foxglove's, crashes are recoverable."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tergodic_cli.errors import TergodicError
from tergodic_cli.runlog import RunLog, read_run_log
from tergodic_cli.runlog import schema as S
from tergodic_cli.rotations import quat_from_axis as _quat_to

LINKS = ("panda_link1", "panda_link2", "panda_hand")


def demo_inputs(steps: int = 120, n_points: int = 400, n_agents: int = 2, robot: bool = False, seed: int = 0) -> dict:
    """Deterministic, awkward inputs (irrational floats, a zero velocity) for a log of ``steps`` steps."""
    rng = np.random.default_rng(seed)
    pts = rng.standard_normal((n_points, 3)) * 0.05
    target = (rng.random(n_points) > 0.8).astype(np.float64)
    P = rng.standard_normal((steps, n_agents, 3)) * 0.05
    V = rng.standard_normal((steps, n_agents, 3)) * 1e-3
    V[min(3, steps - 1), 0] = 0.0  # no heading on one step
    Nrm = rng.standard_normal((steps, n_agents, 3))
    Nrm /= np.linalg.norm(Nrm, axis=2, keepdims=True)
    metrics = {"ergodicity": rng.random(steps) / 3, "residual_ref": rng.random(steps) / 7,
               "touched_fraction": np.sort(rng.random(steps))}
    step_ms = 0.5 + rng.random(steps) / 3
    samples = None
    if robot:
        samples = []
        for k in range(steps):
            wm = rng.standard_normal(6)
            samples.append({
                "t_sim": 0.02 * (k + 1) + 1e-12 * k, "state": "contact" if k > 5 else "approach",
                "ee_pose": np.r_[rng.standard_normal(3), Rotation.random(random_state=k).as_quat()],
                "q": rng.standard_normal(7), "dq": rng.standard_normal(7), "tau": rng.standard_normal(7),
                "link_poses": {name: np.r_[rng.standard_normal(3), Rotation.random(random_state=100 + k).as_quat()]
                               for name in LINKS},
                "wrench_measured": wm, "wrench_desired": np.array([0, 0, -5.0, 0, 0, 0]),
                "force_normal": float(-wm[2]), "in_contact": bool(k > 5),
                "contact_point": rng.standard_normal(3) if k > 5 else None,
                "tilt_deg": float(rng.random() * 3), "track_mm": float(rng.random()),
            })
    clouds = {}
    for k in range(steps):
        if (k + 1) % 50 == 0 or k == steps - 1:
            clouds[k + 1] = {name: rng.random(n_points) * (3 if name == "heat" else 1)
                             for name in ("coverage", "heat", "source")}
    return {"points": pts, "target": target, "P": P, "V": V, "N": Nrm, "metrics": metrics, "step_ms": step_ms,
            "robot": samples, "clouds": clouds, "steps": steps,
            "config": {"steps": steps, "alpha": "10", "seed": 7, "dt": 1.0, "normal_hint": [0.0, 0.0, 1.0]},
            "versions": {"numpy": np.__version__, "tergodic": "0.1.0"},
            "sidecar": {"source": "synthetic bowl", "n_points": n_points, "h": 0.003}}


#: The demo logs' stamp origin (whole seconds, so that a stamp's seconds - T0_S is the step; log times are
#: the wall clock when written).
T0_S = 1_795_000_000
T0 = T0_S * 10**9


def write_demo_log(path: Path, inp: dict, *, close: bool = True, summary: dict | None = None, **kwargs) -> RunLog:
    """Write ``inp`` through RunLog exactly as the explore command would."""
    kwargs.setdefault("time_origin_ns", T0)
    log = RunLog(path, config=inp["config"], seed=inp["config"]["seed"], versions=inp["versions"],
                 capture_sidecar=inp["sidecar"], points=inp["points"], target=inp["target"], cloud_every=50,
                 **kwargs)
    for k in range(inp["steps"]):
        step = k + 1
        log.log_step(step, float(step), positions=inp["P"][k], velocities=inp["V"][k], normals=inp["N"][k],
                     metrics={m: v[k] for m, v in inp["metrics"].items()}, step_ms=inp["step_ms"][k],
                     robot=None if inp["robot"] is None else inp["robot"][k])
        if step == 4:
            log.log_event(step, float(step), "contact established")
        if step in inp["clouds"]:
            log.log_cloud(step, **inp["clouds"][step])
    if close:
        log.close(summary)
    return log


@pytest.fixture(scope="module")
def robot_log(tmp_path_factory):
    """A robot run."""
    inp = demo_inputs(robot=True)
    path = tmp_path_factory.mktemp("robotlog") / "run.mcap"
    write_demo_log(path, inp)
    return path, inp


def _decoded(path: Path) -> dict[str, list]:
    """Every message of ``path`` decoded by mcap's own reader with the protobuf decoder alone (the schemas in
    the file), in file order."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    out: dict[str, list] = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])  # a JSON channel raises DecoderNotFoundError
        for _, channel, message, value in reader.iter_decoded_messages(log_time_order=False):
            out.setdefault(channel.topic, []).append((message, value))
    return out


def _ns(stamp) -> int:
    return stamp.seconds * 10**9 + stamp.nanos


# --- geometry helpers of the writer ------------------------------------------------------------
def test_pose_and_arrow_quaternions():
    rng = np.random.default_rng(1)
    v = np.vstack([rng.standard_normal((300, 3)), [[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [-2, 0, 0], [0, 0, 0]]])
    for a, axis in ((2, [0, 0, 1]), (0, [1, 0, 0])):
        q = np.array([_quat_to(a, x) for x in v])
        np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0)
        got = Rotation.from_quat(q).apply(axis)
        norm = np.linalg.norm(v, axis=1)
        nz = norm > 0
        np.testing.assert_allclose(got[nz], v[nz] / norm[nz, None], atol=1e-12)
        np.testing.assert_allclose(q[~nz], [[0, 0, 0, 1]])  # a zero vector: identity


def test_robot_arrow_quaternion_turns_x_onto_the_direction():
    rng = np.random.default_rng(2)
    for v in list(rng.standard_normal((100, 3))) + [np.array([-1.0, 0, 0]), np.array([1.0, 0, 0])]:
        u = v / np.linalg.norm(v)
        np.testing.assert_allclose(Rotation.from_quat(_quat_to(0, u)).apply([1, 0, 0]), u, atol=1e-12)


# --- the file -------------------------------------------------------------------------------
def test_schema_names_and_encodings_are_foxglove_protobuf(robot_log):
    from mcap.reader import make_reader

    path, _ = robot_log
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    schemas = {s.name: s.encoding for s in summary.schemas.values()}
    by_topic = {c.topic: (summary.schemas[c.schema_id].name, summary.schemas[c.schema_id].encoding, c.message_encoding)
                for c in summary.channels.values()}
    for name in ("foxglove.PointCloud", "foxglove.FrameTransform", "foxglove.SceneUpdate", "foxglove.PoseInFrame",
                 "foxglove.PosesInFrame", "foxglove.JointStates", "foxglove.Log"):
        assert schemas.get(name) == "protobuf", (name, schemas)
    assert by_topic[S.TOPIC_CLOUD] == ("foxglove.PointCloud", "protobuf", "protobuf")
    assert by_topic[S.TOPIC_TF] == ("foxglove.FrameTransform", "protobuf", "protobuf")
    assert by_topic[S.TOPIC_AGENT_SCENE] == ("foxglove.SceneUpdate", "protobuf", "protobuf")
    assert by_topic[S.TOPIC_EE_POSE] == ("foxglove.PoseInFrame", "protobuf", "protobuf")
    assert by_topic[S.TOPIC_METRICS] == ("tergodic.StepRecord", "protobuf", "protobuf")
    assert by_topic[S.TOPIC_ROBOT_SAMPLE] == ("tergodic.RobotSample", "protobuf", "protobuf")
    assert by_topic[S.TOPIC_WRENCH] == ("tergodic.Wrench", "protobuf", "protobuf")
    assert {enc for _, enc, _ in by_topic.values()} == {"protobuf"}  # one encoding
    assert {enc for _, _, enc in by_topic.values()} == {"protobuf"}
    # chunked, indexed, compressed
    assert len(summary.chunk_indexes) >= 3
    assert {ci.compression for ci in summary.chunk_indexes} == {"lz4"}
    assert all(ci.message_index_offsets for ci in summary.chunk_indexes)
    assert summary.statistics.message_count == sum(summary.statistics.channel_message_counts.values())


def test_every_channel_round_trips(robot_log):
    path, inp = robot_log
    T, A = inp["steps"], inp["P"].shape[1]
    msgs = _decoded(path)

    metrics = msgs[S.TOPIC_METRICS]  # decoded with the schema stored in the file, not tergodic's class
    assert len(metrics) == T
    for k, (m, rec) in enumerate(metrics):
        assert rec.step == k + 1 and rec.t == k + 1
        for name, series in inp["metrics"].items():
            assert getattr(rec, name) == series[k]  # exact float64
        assert rec.step_ms == inp["step_ms"][k] and rec.n_agents == A
        assert list(rec.positions) == inp["P"][k].ravel().tolist()
        assert list(rec.velocities) == inp["V"][k].ravel().tolist()
        assert list(rec.normals) == inp["N"][k].ravel().tolist()

    poses = msgs[S.TOPIC_AGENT_POSES]
    assert len(poses) == T
    for k, (_, msg) in enumerate(poses):
        assert msg.frame_id == S.FRAME_OBJECT and len(msg.poses) == A
        assert msg.timestamp.seconds == T0_S + k + 1
        for a, pose in enumerate(msg.poses):
            assert [pose.position.x, pose.position.y, pose.position.z] == inp["P"][k, a].tolist()
            o = pose.orientation
            z = Rotation.from_quat([o.x, o.y, o.z, o.w]).apply([0, 0, 1])
            np.testing.assert_allclose(z, inp["N"][k, a], atol=1e-12)

    extent = np.linalg.norm(inp["points"].max(axis=0) - inp["points"].min(axis=0))
    scene = msgs[S.TOPIC_AGENT_SCENE]
    assert len(scene) == T
    for k, (_, msg) in enumerate(scene):
        assert [e.id for e in msg.entities] == [f"agent{a:04d}" for a in range(A)]
        for a, ent in enumerate(msg.entities):
            (line,) = ent.lines
            ends = np.array([[p.x, p.y, p.z] for p in line.points])
            mid = ends.mean(axis=0)
            direction = ends[1] - ends[0]
            np.testing.assert_allclose(mid, inp["P"][k, a], atol=1e-12)  # the line passes through the agent
            np.testing.assert_allclose(direction / np.linalg.norm(direction), inp["N"][k, a], atol=1e-12)  # along n
            (arrow,) = ent.arrows
            v = inp["V"][k, a]
            ap = arrow.pose.position
            assert [ap.x, ap.y, ap.z] == inp["P"][k, a].tolist()
            if np.linalg.norm(v) > 0:
                o = arrow.pose.orientation
                heading = Rotation.from_quat([o.x, o.y, o.z, o.w]).apply([1, 0, 0])
                np.testing.assert_allclose(heading, v / np.linalg.norm(v), atol=1e-12)  # along the velocity
                assert arrow.shaft_length == pytest.approx(min(5 * np.linalg.norm(v), 0.25 * extent))
            else:
                assert arrow.shaft_length == 0.0

    clouds = msgs[S.TOPIC_CLOUD]
    assert [msg.timestamp.seconds - T0_S for _, msg in clouds] == sorted(inp["clouds"])  # t = step s
    for m, msg in clouds:
        names = [f.name for f in msg.fields]
        assert names == ["x", "y", "z", "target", "coverage", "heat", "source"]
        assert msg.point_stride == 28 and msg.frame_id == S.FRAME_OBJECT
        arr = np.frombuffer(msg.data, dtype="<f4").reshape(-1, 7)
        np.testing.assert_array_equal(arr[:, :3], inp["points"].astype(np.float32))
        np.testing.assert_array_equal(arr[:, 3], inp["target"].astype(np.float32))
        for col, name in ((4, "coverage"), (5, "heat"), (6, "source")):
            np.testing.assert_array_equal(arr[:, col], inp["clouds"][msg.timestamp.seconds - T0_S][name].astype(np.float32))

    samples = msgs[S.TOPIC_ROBOT_SAMPLE]  # tergodic.RobotSample, decoded with the schema in the file
    assert len(samples) == T
    for k, (_, rec) in enumerate(samples):
        src = inp["robot"][k]
        assert _ns(rec.timestamp) == T0 + (k + 1) * 10**9 and rec.step == k + 1
        assert rec.t_sim == src["t_sim"] and rec.state == src["state"] and rec.in_contact == src["in_contact"]
        for key in ("ee_pose", "q", "dq", "tau", "wrench_measured", "wrench_desired"):
            assert list(getattr(rec, key)) == np.asarray(src[key]).tolist(), key
        assert (list(rec.contact_point), list(rec.nulls)) == (([], ["contact_point"]) if src["contact_point"] is None
                                                              else (src["contact_point"].tolist(), []))
        assert {p.name: list(p.pose) for p in rec.link_poses} == {n: p.tolist() for n, p in src["link_poses"].items()}
        assert rec.force_normal == src["force_normal"] and rec.tilt_deg == src["tilt_deg"] and not rec.extras

    ee = msgs[S.TOPIC_EE_POSE]
    for k, (_, msg) in enumerate(ee):
        pose = msg.pose
        got = [pose.position.x, pose.position.y, pose.position.z, pose.orientation.x, pose.orientation.y,
               pose.orientation.z, pose.orientation.w]
        assert got == inp["robot"][k]["ee_pose"].tolist() and msg.frame_id == S.FRAME_BASE

    tfs = msgs[S.TOPIC_TF]
    assert len(tfs) == T * (len(LINKS) + 1)
    for m, tf in tfs:
        k = tf.timestamp.seconds - T0_S - 1
        src = inp["robot"][k]
        expected = src["ee_pose"] if tf.child_frame_id == S.FRAME_EE else src["link_poses"][tf.child_frame_id]
        got = [tf.translation.x, tf.translation.y, tf.translation.z, tf.rotation.x, tf.rotation.y, tf.rotation.z,
               tf.rotation.w]
        assert tf.parent_frame_id == S.FRAME_BASE and got == expected.tolist()

    joints = msgs[S.TOPIC_JOINTS]
    for k, (_, js) in enumerate(joints):
        src = inp["robot"][k]
        assert [j.position for j in js.joints] == src["q"].tolist()
        assert [j.velocity for j in js.joints] == src["dq"].tolist()
        assert [j.effort for j in js.joints] == src["tau"].tolist()

    wrench = msgs[S.TOPIC_WRENCH]
    for k, (_, rec) in enumerate(wrench):
        src = inp["robot"][k]
        components = ("fx", "fy", "fz", "tx", "ty", "tz")
        assert [getattr(rec.measured, c) for c in components] == src["wrench_measured"].tolist()
        assert [getattr(rec.desired, c) for c in components] == src["wrench_desired"].tolist()
        assert rec.force_normal == src["force_normal"] and rec.in_contact == src["in_contact"]
        assert rec.frame_id == S.FRAME_EE and _ns(rec.timestamp) == T0 + (k + 1) * 10**9
    wscene = msgs[S.TOPIC_WRENCH_SCENE]
    _, first = wscene[0]
    desired = next(e for e in first.entities if e.id == "force_desired")
    (arrow,) = desired.arrows
    o = arrow.pose.orientation
    np.testing.assert_allclose(Rotation.from_quat([o.x, o.y, o.z, o.w]).apply([1, 0, 0]), [0, 0, -1], atol=1e-12)
    assert arrow.shaft_length == pytest.approx(0.005 * 5.0)

    (ev_msg, ev), = msgs[S.TOPIC_EVENTS]
    assert ev.message == "step 4: contact established" and _ns(ev.timestamp) == T0 + 4 * 10**9

    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        reader = make_reader(fh)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        atts = {a.name: a.data for a in reader.iter_attachments()}
    assert meta[S.META_TERGODIC]["log_schema_version"] == S.LOG_SCHEMA_VERSION
    assert json.loads(meta[S.META_CONFIG]["json"]) == inp["config"]
    assert meta[S.META_SEED] == {"seed": "7"}
    assert meta[S.META_VERSIONS] == inp["versions"]
    assert meta[S.META_END]["steps"] == str(T) and meta[S.META_END]["status"] == "ok"
    assert json.loads(atts[S.ATTACHMENT_SIDECAR]) == inp["sidecar"]


@pytest.mark.parametrize("compression", ["lz4", "zstd"])
def test_reader_returns_what_was_written(tmp_path, compression):
    inp = demo_inputs(steps=130, robot=True)
    path = tmp_path / "run.mcap"
    write_demo_log(path, inp, compression=compression, summary={"steps": 130, "note": "x"})
    d = read_run_log(tmp_path)  # a run folder resolves to its run.mcap
    assert d.path == path and not d.truncated and d.steps == 130 and d.info["backend"] == "foxglove-sdk"
    assert d.info["compression"] == compression
    assert np.array_equal(d.series["step"], np.arange(1, 131))
    for name, series in inp["metrics"].items():
        assert np.array_equal(d.series[name], series)
    assert np.array_equal(d.series["step_ms"], inp["step_ms"])
    for key, src in (("positions", "P"), ("velocities", "V"), ("normals", "N")):
        assert np.array_equal(d.series[key], inp[src])
    assert d.config == inp["config"] and d.seed == 7 and d.versions == inp["versions"]
    assert d.capture_sidecar == inp["sidecar"] and d.stored_summary == {"steps": 130, "note": "x"}
    assert [c.step for c in d.clouds] == [50, 100, 130]
    last = d.clouds[-1]
    np.testing.assert_allclose(last.points, inp["points"], rtol=1e-6, atol=1e-9)  # float32 in the file
    np.testing.assert_allclose(last.coverage, inp["clouds"][130]["coverage"], rtol=1e-6)
    assert d.cloud_at(99).step == 50 and d.cloud_at(49) is None
    assert d.events == [(4, 4.0, "contact established")]
    rs = d.robot_series()
    assert rs["q"].shape == (130, 7) and np.array_equal(rs["q"][5], inp["robot"][5]["q"])
    assert np.array_equal(rs["force_normal"], [s["force_normal"] for s in inp["robot"]])
    assert np.isnan(rs["contact_point"][0]).all() and np.array_equal(rs["contact_point"][10], inp["robot"][10]["contact_point"])


def test_nonfinite_metrics_survive(tmp_path):
    inp = demo_inputs(steps=3, robot=False)
    inp["metrics"]["ergodicity"][:] = [np.nan, np.inf, -np.inf]
    write_demo_log(tmp_path / "run.mcap", inp)
    e = read_run_log(tmp_path / "run.mcap").series["ergodicity"]
    assert np.isnan(e[0]) and e[1] == np.inf and e[2] == -np.inf


def test_chunks_are_flushed_every_flush_every_steps(tmp_path):
    from mcap.reader import make_reader

    inp = demo_inputs(steps=200, robot=False)
    inp["clouds"] = {}
    write_demo_log(tmp_path / "run.mcap", inp, flush_every=25)
    with open(tmp_path / "run.mcap", "rb") as fh:
        chunks = make_reader(fh).get_summary().chunk_indexes
    # one chunk per 25 steps (+ the event's own step inside the first): 200 / 25 = 8
    assert len(chunks) == 8
    assert _last_step_of_each_chunk(tmp_path / "run.mcap") == list(range(25, 201, 25))


def _last_step_of_each_chunk(path: Path) -> list[int]:
    """The step of the last StepRecord in each chunk, reading the records in file order (a chunk's messages
    are followed by its message indexes)."""
    from mcap.records import Channel, Message, MessageIndex
    from mcap.stream_reader import StreamReader

    from tergodic_cli.runlog.proto import step_record_class

    Record, metrics, out, last = step_record_class(), set(), [], None
    with open(path, "rb") as fh:
        for rec in StreamReader(fh).records:
            if isinstance(rec, Channel) and rec.topic == S.TOPIC_METRICS:
                metrics.add(rec.id)
            elif isinstance(rec, Message) and rec.channel_id in metrics:
                last = Record.FromString(rec.data).step
            elif isinstance(rec, MessageIndex) and last is not None:
                out, last = out + [last], None
    return out


def test_context_manager_finishes_the_file_on_error(tmp_path):
    inp = demo_inputs(steps=10)
    with pytest.raises(RuntimeError):
        with RunLog(tmp_path / "run.mcap", config=inp["config"], seed=1, points=inp["points"]) as log:
            for k in range(5):
                log.log_step(k + 1, k + 1.0, positions=inp["P"][k], velocities=inp["V"][k], normals=inp["N"][k],
                             metrics={m: v[k] for m, v in inp["metrics"].items()}, step_ms=1.0)
            raise RuntimeError("explorer blew up")
    d = read_run_log(tmp_path / "run.mcap")
    assert not d.truncated and d.steps == 5 and d.end["status"] == "error: RuntimeError"


def test_bad_writer_arguments_are_one_line_errors(tmp_path):
    inp = demo_inputs(steps=2)
    with pytest.raises(TergodicError, match="shape"):
        RunLog(tmp_path / "a.mcap", config={}, seed=0, points=np.zeros((5, 2)))
    with pytest.raises(TergodicError, match="target"):
        RunLog(tmp_path / "b.mcap", config={}, seed=0, points=inp["points"], target=np.zeros(3))
    with pytest.raises(TergodicError, match="log-cloud-every"):
        RunLog(tmp_path / "c.mcap", config={}, seed=0, points=inp["points"], cloud_every=0)
    log = RunLog(tmp_path / "d.mcap", config={}, seed=0, points=inp["points"])
    with pytest.raises(TergodicError, match="shape"):
        log.log_cloud(1, coverage=np.zeros(3), heat=np.zeros(3), source=np.zeros(3))
    log.close()
    with pytest.raises(TergodicError, match="closed"):
        log.log_step(1, 1.0, positions=np.zeros(3), velocities=np.zeros(3), normals=np.zeros(3), metrics={}, step_ms=1)


# --- crash safety ------------------------------------------------------------------------------
def test_every_cut_of_a_log_reads_as_a_prefix(tmp_path):
    """Cut a finished log at many offsets: each reads as steps 1..K with truncated=True, or is refused in one line."""
    inp = demo_inputs(steps=150, n_points=300, robot=False)
    full = tmp_path / "full.mcap"
    write_demo_log(full, inp, flush_every=10)
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    seen = set()
    for size in sorted(set(np.linspace(1, len(data) - 1, 120).astype(int)) | {8, 16, 17, 30}):
        cut.write_bytes(data[:size])
        try:
            d = read_run_log(cut)
        except TergodicError as exc:
            assert any(w in str(exc) for w in ("truncated header", "empty log", "cut off before its metadata")), (size, exc)
            continue
        assert d.truncated, size
        K = d.steps
        assert np.array_equal(d.series["step"], np.arange(1, K + 1))
        assert np.array_equal(d.series["ergodicity"], inp["metrics"]["ergodicity"][:K])
        seen.add(K)
    assert len(seen) >= 5  # many different prefixes were recovered
    assert max(seen) >= 140


CHILD = textwrap.dedent("""
    import sys, time
    import numpy as np
    from tergodic_cli.runlog import RunLog
    n = 500
    rng = np.random.default_rng(0)
    pts = rng.standard_normal((n, 3))
    log = RunLog(sys.argv[1], config={"steps": 100000, "seed": 0}, seed=0, points=pts, cloud_every=50, flush_every=20)
    for k in range(1, 100000):
        log.log_step(k, float(k), positions=np.full((1, 3), k * 1e-3), velocities=np.zeros((1, 3)),
                     normals=np.array([[0.0, 0.0, 1.0]]),
                     metrics={"ergodicity": 1.0 / k, "residual_ref": 2.0 / k, "touched_fraction": k / 1e5},
                     step_ms=0.5)
        if k % 50 == 0:
            log.log_cloud(k, coverage=np.full(n, k, float), heat=np.zeros(n), source=np.zeros(n))
        if k % 100 == 0:
            print(k, flush=True)
        time.sleep(0.001)
""")


def test_sigkilled_run_replays_as_truncated(tmp_path):
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    log = tmp_path / "run" / "run.mcap"
    proc = subprocess.Popen([sys.executable, str(script), str(log)], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "OMP_NUM_THREADS": "1"})
    try:
        deadline = time.monotonic() + 600
        last = 0
        while last < 300 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            last = int(line)
        assert last >= 300, "the child did not get going"
        time.sleep(0.05)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(timeout=300)
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    d = read_run_log(log.parent)
    assert d.truncated and d.end is None
    K = d.steps
    assert K >= 200  # step 300 was logged; at most the steps since the last flush (<= 20 + queue) are lost
    assert np.array_equal(d.series["step"], np.arange(1, K + 1))
    assert np.array_equal(d.series["ergodicity"], 1.0 / np.arange(1, K + 1))
    assert all(c.step % 50 == 0 and c.coverage[0] == c.step for c in d.clouds) and len(d.clouds) >= 4

    from conftest import run_cli

    res = run_cli("replay", log.parent, "--json")
    assert res.code == 0, res.err
    out = json.loads(res.out)
    assert out["truncated"] is True and out["steps"] == K
    assert out["ergodicity"] == 1.0 / K
    assert "truncated" in res.err


# --- the step encoding ---------------------------------------------------------------------------
@pytest.mark.parametrize("n_agents", [1, 3, 12])
def test_step_messages_decode_exactly_with_the_official_schemas(tmp_path, n_agents):
    """Awkward values (zeros, NaN, ±inf, huge step, fractional times) through the step encoding."""
    rng = np.random.default_rng(n_agents)
    steps = 37
    inp = demo_inputs(steps=steps, n_agents=n_agents, seed=n_agents)
    inp["P"][0] = 0.0  # zero doubles are still written
    inp["V"][1] = 0.0
    inp["metrics"]["residual_ref"][0] = np.nan
    inp["metrics"]["ergodicity"][2] = np.inf
    inp["metrics"]["touched_fraction"][3] = -0.0
    times = np.cumsum(rng.random(steps) * 3.7)  # not whole seconds: nanos in the timestamps
    t0 = 1_795_000_000_987_654_321  # a wall-clock origin with nanos: multi-byte varints in the timestamps
    log = RunLog(tmp_path / "run.mcap", config={}, seed=0, points=inp["points"], flush_every=10, time_origin_ns=t0)
    for k in range(steps):
        log.log_step(2**40 + k, times[k], positions=inp["P"][k], velocities=inp["V"][k], normals=inp["N"][k],
                     metrics={m: v[k] for m, v in inp["metrics"].items()}, step_ms=inp["step_ms"][k])
    log.close()
    msgs = _decoded(tmp_path / "run.mcap")
    assert len(msgs[S.TOPIC_METRICS]) == len(msgs[S.TOPIC_AGENT_POSES]) == len(msgs[S.TOPIC_AGENT_SCENE]) == steps
    for k, ((m, rec), (_, poses), (_, scene)) in enumerate(zip(msgs[S.TOPIC_METRICS], msgs[S.TOPIC_AGENT_POSES],
                                                                msgs[S.TOPIC_AGENT_SCENE])):
        t_ns = t0 + round(times[k] * 1e9)
        assert rec.step == 2**40 + k and rec.t == times[k] and rec.n_agents == n_agents
        for name, series in inp["metrics"].items():
            np.testing.assert_array_equal(getattr(rec, name), series[k])  # NaN == NaN here
        assert np.signbit(rec.touched_fraction) == np.signbit(inp["metrics"]["touched_fraction"][k])
        assert list(rec.positions) == inp["P"][k].ravel().tolist()
        assert poses.timestamp.seconds * 10**9 + poses.timestamp.nanos == t_ns
        assert [[p.position.x, p.position.y, p.position.z] for p in poses.poses] == inp["P"][k].tolist()
        assert len(scene.entities) == n_agents
        for a, ent in enumerate(scene.entities):
            np.testing.assert_allclose([[p.x, p.y, p.z] for p in ent.lines[0].points],
                                       [inp["P"][k, a] - 0.25 * _extent(inp) * inp["N"][k, a],
                                        inp["P"][k, a] + 0.25 * _extent(inp) * inp["N"][k, a]], rtol=0, atol=1e-15)
    d = read_run_log(tmp_path / "run.mcap")
    assert np.array_equal(d.series["step"], 2**40 + np.arange(steps))
    np.testing.assert_array_equal(d.series["residual_ref"], inp["metrics"]["residual_ref"])


def _extent(inp: dict) -> float:
    return float(np.linalg.norm(inp["points"].max(axis=0) - inp["points"].min(axis=0)))


def test_extra_metrics_and_a_changing_agent_count(tmp_path):
    inp = demo_inputs(steps=6, n_agents=2)
    log = RunLog(tmp_path / "run.mcap", config={}, seed=0, points=inp["points"], flush_every=4)
    for k in range(6):
        n = 1 if k >= 3 else 2  # an agent drops out after step 3
        metrics = {m: v[k] for m, v in inp["metrics"].items()}
        if k == 1:
            metrics = {"ergodicity": 0.5, "contact_ergodicity": 0.25}  # non-standard names
        log.log_step(k + 1, k + 1.0, positions=inp["P"][k, :n], velocities=inp["V"][k, :n], normals=inp["N"][k, :n],
                     metrics=metrics, step_ms=1.0)
    log.close()
    msgs = _decoded(tmp_path / "run.mcap")
    recs = [r for _, r in msgs[S.TOPIC_METRICS]]
    assert [r.n_agents for r in recs] == [2, 2, 2, 1, 1, 1]
    assert recs[1].ergodicity == 0.5 and not recs[1].HasField("touched_fraction")
    assert list(recs[1].extra_names) == ["contact_ergodicity"] and list(recs[1].extra_values) == [0.25]
    assert list(recs[4].positions) == inp["P"][4, 0].tolist()
    d = read_run_log(tmp_path / "run.mcap")
    assert np.isnan(d.series["touched_fraction"][1]) and d.series["ergodicity"][1] == 0.5
    assert d.series["contact_ergodicity"][1] == 0.25 and np.isnan(d.series["contact_ergodicity"][0])
    assert d.series["positions"].dtype == object and d.series["positions"][4].shape == (1, 3)


def test_events_and_robot_messages_follow_their_step(tmp_path):
    inp = demo_inputs(steps=5, robot=True, n_agents=1)
    before = time.time_ns()
    write_demo_log(tmp_path / "run.mcap", inp)  # the event is logged after step 4
    after = time.time_ns()
    from mcap.reader import make_reader

    with open(tmp_path / "run.mcap", "rb") as fh:  # file order: the order of writing
        msgs = [(ch.topic, m) for _, ch, m in make_reader(fh).iter_messages(log_time_order=False)]
    log_times = [m.log_time for _, m in msgs]
    assert log_times == sorted(log_times) and before <= log_times[0] and log_times[-1] <= after  # the wall clock
    order = [topic for topic, _ in msgs]
    starts = [i for i, topic in enumerate(order) if topic == S.TOPIC_METRICS]  # where each step begins
    step4 = order[starts[3]:starts[4]]
    assert step4[:3] == [S.TOPIC_METRICS, S.TOPIC_AGENT_POSES, S.TOPIC_AGENT_SCENE]
    assert S.TOPIC_ROBOT_SAMPLE in step4 and S.TOPIC_TF in step4 and step4[-1] == S.TOPIC_EVENTS


# --- logs written before version 3 ---------------------------------------------------------------
def _write_v2_log(path: Path, inp: dict, t0: int) -> None:
    """A log laid out as tergodic wrote them before version 3, by hand with mcap's own writer: log times
    t0 + simulated t (the stamps the same), /robot/sample as JSON (a JSON schema), the rest protobuf."""
    from foxglove_schemas_protobuf.Log_pb2 import Log
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
    from mcap.writer import Writer
    from mcap_protobuf.schema import build_file_descriptor_set

    from tergodic_cli.runlog.proto import FULL_NAME, step_record_class, step_record_schema

    Record = step_record_class()
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="tergodic before version 3")
        w.add_metadata(S.META_TERGODIC, {"log_schema_version": "2", "time_origin_ns": str(t0), "cloud_every": "50"})
        w.add_metadata(S.META_CONFIG, {"json": json.dumps(inp["config"])})
        w.add_metadata(S.META_SEED, {"seed": "7"})

        def channel(topic: str, name: str, encoding: str, data: bytes, message_encoding: str) -> int:
            return w.register_channel(topic, message_encoding, w.register_schema(name, encoding, data))

        def fds(cls) -> bytes:
            return build_file_descriptor_set(cls).SerializeToString()

        ch_m = channel(S.TOPIC_METRICS, FULL_NAME, "protobuf", step_record_schema(), "protobuf")
        ch_s = channel(S.TOPIC_ROBOT_SAMPLE, "tergodic.RobotSample", "jsonschema", b'{"type": "object"}', "json")
        ch_e = channel(S.TOPIC_EVENTS, "foxglove.Log", "protobuf", fds(Log), "protobuf")
        ch_c = channel(S.TOPIC_CLOUD, "foxglove.PointCloud", "protobuf", fds(PointCloud), "protobuf")
        for k in range(inp["steps"]):
            step, t = k + 1, float(k + 1)
            t_ns = t0 + step * 10**9
            rec = Record(step=step, t=t, step_ms=float(inp["step_ms"][k]), n_agents=inp["P"].shape[1],
                         **{m: float(v[k]) for m, v in inp["metrics"].items()})
            for name, key in (("positions", "P"), ("velocities", "V"), ("normals", "N")):
                getattr(rec, name).extend(inp[key][k].ravel().tolist())
            w.add_message(ch_m, log_time=t_ns, publish_time=t_ns, data=rec.SerializeToString())
            sample = {"step": step, **inp["robot"][k]}
            w.add_message(ch_s, log_time=t_ns, publish_time=t_ns,
                          data=json.dumps(sample, default=lambda a: a.tolist()).encode())
            if step == 4:
                ev = Log(message="step 4: contact established", name="tergodic")
                ev.timestamp.FromNanoseconds(t_ns)
                w.add_message(ch_e, log_time=t_ns, publish_time=t_ns, data=ev.SerializeToString())
            if step in inp["clouds"]:
                c = inp["clouds"][step]
                cols = [inp["points"][:, 0], inp["points"][:, 1], inp["points"][:, 2], inp["target"],
                        c["coverage"], c["heat"], c["source"]]
                names = ("x", "y", "z", *S.CLOUD_FIELDS)
                msg = PointCloud(frame_id=S.FRAME_OBJECT, point_stride=28,
                                 data=np.column_stack(cols).astype("<f4").tobytes())
                msg.timestamp.FromNanoseconds(t_ns)
                for i, name in enumerate(names):
                    msg.fields.add(name=name, offset=4 * i, type=7)  # FLOAT32
                w.add_message(ch_c, log_time=t_ns, publish_time=t_ns, data=msg.SerializeToString())
        w.add_metadata(S.META_END, {"steps": str(inp["steps"]), "clouds": str(len(inp["clouds"])), "status": "ok"})
        w.finish()


def test_a_version_2_log_with_json_samples_reads_as_before(tmp_path):
    """Logs written before version 3 (JSON robot samples, log times = start + simulated time) still read:
    the same samples, steps, event and cloud times as the current writer's log of the same run."""
    inp = demo_inputs(steps=60, robot=True, n_agents=2, seed=5)
    _write_v2_log(tmp_path / "old.mcap", inp, T0)
    write_demo_log(tmp_path / "new.mcap", inp)
    old, new = read_run_log(tmp_path / "old.mcap"), read_run_log(tmp_path / "new.mcap")
    assert old.version == "2" and new.version == S.LOG_SCHEMA_VERSION
    assert old.topics[S.TOPIC_ROBOT_SAMPLE]["message_encoding"] == "json"
    assert new.topics[S.TOPIC_ROBOT_SAMPLE]["message_encoding"] == "protobuf"
    assert old.events == new.events == [(4, 4.0, "contact established")]
    assert [(c.step, c.t) for c in old.clouds] == [(c.step, c.t) for c in new.clouds] == [(50, 50.0), (60, 60.0)]
    np.testing.assert_array_equal(old.clouds[-1].coverage, new.clouds[-1].coverage)
    for key in ("step", "t", "ergodicity", "positions"):
        np.testing.assert_array_equal(old.series[key], new.series[key])
    assert len(old.robot) == len(new.robot) == 60
    for a, b, src in zip(old.robot, new.robot, inp["robot"]):
        assert set(a) == set(b) == {"step", *src}
        for key, v in src.items():
            if isinstance(v, dict):
                assert {n: p.tolist() for n, p in a[key].items()} == {n: p.tolist() for n, p in b[key].items()} \
                    == {n: np.asarray(p).tolist() for n, p in v.items()}
            elif isinstance(v, np.ndarray):
                assert a[key].dtype == b[key].dtype == np.float64
                assert a[key].tolist() == b[key].tolist() == v.tolist(), key
            else:
                assert a[key] == b[key] == v and type(a[key]) is type(b[key]), key
    for key, col in old.robot_series().items():
        np.testing.assert_array_equal(col, new.robot_series()[key])


def test_robot_sample_encoding_keeps_every_key_and_type():
    """tergodic.RobotSample round-trips what a robot may put in a sample: None, keys outside the table,
    values not of their field's kind, integers, nested dicts."""
    from tergodic_cli.runlog.proto import ROBOT_SAMPLE, encode_sample, robot_class, sample_from_message

    sample = {"step": 2**40, "t_sim": 0.1 + 0.2, "state": "explore", "q": np.arange(7) / 3, "contact_point": None,
              "in_contact": np.bool_(True), "tick_steady": np.int64(12), "eps_agent": None,
              "force_normal": 3,  # an int in a double field: a float of the same value
              "link_poses": {"a": np.r_[1.0, 2, 3, 0, 0, 0, 1]}, "joint_names": ["j1", "j2"],
              "recapture": {"share": 0.5, "ok": True}, "note": "hi", "count": 3, "flag": False, "ratio": 0.25,
              "weights": [1, 2.5], "state_list": ["a", "b"], "empty": [], "t_wall": "not a number"}
    msg = robot_class(ROBOT_SAMPLE).FromString(encode_sample(sample, 1_795_000_000_123_456_789))
    assert (msg.timestamp.seconds, msg.timestamp.nanos) == (1_795_000_000, 123_456_789)
    back = sample_from_message(msg)
    assert set(back) == set(sample)
    assert back["step"] == 2**40 and back["t_sim"] == 0.1 + 0.2 and back["state"] == "explore"
    assert back["q"].tolist() == (np.arange(7) / 3).tolist() and back["contact_point"] is None
    assert back["in_contact"] is True and back["tick_steady"] == 12 and back["eps_agent"] is None
    assert back["force_normal"] == 3.0 and back["link_poses"]["a"].tolist() == [1, 2, 3, 0, 0, 0, 1]
    assert back["joint_names"] == ["j1", "j2"] and back["recapture"] == {"share": 0.5, "ok": True}
    assert (back["note"], back["count"], back["flag"], back["ratio"]) == ("hi", 3, False, 0.25)
    assert type(back["count"]) is int and back["weights"].tolist() == [1.0, 2.5]
    assert back["state_list"] == ["a", "b"] and back["empty"] == [] and back["t_wall"] == "not a number"
