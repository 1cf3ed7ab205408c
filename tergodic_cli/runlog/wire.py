"""Fast encoding of the per-step messages, a batch of steps at a time.

Setting a few dozen fields on protobuf objects costs tens of microseconds per
explorer step once the explorer's numpy work has evicted the CPU caches, too much
next to a ~1 ms step. So :class:`~tergodic_cli.runlog.writer.RunLog` only copies
each step's numbers into preallocated arrays, and encodes the steps of a chunk
together, just before the chunk is written.

The layout of the per-step messages never changes during a run (same agent count,
same ids), and ``double`` fields are fixed width on the wire. Each message type is
therefore serialized once, by the real protobuf library, with a distinct sentinel
in every double slot; the sentinels' byte offsets give strided numpy views into a
(batch, message length) byte array, and a batch is a few array assignments. No
field number is hard-coded: the layout comes from the schemas themselves, and each
encoder checks that its views cover exactly the slots it found. Tests decode the
output with the official schemas.

Only a top-level field may vary in length (the PosesInFrame timestamp); it is
encoded on its own and put first (protobuf fields may come in any order). Scene
entities carry no timestamp and are frame-locked.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np


def _sentinel(k: int) -> float:
    # distinct doubles whose 8 bytes cannot occur by accident elsewhere in a template
    return 1.0 + 2.0**-30 + k * 2.0**-40


def _offset(buf: bytes, pattern: bytes) -> int:
    i = buf.find(pattern)
    if i < 0 or buf.find(pattern, i + 1) >= 0:
        raise AssertionError("protobuf template layout: sentinel not found exactly once")
    return i


class _Slots:
    """Hands out sentinels and records which slot each one marks."""

    def __init__(self) -> None:
        self.values: dict[tuple, float] = {}

    def __call__(self, *key: Any) -> float:
        v = _sentinel(len(self.values))
        self.values[key] = v
        return v

    def layout(self, data: bytes, name: str, shape: tuple[int, ...]) -> tuple[int, tuple[int, ...]]:
        """(offset, strides) of the slots ``(name, i, j, ...)``, which must be evenly spaced, C order."""
        keys = [k for k in self.values if k[0] == name]
        offs = {k[1:]: _offset(data, struct.pack("<d", self.values[k])) for k in keys}
        idx = list(np.ndindex(*shape))
        if sorted(offs) != sorted(idx):
            raise AssertionError(f"protobuf template layout: slots of {name} do not form {shape}")
        base = offs[idx[0]]
        strides = []
        for axis, n in enumerate(shape):
            unit = tuple(1 if a == axis else 0 for a in range(len(shape)))
            strides.append(offs[unit] - base if n > 1 else 8)
        for i in idx:
            if offs[i] != base + sum(a * s for a, s in zip(i, strides)):
                raise AssertionError(f"protobuf template layout: slots of {name} are not evenly spaced")
        return base, tuple(strides)


class _Batch:
    """``capacity`` copies of a template message in one (capacity, length) byte array, with views."""

    def __init__(self, data: bytes, capacity: int):
        self.length = len(data)
        self.rows = np.tile(np.frombuffer(data, dtype=np.uint8), (capacity, 1))

    def view(self, offset: int, strides: tuple[int, ...], shape: tuple[int, ...], dtype: str = "<f8") -> np.ndarray:
        cap = len(self.rows)
        return np.ndarray((cap, *shape), dtype=dtype, buffer=self.rows, offset=offset, strides=(self.length, *strides))

    def messages(self, k: int) -> list[bytes]:
        data = self.rows[:k].tobytes()
        n = self.length
        return [data[i * n:(i + 1) * n] for i in range(k)]


_SMALL = [bytes((i,)) for i in range(128)]


def _varint(n: int) -> bytes:
    if n < 128:
        return _SMALL[n]
    out = bytearray()
    while n > 0x7F:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def timestamp_field(field_number: int, t_ns: int) -> bytes:
    """A ``google.protobuf.Timestamp`` field (wire type 2) holding ``t_ns`` nanoseconds."""
    return timestamped(field_number, [int(t_ns)], [b""])[0]


def timestamped(field_number: int, t_ns: list[int], bodies: list[bytes]) -> list[bytes]:
    """Each body with a ``google.protobuf.Timestamp`` field of its time prepended: the bytes of
    :func:`timestamp_field`, a loop with fewer calls (it runs for every logged step)."""
    tag = _varint(field_number << 3 | 2)
    small, varint = _SMALL, _varint
    out = []
    for t, body in zip(t_ns, bodies):
        sec, nanos = divmod(t, 1_000_000_000)
        if sec < 128:
            ts = (b"\x08" + small[sec]) if sec else b""
        elif sec < 16384:
            ts = bytes((8, sec & 0x7F | 0x80, sec >> 7))
        else:
            ts = b"\x08" + varint(sec)
        if nanos:
            ts += b"\x10" + varint(nanos)
        out.append(tag + small[len(ts)] + ts + body)
    return out


def quats_z_to(normals: np.ndarray) -> np.ndarray:
    """Shortest-arc quaternions (M, 4) xyzw turning +z onto each normal (M, 3); a zero normal gives identity."""
    n = np.asarray(normals, dtype=np.float64)
    nn = np.linalg.norm(n, axis=1)
    q = np.empty((len(n), 4))
    q[:, 0], q[:, 1], q[:, 2], q[:, 3] = -n[:, 1], n[:, 0], 0.0, nn + n[:, 2]  # [z × n, |n| + z·n]
    qn = np.linalg.norm(q, axis=1)
    flip = qn < 1e-12 * np.maximum(nn, 1e-300)  # n = -z (half turn about x) or n = 0
    q[flip] = np.where((nn[flip] > 0)[:, None], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    qn[flip] = 1.0
    return q / qn[:, None]


def quats_x_to(vectors: np.ndarray) -> np.ndarray:
    """Shortest-arc quaternions (M, 4) xyzw turning +x onto each vector (M, 3); a zero vector gives identity."""
    v = np.asarray(vectors, dtype=np.float64)
    vn = np.linalg.norm(v, axis=1)
    q = np.empty((len(v), 4))
    q[:, 0], q[:, 1], q[:, 2], q[:, 3] = 0.0, -v[:, 2], v[:, 1], vn + v[:, 0]  # [x × v, |v| + x·v]
    qn = np.linalg.norm(q, axis=1)
    flip = qn < 1e-12 * np.maximum(vn, 1e-300)  # v = -x (half turn about z) or v = 0
    q[flip] = np.where((vn[flip] > 0)[:, None], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    qn[flip] = 1.0
    return q / qn[:, None]


class StepBatch:
    """Encodes a batch of explorer steps: ``tergodic.StepRecord``, ``foxglove.PosesInFrame`` and
    ``foxglove.SceneUpdate`` (normal line and velocity arrow per agent), for N agents."""

    SCALARS = ("t", "ergodicity", "residual_ref", "touched_fraction", "step_ms")

    def __init__(self, n_agents: int, capacity: int, frame_id: str, line_half: float):
        from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
        from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
        from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

        from tergodic_cli.runlog.proto import VECTOR_FIELDS, step_record_class

        N = n_agents
        self.n_agents, self.capacity, self.line_half = N, capacity, float(line_half)

        # tergodic.StepRecord
        s = _Slots()
        rec = step_record_class()()
        rec.step = 0x0102030405060708  # fixed64: 8 bytes whatever the value
        rec.n_agents = N
        for k, name in enumerate(self.SCALARS):
            setattr(rec, name, s("s", k))
        for name in VECTOR_FIELDS:
            getattr(rec, name).extend([s(name, i, j) for i in range(N) for j in range(3)])
        data = rec.SerializeToString()
        self._rec = _Batch(data, capacity)
        self.rec_step = self._rec.view(_offset(data, struct.pack("<Q", 0x0102030405060708)), (), (), "<u8")
        self.rec_scalars = self._rec.view(*s.layout(data, "s", (5,)), (5,))
        self.rec_vectors = [self._rec.view(*s.layout(data, name, (N, 3)), (N, 3)) for name in VECTOR_FIELDS]

        # foxglove.PosesInFrame (its timestamp is prepended per message)
        s = _Slots()
        poses = PosesInFrame(frame_id=frame_id)
        for i in range(N):
            pose = poses.poses.add()
            pose.position.x, pose.position.y, pose.position.z = (s("p", i, j) for j in range(3))
            o = pose.orientation
            o.x, o.y, o.z, o.w = (s("q", i, j) for j in range(4))
        data = poses.SerializeToString()
        self._poses = _Batch(data, capacity)
        self.pose_pos = self._poses.view(*s.layout(data, "p", (N, 3)), (N, 3))
        self.pose_quat = self._poses.view(*s.layout(data, "q", (N, 4)), (N, 4))
        self._ts_field = PosesInFrame.DESCRIPTOR.fields_by_name["timestamp"].number

        # foxglove.SceneUpdate
        s = _Slots()
        scene = SceneUpdate()
        shaft_d = 0.02 * self.line_half + 1e-4
        for i in range(N):
            # equal-length ids keep every entity the same size, so the slots are evenly spaced
            ent = scene.entities.add(frame_id=frame_id, id=f"agent{i:04d}", frame_locked=True)
            line = ent.lines.add(type=LinePrimitive.LINE_LIST, thickness=2.0, scale_invariant=True)
            line.pose.orientation.w = 1.0
            line.color.r, line.color.g, line.color.b, line.color.a = 0.1, 0.8, 1.0, 1.0
            for end in range(2):
                pt = line.points.add()
                pt.x, pt.y, pt.z = (s(f"l{end}", i, j) for j in range(3))
            arrow = ent.arrows.add(shaft_diameter=shaft_d, head_diameter=3 * shaft_d, head_length=3 * shaft_d)
            arrow.color.r, arrow.color.g, arrow.color.b, arrow.color.a = 1.0, 0.5, 0.0, 1.0
            ap = arrow.pose
            ap.position.x, ap.position.y, ap.position.z = (s("ap", i, j) for j in range(3))
            ap.orientation.x, ap.orientation.y, ap.orientation.z, ap.orientation.w = (s("aq", i, j) for j in range(4))
            arrow.shaft_length = s("len", i)
        data = scene.SerializeToString()
        self._scene = _Batch(data, capacity)
        self.line0 = self._scene.view(*s.layout(data, "l0", (N, 3)), (N, 3))
        self.line1 = self._scene.view(*s.layout(data, "l1", (N, 3)), (N, 3))
        self.arrow_pos = self._scene.view(*s.layout(data, "ap", (N, 3)), (N, 3))
        self.arrow_quat = self._scene.view(*s.layout(data, "aq", (N, 4)), (N, 4))
        self.shaft = self._scene.view(*s.layout(data, "len", (N,)), (N,))

    def encode(self, step: np.ndarray, t_ns: list[int], scalars: np.ndarray, P: np.ndarray, V: np.ndarray,
               Nn: np.ndarray) -> tuple[list[bytes], list[bytes], list[bytes]]:
        """Messages of K steps: step (K,), t_ns K ints, scalars (K, 5) = t, ε, ε_ref, touched, step_ms,
        P, V, Nn (K, N, 3). Returns (step records, poses, scenes), K bytes each."""
        K, N = len(step), self.n_agents
        self.rec_step[:K] = step
        self.rec_scalars[:K] = scalars
        for view, values in zip(self.rec_vectors, (P, V, Nn)):
            view[:K] = values
        self.pose_pos[:K] = P
        self.pose_quat[:K] = quats_z_to(Nn.reshape(-1, 3)).reshape(K, N, 4)  # z along the surface normal
        d = Nn * self.line_half
        self.line0[:K] = P - d
        self.line1[:K] = P + d
        self.arrow_pos[:K] = P
        self.arrow_quat[:K] = quats_x_to(V.reshape(-1, 3)).reshape(K, N, 4)  # the arrow points along v
        self.shaft[:K] = np.minimum(5.0 * np.linalg.norm(V, axis=2), self.line_half)  # 5 s of travel
        return self._rec.messages(K), timestamped(self._ts_field, t_ns, self._poses.messages(K)), self._scene.messages(K)
