"""``replay RUN --export rosbag2``: a run as a ROS 2 bag, written with ``rosbags`` (no ROS install needed).

Topics (frames: ``object`` = the capture's frame, ``base`` = the robot's base, ``ee`` = the tool):

============================  ============================  ===========================================
topic                         type                          what
============================  ============================  ===========================================
/tf                           tf2_msgs/TFMessage            base -> object, base -> each link, base -> ee
/explorer/agents              geometry_msgs/PoseArray       the agents, z along the surface normal (object)
/cloud                        sensor_msgs/PointCloud2       x y z target coverage heat source (float32)
/robot/ee_pose                geometry_msgs/PoseStamped     the tool pose (base)
/robot/wrench                 geometry_msgs/WrenchStamped   the measured wrench (ee)
/robot/wrench_desired         geometry_msgs/WrenchStamped   the desired wrench (ee)
/robot/joint_states           sensor_msgs/JointState        q (rad), dq (rad/s), tau (N m)
============================  ============================  ===========================================

Stamps are the run's simulated time from its start (0 s at the first step); messages are written at
the same times, so ``ros2 bag play --clock`` replays the run at its own pace.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from tergodic_cli.errors import TergodicError
from tergodic_cli.rotations import quat_from_axis
from tergodic_cli.runlog import schema as S
from tergodic_cli.runlog.reader import RunLogData

#: The ROS 2 message definitions the bag's types come from (rosbags' bundled Humble store).
TYPESTORE = "ROS2_HUMBLE"
CLOUD_FIELDS = ("target", "coverage", "heat", "source")
TOPIC_AGENTS = "/explorer/agents"
TOPIC_WRENCH_DESIRED = "/robot/wrench_desired"


def require_rosbags() -> None:
    """A one-line TergodicError when rosbags is not installed."""
    import importlib.util

    if importlib.util.find_spec("rosbags") is None:
        raise TergodicError("--export rosbag2 needs the rosbags package", "pip install rosbags")


def write_rosbag2(data: RunLogData, dest: str | os.PathLike) -> Path:
    """Write ``data`` as a ROS 2 bag (sqlite3 storage, bag version 9) into the new folder ``dest``.

    Parameters
    ----------
    data : RunLogData
        A read run log (with clouds for the /cloud topic).
    dest : path
        The bag folder; it must not exist (the caller builds it aside and swaps it in).

    Returns
    -------
    Path
        ``dest``.
    """
    require_rosbags()
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(getattr(Stores, TYPESTORE))
    T = ts.types
    dest = Path(dest)
    builtin = "builtin_interfaces/msg/Time"

    def stamp(t: float):
        ns = int(round(max(float(t), 0.0) * 1e9))
        return T[builtin](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)

    def header(t: float, frame: str):
        return T["std_msgs/msg/Header"](stamp=stamp(t), frame_id=frame)

    def pose(p) -> object:
        p = np.asarray(p, dtype=np.float64)
        return T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
                                           orientation=T["geometry_msgs/msg/Quaternion"](x=p[3], y=p[4], z=p[5], w=p[6]))

    def transform(t: float, child: str, p) -> object:
        p = np.asarray(p, dtype=np.float64)
        tf = T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](x=p[0], y=p[1], z=p[2]),
                                              rotation=T["geometry_msgs/msg/Quaternion"](x=p[3], y=p[4], z=p[5], w=p[6]))
        return T["geometry_msgs/msg/TransformStamped"](header=header(t, S.FRAME_BASE), child_frame_id=str(child),
                                                       transform=tf)

    def wrench(t: float, w) -> object:
        w = np.asarray(w, dtype=np.float64)
        V = T["geometry_msgs/msg/Vector3"]
        return T["geometry_msgs/msg/WrenchStamped"](
            header=header(t, S.FRAME_EE),
            wrench=T["geometry_msgs/msg/Wrench"](force=V(x=w[0], y=w[1], z=w[2]), torque=V(x=w[3], y=w[4], z=w[5])))

    s = data.series
    times = np.asarray(s["t"], dtype=np.float64)
    with Writer(dest, version=9) as w:
        conns = {}

        def put(topic: str, msgtype: str, t: float, msg) -> None:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=ts)
            w.write(conns[topic], int(round(max(float(t), 0.0) * 1e9)), ts.serialize_cdr(msg, msgtype))

        for i in range(data.steps):
            t = float(times[i])
            poses = [pose([*p, *quat_from_axis(2, n)]) for p, n in zip(s["positions"][i], s["normals"][i])]
            put(TOPIC_AGENTS, "geometry_msgs/msg/PoseArray", t,
                T["geometry_msgs/msg/PoseArray"](header=header(t, S.FRAME_OBJECT), poses=poses))
            sample = data.robot[i] if data.robot and i < len(data.robot) else None
            if sample is None:
                continue
            frames = dict(sample.get("link_poses") or {})
            if sample.get("ee_pose") is not None:
                frames[S.FRAME_EE] = sample["ee_pose"]
                put(S.TOPIC_EE_POSE, "geometry_msgs/msg/PoseStamped", t,
                    T["geometry_msgs/msg/PoseStamped"](header=header(t, S.FRAME_BASE), pose=pose(sample["ee_pose"])))
            if sample.get("object_pose") is not None:
                frames[S.FRAME_OBJECT] = sample["object_pose"]
            if frames:
                put(S.TOPIC_TF, "tf2_msgs/msg/TFMessage", t,
                    T["tf2_msgs/msg/TFMessage"](transforms=[transform(t, k, v) for k, v in frames.items()]))
            for topic, key in ((S.TOPIC_WRENCH, "wrench_measured"), (TOPIC_WRENCH_DESIRED, "wrench_desired")):
                if sample.get(key) is not None:
                    put(topic, "geometry_msgs/msg/WrenchStamped", t, wrench(t, sample[key]))
            if sample.get("q") is not None:
                q = np.asarray(sample["q"], dtype=np.float64).ravel()
                dq, tau = (np.asarray(sample.get(k, np.zeros(len(q))), dtype=np.float64).ravel() for k in ("dq", "tau"))
                names = [str(n) for n in (sample.get("joint_names") or [f"joint{j + 1}" for j in range(len(q))])]
                put(S.TOPIC_JOINTS, "sensor_msgs/msg/JointState", t,
                    T["sensor_msgs/msg/JointState"](header=header(t, S.FRAME_BASE), name=names, position=q,
                                                    velocity=dq, effort=tau))
        for cloud in data.clouds:
            put(S.TOPIC_CLOUD, "sensor_msgs/msg/PointCloud2", cloud.t, _cloud2(T, header(cloud.t, S.FRAME_OBJECT), cloud))
    return dest


def _cloud2(T, hdr, cloud) -> object:
    """A PointCloud2 of ``cloud``: x y z and the fields present, float32, little-endian, dense."""
    names = ["x", "y", "z"] + [f for f in CLOUD_FIELDS if f in cloud.fields]
    cols = [cloud.points[:, 0], cloud.points[:, 1], cloud.points[:, 2]] + [cloud.fields[f] for f in names[3:]]
    table = np.column_stack(cols).astype("<f4")
    PF = T["sensor_msgs/msg/PointField"]
    fields = [PF(name=n, offset=4 * j, datatype=PF.FLOAT32, count=1) for j, n in enumerate(names)]
    return T["sensor_msgs/msg/PointCloud2"](header=hdr, height=1, width=len(table), fields=fields, is_bigendian=False,
                                            point_step=4 * len(names), row_step=4 * len(names) * len(table),
                                            data=np.frombuffer(table.tobytes(), dtype=np.uint8), is_dense=True)


def write_rosbag2_aside(data: RunLogData, dest: str | os.PathLike, tmp: str | os.PathLike) -> None:
    """Write the bag into the (empty) folder ``tmp`` that will become ``dest``: rosbags creates its
    own folder, so it writes ``tmp/bag`` and its files are moved up."""
    tmp = Path(tmp)
    inner = write_rosbag2(data, tmp / "bag")
    for f in inner.iterdir():
        shutil.move(str(f), str(tmp / f.name))
    inner.rmdir()
    if (tmp / "metadata.yaml").exists():  # the bag names its files relative to its folder: unchanged by the move
        return
    raise TergodicError(f"the ROS 2 bag for {dest} was not written", "check free disk space and retry")
