"""Where the service's image pairs come from: async wrappers over the frame hand-off.

* :class:`SpoolFrameSource` reads a spool directory (the camera or ``planer sim`` writes pairs
  into it from another process) in its own reader thread: files are opened, checked and
  decoded there, never on the service's event loop, and a pair that takes longer than
  ``SpoolLimits.pair_timeout_s`` is given up (delivered as failed) while the reading goes on.
* :class:`PolledFrameSource` wraps anything with ``poll() -> Frame | None`` (the in-process
  source of ``protocol/frames.py``) into an awaitable ``next()`` that sleeps ``poll_s``
  between empty polls.
* :class:`QueueFrameSource` is an in-process queue (the in-process HIL, tests, benchmarks).

``open_frame_source(cfg)`` builds the one a ``[frames]`` table names. Every source has
``take_skips() -> list[Skip]``: spool files that gave no frame, with the file and the reason.
"""

from __future__ import annotations

import asyncio
import dataclasses
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from config.machine import FramesConfig
from controller.frames.spool_watch import WATCHED_POLL_S, SpoolWatch
from core.checks import check_positive
from protocol.frames import Frame
from protocol.spool import SpoolReader
from protocol.spool_files import Skip, SpoolLimits


class FrameSource(Protocol):
    """An awaitable stream of frames."""

    async def next(self, timeout_s: float | None = None) -> Frame | None:
        """The next frame, or ``None`` when ``timeout_s`` passed without one."""

    def close(self) -> None:
        """Release the source."""

    def take_skips(self) -> list[Skip]:
        """Files that gave no frame since the last call (file and reason)."""


def _resolve(future: asyncio.Future) -> None:
    """Wake a waiting :meth:`SpoolFrameSource.next` (once; on its event loop)."""
    if not future.done():
        future.set_result(None)


class SpoolFrameSource:
    """A spool directory read in a reader thread; the service awaits :meth:`next`.

    Parameters
    ----------
    reader : SpoolReader
        The spool reader (used by the reader thread only from now on).
    poll_s : float, keyword-only
        Wait between empty polls of the directory (reader thread) and of the hand-off queue
        (event loop), seconds.
    maxsize : int, keyword-only
        Frames decoded ahead at most; the reader thread then waits (the spool keeps the files).
    clock : callable, keyword-only
        Monotonic seconds, for the per-pair time limit (``reader.limits.pair_timeout_s``),
        timed from the first :meth:`next` call that finds the reader thread in the pair.
    watch : bool, keyword-only
        Wake the reader thread as a pair is committed (inotify:
        :class:`controller.frames.spool_watch.SpoolWatch`; without it the thread polls every
        ``poll_s``) and read the pairs the events name without listing the folder
        (``SpoolReader.note_committed``; listed about once a second still); ``False``: poll
        only.

    Attributes
    ----------
    received : int
        Frames handed to the service.
    abandoned : int
        Pairs given up because reading them took longer than the time limit.
    restarts : int
        Reader threads restarted after an error (a bug; reported as a skip).
    """

    def __init__(self, reader: SpoolReader, *, poll_s: float = 0.002, maxsize: int = 4,
                 clock: Callable[[], float] = time.monotonic, watch: bool = True) -> None:
        if not isinstance(reader, SpoolReader):
            raise ValueError(f"reader must be a SpoolReader, got {type(reader).__name__}")
        self.poll_s = check_positive("poll_s", poll_s)
        if isinstance(maxsize, bool) or not isinstance(maxsize, int) or maxsize < 1:
            raise ValueError(f"maxsize must be an integer >= 1, got {maxsize!r}")
        self.timeout_s = reader.limits.pair_timeout_s
        self.clock = clock
        self.received = 0
        self.abandoned = 0
        self.restarts = 0
        self.maxsize = maxsize
        self.watch = bool(watch)
        self.reader_priority: tuple[int, int] | None = None
        """``(rt_priority, nice)`` the reader threads ask for (:meth:`raise_reader`)."""
        self.reader_granted = "normal"
        """What the reader thread was granted (``"SCHED_FIFO 9"``, ``"nice -10"``, ...)."""
        self._frames: deque[Frame] = deque()
        self._skips: list[Skip] = []
        self._lock = threading.Lock()
        self._space = threading.Condition(self._lock)
        self._stop = threading.Event()
        self._generation = 0
        self._reader = reader
        self._watch: tuple[int, float] | None = None  # (reader.serial, first seen busy)
        self._failure: str | None = None
        self._arrived: tuple[asyncio.AbstractEventLoop, asyncio.Future] | None = None  # next()'s
        self._thread = self._start(reader, 0)

    @property
    def reader(self) -> SpoolReader:
        """The spool reader now in use (a successor after a pair was abandoned)."""
        return self._reader

    def _start(self, reader: SpoolReader, generation: int) -> threading.Thread:
        t = threading.Thread(target=self._run, args=(reader, generation),
                             name=f"spool-reader-{generation}", daemon=True)
        t.start()
        return t

    def _run(self, reader: SpoolReader, generation: int) -> None:
        # woken by the folder's commits (inotify) where possible, else polling every poll_s
        watch = SpoolWatch(reader.directory, stop=self._stop) if self.watch else None
        applied: tuple[int, int] | None = None
        waited = woken = False  # a wait came before this poll; it ended by a commit's event
        trusted = False  # the events announced the last pair found after a wait
        try:
            while not self._stop.is_set() and generation == self._generation:
                wanted = self.reader_priority
                if wanted is not None and wanted != applied:
                    from core.realtime import raise_priority

                    applied = wanted
                    self.reader_granted = raise_priority(rt_priority=wanted[0], nice=wanted[1])
                # after a pair, with events proved and none of the last listing left: wait
                # for the next commit's event rather than list the folder again at once (a
                # listing, 0.2-0.5 ms, taking the interpreter lock from a measurement)
                quiet = (not waited and trusted and watch is not None and watch.active
                         and reader.pending == 0)
                frame = None if quiet else reader.poll()
                if frame is None:
                    if watch is not None and not watch.active and watch.retry():
                        watch = SpoolWatch(reader.directory, stop=self._stop)
                    if watch is not None:  # a commit wakes it; polls only as a fallback
                        # once the events proved to come (a pair found after one): rarely
                        woken = watch.wait(max(self.poll_s, WATCHED_POLL_S)
                                           if watch.active and trusted else self.poll_s)
                        waited = True
                        slots = watch.take_committed() if woken else None
                        if slots:  # the events name the pairs: read them without a listing
                            reader.note_committed(slots)
                    else:
                        self._stop.wait(self.poll_s)
                    continue
                if waited:  # a pair found by a poll the events missed: back to poll_s
                    trusted, waited = woken, False
                with self._space:
                    while (not self._stop.is_set() and generation == self._generation
                           and len(self._frames) >= self.maxsize):
                        self._space.wait(0.05)
                    if generation == self._generation and not self._stop.is_set():
                        self._frames.append(frame)  # else given up meanwhile: delivered
                        self._wake()
        finally:  # an error (a bug) ends the thread; next() reports it and starts another
            if watch is not None:
                watch.close()
            exc = sys.exc_info()[1]
            if exc is not None:
                with self._lock:
                    self._failure = f"{type(exc).__name__}: {exc}"

    def raise_reader(self, *, rt_priority: int | None = None, nice: int | None = None) -> None:
        """Schedule the reader thread (and any started after it) first: real time if permitted.

        Its work is light (a folder listing, three small files, a raw or PNG decode: well under
        a millisecond per pair) and a pair waits for it, so on a busy host it runs with the
        service's bus thread (:func:`core.realtime.raise_priority`: ``SCHED_FIFO`` at
        ``rt_priority``, default ``BUS_RT_PRIORITY``, else nice ``nice``, default
        ``INTERFACE_NICE``). Applied by the thread itself at its next turn; granted:
        :attr:`reader_granted`.
        """
        from core.realtime import BUS_RT_PRIORITY, INTERFACE_NICE

        self.reader_priority = (BUS_RT_PRIORITY if rt_priority is None else int(rt_priority),
                                INTERFACE_NICE if nice is None else int(nice))

    def _give_up(self, slot: int | None, meta_frame: Frame | None, text: str) -> None:
        """Deliver the pair being read as failed (or a skip) and read on in a new thread."""
        name = "<reader>" if slot is None else f"pair-{slot:012d}.json"
        if meta_frame is not None:  # after the pairs read before it, before the next ones
            self._frames.append(dataclasses.replace(meta_frame, error=f"{name}: {text}"))
        else:
            self._skips.append(Skip(name, text, slot))
        self._watch = None
        self._generation += 1
        self._reader = self._reader.successor(skip_slot=slot)
        self._thread = self._start(self._reader, self._generation)

    def _check_reader(self) -> None:
        """Restart a reader thread that ended by an error, past the pair it was reading."""
        with self._lock:
            if self._stop.is_set() or self._thread.is_alive():
                return
            current = self._reader.current
            slot, meta_frame = current if current is not None else (None, None)
            self.restarts += 1
            self._give_up(slot, meta_frame,
                          f"reader error: {self._failure or 'reader thread ended'}")
            self._failure = None

    def _check_time_limit(self) -> None:
        """Give up the pair the reader thread has been busy with for too long."""
        with self._lock:
            reader = self._reader
            current, serial = reader.current, reader.serial
            if current is None:  # between pairs: nothing to time
                self._watch = None
                return
            now = self.clock()
            if self._watch is None or self._watch[0] != serial:
                self._watch = (serial, now)  # first seen busy with this pair now
                return
            if now - self._watch[1] <= self.timeout_s:
                return
            slot, meta_frame = current
            self.abandoned += 1
            self._give_up(slot, meta_frame,
                          f"reading took longer than {self.timeout_s:g} s (given up)")

    def _wake(self) -> None:
        """Wake a waiting :meth:`next` at once (reader thread; no poll interval lost)."""
        arrived = self._arrived
        if arrived is not None:
            try:
                arrived[0].call_soon_threadsafe(_resolve, arrived[1])
            except RuntimeError:  # its loop is closed: nobody waits
                pass

    def _take(self) -> Frame | None:
        with self._space:
            if not self._frames:
                return None
            frame = self._frames.popleft()
            self._space.notify()
            return frame

    async def next(self, timeout_s: float | None = None) -> Frame | None:
        """The next frame (``None`` after ``timeout_s`` seconds without one)."""
        loop = asyncio.get_running_loop()
        deadline = None if timeout_s is None else loop.time() + timeout_s
        while True:
            self._check_reader()
            self._check_time_limit()
            frame = self._take()
            if frame is not None:
                self.received += 1
                return frame
            if deadline is not None and loop.time() >= deadline:
                return None
            wait = self.poll_s
            if deadline is not None:
                wait = max(0.0, min(wait, deadline - loop.time()))
            # woken by the reader thread as a pair arrives (one future, resolved from there
            # with one call_soon_threadsafe), else after poll_s
            arrived = loop.create_future()
            self._arrived = (loop, arrived)
            if self._frames:  # appended before the reader could see this future
                self._arrived = None
                continue
            timer = loop.call_later(wait, _resolve, arrived)
            try:
                await arrived
            finally:
                timer.cancel()
                self._arrived = None

    def take_skips(self) -> list[Skip]:
        """Spool files that gave no frame since the last call (file and reason), oldest first.

        A reader thread that ended by an error (a bug) is reported here too, as a skip of the
        pair it was reading (``reader error: ...``), and restarted past that pair.
        """
        self._check_reader()
        with self._lock:
            out, self._skips = self._skips, []
        return out + self._reader.take_skips()

    @property
    def missed(self) -> int:
        """Pairs pruned or removed before the reader got to them (true count)."""
        return self._reader.missed

    def close(self, timeout_s: float = 1.0) -> None:
        """Stop the reader thread (waits at most ``timeout_s`` for it; never hangs)."""
        self._stop.set()
        with self._space:
            self._space.notify_all()
        self._thread.join(timeout_s)


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

    def take_skips(self) -> list[Skip]:
        """The poller's skips (a :class:`SpoolReader`'s), or none."""
        take = getattr(self.poller, "take_skips", None)
        return list(take()) if callable(take) else []


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

    def take_skips(self) -> list[Skip]:
        """Nothing is skipped in process."""
        return []


def open_frame_source(cfg: FramesConfig, *, inprocess: Any = None,
                      latch_reader: Any = None) -> FrameSource:
    """The frame source a ``[frames]`` table names.

    Parameters
    ----------
    cfg : FramesConfig
        ``source = "spool"`` reads ``spool_dir`` with a :class:`SpoolFrameSource` (images
        must be ``image_width`` x ``image_height`` when both are set); ``"inprocess"`` uses
        ``inprocess``.
    inprocess : object, optional
        For ``"inprocess"``: a :class:`QueueFrameSource`, or anything with ``poll()``.
    latch_reader : callable, optional
        For ``"camera"`` (Aravis camera, ``docs/camera.md``): the PLC's trigger latches, e.g.
        ``controller.frames.camera.latches.ModbusLatchReader``; ``None``: pairs carry counts 0.

    Raises
    ------
    ValueError
        ``"inprocess"`` without an in-process source.
    """
    if cfg.source == "camera":  # Aravis loads only here (optional extra "camera")
        from controller.frames.camera.source import open_camera_source

        return open_camera_source(cfg, latch_reader=latch_reader)  # docs/camera.md
    if cfg.source == "spool":
        Path(cfg.spool_dir).mkdir(parents=True, exist_ok=True)
        shape = cfg.image_shape
        limits = SpoolLimits(image_shape=shape, max_pixels=max(
            SpoolLimits.max_pixels, shape[0] * shape[1] if shape else 0))
        return SpoolFrameSource(SpoolReader(cfg.spool_dir, limits=limits), poll_s=cfg.poll_s)
    if inprocess is None:
        raise ValueError("frames.source = inprocess needs an in-process frame source")
    if hasattr(inprocess, "next"):
        return inprocess
    return PolledFrameSource(inprocess, poll_s=cfg.poll_s)
