"""Write one exploration run, step by step, into a chunked, indexed MCAP file.

Visual topics use Foxglove's well-known protobuf schemas so Foxglove and Rerun
open the file as it is. The numbers replay needs are float64 exactly as the
explorer produced them: protobuf ``double`` in ``tergodic.StepRecord`` (proto.py),
and JSON for the robot samples (Python's ``repr`` round-trips a float64), so
``tergodic replay`` recomputes ``summary.json`` bit for bit.

Crash safety: the file is written in place. Every ``flush_every`` steps (or
``flush_seconds`` of wall time, whichever comes first) the pending steps are
written as one chunk and the file is flushed to the OS; each point cloud gets a
chunk of its own, on disk at once. A run killed with SIGKILL therefore loses at
most the steps since the last flush, and the reader recovers everything before.

Speed: a step is copied into preallocated arrays (a few microseconds); the steps
of a chunk are encoded together from serialized templates (:mod:`wire`) and
handed to foxglove-sdk's native MCAP writer (about 1 µs a message; chunking and
compression in native code). Without foxglove-sdk, the pure-Python ``mcap``
writer writes the same layout, about 10x slower per message.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from tergodic_cli.errors import TergodicError
from tergodic_cli.runlog import schema as S

#: Default cadence of chunk flushes, in explorer steps.
FLUSH_EVERY = 50
#: Upper bound on a chunk's uncompressed size; a chunk is also closed at every flush.
CHUNK_BYTES = 4 * 1024 * 1024


def _proto_classes() -> dict[str, Any]:
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
    from foxglove_schemas_protobuf.JointStates_pb2 import JointStates
    from foxglove_schemas_protobuf.Log_pb2 import Log
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
    from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    return {
        S.TOPIC_AGENT_POSES: PosesInFrame,
        S.TOPIC_AGENT_SCENE: SceneUpdate,
        S.TOPIC_EE_POSE: PoseInFrame,
        S.TOPIC_TF: FrameTransform,
        S.TOPIC_JOINTS: JointStates,
        S.TOPIC_WRENCH_SCENE: SceneUpdate,
        S.TOPIC_CLOUD: PointCloud,
        S.TOPIC_EVENTS: Log,
    }


#: JSON topics and their JSON-schema title.
_JSON_TOPICS = {
    S.TOPIC_ROBOT_SAMPLE: "tergodic.RobotSample",
    S.TOPIC_WRENCH: "tergodic.Wrench",
}


# ---------------------------------------------------------------------------------------------
# Backends: who turns (topic, time, bytes) into MCAP records. Both write the same file layout.
# ---------------------------------------------------------------------------------------------
def _schema_for(topic: str, classes: dict[str, Any]) -> tuple[str, str, bytes, str]:
    """(schema name, schema encoding, schema data, message encoding) of a topic."""
    if topic in _JSON_TOPICS:
        title = _JSON_TOPICS[topic]
        return title, "jsonschema", json.dumps(S.JSON_SCHEMAS[title]).encode(), "json"
    if topic == S.TOPIC_METRICS:
        from tergodic_cli.runlog.proto import FULL_NAME, step_record_schema

        return FULL_NAME, "protobuf", step_record_schema(), "protobuf"
    cls = classes[topic]
    return cls.DESCRIPTOR.full_name, "protobuf", _file_descriptor_set(cls), "protobuf"


def _file_descriptor_set(cls: Any) -> bytes:
    """The serialized FileDescriptorSet of a message class: its .proto file after every dependency."""
    from google.protobuf.descriptor_pb2 import FileDescriptorSet

    fds, seen = FileDescriptorSet(), set()

    def add(fd: Any) -> None:
        for dep in fd.dependencies:
            if dep.name not in seen:
                seen.add(dep.name)
                add(dep)
        fd.CopyToProto(fds.file.add())

    add(cls.DESCRIPTOR.file)
    return fds.SerializeToString()


def foxglove_sdk_available() -> bool:
    try:
        import foxglove  # noqa: F401
        from foxglove.mcap import MCAPWriteOptions  # noqa: F401
    except ImportError:
        return False
    return True


class _FoxgloveBackend:
    """foxglove-sdk's native MCAP writer: about 1 µs per message, compression in native code."""

    name = "foxglove-sdk"

    def __init__(self, path: Path, compression: str, chunk_bytes: int, classes: dict[str, Any], live: Any = None):
        import foxglove
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions

        from tergodic_cli.runlog.live import LiveServer

        self._foxglove = foxglove
        self._classes = classes
        self._own_live = None
        if live is not None and not isinstance(live, LiveServer):  # "HOST:PORT": a server of our own
            live = self._own_live = LiveServer.start(live)
        # private to this log (channels never leak into another sink); with a live server, the
        # server's context: every message goes to the file and to connected clients, encoded once
        self.ctx = live.context if live is not None else foxglove.Context()
        comp = {"zstd": MCAPCompression.Zstd, "lz4": MCAPCompression.Lz4}[compression]
        # zstd level 1: clouds compress ~30% faster than at the default 3, for ~1% more bytes (measured)
        level = 1 if compression == "zstd" else 0
        opts = MCAPWriteOptions(compression=comp, profile=S.PROFILE, chunk_size=chunk_bytes, compression_threads=0,
                                compression_level=level)
        # written in place (not temp+rename): a killed run must leave its log behind
        self.writer = foxglove.open_mcap(str(path), allow_overwrite=True, context=self.ctx, writer_options=opts)
        self._channels: dict[str, Any] = {}

    def _channel(self, topic: str) -> Any:
        ch = self._channels.get(topic)
        if ch is None:
            name, enc, data, menc = _schema_for(topic, self._classes)
            schema = self._foxglove.Schema(name=name, encoding=enc, data=data)
            ch = self._foxglove.Channel(topic, schema=schema, message_encoding=menc, context=self.ctx)
            self._channels[topic] = ch
        return ch

    def write_many(self, msgs: list) -> None:
        for topic, t_ns, _seq, data in msgs:  # the SDK numbers messages per channel itself
            ch = self._channels.get(topic) or self._channel(topic)
            ch.base.log(data, t_ns)  # the raw channel: bytes in, no per-call type checks

    def logger(self, topic: str) -> Any:
        """A callable ``(data, t_ns)`` writing one message on ``topic``."""
        return (self._channels.get(topic) or self._channel(topic)).base.log

    def flush(self) -> None:
        self.writer.flush()  # closes the chunk in progress and flushes the file

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self.writer.write_metadata(name, data)

    def attach(self, name: str, media_type: str, data: bytes, t_ns: int) -> None:
        self.writer.attach(log_time=t_ns, create_time=t_ns, name=name, media_type=media_type, data=data)

    def finish(self) -> None:
        self.writer.close()
        for ch in self._channels.values():
            ch.close()
        if self._own_live is not None:
            self._own_live.stop()

    def abort(self) -> None:
        try:
            self.writer.close()
        except Exception:  # noqa: BLE001 - best effort on the error path
            pass
        if self._own_live is not None:
            self._own_live.stop()


class _McapPythonBackend:
    """The pure-Python ``mcap`` writer (about 10 µs per message); used when foxglove-sdk is absent."""

    name = "mcap-python"

    def __init__(self, path: Path, compression: str, chunk_bytes: int, classes: dict[str, Any], live: Any = None):
        from mcap.writer import CompressionType, IndexType, Writer

        if live is not None:
            raise TergodicError("a live view needs foxglove-sdk's writer", "pip install foxglove-sdk, or drop --live")

        from tergodic_cli import __version__ as tergodic_version

        self._classes = classes
        self.fh = open(path, "wb")  # in place, not temp+rename: a killed run must leave its log behind
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}[compression]
        self.writer = Writer(self.fh, chunk_size=chunk_bytes, compression=comp, index_types=IndexType.ALL,
                             repeat_channels=True, repeat_schemas=True, use_chunking=True, use_statistics=True,
                             use_summary_offsets=True, enable_crcs=True)
        self.writer.start(profile=S.PROFILE, library=f"tergodic/{tergodic_version}")
        self._can_flush = hasattr(self.writer, "flush")  # mcap >= 1.5 closes the open chunk on demand
        self._channels: dict[str, int] = {}

    def _channel(self, topic: str) -> int:
        name, enc, data, menc = _schema_for(topic, self._classes)
        sid = self.writer.register_schema(name=name, encoding=enc, data=data)
        cid = self.writer.register_channel(topic=topic, message_encoding=menc, schema_id=sid)
        self._channels[topic] = cid
        return cid

    def write_many(self, msgs: list) -> None:
        add = self.writer.add_message
        for topic, t_ns, seq, data in msgs:
            cid = self._channels.get(topic) or self._channel(topic)
            add(channel_id=cid, log_time=t_ns, data=data, publish_time=t_ns, sequence=seq)

    def logger(self, topic: str) -> Any:
        """A callable ``(data, t_ns)`` writing one message on ``topic``."""
        cid = self._channels.get(topic) or self._channel(topic)
        add = self.writer.add_message
        return lambda data, t_ns: add(channel_id=cid, log_time=t_ns, data=data, publish_time=t_ns)

    def flush(self) -> None:
        if self._can_flush:
            self.writer.flush()
        else:  # older mcap: chunks close by size only
            self.fh.flush()

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self.writer.add_metadata(name, data)
        self.fh.flush()

    def attach(self, name: str, media_type: str, data: bytes, t_ns: int) -> None:
        self.writer.add_attachment(create_time=t_ns, log_time=t_ns, name=name, media_type=media_type, data=data)
        self.fh.flush()

    def finish(self) -> None:
        self.writer.finish()
        self.fh.close()

    def abort(self) -> None:
        try:
            self.fh.close()
        except OSError:
            pass


BACKENDS = {"foxglove-sdk": _FoxgloveBackend, "mcap-python": _McapPythonBackend}


# ---------------------------------------------------------------------------------------------
# Helpers.
# ---------------------------------------------------------------------------------------------
_METRIC_FIELDS = frozenset(("ergodicity", "residual_ref", "touched_fraction"))


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, (set, tuple)):
        return list(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def _dumps(obj: Any) -> str:
    return json.dumps(obj, default=_json_default, allow_nan=True)


def _quat_x_to(v: tuple[float, float, float]) -> tuple[float, float, float, float]:
    """Shortest-arc quaternion (x, y, z, w) turning +x onto the unit vector ``v``."""
    x, y, z = v
    w = 1.0 + x
    if w < 1e-9:  # v = -x: half-turn about z
        return 0.0, 0.0, 1.0, 0.0
    # axis = (1,0,0) × v = (0, -z, y)
    n = math.sqrt(w * w + z * z + y * y)
    return 0.0, -z / n, y / n, w / n


def _set_time(stamp: Any, t_ns: int) -> None:
    stamp.seconds, stamp.nanos = divmod(t_ns, 1_000_000_000)


@dataclass(frozen=True)
class SpectralField:
    """A per-point field given as ``field_basis @ coeffs + residual``, evaluated by the log.

    ``coeffs`` (nK,) or None (the field is ``residual`` alone), ``residual`` (n,); the
    ``field_basis`` (n, nK) is the one the log was opened with (``Explorer.evecs``). A run
    log in a writer process then reconstructs the heat there, not in the explorer's loop.
    """

    coeffs: np.ndarray | None
    residual: np.ndarray


def check_field_basis(field_basis: Any, n: int) -> np.ndarray | None:
    """``field_basis`` as a C-contiguous float64 (n, nK) array, or None."""
    if field_basis is None:
        return None
    B = np.ascontiguousarray(field_basis, dtype=np.float64)
    if B.ndim != 2 or B.shape[0] != n:
        raise TergodicError(f"run log field_basis has shape {B.shape}, expected ({n}, nK)", "pass Explorer.evecs")
    return B


def check_spectral_field(f: SpectralField, field_basis: np.ndarray | None, n: int) -> None:
    if np.shape(f.residual) != (n,):
        raise TergodicError(f"run log field residual has shape {np.shape(f.residual)}, expected ({n},)",
                            "pass one value per point")
    if f.coeffs is not None:
        if field_basis is None:
            raise TergodicError("run log got a spectral field but no field_basis", "open the log with field_basis=evecs")
        if np.shape(f.coeffs) != (field_basis.shape[1],):
            raise TergodicError(f"run log field coefficients have shape {np.shape(f.coeffs)}, "
                                f"expected ({field_basis.shape[1]},)", "pass one coefficient per basis vector")


def evaluate_field(values: Any, field_basis: np.ndarray | None, n: int) -> np.ndarray:
    """A cloud field as an (n,) array: ``values`` itself, or a :class:`SpectralField` evaluated."""
    if isinstance(values, SpectralField):
        check_spectral_field(values, field_basis, n)
        r = np.asarray(values.residual, dtype=np.float64)
        return r.copy() if values.coeffs is None else field_basis @ np.asarray(values.coeffs, dtype=np.float64) + r
    return np.asarray(values)


def check_agent_arrays(positions: Any, velocities: Any, normals: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One step's agent positions, velocities and normals as (N, 3) float64 arrays, N >= 1 each."""
    P = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    V = np.asarray(velocities, dtype=np.float64).reshape(-1, 3)
    Nn = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if not (len(P) == len(V) == len(Nn)) or len(P) == 0:
        raise TergodicError(f"run log got {len(P)} positions, {len(V)} velocities, {len(Nn)} normals",
                            "pass (N, 3) arrays for N >= 1 agents")
    return P, V, Nn


def check_log_args(points: Any, target: Any, compression: str, cloud_every: int,
                   backend: str) -> tuple[np.ndarray, np.ndarray, str]:
    """Validate a run log's arguments: (points (n, 3) float64, target (n,) float64, backend name)."""
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
    if backend == "auto":
        backend = "foxglove-sdk" if foxglove_sdk_available() else "mcap-python"
    if backend not in BACKENDS:
        raise TergodicError(f"unknown log backend '{backend}'", f"use one of {', '.join(BACKENDS)}")
    return pts, target, backend


# ---------------------------------------------------------------------------------------------
# The public writer.
# ---------------------------------------------------------------------------------------------
class ClosesOnExit:
    """``with`` support for a run log: leaving the block closes it, with the status ``ok``,
    ``interrupted`` (Ctrl-C) or ``error: <type>``, so even a failed run leaves a readable file.
    Subclasses have ``_closed`` and ``close(summary, status=...)``."""

    _closed: bool

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if self._closed:
            return
        if exc_type is None:
            self.close(None)
            return
        status = "interrupted" if issubclass(exc_type, KeyboardInterrupt) else f"error: {exc_type.__name__}"
        try:
            self.close(None, status=status)
        except TergodicError:
            pass  # the original exception matters more


class AgentRows:
    """Both writers keep pending step rows laid out for one agent count; a new count writes out the
    rows so far (``_flush_pending``) and lays out new ones (``_alloc``)."""

    _n_agents: int

    def _agent_arrays(self, positions, velocities, normals) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The slow path of log_step: validate shapes, (re)allocate for a new agent count."""
        P, V, Nn = check_agent_arrays(positions, velocities, normals)
        if len(P) != self._n_agents:
            self._flush_pending()  # the rows so far keep their own layout
            self._alloc(len(P))
        return P, V, Nn


class RunLog(ClosesOnExit, AgentRows):
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
        Write, close and flush a chunk every this many steps (default ``min(cloud_every, 50)``).
        A run killed with SIGKILL loses at most the steps since the last flush.
    flush_seconds : float
        Also flush when this much wall time has passed since the last flush (slow robot steps).
    backend : {"auto", "foxglove-sdk", "mcap-python"}
        The MCAP writer; "auto" takes foxglove-sdk when installed.
    field_basis : (n, nK) float array or None
        The basis of :class:`SpectralField` cloud fields (``Explorer.evecs``).
    time_origin_ns : int or None
        Unix time (ns) of simulated time 0: every log time is this plus the simulated time
        (default: now). Stored in metadata ``tergodic`` as ``time_origin_ns``.
    live : str, LiveServer or None
        Also stream every message to Foxglove over WebSocket: ``"HOST:PORT"`` starts a server
        for this log (stopped at close), a :class:`~tergodic_cli.runlog.live.LiveServer` is used as is.

    Notes
    -----
    A step is only copied into Python lists; its messages are encoded and written
    with the rest of its chunk (see :mod:`tergodic_cli.runlog.wire`), in step order, each
    with its own log time. Use it as a context manager; ``close(summary)`` stores the summary
    and finishes the file (summary section, indexes, footer). Write errors surface as a
    :class:`TergodicError`.
    """

    def __init__(self, path: str | os.PathLike, *, config: Mapping[str, Any], seed: int | None,
                 versions: Mapping[str, Any] | None = None, capture_sidecar: Mapping[str, Any] | None = None,
                 points: np.ndarray, target: np.ndarray | None = None, cloud_every: int = 50,
                 compression: str = "lz4", flush_every: int | None = None, flush_seconds: float = 2.0,
                 chunk_bytes: int = CHUNK_BYTES, backend: str = "auto", field_basis: np.ndarray | None = None,
                 time_origin_ns: int | None = None, live: Any = None):
        from tergodic_cli import __version__ as tergodic_version

        self.path = Path(path)
        pts, target, backend = check_log_args(points, target, compression, cloud_every, backend)
        self._field_basis = check_field_basis(field_basis, len(pts))
        n = len(pts)
        self.cloud_every = int(cloud_every)
        self.flush_every = max(1, int(flush_every) if flush_every else min(self.cloud_every, FLUSH_EVERY))
        self.flush_seconds = float(flush_seconds)
        self.points = pts
        self.target = target
        self.backend = backend
        self.n_steps = 0
        self.n_clouds = 0
        self._closed = False
        self._last_t = 0.0
        self._last_flush = time.monotonic()
        # log times are wall-clock (viewers place the run in real time): origin + simulated t
        self.time_origin_ns = time.time_ns() if time_origin_ns is None else int(time_origin_ns)
        self._classes = _proto_classes()
        extent = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
        self._line_half = 0.25 * extent  # half-length of the drawn normal line
        # the pending steps: plain lists until their chunk is written (_flush_pending)
        self._rows: list[tuple] = []  # (step, t, ε, ε_ref, touched, step_ms)
        self._rows_tns: list[int] = []  # log times, ns
        self._vecs: list[list] = []  # [positions, velocities, normals] as nested lists
        self._n_agents = -1
        self._shape: tuple = ()
        self._pending: dict[int, list] = {}  # row -> robot and event messages of that step
        self._extras: dict[int, dict] = {}  # row -> metrics of a step with non-standard names
        self._cloud_buf = np.empty((n, 3 + len(S.CLOUD_FIELDS)), dtype=np.float32)
        self._cloud_buf[:, :3] = pts
        self._cloud_msg = self._build_cloud_template(n)

        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._b = BACKENDS[backend](self.path, compression, int(chunk_bytes), self._classes, live)
        except OSError as exc:
            raise TergodicError(f"cannot write {self.path}: {exc}", "check the folder exists and is writable") from None

        info = {"log_schema_version": S.LOG_SCHEMA_VERSION, "writer": f"tergodic {tergodic_version}",
                "frame_object": S.FRAME_OBJECT, "frame_base": S.FRAME_BASE, "cloud_every": str(self.cloud_every),
                "flush_every": str(self.flush_every), "n_points": str(n), "compression": compression,
                "backend": backend, "created_unix": repr(time.time()),
                "time_origin_ns": str(self.time_origin_ns)}
        versions = {str(k): str(v) for k, v in (versions or {}).items()} or {"tergodic": tergodic_version}
        try:
            self._b.metadata(S.META_TERGODIC, info)
            self._b.metadata(S.META_CONFIG, {"json": _dumps(dict(config))})
            self._b.metadata(S.META_SEED, {"seed": "none" if seed is None else str(int(seed))})
            self._b.metadata(S.META_VERSIONS, versions)
            if capture_sidecar is not None:
                self._b.attach(S.ATTACHMENT_SIDECAR, "application/json", _dumps(dict(capture_sidecar)).encode(),
                               self.time_origin_ns)
            self._b.flush()  # the version marker and config are on disk before the first step
        except (OSError, RuntimeError) as exc:
            self._fail(exc)

    # -- plumbing ------------------------------------------------------------------------------
    def _fail(self, exc: BaseException) -> None:
        """Turn an I/O failure of the writer into one TergodicError (the log is then closed)."""
        self._closed = True
        self._b.abort()
        raise TergodicError(f"writing {self.path} failed: {exc}", "check free disk space and permissions") from None

    def _require_open(self) -> None:
        if self._closed:
            raise TergodicError(f"the run log {self.path} is closed", "log steps before close()")

    def _alloc(self, n_agents: int) -> None:
        """The encoder for ``flush_every`` steps of ``n_agents`` agents."""
        from tergodic_cli.runlog.wire import StepBatch

        self._enc = StepBatch(n_agents, self.flush_every, S.FRAME_OBJECT, self._line_half)
        self._loggers = tuple(self._b.logger(t) for t in (S.TOPIC_METRICS, S.TOPIC_AGENT_POSES, S.TOPIC_AGENT_SCENE))
        self._n_agents = n_agents
        self._shape = (n_agents, 3)

    def _flush_pending(self) -> None:
        """Encode the pending steps and hand their messages to the writer, in step order."""
        k = len(self._rows)
        if k == 0:
            return
        rows = np.array(self._rows)  # (K, 6): step, t, ε, ε_ref, touched, step_ms
        vecs = np.array(self._vecs).reshape(k, 3, self._n_agents, 3)
        t_ns = self._rows_tns
        records, poses, scenes = self._enc.encode(rows[:, 0].astype(np.uint64), t_ns, rows[:, 1:], vecs[:, 0],
                                                  vecs[:, 1], vecs[:, 2])
        for i in self._extras:
            records[i] = self._step_record_slow(i, vecs[i])
        log_rec, log_pose, log_scene = self._loggers
        pending = self._pending
        try:
            for i in range(k):
                t = t_ns[i]
                log_rec(records[i], t)
                log_pose(poses[i], t)
                log_scene(scenes[i], t)
                if i in pending:
                    self._b.write_many(pending[i])
        except (OSError, RuntimeError) as exc:
            self._fail(exc)
        finally:
            self._rows.clear()
            self._rows_tns.clear()
            self._vecs.clear()
            pending.clear()
            self._extras.clear()

    def _flush(self) -> None:
        self._flush_pending()
        try:
            self._b.flush()  # close the chunk and flush the file: it survives a crash from here on
        except (OSError, RuntimeError) as exc:
            self._fail(exc)
        self._last_flush = time.monotonic()

    def sync(self) -> None:
        """Write everything logged so far and flush the file: it survives a crash from here on."""
        self._require_open()
        self._flush()

    def _step_record_slow(self, row: int, vecs: np.ndarray) -> bytes:
        """The step record of a step whose metrics have non-standard names, through the protobuf library."""
        from tergodic_cli.runlog.proto import step_record_class

        rec = step_record_class()()
        step, t, _e, _r, _f, step_ms = self._rows[row]
        rec.step, rec.t, rec.step_ms, rec.n_agents = int(step), t, step_ms, self._n_agents
        for k, v in self._extras[row].items():
            if k in _METRIC_FIELDS:
                setattr(rec, k, v)
            else:
                rec.extra_names.append(k)
                rec.extra_values.append(v)
        rec.positions.extend(vecs[0].ravel().tolist())
        rec.velocities.extend(vecs[1].ravel().tolist())
        rec.normals.extend(vecs[2].ravel().tolist())
        return rec.SerializeToString()

    def _build_cloud_template(self, n: int) -> Any:
        from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField

        msg = self._classes[S.TOPIC_CLOUD](frame_id=S.FRAME_OBJECT, point_stride=4 * (3 + len(S.CLOUD_FIELDS)))
        msg.pose.position.SetInParent()  # a full pose: viewers (Rerun) need the position present
        msg.pose.orientation.w = 1.0
        for i, name in enumerate(("x", "y", "z") + S.CLOUD_FIELDS):
            msg.fields.add(name=name, offset=4 * i, type=PackedElementField.FLOAT32)
        return msg

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
            Simulated time of the step, s (>= 0), kept in the step record; the messages' log time is
            ``time_origin_ns`` plus this.
        positions, velocities, normals : (N, 3) float arrays
            Agent positions (m), velocities (m/s) and unit surface normals, object frame.
        metrics : dict
            ``explorer.metrics()``: ergodicity, residual_ref, touched_fraction (other
            numeric names are kept too, at some cost).
        step_ms : float
            Wall time of the explorer step, ms.
        robot : dict or None
            The robot sample of this step (CONTRACTS.md ``robot_sample_dict``), or None.
        """
        if self._closed:
            self._require_open()
        t = float(t)
        if step < 0 or not 0.0 <= t < math.inf:
            raise TergodicError(f"run log got step {step} at t = {t}", "steps must be >= 0 and times finite, >= 0")
        shape = self._shape
        try:
            fast = positions.shape == shape and velocities.shape == shape and normals.shape == shape
        except AttributeError:  # lists
            fast = False
        if not fast:
            positions, velocities, normals = self._agent_arrays(positions, velocities, normals)
        i = len(self._rows)
        t_ns = self.time_origin_ns + round(t * 1e9)
        if metrics.keys() == _METRIC_FIELDS:  # the standard names: a fixed layout, encoded in bulk
            self._rows.append((step, t, metrics["ergodicity"], metrics["residual_ref"], metrics["touched_fraction"],
                               step_ms))
        else:
            self._extra_metrics(i, metrics)
            self._rows.append((step, t, np.nan, np.nan, np.nan, step_ms))
        self._rows_tns.append(t_ns)
        self._vecs.append((positions.tolist(), velocities.tolist(), normals.tolist()))
        if robot is not None:
            self._pending[i] = self._robot_messages(int(step), t_ns, robot)
        self.n_steps += 1
        self._last_t = t
        if i + 1 == self.flush_every or (
                self.flush_seconds > 0 and (i & 7) == 7 and time.monotonic() - self._last_flush >= self.flush_seconds):
            self._flush()

    def log_steps(self, step: np.ndarray, t: np.ndarray, *, positions: np.ndarray, velocities: np.ndarray,
                  normals: np.ndarray, metrics: np.ndarray, step_ms: np.ndarray, cloud: dict | None = None) -> None:
        """Log K steps at once, as K :meth:`log_step` calls with the standard metrics would.

        Parameters
        ----------
        step : (K,) int array
        t : (K,) float array, s
        positions, velocities, normals : (K, N, 3) float arrays (m, m/s, unit)
        metrics : (K, 3) float array
            ergodicity, residual_ref, touched_fraction per step.
        step_ms : (K,) float array
        cloud : dict or None
            :meth:`log_cloud`'s keyword arguments for a cloud at the block's last step, logged after it.
        """
        self._require_open()
        step = np.asarray(step, dtype=np.int64)
        t = np.asarray(t, dtype=np.float64)
        K = len(step)
        if K == 0:
            return
        if step.min() < 0 or not (np.all(np.isfinite(t)) and t.min() >= 0.0):
            raise TergodicError("run log got a negative step or a bad time", "steps must be >= 0 and times finite, >= 0")
        P = np.asarray(positions, dtype=np.float64)
        if P.ndim != 3 or P.shape[0] != K or P.shape[2] != 3 or P.shape[1] == 0:
            raise TergodicError(f"run log got positions of shape {P.shape}, expected ({K}, N, 3)", "pass (K, N, 3) arrays")
        self._flush_pending()
        if P.shape[1] != self._n_agents:
            self._alloc(P.shape[1])
        cap = self.flush_every
        for a in range(0, K, cap):  # the encoder holds flush_every steps
            b = min(K, a + cap)
            t0 = self.time_origin_ns
            t_ns = [t0 + round(x * 1e9) for x in t[a:b].tolist()]  # as log_step: Python's round of t * 1e9
            scalars = np.column_stack((t[a:b], metrics[a:b], step_ms[a:b]))
            records, poses, scenes = self._enc.encode(step[a:b].astype(np.uint64), t_ns, scalars, P[a:b],
                                                      velocities[a:b], normals[a:b])
            log_rec, log_pose, log_scene = self._loggers
            try:
                for i, tn in enumerate(t_ns):
                    log_rec(records[i], tn)
                    log_pose(poses[i], tn)
                    log_scene(scenes[i], tn)
            except (OSError, RuntimeError) as exc:
                self._fail(exc)
            self._flush()
        self.n_steps += K
        self._last_t = float(t[-1])
        if cloud is not None:
            self.log_cloud(int(step[-1]), **cloud)

    def _extra_metrics(self, row: int, metrics: Mapping[str, float]) -> None:
        extras = {}
        for k, v in metrics.items():
            if not isinstance(k, str) or k in ("step", "t", "step_ms"):
                raise TergodicError(f"run log metric name {k!r} is not allowed", "use another name")
            extras[k] = float(v)
        self._extras[row] = extras

    def _robot_messages(self, step: int, t_ns: int, robot: Mapping[str, Any]) -> list:
        C = self._classes
        out = [(S.TOPIC_ROBOT_SAMPLE, t_ns, step, _dumps({"step": step, **robot}).encode())]
        ee = robot.get("ee_pose")
        if ee is not None:
            ee = np.asarray(ee, dtype=np.float64).tolist()
            msg = C[S.TOPIC_EE_POSE](frame_id=S.FRAME_BASE)
            _set_time(msg.timestamp, t_ns)
            msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = ee[:3]
            o = msg.pose.orientation
            o.x, o.y, o.z, o.w = ee[3:7]
            out.append((S.TOPIC_EE_POSE, t_ns, step, msg.SerializeToString()))
        frames = dict(robot.get("link_poses") or {})
        if ee is not None:
            frames[S.FRAME_EE] = ee
        obj = robot.get("object_pose")  # optional: where the capture frame sits in the base frame
        if obj is not None:
            frames[S.FRAME_OBJECT] = obj
        for child, pose in frames.items():
            pose = np.asarray(pose, dtype=np.float64).tolist()
            tf = C[S.TOPIC_TF](parent_frame_id=S.FRAME_BASE, child_frame_id=str(child))
            _set_time(tf.timestamp, t_ns)
            tf.translation.x, tf.translation.y, tf.translation.z = pose[:3]
            r = tf.rotation
            r.x, r.y, r.z, r.w = pose[3:7]
            out.append((S.TOPIC_TF, t_ns, step, tf.SerializeToString()))
        q = robot.get("q")
        if q is not None:
            q = np.asarray(q, dtype=np.float64).ravel().tolist()
            dq = np.asarray(robot.get("dq", np.zeros(len(q))), dtype=np.float64).ravel().tolist()
            tau = np.asarray(robot.get("tau", np.zeros(len(q))), dtype=np.float64).ravel().tolist()
            names = list(robot.get("joint_names") or [f"joint{i + 1}" for i in range(len(q))])
            js = C[S.TOPIC_JOINTS]()
            _set_time(js.timestamp, t_ns)
            for name, a, b, c in zip(names, q, dq, tau):
                js.joints.add(name=str(name), position=a, velocity=b, effort=c)
            out.append((S.TOPIC_JOINTS, t_ns, step, js.SerializeToString()))
        wm, wd = robot.get("wrench_measured"), robot.get("wrench_desired")
        if wm is not None or wd is not None:
            names = ("fx", "fy", "fz", "tx", "ty", "tz")
            rec: dict[str, Any] = {"step": step}
            scene = C[S.TOPIC_WRENCH_SCENE]()
            for key, w, colour in (("measured", wm, (1.0, 0.2, 0.2)), ("desired", wd, (0.2, 1.0, 0.2))):
                if w is None:
                    continue
                w = np.asarray(w, dtype=np.float64).ravel().tolist()
                rec[key] = dict(zip(names, w))
                f = w[:3]
                fn = math.sqrt(f[0] ** 2 + f[1] ** 2 + f[2] ** 2)
                ent = scene.entities.add(frame_id=S.FRAME_EE, id=f"force_{key}")
                _set_time(ent.timestamp, t_ns)
                if fn > 1e-9:
                    arrow = ent.arrows.add(shaft_length=0.005 * fn, shaft_diameter=0.002, head_length=0.006,
                                           head_diameter=0.006)  # 5 mm per newton
                    arrow.pose.orientation.x, arrow.pose.orientation.y, arrow.pose.orientation.z, \
                        arrow.pose.orientation.w = _quat_x_to((f[0] / fn, f[1] / fn, f[2] / fn))
                    arrow.color.r, arrow.color.g, arrow.color.b = colour
                    arrow.color.a = 1.0
            for key in ("force_normal", "in_contact"):
                if key in robot:
                    rec[key] = robot[key]
            out.append((S.TOPIC_WRENCH, t_ns, step, _dumps(rec).encode()))
            out.append((S.TOPIC_WRENCH_SCENE, t_ns, step, scene.SerializeToString()))
        return out

    # -- every K steps -------------------------------------------------------------------------
    def log_cloud(self, step: int, *, coverage: np.ndarray, heat: np.ndarray, source: np.ndarray,
                  target: np.ndarray | None = None, t: float | None = None) -> None:
        """Log the cloud with per-point target p, coverage c, heat u and source s, each (n,).

        ``target`` None repeats the last target logged (the one given at open, or by an earlier
        cloud). Any field may also be a :class:`SpectralField` (evaluated here). ``t`` defaults to the time of the last logged step. The message is a
        ``foxglove.PointCloud`` with float32 fields x y z target coverage heat source, in a
        chunk of its own that is on disk when this returns.
        """
        self._require_open()
        n = len(self.points)
        buf = self._cloud_buf
        if target is not None:  # the target from now on (a re-capture changed it)
            target = evaluate_field(target, self._field_basis, n)
            if target.shape == (n,):
                self.target = np.array(target, dtype=np.float64)
        for col, name, values in ((3, "target", self.target if target is None else target),
                                  (4, "coverage", coverage), (5, "heat", heat), (6, "source", source)):
            values = evaluate_field(values, self._field_basis, n)
            if values.shape != (n,):
                raise TergodicError(f"run log cloud field {name} has shape {values.shape}, expected ({n},)",
                                    "pass one value per point")
            buf[:, col] = values
        t = self._last_t if t is None else float(t)
        t_ns = self.time_origin_ns + int(round(t * 1e9))
        msg = self._cloud_msg
        _set_time(msg.timestamp, t_ns)
        msg.data = buf.tobytes()
        data = msg.SerializeToString()
        msg.data = b""
        self.n_clouds += 1
        self._flush()  # the steps before the cloud, in their own chunk
        try:
            self._b.write_many([(S.TOPIC_CLOUD, t_ns, int(step), data)])
            self._b.flush()
        except (OSError, RuntimeError) as exc:
            self._fail(exc)

    def log_event(self, step: int, t: float, text: str, level: str = "info") -> None:
        """Log a state-machine transition or warning as a ``foxglove.Log`` ("step N: text")."""
        self._require_open()
        Log = self._classes[S.TOPIC_EVENTS]
        levels = {"debug": Log.DEBUG, "info": Log.INFO, "warning": Log.WARNING, "error": Log.ERROR}
        t_ns = self.time_origin_ns + int(round(float(t) * 1e9))
        msg = Log(level=levels.get(level, Log.INFO), message=f"step {int(step)}: {text}", name="tergodic")
        _set_time(msg.timestamp, t_ns)
        item = (S.TOPIC_EVENTS, t_ns, int(step), msg.SerializeToString())
        if self._rows:  # after the step it follows
            self._pending.setdefault(len(self._rows) - 1, []).append(item)
            return
        try:
            self._b.write_many([item])
        except (OSError, RuntimeError) as exc:
            self._fail(exc)

    # -- end -----------------------------------------------------------------------------------
    def close(self, summary: Mapping[str, Any] | None = None, status: str = "ok") -> None:
        """Store ``summary`` (the summary.json dict) and finish the file; idempotent."""
        if self._closed:
            return
        self._flush_pending()
        self._closed = True
        try:
            if summary is not None:
                self._b.metadata(S.META_SUMMARY, {"json": _dumps(dict(summary))})
            self._b.metadata(S.META_END, {"steps": str(self.n_steps), "clouds": str(self.n_clouds), "status": status})
            self._b.finish()
        except (OSError, RuntimeError) as exc:
            self._fail(exc)
