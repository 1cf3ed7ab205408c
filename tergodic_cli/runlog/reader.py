"""Read a run log back: series, robot samples, clouds, events, metadata.

Times come from the messages (the step records' ``t``, the robot samples' ``t_sim``, the clouds' and
events' stamps minus the log's ``time_origin_ns``), never from log times, which are the wall clock
from version 3 on. Robot samples are read from protobuf (version 3) or JSON (before). Record by
record, so a log cut short by a crash reads up to its last complete chunk (``truncated = True``);
chunk CRCs are checked, so a half-written chunk is dropped (docs/logging.md).
"""

from __future__ import annotations

import json
import os
import re
import struct
import zlib
from contextlib import suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tergodic_cli.errors import TergodicError, require
from tergodic_cli.runlog import schema as S
from tergodic_cli.runlog.proto import FULL_NAME, METRIC_FIELDS, VECTOR_FIELDS

_MAGIC = b"\x89MCAP0\r\n"
_EVENT_RE = re.compile(r"^step (\d+): (.*)$", re.S)
_RUN_FIX = "pass a run folder written by 'tergodic explore' or its run.mcap"


@dataclass
class CloudFrame:
    """One logged point cloud: points (n, 3) m and per-point fields (n,), as float64."""

    step: int
    t: float
    points: np.ndarray
    fields: dict[str, np.ndarray]
    t_ns: int = 0

    def __getattr__(self, name: str) -> np.ndarray:  # cloud.target, cloud.coverage, ...
        fields = self.__dict__.get("fields", {})
        if name in fields:
            return fields[name]
        raise AttributeError(name)


@dataclass
class RunLogData:
    """Everything a run log holds.

    Attributes
    ----------
    series : dict of arrays, one row per logged step
        ``step`` (T,) int64, ``t`` (T,) s, every metric (``ergodicity``, ``residual_ref``,
        ``touched_fraction``, ...) (T,), ``step_ms`` (T,), and ``positions``,
        ``velocities``, ``normals`` (T, N, 3) in the object frame (m, m/s).
    robot : list of dict or None
        The robot samples as logged (lists turned into float arrays), one per step.
    clouds : list of CloudFrame
        The point clouds in log order.
    truncated : bool
        True when the file ends before its footer (a killed run).
    status : str
        "complete", "interrupted" (closed by the writer after Ctrl-C/SIGTERM, marked in its
        end record), "truncated" (cut at the end), or "error: TYPE" (closed after an error).
    """

    path: Path
    version: str
    info: dict[str, str]
    config: dict[str, Any]
    seed: int | None
    versions: dict[str, str]
    capture_sidecar: dict[str, Any] | None
    stored_summary: dict[str, Any] | None
    end: dict[str, str] | None
    series: dict[str, np.ndarray]
    robot: list[dict[str, Any]] | None
    clouds: list[CloudFrame]
    events: list[tuple[int, float, str]]
    topics: dict[str, dict[str, Any]]
    truncated: bool
    truncation_note: str = ""
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    #: Robot runs: the state transitions (/robot/phase) and the 1 kHz force windows (/robot/force), as
    #: dicts of their fields (absent fields left out), in log order.
    phases: list[dict[str, Any]] = field(default_factory=list)
    force_windows: list[dict[str, Any]] = field(default_factory=list)

    @property
    def status(self) -> str:
        if self.truncated:
            return "truncated"
        end = (self.end or {}).get("status", "ok")
        return "complete" if end == "ok" else end

    @property
    def steps(self) -> int:
        """Number of logged steps."""
        return len(self.series["step"])

    def index_of(self, step: int) -> int:
        """Row of explorer step ``step`` in the series (one-line error when it is not logged)."""
        hits = np.flatnonzero(self.series["step"] == step)
        if len(hits) == 0:
            lo, hi = int(self.series["step"][0]), int(self.series["step"][-1])
            raise TergodicError(f"step {step} is not in this log (steps {lo}..{hi})", f"use --step between {lo} and {hi}")
        return int(hits[-1])

    def cloud_at(self, step: int) -> CloudFrame | None:
        """The last cloud logged at or before ``step`` (None if there is none)."""
        before = [c for c in reversed(self.clouds) if c.step <= step]  # later ones first
        return max(before, key=lambda c: c.step, default=None)

    def robot_series(self) -> dict[str, np.ndarray]:
        """Robot samples stacked per key: numbers and equal-length vectors as (T,) / (T, k) arrays."""
        if not self.robot:
            return {}
        out: dict[str, np.ndarray] = {}
        for k in (k for k in self.robot[0] if k != "link_poses"):
            vals = [s.get(k) for s in self.robot]
            if k == "contact_point":  # None when not in contact
                vals = [np.full(3, np.nan) if v is None else v for v in vals]
            with suppress(TypeError, ValueError):  # ragged or not numbers: left out
                if not any(v is None for v in vals):
                    out[k] = np.array(vals, dtype=None if isinstance(vals[0], str) else np.float64)
        return out


def resolve_log_path(path: str | os.PathLike) -> Path:
    """``RUN_DIR`` -> ``RUN_DIR/run.mcap``; a file path is returned as it is."""
    p = Path(path)
    if not p.exists():
        left = _unfinished_siblings(p)
        if left:  # a run killed by SIGKILL (or still running) stays in its temporary sibling
            more = f" (and {len(left) - 1} more)" if len(left) > 1 else ""
            raise TergodicError(f"{p} does not exist, but {left[0]}{more} beside it holds a run that did not finish "
                                f"(killed, or still running)",
                                f"read it with 'tergodic replay {left[0]}', or keep it as the run with "
                                f"'mv {left[0]} {p}'")
        raise TergodicError(f"{p} does not exist", _RUN_FIX)
    if p.is_dir():
        f = p / "run.mcap"
        require(f.exists(), f"{p} has no run.mcap", _RUN_FIX)
        return f
    return p


def _unfinished_siblings(p: Path) -> list[Path]:
    """The temporary folders (``.NAME.tmp-*``) of runs into ``p`` that never finished, newest first."""
    with suppress(OSError):
        found = [q for q in p.parent.glob(f".{p.name}.tmp-*") if q.is_dir()]
        return sorted(found, key=lambda q: q.stat().st_mtime, reverse=True)
    return []


def _check_head(path: Path) -> None:
    """Tell 'not an MCAP file' from 'truncated header' before parsing."""
    head = _read_at(path, 0, len(_MAGIC) + 9)
    if len(head) == 0:
        raise TergodicError(f"{path} is empty (0 bytes)", "the run wrote nothing; re-run 'tergodic explore'")
    if not _MAGIC.startswith(head[:len(_MAGIC)]):
        raise TergodicError(f"{path} is not an MCAP file (bad magic bytes)", _RUN_FIX)
    if len(head) < len(_MAGIC) + 9:
        raise TergodicError(f"{path} has a truncated header ({len(head)} bytes)", "the run died at start; re-run it")
    if head[len(_MAGIC)] != 0x01:  # the first record of an MCAP file is its Header (opcode 0x01)
        raise TergodicError(f"{path} is not an MCAP file (no header record)", _RUN_FIX)


def read_run_log(path: str | os.PathLike, *, clouds: bool = True) -> RunLogData:
    """Read a run log (a ``run.mcap`` or a run folder holding one).

    Parameters
    ----------
    path : path-like
        ``RUN_DIR`` or ``RUN_DIR/run.mcap``.
    clouds : bool
        Decode the point clouds (skip for speed when only the numbers are needed).

    Raises
    ------
    TergodicError
        Not an MCAP file, a truncated header, an unknown log schema version, not a
        tergodic log, or no step at all (one line, exit 2 in the CLI).
    """
    from foxglove_schemas_protobuf.Log_pb2 import Log
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
    from mcap.records import Attachment, Channel, Footer, Header, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    path = resolve_log_path(path)
    _check_head(path)
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    counts: dict[int, int] = {}
    metadata: dict[str, dict[str, str]] = {}
    attachments: dict[str, bytes] = {}
    rows, robot, cloud_frames, events = [], [], [], []
    robot_records: dict[str, list] = {S.TOPIC_ROBOT_PHASE: [], S.TOPIC_ROBOT_FORCE: []}
    record_decoders: dict[int, Any] = {}
    truncated, note, have_header, complete = False, "", False, False
    step_decoder, t0 = None, 0

    size = path.stat().st_size
    finished = _has_footer(path, size)
    with open(path, "rb") as fh:
        reader = StreamReader(fh, validate_crcs=True)
        stream = reader._stream  # its byte count is the offset of the next record
        records = iter(reader.records)
        while True:
            try:
                # A chunk is read and checked whole before its first message is yielded, so a
                # failing call starts at the next record's offset: a bad chunk is named by it.
                at = max(stream.count, len(_MAGIC))  # the first call reads the magic first
                rec = next(records)
            except StopIteration:
                break
            except Exception as exc:  # a cut (EndOfFile, short record) or damage (bad CRC, garbage)
                if complete and _cut_magic(path, at):
                    truncated, note = True, "cut inside the closing magic"
                    break
                if finished or complete or not (_runs_past_end(path, at, size) or _unfinished_chunk(path, at, size)):
                    raise _corrupt(path, at, exc) from None
                if not have_header:
                    raise TergodicError(f"{path} has a truncated header ({type(exc).__name__})",
                                        "the run died at start; re-run it") from None
                truncated, note = True, f"{type(exc).__name__}: {exc}".strip().rstrip(":")
                break
            if isinstance(rec, Message):
                ch = channels.get(rec.channel_id)
                topic = ch and ch.topic
                counts[rec.channel_id] = counts.get(rec.channel_id, 0) + 1
                if topic == S.TOPIC_METRICS:
                    step_decoder = step_decoder or _step_decoder(schemas[ch.schema_id])
                    rows.append(step_decoder(rec.data))
                elif topic == S.TOPIC_ROBOT_SAMPLE:
                    if ch.message_encoding == "json":  # written before version 3
                        robot.append(_arrays(json.loads(rec.data)))
                    else:
                        if ch.schema_id not in record_decoders:
                            record_decoders[ch.schema_id] = _sample_decoder(schemas[ch.schema_id])
                        robot.append(record_decoders[ch.schema_id](rec.data))
                elif topic in robot_records:
                    if ch.schema_id not in record_decoders:
                        record_decoders[ch.schema_id] = _record_decoder(schemas[ch.schema_id])
                    robot_records[topic].append(record_decoders[ch.schema_id](rec.data))
                elif topic == S.TOPIC_CLOUD and clouds:
                    cloud_frames.append(_decode_cloud(PointCloud.FromString(rec.data), rec, t0))
                elif topic == S.TOPIC_EVENTS:
                    msg = Log.FromString(rec.data)
                    m = _EVENT_RE.match(msg.message)
                    step, text = (int(m.group(1)), m.group(2)) if m else (int(rec.sequence), msg.message)
                    events.append((step, (_stamp_ns(msg, rec) - t0) / 1e9, text))  # t0: metadata first
            elif isinstance(rec, Channel):
                channels[rec.id] = rec
            elif isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Metadata):
                metadata[rec.name] = dict(rec.metadata)
                if rec.name == S.META_TERGODIC:
                    t0 = _time_origin(rec.metadata)  # the stamp of simulated time 0 (0 in version 1)
                    if (v := rec.metadata.get("log_schema_version")) not in S.SUPPORTED_VERSIONS:
                        raise TergodicError(f"{path} uses log schema version {v!r}; this tergodic "
                                            f"reads {', '.join(S.SUPPORTED_VERSIONS)}",
                                            "replay it with the tergodic version that wrote it "
                                            "(see its 'tergodic' metadata)")
            elif isinstance(rec, Attachment):
                attachments[rec.name] = rec.data
            elif isinstance(rec, Header):
                have_header = True
            elif isinstance(rec, Footer):
                complete = True
                _check_summary_crc(path, rec, at)
        if complete and stream.count < size:  # bytes after the closing magic: not written by the log's writer
            raise TergodicError(f"{path} has {size - stream.count} bytes of garbage after the end of the log "
                                f"(from byte {stream.count})",
                                f"remove them (truncate -s {stream.count} {path}), or re-run 'tergodic explore'")
    if not complete and not truncated:
        truncated, note = True, "no footer"
    version = metadata.get(S.META_TERGODIC, {}).get("log_schema_version")
    if S.META_TERGODIC not in metadata:
        if truncated:
            raise TergodicError(f"{path} is cut off before its metadata (the run died at start)", "re-run it")
        raise TergodicError(f"{path} is not a tergodic run log (no '{S.META_TERGODIC}' metadata)", _RUN_FIX)
    stored = metadata.get(S.META_SUMMARY, {}).get("json")
    # A robot that stopped on a fault before its first explorer step: a complete log with its events and
    # summary and no step; it replays (its series are empty).
    no_step_fault = complete and not rows and stored is not None and json.loads(stored).get("final_state") == "stopped"
    if not rows and not no_step_fault:
        if events:
            raise TergodicError(f"{path} is an empty log: no step recorded; its last event says: {events[-1][2]}",
                                "fix that and re-run 'tergodic explore'")
        why = " (the run was cut before its first chunk)" if truncated else ""
        raise TergodicError(f"{path} is an empty log: no step recorded{why}", "re-run 'tergodic explore' with --steps >= 1")

    topics = {}
    for cid, ch in channels.items():
        sc = schemas.get(ch.schema_id)
        topics[ch.topic] = {"schema": sc.name if sc else "", "schema_encoding": sc.encoding if sc else "",
                            "message_encoding": ch.message_encoding, "count": counts.get(cid, 0)}

    def _meta_json(name: str) -> Any:
        raw = metadata.get(name, {}).get("json")
        return None if raw is None else json.loads(raw)

    seed_txt = metadata.get(S.META_SEED, {}).get("seed", "")
    series = _stack_rows(rows)
    if no_step_fault:
        from tergodic_cli.explore.summary import SERIES

        series.update({k: np.zeros(0) for k in SERIES if k not in series})
    _assign_cloud_steps(cloud_frames, series)
    sidecar = attachments.get(S.ATTACHMENT_SIDECAR)
    return RunLogData(
        path=path, version=version, info=metadata.get(S.META_TERGODIC, {}),
        config=_meta_json(S.META_CONFIG) or {}, seed=int(seed_txt) if seed_txt.strip().lstrip("-").isdigit() else None,
        versions=metadata.get(S.META_VERSIONS, {}), capture_sidecar=json.loads(sidecar) if sidecar else None,
        stored_summary=_meta_json(S.META_SUMMARY), end=metadata.get(S.META_END),
        series=series, robot=robot or None, clouds=cloud_frames, events=events,
        topics=topics, truncated=truncated, truncation_note=note, metadata=metadata,
        phases=robot_records[S.TOPIC_ROBOT_PHASE], force_windows=robot_records[S.TOPIC_ROBOT_FORCE])


_FOOTER_LEN = 1 + 8 + 20  # opcode, length, summary_start, summary_offset_start, summary_crc


def _read_at(path: Path, offset: int, n: int = -1) -> bytes:
    with open(path, "rb") as fh:
        fh.seek(offset)
        return fh.read(n)


def _has_footer(path: Path, size: int) -> bool:
    """The file ends in a footer record and the closing magic: it was finished, so a bad
    record inside it is damage, not a cut."""
    if size < len(_MAGIC) * 2 + _FOOTER_LEN:
        return False
    tail = _read_at(path, size - len(_MAGIC) - _FOOTER_LEN)
    return tail[-len(_MAGIC):] == _MAGIC and tail[0] == 0x02 and struct.unpack_from("<Q", tail, 1)[0] == 20


def _cut_magic(path: Path, at: int) -> bool:
    """After the footer the file holds only a part of the closing magic: cut in its last bytes."""
    rest = _read_at(path, at)
    return len(rest) < len(_MAGIC) and _MAGIC.startswith(rest)


def _runs_past_end(path: Path, at: int, size: int) -> bool:
    """The record at byte ``at`` is a known record type whose length reaches past the end of the
    file: the file was cut inside it (a truncation), not damaged."""
    head = _read_at(path, at, 9)
    if len(head) < 9:
        return True
    opcode, length = head[0], struct.unpack_from("<Q", head, 1)[0]
    return 0x01 <= opcode <= 0x0F and at + 9 + length > size


_PLACEHOLDER_TOP = 0xFF  # the top byte of the writer's 2^64 - 1 placeholder sizes


def _unfinished_chunk(path: Path, at: int, size: int) -> bool:
    """The record at byte ``at`` is a chunk, the last record of the file, whose header the writer
    had not finished: it writes a chunk's header with placeholder sizes (2^64 - 1), streams the
    compressed records, then goes back to fill in the header and only then appends the message
    indexes. A SIGKILL inside that short write (split at a page boundary) leaves the length filled
    in but the compressed size still the placeholder (its top byte 0xFF, as no real size has):
    a cut, not damage."""
    fixed = 9 + 8 + 8 + 8 + 4 + 4  # opcode, length, start and end time, uncompressed size and crc, name length
    head = _read_at(path, at, fixed)
    if len(head) < fixed or head[0] != 0x06:
        return False
    length = struct.unpack_from("<Q", head, 1)[0]
    name_len = struct.unpack_from("<I", head, fixed - 4)[0]
    if at + 9 + length != size or name_len > 16:
        return False
    compressed = _read_at(path, at + fixed + name_len, 8)
    return len(compressed) == 8 and compressed[7] == _PLACEHOLDER_TOP


def _corrupt(path: Path, at: int, exc: BaseException | None, why: str = "") -> TergodicError:
    from mcap.records import DataEnd

    what = type(exc).__name__
    record = getattr(exc, "record", None)
    if why:
        where = f"at byte {at} ({why})"
    elif isinstance(record, DataEnd):  # the whole data section's checksum, checked at its end
        where = f"before byte {at} (the data section's checksum does not match)"
    else:
        where = f"at byte {at} ({'bad CRC of the chunk starting there' if 'CRC' in what else f'unreadable record, {what}'})"
    return TergodicError(f"{path} is corrupt {where}; the file was damaged after it was written",
                         "restore it from a copy, or re-run 'tergodic explore'")


def _check_summary_crc(path: Path, footer: Any, at: int) -> None:
    """The footer's CRC over the summary section (the reader does not check it)."""
    if not footer.summary_crc or not footer.summary_start:
        return
    end = at + 1 + 8 + 16  # up to the footer's own CRC field
    body = _read_at(path, footer.summary_start, end - footer.summary_start)
    if zlib.crc32(body) != footer.summary_crc:
        raise _corrupt(path, footer.summary_start, None, "the summary section's checksum does not match")


def _step_decoder(schema: Any):
    """bytes -> row dict for the step records, decoded with the schema stored in the file."""
    from mcap_protobuf.decoder import DecoderFactory

    if schema.encoding != "protobuf" or schema.name != FULL_NAME:
        raise TergodicError(f"step records have schema {schema.name!r} ({schema.encoding})",
                            "this log was not written by a tergodic that this version reads")
    decode = DecoderFactory().decoder_for("protobuf", schema)

    def row(data: bytes) -> dict:
        m = decode(data)
        vec = {k: np.asarray(getattr(m, k), dtype=np.float64).reshape(m.n_agents, 3)
               for k in VECTOR_FIELDS}
        return {"step": m.step, "t": m.t, **{k: getattr(m, k) if m.HasField(k) else None
                                             for k in METRIC_FIELDS},
                "step_ms": m.step_ms, **dict(zip(m.extra_names, m.extra_values)), **vec}

    return row


def _record_decoder(schema: Any):
    """bytes -> dict of the fields present, for a robot record (proto.ROBOT_RECORDS), decoded with the
    schema stored in the file."""
    from mcap_protobuf.decoder import DecoderFactory

    from tergodic_cli.runlog.proto import ROBOT_RECORDS

    if schema.encoding != "protobuf" or schema.name not in ROBOT_RECORDS:
        raise TergodicError(f"robot records have schema {schema.name!r} ({schema.encoding})",
                            "this log was not written by a tergodic that this version reads")
    decode = DecoderFactory().decoder_for("protobuf", schema)
    names = [f for f, _ in ROBOT_RECORDS[schema.name]]

    def record(data: bytes) -> dict:
        m = decode(data)
        return {f: getattr(m, f) for f in names if m.HasField(f)}

    return record


def _sample_decoder(schema: Any):
    """bytes -> the robot sample dict, for /robot/sample (tergodic.RobotSample), decoded with the schema
    stored in the file."""
    from mcap_protobuf.decoder import DecoderFactory

    from tergodic_cli.runlog.proto import ROBOT_SAMPLE, sample_from_message

    if schema.encoding != "protobuf" or schema.name != ROBOT_SAMPLE:
        raise TergodicError(f"robot samples have schema {schema.name!r} ({schema.encoding})",
                            "this log was not written by a tergodic that this version reads")
    decode = DecoderFactory().decoder_for("protobuf", schema)
    return lambda data: sample_from_message(decode(data))


def _stamp_ns(msg: Any, rec: Any) -> int:
    """A Foxglove message's ``timestamp`` in ns (its simulated time + the origin); the log time when it has none."""
    if not msg.HasField("timestamp"):
        return int(rec.log_time)
    return msg.timestamp.seconds * 1_000_000_000 + msg.timestamp.nanos


def _stack_rows(rows: list[dict]) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {"step": np.array([r["step"] for r in rows], dtype=np.int64),
                                  "t": np.array([r["t"] for r in rows], dtype=np.float64)}
    for key in dict.fromkeys(k for r in rows for k in r):  # every name, first-seen order
        if key in out:
            continue
        vals = [r.get(key) for r in rows]
        if key in VECTOR_FIELDS:
            try:
                out[key] = np.array(vals, dtype=np.float64)
            except ValueError:  # the agent count changed mid-run: keep per-step arrays
                out[key] = np.array([np.asarray(v, dtype=np.float64) for v in vals], dtype=object)
            continue
        out[key] = np.array([np.nan if v is None else v for v in vals], dtype=np.float64)
    return out


def _time_origin(info: dict) -> int:
    """The log's ``time_origin_ns`` (0 for version 1, which has none)."""
    raw = info.get("time_origin_ns", "0") or "0"
    if not raw.isdigit():
        raise TergodicError(f"the log's time_origin_ns {raw[:40]!r} is not a whole number of nanoseconds",
                            "the file is damaged; re-run 'tergodic explore'")
    return int(raw)


def _assign_cloud_steps(clouds: list[CloudFrame], series: dict[str, np.ndarray]) -> None:
    """A cloud belongs to the last step at or before its simulated time (writers number messages differently)."""
    t_ns = np.rint(series["t"] * 1e9).astype(np.int64)
    order = np.argsort(t_ns, kind="stable")
    for c in clouds:
        k = np.searchsorted(t_ns[order], c.t_ns, side="right") - 1
        if k >= 0:
            c.step = int(series["step"][order[k]])


def _arrays(sample: dict) -> dict:
    out = {}
    for k, v in sample.items():
        if isinstance(v, list) and v and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
            out[k] = np.asarray(v, dtype=np.float64)
        elif k == "link_poses" and isinstance(v, dict):
            out[k] = {name: np.asarray(p, dtype=np.float64) for name, p in v.items()}
        else:
            out[k] = v
    return out


_NUMPY_OF = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}  # foxglove NumericType


def _decode_cloud(msg: Any, rec: Any, t0: int) -> CloudFrame:
    """``t0``: the log's time origin; the cloud's simulated time is its stamp minus it."""
    stride = msg.point_stride
    n = len(msg.data) // stride if stride else 0
    dtype = np.dtype({"names": [f.name for f in msg.fields],
                      "formats": ["<" + _NUMPY_OF[f.type] for f in msg.fields],
                      "offsets": [f.offset for f in msg.fields], "itemsize": stride})
    arr = np.frombuffer(msg.data, dtype=dtype, count=n)
    pts = np.column_stack([arr["x"], arr["y"], arr["z"]]).astype(np.float64)
    fields = {f.name: arr[f.name].astype(np.float64) for f in msg.fields if f.name not in ("x", "y", "z")}
    t_ns = _stamp_ns(msg, rec) - t0
    return CloudFrame(step=int(rec.sequence), t=t_ns / 1e9, points=pts, fields=fields, t_ns=t_ns)


__all__ = ["CloudFrame", "RunLogData", "read_run_log", "resolve_log_path"]
