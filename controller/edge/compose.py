"""The servers in a composition (``planer serve``, ``planer hil``): one helper for both.

:func:`serving` starts the OPC UA server and the web pages that machine.toml (or ``--opcua``,
``--http``) asks for in a process of their own (:mod:`controller.edge.process`) and feeds it
from the service: :func:`controller.edge.feed.follow` on the service's loop puts references
in a bounded :class:`~controller.edge.feed.Mailbox`; a thread here translates and sends them.
The loop never waits for the servers: a slow servers' process loses the oldest updates.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing
import threading
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from config.machine import MachineConfig
from controller.edge.feed import Mailbox, Translator, follow, head_config_json
from controller.edge.limits import ServerLimits, raise_nofile
from controller.edge.process import ServersSpec, run_servers
from controller.opcua.compose import opcua_options
from controller.web.compose import listen_for

__all__ = ["Servers", "moulder_heads", "serving"]

_log = logging.getLogger(__name__)

START_TIMEOUT_S = 120.0
"""Longest wait for the servers' process to say ready (imports on a loaded 2-core host)."""


class Servers:
    """The running servers' process, as the composition sees it.

    Attributes
    ----------
    url : str or None
        The web pages' ``http://HOST:PORT/`` (``None``: no pages).
    endpoint : str or None
        The OPC UA endpoint (``None``: no OPC UA).
    info : dict
        The process's ready report: ``limits`` in force, ``nofile`` (soft, hard), ``pid``,
        ``nice`` (the nice value it runs at: the service's loop comes first).
    mailbox : Mailbox
        The hand-off from the service (``mailbox.dropped``: updates lost to a slow process).
    """

    def __init__(self, info: dict[str, Any], mailbox: Mailbox, process: Any) -> None:
        self.info = info
        self.url: str | None = info.get("url")
        self.endpoint: str | None = info.get("endpoint")
        self.mailbox = mailbox
        self.process = process
        self.sent = 0
        """Messages sent to the servers' process."""
        self._stats: dict[str, Any] = {}
        self._stats_cond = threading.Condition()

    def stats(self) -> dict[str, Any]:
        """The servers' latest report (plain JSON).

        ``http`` (``connections``, ``refused``, ``header_timeouts``, ``bad_host``,
        ``sse_refused``, ``streams``, ``requests``), ``opcua`` (``connections``,
        ``subscriptions``, ``published``), ``log`` (``emitted``, ``suppressed``), ``received``.
        """
        with self._stats_cond:
            return dict(self._stats)

    def wait_stats(self, ok: Callable[[dict[str, Any]], bool], timeout_s: float) -> dict:
        """Block (at most ``timeout_s``) until a report satisfies ``ok``; return the last."""
        deadline = time.monotonic() + timeout_s
        with self._stats_cond:
            while not (self._stats and ok(self._stats)):
                left = deadline - time.monotonic()
                if left <= 0 or not self.process.is_alive():
                    break
                self._stats_cond.wait(min(left, 1.0))
            return dict(self._stats)

    def _take(self, stats: dict[str, Any]) -> None:
        with self._stats_cond:
            self._stats = stats
            self._stats_cond.notify_all()


def _send_loop(box: Mailbox, translator: Translator, conn: Any, servers: Servers,
               stop: threading.Event) -> None:
    """The sender thread: mailbox batches -> messages -> the servers' process."""
    while not stop.is_set():
        items = box.take(0.5)
        if not items:
            continue
        try:
            msg = translator.message(items)
        except (AttributeError, TypeError, ValueError, KeyError, IndexError):
            _log.exception("servers: an update could not be translated")
            continue
        try:
            conn.send(msg)
        except (OSError, ValueError):  # the servers' process is gone
            return
        servers.sent += 1


def _receive_loop(conn: Any, servers: Servers, stopping: threading.Event,
                  say: Callable[[str], None] | None) -> None:
    """The reports of the servers' process; says once when it ends unasked."""
    try:
        while True:
            msg = conn.recv()
            if msg[0] == "stats":
                servers._take(msg[1])
    except (EOFError, OSError):
        pass
    if not stopping.is_set():
        servers.process.join(5.0)
        line = (f"servers: the servers' process ended (exit code {servers.process.exitcode}); "
                "the service goes on without its pages and OPC UA")
        (say or _log.warning)(line)


async def _wait_ready(conn: Any, process: Any) -> dict[str, Any]:
    """The first report of the servers' process, raised as one line when it is an error."""
    deadline = time.monotonic() + START_TIMEOUT_S
    while not await asyncio.to_thread(conn.poll, 0.2):
        if not process.is_alive():
            raise OSError(f"servers: the servers' process ended at start "
                          f"(exit code {process.exitcode})")
        if time.monotonic() > deadline:
            raise OSError(f"servers: not ready after {START_TIMEOUT_S:.0f} s")
    try:
        msg = conn.recv()
    except EOFError:
        raise OSError(f"servers: the servers' process ended at start "
                      f"(exit code {process.exitcode})") from None
    if msg[0] == "error":
        raise (ValueError if msg[1] == "ValueError" else OSError)(msg[2])
    return msg[1]


async def _stop_process(process: Any, inbox: Any, threads: list[threading.Thread]) -> None:
    """End the servers' process: the sender first, then the inbox (a clean stop), then signals.

    ``threads``: the sender and the receiver (their stop event already set).
    """
    sender = threads[0] if threads else None
    if sender is not None:
        await asyncio.to_thread(sender.join, 2.0)
        if sender.is_alive():  # blocked sending to a process that does not read: end it
            process.terminate()
            await asyncio.to_thread(sender.join, 5.0)
    inbox.close()  # no thread writes to it now
    await asyncio.to_thread(process.join, 10.0)
    if process.is_alive():
        process.terminate()
        await asyncio.to_thread(process.join, 5.0)
    if process.is_alive():
        process.kill()
        await asyncio.to_thread(process.join, 5.0)
    for t in threads[1:]:
        await asyncio.to_thread(t.join, 5.0)


def moulder_heads(cfg: MachineConfig) -> list[dict[str, Any]] | None:
    """A moulder's heads (``[[heads]]``, two or more) as plain dicts; ``None`` for one head.

    One head: the servers show a single machine, as without ``[[heads]]``.
    """
    heads = tuple(getattr(cfg, "heads", ()) or ())
    if len(heads) < 2:
        return None
    return [head_config_json(h) for h in heads]


@asynccontextmanager
async def serving(
    cfg: MachineConfig,
    get_service: Callable[[], Any],
    *,
    opcua: str | None = None,
    http: str | None = None,
    say: Callable[[str], None] | None = None,
    log: str | Path | None = None,
    period_s: float = 0.1,
    limits: ServerLimits | None = None,
    nice: int = 10,
) -> AsyncIterator[Servers | None]:
    """Serve OPC UA and the web pages (those asked for) while the block runs.

    Parameters
    ----------
    cfg : MachineConfig
        ``[opcua]``, ``[http] listen``, ``[log] path`` (the quality page's log), ``[quality]``,
        ``[identification]``.
    get_service : callable
        Returns the running service, or ``None`` before there is one (called on this loop).
    opcua : str, keyword-only, optional
        ``--opcua ENDPOINT``: overrides ``[opcua] endpoint``.
    http : str, keyword-only, optional
        ``--http HOST:PORT``: overrides ``[http] listen``.
    say : callable, keyword-only, optional
        Receives the lines naming the addresses (and the process's unasked end).
    log : str or Path, keyword-only, optional
        The quality log the quality page browses (default ``[log] path``).
    period_s : float, keyword-only
        How often the service is looked at, s.
    limits : ServerLimits, keyword-only, optional
        Connections, timeouts, descriptors, log lines (default :class:`ServerLimits`).
    nice : int, keyword-only
        Added to the servers' process's nice value.

    Yields
    ------
    Servers or None
        The running servers (``url``, ``endpoint``, ``stats()``), or ``None`` when none is asked
        for. A busy port or a bad address raises ``OSError`` / ``ValueError`` (one line) before
        the block starts.
    """
    if not period_s > 0:
        raise ValueError(f"period_s must be > 0, got {period_s}")
    options = opcua_options(cfg, opcua)
    listen = listen_for(cfg, http)
    if options is None and listen is None:
        yield None
        return
    from controller.service.records import quality_class_of

    raise_nofile()  # the service's own budget: spool, buses, log, workers
    qc = quality_class_of(cfg)
    heads = moulder_heads(cfg)
    if options is not None and heads is not None:
        options = {**options, "heads": heads}
    spec = ServersSpec(opcua=options, http=listen, heads=heads,
                       quality_log=None if listen is None else str(cfg.log.path if log is None
                                                                    else log),
                       quality_class=qc, limits=limits or ServerLimits(), nice=nice)
    ctx = multiprocessing.get_context("spawn")
    inbox_r, inbox_w = ctx.Pipe(duplex=False)
    outbox_r, outbox_w = ctx.Pipe(duplex=False)
    process = ctx.Process(target=run_servers, args=(spec, inbox_r, outbox_w),
                          name="planer-servers", daemon=True)
    process.start()  # from this (long-lived) thread: the child dies with it
    inbox_r.close()
    outbox_w.close()
    stopping = threading.Event()
    threads: list[threading.Thread] = []
    task: asyncio.Task[None] | None = None
    try:
        info = await _wait_ready(outbox_r, process)
        box = Mailbox()
        servers = Servers(info, box, process)
        translator = Translator(web=listen is not None, opcua=options is not None,
                                quality_class=qc)
        threads = [
            threading.Thread(target=_send_loop, args=(box, translator, inbox_w, servers,
                                                      stopping),
                             name="servers-feed", daemon=True),
            threading.Thread(target=_receive_loop, args=(outbox_r, servers, stopping, say),
                             name="servers-reports", daemon=True),
        ]
        for t in threads:
            t.start()
        if say is not None:
            if servers.endpoint is not None:
                where = "" if heads is None else "; its heads under State/SubUnits"
                say(f"opcua: {servers.endpoint} (WwMachineType under Objects/Machines{where})")
            if servers.url is not None:
                say(f"http: {servers.url} (operator page; quality page {servers.url}quality)")
        task = asyncio.create_task(follow(get_service, box, period_s=period_s),
                                   name="servers-follow")
        yield servers
    finally:
        stopping.set()
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        await _stop_process(process, inbox_w, threads)
        with contextlib.suppress(OSError):
            outbox_r.close()
