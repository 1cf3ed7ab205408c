"""``tergodic.StepRecord``: the exact per-step record, as a protobuf message built at import.

Binary float64 (protobuf ``double``) is exact and costs no text formatting, at one record per
explorer step. The proto2 message is described in code (no protoc): step (fixed64), t (s), the
three metrics, step_ms, n_agents, then positions (m), velocities (m/s) and normals as packed (N, 3)
row-major doubles, and extra_names / extra_values for further metrics. Its FileDescriptorSet
travels in the MCAP schema record, so protobuf-aware viewers decode it without tergodic
(docs/logging.md). proto2 keeps explicit presence: a metric never set reads as absent, not 0.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

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
