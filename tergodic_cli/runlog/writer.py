"""Write one exploration run, step by step, into a chunked, indexed MCAP file.

Every channel is protobuf: visual topics use Foxglove's schemas through foxglove-sdk's typed channels;
the numbers replay needs are float64 as the explorer and the robot produced them (``tergodic.StepRecord``,
``tergodic.RobotSample``: runlog/proto.py), so ``tergodic replay`` recomputes ``summary.json`` bit for bit.
Each message's log time is the wall clock when it is written; its simulated time is in the message
(the stamps, the records' ``t``). The file is written in place and flushed every few steps (crash
safety: docs/logging.md).
"""

from __future__ import annotations

import json
import math
import os
import time
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from tergodic_cli.atomic import _json_default
from tergodic_cli.errors import TergodicError
from tergodic_cli.rotations import quat_from_axis
from tergodic_cli.runlog import schema as S
from tergodic_cli.runlog.proto import METRIC_FIELDS, VECTOR_FIELDS

#: Default cadence of chunk flushes, in explorer steps.
FLUSH_EVERY = 50
#: Upper bound on a chunk's uncompressed size; a chunk is also closed at every flush.
CHUNK_BYTES = 4 * 1024 * 1024


def _dumps(obj: Any) -> str:
    return json.dumps(obj, default=_json_default, allow_nan=True)


def _quat(M: Any, x: float, y: float, z: float, w: float) -> Any:
    return M.Quaternion(x=x, y=y, z=z, w=w)


def _stamp(M: Any, t_ns: int) -> Any:
    return M.Timestamp(sec=t_ns // 1_000_000_000, nsec=t_ns % 1_000_000_000)


class RunLog:
    """Log an exploration run into ``path`` (an MCAP file), one call per explorer step.

    Parameters
    ----------
    path : path-like
        The MCAP file to write, normally ``RUN_DIR/run.mcap``. It is written in place
        (a killed run keeps its log); an existing file is replaced.
    config : dict
        The run config (JSON-serialisable), stored as metadata ``config`` and used by
        ``tergodic replay`` to recompute the summary.
    seed : int
        The run's seed (metadata ``seed``).
    versions : dict
        Library versions (metadata ``versions``), e.g. ``provenance.library_versions()``.
    capture_sidecar : dict or None
        The capture's ``capture.json``; stored as the attachment ``capture.json``.
    points : (n, 3) float array, metres
        The cloud, in the object frame; every point cloud message carries it.
    target : (n,) float array
        The target weight p; the default for :meth:`log_cloud`'s ``target``.
    cloud_every : int
        How often the caller logs the cloud (recorded for readers; the caller decides).
    compression : {"lz4", "zstd"}
        Chunk compression. lz4 (default) compresses a cloud about twice as fast as zstd at
        level 1, for files about 20 % larger (measured on the bunny).
    flush_every : int or None
        Close the chunk and flush the file every this many steps (default ``min(cloud_every, 50)``).
        A run killed with SIGKILL loses at most the steps since the last flush.
    flush_seconds : float
        Also flush when this much wall time has passed since the last flush (slow robot steps).
    time_origin_ns : int or None
        Unix time (ns) of simulated time 0: every message's stamp is this plus the simulated time
        (default: now). Stored in metadata ``tergodic`` as ``time_origin_ns``. Log times are the
        wall clock when each message is written, whatever this is.
    live : str, (host, port), LiveServer or None
        Also stream every message to Foxglove over WebSocket: ``"HOST:PORT"`` or ``(host, port)``
        starts a server for this log (stopped at close); a
        :class:`~tergodic_cli.runlog.live.LiveServer` is used as is.

    Notes
    -----
    Each message is encoded by foxglove-sdk when it is logged and goes to the file (and to a
    live server's clients). Use it as a context manager: leaving the block closes the log with
    the status ``ok``, ``interrupted`` (Ctrl-C) or ``error: <type>``. Write errors surface as a
    :class:`TergodicError`.
    """

    def __init__(self, path: str | os.PathLike, *, config: Mapping[str, Any], seed: int | None,
                 versions: Mapping[str, Any] | None = None, capture_sidecar: Mapping[str, Any] | None = None,
                 points: np.ndarray, target: np.ndarray | None = None, cloud_every: int = 50,
                 compression: str = "lz4", flush_every: int | None = None, flush_seconds: float = 2.0,
                 time_origin_ns: int | None = None, live: Any = None):
        import foxglove
        from foxglove import channels as C
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions

        from tergodic_cli import __version__ as tergodic_version
        from tergodic_cli.runlog.live import LiveServer
        from tergodic_cli.runlog.proto import (FULL_NAME, ROBOT_SAMPLE, WRENCH, robot_schema, step_record_class,
                                               step_record_schema)

        self.path = Path(path)
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
            raise TergodicError(f"run log needs points of shape (n, 3), got {pts.shape}", "pass basis.points")
        n = len(pts)
        target = np.zeros(n) if target is None else np.asarray(target, dtype=np.float64)
        if target.shape != (n,):
            raise TergodicError(f"run log target has shape {target.shape}, expected ({n},)", "pass the per-point target p")
        if compression not in ("zstd", "lz4"):
            raise TergodicError(f"unknown log compression '{compression}'", "use zstd or lz4")
        if int(cloud_every) < 1:
            raise TergodicError(f"--log-cloud-every must be >= 1, got {cloud_every}", "e.g. --log-cloud-every 50")
        self.cloud_every = int(cloud_every)
        self.flush_every = max(1, int(flush_every) if flush_every else min(self.cloud_every, FLUSH_EVERY))
        self.flush_seconds = float(flush_seconds)
        self.points, self.target = pts, target
        self.n_steps = self.n_clouds = self._since_flush = 0
        self._closed, self._last_t, self._last_flush = False, 0.0, time.monotonic()
        # stamps: origin + simulated t (the run's own clock); log times: the wall clock when written
        self.time_origin_ns = time.time_ns() if time_origin_ns is None else int(time_origin_ns)
        self._log_ns = 0  # the last log time handed out (they never decrease within the file)
        self._line_half = 0.25 * float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))  # the drawn normal line
        self._cloud_buf = np.empty((n, 3 + len(S.CLOUD_FIELDS)), dtype=np.float32)
        self._cloud_buf[:, :3] = pts
        self._Record = step_record_class()

        self.live = None
        if live is not None and not isinstance(live, LiveServer):  # "HOST:PORT": a server of our own, stopped at close
            live = self.live = LiveServer.start(live)
        # a context private to this log (channels never leak into another sink); with a live server, the
        # server's: each message is encoded once and goes to the file and to connected clients
        ctx = live.context if live is not None else foxglove.Context()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # zstd level 1: clouds compress ~30% faster than at the default 3, for ~1% more bytes (measured)
        opts = MCAPWriteOptions(compression=MCAPCompression.Zstd if compression == "zstd" else MCAPCompression.Lz4,
                                profile=S.PROFILE, chunk_size=CHUNK_BYTES, compression_threads=0,
                                compression_level=1 if compression == "zstd" else 0)
        try:  # written in place (not temp+rename): a killed run must leave its log behind
            self._w = foxglove.open_mcap(str(self.path), allow_overwrite=True, context=ctx, writer_options=opts)
        except OSError as exc:
            self._stop_live()
            raise TergodicError(f"cannot write {self.path}: {exc}", "check the folder exists and is writable") from None

        def raw(topic: str, name: str, encoding: str, data: bytes, message_encoding: str) -> Any:
            schema = foxglove.Schema(name=name, encoding=encoding, data=data)
            return foxglove.Channel(topic, schema=schema, message_encoding=message_encoding, context=ctx)

        self._raw = raw

        def pb(topic: str, name: str) -> Any:
            return raw(topic, name, "protobuf", robot_schema(name), "protobuf")

        self._ch = {
            S.TOPIC_METRICS: raw(S.TOPIC_METRICS, FULL_NAME, "protobuf", step_record_schema(), "protobuf"),
            S.TOPIC_AGENT_POSES: C.PosesInFrameChannel(S.TOPIC_AGENT_POSES, context=ctx),
            S.TOPIC_AGENT_SCENE: C.SceneUpdateChannel(S.TOPIC_AGENT_SCENE, context=ctx),
            S.TOPIC_CLOUD: C.PointCloudChannel(S.TOPIC_CLOUD, context=ctx),
            S.TOPIC_EVENTS: C.LogChannel(S.TOPIC_EVENTS, context=ctx),
        }
        self._robot_channels = lambda: {
            S.TOPIC_ROBOT_SAMPLE: pb(S.TOPIC_ROBOT_SAMPLE, ROBOT_SAMPLE),
            S.TOPIC_WRENCH: pb(S.TOPIC_WRENCH, WRENCH),
            S.TOPIC_EE_POSE: C.PoseInFrameChannel(S.TOPIC_EE_POSE, context=ctx),
            S.TOPIC_TF: C.FrameTransformChannel(S.TOPIC_TF, context=ctx),
            S.TOPIC_JOINTS: C.JointStatesChannel(S.TOPIC_JOINTS, context=ctx),
            S.TOPIC_WRENCH_SCENE: C.SceneUpdateChannel(S.TOPIC_WRENCH_SCENE, context=ctx),
        }  # made at the first robot sample: a kinematic log has none of these channels

        info = {"log_schema_version": S.LOG_SCHEMA_VERSION, "writer": f"tergodic {tergodic_version}",
                "frame_object": S.FRAME_OBJECT, "frame_base": S.FRAME_BASE, "cloud_every": str(self.cloud_every),
                "flush_every": str(self.flush_every), "n_points": str(n), "compression": compression,
                "backend": "foxglove-sdk", "created_unix": repr(time.time()), "time_origin_ns": str(self.time_origin_ns)}
        versions = {str(k): str(v) for k, v in (versions or {}).items()} or {"tergodic": tergodic_version}
        with self._writing():
            self._w.write_metadata(S.META_TERGODIC, info)
            self._w.write_metadata(S.META_CONFIG, {"json": _dumps(dict(config))})
            self._w.write_metadata(S.META_SEED, {"seed": "none" if seed is None else str(int(seed))})
            self._w.write_metadata(S.META_VERSIONS, versions)
            if capture_sidecar is not None:
                now = self._now_ns()
                self._w.attach(log_time=now, create_time=now,
                               name=S.ATTACHMENT_SIDECAR, media_type="application/json",
                               data=_dumps(dict(capture_sidecar)).encode())
            self._w.flush()  # the version marker and config are on disk before the first step

    # -- plumbing ------------------------------------------------------------------------------
    @contextmanager
    def _writing(self) -> Iterator[None]:
        """Turns an I/O failure of the SDK's writer into one TergodicError; the log is then closed."""
        try:
            yield
        except (OSError, RuntimeError) as exc:
            self._closed = True
            with suppress(Exception):  # best effort on the error path
                self._w.close()
            self._stop_live()
            raise TergodicError(f"writing {self.path} failed: {exc}", "check free disk space and permissions") from None

    def _stop_live(self) -> None:
        if self.live is not None:
            self.live.stop()
            self.live = None

    def _require_open(self) -> None:
        if self._closed:
            raise TergodicError(f"the run log {self.path} is closed", "log steps before close()")

    def _t_ns(self, t: float) -> int:
        """The stamp of simulated time ``t`` (s): ns since the epoch."""
        return self.time_origin_ns + round(float(t) * 1e9)

    def _now_ns(self) -> int:
        """The log time of what is written now: the wall clock, held at the last one if the clock stepped back."""
        self._log_ns = max(time.time_ns(), self._log_ns)
        return self._log_ns

    def sync(self) -> None:
        """Close the chunk in progress and flush the file: what was logged survives a crash from here on."""
        self._require_open()
        with self._writing():
            self._w.flush()
        self._since_flush = 0
        self._last_flush = time.monotonic()

    # -- per step ------------------------------------------------------------------------------
    def log_step(self, step: int, t: float, *, positions: np.ndarray, velocities: np.ndarray,
                 normals: np.ndarray, metrics: Mapping[str, float], step_ms: float,
                 robot: Mapping[str, Any] | None = None) -> None:
        """Log one explorer step.

        Parameters
        ----------
        step : int
            Explorer step index (>= 0).
        t : float
            Simulated time of the step, s (>= 0), kept in the step record and the robot sample; the
            messages' stamps are ``time_origin_ns`` plus this, their log time the wall clock now.
        positions, velocities, normals : (N, 3) float arrays
            Agent positions (m), velocities (m/s) and unit surface normals, object frame.
        metrics : dict
            ``explorer.metrics()``: ergodicity, residual_ref, touched_fraction (any other
            numeric name goes to the record's extra_names / extra_values).
        step_ms : float
            Wall time of the explorer step, ms.
        robot : dict or None
            The robot sample of this step (CONTRACTS.md ``robot_sample_dict``), or None.
        """
        from foxglove import messages as M

        self._require_open()
        t = float(t)
        if step < 0 or not 0.0 <= t < math.inf:
            raise TergodicError(f"run log got step {step} at t = {t}", "steps must be >= 0 and times finite, >= 0")
        P, V, Nn = (np.asarray(a, dtype=np.float64).reshape(-1, 3) for a in (positions, velocities, normals))
        if not (len(P) == len(V) == len(Nn)) or len(P) == 0:
            raise TergodicError(f"run log got {len(P)} positions, {len(V)} velocities, "
                                f"{len(Nn)} normals", "pass (N, 3) arrays for N >= 1 agents")
        t_ns, now = self._t_ns(t), self._now_ns()
        rec = self._Record(step=int(step), t=t, step_ms=float(step_ms), n_agents=len(P))
        for k, v in metrics.items():
            if not isinstance(k, str) or k in ("step", "t", "step_ms"):
                raise TergodicError(f"run log metric name {k!r} is not allowed", "use another name")
            if k in METRIC_FIELDS:
                setattr(rec, k, float(v))
            else:
                rec.extra_names.append(k)
                rec.extra_values.append(float(v))
        for name, A in zip(VECTOR_FIELDS, (P, V, Nn)):
            getattr(rec, name).extend(A.ravel().tolist())
        stamp = _stamp(M, t_ns)
        half = self._line_half
        shaft_d = 0.02 * half + 1e-4
        poses, entities = [], []
        for i, (p, v, nrm) in enumerate(zip(P.tolist(), V.tolist(), Nn.tolist())):
            pos = M.Vector3(x=p[0], y=p[1], z=p[2])
            poses.append(M.Pose(position=pos, orientation=_quat(M, *quat_from_axis(2, nrm))))  # z along the normal
            speed = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
            line = M.LinePrimitive(type=M.LinePrimitiveLineType.LineList, pose=M.Pose(orientation=M.Quaternion(w=1.0)),
                                   thickness=2.0, scale_invariant=True, color=M.Color(r=0.1, g=0.8, b=1.0, a=1.0),
                                   points=[M.Point3(x=p[0] + s * nrm[0], y=p[1] + s * nrm[1], z=p[2] + s * nrm[2])
                                           for s in (-half, half)])
            arrow = M.ArrowPrimitive(pose=M.Pose(position=pos, orientation=_quat(M, *quat_from_axis(0, v))),
                                     shaft_length=min(5.0 * speed, half), shaft_diameter=shaft_d,  # 5 s of travel
                                     head_length=3 * shaft_d, head_diameter=3 * shaft_d,
                                     color=M.Color(r=1.0, g=0.5, b=0.0, a=1.0))
            entities.append(M.SceneEntity(timestamp=stamp, frame_id=S.FRAME_OBJECT, id=f"agent{i:04d}",
                                          frame_locked=True, lines=[line], arrows=[arrow]))
        with self._writing():
            self._ch[S.TOPIC_METRICS].log(rec.SerializeToString(), log_time=now)
            self._ch[S.TOPIC_AGENT_POSES].log(M.PosesInFrame(timestamp=stamp, frame_id=S.FRAME_OBJECT, poses=poses),
                                              log_time=now)
            self._ch[S.TOPIC_AGENT_SCENE].log(M.SceneUpdate(entities=entities), log_time=now)
            if robot is not None:
                self._log_robot(int(step), t_ns, now, stamp, robot)
        self.n_steps += 1
        self._last_t = t
        self._since_flush += 1
        if self._since_flush >= self.flush_every or (
                self.flush_seconds > 0 and time.monotonic() - self._last_flush >= self.flush_seconds):
            self.sync()

    def _log_robot(self, step: int, t_ns: int, now: int, stamp: Any, robot: Mapping[str, Any]) -> None:
        """The robot sample's messages, stamped ``t_ns`` (simulated time) and logged at ``now`` (wall clock)."""
        from foxglove import messages as M

        from tergodic_cli.runlog.proto import encode_sample, encode_wrench

        if S.TOPIC_TF not in self._ch:
            self._ch.update(self._robot_channels())
        ch = self._ch
        ch[S.TOPIC_ROBOT_SAMPLE].log(encode_sample({"step": step, **robot}, t_ns), log_time=now)
        frames = dict(robot.get("link_poses") or {})
        ee = robot.get("ee_pose")
        if ee is not None:
            ee = frames[S.FRAME_EE] = np.asarray(ee, dtype=np.float64).tolist()
            pose = M.Pose(position=M.Vector3(x=ee[0], y=ee[1], z=ee[2]), orientation=_quat(M, *ee[3:7]))
            ch[S.TOPIC_EE_POSE].log(M.PoseInFrame(timestamp=stamp, frame_id=S.FRAME_BASE, pose=pose), log_time=now)
        if robot.get("object_pose") is not None:  # where the capture frame sits in the base frame
            frames[S.FRAME_OBJECT] = robot["object_pose"]
        for child, pose in frames.items():
            p = np.asarray(pose, dtype=np.float64).tolist()
            ch[S.TOPIC_TF].log(M.FrameTransform(timestamp=stamp, parent_frame_id=S.FRAME_BASE, child_frame_id=str(child),
                                                translation=M.Vector3(x=p[0], y=p[1], z=p[2]),
                                                rotation=_quat(M, *p[3:7])), log_time=now)
        q = robot.get("q")
        if q is not None:
            q = np.asarray(q, dtype=np.float64).ravel().tolist()
            dq, tau = (np.asarray(robot.get(k, np.zeros(len(q))), dtype=np.float64).ravel().tolist() for k in ("dq", "tau"))
            names = list(robot.get("joint_names") or [f"joint{i + 1}" for i in range(len(q))])
            joints = [M.JointState(name=str(name), position=a, velocity=b, effort=c)
                      for name, a, b, c in zip(names, q, dq, tau)]
            ch[S.TOPIC_JOINTS].log(M.JointStates(timestamp=stamp, joints=joints), log_time=now)
        wm, wd = robot.get("wrench_measured"), robot.get("wrench_desired")
        if wm is None and wd is None:
            return
        entities = []
        for key, w, (r, g, b) in (("measured", wm, (1.0, 0.2, 0.2)), ("desired", wd, (0.2, 1.0, 0.2))):
            if w is None:
                continue
            w = np.asarray(w, dtype=np.float64).ravel().tolist()
            fn = math.sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2)
            arrows = [] if fn <= 1e-9 else [M.ArrowPrimitive(  # 5 mm per newton
                pose=M.Pose(orientation=_quat(M, *quat_from_axis(0, w[:3]))), shaft_length=0.005 * fn,
                shaft_diameter=0.002, head_length=0.006, head_diameter=0.006, color=M.Color(r=r, g=g, b=b, a=1.0))]
            entities.append(M.SceneEntity(timestamp=stamp, frame_id=S.FRAME_EE, id=f"force_{key}", arrows=arrows))
        ch[S.TOPIC_WRENCH].log(encode_wrench(step, t_ns, wm, wd, robot.get("force_normal"), robot.get("in_contact")),
                               log_time=now)
        ch[S.TOPIC_WRENCH_SCENE].log(M.SceneUpdate(entities=entities), log_time=now)

    def log_robot_record(self, kind: str, step: int, t: float, record: Mapping[str, Any]) -> None:
        """Log one of the robot's own records (``ContactRun``'s ``on_log``): kind "phase" (a state
        transition, ``tergodic.RobotPhase`` on /robot/phase) or "force" (a window of 1 kHz ticks,
        ``tergodic.ForceWindow`` on /robot/force), at explorer step ``step`` and simulated time ``t``
        (s, the explorer's time base, like the events; the records carry the robot's own time ``t``),
        logged at the wall clock."""
        from tergodic_cli.runlog.proto import FORCE_WINDOW, ROBOT_PHASE, encode_record, record_schema

        self._require_open()
        topic, name = {"phase": (S.TOPIC_ROBOT_PHASE, ROBOT_PHASE), "force": (S.TOPIC_ROBOT_FORCE, FORCE_WINDOW)}[kind]
        with self._writing():
            if topic not in self._ch:  # made at the first record: a kinematic log has none
                self._ch[topic] = self._raw(topic, name, "protobuf", record_schema(name), "protobuf")
            self._ch[topic].log(encode_record(name, {**record, "step": int(step)}), log_time=self._now_ns())

    # -- every K steps -------------------------------------------------------------------------
    def log_cloud(self, step: int, *, coverage: np.ndarray, heat: np.ndarray, source: np.ndarray,
                  target: np.ndarray | None = None, t: float | None = None) -> None:
        """Log the cloud with per-point target p, coverage c, heat u and source s, each (n,).

        ``target`` None repeats the last target logged (the one given at open, or by an earlier
        cloud). ``t`` (simulated s, the message's stamp) defaults to the time of the last logged step. The message is a
        ``foxglove.PointCloud`` with float32 fields x y z target coverage heat source, in a
        chunk of its own that is on disk when this returns.
        """
        from foxglove import messages as M

        self._require_open()
        n = len(self.points)
        buf = self._cloud_buf
        if target is not None and np.shape(target) == (n,):  # the target from now on (a re-capture changed it)
            self.target = np.array(target, dtype=np.float64)
        for col, name, values in ((3, "target", self.target if target is None else target),
                                  (4, "coverage", coverage), (5, "heat", heat), (6, "source", source)):
            if np.shape(values) != (n,):
                raise TergodicError(f"run log cloud field {name} has shape {np.shape(values)}, expected ({n},)",
                                    "pass one value per point")
            buf[:, col] = values
        t_ns = self._t_ns(self._last_t if t is None else t)
        F32 = M.PackedElementFieldNumericType.Float32
        msg = M.PointCloud(timestamp=_stamp(M, t_ns), frame_id=S.FRAME_OBJECT,
                           # a full pose: Rerun's converter needs the position present
                           pose=M.Pose(position=M.Vector3(x=0.0, y=0.0, z=0.0), orientation=M.Quaternion(w=1.0)),
                           point_stride=4 * buf.shape[1], data=buf.tobytes(),
                           fields=[M.PackedElementField(name=name, offset=4 * i, type=F32)
                                   for i, name in enumerate(("x", "y", "z") + S.CLOUD_FIELDS)])
        self.sync()  # the steps before the cloud, in their own chunk
        with self._writing():
            self._ch[S.TOPIC_CLOUD].log(msg, log_time=self._now_ns())
        self.n_clouds += 1
        self.sync()

    def log_event(self, step: int, t: float, text: str) -> None:
        """Log a state-machine transition or warning as a ``foxglove.Log`` ("step N: text") stamped with
        simulated time ``t`` (s)."""
        from foxglove import messages as M

        self._require_open()
        t_ns = self._t_ns(t)
        msg = M.Log(timestamp=_stamp(M, t_ns), level=M.LogLevel.Info, name="tergodic",
                    message=f"step {int(step)}: {text}")
        with self._writing():
            self._ch[S.TOPIC_EVENTS].log(msg, log_time=self._now_ns())

    # -- end -----------------------------------------------------------------------------------
    def close(self, summary: Mapping[str, Any] | None = None, status: str = "ok", hold=None) -> None:
        """Store ``summary`` (the summary.json dict) and finish the file; idempotent. ``hold()``, when
        given, runs once the file is complete and before the live channels close (``--live-wait``)."""
        if self._closed:
            return
        try:
            with self._writing():
                if summary is not None:
                    self._w.write_metadata(S.META_SUMMARY, {"json": _dumps(dict(summary))})
                self._w.write_metadata(S.META_END, {"steps": str(self.n_steps), "clouds": str(self.n_clouds),
                                                    "status": status})
                self._w.close()
            if hold is not None:
                hold()
        finally:
            self._closed = True
            for ch in self._ch.values():
                ch.close()
            self._stop_live()

    def __enter__(self) -> "RunLog":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            return self.close(None)
        status = "interrupted" if issubclass(exc_type, KeyboardInterrupt) else f"error: {exc_type.__name__}"
        with suppress(TergodicError):  # the original exception matters more
            self.close(None, status=status)
