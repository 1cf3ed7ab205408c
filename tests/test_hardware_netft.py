"""ATI Net F/T over its RDT UDP protocol, against a real UDP server on 127.0.0.1 (tests/fakes/netft_server.py).

Loopback only, every server bounded in time (max_seconds) and closed by its context manager.
"""

from __future__ import annotations

import struct
import threading
import time
from http.server import BaseHTTPRequestHandler, HTTPServer

import numpy as np
import pytest

from fakes import install, scenario
from fakes.netft_server import NetFTServer

from tergodic_cli.errors import TergodicError
from tergodic_cli.backends.netft import NetFTConfig, NetFTSensor, rdt
from tergodic_cli.robot.safety import SafetyConfig, SafetyGuard

W = np.array([1.5, -2.25, 10.0, 0.1, -0.2, 0.05])


def _eventually(cond, seconds: float = 60.0) -> bool:
    """Poll a condition on the server thread's state (UDP is asynchronous), bounded in time (generously:
    it returns as soon as the condition holds, and a loaded machine delays the server's thread)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.005)
    return cond()


def _sensor(port, **kw) -> NetFTSensor:
    kw.setdefault("counts_per_force", 1_000_000.0)
    kw.setdefault("counts_per_torque", 1_000_000.0)
    return NetFTSensor(NetFTConfig(address=f"127.0.0.1:{port}", **kw))


def test_wire_format_round_trips():
    assert rdt.request(rdt.CMD_START_REALTIME, 0) == bytes.fromhex("1234000200000000")
    rec = struct.pack(">IIIiiiiii", 3, 7, 0, 1, -2, 3, -4, 5, -6)  # the box's side of the wire
    assert len(rec) == 36
    assert rdt.parse_record(rec) == (3, 7, 0, (1, -2, 3, -4, 5, -6))
    with pytest.raises(ValueError):
        rdt.parse_record(rec[:-1])


def test_reads_the_stream_in_newtons():
    with NetFTServer(lambda: W, max_seconds=300) as srv:
        s = _sensor(srv.port)
        s.connect()
        try:
            r1, r2 = s.read(), s.read()
            np.testing.assert_allclose(r1.wrench, W, atol=1e-6)  # counts / counts-per-unit, exactly
            assert r2.t > r1.t  # every read is a new record
            assert s.last_record[0] >= 2 and s.last_record[2] == 0
            s.tare()
            np.testing.assert_allclose(s.read().wrench, 0.0, atol=1e-6)
        finally:
            s.disconnect()
        assert srv.requests[0] == (rdt.CMD_START_REALTIME, 0)
        assert _eventually(lambda: srv.requests[-1] == (rdt.CMD_STOP, 0))


def test_box_units_are_converted_to_si():
    lbf = np.array([1.0, -2.0, 3.0, 4.0, 5.0, -6.0])  # the box is set to lbf and lbf-in
    with NetFTServer(lambda: lbf, counts_per_force=1000, counts_per_torque=1000, max_seconds=300) as srv:
        s = _sensor(srv.port, counts_per_force=1000, counts_per_torque=1000, force_unit="lbf", torque_unit="lbf-in")
        s.connect()
        try:
            w = s.read().wrench
        finally:
            s.disconnect()
    np.testing.assert_allclose(w[:3], lbf[:3] * 4.4482216152605, rtol=1e-9)
    np.testing.assert_allclose(w[3:], lbf[3:] * 0.112984829027617, rtol=1e-9)


def test_calibration_from_the_web_page():
    xml = (b"<?xml version='1.0'?><netft><cfgcpf>1000</cfgcpf><cfgcpt>10</cfgcpt>"
           b"<scfgfu>N</scfgfu><scfgtu>Nmm</scfgtu></netft>")

    class Page(BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802
            self.send_response(200 if self.path == "/netftapi2.xml" else 404)
            self.end_headers()
            self.wfile.write(xml)

        def log_message(self, *a):
            pass

    http = HTTPServer(("127.0.0.1", 0), Page)
    th = threading.Thread(target=http.serve_forever, daemon=True)
    th.start()
    try:
        with NetFTServer(lambda: W, counts_per_force=1000, counts_per_torque=10, max_seconds=300) as srv:
            # the box's torque unit is N·mm: the source's W[3:] are N·mm values on the wire
            s = NetFTSensor(NetFTConfig(address=f"127.0.0.1:{srv.port}", http_port=http.server_address[1]))
            s.connect()
            try:
                w = s.read().wrench
            finally:
                s.disconnect()
        assert s.calibration == {"counts_per_force": 1000.0, "counts_per_torque": 10.0, "force_unit": "N", "torque_unit": "Nmm"}
        np.testing.assert_allclose(w[:3], W[:3], atol=1e-3)
        np.testing.assert_allclose(w[3:], np.round(W[3:] * 10) / 10 * 1e-3, atol=1e-9)
    finally:
        http.shutdown()
        http.server_close()


def test_bad_status_reads_nan_and_a_stalled_stream_trips_the_guard():
    status = {"v": 0}
    with NetFTServer(lambda: W, status=lambda: status["v"], max_seconds=300) as srv:
        s = _sensor(srv.port, fresh_timeout=0.02)
        s.connect()
        try:
            guard = SafetyGuard(SafetyConfig(sensor_timeout=0.05), np.full(7, -3), np.full(7, 3), np.full(7, 2), 5.0)
            r = s.read()
            assert guard.check_sensor(0.0, r.t, r.wrench) is None
            status["v"] = 0x80010000  # an error bit in the status word
            assert _eventually(lambda: np.all(np.isnan(s.read().wrench)))  # records already in flight drain first
            r = s.read()
            assert np.all(np.isnan(r.wrench))
            assert guard.check_sensor(0.01, r.t, r.wrench).reason.startswith("the force/torque sensor returned non-finite")
            status["v"] = 0
            assert _eventually(lambda: np.all(np.isfinite(s.read().wrench)))
            srv.paused = True  # the box stops sending
            assert _eventually(lambda: s.read().t == s.read().t)  # no new record: the same sample again
            t_last = s.read().t
            r = s.read()
            assert r.t == t_last
            assert guard.check_sensor(1.0, r.t, r.wrench) is None
            fault = guard.check_sensor(1.1, r.t, r.wrench)
            assert fault is not None and "stopped updating" in fault.reason and fault.action == "hold"
        finally:
            s.disconnect()


def test_no_box_is_a_one_line_error():
    with NetFTServer(lambda: W, max_seconds=300) as srv:
        port = srv.port  # a port that existed: closed again below
    s = _sensor(port, connect_timeout=0.3)
    with pytest.raises(TergodicError) as e:
        s.connect()
    assert "sent no data within 0.3 s" in str(e.value) and "\n" not in str(e.value)
    assert not s.is_connected
    with pytest.raises(TergodicError, match="bad port"):
        NetFTSensor(NetFTConfig(address="127.0.0.1:http"))


@pytest.fixture(scope="module")
def plate():
    pytest.importorskip("pygafro")
    return scenario.make_plate()


def test_exploration_loop_with_netft(plate, monkeypatch):
    from tergodic_cli.backends import HardwareRunConfig, explore_with_hardware, make_hardware

    install(monkeypatch, "franky")
    world = scenario.world(plate, monkeypatch, normal_force_bias=-1.0)
    cfg = scenario.robot_config(plate)
    ex = scenario.explorer(plate, cfg)
    with NetFTServer(world.sensor_wrench, counts_per_force=1e6, counts_per_torque=1e6, max_seconds=60) as srv:
        arm, sensor = make_hardware("franka", scenario.ROBOT_IP, "netft", f"127.0.0.1:{srv.port}",
                                    counts_per_force=1e6, counts_per_torque=1e6)
        out = explore_with_hardware(plate.capture, ex, cfg, 10, arm, sensor, hw=HardwareRunConfig(move_speed=0.3),
                                    pace=world.advance)
        assert _eventually(lambda: srv.requests[-1] == (rdt.CMD_STOP, 0))  # the stream was stopped on the way out
    assert out["final_state"] == "done", out["stop_reason"]
    assert out["force_mean_N"] == pytest.approx(5.0, rel=0.1)
    assert out["track_mm_median"] < 1.0 and out["contact_fraction"] == 1.0
    assert not sensor.is_connected
