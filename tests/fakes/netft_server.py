"""A Net F/T box on the loopback interface: a real UDP server speaking ATI's RDT protocol.

Bound to 127.0.0.1 on an ephemeral port, it answers the documented requests (0x0002 start real-time
streaming with a sample count, 0 = endless; 0x0000 stop; 0x0042 set bias) by sending 36-byte records
to the requester at ``rate_hz``, with the wrench of a data source (a callable returning (6,) N, N m)
scaled by counts per force/torque. It stops by itself after ``max_seconds`` and on close().
"""

from __future__ import annotations

import socket
import struct
import threading
import time

import numpy as np

HEADER = 0x1234


class NetFTServer:
    def __init__(self, source, counts_per_force: float = 1_000_000.0, counts_per_torque: float = 1_000_000.0,
                 rate_hz: float = 1000.0, max_seconds: float = 60.0, status=lambda: 0):
        self.source = source
        self.cpf, self.cpt = float(counts_per_force), float(counts_per_torque)
        self.period = 1.0 / rate_hz
        self.max_seconds = float(max_seconds)
        self.status = status
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.0005)
        self.port = self.sock.getsockname()[1]
        self.requests: list[tuple[int, int]] = []
        self.sent = 0
        self.bias = np.zeros(6)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="fake-netft", daemon=True)
        self.paused = False

    def __enter__(self) -> "NetFTServer":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.sock.close()

    def _serve(self) -> None:
        t_end = time.monotonic() + self.max_seconds
        peer, remaining, seq, ft_seq = None, 0, 0, 0
        next_t = time.monotonic()
        while not self._stop.is_set() and time.monotonic() < t_end:
            try:
                data, addr = self.sock.recvfrom(64)
                if len(data) == 8:
                    header, cmd, count = struct.unpack(">HHI", data)
                    if header == HEADER:
                        self.requests.append((cmd, count))
                        if cmd in (0x0002, 0x0003):
                            peer, remaining = addr, (count if count else -1)
                        elif cmd == 0x0000:
                            peer = None
                        elif cmd == 0x0042:
                            self.bias = np.asarray(self.source(), dtype=float)
            except socket.timeout:
                pass
            now = time.monotonic()
            while peer is not None and remaining != 0 and now >= next_t and not self.paused:
                w = np.asarray(self.source(), dtype=float) - self.bias
                w = np.nan_to_num(w)
                counts = [int(round(x * self.cpf)) for x in w[:3]] + [int(round(x * self.cpt)) for x in w[3:]]
                seq += 1
                ft_seq += 7  # the box's internal rate is higher than the UDP rate
                self.sock.sendto(struct.pack(">IIIiiiiii", seq, ft_seq, int(self.status()), *counts), peer)
                self.sent += 1
                remaining = remaining - 1 if remaining > 0 else remaining
                next_t += self.period
            if now - next_t > 0.05:  # never burst to catch up after a stall
                next_t = now
