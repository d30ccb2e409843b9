"""Talking to systemd when the service runs as a unit (``Type=notify``, ``WatchdogSec=``).

systemd hands the service a notification socket (``NOTIFY_SOCKET``) and, with ``WatchdogSec=``,
the watchdog period (``WATCHDOG_USEC``, for the process ``WATCHDOG_PID``). :class:`Notifier`
sends ``READY=1`` once the service serves, ``STATUS=`` with its one-line state, ``STOPPING=1``
on the way out, and ``WATCHDOG=1`` every half period from :meth:`Notifier.watchdog`, a task on
the service's own event loop: a loop that is stuck stops the pings and systemd restarts the
service. Outside systemd (no ``NOTIFY_SOCKET``) every call does nothing.

The datagrams go through the ``sdnotify`` package (pure Python, no system headers).
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import Mapping

import sdnotify

__all__ = ["Notifier", "under_journald"]


def under_journald(environ: Mapping[str, str] | None = None) -> bool:
    """Whether our output goes to the journal (``JOURNAL_STREAM`` or ``INVOCATION_ID`` set).

    The journal stamps every line itself: a service under it prints no times of its own.
    """
    env = os.environ if environ is None else environ
    return bool(env.get("JOURNAL_STREAM") or env.get("INVOCATION_ID"))


class Notifier:
    """The service's end of systemd's notification protocol.

    ``NOTIFY_SOCKET``, ``WATCHDOG_USEC`` and ``WATCHDOG_PID`` are read from the environment.

    Raises
    ------
    ValueError
        ``WATCHDOG_USEC`` set but not a positive integer, or ``NOTIFY_SOCKET`` not a path.
    OSError
        ``NOTIFY_SOCKET`` set but nothing listens there.
    """

    def __init__(self) -> None:
        env = os.environ
        self.socket_path = env.get("NOTIFY_SOCKET") or None
        """The notification socket (``None``: not under systemd; every call does nothing)."""
        self.watchdog_s = _watchdog_period(env)
        """systemd's watchdog period in seconds (``None``: no watchdog asked for)."""
        self._notifier = None
        if self.socket_path is not None:
            self._notifier = _connect(self.socket_path)
        self._status = ""

    @property
    def enabled(self) -> bool:
        """Whether there is a socket to talk to."""
        return self._notifier is not None

    def send(self, *fields: str) -> None:
        """Send ``KEY=value`` fields in one datagram (nothing without a socket)."""
        if self._notifier is not None and fields:
            self._notifier.notify("\n".join(fields))

    def ready(self, status: str = "") -> None:
        """``READY=1`` (systemd then counts the unit as started), with a status line."""
        self.send("READY=1", *([_status_field(status)] if status else []))
        self._status = status or self._status

    def status(self, text: str) -> None:
        """``STATUS=<text>`` (``systemctl status`` shows it); the same text again is not sent."""
        if text and text != self._status:
            self._status = text
            self.send(_status_field(text))

    def stopping(self, status: str = "") -> None:
        """``STOPPING=1``: the service is shutting down on purpose."""
        self.send("STOPPING=1", *([_status_field(status)] if status else []))

    def ping(self) -> None:
        """One ``WATCHDOG=1``."""
        self.send("WATCHDOG=1")

    async def watchdog(self) -> None:
        """Ping every half watchdog period until cancelled (returns at once with no watchdog).

        Run it as a task on the service's event loop: when the loop is blocked, no ping goes.
        """
        if self.watchdog_s is None or not self.enabled:
            return
        period = self.watchdog_s / 2.0
        while True:
            self.ping()
            await asyncio.sleep(period)


def _status_field(text: str) -> str:
    return "STATUS=" + " ".join(str(text).split())  # one line


def _connect(path: str) -> sdnotify.SystemdNotifier:
    if not path.startswith(("/", "@")):
        raise ValueError(f"NOTIFY_SOCKET must be an absolute path or @name, got {path!r}")
    try:
        notifier = sdnotify.SystemdNotifier(debug=True)  # debug: a socket it cannot reach raises
    except OSError as exc:
        raise OSError(f"cannot reach systemd's NOTIFY_SOCKET {path}: {exc.strerror}") from None
    notifier.debug = False  # afterwards a lost datagram must not stop the service
    return notifier


def _watchdog_period(env: Mapping[str, str]) -> float | None:
    raw = env.get("WATCHDOG_USEC")
    if not raw:
        return None
    pid = env.get("WATCHDOG_PID")
    if pid and pid.strip() != str(os.getpid()):
        return None  # meant for another process (the one systemd started, not a child)
    try:
        usec = int(raw)
    except ValueError:
        raise ValueError(f"WATCHDOG_USEC must be a positive integer, got {raw!r}") from None
    if usec <= 0:
        raise ValueError(f"WATCHDOG_USEC must be a positive integer, got {raw!r}")
    return usec / 1e6
