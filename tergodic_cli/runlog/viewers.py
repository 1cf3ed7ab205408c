"""Re-drive viewers from a log: the PyBullet GUI from logged joint states, and a Rerun recording.

Both are optional paths: without a display, or without ``rerun-sdk``, they raise a
one-line :class:`TergodicError` saying so (exit 2 in the CLI).
"""

from __future__ import annotations

import importlib.util
import os
import sys
import time
from pathlib import Path

import numpy as np

from tergodic_cli.errors import TergodicError
from tergodic_cli.runlog.reader import RunLogData


def require_display() -> None:
    """One line (exit 2) unless a GUI window can open (an X or Wayland display on Linux)."""
    screen = os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    fix = "run it on a desktop, or use --plot OUT_DIR / open run.mcap in Foxglove"
    if sys.platform.startswith("linux") and not screen:
        raise TergodicError("no display: --gui needs a screen (DISPLAY is not set)", fix)
    display = os.environ.get("DISPLAY")
    if sys.platform.startswith("linux") and display and not x_server_answers(display):
        # PyBullet ends the whole process when its window cannot open: asked here instead
        raise TergodicError(f"no display: DISPLAY={display} names no X server that answers", fix)


def x_server_answers(display: str, timeout: float = 1.0) -> bool:
    """Whether the X server a ``DISPLAY`` names accepts a connection.

    Parameters
    ----------
    display : str
        ":N", "host:N.S", "unix:N" or "/path/to/socket:N".
    timeout : float
        Seconds to wait for a TCP connection.

    Returns
    -------
    bool
        Its socket in /tmp/.X11-unix (or Linux's abstract one) answers locally, or TCP port
        6000 + N on a host.
    """
    import re
    import socket

    m = re.fullmatch(r"(.*):(\d+)(?:\.\d+)?", display.strip())
    if m is None:
        return False
    host, n = m.group(1), int(m.group(2))
    if host in ("", "unix") or host.startswith("/"):
        paths = [host if host.startswith("/") else f"/tmp/.X11-unix/X{n}"]
        for addr in (paths[0], "\0" + paths[0]):  # the file socket, then Linux's abstract one
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
                sock.settimeout(timeout)
                try:
                    sock.connect(addr)
                    return True
                except OSError:
                    continue
        return False
    try:
        with socket.create_connection((host, 6000 + n), timeout=timeout):
            return True
    except OSError:
        return False


def require_rerun() -> None:
    """One line (exit 2) unless rerun-sdk is installed."""
    if not rerun_available():
        raise TergodicError("rerun-sdk is not installed",
                            "pip install rerun-sdk  (or: pip install 'tergodic[rerun]')")


def joint_series(data: RunLogData) -> tuple[np.ndarray, list[str] | None]:
    """Logged joint positions (T, J) and their names (None when the log does not name them)."""
    if not data.robot or data.robot[0].get("q") is None:
        raise TergodicError(f"{data.path} has no joint states (a kinematic run)", "--gui replays robot runs; use --plot")
    q = np.array([np.asarray(s["q"], dtype=np.float64) for s in data.robot])
    names = data.robot[0].get("joint_names")
    return q, (list(names) if names else None)


def load_arm(client: int, names: list[str] | None = None) -> tuple[int, list[int]]:
    """Load the logged arm's stock URDF from pybullet_data (the simulated arm whose joints are ``names``, the
    log's joint names; else the Panda); returns (body id, its movable joint indices in order)."""
    import pybullet as p
    import pybullet_data

    from tergodic_cli.backends.pybullet.arms import ARMS

    spec = next((a for a in ARMS.values() if names and list(a.joints) == list(names)), ARMS["panda"])
    p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=client)
    body = p.loadURDF(spec.urdf, useFixedBase=True, physicsClientId=client)
    movable = [j for j in range(p.getNumJoints(body, physicsClientId=client))
               if p.getJointInfo(body, j, physicsClientId=client)[2] in (p.JOINT_REVOLUTE, p.JOINT_PRISMATIC)]
    return body, movable


def joint_indices(client: int, body: int, movable: list[int], names: list[str] | None, n: int) -> list[int]:
    """Indices of the logged joints in the body: by name when the log names them, else the first ``n`` movable."""
    import pybullet as p

    if names:
        by_name = {p.getJointInfo(body, j, physicsClientId=client)[1].decode(): j for j in movable}
        if all(name in by_name for name in names):
            return [by_name[name] for name in names]
    if len(movable) < n:
        raise TergodicError(f"the log has {n} joints but the arm model has {len(movable)}", "replay with a matching arm")
    return movable[:n]


def set_joints(client: int, body: int, indices: list[int], q: np.ndarray) -> None:
    """Put the arm in configuration ``q`` (kinematically; no physics step)."""
    import pybullet as p

    for j, value in zip(indices, q):
        p.resetJointState(body, j, float(value), physicsClientId=client)


def replay_gui(data: RunLogData, speed: float = 1.0) -> int:
    """Open the PyBullet GUI and replay the logged joint states at ``speed`` times real time."""
    q, names = joint_series(data)
    require_display()
    import pybullet as p

    try:
        client = p.connect(p.GUI)
    except Exception as exc:  # pybullet.error: no X server behind DISPLAY, no OpenGL
        raise TergodicError(f"PyBullet could not open its GUI window ({exc})", "check the display, or use --plot OUT_DIR") from None
    if client < 0:
        raise TergodicError("PyBullet could not open its GUI window", "check the display, or use --plot OUT_DIR")
    try:
        body, movable = load_arm(client, names)
        idx = joint_indices(client, body, movable, names, q.shape[1])
        cloud = data.clouds[-1] if data.clouds else None
        obj = data.robot[0].get("object_pose")
        if cloud is not None and obj is not None:  # show the object where the robot saw it
            from scipy.spatial.transform import Rotation

            obj = np.asarray(obj, dtype=np.float64)
            pts = Rotation.from_quat(obj[3:7]).apply(cloud.points) + obj[:3]
            cov = cloud.fields.get("coverage", np.zeros(len(pts)))
            c = np.clip(cov / (cov.max() or 1.0), 0, 1)
            p.addUserDebugPoints(pts.tolist(), np.column_stack([c, 0.3 * np.ones_like(c), 1 - c]).tolist(),
                                 pointSize=2, physicsClientId=client)
        t = np.array([s.get("t_sim", i) for i, s in enumerate(data.robot)], dtype=np.float64)
        start = time.monotonic()
        for i in range(len(q)):
            set_joints(client, body, idx, q[i])
            time.sleep(max(0.0, (t[i] - t[0]) / max(speed, 1e-6) - (time.monotonic() - start)))
    finally:
        p.disconnect(client)
    return 0


def rerun_available() -> bool:
    return importlib.util.find_spec("rerun") is not None


_FORCE_M_PER_N = 0.005  # arrow length per newton, as the log's /robot/wrench_scene


def _transform(rr, pose) -> object:
    """A Rerun transform from a pose x y z qx qy qz qw (parent frame: the robot base)."""
    p = np.asarray(pose, dtype=np.float64)
    return rr.Transform3D(translation=p[:3], quaternion=rr.Quaternion(xyzw=p[3:7]))


def _log_robot_sample(rr, rec, sample: dict) -> None:
    """One robot sample: link and tool transforms, the arm's skeleton, the object's pose, the wrench arrows."""
    axes = getattr(rr, "TransformAxes3D", None)  # rerun >= 0.27 draws frame axes with its own archetype
    links = sample.get("link_poses") or {}
    for name, pose in links.items():
        rec.log(f"arm/{name}", _transform(rr, pose))
        if axes is not None:
            rec.log(f"arm/{name}", axes(axis_length=0.05))
    if len(links) > 1:
        rec.log("arm/skeleton", rr.LineStrips3D([np.array([np.asarray(p)[:3] for p in links.values()])],
                                                 colors=[200, 200, 200], radii=0.004))
    if sample.get("object_pose") is not None:
        rec.log("object", _transform(rr, sample["object_pose"]))
    if sample.get("ee_pose") is None:
        return
    rec.log("arm/ee", _transform(rr, sample["ee_pose"]))
    for key, colour in (("wrench_measured", [255, 50, 50]), ("wrench_desired", [50, 255, 50])):
        w = sample.get(key)
        if w is not None:  # force in the tool frame, as logged
            f = np.asarray(w, dtype=np.float64)[:3] * _FORCE_M_PER_N
            rec.log(f"arm/ee/{key}", rr.Arrows3D(origins=[[0.0, 0.0, 0.0]], vectors=[f], colors=[colour]))


def write_rerun(data: RunLogData, dest: str | os.PathLike) -> Path:
    """Write a Rerun recording (``.rrd``): the metrics over steps, the agents, and every cloud; for robot
    runs also the arm (a transform per link and the tool ``arm/ee``, in the base frame = the root), the
    cloud where the robot saw it (``object`` placed by ``object_pose``) and the wrench as arrows."""
    require_rerun()
    import rerun as rr

    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream("tergodic_replay")
    tmp = dest.with_name(f".{dest.name}.tmp")
    rec.save(str(tmp))

    s = data.series
    keys = [k for k in ("ergodicity", "residual_ref", "touched_fraction", "step_ms") if k in s]
    clouds = {c.step: c for c in data.clouds}
    rs = data.robot_series()
    for i, step in enumerate(s["step"].tolist()):
        rec.set_time("step", sequence=int(step))
        for k in keys:
            rec.log(f"metrics/{k}", rr.Scalars(float(s[k][i])))
        if "positions" in s and s["positions"].dtype != object:
            rec.log("object/agents", rr.Points3D(s["positions"][i], radii=0.002, colors=[0, 180, 255]))
        if "force_normal" in rs:
            rec.log("robot/force_normal", rr.Scalars(float(rs["force_normal"][i])))
        if (c := clouds.get(step)) is not None:
            cov = c.fields.get("coverage", np.zeros(len(c.points)))
            tgt = c.fields.get("target", np.zeros(len(c.points)))
            g = np.clip(cov / (cov.max() or 1.0), 0, 1)
            colors = np.column_stack([tgt, g, 1 - g]) * 255
            rec.log("object/cloud", rr.Points3D(c.points, colors=colors.astype(np.uint8), radii=0.0008))
    for sample in data.robot or ():
        if "step" in sample:
            rec.set_time("step", sequence=int(sample["step"]))
            _log_robot_sample(rr, rec, sample)
    rec.flush()  # blocks until everything is in the file
    rec.disconnect()
    os.replace(tmp, dest)
    return dest
