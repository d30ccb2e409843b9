"""The web pages in a composition (``planer serve``, ``planer hil``): from machine.toml.

Imports Starlette and uvicorn only when a server is asked for (``--http`` or ``[http]
listen``), so the commands run without the ``web`` extra installed.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from config.machine import MachineConfig

__all__ = ["listen_for", "serving"]


def listen_for(cfg: MachineConfig, listen: str | None = None) -> str | None:
    """The ``HOST:PORT`` asked for (``--http`` over ``[http] listen``), ``None`` when off.

    Checked, so a bad address fails before anything starts.

    Raises
    ------
    ValueError
        A bad address, or Starlette / uvicorn missing.
    """
    from controller.web.server import parse_listen

    http = getattr(cfg, "http", None)
    listen = listen or (getattr(http, "listen", "") if http is not None else "")
    if not listen:
        return None
    parse_listen(listen)
    try:
        import starlette  # noqa: F401
        import uvicorn  # noqa: F401
    except ImportError as exc:
        raise ValueError(f"http {listen}: the web pages need starlette and uvicorn "
                         f"(pip install 'smart-planer[web]'): {exc}") from None
    return listen


@asynccontextmanager
async def serving(
    cfg: MachineConfig,
    listen: str | None,
    get_service: Callable[[], Any],
    *,
    say: Callable[[str], None] | None = None,
    log: str | Path | None = None,
    period_s: float = 0.1,
) -> AsyncIterator[Any]:
    """Serve the operator and quality pages (when asked for) while the block runs.

    Parameters
    ----------
    cfg : MachineConfig
        ``[http] listen``, ``[log] path`` (the quality page's log), ``[quality]``.
    listen : str or None
        ``--http HOST:PORT``: overrides ``[http] listen``.
    get_service : callable
        Returns the running service, or ``None`` before there is one.
    say : callable, optional
        Receives the line naming the address.
    log : str or Path, keyword-only, optional
        The quality log the quality page browses (``--log``; default ``[log] path``).
    period_s : float, keyword-only
        How often the service is polled, s.

    Yields
    ------
    WebServer or None
        The started server (``server.url``, ``server.app.state.requests``), or ``None`` when the
        pages are off. A busy port raises ``OSError`` (one line) before the block starts.
    """
    listen = listen_for(cfg, listen)
    if listen is None:
        yield None
        return
    import threading

    from controller.service.records import quality_class_of
    from controller.web.app import make_app
    from controller.web.live import LiveView
    from controller.web.quality import QualityBrowser
    from controller.web.server import WebServer

    live = LiveView(quality_class_of(cfg))
    quality = QualityBrowser(cfg.log.path if log is None else log)
    stopping = threading.Event()
    server = WebServer(make_app(live, quality, stopping=stopping), listen, stopping=stopping)
    await asyncio.to_thread(server.start)
    if say is not None:
        say(f"http: {server.url} (operator page; quality page {server.url}quality)")
    task = asyncio.create_task(live.follow(get_service, period_s=period_s))
    try:
        yield server
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        await asyncio.to_thread(server.stop)
        quality.close()
