"""A TCP server that speaks the Nanonis programming interface's framing (no ROS): it reads whole
requests, hands each to a dispatcher, and sends its response.

The dispatcher is a function ``(name, body) -> response bytes`` (a whole response,
:func:`afm_ros.formats.nanonis_wire.response`); the server knows nothing of the commands. What the
server guarantees, whatever a client sends:

- it listens on 127.0.0.1 unless told otherwise (the protocol has no authentication: another
  address is logged as a warning), on port 6501 by default, and serves at most ``max_clients``
  connections at once (Nanonis: 4); one more is closed at once, with a log line;
- each connection has its own thread and is served in order, one command after the other; a
  dispatcher that raises answers that command with an error section naming it and the
  connection goes on;
- it never allocates more than a request's bounded body: a header whose body size is negative or
  over ``max_body`` [B] is answered with an error naming the limit and the connection is closed
  (its framing can no longer be trusted); a header that is not a command name, the same;
- a client that disconnects mid-message only ends its own connection; a client that stops reading
  its responses is dropped after ``send_timeout`` [s] of a blocked send; neither disturbs the
  other connections or the instrument.

Every event worth knowing (connect, disconnect, a refused or malformed request) goes to
``log(level, text)`` with level 'info', 'warn' or 'error'.
"""

from __future__ import annotations

import socket
import threading
from typing import Callable

from afm_ros.formats.nanonis_wire import (
    HEADER_SIZE,
    MAX_REQUEST_BODY,
    WireError,
    parse_header,
    response,
)

DEFAULT_PORT = 6501
MAX_CLIENTS = 4  # as the controller: "the Client can open one, two, three or four connections"
SEND_TIMEOUT_S = 10.0  # [s] wall: a response this long unread ends its connection
LOOPBACK = ("127.0.0.1", "::1", "localhost")


class ConnectionClosed(Exception):
    """The peer closed the connection (or it was shut down)."""


def _receive(sock: socket.socket, n: int) -> bytes:
    """Exactly ``n`` bytes (n is bounded by the caller); ConnectionClosed if the peer ends
    first."""
    parts, left = [], n
    while left:
        chunk = sock.recv(min(left, 1 << 16))
        if not chunk:
            raise ConnectionClosed(f"closed with {left} of {n} bytes still to come")
        parts.append(chunk)
        left -= len(chunk)
    return b"".join(parts)


class NanonisServer:
    """See the module doc. ``dispatch(name, body) -> bytes``; :meth:`start` binds and serves in
    background threads, :meth:`close` stops and waits for them."""

    def __init__(
        self,
        dispatch: Callable[[str, bytes], bytes],
        address: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        max_clients: int = MAX_CLIENTS,
        max_body: int = MAX_REQUEST_BODY,
        send_timeout: float = SEND_TIMEOUT_S,
        log: Callable[[str, str], None] | None = None,
    ):
        if not isinstance(port, int) or not 0 <= port <= 65535:
            raise ValueError(f"port={port!r}: an integer in [0, 65535] (0 = any free port)")
        if not isinstance(max_clients, int) or not 1 <= max_clients <= 64:
            raise ValueError(f"max_clients={max_clients!r}: an integer in [1, 64]")
        self.dispatch = dispatch
        self.address = address
        self.requested_port = port
        self.max_clients = max_clients
        self.max_body = max_body
        self.send_timeout = send_timeout
        self.log = log or (lambda level, text: None)
        self._listener: socket.socket | None = None
        self._clients: dict[int, socket.socket] = {}
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self._closing = threading.Event()
        self._ids = 0
        self.served = 0  # requests answered so far

    @property
    def port(self) -> int:
        """The port listened on (the one the system chose for port 0)."""
        return self._listener.getsockname()[1] if self._listener else self.requested_port

    @property
    def bound(self) -> tuple:
        """The (address, port) listened on."""
        return self._listener.getsockname()[:2] if self._listener else (self.address, self.port)

    @property
    def clients(self) -> int:
        """Connections open now."""
        with self._lock:
            return len(self._clients)

    def start(self) -> "NanonisServer":
        """Bind and listen (OSError naming the address and port if that fails), then accept in a
        background thread."""
        if self.address not in LOOPBACK:
            self.log(
                "warn",
                f"listening on {self.address}, beyond loopback: the Nanonis protocol has no "
                "authentication, anyone who reaches this port drives the instrument",
            )
        family = socket.AF_INET6 if ":" in self.address else socket.AF_INET
        listener = socket.socket(family, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            listener.bind((self.address, self.requested_port))
        except OSError as exc:
            listener.close()
            raise OSError(
                f"cannot listen on {self.address}:{self.requested_port}: {exc.strerror or exc}"
            ) from None
        listener.listen(8)
        self._listener = listener
        self._spawn(self._accept_loop, "nanonis-accept")
        return self

    def _spawn(self, target, name: str, *args) -> None:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        self._threads.append(thread)
        thread.start()

    def _accept_loop(self) -> None:
        while not self._closing.is_set():
            try:
                sock, peer = self._listener.accept()
            except OSError:
                return  # closed
            with self._lock:
                full = len(self._clients) >= self.max_clients
                if not full:
                    self._ids += 1
                    cid = self._ids
                    self._clients[cid] = sock
            if full:
                self.log(
                    "warn",
                    f"refused a connection from {peer[0]}:{peer[1]}: {self.max_clients} clients "
                    "are connected (the most the controller serves)",
                )
                sock.close()
                continue
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.log("info", f"client {cid} connected from {peer[0]}:{peer[1]}")
            self._threads = [t for t in self._threads if t.is_alive()]
            self._spawn(self._serve, f"nanonis-client-{cid}", cid, sock)

    def _serve(self, cid: int, sock: socket.socket) -> None:
        why = "closed by the client"
        try:
            while not self._closing.is_set():
                why = self._serve_one(cid, sock)
                if why:
                    break
        except ConnectionClosed as exc:
            why = f"closed by the client mid-message ({exc})"
        except OSError as exc:
            why = f"connection error: {exc}"
        finally:
            with self._lock:
                self._clients.pop(cid, None)
            try:
                sock.close()
            except OSError:
                pass
            if not self._closing.is_set():
                self.log("info", f"client {cid}: {why}")

    def _serve_one(self, cid: int, sock: socket.socket) -> str:
        """One request and its response; '' to go on, else why the connection ends."""
        sock.settimeout(None)
        first = sock.recv(HEADER_SIZE)
        if not first:
            return "closed by the client"
        raw = first + _receive(sock, HEADER_SIZE - len(first))
        try:
            header = parse_header(raw)
        except WireError as exc:
            self.log("warn", f"client {cid}: {exc}; closing the connection")
            self._send(sock, response("Unknown", error=f"malformed request: {exc}"))
            return f"malformed header ({exc})"
        if header.body_size > self.max_body:
            text = (
                f"{header.name}: body size {header.body_size} B exceeds the server's limit of "
                f"{self.max_body} B; closing the connection"
            )
            self.log("warn", f"client {cid}: {text}")
            self._send(sock, response(header.name, error=text))
            return "request too large"
        body = _receive(sock, header.body_size)
        try:
            answer = self.dispatch(header.name, body)
        except Exception as exc:  # the dispatcher's own fault: this command fails, not the server
            self.log("error", f"client {cid}: {header.name} failed: {exc!r}")
            answer = response(header.name, error=f"{header.name}: internal error: {exc}")
        self.served += 1
        if header.respond:
            self._send(sock, answer)
        return ""

    def _send(self, sock: socket.socket, data: bytes) -> None:
        """One sendall (the clients read the header in one recv); a client that does not read
        within send_timeout loses its connection."""
        sock.settimeout(self.send_timeout)
        try:
            sock.sendall(data)
        except socket.timeout:
            raise OSError(
                f"the client did not read a {len(data)} B response for {self.send_timeout:g} s"
            ) from None
        finally:
            sock.settimeout(None)

    def close(self, timeout: float = 5.0) -> None:
        """Stop accepting, close every connection and wait for the threads (at most ``timeout``
        s)."""
        self._closing.set()
        if self._listener is not None:
            try:
                self._listener.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            self._listener.close()
        with self._lock:
            clients = list(self._clients.values())
        for sock in clients:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        for thread in self._threads:
            thread.join(timeout)
