"""Over the connection cap, a connection whose request is already in its socket is not evicted.

The server makes room for a new connection by closing the oldest one still waiting for its
request head. Under a flood of idle sockets on a busy host the server's loop can accept a batch
of connections before it reads any of them: the oldest "waiting" one may be a client whose
request is already in the kernel's buffer. The test makes that happen on purpose (the server's
loop held while a client sends its request and three idle sockets connect behind it, cap 3)
and checks that an idle socket makes room, not the client that asked.
"""

from __future__ import annotations

import socket
import threading

import pytest

pytest.importorskip("starlette", reason="the web extra (starlette) is not installed")
pytest.importorskip("uvicorn", reason="the web extra (uvicorn) is not installed")

from controller.web.app import make_app  # noqa: E402
from controller.web.live import LiveView  # noqa: E402
from controller.web.server import WebServer  # noqa: E402

WAIT_S = 30.0  # generous: the machine is shared


def _reply(s: socket.socket) -> bytes:
    """Everything the server sends on ``s`` until it closes it (b"" when reset unanswered)."""
    s.settimeout(WAIT_S)
    chunks = []
    try:
        while chunk := s.recv(65536):
            chunks.append(chunk)
    except ConnectionResetError:
        pass
    return b"".join(chunks)


def test_a_client_whose_request_is_waiting_unread_is_not_the_one_evicted():
    stopping = threading.Event()
    server = WebServer(make_app(LiveView(), None, stopping=stopping), "127.0.0.1:0",
                       stopping=stopping, max_connections=3, header_timeout_s=60.0)
    server.start()
    socks: list[socket.socket] = []
    release = threading.Event()
    try:
        loop = server._server.servers[0].get_loop()
        held = threading.Event()
        loop.call_soon_threadsafe(lambda: (held.set(), release.wait(WAIT_S)))
        assert held.wait(WAIT_S)  # the server's loop accepts and reads nothing now
        asking = socket.create_connection(("127.0.0.1", server.port), timeout=WAIT_S)
        socks.append(asking)
        asking.sendall(b"GET /api/live HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        idle = [socket.create_connection(("127.0.0.1", server.port), timeout=WAIT_S)
                for _ in range(3)]
        socks += idle
        release.set()  # four connections at once, one over the cap
        reply = _reply(asking)
        assert reply.startswith(b"HTTP/1.1 200"), reply[:200]
        assert server.counters["evicted"] == 1 and server.counters["refused"] == 0
        assert _reply(idle[0]) == b""  # the oldest idle socket made room
    finally:
        release.set()
        for s in socks:
            s.close()
        server.stop()
