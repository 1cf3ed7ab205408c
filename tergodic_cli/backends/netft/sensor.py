"""ATI Net F/T boxes over their RDT UDP stream (no SDK: the standard library's socket module).

The sensor is asked to stream (command 0x0002, endless) from port 49152; a background thread keeps
the latest record. :meth:`NetFTSensor.read` returns the first record newer than the one it
returned last, waiting at most ``fresh_timeout`` for it (one sample period of a 1 kHz stream is
1 ms): a stream that stops shows up as a repeated sample time, which the safety guard's sensor
watchdog turns into a hold. Records with a non-zero status word read as NaN.

Counts per force and torque and the units come from the box's configuration page
(``http://ADDRESS/netftapi2.xml``) unless given.
"""

from __future__ import annotations

import socket
import threading
import time
import xml.etree.ElementTree as ET
from contextlib import suppress
from dataclasses import dataclass

import numpy as np

from tergodic_cli.errors import TergodicError, require
from tergodic_cli.backends.netft import rdt
from tergodic_cli.robot.interfaces import WrenchSensor


@dataclass
class NetFTConfig:
    """address : host or host:port of the Net F/T box (port 49152 by default).
    counts_per_force, counts_per_torque : the box's cfgcpf / cfgcpt; None = read them over HTTP.
    force_unit, torque_unit : the box's scfgfu / scfgtu (ignored when the counts are read over HTTP).
    frame_in_ee : (4, 4) sensor frame in the TCP frame. tare_samples : records averaged by tare().
    connect_timeout : s to wait for the first record. fresh_timeout : s read() waits for a new record.
    http_port : port of the configuration page.
    """

    address: str
    counts_per_force: float | None = None
    counts_per_torque: float | None = None
    force_unit: str = "N"
    torque_unit: str = "Nm"
    frame_in_ee: np.ndarray | None = None
    tare_samples: int = 50
    connect_timeout: float = 1.0
    fresh_timeout: float = 0.05
    http_port: int = 80

    def host_port(self) -> tuple[str, int]:
        a = str(self.address or "").strip()
        require(a != "", "--ft netft needs the box's address", "pass --ft-address, e.g. 192.168.1.1")
        host, _, port = a.rpartition(":") if a.count(":") == 1 else (a, "", "")
        host = host or a
        try:
            p = int(port) if port else rdt.PORT
        except ValueError:
            raise TergodicError(f"--ft-address '{a}' has a bad port", "give host or host:port, e.g. 192.168.1.1:49152") from None
        require(0 < p < 65536, f"--ft-address port {p} is out of range", "the Net F/T streams on 49152")
        return host, p


def fetch_calibration(host: str, port: int = 80, timeout: float = 2.0) -> dict:
    """counts per force/torque and unit factors from the box's ``netftapi2.xml`` page."""
    from urllib.request import urlopen

    url = f"http://{host}:{port}/netftapi2.xml"
    try:
        with urlopen(url, timeout=timeout) as resp:  # noqa: S310 - the user's sensor on the local network
            root = ET.fromstring(resp.read())
    except Exception as exc:
        raise TergodicError(f"cannot read the Net F/T configuration page {url}: {' '.join(str(exc).split())[:160]}",
                            "check the address, or give the counts per force and torque explicitly") from None
    vals = {el.tag.rsplit("}", 1)[-1].lower(): (el.text or "").strip() for el in root.iter()}
    try:
        cpf, cpt = float(vals["cfgcpf"]), float(vals["cfgcpt"])
    except (KeyError, ValueError):
        raise TergodicError(f"{url} has no counts per force/torque (cfgcpf, cfgcpt)",
                            "give the counts per force and torque explicitly") from None
    return {"counts_per_force": cpf, "counts_per_torque": cpt, "force_unit": vals.get("scfgfu", "N") or "N",
            "torque_unit": vals.get("scfgtu", "Nm") or "Nm"}


class NetFTSensor(WrenchSensor):
    """An ATI Net F/T behind :class:`~tergodic_cli.robot.interfaces.WrenchSensor`.

    ``read().t`` is the host's monotonic clock when the record arrived (s); the record's own
    sequence numbers are kept in ``last_record``. ``tare()`` averages ``tare_samples`` new records.
    """

    bad_tare = ("the Net F/T reported a bad status while taring",
                "check the sensor (its web page shows the status word) and retry")

    def __init__(self, cfg: NetFTConfig):
        self.cfg = cfg
        self.host, self.port = cfg.host_port()
        super().__init__(cfg.frame_in_ee, cfg.tare_samples)
        # scale (6,): counts -> N, N m; _latest: (serial, t, wrench, record) from the receiver
        self.scale = self.sock = self._thread = self._latest = self.last_record = None
        self._stop, self._cv = threading.Event(), threading.Condition()
        self._serial, self._returned = 0, -1

    @property
    def is_connected(self) -> bool:
        return self.sock is not None

    def connect(self) -> None:
        if self.sock is not None:
            return
        cfg = self.cfg
        cal = (fetch_calibration(self.host, cfg.http_port)
               if cfg.counts_per_force is None or cfg.counts_per_torque is None else
               {"counts_per_force": cfg.counts_per_force, "force_unit": cfg.force_unit,
                "counts_per_torque": cfg.counts_per_torque, "torque_unit": cfg.torque_unit})
        fu, tu = cal["force_unit"], cal["torque_unit"]
        require(fu in rdt.FORCE_UNITS, f"unknown Net F/T force unit '{fu}'", f"set the box to one of {', '.join(rdt.FORCE_UNITS)}")
        require(tu in rdt.TORQUE_UNITS, f"unknown Net F/T torque unit '{tu}'", f"set the box to one of {', '.join(rdt.TORQUE_UNITS)}")
        require(cal["counts_per_force"] > 0 and cal["counts_per_torque"] > 0, "counts per force/torque must be > 0",
                "read them from the box's web page (Settings)")
        f = rdt.FORCE_UNITS[fu] / float(cal["counts_per_force"])
        t = rdt.TORQUE_UNITS[tu] / float(cal["counts_per_torque"])
        self.scale = np.array([f, f, f, t, t, t])
        self.calibration = cal
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.connect((self.host, self.port))
            sock.settimeout(0.1)
            sock.send(rdt.request(rdt.CMD_START_REALTIME))
        except OSError as exc:
            sock.close()
            raise TergodicError(f"cannot reach the Net F/T at {self.host}:{self.port}: {exc}", "check the address and the network cable") from None
        self.sock = sock
        self._stop.clear()
        self._thread = threading.Thread(target=self._receive, name="netft-rdt", daemon=True)
        self._thread.start()
        with self._cv:
            got = self._cv.wait_for(lambda: self._latest is not None, timeout=cfg.connect_timeout)
        if not got:
            self.disconnect()
            raise TergodicError(f"the Net F/T at {self.host}:{self.port} sent no data within {cfg.connect_timeout:g} s",
                                    "check the address, that RDT is enabled on the box, and that no firewall drops UDP 49152")

    def _receive(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(1024)
            except socket.timeout:
                continue
            except OSError:
                break
            try:
                seq, ft_seq, status, counts = rdt.parse_record(data)
            except ValueError:
                continue
            w = np.asarray(counts, dtype=float) * self.scale if status == 0 else np.full(6, np.nan)
            with self._cv:
                self._serial += 1
                self._latest = (self._serial, time.monotonic(), w, (seq, ft_seq, status, counts))
                self._cv.notify_all()

    def _sample(self) -> tuple[float, np.ndarray]:
        require(self.sock is not None, "the Net F/T is not connected", "call connect() first")
        with self._cv:
            self._cv.wait_for(lambda: self._latest is not None and self._latest[0] != self._returned, timeout=self.cfg.fresh_timeout)
            serial, t, w, rec = self._latest
        self._returned = serial
        self.last_record = rec
        return t, w

    def disconnect(self) -> None:
        sock = self.sock
        if sock is None:
            return
        self._stop.set()
        with suppress(OSError):
            sock.send(rdt.request(rdt.CMD_STOP))
        if self._thread is not None:
            self._thread.join(timeout=1.0)
        sock.close()
        self.sock = None
