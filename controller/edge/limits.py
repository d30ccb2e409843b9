"""The servers' limits: connections, timeouts, file descriptors, log lines.

Pure bookkeeping and standard-library calls (``resource``, ``logging``): the servers' process
(:mod:`controller.edge.process`) applies them. Nothing here touches the service.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, fields, replace

__all__ = ["LogRateLimit", "ServerLimits", "fit_to_descriptors", "raise_nofile"]


@dataclass(frozen=True)
class ServerLimits:
    """What the operator page and the OPC UA server may take.

    Attributes
    ----------
    http_max_connections : int
        Open HTTP connections at once; one more is closed on accept (counted ``refused``).
    http_header_timeout_s : float
        A request's head (request line and headers) must be complete this long after the
        connection opened or went idle, s; else the connection is closed (slow or idle clients).
    http_keep_alive_s : int
        An idle keep-alive connection is closed after this long, s (uvicorn's
        ``timeout_keep_alive``).
    http_max_header_bytes : int
        Largest request head, bytes (h11's ``max_incomplete_event_size``).
    http_max_sse : int
        Event streams (``/api/live/stream``) at once; one more is answered 503.
    opcua_max_connections : int
        OPC UA TCP connections at once (asyncua refuses more on accept).
    opcua_max_subscriptions : int
        Subscriptions on the whole server (``BadTooManySubscriptions`` past it).
    opcua_min_publishing_ms : float
        Shortest publishing interval granted, ms (a client asking for less gets this).
    opcua_activation_s : float
        A connection without an activated session is closed after this long, s.
    opcua_max_session_timeout_ms : float
        Longest session timeout granted, ms (abandoned sessions go after it).
    fd_reserve : int
        File descriptors the servers' process keeps free beyond its clients (its own files,
        pipes, the quality log, the listening sockets).
    log_every_s : float
        Of the servers' log lines of one kind, one per this many seconds (the next says how
        many were suppressed).
    """

    http_max_connections: int = 256
    http_header_timeout_s: float = 5.0
    http_keep_alive_s: int = 5
    http_max_header_bytes: int = 16_384
    http_max_sse: int = 32
    opcua_max_connections: int = 32
    opcua_max_subscriptions: int = 64
    opcua_min_publishing_ms: float = 100.0
    opcua_activation_s: float = 10.0
    opcua_max_session_timeout_ms: float = 60_000.0
    fd_reserve: int = 128
    log_every_s: float = 10.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or v <= 0:
                raise ValueError(f"server limits: {f.name} must be a number > 0, got {v!r}")
            if f.type in ("int", int) and not isinstance(v, int):
                raise ValueError(f"server limits: {f.name} must be an integer, got {v!r}")
        if self.http_max_sse >= self.http_max_connections:
            raise ValueError(f"server limits: http_max_sse ({self.http_max_sse}) must be below "
                             f"http_max_connections ({self.http_max_connections})")


def raise_nofile() -> tuple[int, int]:
    """Raise this process's soft ``RLIMIT_NOFILE`` to its hard limit where allowed.

    Returns
    -------
    (int, int)
        The soft and hard limits after the attempt (unchanged where not permitted).
    """
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = hard if hard != resource.RLIM_INFINITY else max(soft, 65_536)
    if soft != resource.RLIM_INFINITY and soft < target:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
        except (ValueError, OSError):
            pass
    return resource.getrlimit(resource.RLIMIT_NOFILE)


def fit_to_descriptors(limits: ServerLimits, soft: int) -> ServerLimits:
    """``limits`` with the connection caps cut to fit ``soft`` descriptors.

    HTTP and OPC UA clients together get at most ``soft - fd_reserve`` descriptors, shared in
    proportion to their caps (each at least 4): a client is refused before the process runs
    out of descriptors.
    """
    budget = soft - limits.fd_reserve
    want = limits.http_max_connections + limits.opcua_max_connections
    if budget >= want:
        return limits
    if budget < 16:
        raise ValueError(f"server limits: RLIMIT_NOFILE {soft} leaves no room for clients "
                         f"beyond fd_reserve {limits.fd_reserve}")
    http = max(4, budget * limits.http_max_connections // want)
    opcua = max(4, budget - http)
    return replace(limits, http_max_connections=http, opcua_max_connections=opcua,
                   http_max_sse=min(limits.http_max_sse, http - 1))


class LogRateLimit(logging.Filter):
    """A handler filter: one line per kind per ``every_s`` seconds, the rest counted.

    A kind is the logger name, the level and the message template (before its arguments), so
    8,000 refused writes from one client are one line per period. The first line after a
    quiet spell carries ``[N more suppressed in the last T s]``.

    Parameters
    ----------
    every_s : float
        Period per kind, s.
    clock : callable, optional
        Monotonic seconds (injected in tests).
    max_kinds : int
        Kinds remembered (the oldest forgotten past it).
    """

    def __init__(self, every_s: float = 10.0, *, clock: Callable[[], float] | None = None,
                 max_kinds: int = 1000) -> None:
        super().__init__()
        if not every_s > 0:
            raise ValueError(f"every_s must be > 0, got {every_s!r}")
        self.every_s = float(every_s)
        self._clock = clock or time.monotonic
        self._max_kinds = int(max_kinds)
        self._kinds: dict[tuple[str, int, str], list[float]] = {}  # kind -> [emitted_at, n]
        self.suppressed = 0
        """Lines suppressed in all."""
        self.emitted = 0
        """Lines let through in all."""

    def filter(self, record: logging.LogRecord) -> bool:
        """Whether ``record`` is let through (the first of its kind in a period)."""
        key = (record.name, record.levelno, str(record.msg))
        now = self._clock()
        seen = self._kinds.get(key)
        if seen is not None and now - seen[0] < self.every_s:
            seen[1] += 1
            self.suppressed += 1
            return False
        if seen is not None and seen[1]:
            note = f" [{int(seen[1])} more suppressed in the last {now - seen[0]:.0f} s]"
            record.msg = f"{record.getMessage()}{note}"
            record.args = None
        if seen is None and len(self._kinds) >= self._max_kinds:
            self._kinds.pop(next(iter(self._kinds)))
        self._kinds[key] = [now, 0]
        self.emitted += 1
        return True
