"""The web server on its own thread (uvicorn).

The pages stay responsive while the service's event loop is busy; the socket is bound before
the thread starts, so a busy port or a bad address is one clear ``OSError`` / ``ValueError``
line at start.
"""

from __future__ import annotations

import asyncio
import ipaddress
import socket
import threading
import time
from typing import Any

__all__ = ["WebServer", "bind", "parse_listen"]


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
    """

    def __init__(self, app: Any, listen: str, *, stopping: threading.Event | None = None) -> None:
        self.host, port = parse_listen(listen)
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
        config = uvicorn.Config(self.app, log_level="warning", access_log=False, lifespan="off",
                                timeout_graceful_shutdown=1, ws="none")
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
