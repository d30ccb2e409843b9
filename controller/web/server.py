"""The web server on its own thread (uvicorn), bounded.

The socket is bound before the thread starts, so a busy port or a bad address is one clear
``OSError`` / ``ValueError`` line at start. The server holds at most ``max_connections``
connections (one more evicts the oldest still waiting for its request head, or is closed as
it is accepted when all are busy), closes a connection whose request head
is not complete ``header_timeout_s`` after it opened or went idle (idle and slow clients), an
idle keep-alive connection after ``keep_alive_s``, and refuses a request head over
``max_header_bytes``. :attr:`WebServer.counters` counts what it refused.
"""

from __future__ import annotations

import array
import asyncio
import fcntl
import ipaddress
import socket
import termios
import threading
import time
from typing import Any

__all__ = ["WebServer", "bind", "bounded_h11", "parse_listen"]

EVICT_LOOK_AT = 64
"""Most waiting connections looked at (one ``FIONREAD`` each) to find one to evict whose
socket holds no bytes of a request yet."""


def _unread_bytes(transport: Any) -> int:
    """Bytes in a connection's socket the server has not read yet (0 when unknown)."""
    sock = transport.get_extra_info("socket")
    if sock is None:
        return 0
    buf = array.array("i", [0])
    try:
        fcntl.ioctl(sock.fileno(), termios.FIONREAD, buf, True)
    except (OSError, ValueError):
        return 0
    return int(buf[0])


def _to_evict(waiting: dict[Any, None]) -> Any:
    """The oldest waiting connection with nothing in its socket (else the oldest).

    A loop that accepted a batch of connections before reading any of them (a flood on a busy
    host) would otherwise close a client whose request already arrived.
    """
    oldest = next(iter(waiting))
    for n, proto in enumerate(waiting):
        if n >= EVICT_LOOK_AT:
            break
        if _unread_bytes(proto.transport) == 0:
            return proto
    return oldest


def parse_listen(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[v6]:PORT`` for IPv6) as ``(host, port)``.

    Raises
    ------
    ValueError
        Not of that form, or the port outside 0..65535 (the message names ``listen``).
    """
    if not isinstance(text, str) or ":" not in text:
        raise ValueError(f"http listen address must look like 127.0.0.1:8080, got {text!r:.80}")
    host, _, port_text = text.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not host or not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
        raise ValueError(f"http listen address must look like 127.0.0.1:8080 (port 0..65535), "
                         f"got {text!r:.80}")
    return host, int(port_text)


def bind(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port`` (0: an ephemeral port).

    Raises
    ------
    OSError
        One line: ``http HOST:PORT: cannot listen: <reason>`` (busy port, address not on this
        machine, unknown host name).
    """
    where = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
    try:
        family = socket.AF_INET6 if isinstance(ipaddress.ip_address(host),
                                               ipaddress.IPv6Address) else socket.AF_INET
        addr = host
    except ValueError:  # a host name: resolve it (no name service traffic for addresses)
        try:
            info = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        except OSError as exc:
            raise OSError(f"http {where}: cannot listen: {exc.strerror or exc}") from None
        family, addr = info[0][0], info[0][4][0]
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((addr, port))
        sock.listen(64)
    except OSError as exc:
        sock.close()
        raise OSError(f"http {where}: cannot listen: {exc.strerror or exc}") from None
    sock.setblocking(False)
    return sock


def bounded_h11(max_connections: int, header_timeout_s: float,
                counters: dict[str, int]) -> type:
    """The h11 protocol of uvicorn with a connection cap and a deadline on the request head.

    Parameters
    ----------
    max_connections : int
        Connections at once. One more evicts the oldest connection still waiting for its
        request head with no bytes of it in its socket yet (``evicted``: a flood of idle
        sockets cannot starve a client that sends its request, even when the loop accepted
        it unread); when every connection is busy, the new one is aborted (``refused``).
    header_timeout_s : float
        The request head must be complete this long after the connection opened or its last
        response completed; else the connection is closed (``header_timeouts``). Bytes
        trickling in do not extend it.
    counters : dict
        ``refused``, ``evicted`` and ``header_timeouts`` are counted here (the server's
        thread only).
    """
    import h11
    from uvicorn.protocols.http.h11_impl import H11Protocol

    waiting: dict[Any, None] = {}  # connections waiting for a request head, oldest first

    class BoundedH11(H11Protocol):
        _head_timer: asyncio.TimerHandle | None = None

        def connection_made(self, transport: Any) -> None:  # type: ignore[override]
            super().connection_made(transport)
            if len(self.connections) > max_connections:
                if waiting:
                    oldest = _to_evict(waiting)
                    oldest._cancel_head_timer()
                    oldest.connections.discard(oldest)
                    counters["evicted"] += 1
                    oldest.transport.abort()
                else:
                    self.connections.discard(self)
                    counters["refused"] += 1
                    transport.abort()
                    return
            self._arm_head_timer()

        def _arm_head_timer(self) -> None:
            if self._head_timer is None:
                self._head_timer = self.loop.call_later(header_timeout_s, self._head_too_slow)
                waiting[self] = None

        def _cancel_head_timer(self) -> None:
            waiting.pop(self, None)
            if self._head_timer is not None:
                self._head_timer.cancel()
                self._head_timer = None

        def _head_too_slow(self) -> None:
            self._head_timer = None
            waiting.pop(self, None)
            if not self.transport.is_closing():
                counters["header_timeouts"] += 1
                self.transport.abort()

        def handle_events(self) -> None:
            super().handle_events()
            if self.conn.their_state is not h11.IDLE:  # the request head is in
                self._cancel_head_timer()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if not self.transport.is_closing():
                self._arm_head_timer()

        def connection_lost(self, exc: Exception | None) -> None:
            self._cancel_head_timer()
            super().connection_lost(exc)

    return BoundedH11


class WebServer:
    """An ASGI app served by uvicorn on a thread of its own.

    Parameters
    ----------
    app : ASGI application
        E.g. :func:`controller.web.app.make_app`.
    listen : str
        ``HOST:PORT`` (port 0: ephemeral; :attr:`port` tells which).
    stopping : threading.Event, optional
        Set by :meth:`stop` before the server shuts down (the app's streams end on it).
    max_connections : int, keyword-only
        Connections at once (one more is closed on accept).
    header_timeout_s : float, keyword-only
        Deadline of a request head after the connection opened or went idle, s.
    keep_alive_s : int, keyword-only
        An idle keep-alive connection is closed after this long, s.
    max_header_bytes : int, keyword-only
        Largest request head, bytes.
    """

    def __init__(self, app: Any, listen: str, *, stopping: threading.Event | None = None,
                 max_connections: int = 256, header_timeout_s: float = 5.0,
                 keep_alive_s: int = 5, max_header_bytes: int = 16_384) -> None:
        self.host, port = parse_listen(listen)
        for name, v in (("max_connections", max_connections), ("keep_alive_s", keep_alive_s),
                        ("max_header_bytes", max_header_bytes)):
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"http {name} must be an integer >= 1, got {v!r}")
        if not 0 < header_timeout_s < float("inf"):
            raise ValueError(f"http header_timeout_s must be > 0 s, got {header_timeout_s!r}")
        self.max_connections = max_connections
        self.header_timeout_s = float(header_timeout_s)
        self.keep_alive_s = keep_alive_s
        self.max_header_bytes = max_header_bytes
        self.counters = {"refused": 0, "evicted": 0, "header_timeouts": 0}
        """Connections refused over the cap (all busy), evicted for a newer one while waiting
        for their request head, closed for a slow request head."""
        self.app = app
        self.stopping = stopping if stopping is not None else threading.Event()
        self._sock: socket.socket | None = None
        self._server: Any = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self.port = port

    @property
    def url(self) -> str:
        """``http://HOST:PORT/``."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def start(self, *, timeout_s: float = 30.0) -> None:
        """Bind, then serve on a thread; returns once the server accepts connections.

        Raises
        ------
        OSError
            The address cannot be bound (one line), or the server did not start in time.
        ImportError
            uvicorn is not installed.
        """
        import uvicorn

        self._sock = bind(self.host, self.port)
        self.port = int(self._sock.getsockname()[1])
        protocol = bounded_h11(self.max_connections, self.header_timeout_s, self.counters)
        config = uvicorn.Config(self.app, log_level="warning", access_log=False, lifespan="off",
                                timeout_graceful_shutdown=1, ws="none", http=protocol,
                                log_config=None, limit_concurrency=self.max_connections + 1,
                                timeout_keep_alive=self.keep_alive_s,
                                h11_max_incomplete_event_size=self.max_header_bytes)
        self._server = uvicorn.Server(config)
        sock = self._sock

        def serve() -> None:
            try:
                asyncio.run(self._server.serve(sockets=[sock]))
            except (OSError, RuntimeError, SystemExit) as exc:  # reported by start()
                self._error = exc

        self._thread = threading.Thread(target=serve, name="web-server", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + timeout_s
        while not self._server.started:  # the server's own thread sets it within milliseconds
            if not self._thread.is_alive() or time.monotonic() > deadline:
                self.stop()
                raise OSError(f"http {self.url}: the server did not start: {self._error}")
            time.sleep(0.01)

    @property
    def connections(self) -> int:
        """Connections open now."""
        server = self._server
        return 0 if server is None else len(server.server_state.connections)

    def stop(self, *, timeout_s: float = 10.0) -> None:
        """Stop serving and join the thread (idempotent)."""
        self.stopping.set()
        if self._server is not None:
            self._server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None
