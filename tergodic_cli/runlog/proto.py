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
