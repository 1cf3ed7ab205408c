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

    bridge: "SubprotocolBridge | None" = None

    @classmethod
    def start(cls, where: str | tuple[str, int]) -> "LiveServer":
        """The SDK's server on a private loopback port, behind a :class:`SubprotocolBridge` on ``where``."""
        import foxglove

        host, port = parse_live(where) if isinstance(where, str) else (str(where[0]), int(where[1]))
        check_bindable(host, port)
        ctx = foxglove.Context()
        try:
            server = foxglove.start_server(name="tergodic", host="127.0.0.1", port=0, context=ctx)
        except Exception as exc:  # noqa: BLE001 - the SDK raises its own error type for bind failures
            raise TergodicError(f"--live {host}:{port}: the server did not start ({str(exc).splitlines()[0][:120]})",
                                "stop what listens there, or choose another port: --live HOST:PORT") from None
        try:
            bridge = SubprotocolBridge(host, port, server.port)
        except OSError as exc:
            server.stop()
            raise TergodicError(f"--live {host}:{port}: cannot listen there ({exc.strerror or exc})", _FIX) from None
        return cls(host, bridge.port, ctx, server, bridge)

    def wait_for_viewer(self) -> None:
        """Block until a viewer has completed its handshake (Ctrl-C and SIGTERM interrupt the wait)."""
        while self.bridge is not None and not self.bridge.connected.wait(0.2):
            pass

    def hold(self, say) -> None:
        """Keep the server (and the viewers' connections, showing the final state) up until Ctrl-C or
        SIGTERM, which end the hold, not the run: the run is complete."""
        try:  # the line inside: a Ctrl-C right after it still ends the hold, not the run
            say("live: the run is complete; serving its final state until Ctrl-C")
            while True:
                time.sleep(0.2)
        except KeyboardInterrupt:
            say("live: stopped")

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def stop(self, wait_s: float = 2.0) -> None:
        """Stop the server and wait (up to ``wait_s`` seconds) until its port is free: the SDK
        shuts its listener down on its own thread, and a next run may want the same port."""
        if self.bridge is not None:
            self.bridge.stop()
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


#: The protocol's names: foxglove-sdk 0.30 accepts only the first; clients written to the published
#: ws-protocol spec (Lichtblick, older Foxglove builds) offer the second. The protocol is the same.
SDK_SUBPROTOCOL, SPEC_SUBPROTOCOL = "foxglove.sdk.v1", "foxglove.websocket.v1"
_MAX_HEADER = 16384


class SubprotocolBridge:
    """The public ``--live`` port: forwards each WebSocket connection to the SDK's private port,
    renaming the subprotocol a ``foxglove.websocket.v1`` client offers (and the server's answer), so
    clients of either name connect. A client offering neither gets a 400 and one line on stderr.

    One thread accepts; one thread per connection pumps bytes both ways. A slow viewer only slows its
    own pump; the SDK drops what that viewer cannot take, so the run never waits for it.
    """

    def __init__(self, host: str, port: int, upstream_port: int):
        import threading

        family, _, _, _, addr = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0]
        self.sock = socket.socket(family, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self.sock.bind(addr)
            self.sock.listen(16)
        except OSError:
            self.sock.close()
            raise
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]
        self.upstream = ("127.0.0.1", int(upstream_port))
        self.connected = threading.Event()  # set once a viewer completed its handshake
        self._stop = threading.Event()
        self._conns: list[socket.socket] = []
        self._said: set[str] = set()
        self._thread = threading.Thread(target=self._accept, name="tergodic-live-bridge", daemon=True)
        self._thread.start()

    def _accept(self) -> None:
        import threading

        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except (TimeoutError, socket.timeout):
                continue
            except OSError:
                return
            self._conns.append(conn)
            threading.Thread(target=self._serve, args=(conn,), name="tergodic-live-client", daemon=True).start()

    def _say(self, line: str) -> None:
        import sys

        if line not in self._said:  # once per reason, not once per attempt
            self._said.add(line)
            sys.stderr.write(line + "\n")

    def _serve(self, client: socket.socket) -> None:
        upstream = None
        try:
            client.settimeout(10.0)
            head, rest = _read_header(client)
            if head is None:
                return
            lines = head.split(b"\r\n")
            offered, at = [], None
            for i, line in enumerate(lines):
                name, _, value = line.partition(b":")
                if name.strip().lower() == b"sec-websocket-protocol":
                    offered, at = [v.strip().decode("latin-1") for v in value.split(b",")], i
            if SDK_SUBPROTOCOL not in offered and SPEC_SUBPROTOCOL not in offered:
                self._say(f"tergodic: live: refused a viewer offering {', '.join(offered) or 'no subprotocol'}; "
                          f"connect with Foxglove or Lichtblick (subprotocol {SDK_SUBPROTOCOL} or {SPEC_SUBPROTOCOL})")
                client.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\nConnection: close\r\n\r\n")
                return
            legacy = SDK_SUBPROTOCOL not in offered
            if legacy:
                lines[at] = b"Sec-WebSocket-Protocol: " + SDK_SUBPROTOCOL.encode()
            upstream = socket.create_connection(self.upstream, timeout=10.0)
            self._conns.append(upstream)
            upstream.sendall(b"\r\n".join(lines) + b"\r\n\r\n" + rest)
            answer, more = _read_header(upstream)
            if answer is None:
                return
            if legacy:
                answer = answer.replace(SDK_SUBPROTOCOL.encode(), SPEC_SUBPROTOCOL.encode())
            client.sendall(answer + b"\r\n\r\n" + more)
            if answer.startswith(b"HTTP/1.1 101"):
                self.connected.set()
            _pump(client, upstream, self._stop)
        except OSError:
            pass
        finally:
            for s in (client, upstream):
                if s is not None:
                    with _suppress_os():
                        s.close()

    def stop(self) -> None:
        """Close the port and every connection."""
        self._stop.set()
        with _suppress_os():
            self.sock.close()
        for s in list(self._conns):
            with _suppress_os():
                s.shutdown(socket.SHUT_RDWR)
            with _suppress_os():
                s.close()
        self._thread.join(timeout=1.0)


def _suppress_os():
    from contextlib import suppress

    return suppress(OSError)


def _read_header(sock: socket.socket) -> tuple[bytes | None, bytes]:
    """An HTTP header (without its blank line) and any bytes read past it; None when the peer closed
    or sent more than 16 KB of header."""
    buf = b""
    while b"\r\n\r\n" not in buf:
        chunk = sock.recv(4096)
        if not chunk or len(buf) > _MAX_HEADER:
            return None, b""
        buf += chunk
    head, _, rest = buf.partition(b"\r\n\r\n")
    return head, rest


def _pump(a: socket.socket, b: socket.socket, stop) -> None:
    """Copy bytes both ways until either side closes or ``stop`` is set."""
    import selectors

    sel = selectors.DefaultSelector()
    a.settimeout(None)
    b.settimeout(None)
    sel.register(a, selectors.EVENT_READ, b)
    sel.register(b, selectors.EVENT_READ, a)
    try:
        while not stop.is_set():
            for key, _ in sel.select(timeout=0.2):
                data = key.fileobj.recv(65536)
                if not data:
                    return
                key.data.sendall(data)
    finally:
        sel.close()
