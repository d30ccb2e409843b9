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
own origin only. The app records each request's client address and path in
``app.state.requests`` (the last 1000) for tests and diagnostics.
"""

from __future__ import annotations

import asyncio
import json
import threading
from collections import deque
from collections.abc import AsyncIterator
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

__all__ = ["CSP", "STATIC_DIR", "make_app"]

STATIC_DIR = Path(__file__).with_name("static")
"""The pages and their assets."""

CSP = ("default-src 'self'; img-src 'self' data:; style-src 'self'; script-src 'self'; "
       "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'")
"""The pages may load and connect to their own origin only."""

_HEADERS = {"Content-Security-Policy": CSP, "X-Content-Type-Options": "nosniff",
            "Cache-Control": "no-store", "Referrer-Policy": "no-referrer"}


class _Recorder:
    """ASGI wrapper: records requests, adds the security headers to every response."""

    def __init__(self, app: Any, requests: deque) -> None:
        self.app = app
        self.requests = requests

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        client = scope.get("client") or ("", 0)
        self.requests.append({"client": client[0], "method": scope["method"],
                              "path": scope["path"]})

        async def send_with_headers(message: dict) -> None:
            if message["type"] == "http.response.start":
                headers = [(k, v) for k, v in message.get("headers", [])
                           if k.decode("latin-1").lower() not in
                           {h.lower() for h in _HEADERS}]
                headers += [(k.lower().encode(), v.encode()) for k, v in _HEADERS.items()]
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_headers)


def make_app(
    live: LiveView | None = None,
    quality: QualityBrowser | None = None,
    *,
    period_s: float = 0.25,
    stopping: threading.Event | None = None,
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

    Returns
    -------
    ASGI application
        With ``app.state.requests`` (deque of ``{"client", "method", "path"}``).
    """
    if not 0 < period_s <= 0.5:
        raise ValueError(f"period_s must be in (0, 0.5] s, got {period_s}")
    view = live if live is not None else LiveView()
    stop = stopping if stopping is not None else threading.Event()

    def page(name: str) -> Any:
        async def endpoint(request: Request) -> Response:
            return FileResponse(STATIC_DIR / name, media_type="text/html")
        return endpoint

    async def favicon(request: Request) -> Response:
        return FileResponse(STATIC_DIR / "favicon.svg", media_type="image/svg+xml")

    async def live_json(request: Request) -> Response:
        return JSONResponse(view.snapshot())

    async def live_stream(request: Request) -> Response:
        async def messages() -> AsyncIterator[str]:
            yield "retry: 1000\n\n"
            sent, quiet = -1, 0.0
            while not stop.is_set():
                version = view.version
                if version != sent:
                    sent, quiet = version, 0.0
                    data = json.dumps(view.snapshot(), allow_nan=False, separators=(",", ":"))
                    yield f"id: {version}\ndata: {data}\n\n"
                elif quiet >= 1.0:
                    quiet = 0.0
                    yield ": alive\n\n"
                await asyncio.sleep(period_s)
                quiet += period_s

        return StreamingResponse(messages(), media_type="text/event-stream",
                                 headers={"X-Accel-Buffering": "no"})

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

    async def not_found(request: Request, exc: Exception) -> Response:
        return PlainTextResponse(f"not found: {exc}", status_code=404)

    async def unavailable(request: Request, exc: Exception) -> Response:
        return PlainTextResponse(f"quality log unavailable: {exc}", status_code=503)

    routes = [
        Route("/", page("operator.html")),
        Route("/quality", page("quality.html")),
        Route("/favicon.ico", favicon),
        Route("/api/live", live_json),
        Route("/api/live/stream", live_stream),
        Route("/api/quality/boards", boards),
        Route("/api/quality/boards/{board_id:int}", board),
        Route("/api/quality/boards/{board_id:int}.csv", board_csv),
        Route("/api/quality/boards/{board_id:int}/{name:str}.png", figure),
        Route("/api/quality/records.csv", all_csv),
        Mount("/static", StaticFiles(directory=STATIC_DIR), name="static"),
    ]
    app = Starlette(routes=routes, exception_handlers={
        KeyError: not_found, LookupError: not_found, OSError: unavailable,
        ValueError: unavailable})
    requests: deque = deque(maxlen=1000)
    wrapped = _Recorder(app, requests)
    app.state.requests = requests
    wrapped.state = app.state  # type: ignore[attr-defined]
    return wrapped
