"""The web app (controller/web/app.py, quality.py, server.py, compose.py): routes, assets,
quality log browsing, server-sent events, address errors. No browser (see test_web_browser.py).
"""

from __future__ import annotations

import csv
import io
import json
import re
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

pytest.importorskip("starlette", reason="the web extra (starlette) is not installed")
pytest.importorskip("uvicorn", reason="the web extra (uvicorn) is not installed")
httpx = pytest.importorskip("httpx", reason="httpx (the test's HTTP client) is not installed")

from controller.quality.log import (  # noqa: E402
    CSV_COLUMNS,
    QualityClass,
    QualityRecord,
    open_quality_log,
    utc_iso,
)
from controller.service.events import EventKind, ServiceEvent  # noqa: E402
from controller.web.app import CSP, STATIC_DIR, make_app  # noqa: E402
from controller.web.live import LiveView  # noqa: E402
from controller.web.quality import QualityBrowser  # noqa: E402
from controller.web.server import WebServer, bind, parse_listen  # noqa: E402

ROOT = Path(__file__).resolve().parents[3]
BOARDS = {1: 5, 2: 3}  # board id -> records


def _records() -> list[QualityRecord]:
    out, seq = [], 0
    for board, n in BOARDS.items():
        for k in range(n):
            ok = k != 1
            out.append(QualityRecord(
                t_s=seq * 0.1, wall_time=utc_iso(1.7e9 + seq), seq=seq, board_id=board,
                board_position_mm=100.0 * k, ok=ok, error=None if ok else "registration failed: x",
                pitch_mm=1.5 + 0.01 * k if ok else None, uniformity_cv=0.03 if ok else None,
                depth_um=3.0 if ok else None, feed_setpoint_mm_s=600.0,
                piezo_offsets_um=(0.0, 1.0), mark_widths_mm=(1.5, 1.5) if ok else (),
                target_pitch_mm=1.5, passed=True if ok else None,
                extra={"state": "run", "profile": {"x_mm": [0.0, 1.0, 2.0],
                                                   "height_um": [0.0, -2.0, 0.0]}}))
            seq += 1
    return out


@pytest.fixture()
def log_path(tmp_path: Path) -> Path:
    path = tmp_path / "q.sqlite"
    with open_quality_log(path) as log:
        log.set_quality_class(QualityClass(name="fine", target_pitch_mm=1.5,
                                           pitch_tolerance=0.02, uniformity_max_cv=0.05))
        for r in _records():
            log.append(r)
    return path


@contextmanager
def _served(app) -> Iterator[httpx.Client]:
    """The app on an ephemeral 127.0.0.1 port, and a client of it."""
    server = WebServer(app, "127.0.0.1:0")
    server.start()
    try:
        with httpx.Client(base_url=server.url, timeout=60.0) as c:
            yield c
    finally:
        server.stop()


@pytest.fixture()
def client(log_path: Path):
    live = LiveView()
    quality = QualityBrowser(log_path)
    with _served(make_app(live, quality)) as c:
        c.live = live
        yield c
    quality.close()


def test_pages_carry_a_same_origin_policy_and_only_local_assets(client):
    for page in ("/", "/quality"):
        r = client.get(page)
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
        assert r.headers["content-security-policy"] == CSP
        refs = re.findall(r'(?:src|href)="([^"]+)"', r.text)
        assert refs, page
        for ref in refs:
            assert ref.startswith("/"), f"{page}: {ref} is not served by this server"
            assert client.get(ref).status_code == 200, ref


def test_static_files_name_no_other_host():
    # the SVG namespace is an identifier, never fetched; anything else would be a CDN
    allowed = {"http://www.w3.org/2000/svg"}
    for path in STATIC_DIR.iterdir():
        urls = set(re.findall(r"https?://[^\s\"'`)]+", path.read_text()))
        assert urls <= allowed, (path.name, urls - allowed)


def test_read_only_other_methods_are_refused(client):
    for method in ("POST", "PUT", "DELETE", "PATCH"):
        assert client.request(method, "/api/live").status_code == 405
        assert client.request(method, "/api/quality/boards").status_code == 405


def test_live_json_is_the_views_snapshot(client):
    client.live.event(ServiceEvent(0.5, EventKind.RECOVERED, "recovered: control resumed"))
    r = client.get("/api/live")
    assert r.status_code == 200
    assert r.json() == json.loads(json.dumps(client.live.snapshot()))
    assert r.json()["events"][0]["kind"] == "recovered"


def test_boards_list_counts_every_record_once(client):
    data = client.get("/api/quality/boards").json()
    assert {b["board_id"]: b["records"] for b in data["boards"]} == BOARDS
    assert {b["board_id"]: b["ok"] for b in data["boards"]} == {b: n - 1 for b, n in BOARDS.items()}
    assert data["quality_class"]["name"] == "fine"
    board1 = client.get("/api/quality/boards/1").json()
    assert [r["seq"] for r in board1["records"]] == list(range(BOARDS[1]))
    assert [r["ok"] for r in board1["records"]].count(False) == 1
    assert board1["figures"] == ["pitch_uniformity", "setpoints", "profile"]


def test_board_csv_has_the_logs_columns_and_only_that_boards_rows(client):
    r = client.get("/api/quality/boards/2.csv")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
    assert "attachment" in r.headers["content-disposition"]
    rows = list(csv.reader(io.StringIO(r.text)))
    assert tuple(rows[0]) == CSV_COLUMNS
    assert len(rows) - 1 == BOARDS[2]
    col = rows[0].index("board_id")
    assert {row[col] for row in rows[1:]} == {"2"}
    everything = list(csv.reader(io.StringIO(client.get("/api/quality/records.csv").text)))
    assert len(everything) - 1 == sum(BOARDS.values())


def test_figures_are_png_and_unknown_ones_are_404(client):
    for name in ("pitch_uniformity", "setpoints", "profile"):
        r = client.get(f"/api/quality/boards/1/{name}.png")
        assert r.status_code == 200 and r.content[:8] == b"\x89PNG\r\n\x1a\n", name
    assert client.get("/api/quality/boards/1/nonsense.png").status_code == 404
    assert client.get("/api/quality/boards/99").status_code == 404
    assert client.get("/api/quality/boards/99.csv").status_code == 404


def test_figures_asked_for_at_once_all_arrive(client):
    # the page asks for a board's figures together; matplotlib is not thread-safe
    from concurrent.futures import ThreadPoolExecutor

    names = ["pitch_uniformity", "setpoints", "profile"] * 3
    with ThreadPoolExecutor(len(names)) as pool:
        got = list(pool.map(lambda n: client.get(f"/api/quality/boards/2/{n}.png"), names))
    assert [r.status_code for r in got] == [200] * len(names)
    by_name: dict = {}
    for n, r in zip(names, got, strict=True):
        by_name.setdefault(n, set()).add(r.content)
    assert all(len(v) == 1 for v in by_name.values())  # drawn once, the same bytes for all


def test_new_records_appear_without_restarting(client, log_path):
    n0 = len(client.get("/api/quality/boards/2").json()["records"])
    with open_quality_log(log_path) as log:
        log.append(_records()[-1])
    assert len(client.get("/api/quality/boards/2").json()["records"]) == n0 + 1


def test_without_a_quality_log_the_quality_api_says_so():
    with _served(make_app(LiveView(), None)) as c:
        r = c.get("/api/quality/boards")
        assert r.status_code == 404 and "no quality log" in r.text


def test_a_missing_log_is_unavailable_not_created(tmp_path):
    missing = tmp_path / "none.sqlite"
    with _served(make_app(LiveView(), QualityBrowser(missing))) as c:
        assert c.get("/api/quality/boards").status_code == 503
    assert not missing.exists()


@pytest.mark.parametrize("text, expected", [
    ("127.0.0.1:8080", ("127.0.0.1", 8080)), ("localhost:0", ("localhost", 0)),
    ("[::1]:9000", ("::1", 9000)),
])
def test_parse_listen_good(text, expected):
    assert parse_listen(text) == expected


@pytest.mark.parametrize("text", ["8080", "127.0.0.1:", ":80", "127.0.0.1:65536", "h:-1", "h:x"])
def test_parse_listen_bad(text):
    with pytest.raises(ValueError, match="127.0.0.1:8080"):
        parse_listen(text)


def test_a_busy_port_is_one_line_naming_it():
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen(1)
        port = held.getsockname()[1]
        with pytest.raises(OSError, match=rf"^http 127.0.0.1:{port}: cannot listen: ") as info:
            bind("127.0.0.1", port)
        assert "\n" not in str(info.value)


def test_an_address_not_on_this_machine_cannot_be_bound():
    with pytest.raises(OSError, match="cannot listen"):
        bind("192.0.2.1", 0)  # TEST-NET-1: never a local address


def test_server_streams_every_change_over_sse_on_an_ephemeral_port():
    live = LiveView()
    stopping = threading.Event()
    server = WebServer(make_app(live, None, stopping=stopping), "127.0.0.1:0", stopping=stopping)
    server.start()
    try:
        assert server.port > 0 and server.url == f"http://127.0.0.1:{server.port}/"
        with httpx.Client(base_url=server.url, timeout=30.0) as c, \
                c.stream("GET", "/api/live/stream") as r:
            assert r.headers["content-type"].startswith("text/event-stream")
            lines = r.iter_lines()
            first = _events_from(lines, 1)[0]
            live.event(ServiceEvent(1.0, EventKind.SAFE_STATE, "safe state: plc gone",
                                    "plc gone"))
            second = _events_from(lines, 1)[0]
            assert second["version"] > first["version"]
            assert second["events"][-1]["text"] == "safe state: plc gone"
        assert all(r["client"] == "127.0.0.1" for r in server.app.state.requests)
    finally:
        server.stop()
    with pytest.raises(httpx.ConnectError):
        httpx.get(server.url, timeout=5.0)


def _events_from(lines, count: int) -> list[dict]:
    out = []
    for line in lines:
        if line.startswith("data: "):
            out.append(json.loads(line[6:]))
            if len(out) == count:
                return out
    raise AssertionError("stream ended early")


def _planer(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "planer.cli", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)


def test_hil_with_a_busy_port_or_bad_address_stops_with_one_line(tmp_path):
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen(1)
        port = held.getsockname()[1]
        p = _planer("hil", "--in-process", "--distance-m", "0.1",
                    "--log", str(tmp_path / "h.sqlite"), "--http", f"127.0.0.1:{port}")
    assert p.returncode == 2, p.stderr
    err = [ln for ln in p.stderr.splitlines() if "error" in ln]
    assert len(err) == 1 and f"127.0.0.1:{port}: cannot listen" in err[0], p.stderr
    p = _planer("hil", "--in-process", "--distance-m", "0.1",
                "--log", str(tmp_path / "h2.sqlite"), "--http", "nonsense")
    assert p.returncode == 2 and "127.0.0.1:8080" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr
