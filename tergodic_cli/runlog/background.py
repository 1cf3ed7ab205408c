"""Write the run log from a child process, so logging costs the explorer a few microseconds a step.

Encoding a step's protobuf messages and compressing chunks takes tens of microseconds,
as long as the kinematic step itself. :class:`BackgroundRunLog` has the same API as
:class:`~tergodic_cli.runlog.writer.RunLog`, but a step only lands in preallocated
arrays; every ``flush_every`` steps the batch goes down a pipe, raw bytes, to a child
process (``python -m tergodic_cli.runlog.background``) that runs the ordinary
:class:`RunLog` on it. On a machine with two or more cores the encoding runs beside the
explorer instead of inside its step.

Wire format (this module is both ends; no pickle): each frame is
``uint32 header length, uint32 payload length, JSON header, payload``; the header names
the operation and the dtype and shape of every array packed, in order, into the payload.

Crash safety is the in-process writer's: when the parent dies (SIGKILL included) the
child sees end-of-file without a ``close`` frame, writes the steps it has as a last
chunk and exits *without* the summary section, so the log reads as truncated and
holds every step that reached the child.
"""

from __future__ import annotations

import json
import math
import collections
import itertools
import os
import select
import struct
import subprocess
import sys
import time
import weakref
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from tergodic_cli.errors import TergodicError
from tergodic_cli.runlog.writer import (CHUNK_BYTES, FLUSH_EVERY, AgentRows, ClosesOnExit, SpectralField, _dumps,
                                        check_field_basis, check_log_args, check_spectral_field)

_FRAME = struct.Struct("<II")
_IOV_BATCH = 64  # buffers per writev call (Linux allows 1024)
_METRIC_NAMES = ("ergodicity", "residual_ref", "touched_fraction")
#: Seconds ``close`` waits for the child to finish the file.
CLOSE_TIMEOUT_S = 300.0
#: Environment switch: ``TERGODIC_LOG_WRITER=inline`` keeps the writer in the explorer's process.
ENV_WRITER = "TERGODIC_LOG_WRITER"
#: Environment switch: the writer child's scheduling, ``batch`` (default), ``idle`` or ``normal``.
ENV_PRIORITY = "TERGODIC_LOG_PRIORITY"


_HEADERS: dict[tuple, str] = {}  # (op, array layout) -> the header's JSON up to its fields


def _pack(op: str, arrays: Mapping[str, np.ndarray] = (), *, borrow: bool = False, **fields: Any) -> list:
    """One frame as parts: the length prefix and JSON header (op, fields, array layout), then
    each array's bytes. With ``borrow`` contiguous arrays are not copied (they must not change
    until written); otherwise each is copied now."""
    layout, blobs, size = [], [], 0
    for name, a in dict(arrays).items():
        a = np.ascontiguousarray(a)
        layout.append((name, a.dtype.str, a.shape))
        blobs.append(memoryview(a).cast("B") if borrow else a.tobytes())
        size += a.nbytes
    key = (op, tuple(layout))
    prefix = _HEADERS.get(key)
    if prefix is None:  # json.dumps costs ~15 µs a call here: the fixed part is made once per layout
        prefix = _HEADERS[key] = json.dumps({"op": op, "arrays": layout})[:-1]
    parts = [prefix]
    for k, v in fields.items():
        if type(v) is int or type(v) is float:  # repr is valid JSON for these (NaN/Infinity as json writes them)
            parts.append(f'"{k}": {_json_number(v)}')
        else:
            try:
                parts.append(f'"{k}": {json.dumps(v)}')
            except TypeError:  # numpy values in a config or summary
                parts.append(f'"{k}": {_dumps(v)}')
    header = (", ".join(parts) + "}").encode()
    return [_FRAME.pack(len(header), size) + header, *blobs]


def _json_number(v: int | float) -> str:
    if type(v) is float and not math.isfinite(v):
        return "NaN" if v != v else ("Infinity" if v > 0 else "-Infinity")
    return repr(v)


def _unpack(header: bytes, payload: bytes) -> tuple[dict, dict[str, np.ndarray]]:
    head = json.loads(header)
    arrays, off = {}, 0
    for name, dtype, shape in head.pop("arrays"):
        dt = np.dtype(dtype)
        if dt.hasobject:  # never objects: this is data, not code
            raise ValueError(f"object array '{name}' in a log frame")
        count = math.prod(shape)
        arrays[name] = np.frombuffer(payload, dtype=dt, count=count, offset=off).reshape(shape)
        off += count * dt.itemsize
    return head, arrays


class LogWriterProcess:
    """The child process that writes a run log, and the pipe that feeds it.

    Start it early (:func:`start_log_writer`): the child spends a few hundred milliseconds
    importing the MCAP stack, which then overlaps the caller's own set-up. Frames go to the
    pipe without blocking: what the pipe cannot take yet waits in memory and goes with the
    next send, so the caller never waits on the child unless more than ``max_pending_bytes``
    pile up (then it does, which bounds memory). No thread: a Python thread would have to
    win the GIL back from the explorer for every write.
    """

    def __init__(self, max_pending_bytes: int = 64 << 20, live: tuple[str, int] | None = None):
        env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
        argv = [sys.executable, "-m", "tergodic_cli.runlog.background"]
        if live is not None:  # the child starts the WebSocket server first thing (see wait_live)
            argv += ["--live", f"{live[0]}:{live[1]}"]
        self.live = live
        self.proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env, close_fds=True)
        self._fd = self.proc.stdin.fileno()
        _grow_pipe(self._fd)
        os.set_blocking(self._fd, False)
        self._pending: collections.deque[memoryview] = collections.deque()
        self._pending_bytes = 0
        self.max_pending_bytes = int(max_pending_bytes)
        self.error: BaseException | None = None
        self._ended = False
        # a writer dropped unused (the run failed before logging) ends its child: end-of-file, nothing written
        self._finalizer = weakref.finalize(self, self.proc.stdin.close)

    def wait_live(self, timeout: float = 30.0) -> str:
        """Block until the child's live server listens; its ws:// URL. A TergodicError if it could not start."""
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        line = self.proc.stdout.readline().decode(errors="replace").strip() if ready else ""
        if line.startswith("live\t"):
            return line.split("\t", 1)[1]
        self.finish(timeout=5.0)
        raise _reported_error(line) or TergodicError(
            "--live: the log writer process did not start its server" + ("" if ready else f" within {timeout:.0f} s"),
            "retry, or run without --live")

    def wait_ready(self, timeout: float = 60.0) -> bool:
        """Block until the child has imported the MCAP stack (benchmarks use it to leave start-up out)."""
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        return bool(ready) and self.proc.stdout.readline().strip() == b"ready"

    def send(self, *parts: bytes | memoryview) -> None:
        """Queue the parts of one frame and write what the pipe takes now.

        Parts are not copied: pass bytes, or views of arrays that do not change afterwards.
        Raises OSError once the child has stopped reading.
        """
        if self.error is not None or self._ended:
            raise BrokenPipeError("the log writer process stopped")
        for part in parts:
            mv = memoryview(part).cast("B")
            if len(mv):
                self._pending.append(mv)
                self._pending_bytes += len(mv)
        self._drain(block=self._pending_bytes > self.max_pending_bytes)

    def send_reused(self, *parts: bytes | memoryview | np.ndarray) -> None:
        """Like :meth:`send`, for parts the caller will overwrite after this call returns
        (a :class:`StepBlock`'s buffer): what the pipe does not take now is copied."""
        if self.error is not None or self._ended:
            raise BrokenPipeError("the log writer process stopped")
        pending = self._pending
        if not pending:  # the common case: straight into the pipe, one system call
            views = [memoryview(p).cast("B") for p in parts]
            try:
                n = os.writev(self._fd, views)
            except BlockingIOError:
                n = 0
            except OSError as exc:
                self.error = exc
                raise
            for mv in views:
                if n >= len(mv):
                    n -= len(mv)
                    continue
                rest = bytes(mv[n:])
                n = 0
                pending.append(memoryview(rest))
                self._pending_bytes += len(rest)
            if pending:
                self._drain(block=self._pending_bytes > self.max_pending_bytes)
            return
        self.send(*(bytes(memoryview(p).cast("B")) for p in parts))

    def _drain(self, block: bool) -> None:
        """Write pending bytes, many buffers per system call; with ``block``, until none are left."""
        pending = self._pending
        try:
            while pending:
                bufs = list(itertools.islice(pending, _IOV_BATCH))
                try:
                    n = os.writev(self._fd, bufs)
                except BlockingIOError:
                    if not block:
                        return
                    select.select([], [self._fd], [], 1.0)
                    continue
                self._pending_bytes -= n
                while n:
                    mv = pending[0]
                    if n >= len(mv):
                        n -= len(mv)
                        pending.popleft()
                    else:
                        pending[0] = mv[n:]
                        n = 0
        except OSError as exc:  # EPIPE: the child is gone
            self.error = exc
            pending.clear()
            raise

    def finish(self, timeout: float = CLOSE_TIMEOUT_S) -> tuple[int, str]:
        """Write what is pending, send end-of-file, wait for the child; (exit code, its last stdout line)."""
        if not self._ended:
            self._ended = True
            self._finalizer.detach()
            if self.error is None:
                try:
                    self._drain(block=True)
                except OSError:
                    pass
            try:
                self.proc.stdin.close()
            except OSError:
                pass
        line = b"ready"
        while line.strip() == b"ready" or line.startswith(b"live\t"):  # its last line comes once the file is complete
            line = self.proc.stdout.readline()
        last = line.decode(errors="replace").strip()
        if last == "ok" and self.live is None:  # the file is finished: leave the child's exit to the system
            self.proc.stdout.close()
            return 0, last
        if last == "ok":  # a live server: wait until its port is free again (a rerun may take it at once)
            self.proc.stdout.close()
            try:
                self.proc.wait(timeout=10.0)
            except subprocess.TimeoutExpired:
                pass
            return 0, last
        self.proc.stdout.close()
        try:
            self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        return self.proc.returncode, last


class StepBlock:
    """A reusable frame of ``k`` steps, and optionally the cloud at the last of them, for
    :meth:`BackgroundRunLog.send_block`. Fill the arrays, then send; the block can be
    refilled as soon as ``send_block`` returns.

    The arrays are views into one byte buffer laid out as the child expects, so sending
    copies nothing and costs one system call, whatever the number of arrays.

    Attributes
    ----------
    rows : (k, 6) float64
        Per step: step number, t (s), ergodicity, residual_ref, touched fraction, step_ms.
    P, V, N : (k, n_agents, 3) float64
        Agent positions (m), velocities (m/s), unit normals.
    PVN : (3, k, n_agents, 3) float64
        P, V and N as one array (they are consecutive in the buffer).
    coverage, source : (n,) float32
        The cloud's fields (when the block has a cloud).
    target : (n,) float32 or None
        The target, in a block made ``with_target``; without it the log repeats the last one.
    heat_coeffs : (n_coeffs,) float64, heat_residual : (n,) float64
        The heat u = Φ a + r (a :class:`SpectralField`); no ``heat_coeffs`` when
        ``n_coeffs`` is 0 (u = r).
    """

    def __init__(self, k: int, n_agents: int, n_points: int = 0, n_coeffs: int = 0, with_target: bool = True):
        layout = [("rows", "<f8", (k, 6))] + [(v, "<f8", (k, n_agents, 3)) for v in ("P", "V", "N")]
        self.has_cloud = n_points > 0
        if self.has_cloud:
            layout += [("cloud.coverage", "<f4", (n_points,)), ("cloud.source", "<f4", (n_points,)),
                       ("cloud.heat.residual", "<f8", (n_points,))]
            if n_coeffs:
                layout.append(("cloud.heat.coeffs", "<f8", (n_coeffs,)))
            if with_target:
                layout.append(("cloud.target", "<f4", (n_points,)))
        size = sum(np.dtype(d).itemsize * math.prod(shape) for _, d, shape in layout)
        self.buf = np.zeros(size, dtype=np.uint8)
        views, off = {}, 0
        for name, d, shape in layout:
            dt = np.dtype(d)
            views[name] = np.ndarray(shape, dtype=dt, buffer=self.buf, offset=off)
            off += dt.itemsize * math.prod(shape)
        self.k = k
        self.rows, self.P, self.V, self.N = views["rows"], views["P"], views["V"], views["N"]
        self.PVN = np.ndarray((3, k, n_agents, 3), dtype="<f8", buffer=self.buf, offset=views["rows"].nbytes)
        self.target = views.get("cloud.target")
        self.coverage = views.get("cloud.coverage")
        self.source = views.get("cloud.source")
        self.heat_residual = views.get("cloud.heat.residual")
        self.heat_coeffs = views.get("cloud.heat.coeffs")
        head = (json.dumps({"op": "steps", "arrays": layout})[:-1] + ', "slow": {}}').encode()
        self.head = _FRAME.pack(len(head), size) + head


def start_log_writer(live: tuple[str, int] | None = None) -> LogWriterProcess | None:
    """Start a log writer child now (None when ``TERGODIC_LOG_WRITER=inline`` or it cannot start);
    with ``live`` (host, port) it also serves the log's channels there (:meth:`LogWriterProcess.wait_live`)."""
    if not use_background_writer():
        return None
    try:
        return LogWriterProcess(live=live)
    except OSError:
        return None


def use_background_writer() -> bool:
    """Whether :func:`open_run_log` starts a child writer (``TERGODIC_LOG_WRITER`` = process|inline)."""
    return os.environ.get(ENV_WRITER, "process").strip().lower() != "inline"


class BackgroundRunLog(ClosesOnExit, AgentRows):
    """A :class:`~tergodic_cli.runlog.writer.RunLog` whose encoding and writing run in a child process.

    Parameters are those of :class:`~tergodic_cli.runlog.writer.RunLog` and mean the same;
    they are validated here, so a bad one raises at once. ``field_basis_file``
    (``basis.meta["evecs_file"]``: the cache file holding ``field_basis`` row for row, and its
    checksum) lets the child read Φ from disk instead of the pipe. The file is the same byte
    layout the in-process writer makes (only the creation time in its metadata differs).

    Notes
    -----
    Per step the caller pays a few array stores. ``flush_every`` steps (or ``flush_seconds``
    of wall time) go to the child together; points clouds, events and ``sync`` go at once,
    in call order. If the child fails (disk full, killed), the next call raises a
    :class:`TergodicError` carrying the child's one-line reason.
    """

    def __init__(self, path: str | os.PathLike, *, config: Mapping[str, Any], seed: int | None,
                 versions: Mapping[str, Any] | None = None, capture_sidecar: Mapping[str, Any] | None = None,
                 points: np.ndarray, target: np.ndarray | None = None, cloud_every: int = 50,
                 compression: str = "lz4", flush_every: int | None = None, flush_seconds: float = 2.0,
                 chunk_bytes: int = CHUNK_BYTES, backend: str = "auto", field_basis: np.ndarray | None = None,
                 writer: LogWriterProcess | None = None, field_basis_file: Mapping[str, str] | None = None,
                 time_origin_ns: int | None = None):
        self.path = Path(path)
        self.time_origin_ns = time.time_ns() if time_origin_ns is None else int(time_origin_ns)  # the run's start
        pts, target, backend = check_log_args(points, target, compression, cloud_every, backend)
        self._field_basis = check_field_basis(field_basis, len(pts))
        self.points, self.target, self.backend = pts, target, backend
        self.cloud_every = int(cloud_every)
        self.flush_every = max(1, int(flush_every) if flush_every else min(self.cloud_every, FLUSH_EVERY))
        self.flush_seconds = float(flush_seconds)
        self.n_steps = 0
        self.n_clouds = 0
        self._closed = False
        self._last_t = 0.0
        self._n_agents = -1
        self._k = 0  # rows pending
        self._rows: list[tuple] = []  # (step, t, ε, ε_ref, touched, step_ms) of the pending rows
        self._shape: tuple = ()
        self._slow: dict[int, dict] = {}  # row -> {"metrics": ..., "robot": ...} of steps off the fast layout
        self._last_send = time.monotonic()
        self._closing = False  # the close frame is sent; the child is finishing the file
        self._blocks: dict[tuple, StepBlock] = {}
        try:  # fail here, in the caller, on an unwritable path (the child re-opens it)
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path, "wb"):
                pass
        except OSError as exc:
            raise TergodicError(f"cannot write {self.path}: {exc.strerror or exc}",
                                "check the folder exists and is writable") from None
        self._writer = writer or LogWriterProcess()
        arrays = {"points": pts.copy(), "target": target.copy()}  # copies: borrowed below
        basis_file = None
        if self._field_basis is not None:
            if field_basis_file:  # the child reads Φ from the basis cache: nothing to send
                basis_file = {"path": str(field_basis_file["path"]), "checksum": str(field_basis_file["checksum"]),
                              "columns": int(self._field_basis.shape[1])}
            else:  # Φ once, not copied: it is sent while the run goes on
                arrays["field_basis"] = self._field_basis
        self._send(_pack("open", arrays, borrow=True, path=str(self.path), config=dict(config),
                         field_basis_file=basis_file,
                         seed=None if seed is None else int(seed), versions=dict(versions or {}) or None,
                         capture_sidecar=None if capture_sidecar is None else dict(capture_sidecar),
                         cloud_every=self.cloud_every, compression=compression, flush_every=self.flush_every,
                         flush_seconds=self.flush_seconds, chunk_bytes=int(chunk_bytes), backend=backend,
                         time_origin_ns=self.time_origin_ns))

    # -- plumbing ------------------------------------------------------------------------------
    def _send(self, parts: list, reused: bool = False) -> None:
        try:
            (self._writer.send_reused if reused else self._writer.send)(*parts)
        except OSError:
            self._closed = True
            code, line = self._writer.finish()
            raise _reported_error(line) or TergodicError(
                f"writing {self.path} failed: the log writer process stopped (exit code {code})",
                "check free disk space and permissions, or set TERGODIC_LOG_WRITER=inline") from None

    def _require_open(self) -> None:
        if self._closed or self._closing:
            raise TergodicError(f"the run log {self.path} is closed", "log steps before close()")

    def _alloc(self, n_agents: int) -> None:
        cap = self.flush_every
        self._P = np.zeros((cap, n_agents, 3))
        self._V = np.zeros((cap, n_agents, 3))
        self._N = np.zeros((cap, n_agents, 3))
        self._n_agents = n_agents
        self._shape = (n_agents, 3)

    def _flush_pending(self) -> None:
        k = self._k
        if k == 0:
            return
        arrays = {"rows": np.array(self._rows, dtype=np.float64), "P": self._P[:k], "V": self._V[:k], "N": self._N[:k]}
        slow = {str(i): v for i, v in self._slow.items()}
        self._k = 0
        self._rows = []
        self._slow = {}
        self._last_send = time.monotonic()
        self._send(_pack("steps", arrays, slow=slow))

    # -- the RunLog API ------------------------------------------------------------------------
    def log_step(self, step: int, t: float, *, positions: np.ndarray, velocities: np.ndarray,
                 normals: np.ndarray, metrics: Mapping[str, float], step_ms: float,
                 robot: Mapping[str, Any] | None = None) -> None:
        """Log one explorer step; see :meth:`RunLog.log_step <tergodic_cli.runlog.writer.RunLog.log_step>`.

        The values are copied: the caller may reuse its arrays at once.
        """
        if self._closed or self._closing:
            self._require_open()
        t = float(t)
        if step < 0 or not 0.0 <= t < math.inf:
            raise TergodicError(f"run log got step {step} at t = {t}", "steps must be >= 0 and times finite, >= 0")
        i = self._k
        try:  # the fast path: three array stores (numpy raises on a shape that does not fit)
            if positions.shape != self._shape:
                raise ValueError
            self._P[i] = positions
            self._V[i] = velocities
            self._N[i] = normals
        except (AttributeError, ValueError, TypeError):
            positions, velocities, normals = self._agent_arrays(positions, velocities, normals)
            i = self._k
            self._P[i], self._V[i], self._N[i] = positions, velocities, normals
        try:
            if len(metrics) != 3:
                raise KeyError
            row = (step, t, metrics["ergodicity"], metrics["residual_ref"], metrics["touched_fraction"], step_ms)
        except KeyError:
            self._slow.setdefault(i, {})["metrics"] = {str(k): float(v) for k, v in metrics.items()}
            row = (step, t, math.nan, math.nan, math.nan, step_ms)
        self._rows.append(row)
        if robot is not None:
            self._slow.setdefault(i, {})["robot"] = dict(robot)
        self._k = i + 1
        self.n_steps += 1
        self._last_t = t
        if self._k == self.flush_every or (
                self.flush_seconds > 0 and (i & 7) == 7 and time.monotonic() - self._last_send >= self.flush_seconds):
            self._flush_pending()

    def log_steps(self, step: np.ndarray, t: np.ndarray, *, positions: np.ndarray, velocities: np.ndarray,
                  normals: np.ndarray, metrics: np.ndarray, step_ms: np.ndarray, cloud: dict | None = None) -> None:
        """Log K steps at once; see :meth:`RunLog.log_steps <tergodic_cli.runlog.writer.RunLog.log_steps>`.

        The cheapest way to log: a caller that keeps its own per-step arrays (as ``tergodic
        explore`` does for ``trajectory.npz``) hands over a block every few dozen steps, with the
        cloud of the block's last step (``cloud``: :meth:`log_cloud`'s keyword arguments) in the
        same frame.
        """
        self._require_open()
        K = len(step)
        if K == 0:
            return
        P = np.asarray(positions, dtype=np.float64)
        if P.ndim != 3 or P.shape[0] != K or P.shape[2] != 3 or np.shape(metrics) != (K, 3) or np.shape(t) != (K,):
            raise TergodicError(f"run log got a block of {K} steps with positions {P.shape}, metrics {np.shape(metrics)}",
                                "pass (K, N, 3) vectors, (K, 3) metrics and (K,) step, t, step_ms")
        rows = np.empty((K, 6))
        rows[:, 0] = step
        rows[:, 1] = t
        rows[:, 2:5] = metrics
        rows[:, 5] = step_ms
        lo = rows[:, :2].min(axis=0)
        if not (lo[0] >= 0.0 and lo[1] >= 0.0 and math.isfinite(rows[:, 1].sum())):
            raise TergodicError("run log got a negative step or a bad time", "steps must be >= 0 and times finite, >= 0")
        arrays = {"rows": rows, "P": P, "V": velocities, "N": normals}
        if cloud is not None:
            arrays.update(self._cloud_arrays(**cloud, prefix="cloud."))
            self.n_clouds += 1
        self._flush_pending()
        self._send(_pack("steps", arrays, slow={}))
        self.n_steps += K
        self._last_t = float(rows[-1, 1])

    def step_block(self, k: int, n_agents: int, cloud: bool = False, n_coeffs: int = 0,
                   with_target: bool = False) -> StepBlock:
        """A reusable :class:`StepBlock` for ``k`` steps of ``n_agents`` agents (with the cloud's
        fields when ``cloud``; ``n_coeffs`` spectral coefficients of the heat, 0 for none; the
        target too when ``with_target``, else the last target logged is repeated)."""
        key = (int(k), int(n_agents), bool(cloud), int(n_coeffs), bool(with_target))
        block = self._blocks.get(key)
        if block is None:
            if cloud and n_coeffs and (self._field_basis is None or self._field_basis.shape[1] != n_coeffs):
                raise TergodicError(f"a cloud block with {n_coeffs} heat coefficients needs a field basis of as many "
                                    "columns", "open the log with field_basis=Explorer.evecs")
            block = self._blocks[key] = StepBlock(k, n_agents, len(self.points) if cloud else 0, n_coeffs, with_target)
        return block

    def send_block(self, block: StepBlock) -> None:
        """Log the block's steps (and cloud), as :meth:`log_steps` would; the block may be refilled at once."""
        self._require_open()
        rows = block.rows
        # scalar reads, not array reductions: this runs every few dozen explorer steps, with cold caches
        if not (rows[0, 0] >= 0.0 and rows[0, 1] >= 0.0 and math.isfinite(rows[-1, 1])):
            raise TergodicError("run log got a negative step or a bad time", "steps must be >= 0 and times finite, >= 0")
        self._flush_pending()
        self._send([block.head, block.buf], reused=True)
        self.n_steps += block.k
        self.n_clouds += block.has_cloud
        self._last_t = float(rows[-1, 1])

    def log_cloud(self, step: int, *, coverage: np.ndarray, heat: np.ndarray | SpectralField, source: np.ndarray,
                  target: np.ndarray | None = None, t: float | None = None) -> None:
        """Log the cloud with per-point fields; see :meth:`RunLog.log_cloud <tergodic_cli.runlog.writer.RunLog.log_cloud>`.

        ``heat`` as a :class:`~tergodic_cli.runlog.writer.SpectralField` (from ``Explorer.cloud_fields()``)
        is reconstructed by the child from the ``field_basis`` sent once at open, so the
        O(n nK) product never runs in the caller.
        """
        self._require_open()
        arrays = self._cloud_arrays(coverage=coverage, heat=heat, source=source, target=target)
        self._flush_pending()
        self.n_clouds += 1
        self._send(_pack("cloud", arrays, step=int(step), t=self._last_t if t is None else float(t)))

    def _cloud_arrays(self, *, coverage, heat, source, target=None, prefix: str = "") -> dict[str, np.ndarray]:
        """A cloud's fields as frame arrays: float32 values, or a SpectralField's coeffs and residual."""
        n = len(self.points)
        arrays = {}
        for name, values in (("target", target), ("coverage", coverage), ("heat", heat), ("source", source)):
            if values is None:
                continue
            if isinstance(values, SpectralField):
                check_spectral_field(values, self._field_basis, n)
                if values.coeffs is not None:
                    arrays[f"{prefix}{name}.coeffs"] = np.asarray(values.coeffs, dtype=np.float64)
                arrays[f"{prefix}{name}.residual"] = np.asarray(values.residual, dtype=np.float64)
                continue
            values = np.asarray(values)
            if values.shape != (n,):
                raise TergodicError(f"run log cloud field {name} has shape {values.shape}, expected ({n},)",
                                    "pass one value per point")
            arrays[prefix + name] = values.astype(np.float32)  # the message's field type: the same rounding as in-process
        return arrays

    def log_event(self, step: int, t: float, text: str, level: str = "info") -> None:
        """Log a ``foxglove.Log`` event after the steps so far."""
        self._require_open()
        self._flush_pending()
        self._send(_pack("event", step=int(step), t=float(t), text=str(text), level=str(level)))

    def sync(self) -> None:
        """Hand everything logged so far to the writer and have it flush the file."""
        self._require_open()
        self._flush_pending()
        self._send(_pack("sync"))

    def begin_close(self, summary: Mapping[str, Any] | None = None, status: str = "ok") -> None:
        """Send the end of the log and return at once: the child finishes the file while the
        caller does other work (explore writes trajectory.npz and summary.json meanwhile).
        :meth:`close` then waits for it. Idempotent."""
        if self._closed or self._closing:
            return
        self._flush_pending()
        self._send(_pack("close", summary=None if summary is None else dict(summary), status=str(status)))
        self._closing = True

    def close(self, summary: Mapping[str, Any] | None = None, status: str = "ok") -> None:
        """Store ``summary`` and finish the file; returns when the file is complete. Idempotent.

        After :meth:`begin_close` it only waits (its summary and status stand)."""
        if self._closed:
            return
        self.begin_close(summary, status)
        self._closed = True
        code, line = self._writer.finish()
        if code != 0 or line != "ok":
            raise _reported_error(line) or TergodicError(
                f"writing {self.path} failed: the log writer process did not finish (exit code {code})",
                "check free disk space and permissions")


def _reported_error(line: str) -> TergodicError | None:
    """The error a child reported as ``error<TAB>problem<TAB>fix``, or None."""
    parts = line.split("\t")
    if parts[0] != "error" or len(parts) < 2:
        return None
    return TergodicError(parts[1], (parts[2] or None) if len(parts) > 2 else None)


def _grow_pipe(fd: int, size: int = 1 << 20) -> None:
    """Ask Linux for a 1 MiB pipe, so a point cloud rarely waits for the child to read."""
    try:
        import fcntl

        fcntl.fcntl(fd, getattr(fcntl, "F_SETPIPE_SZ", 1031), size)
    except (ImportError, OSError):
        pass  # the default 64 KiB pipe works, a little slower


def open_run_log(path: str | os.PathLike, writer: LogWriterProcess | None = None, **kwargs: Any):
    """A run log for ``path``, written by ``writer`` (or a new child process), or in this
    process when ``TERGODIC_LOG_WRITER=inline``. ``kwargs`` are :class:`RunLog`'s."""
    if writer is not None or use_background_writer():
        return BackgroundRunLog(path, writer=writer, **kwargs)
    from tergodic_cli.runlog.writer import RunLog

    kwargs.pop("field_basis_file", None)  # in this process Φ is at hand
    return RunLog(path, **kwargs)


# ---------------------------------------------------------------------------------------------
# The child: read frames from stdin, run the in-process RunLog on them.
# ---------------------------------------------------------------------------------------------
def _read_exact(fh: Any, n: int) -> bytes | None:
    buf = bytearray(n)
    view, got = memoryview(buf), 0
    while got < n:
        r = fh.readinto(view[got:])
        if not r:
            return None
        got += r
    return bytes(buf)


def _write_steps(log: Any, a: dict[str, np.ndarray], slow: dict[str, dict]) -> None:
    """Rows of the fast layout in bulk; a row with a robot sample or other metrics through log_step."""
    rows, P, V, N = a["rows"], a["P"], a["V"], a["N"]
    step, t, m, step_ms = rows[:, 0].astype(np.int64), rows[:, 1], rows[:, 2:5], rows[:, 5]
    if not slow:
        log.log_steps(step, t, positions=P, velocities=V, normals=N, metrics=m, step_ms=step_ms)
        return
    for i in range(len(step)):
        extra = slow.get(str(i)) or {}
        metrics = extra.get("metrics") or dict(zip(_METRIC_NAMES, m[i].tolist()))
        log.log_step(int(step[i]), float(t[i]), positions=P[i], velocities=V[i], normals=N[i], metrics=metrics,
                     step_ms=float(step_ms[i]), robot=extra.get("robot"))


def _cloud_fields(a: dict[str, np.ndarray], prefix: str = "", have_basis: bool = True) -> dict:
    """log_cloud's field arguments from frame arrays (``name`` or ``name.coeffs`` / ``name.residual``);
    without the field basis a spectral field is logged as NaN."""
    fields = {}
    for name in ("target", "coverage", "heat", "source"):
        key = prefix + name
        if key in a:
            fields[name] = a[key]
        elif f"{key}.residual" in a:
            coeffs = a.get(f"{key}.coeffs")
            if coeffs is not None and not have_basis:
                fields[name] = np.full(len(a[f"{key}.residual"]), np.nan)
            else:
                fields[name] = SpectralField(coeffs, a[f"{key}.residual"])
    return fields


def _read_field_basis(ref: Mapping[str, Any], n: int) -> tuple[np.ndarray | None, str | None]:
    """Φ (n, columns) from the basis cache file ``ref`` names, or (None, why not)."""
    from tergodic_cli.checked_npy import CacheMiss, read_checked_array

    try:
        phi = read_checked_array(ref["path"], ref["checksum"])
    except CacheMiss as exc:
        return None, f"the basis cache file {ref['path']} changed or became unreadable since the run started ({exc})"
    cols = int(ref["columns"])
    if phi.ndim != 2 or phi.shape[0] != n or phi.shape[1] < cols:
        return None, f"the basis cache file {ref['path']} does not fit this cloud"
    return (phi if phi.shape[1] == cols else np.ascontiguousarray(phi[:, :cols])), None


_ABANDONED: list = []


def _serve(fh: Any, live: Any = None) -> int:
    """Run the writer on the frames in ``fh``; the exit code (0 closed, 3 abandoned by the parent).
    ``live``: a :class:`~tergodic_cli.runlog.live.LiveServer` the log also streams to."""
    from tergodic_cli.runlog.writer import RunLog

    log = None
    while True:
        head = _read_exact(fh, _FRAME.size)
        if head is None:
            break
        hlen, plen = _FRAME.unpack(head)
        header = _read_exact(fh, hlen)
        payload = _read_exact(fh, plen) if plen else b""
        if header is None or payload is None:
            break
        h, a = _unpack(header, payload)
        op = h["op"]
        if op == "steps":
            _write_steps(log, a, h["slow"])
            cloud = _cloud_fields(a, "cloud.", log._field_basis is not None)
            if cloud:  # the block's last step's cloud, sent in the same frame
                log.log_cloud(int(a["rows"][-1, 0]), **cloud)
        elif op == "cloud":
            log.log_cloud(h["step"], t=h["t"], **_cloud_fields(a, "", log._field_basis is not None))
        elif op == "event":
            log.log_event(h["step"], h["t"], h["text"], h["level"])
        elif op == "sync":
            log.sync()
        elif op == "open":
            field_basis, missing = a.get("field_basis"), None
            if h.get("field_basis_file"):
                field_basis, missing = _read_field_basis(h["field_basis_file"], len(a["points"]))
            log = RunLog(h["path"], config=h["config"], seed=h["seed"], versions=h["versions"],
                         capture_sidecar=h["capture_sidecar"], points=a["points"], target=a["target"],
                         field_basis=field_basis,
                         cloud_every=h["cloud_every"], compression=h["compression"], flush_every=h["flush_every"],
                         flush_seconds=h["flush_seconds"], chunk_bytes=h["chunk_bytes"], backend=h["backend"],
                         time_origin_ns=h.get("time_origin_ns"), live=live)
            if missing:
                log.log_event(0, 0.0, f"warning: the heat field is not logged: {missing}", "warning")
        elif op == "close":
            log.close(h["summary"], status=h["status"])
            return 0
        else:
            raise ValueError(f"unknown log frame '{op}'")
    if log is not None:  # the parent died: keep what arrived, leave the file without its summary (truncated)
        log.sync()
        _ABANDONED.append(log)  # freeing the writer would finish the file (foxglove-sdk closes it on drop)
    return 3


def _warm_up(RunLog: type) -> None:
    """Run every code path once on a throw-away file while the parent is still importing, so
    the real run does not pay first-call costs (templates, schemas, native writer set-up)."""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="tergodic-log-warm-") as tmp:
        rng = np.random.default_rng(0)
        pts = rng.standard_normal((8, 3))
        log = RunLog(Path(tmp) / "warm.mcap", config={}, seed=0, points=pts, field_basis=np.eye(8, 2))
        z = np.zeros((2, 1, 3))
        log.log_steps(np.arange(1, 3), np.arange(1.0, 3.0), positions=z, velocities=z, normals=z + 1.0,
                      metrics=np.zeros((2, 3)), step_ms=np.zeros(2))
        log.log_cloud(2, coverage=np.zeros(8), heat=SpectralField(np.ones(2), np.zeros(8)), source=np.zeros(8))
        log.log_event(2, 2.0, "warm-up")
        log.close({"steps": 2})


def _yield_to_parent() -> None:
    """Keep the child out of the explorer's way (``TERGODIC_LOG_PRIORITY``: batch (default),
    idle or normal). Woken by the parent's write, a normal child tends to run on the parent's
    core and pre-empt the explorer until the scheduler moves it. Linux ``SCHED_BATCH`` never
    pre-empts on wake-up but keeps a fair share of the CPU, so ``close`` never waits long on a
    busy machine; ``SCHED_IDLE`` runs the child only on a free core (on a busy machine the
    work then piles up until ``close``)."""
    policy = {"batch": "SCHED_BATCH", "idle": "SCHED_IDLE"}.get(os.environ.get(ENV_PRIORITY, "batch"))
    if policy is None or not hasattr(os, policy):
        return
    try:
        os.sched_setscheduler(0, getattr(os, policy), os.sched_param(0))
    except OSError:
        pass


def _quiet_foxglove() -> None:
    """foxglove-sdk prints its write errors (e.g. a full disk) on stderr beside the one line the
    parent prints from our report; FOXGLOVE_LOG_LEVEL still wins."""
    try:
        import foxglove

        foxglove.set_log_level("CRITICAL")
    except (ImportError, AttributeError):
        pass


def _start_live(argv: list[str]) -> Any:
    """The live server ``--live HOST:PORT`` asks for, started before the heavy imports; its URL goes
    to the parent at once (a bind failure is reported as the child's one error line). The SDK's
    own lines stay quiet (:func:`_quiet_foxglove`)."""
    if "--live" not in argv:
        return None
    from tergodic_cli.runlog.live import LiveServer

    live = LiveServer.start(argv[argv.index("--live") + 1])
    sys.stdout.write(f"live\t{live.url}\n")
    sys.stdout.flush()
    return live


def main() -> None:
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the parent, which closes the log properly
    _quiet_foxglove()
    live = None
    try:
        live = _start_live(sys.argv)
    except TergodicError as exc:
        sys.stdout.write(f"error\t{exc.problem}\t{exc.fix or ''}".replace("\n", " ") + "\n")
        sys.stdout.flush()
        os._exit(2)
    _yield_to_parent()
    try:
        from tergodic_cli.runlog import writer as _w  # the MCAP stack, before saying ready
        from tergodic_cli.runlog.proto import step_record_class

        import tergodic_cli.checked_npy  # noqa: F401  (reads Φ from the basis cache at open; no scipy)

        _w._proto_classes(), step_record_class(), _w.foxglove_sdk_available()  # build the schemas once, now
        _warm_up(_w.RunLog)
        try:
            sys.stdout.write("ready\n")
            sys.stdout.flush()
        except OSError:  # the parent is gone already: still write what it sent
            pass
        code = _serve(sys.stdin.buffer, live)
        msg = "ok" if code == 0 else "abandoned"
    except TergodicError as exc:
        code, msg = 2, f"error\t{exc.problem}\t{exc.fix or ''}"
    except Exception as exc:  # noqa: BLE001 - reported to the parent in one line
        code, msg = 1, f"error\tthe log writer failed: {type(exc).__name__}: {exc}\tset TERGODIC_LOG_WRITER=inline"
    try:
        sys.stdout.write(msg.replace("\n", " ") + "\n")
        sys.stdout.flush()
    except OSError:
        pass
    if live is not None:
        live.stop()
    os._exit(code)  # no interpreter teardown: the MCAP writer must not finish a file the parent abandoned


if __name__ == "__main__":
    main()
