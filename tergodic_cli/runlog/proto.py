"""The project's protobuf schemas, for the channels Foxglove has no schema for: ``tergodic.StepRecord``
(the exact per-step record), ``tergodic.RobotSample`` and ``tergodic.Wrench`` (the robot's sample and
wrench), ``tergodic.RobotPhase`` and ``tergodic.ForceWindow`` (the robot's own records).

Binary float64 (protobuf ``double``) is exact and costs no text formatting, at one record per
explorer step. Each proto2 message is described in code (no protoc); the step record: step (fixed64),
t (s), the three metrics, step_ms, n_agents, then positions (m), velocities (m/s) and normals as packed
(N, 3) row-major doubles, and extra_names / extra_values for further metrics. Each FileDescriptorSet
travels in its MCAP schema record, so protobuf-aware viewers decode them without tergodic
(docs/logging.md). proto2 keeps explicit presence: a metric never set reads as absent, not 0.
"""

from __future__ import annotations

import json
import numbers
from functools import lru_cache
from typing import Any

import numpy as np

PACKAGE = "tergodic"
NAME = "StepRecord"
FULL_NAME = f"{PACKAGE}.{NAME}"
#: Named metric fields; any other metric goes to extra_names / extra_values.
METRIC_FIELDS = ("ergodicity", "residual_ref", "touched_fraction")
VECTOR_FIELDS = ("positions", "velocities", "normals")


def _file_descriptor_proto() -> Any:
    from google.protobuf import descriptor_pb2 as d

    F = d.FieldDescriptorProto
    fdp = d.FileDescriptorProto(name="tergodic/StepRecord.proto", package=PACKAGE, syntax="proto2")
    msg = fdp.message_type.add(name=NAME)
    # field numbers 1.. in this order; the last five are repeated (the doubles packed)
    D = F.TYPE_DOUBLE
    types = (F.TYPE_FIXED64, D, D, D, D, D, F.TYPE_UINT32, D, D, D, F.TYPE_STRING, D)
    names = ("step", "t", *METRIC_FIELDS, "step_ms", "n_agents", *VECTOR_FIELDS,
             "extra_names", "extra_values")
    for number, (name, ftype) in enumerate(zip(names, types), start=1):
        repeated = number > 7
        f = msg.field.add(name=name, number=number, type=ftype,
                          label=F.LABEL_REPEATED if repeated else F.LABEL_OPTIONAL)
        if repeated and ftype == F.TYPE_DOUBLE:
            f.options.packed = True
    return fdp


@lru_cache(maxsize=1)
def step_record_class() -> type:
    """The generated message class (its own descriptor pool: never clashes with another definition)."""
    from google.protobuf import message_factory

    return message_factory.GetMessages([_file_descriptor_proto()])[FULL_NAME]


@lru_cache(maxsize=1)
def step_record_schema() -> bytes:
    """The serialized FileDescriptorSet stored in the MCAP schema record."""
    from google.protobuf import descriptor_pb2

    return descriptor_pb2.FileDescriptorSet(file=[_file_descriptor_proto()]).SerializeToString()


# --- the robot's own records: its state transitions and its 1 kHz force, window by window ---------------
ROBOT_PHASE = f"{PACKAGE}.RobotPhase"
FORCE_WINDOW = f"{PACKAGE}.ForceWindow"
#: Fields of each robot record, in field-number order: (name, type); every field optional (proto2
#: presence: a figure that is None stays absent).
ROBOT_RECORDS = {
    # One per state transition: the explorer step, the robot's time (s since the run's start), the
    # state left and the state entered, and why.
    ROBOT_PHASE: (("step", "fixed64"), ("t", "double"), ("source", "string"), ("target", "string"),
                  ("reason", "string")),
    # One per window of 1 kHz control ticks (closed at every robot sample, transition and at the end,
    # so every tick is in one window): the state, the window's robot time (s), its ticks, the max and
    # mean of the contact force |f| over them (N), and the run's cumulative tick figures at its end.
    FORCE_WINDOW: (("step", "fixed64"), ("state", "string"), ("t_start", "double"), ("t_end", "double"),
                   ("ticks", "uint32"), ("force_max", "double"), ("force_mean", "double"),
                   ("tick_force_peak_N", "double"), ("tick_steady", "uint64"), ("tick_force_rms_rel", "double"),
                   ("tick_tilt_median_deg", "double"), ("tick_tilt_p95_deg", "double")),
}


def _record_descriptor_proto(full_name: str) -> Any:
    from google.protobuf import descriptor_pb2 as d

    F = d.FieldDescriptorProto
    types = {"double": F.TYPE_DOUBLE, "fixed64": F.TYPE_FIXED64, "uint32": F.TYPE_UINT32, "uint64": F.TYPE_UINT64,
             "string": F.TYPE_STRING}
    name = full_name.split(".", 1)[1]
    fdp = d.FileDescriptorProto(name=f"{PACKAGE}/{name}.proto", package=PACKAGE, syntax="proto2")
    msg = fdp.message_type.add(name=name)
    for number, (field, ftype) in enumerate(ROBOT_RECORDS[full_name], start=1):
        msg.field.add(name=field, number=number, type=types[ftype], label=F.LABEL_OPTIONAL)
    return fdp


@lru_cache(maxsize=None)
def record_class(full_name: str) -> type:
    """The generated message class of a robot record (:data:`ROBOT_RECORDS`)."""
    from google.protobuf import message_factory

    return message_factory.GetMessages([_record_descriptor_proto(full_name)])[full_name]


@lru_cache(maxsize=None)
def record_schema(full_name: str) -> bytes:
    """The serialized FileDescriptorSet of a robot record, for the MCAP schema record."""
    from google.protobuf import descriptor_pb2

    return descriptor_pb2.FileDescriptorSet(file=[_record_descriptor_proto(full_name)]).SerializeToString()


def encode_record(full_name: str, record: dict) -> bytes:
    """``record`` (its known fields; None left absent) as the protobuf bytes of ``full_name``."""
    msg = record_class(full_name)()
    for field, _ in ROBOT_RECORDS[full_name]:
        v = record.get(field)
        if v is not None:
            setattr(msg, field, v)
    return msg.SerializeToString()


# --- the robot sample and the wrench (/robot/sample, /robot/wrench) --------------------------------------
# Foxglove has no wrench schema (foxglove-schemas-protobuf 0.4, foxglove-sdk 0.30): both are project
# schemas, protobuf like every other channel, so a reader with only the protobuf decoder reads the log.
ROBOT_SAMPLE = f"{PACKAGE}.RobotSample"
WRENCH = f"{PACKAGE}.Wrench"
_TIMESTAMP_FILE = "google/protobuf/timestamp.proto"
#: The robot sample's named fields, in field-number order from 2 (1 is ``timestamp``): (key, kind). Kinds:
#: double, int64, bool, string, doubles (packed 1-D), strings, poses (name -> 7-vector, ``link_poses``).
#: Append only: a field's number is its place here. A key not listed, or a value not of its kind, goes to
#: ``extras``; a key whose value is None to ``nulls``; so the decoded dict is the sample as the robot made it.
SAMPLE_FIELDS = (
    ("step", "int64"), ("t_sim", "double"), ("t_wall", "double"), ("state", "string"),
    ("ee_pose", "doubles"), ("q", "doubles"), ("dq", "doubles"), ("tau", "doubles"), ("joint_names", "strings"),
    ("link_poses", "poses"), ("object_pose", "doubles"), ("wrench_measured", "doubles"),
    ("wrench_desired", "doubles"), ("force_normal", "double"), ("force_contact", "double"),
    ("force_filtered", "double"), ("in_contact", "bool"), ("contact_point", "doubles"), ("tilt_deg", "double"),
    ("track_mm", "double"), ("agent_line_point", "doubles"), ("agent_line_dir", "doubles"),
    ("eps_agent", "double"), ("touched_agent", "double"), ("tick_force_peak_N", "double"), ("tick_steady", "int64"),
    ("tick_force_rms_rel", "double"), ("tick_tilt_median_deg", "double"), ("tick_tilt_p95_deg", "double"),
    ("eps_sponge", "double"), ("touched_sponge", "double"), ("stop_reason", "string"),
)
_SAMPLE_KIND = dict(SAMPLE_FIELDS)
#: The wrench's components, named as in the Plot panel paths (``/robot/wrench.measured.fz``).
WRENCH_COMPONENTS = ("fx", "fy", "fz", "tx", "ty", "tz")


def _timestamp_file() -> Any:
    from google.protobuf import descriptor_pb2, timestamp_pb2

    fdp = descriptor_pb2.FileDescriptorProto()
    timestamp_pb2.DESCRIPTOR.CopyToProto(fdp)
    return fdp


def _robot_file(full_name: str) -> Any:
    """The FileDescriptorProto of tergodic.RobotSample or tergodic.Wrench (proto2, no protoc)."""
    from google.protobuf import descriptor_pb2 as d

    F = d.FieldDescriptorProto
    OPT, REP = F.LABEL_OPTIONAL, F.LABEL_REPEATED
    name = full_name.split(".", 1)[1]
    fdp = d.FileDescriptorProto(name=f"{PACKAGE}/{name}.proto", package=PACKAGE, syntax="proto2",
                                dependency=[_TIMESTAMP_FILE])
    msg = fdp.message_type.add(name=name)

    def add(m: Any, field: str, number: int, ftype: int, label: int = OPT, type_name: str = "") -> None:
        f = m.field.add(name=field, number=number, type=ftype, label=label)
        if type_name:
            f.type_name = type_name
        if label == REP and ftype == F.TYPE_DOUBLE:
            f.options.packed = True

    # simulated time, as in the Foxglove messages: the log's time_origin_ns + the explorer step's t
    add(msg, "timestamp", 1, F.TYPE_MESSAGE, type_name=".google.protobuf.Timestamp")
    if full_name == WRENCH:
        comp = msg.nested_type.add(name="Components")
        for number, c in enumerate(WRENCH_COMPONENTS, start=1):
            add(comp, c, number, F.TYPE_DOUBLE)
        comps = f".{PACKAGE}.{name}.Components"
        for number, (field, ftype, tn) in enumerate(
                (("frame_id", F.TYPE_STRING, ""), ("step", F.TYPE_INT64, ""), ("measured", F.TYPE_MESSAGE, comps),
                 ("desired", F.TYPE_MESSAGE, comps), ("force_normal", F.TYPE_DOUBLE, ""),
                 ("in_contact", F.TYPE_BOOL, "")), start=2):
            add(msg, field, number, ftype, type_name=tn)
        return fdp
    pose = msg.nested_type.add(name="LinkPose")  # link_poses: name -> (x y z qx qy qz qw)
    add(pose, "name", 1, F.TYPE_STRING)
    add(pose, "pose", 2, F.TYPE_DOUBLE, REP)
    extra = msg.nested_type.add(name="Extra")  # a key the table does not list; one of its values is set
    for number, (field, ftype, label) in enumerate(
            (("name", F.TYPE_STRING, OPT), ("number", F.TYPE_DOUBLE, OPT), ("integer", F.TYPE_SINT64, OPT),
             ("flag", F.TYPE_BOOL, OPT), ("text", F.TYPE_STRING, OPT), ("numbers", F.TYPE_DOUBLE, REP),
             ("json", F.TYPE_STRING, OPT)), start=1):
        add(extra, field, number, ftype, label)
    scalar = {"double": F.TYPE_DOUBLE, "int64": F.TYPE_INT64, "bool": F.TYPE_BOOL, "string": F.TYPE_STRING}
    for number, (field, kind) in enumerate(SAMPLE_FIELDS, start=2):
        if kind in scalar:
            add(msg, field, number, scalar[kind])
        elif kind == "doubles":
            add(msg, field, number, F.TYPE_DOUBLE, REP)
        elif kind == "strings":
            add(msg, field, number, F.TYPE_STRING, REP)
        else:  # poses
            add(msg, field, number, F.TYPE_MESSAGE, REP, f".{PACKAGE}.{name}.LinkPose")
    add(msg, "nulls", 100, F.TYPE_STRING, REP)  # keys whose value was None
    add(msg, "extras", 101, F.TYPE_MESSAGE, REP, f".{PACKAGE}.{name}.Extra")
    return fdp


@lru_cache(maxsize=None)
def robot_class(full_name: str) -> type:
    """The generated class of tergodic.RobotSample or tergodic.Wrench (its own descriptor pool)."""
    from google.protobuf import message_factory

    return message_factory.GetMessages([_timestamp_file(), _robot_file(full_name)])[full_name]


@lru_cache(maxsize=None)
def robot_schema(full_name: str) -> bytes:
    """The serialized FileDescriptorSet (timestamp.proto included) for the MCAP schema record."""
    from google.protobuf import descriptor_pb2

    return descriptor_pb2.FileDescriptorSet(file=[_timestamp_file(), _robot_file(full_name)]).SerializeToString()


def _set_stamp(msg: Any, t_ns: int) -> None:
    msg.timestamp.seconds, msg.timestamp.nanos = divmod(int(t_ns), 1_000_000_000)


_BOOL = (bool, np.bool_)
_INT = (numbers.Integral, np.integer)


def _is_real(v: Any) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, _BOOL)


def _flat_reals(v: Any) -> list | None:
    """``v`` as a non-empty list of floats when it is a 1-D sequence of real numbers, else None."""
    if isinstance(v, (str, bytes, dict)) or not hasattr(v, "__len__"):
        return None
    try:
        a = np.asarray(v)
    except (TypeError, ValueError):
        return None
    if a.ndim != 1 or len(a) == 0 or a.dtype.kind not in "iuf":
        return None
    return a.astype(np.float64).tolist()


def encode_sample(sample: dict, t_ns: int) -> bytes:
    """A robot sample as ``tergodic.RobotSample`` bytes, lossless for what a robot produces.

    Parameters
    ----------
    sample : dict
        The robot sample (CONTRACTS robot_sample_dict plus extras; SI units, base frame). Keys of
        :data:`SAMPLE_FIELDS` with a value of their kind go to their field, None values to ``nulls``,
        anything else to ``extras`` (typed; nested values as JSON).
    t_ns : int
        The stamp, ns since the epoch: the log's ``time_origin_ns`` + the simulated time.

    Returns
    -------
    bytes
        The serialized message; :func:`sample_from_message` gives the same keys and values back
        (vectors as (k,) float64 arrays).
    """
    msg = robot_class(ROBOT_SAMPLE)()
    _set_stamp(msg, t_ns)
    for key, v in sample.items():
        kind = _SAMPLE_KIND.get(key)
        if v is None:
            msg.nulls.append(key)
            continue
        if kind == "double" and _is_real(v):
            setattr(msg, key, float(v))
            continue
        if kind == "int64" and isinstance(v, _INT) and not isinstance(v, _BOOL):
            setattr(msg, key, int(v))
            continue
        if kind == "bool" and isinstance(v, _BOOL):
            setattr(msg, key, bool(v))
            continue
        if kind == "string" and isinstance(v, str):
            setattr(msg, key, v)
            continue
        if kind == "doubles" and (vals := _flat_reals(v)) is not None:
            getattr(msg, key).extend(vals)
            continue
        if kind == "strings" and isinstance(v, (list, tuple)) and v and all(isinstance(s, str) for s in v):
            getattr(msg, key).extend(v)
            continue
        if kind == "poses" and isinstance(v, dict) and v and all(
                isinstance(n, str) and _flat_reals(p) is not None for n, p in v.items()):
            for n, p in v.items():
                msg.link_poses.add(name=n, pose=_flat_reals(p))
            continue
        ex = msg.extras.add(name=str(key))  # not in the table, or not of its kind
        if isinstance(v, _BOOL):
            ex.flag = bool(v)
        elif isinstance(v, _INT):
            ex.integer = int(v)
        elif _is_real(v):
            ex.number = float(v)
        elif isinstance(v, str):
            ex.text = v
        elif (vals := _flat_reals(v)) is not None:
            ex.numbers.extend(vals)
        else:
            from tergodic_cli.atomic import _json_default

            ex.json = json.dumps(v, default=_json_default, allow_nan=True)
    return msg.SerializeToString()


def sample_from_message(m: Any) -> dict:
    """A decoded ``tergodic.RobotSample`` back to the sample dict.

    Parameters
    ----------
    m : protobuf message
        The decoded message, of any class generated from the schema (tergodic's, or ``mcap_protobuf``'s
        from the schema stored in the file).

    Returns
    -------
    dict
        The sample's keys in :data:`SAMPLE_FIELDS` order, then the extras: vectors as (k,) float64 arrays,
        ``link_poses`` as {name: (7,) array}, ``joint_names`` as a list, None where the sample had None.
    """
    nulls = set(m.nulls)
    out: dict = {}
    for key, kind in SAMPLE_FIELDS:
        if kind in ("doubles", "strings", "poses"):
            vals = getattr(m, key)
            if len(vals):
                out[key] = (np.array(vals, dtype=np.float64) if kind == "doubles" else list(vals) if kind == "strings"
                            else {p.name: np.array(p.pose, dtype=np.float64) for p in vals})
            elif key in nulls:
                out[key] = None
        elif m.HasField(key):
            out[key] = getattr(m, key)
        elif key in nulls:
            out[key] = None
    for key in m.nulls:
        out.setdefault(key, None)
    for ex in m.extras:
        which = next((f for f in ("number", "integer", "flag", "text", "json") if ex.HasField(f)), None)
        out[ex.name] = (np.array(ex.numbers, dtype=np.float64) if which is None
                        else json.loads(ex.json) if which == "json" else getattr(ex, which))
    return out


def encode_wrench(step: int, t_ns: int, measured: Any, desired: Any, force_normal: Any, in_contact: Any) -> bytes:
    """The ``tergodic.Wrench`` message of one robot sample.

    Parameters
    ----------
    step : int
        Explorer step.
    t_ns : int
        The stamp, ns since the epoch: the log's ``time_origin_ns`` + the simulated time.
    measured, desired : (6,) float array or None
        Wrench fx fy fz (N), tx ty tz (N m) in the ee frame; None leaves it absent.
    force_normal : float or None
        Normal force on the surface, N.
    in_contact : bool or None
        Whether the tool is in contact.

    Returns
    -------
    bytes
        The serialized message.
    """
    msg = robot_class(WRENCH)()
    _set_stamp(msg, t_ns)
    msg.frame_id, msg.step = "ee", int(step)
    for key, w in (("measured", measured), ("desired", desired)):
        if w is not None:
            part = getattr(msg, key)
            for c, v in zip(WRENCH_COMPONENTS, _flat_reals(w) or ()):
                setattr(part, c, v)
    if force_normal is not None:
        msg.force_normal = float(force_normal)
    if in_contact is not None:
        msg.in_contact = bool(in_contact)
    return msg.SerializeToString()
