"""The web pages' ASGI app (Starlette): read-only routes, server-sent events, local assets only.

Routes (all ``GET``; anything else is refused with 405):

- ``/`` the operator page, ``/quality`` the quality staff page, ``/static/...`` their assets
  (HTML, JS, CSS and the plotting code: all served from the package, no CDN);
- ``/api/live`` the :class:`~controller.web.live.LiveView` snapshot as JSON, and
  ``/api/live/stream`` the same as server-sent events (a message on every change, at most
  every ``period_s``; a comment line every second when nothing changes);
- ``/api/quality/boards`` (list), ``/api/quality/boards/{id}`` (records),
  ``/api/quality/boards/{id}/{figure}.png``, ``/api/quality/boards/{id}.csv`` and
  ``/api/quality/records.csv`` (:class:`~controller.web.quality.QualityBrowser`).

Every response carries a Content-Security-Policy that lets the page load and connect to its
own origin only. A request whose ``Host`` is not one of the allowed names (the bind address,
``localhost``, ``127.0.0.1``, ``::1``) is answered 421 (400 without a ``Host``): a page of
another site that a DNS name rebound to this machine cannot read it. At most ``max_streams``
event streams run at once (503 past it). The app records each request's client address and
path in ``app.state.requests`` (the last 1000) and counts refusals in ``app.state.counters``.
"""

from __future__ import annotations

import asyncio
import json
import threading
from collections import deque
from collections.abc import AsyncIterator, Iterable
from pathlib import Path
from typing import Any

from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import (
    FileResponse,
    JSONResponse,
    PlainTextResponse,
    Response,
    StreamingResponse,
)
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from controller.web.live import LiveView
from controller.web.quality import QualityBrowser

__all__ = ["CSP", "LOOPBACK_HOSTS", "STATIC_DIR", "host_of", "make_app"]

STATIC_DIR = Path(__file__).with_name("static")
"""The pages and their assets."""

CSP = ("default-src 'self'; img-src 'self' data:; style-src 'self'; script-src 'self'; "
       "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'")
"""The pages may load and connect to their own origin only."""

LOOPBACK_HOSTS = frozenset({"localhost", "127.0.0.1", "::1"})
"""Host names always allowed (with the bind address)."""

_HEADERS = {"Content-Security-Policy": CSP, "X-Content-Type-Options": "nosniff",
            "Cache-Control": "no-store", "Referrer-Policy": "no-referrer"}


def host_of(header: str) -> str | None:
    """The host name of a ``Host`` header (``"[::1]:8080"`` -> ``"::1"``), lower case.

    ``None`` for an empty or malformed header.
    """
    h = header.strip().lower()
    if not h:
        return None
    if h.startswith("["):
        end = h.find("]")
        if end < 0 or (h[end + 1:] and not h[end + 1:].startswith(":")):
            return None
        name, port = h[1:end], h[end + 2:]
    else:
        name, _, port = h.partition(":") if h.count(":") <= 1 else (h, "", "")
    if port and not port.isdigit():
        return None
    name = name.rstrip(".")
    return name or None


async def _plain(send: Any, status: int, text: str, extra: dict[str, str] | None = None) -> None:
    headers = [(b"content-type", b"text/plain; charset=utf-8"), (b"connection", b"close")]
    headers += [(k.lower().encode(), v.encode()) for k, v in {**_HEADERS, **(extra or {})}.items()]
    body = text.encode()
    headers.append((b"content-length", str(len(body)).encode()))
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


class _Recorder:
    """ASGI wrapper: refuses foreign hosts, records requests, adds the security headers."""

    def __init__(self, app: Any, requests: deque, allowed: frozenset[str],
                 counters: dict[str, int]) -> None:
        self.app = app
        self.requests = requests
        self.allowed = allowed
        self.counters = counters

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        client = scope.get("client") or ("", 0)
        self.requests.append({"client": client[0], "method": scope["method"],
                              "path": scope["path"]})
        hosts = [v.decode("latin-1") for k, v in scope.get("headers", []) if k == b"host"]
        name = host_of(hosts[0]) if len(hosts) == 1 else None
        if name is None:
            self.counters["bad_host"] += 1
            await _plain(send, 400, "bad request: one Host header naming this server expected")
            return
        if name not in self.allowed:
            self.counters["bad_host"] += 1
            await _plain(send, 421, f"misdirected request: this server does not answer for "
                                    f"{name[:80]}")
            return

        async def send_with_headers(message: dict) -> None:
            if message["type"] == "http.response.start":
                headers = [(k, v) for k, v in message.get("headers", [])
                           if k.decode("latin-1").lower() not in
                           {h.lower() for h in _HEADERS}]
                headers += [(k.lower().encode(), v.encode()) for k, v in _HEADERS.items()]
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_headers)


class _Encoded:
    """The view's snapshot as one SSE message, encoded once per version for every stream."""

    def __init__(self, view: LiveView) -> None:
        self.view = view
        self._version = -1
        self._text = ""

    def message(self, version: int) -> tuple[int, str]:
        if version != self._version:
            snap = self.view.snapshot()  # its own version: at least ``version``
            data = json.dumps(snap, allow_nan=False, separators=(",", ":"))
            self._version, self._text = snap["version"], f"id: {snap['version']}\ndata: {data}\n\n"
        return self._version, self._text


class _Streams:
    """``/api/live/stream``: server-sent events, at most ``limit`` streams at once."""

    def __init__(self, view: LiveView, stop: threading.Event, period_s: float, limit: int,
                 counters: dict[str, int]) -> None:
        self.encoded = _Encoded(view)
        self.view, self.stop, self.period_s = view, stop, period_s
        self.limit, self.counters = limit, counters
        self.open = 0

    async def messages(self) -> AsyncIterator[str]:
        yield "retry: 1000\n\n"
        sent, quiet = -1, 0.0
        while not self.stop.is_set():
            version = self.view.version
            if version != sent:
                quiet = 0.0
                sent, text = self.encoded.message(version)
                yield text
            elif quiet >= 1.0:
                quiet = 0.0
                yield ": alive\n\n"
            await asyncio.sleep(self.period_s)
            quiet += self.period_s

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["method"] not in ("GET", "HEAD"):
            await _plain(send, 405, "method not allowed", {"Allow": "GET"})
            return
        if self.open >= self.limit:
            self.counters["sse_refused"] += 1
            await _plain(send, 503, f"busy: {self.limit} event streams are open; "
                                    "poll /api/live instead", {"Retry-After": "5"})
            return
        self.open += 1
        try:
            response = StreamingResponse(self.messages(), media_type="text/event-stream",
                                         headers={"X-Accel-Buffering": "no"})
            await response(scope, receive, send)
        finally:
            self.open -= 1


def _quality_routes(quality: QualityBrowser | None) -> list[Route]:
    """The quality page's API (``/api/quality/...``)."""

    def need_quality() -> QualityBrowser:
        if quality is None:
            raise LookupError("no quality log is configured for this server")
        return quality

    async def in_thread(fn: Any, *args: Any) -> Any:
        return await asyncio.to_thread(fn, *args)

    def board_id(request: Request) -> int:
        return int(request.path_params["board_id"])

    async def boards(request: Request) -> Response:
        q = need_quality()
        items = await in_thread(q.boards)
        qc = q.quality_class
        return JSONResponse({"log": str(q.target), "boards": items,
                             "quality_class": None if qc is None else qc.to_dict()})

    async def board(request: Request) -> Response:
        return JSONResponse(await in_thread(need_quality().board, board_id(request)))

    async def figure(request: Request) -> Response:
        png = await in_thread(need_quality().figure_png, board_id(request),
                              request.path_params["name"])
        return Response(png, media_type="image/png")

    async def board_csv(request: Request) -> Response:
        bid = board_id(request)
        text = await in_thread(need_quality().csv_text, bid)
        return Response(text, media_type="text/csv", headers={
            "Content-Disposition": f'attachment; filename="board-{bid}.csv"'})

    async def all_csv(request: Request) -> Response:
        text = await in_thread(need_quality().csv_text)
        return Response(text, media_type="text/csv", headers={
            "Content-Disposition": 'attachment; filename="quality.csv"'})

    return [
        Route("/api/quality/boards", boards),
        Route("/api/quality/boards/{board_id:int}", board),
        Route("/api/quality/boards/{board_id:int}.csv", board_csv),
        Route("/api/quality/boards/{board_id:int}/{name:str}.png", figure),
        Route("/api/quality/records.csv", all_csv),
    ]


def make_app(
    live: LiveView | None = None,
    quality: QualityBrowser | None = None,
    *,
    period_s: float = 0.25,
    stopping: threading.Event | None = None,
    max_streams: int = 32,
    allowed_hosts: Iterable[str] = (),
) -> Any:
    """The ASGI app of the operator and quality pages.

    Parameters
    ----------
    live : LiveView, optional
        What the operator page shows (``None``: an empty view, "no service").
    quality : QualityBrowser, optional
        The quality log the quality page browses (``None``: the page says there is none).
    period_s : float, keyword-only
        Shortest time between two server-sent messages, s (at most 0.5: the page updates at
        least twice a second while the service changes).
    stopping : threading.Event, keyword-only, optional
        Set when the server stops: open event streams end.
    max_streams : int, keyword-only
        Event streams at once; one more is answered 503 (the page then polls ``/api/live``).
    allowed_hosts : iterable of str, keyword-only
        Host names answered besides :data:`LOOPBACK_HOSTS` (the bind address).

    Returns
    -------
    ASGI application
        With ``app.state.requests`` (deque of ``{"client", "method", "path"}``),
        ``app.state.counters`` (``bad_host``, ``sse_refused``) and ``app.state.streams`` (the
        open event streams, ``.open``).
    """
    if not 0 < period_s <= 0.5:
        raise ValueError(f"period_s must be in (0, 0.5] s, got {period_s}")
    if isinstance(max_streams, bool) or not isinstance(max_streams, int) or max_streams < 1:
        raise ValueError(f"max_streams must be an integer >= 1, got {max_streams!r}")
    allowed = LOOPBACK_HOSTS | {h.strip("[]").lower() for h in allowed_hosts}
    view = live if live is not None else LiveView()
    stop = stopping if stopping is not None else threading.Event()
    counters = {"bad_host": 0, "sse_refused": 0}
    streams = _Streams(view, stop, period_s, max_streams, counters)

    def page(name: str) -> Any:
        async def endpoint(request: Request) -> Response:
            return FileResponse(STATIC_DIR / name, media_type="text/html")
        return endpoint

    async def favicon(request: Request) -> Response:
        return FileResponse(STATIC_DIR / "favicon.svg", media_type="image/svg+xml")

    async def live_json(request: Request) -> Response:
        return JSONResponse(view.snapshot())

    async def not_found(request: Request, exc: Exception) -> Response:
        return PlainTextResponse(f"not found: {exc}", status_code=404)

    async def unavailable(request: Request, exc: Exception) -> Response:
        return PlainTextResponse(f"quality log unavailable: {exc}", status_code=503)

    routes = [
        Route("/", page("operator.html")),
        Route("/quality", page("quality.html")),
        Route("/favicon.ico", favicon),
        Route("/api/live", live_json),
        Route("/api/live/stream", streams),
        *_quality_routes(quality),
        Mount("/static", StaticFiles(directory=STATIC_DIR), name="static"),
    ]
    app = Starlette(routes=routes, exception_handlers={
        KeyError: not_found, LookupError: not_found, OSError: unavailable,
        ValueError: unavailable})
    requests: deque = deque(maxlen=1000)
    wrapped = _Recorder(app, requests, frozenset(allowed), counters)
    app.state.requests = requests
    app.state.counters = counters
    app.state.streams = streams
    wrapped.state = app.state  # type: ignore[attr-defined]
    return wrapped
