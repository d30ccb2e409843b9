"""The page's limits: Host allow-list, connection cap, request-head deadline, event-stream cap;
the servers' limits bookkeeping (descriptors, rate-limited log lines, the bounded hand-off)."""

from __future__ import annotations

import logging
import socket
import threading
import time

import pytest

pytest.importorskip("starlette", reason="the web extra (starlette) is not installed")
pytest.importorskip("uvicorn", reason="the web extra (uvicorn) is not installed")
httpx = pytest.importorskip("httpx", reason="httpx (the test's HTTP client) is not installed")

from controller.edge.feed import Mailbox, Translator, follow_once  # noqa: E402
from controller.edge.limits import LogRateLimit, ServerLimits, fit_to_descriptors  # noqa: E402
from controller.service.events import EventKind, ServiceEvent  # noqa: E402
from controller.web.app import host_of, make_app  # noqa: E402
from controller.web.live import LiveView  # noqa: E402
from controller.web.server import WebServer  # noqa: E402

WAIT_S = 30.0  # generous: the machine is shared


def _server(**kwargs) -> tuple[WebServer, LiveView, threading.Event]:
    live = LiveView()
    stopping = threading.Event()
    app_kw = {k: kwargs.pop(k) for k in ("max_streams",) if k in kwargs}
    server = WebServer(make_app(live, None, stopping=stopping, **app_kw), "127.0.0.1:0",
                       stopping=stopping, **kwargs)
    server.start()
    return server, live, stopping


def _closed_by_server(s: socket.socket, timeout_s: float = WAIT_S) -> bool:
    """Whether the server closes ``s`` within ``timeout_s`` (reads until EOF or reset)."""
    s.settimeout(timeout_s)
    try:
        while True:
            if s.recv(4096) == b"":
                return True
    except (ConnectionResetError, BrokenPipeError):
        return True
    except TimeoutError:
        return False


def _raw(port: int, data: bytes) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=WAIT_S) as s:
        s.sendall(data)
        chunks = []
        while chunk := s.recv(65536):
            chunks.append(chunk)
    return b"".join(chunks)


@pytest.mark.parametrize("header, name", [
    ("127.0.0.1:8080", "127.0.0.1"), ("LOCALHOST", "localhost"), ("[::1]:80", "::1"),
    ("localhost.", "localhost"), ("evil.example:8080", "evil.example"), ("", None),
    ("[::1", None), ("a:b", None),
])
def test_host_of_reads_the_name(header, name):
    assert host_of(header) == name


def test_a_foreign_host_is_refused_and_counted():
    server, _, _ = _server()
    try:
        with httpx.Client(base_url=server.url, timeout=WAIT_S) as c:
            assert c.get("/api/live").status_code == 200
            assert c.get("/api/live", headers={"Host": f"localhost:{server.port}"}).status_code \
                == 200
            r = c.get("/api/quality/records.csv", headers={"Host": "rebound.example"})
            assert r.status_code == 421 and "rebound.example" in r.text
            assert "Content-Security-Policy" in r.headers
        # HTTP/1.0 without a Host header: 400
        reply = _raw(server.port, b"GET /api/live HTTP/1.0\r\n\r\n")
        assert reply.startswith(b"HTTP/1.1 400")
        assert server.app.state.counters["bad_host"] == 2
    finally:
        server.stop()


def test_the_bind_address_is_answered_besides_loopback_names():
    app = make_app(LiveView(), None, allowed_hosts=["192.0.2.7"])
    server = WebServer(app, "127.0.0.1:0")
    server.start()
    try:
        with httpx.Client(base_url=server.url, timeout=WAIT_S) as c:
            assert c.get("/", headers={"Host": "192.0.2.7:8080"}).status_code == 200
            assert c.get("/", headers={"Host": "192.0.2.8:8080"}).status_code == 421
    finally:
        server.stop()


def _until(cond, what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not cond():
        assert time.monotonic() < deadline, what
        time.sleep(0.01)  # polling the server's thread


def test_over_the_cap_the_oldest_idle_connection_makes_room_and_busy_ones_are_kept():
    server, live, _ = _server(max_connections=3, header_timeout_s=60.0, max_streams=3)
    idle = [socket.create_connection(("127.0.0.1", server.port), timeout=WAIT_S)
            for _ in range(3)]
    try:
        _until(lambda: server.connections == 3, "three connections accepted")
        # a client that sends its request gets in: the oldest idle socket makes room
        with httpx.Client(base_url=server.url, timeout=WAIT_S) as c:
            assert c.get("/api/live").status_code == 200
        assert _closed_by_server(idle[0])
        assert server.counters["evicted"] >= 1 and server.counters["refused"] == 0
        for s in idle:
            s.close()
        _until(lambda: server.connections == 0, "the idle sockets gone")
        # three busy connections (event streams): one more is refused, the streams kept
        with httpx.Client(base_url=server.url, timeout=WAIT_S,
                          limits=httpx.Limits(max_connections=5)) as c, \
                c.stream("GET", "/api/live/stream") as a, \
                c.stream("GET", "/api/live/stream") as b, \
                c.stream("GET", "/api/live/stream") as d:
            streams = [a, b, d]
            assert all(r.status_code == 200 for r in streams)
            lines = [r.iter_lines() for r in streams]
            for it in lines:
                next(it)
            extra = socket.create_connection(("127.0.0.1", server.port), timeout=WAIT_S)
            with extra:
                assert _closed_by_server(extra)
            assert server.counters["refused"] == 1
            live.event(ServiceEvent(0.0, EventKind.RECOVERED, "still streaming"))
            for it in lines:  # every stream still gets the change
                assert any("still streaming" in ln for ln in it)
    finally:
        for s in idle:
            s.close()
        server.stop()


def test_a_request_head_not_complete_in_time_closes_the_connection():
    server, _, _ = _server(header_timeout_s=0.3)
    try:
        with socket.create_connection(("127.0.0.1", server.port), timeout=WAIT_S) as idle, \
                socket.create_connection(("127.0.0.1", server.port), timeout=WAIT_S) as slow:
            slow.sendall(b"GET /api/live HTTP/1.1\r\nHost: 127.0")  # and nothing more
            assert _closed_by_server(idle)
            assert _closed_by_server(slow)
        assert server.counters["header_timeouts"] == 2
        # a complete request is answered, and the keep-alive connection then idles out too
        with socket.create_connection(("127.0.0.1", server.port), timeout=WAIT_S) as ok:
            ok.sendall(b"GET /api/live HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            assert ok.recv(12).startswith(b"HTTP/1.1 200")
            assert _closed_by_server(ok)
    finally:
        server.stop()


def test_event_streams_over_the_cap_are_answered_503():
    server, live, _ = _server(max_streams=2)
    try:
        with httpx.Client(base_url=server.url, timeout=WAIT_S) as c:
            with c.stream("GET", "/api/live/stream") as a, c.stream("GET", "/api/live/stream") \
                    as b:
                assert a.status_code == b.status_code == 200
                la, lb = a.iter_lines(), b.iter_lines()  # kept: a dropped iterator closes
                next(la)
                next(lb)
                r = c.get("/api/live/stream")
                assert r.status_code == 503 and r.headers["Retry-After"] == "5"
                assert c.get("/api/live").status_code == 200  # polling still works
            deadline = time.monotonic() + WAIT_S
            while server.app.state.streams.open and time.monotonic() < deadline:
                live.event(ServiceEvent(0.0, EventKind.RECOVERED, "tick"))  # wakes the streams
                time.sleep(0.05)
            assert server.app.state.streams.open == 0
            with c.stream("GET", "/api/live/stream") as again:
                assert again.status_code == 200
        assert server.app.state.counters["sse_refused"] == 1
    finally:
        server.stop()


def test_bad_limits_are_refused_naming_the_parameter():
    with pytest.raises(ValueError, match="http_max_sse"):
        ServerLimits(http_max_sse=300, http_max_connections=256)
    with pytest.raises(ValueError, match="opcua_max_connections"):
        ServerLimits(opcua_max_connections=0)
    with pytest.raises(ValueError, match="http_max_connections"):
        ServerLimits(http_max_connections=2.5)
    with pytest.raises(ValueError, match="max_connections"):
        WebServer(make_app(), "127.0.0.1:0", max_connections=0)
    with pytest.raises(ValueError, match="max_streams"):
        make_app(max_streams=0)


def test_the_connection_caps_fit_below_the_descriptor_limit():
    lim = ServerLimits(http_max_connections=256, opcua_max_connections=32, fd_reserve=128)
    assert fit_to_descriptors(lim, 20_000) == lim
    small = fit_to_descriptors(lim, 400)  # 272 for clients
    assert small.http_max_connections + small.opcua_max_connections <= 400 - 128
    assert small.http_max_sse < small.http_max_connections
    with pytest.raises(ValueError, match="RLIMIT_NOFILE"):
        fit_to_descriptors(lim, 130)


def _record(msg: str, *args, name: str = "asyncua.server.uaprocessor",
            level: int = logging.WARNING) -> logging.LogRecord:
    return logging.LogRecord(name, level, __file__, 1, msg, args, None)


def test_log_lines_are_rate_limited_per_kind_with_the_count_of_the_suppressed():
    now = [0.0]
    rate = LogRateLimit(10.0, clock=lambda: now[0])
    passed = [r for r in (_record("%s attempted to do something", f"user{i}")
                          for i in range(100)) if rate.filter(r)]
    assert len(passed) == 1 and rate.suppressed == 99
    other = _record("Refusing connection from %s", "x")  # another kind: its own budget
    assert rate.filter(other)
    now[0] = 10.5
    later = _record("%s attempted to do something", "user100")
    assert rate.filter(later)
    assert later.getMessage() == "user100 attempted to do something [99 more suppressed in " \
                                 "the last 10 s]"
    assert rate.emitted == 3


def test_the_mailbox_drops_the_oldest_and_never_waits():
    box = Mailbox(3)
    for i in range(5):
        box.put("n", i)
    assert box.dropped == 2 and [x for _, x in box.take(0.0)] == [2, 3, 4]
    assert box.take(0.01) == []


class _FakeService:
    def __init__(self) -> None:
        from controller.service.status import ServiceStatus

        self.events: list = []
        self.results: list = []
        self.keep_results = True
        self.quality_class = None
        self._status = ServiceStatus(t_s=1.0, state="run", safe_reason=None, missing=(),
                                     feed_setpoint_mm_s=600.0, feed_actual_mm_s=600.0,
                                     offsets_um=(0.0, 1.0), amplifier_enabled=True,
                                     last_measurement=None,
                                     counters=ServiceStatus.freeze({"frames": 0}))

    def status(self):
        return self._status


def test_following_takes_each_event_once_and_the_translator_speaks_for_both_servers():
    svc, box, seen = _FakeService(), Mailbox(), {}
    svc.events.append(ServiceEvent(0.5, EventKind.SAFE_STATE, "safe state: plc gone",
                                   "plc gone"))
    follow_once(svc, seen, box)
    follow_once(svc, seen, box)  # nothing new: the event not taken twice
    items = box.take(0.0)
    assert [k for k, _ in items].count("event") == 1
    msg = Translator(web=True, opcua=True).message(items)
    assert msg["web"]["events"][0]["text"] == "safe state: plc gone"
    assert msg["web"]["status"]["feed_actual_mm_s"] == 600.0
    assert msg["opcua"]["values"]["State/Machine/Flags/FeedRuns"] is True
    assert msg["opcua"]["events"][0].message_id == "safe_state"
    # the same status again: nothing to send to the page
    follow_once(svc, seen, box)
    t = Translator(web=True, opcua=False)
    t.message(box.take(0.0))
    follow_once(svc, seen, box)
    again = t.message(box.take(0.0))
    assert again["web"]["status"] is None and "opcua" not in again
