"""Where the service's image pairs come from: async wrappers over the frame hand-off.

* :class:`PolledFrameSource` wraps anything with ``poll() -> Frame | None`` — the spool reader
  of ``protocol/frames.py`` (the camera or ``planer sim`` writes pairs into a spool
  directory from another process) or its in-process source — and turns it into an awaitable
  ``next()`` that sleeps ``poll_s`` between empty polls.
* :class:`QueueFrameSource` is an in-process queue (the in-process HIL, tests, benchmarks).

``open_frame_source(cfg)`` builds the one a ``[frames]`` table names.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any, Protocol

from config.machine import FramesConfig
from core.checks import check_positive
from protocol.frames import Frame


class FrameSource(Protocol):
    """An awaitable stream of frames."""

    async def next(self, timeout_s: float | None = None) -> Frame | None:
        """The next frame, or ``None`` when ``timeout_s`` passed without one."""

    def close(self) -> None:
        """Release the source."""


class PolledFrameSource:
    """Async ``next()`` over a non-blocking ``poll() -> Frame | None``.

    Parameters
    ----------
    poller : object
        Has ``poll()`` returning the next frame or ``None`` (e.g. ``SpoolReader``).
    poll_s : float
        Sleep between empty polls, seconds.
    """

    def __init__(self, poller: Any, *, poll_s: float = 0.002) -> None:
        self.poller = poller
        self.poll_s = check_positive("poll_s", poll_s)
        self.received = 0

    async def next(self, timeout_s: float | None = None) -> Frame | None:
        """Wait for the next frame (``None`` after ``timeout_s`` seconds without one)."""
        loop = asyncio.get_running_loop()
        deadline = None if timeout_s is None else loop.time() + timeout_s
        while True:
            frame = self.poller.poll()
            if frame is not None:
                self.received += 1
                return frame
            if deadline is not None and loop.time() >= deadline:
                return None
            wait = self.poll_s
            if deadline is not None:
                wait = max(0.0, min(wait, deadline - loop.time()))
            await asyncio.sleep(wait)

    def close(self) -> None:
        """Close the poller if it can be closed."""
        close = getattr(self.poller, "close", None)
        if callable(close):
            close()


class QueueFrameSource:
    """In-process frame queue: producers ``put`` frames, the service awaits ``next()``.

    Parameters
    ----------
    maxsize : int
        Queue bound; when full, the oldest frame is dropped (a camera never waits for the
        service) and counted in :attr:`dropped`.
    """

    def __init__(self, maxsize: int = 16) -> None:
        self._q: asyncio.Queue[Frame] = asyncio.Queue(maxsize=maxsize)
        self.dropped = 0
        self.received = 0

    def put(self, frame: Frame) -> None:
        """Queue a frame (from the event loop's thread)."""
        if self._q.full():
            self._q.get_nowait()
            self.dropped += 1
        self._q.put_nowait(frame)

    async def next(self, timeout_s: float | None = None) -> Frame | None:
        """The next queued frame (``None`` after ``timeout_s`` seconds without one)."""
        try:
            if timeout_s is None:
                frame = await self._q.get()
            else:
                frame = await asyncio.wait_for(self._q.get(), timeout=timeout_s)
        except asyncio.TimeoutError:
            return None
        self.received += 1
        return frame

    def close(self) -> None:
        """Nothing to release."""


def open_frame_source(cfg: FramesConfig, *, inprocess: Any = None) -> FrameSource:
    """The frame source a ``[frames]`` table names.

    Parameters
    ----------
    cfg : FramesConfig
        ``source = "spool"`` reads ``spool_dir`` with ``protocol.frames.SpoolReader``;
        ``"inprocess"`` uses ``inprocess``.
    inprocess : object, optional
        For ``"inprocess"``: a :class:`QueueFrameSource`, or anything with ``poll()``.

    Raises
    ------
    ValueError
        ``"inprocess"`` without an in-process source.
    """
    if cfg.source == "spool":
        from protocol import frames

        reader_cls = getattr(frames, "SpoolReader", None)
        if reader_cls is None:  # pragma: no cover - until the spool lands
            raise ValueError("frames.source = spool needs protocol.frames.SpoolReader")
        Path(cfg.spool_dir).mkdir(parents=True, exist_ok=True)
        return PolledFrameSource(reader_cls(cfg.spool_dir), poll_s=cfg.poll_s)
    if inprocess is None:
        raise ValueError("frames.source = inprocess needs an in-process frame source")
    if hasattr(inprocess, "next"):
        return inprocess
    return PolledFrameSource(inprocess, poll_s=cfg.poll_s)
