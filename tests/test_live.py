"""``explore --live`` (issue 17 item 5): a Foxglove WebSocket client on loopback sees the log's channels."""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
import time

import numpy as np
import pytest
from conftest import REPO, assert_one_line_error, run_cli
from test_runlog import demo_inputs

from tergodic_cli.commands.explore import expand_live
from tergodic_cli.runlog import schema as S
from tergodic_cli.runlog import RunLog
from tergodic_cli.runlog.live import parse_live

BOWL = REPO / "data" / "bowl"
DEADLINE_S = 300.0  # every wait below is bounded by this (event-based: a loaded machine only makes them longer)
# foxglove-sdk 0.30 speaks the protocol under the name foxglove.sdk.v1; foxglove.websocket.v1 is its earlier name
SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")


class FoxgloveClient:
    """The least of a Foxglove WebSocket protocol client (``foxglove.websocket.v1``, called ``foxglove.sdk.v1``
    by foxglove-sdk 0.30): RFC 6455 framing over a plain socket."""

    def __init__(self, port: int, subprotocols: tuple[str, ...] = SUBPROTOCOLS):
        end = time.monotonic() + DEADLINE_S
        while True:
            try:
                self.sock = socket.create_connection(("127.0.0.1", port), timeout=DEADLINE_S)
                break
            except ConnectionRefusedError:
                if time.monotonic() > end:
                    raise
                time.sleep(0.05)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                           f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                           f"Sec-WebSocket-Protocol: {', '.join(subprotocols)}\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(4096)
            assert chunk, "the server closed during the handshake"
            head += chunk
        head, self.buf = head.split(b"\r\n\r\n", 1)
        self.status = head.split(b"\r\n", 1)[0]
        if not head.startswith(b"HTTP/1.1 101"):
            self.subprotocol = None
            return
        self.subprotocol = next(p for p in subprotocols if p.encode() in head.lower())

    def _read(self, n: int) -> bytes:
        while len(self.buf) < n:
            chunk = self.sock.recv(65536)
            assert chunk, "the server closed the connection"
            self.buf += chunk
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def frame(self) -> tuple[int, bytes]:
        """(opcode, payload) of the next whole message (fragments joined)."""
        opcode, data = None, b""
        while True:
            b0, b1 = self._read(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._read(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._read(8))[0]
            mask = self._read(4) if b1 & 0x80 else None
            payload = self._read(n)
            if mask:
                payload = bytes(c ^ mask[i % 4] for i, c in enumerate(payload))
            op = b0 & 0x0F
            if op == 0x9:  # ping: answer, keep reading
                self._send(0xA, payload)
                continue
            opcode = op if opcode is None or op != 0 else opcode
            data += payload
            if b0 & 0x80:
                return opcode, data

    def _send(self, opcode: int, payload: bytes) -> None:
        mask = os.urandom(4)  # clients must mask (RFC 6455 5.3)
        n = len(payload)
        head = bytes((0x80 | opcode,)) + (bytes((0x80 | n,)) if n < 126 else bytes((0x80 | 126,)) + struct.pack(">H", n))
        self.sock.sendall(head + mask + bytes(c ^ mask[i % 4] for i, c in enumerate(payload)))

    def send_json(self, obj: dict) -> None:
        self._send(0x1, json.dumps(obj).encode())

    def close(self) -> None:
        self.sock.close()


@pytest.mark.parametrize("offered", [("foxglove.websocket.v1",), ("foxglove.sdk.v1",)])
def test_clients_of_either_protocol_name_connect_and_get_the_server_info(tmp_path, offered):
    """A client written to the published spec offers only foxglove.websocket.v1; foxglove-sdk's own
    name is foxglove.sdk.v1. Each is answered under the name it offered and then speaks the protocol."""
    inp = demo_inputs(steps=5, seed=1)
    port = _free_port()
    log = RunLog(tmp_path / "run.mcap", config=inp["config"], seed=1, points=inp["points"], target=inp["target"],
                 live=("127.0.0.1", port))
    try:
        client = FoxgloveClient(port, offered)
        assert client.subprotocol == offered[0], client.status
        op, data = client.frame()
        assert op == 0x1 and json.loads(data)["op"] == "serverInfo"
        client.close()
    finally:
        log.close()


def test_a_client_offering_no_foxglove_protocol_is_refused_in_one_line(tmp_path, capfd):
    inp = demo_inputs(steps=5, seed=1)
    port = _free_port()
    log = RunLog(tmp_path / "run.mcap", config=inp["config"], seed=1, points=inp["points"], target=inp["target"],
                 live=("127.0.0.1", port))
    try:
        for _ in range(3):
            client = FoxgloveClient(port, ("chat.v2",))
            assert client.status.startswith(b"HTTP/1.1 400"), client.status
            client.close()
    finally:
        log.close()
    lines = [ln for ln in capfd.readouterr().err.splitlines() if "live:" in ln]
    assert len(lines) == 1 and "foxglove.websocket.v1" in lines[0] and "chat.v2" in lines[0], lines


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_client_sees_the_channels_and_decodes_a_point_cloud(tmp_path):
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

    inp = demo_inputs(steps=120, robot=True, n_agents=2, seed=3)
    port = _free_port()
    log = RunLog(tmp_path / "run.mcap", config=inp["config"], seed=1, points=inp["points"], target=inp["target"],
                 cloud_every=50, flush_every=10, live=("127.0.0.1", port))
    assert log.live.url == f"ws://127.0.0.1:{port}"
    client = None

    def steps(a: int, b: int) -> None:
        for k in range(a, b):
            log.log_step(k + 1, float(k + 1), positions=inp["P"][k], velocities=inp["V"][k], normals=inp["N"][k],
                         metrics={m: v[k] for m, v in inp["metrics"].items()}, step_ms=inp["step_ms"][k],
                         robot=inp["robot"][k])
        c = inp["clouds"].get(b) or inp["clouds"][max(inp["clouds"])]
        log.log_cloud(b, coverage=c["coverage"], heat=c["heat"], source=c["source"])
        log.sync()

    try:
        steps(0, 50)  # the channels exist once they carry a message
        client = FoxgloveClient(port)
        channels, end = {}, time.monotonic() + DEADLINE_S
        while S.TOPIC_CLOUD not in channels or S.TOPIC_TF not in channels:
            assert time.monotonic() < end, f"advertised only {sorted(channels)}"
            op, data = client.frame()
            if op == 0x1:
                msg = json.loads(data)
                if msg["op"] == "serverInfo":
                    assert msg["name"] == "tergodic"
                if msg["op"] == "advertise":
                    channels.update({ch["topic"]: ch for ch in msg["channels"]})
        expected = {S.TOPIC_METRICS: "tergodic.StepRecord", S.TOPIC_AGENT_POSES: "foxglove.PosesInFrame",
                    S.TOPIC_AGENT_SCENE: "foxglove.SceneUpdate", S.TOPIC_CLOUD: "foxglove.PointCloud",
                    S.TOPIC_TF: "foxglove.FrameTransform", S.TOPIC_WRENCH: "tergodic.Wrench",
                    S.TOPIC_WRENCH_SCENE: "foxglove.SceneUpdate", S.TOPIC_EE_POSE: "foxglove.PoseInFrame",
                    S.TOPIC_ROBOT_SAMPLE: "tergodic.RobotSample"}
        for topic, schema in expected.items():  # the MCAP's channels, advertised with their schemas
            assert channels[topic]["schemaName"] == schema, topic
            assert channels[topic]["schema"], topic
        assert {ch["encoding"] for ch in channels.values()} == {"protobuf"}  # one encoding on every channel

        time.sleep(0.2)  # the SDK may send an advertisement before it takes subscriptions to that channel
        client.send_json({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": channels[S.TOPIC_CLOUD]["id"]}]})
        time.sleep(0.2)  # the subscription reaches the server before the next cloud
        sent_after = time.time_ns()
        steps(50, 100)
        end = time.monotonic() + DEADLINE_S
        while True:
            assert time.monotonic() < end, "no point cloud arrived"
            op, data = client.frame()
            if op == 0x2 and data[0] == 0x01:  # binary MessageData: opcode, subscription id, log time, payload
                sub_id, log_time = struct.unpack_from("<IQ", data, 1)
                cloud = PointCloud.FromString(data[13:])
                break
        # the log time is the wall clock when the cloud was written, its stamp the simulated time (step 100 = 100 s)
        assert sub_id == 7 and sent_after <= log_time <= time.time_ns()
        assert cloud.timestamp.seconds * 10**9 + cloud.timestamp.nanos == log.time_origin_ns + 100 * 10**9
        assert cloud.frame_id == S.FRAME_OBJECT and cloud.pose.HasField("position")
        assert len(cloud.data) // cloud.point_stride == len(inp["points"])
        xyz = np.frombuffer(cloud.data, dtype="<f4").reshape(-1, 7)[:, :3]
        np.testing.assert_array_equal(xyz, inp["points"].astype(np.float32))
    finally:
        if client is not None:
            client.close()
        log.close({"steps": 100})


def test_live_address_parsing_and_the_optional_value():
    assert parse_live(None) == ("127.0.0.1", 8765)
    assert parse_live("0.0.0.0:9000") == ("0.0.0.0", 9000)
    assert parse_live(":9001") == ("127.0.0.1", 9001) and parse_live("9002") == ("127.0.0.1", 9002)
    assert parse_live("[::1]:9003") == ("::1", 9003)
    assert expand_live(["explore", str(BOWL), "--live"]) == ["explore", str(BOWL), "--live=127.0.0.1:8765"]
    assert expand_live(["explore", "--live", str(BOWL)]) == ["explore", "--live=127.0.0.1:8765", str(BOWL)]
    assert expand_live(["explore", "--live", "--steps", "5"])[1] == "--live=127.0.0.1:8765"
    assert expand_live(["explore", "--live", "127.0.0.1:9000"]) == ["explore", "--live", "127.0.0.1:9000"]


def test_bad_address_or_busy_port_is_one_line_before_anything_is_written(tmp_path):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        for i, where in enumerate((f"127.0.0.1:{port}", "127.0.0.1:70000", "not an address", "host.invalid:9000")):
            out = tmp_path / f"run{i}"
            res = run_cli("explore", BOWL, "--steps", "5", "--out", out, "--live", where)
            assert_one_line_error(res, "--live")
            assert not out.exists()
    assert_one_line_error(run_cli("explore", BOWL, "--no-log", "--live", "--out", tmp_path / "x"), "--live", "--no-log")
    assert not (tmp_path / "x").exists()


def test_explore_with_live_runs_and_says_where(tmp_path):
    port = _free_port()
    res = run_cli("explore", BOWL, "--steps", "60", "--nk", "60", "--out", tmp_path / "run", "--live", f"127.0.0.1:{port}")
    assert res.code == 0, res.err
    assert f"live: ws://127.0.0.1:{port}" in res.err
    assert (tmp_path / "run" / "run.mcap").is_file()
    with socket.socket() as s:  # the server is gone with the run
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))


@pytest.mark.parametrize("flag", ["--live"])
def test_live_is_in_the_help(flag):
    res = run_cli("explore", "--help")
    assert flag in res.out and "HOST:PORT" in res.out


def test_live_wait_starts_when_a_viewer_connects_and_serves_until_ctrl_c(tmp_path):
    import signal
    import subprocess
    import sys
    from pathlib import Path

    from conftest import default_signals

    port = _free_port()
    exe = Path(sys.executable).with_name("tergodic")
    proc = subprocess.Popen([str(exe), "explore", str(BOWL), "--steps", "30", "--nk", "40", "--live-wait",
                             "--live", f"127.0.0.1:{port}", "--out", str(tmp_path / "run")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=default_signals,
                            env={**os.environ, "TERGODIC_NO_PROGRESS": "1"})
    try:
        seen = []
        for line in proc.stderr:
            seen.append(line)
            if "waiting for a viewer" in line:
                break
        assert any("waiting for a viewer" in ln for ln in seen), seen
        time.sleep(0.5)
        assert proc.poll() is None and not any(tmp_path.glob(".run.tmp-*/summary.json"))  # held before step 1
        client = FoxgloveClient(port, ("foxglove.websocket.v1",))
        assert client.subprotocol == "foxglove.websocket.v1"
        for line in proc.stderr:
            seen.append(line)
            if "serving its final state" in line:
                break
        assert any("serving its final state" in ln for ln in seen), seen
        assert proc.poll() is None  # still serving the viewer
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=300)
        client.close()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, "".join(seen) + err
    assert "live: stopped" in err and "Traceback" not in err
    assert (tmp_path / "run" / "summary.json").exists()  # the run is complete and in place


def test_a_viewer_that_stops_reading_never_holds_the_run(tmp_path):
    """A real client subscribes to every channel, then never reads again (its receive buffer 4 KB) while the
    run logs 20 clouds a second. The run still completes, serves its final state (--live-wait), and a SIGTERM
    then ends the process at once: the stalled viewer is dropped, the run is whole (issue 27)."""
    import fcntl
    import signal
    import subprocess
    import sys
    import termios
    from pathlib import Path

    from conftest import default_signals

    from tergodic_cli.runlog import read_run_log

    port = _free_port()
    exe = Path(sys.executable).with_name("tergodic")
    proc = subprocess.Popen([str(exe), "explore", str(BOWL), "--steps", "600", "--nk", "40", "--log-cloud-every", "5",
                             "--live-wait", "--live", f"127.0.0.1:{port}", "--out", str(tmp_path / "run")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=default_signals,
                            env={**os.environ, "TERGODIC_NO_PROGRESS": "1"})
    client = None
    try:
        seen = []
        for line in proc.stderr:
            seen.append(line)
            if "waiting for a viewer" in line:
                break
        client = FoxgloveClient(port)
        client.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        subscribed, end = set(), time.monotonic() + DEADLINE_S
        while S.TOPIC_CLOUD not in subscribed:  # subscribe to each channel as it is advertised, up to the cloud's
            assert time.monotonic() < end, f"advertised only {sorted(subscribed)}"
            op, data = client.frame()
            msg = json.loads(data) if op == 0x1 else {}
            if msg.get("op") == "advertise":
                client.send_json({"op": "subscribe", "subscriptions": [{"id": ch["id"], "channelId": ch["id"]}
                                                                         for ch in msg["channels"]]})
                subscribed.update(ch["topic"] for ch in msg["channels"])
        # from here on the client reads nothing
        for line in proc.stderr:
            seen.append(line)
            if "serving its final state" in line:
                break
        assert any("serving its final state" in ln for ln in seen), "".join(seen)
        pending = struct.unpack("i", fcntl.ioctl(client.sock.fileno(), termios.FIONREAD, b"\0\0\0\0"))[0]
        assert pending > 0  # the viewer really is behind: data waits in its socket, unread
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)  # generous; the hold ends at once (docs/logging.md)
    finally:
        if client is not None:
            client.close()
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, "".join(seen) + err  # SIGTERM ends the hold, not the run: the run is complete
    assert "live: stopped" in err and "Traceback" not in err
    assert (tmp_path / "run" / "summary.json").exists()
    log = read_run_log(tmp_path / "run")
    assert log.status == "complete" and len(log.clouds) >= 100
