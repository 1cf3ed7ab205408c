"""``replay RUN --export rosbag2``: the bag read back with rosbags' own reader, message by message."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli
from scipy.spatial.transform import Rotation
from test_runlog import demo_inputs, write_demo_log

pytest.importorskip("rosbags")


def _read_bag(path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    out: dict[str, list] = {}
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        for conn, t_ns, raw in reader.messages():
            out.setdefault(conn.topic, []).append((t_ns, conn.msgtype, reader.deserialize(raw, conn.msgtype)))
    return out


@pytest.fixture(scope="module")
def robot_run(tmp_path_factory):
    inp = demo_inputs(steps=60, robot=True)
    run = tmp_path_factory.mktemp("run")
    write_demo_log(run / "run.mcap", inp)
    return run, inp


def test_a_robot_run_reads_back_from_the_bag(robot_run, tmp_path):
    run, inp = robot_run
    bag = tmp_path / "bag"
    res = run_cli("replay", run, "--export", "rosbag2", "--export-out", bag)
    assert res.code == 0, res.err
    msgs = _read_bag(bag)
    steps = inp["steps"]
    assert {k: len(v) for k, v in msgs.items()} == {
        "/explorer/agents": steps, "/robot/ee_pose": steps, "/tf": steps, "/robot/wrench": steps,
        "/robot/wrench_desired": steps, "/robot/joint_states": steps, "/cloud": len(inp["clouds"])}
    k = 17
    t_ns, kind, agents = msgs["/explorer/agents"][k]
    assert kind == "geometry_msgs/msg/PoseArray" and agents.header.frame_id == "object"
    assert t_ns == (k + 1) * 10**9  # the step's simulated time (t = step, 1 s per step here)
    for a, pose in enumerate(agents.poses):
        np.testing.assert_allclose([pose.position.x, pose.position.y, pose.position.z], inp["P"][k][a])
        q = [pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w]
        np.testing.assert_allclose(Rotation.from_quat(q).apply([0, 0, 1]), inp["N"][k][a], atol=1e-12)
    sample = inp["robot"][k]
    w = msgs["/robot/wrench"][k][2].wrench
    np.testing.assert_allclose([w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z],
                               sample["wrench_measured"])
    js = msgs["/robot/joint_states"][k][2]
    np.testing.assert_allclose(js.position, sample["q"])
    np.testing.assert_allclose(js.effort, sample["tau"])
    tf = {t.child_frame_id: t for t in msgs["/tf"][k][2].transforms}
    assert set(sample["link_poses"]) | {"ee"} <= set(tf)
    ee = tf["ee"].transform
    np.testing.assert_allclose([ee.translation.x, ee.translation.y, ee.translation.z, ee.rotation.x, ee.rotation.y,
                                ee.rotation.z, ee.rotation.w], sample["ee_pose"])


def test_the_cloud_fields_read_back_as_logged(robot_run, tmp_path):
    run, inp = robot_run
    bag = tmp_path / "bag"
    assert run_cli("replay", run, "--export", "rosbag2", "--export-out", bag).code == 0
    step = sorted(inp["clouds"])[-1]
    cloud = _read_bag(bag)["/cloud"][-1][2]
    names = [f.name for f in cloud.fields]
    assert names == ["x", "y", "z", "target", "coverage", "heat", "source"]
    table = np.frombuffer(bytes(cloud.data), dtype="<f4").reshape(cloud.width, len(names))
    np.testing.assert_array_equal(table[:, :3], inp["points"].astype("<f4"))
    np.testing.assert_array_equal(table[:, 3], inp["target"].astype("<f4"))
    for j, name in enumerate(("coverage", "heat", "source"), start=4):
        np.testing.assert_array_equal(table[:, j], inp["clouds"][step][name].astype("<f4"))


def test_an_existing_bag_is_kept_unless_overwrite(robot_run, tmp_path):
    run, _ = robot_run
    bag = tmp_path / "bag"
    assert run_cli("replay", run, "--export", "rosbag2", "--export-out", bag).code == 0
    before = {p.name: p.read_bytes() for p in bag.iterdir()}
    assert_one_line_error(run_cli("replay", run, "--export", "rosbag2", "--export-out", bag), "overwrite")
    assert {p.name: p.read_bytes() for p in bag.iterdir()} == before
    assert run_cli("replay", run, "--export", "rosbag2", "--export-out", bag, "--overwrite").code == 0
    assert (bag / "metadata.yaml").exists()
