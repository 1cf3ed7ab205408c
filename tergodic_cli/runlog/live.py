"""``tergodic explore --live``: stream the run log's channels to Foxglove over WebSocket.

foxglove-sdk's server on the log's own ``foxglove.Context``: each message is encoded once and
goes to the file and to every subscribed client (docs/logging.md).
"""

from __future__ import annotations

import errno
import socket
import time
from dataclasses import dataclass
from typing import Any

from tergodic_cli.errors import TergodicError

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765
DEFAULT = f"{DEFAULT_HOST}:{DEFAULT_PORT}"
_FIX = "give HOST:PORT, e.g. --live 127.0.0.1:8765 (or --live alone for that default)"


def parse_live(text: str | None) -> tuple[str, int]:
    """``HOST:PORT``, ``:PORT``, ``PORT`` or ``[IPv6]:PORT`` -> (host, port); host defaults to 127.0.0.1."""
    raw = (text or "").strip() or DEFAULT
    host, _, port_txt = raw.rpartition(":")  # no ":": the host is ""
    host = host.strip() or DEFAULT_HOST
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    try:
        port = int(port_txt)
    except ValueError:
        raise TergodicError(f"--live '{raw}' is not HOST:PORT", _FIX) from None
    if not 1 <= port <= 65535:
        raise TergodicError(f"--live port {port} is outside 1..65535", _FIX)
    if any(c.isspace() for c in host) or "/" in host:
        raise TergodicError(f"--live '{raw}' is not HOST:PORT", _FIX)
    return host, port


def check_bindable(host: str, port: int) -> None:
    """Raise a one-line TergodicError unless a server can listen on host:port now.

    Bound and closed at once, with SO_REUSEADDR as the server sets it: a port held by another
    listener fails, one in TIME_WAIT does not.
    """
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise TergodicError(f"--live host '{host}' does not resolve ({exc.strerror})", _FIX) from None
    family, _, _, _, addr = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(addr)
            s.listen(1)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise TergodicError(f"--live {host}:{port}: the port is in use",
                                    "stop what listens there, or choose another port: --live HOST:PORT") from None
            raise TergodicError(f"--live {host}:{port}: cannot listen there ({exc.strerror or exc})", _FIX) from None


@dataclass
class LiveServer:
    """A running foxglove-sdk WebSocket server and the context its channels live in."""

    host: str
    port: int
    context: Any
    server: Any

    @classmethod
    def start(cls, where: str | tuple[str, int]) -> "LiveServer":
        import foxglove

        host, port = parse_live(where) if isinstance(where, str) else (str(where[0]), int(where[1]))
        ctx = foxglove.Context()
        try:
            server = foxglove.start_server(name="tergodic", host=host, port=port, context=ctx)
        except Exception as exc:  # noqa: BLE001 - the SDK raises its own error type for bind failures
            raise TergodicError(f"--live {host}:{port}: the server did not start ({str(exc).splitlines()[0][:120]})",
                                "stop what listens there, or choose another port: --live HOST:PORT") from None
        return cls(host, server.port, ctx, server)

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def stop(self, wait_s: float = 2.0) -> None:
        """Stop the server and wait (up to ``wait_s`` seconds) until its port is free: the SDK
        shuts its listener down on its own thread, and a next run may want the same port."""
        try:
            self.server.stop()
        except Exception:  # noqa: BLE001 - best effort at the end of a run
            return
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            try:
                return check_bindable(self.host, self.port)
            except TergodicError:
                time.sleep(0.02)
