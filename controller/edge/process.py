"""The servers' own process: the OPC UA server and the web pages, fed over a pipe.

:func:`run_servers` is the process's entry point (``multiprocessing`` spawn). It lowers its
priority, dies with its parent, raises its ``RLIMIT_NOFILE`` soft limit to the hard one and
fits the connection caps below it (:func:`controller.edge.limits.fit_to_descriptors`), rate-
limits its log lines, starts the servers asked for and answers on ``outbox`` with one
``("ready", info)`` or ``("error", kind, line)``; then, until ``inbox`` ends, it applies the
messages of :class:`controller.edge.feed.Translator` and sends ``("stats", dict)`` every
``stats_every_s``. Client load lands here: not on the service's event loop, not in its
process's file descriptor table, not on its interpreter lock.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import sys
import threading
from dataclasses import asdict, dataclass
from typing import Any

from controller.edge.limits import LogRateLimit, ServerLimits, fit_to_descriptors, raise_nofile
from controller.quality.schema import QualityClass

__all__ = ["ServersSpec", "run_servers"]

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ServersSpec:
    """What the servers' process serves (picklable).

    Attributes
    ----------
    opcua : dict or None
        :class:`controller.opcua.server.OpcUaServer` arguments (``endpoint``,
        ``identification``, ``quality_class``, ``security``); ``None``: no OPC UA.
    http : str or None
        ``HOST:PORT`` of the web pages; ``None``: no pages.
    quality_log : str or None
        The quality log the quality page browses.
    quality_class : QualityClass or None
        The band the operator page draws.
    limits : ServerLimits
        Connections, timeouts, descriptors, log lines.
    nice : int
        Added to the process's nice value (the service's loop comes first).
    stats_every_s : float
        Period of the ``("stats", ...)`` reports, s.
    heads : list of dict or None
        A moulder's heads (:func:`controller.edge.feed.head_config_json`), shown from the
        start; ``None``: one head (or heads told later by the messages).
    """

    opcua: dict[str, Any] | None
    http: str | None
    quality_log: str | None = None
    quality_class: QualityClass | None = None
    limits: ServerLimits = ServerLimits()
    nice: int = 10
    stats_every_s: float = 0.5
    heads: list[dict[str, Any]] | None = None


def _die_with_parent() -> None:
    """Ask the kernel for SIGTERM when the parent goes (Linux; elsewhere the pipe's EOF)."""
    try:
        import ctypes
        import signal

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _quiet_logging(every_s: float) -> LogRateLimit:
    """Warnings and worse to stderr, one line per kind per ``every_s``."""
    rate = LogRateLimit(every_s)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("planer servers: %(levelname)s %(name)s: %(message)s"))
    handler.addFilter(rate)
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.WARNING)
    return rate


def run_servers(spec: ServersSpec, inbox: Any, outbox: Any) -> None:
    """Entry point of the servers' process (see the module's description)."""
    _die_with_parent()
    with contextlib.suppress(OSError):
        os.nice(spec.nice)
    soft, hard = raise_nofile()
    try:
        limits = fit_to_descriptors(spec.limits, soft)
    except ValueError as exc:
        outbox.send(("error", "ValueError", str(exc)))
        return
    rate = _quiet_logging(limits.log_every_s)
    servers = _Servers(spec, limits, rate, (soft, hard))
    try:
        asyncio.run(servers.serve(inbox, outbox))
    except (OSError, ValueError) as exc:  # a start failure: one line, told to the parent
        with contextlib.suppress(OSError):
            outbox.send(("error", type(exc).__name__, str(exc).splitlines()[0]))
    except KeyboardInterrupt:
        pass


class _Servers:
    """The servers of one process and what they have been told."""

    def __init__(self, spec: ServersSpec, limits: ServerLimits, rate: LogRateLimit,
                 nofile: tuple[int, int]) -> None:
        self.spec, self.limits, self.rate, self.nofile = spec, limits, rate, nofile
        self.opcua: Any = None
        self.web: Any = None
        self.live: Any = None
        self.quality: Any = None
        self.received = 0
        self.apply_errors = 0

    async def _start_opcua(self) -> None:
        from controller.opcua.server import OpcUaServer

        lim = self.limits
        self.opcua = OpcUaServer(
            **self.spec.opcua, max_connections=lim.opcua_max_connections,
            max_subscriptions=lim.opcua_max_subscriptions,
            min_publishing_ms=lim.opcua_min_publishing_ms, activation_s=lim.opcua_activation_s,
            max_session_timeout_ms=lim.opcua_max_session_timeout_ms)
        await self.opcua.start()

    async def _start_web(self) -> None:
        from controller.web.app import make_app
        from controller.web.live import LiveView
        from controller.web.quality import QualityBrowser
        from controller.web.server import WebServer, parse_listen

        spec, lim = self.spec, self.limits
        host, _ = parse_listen(spec.http)
        self.live = LiveView(spec.quality_class)
        if spec.heads:
            self.live.set_heads(spec.heads)
        self.quality = QualityBrowser(spec.quality_log) if spec.quality_log else None
        stopping = threading.Event()
        app = make_app(self.live, self.quality, stopping=stopping, max_streams=lim.http_max_sse,
                       allowed_hosts=[host])
        self.web = WebServer(app, spec.http, stopping=stopping,
                             max_connections=lim.http_max_connections,
                             header_timeout_s=lim.http_header_timeout_s,
                             keep_alive_s=lim.http_keep_alive_s,
                             max_header_bytes=lim.http_max_header_bytes)
        await asyncio.to_thread(self.web.start)

    async def serve(self, inbox: Any, outbox: Any) -> None:
        """Start, report, apply messages until ``inbox`` ends, stop."""
        loop = asyncio.get_running_loop()
        done = asyncio.Event()
        try:
            if self.spec.opcua is not None:
                await self._start_opcua()
            if self.spec.http is not None:
                await self._start_web()
            outbox.send(("ready", {
                "url": None if self.web is None else self.web.url,
                "endpoint": None if self.opcua is None else self.opcua.endpoint,
                "limits": asdict(self.limits), "nofile": list(self.nofile), "pid": os.getpid(),
                "nice": os.getpriority(os.PRIO_PROCESS, 0)}))

            def receive() -> None:
                try:
                    while True:
                        self.apply(inbox.recv())
                except (EOFError, OSError):
                    pass
                finally:
                    loop.call_soon_threadsafe(done.set)

            threading.Thread(target=receive, name="servers-inbox", daemon=True).start()
            while not done.is_set():
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(done.wait(), self.spec.stats_every_s)
                try:
                    outbox.send(("stats", self.stats()))
                except OSError:  # the parent is gone
                    break
        finally:
            await self._stop()

    async def _stop(self) -> None:
        if self.web is not None:
            await asyncio.to_thread(self.web.stop)
        if self.opcua is not None:
            await self.opcua.stop()
        if self.quality is not None:
            self.quality.close()

    def apply(self, msg: dict[str, Any]) -> None:
        """Apply one :class:`~controller.edge.feed.Translator` message (the inbox thread)."""
        self.received += 1
        try:
            web, live = msg.get("web"), self.live
            if web is not None and live is not None:
                _apply_web(live, web)
            op = msg.get("opcua")
            if op is not None and self.opcua is not None:
                self.opcua.apply(op["values"], op["events"], op.get("heads"))
        except (KeyError, TypeError, ValueError, AttributeError):
            self.apply_errors += 1
            _log.exception("servers: a message from the service could not be shown")

    def stats(self) -> dict[str, Any]:
        """What the servers hold and refused, for the parent (plain JSON)."""
        out: dict[str, Any] = {"received": self.received, "apply_errors": self.apply_errors,
                               "log": {"emitted": self.rate.emitted,
                                       "suppressed": self.rate.suppressed}}
        if self.web is not None:
            state = self.web.app.state
            out["http"] = {"connections": self.web.connections, **self.web.counters,
                           **state.counters, "streams": state.streams.open,
                           "requests": list(state.requests)[-20:]}
        if self.opcua is not None:
            out["opcua"] = self.opcua.clients()
        return out


def _apply_web(live: Any, web: dict[str, Any]) -> None:
    """A message's ``web`` part into the page's :class:`~controller.web.live.LiveView`."""
    if web.get("heads") is not None:
        live.set_heads(web["heads"])
    for head, qc in (web.get("head_qc") or {}).items():
        if qc is not None:
            live.set_quality_class(qc, head)
    if web.get("counts_per_mm") is not None:
        live.set_counts_per_mm(web["counts_per_mm"])
    for head, cpm in (web.get("head_counts_per_mm") or {}).items():
        live.set_counts_per_mm(cpm, head)
    for e in web["events"]:
        live.take_event(e)
    for r in web["results"]:
        live.take_result(r)
    if web["status"] is not None:
        live.take_status(web["status"])
    for head, d in (web.get("head_status") or {}).items():
        live.take_status(d, head)
    for head, facts in (web.get("head_plc") or {}).items():
        live.take_plc(head, facts)
    if web.get("machine") is not None:
        live.take_machine(web["machine"])
