"""A spool folder's commits as they happen: Linux inotify (``inotify_simple``), no polling.

A :class:`~protocol.spool.SpoolWriter` commits a pair by renaming its metadata file
(``pair-<slot>.json``) into the folder, last (``docs/frames.md``). :class:`SpoolWatch` asks the
kernel for the folder's renames-in and closed writes (``IN_MOVED_TO``, ``IN_CLOSE_WRITE``) and
:meth:`SpoolWatch.wait` returns as soon as one of them names a metadata file: the spool reader
thread (:class:`controller.frames.source.SpoolFrameSource`) reads the pair at once instead of at
its next poll (``frames.poll_s``, 2 ms: 1 ms on average lost per pair, 2 ms at worst). The
images renamed in before it and the writer's temporary files do not wake it.

Where inotify is missing (not Linux, no ``libc``, the folder not there, the watch limit reached)
:attr:`SpoolWatch.active` is false and :meth:`wait` just sleeps its timeout: the reader polls as
before. The events also name the committed pairs (:func:`summarize`,
:meth:`SpoolWatch.take_committed`): the reader reads those without listing the folder
(``SpoolReader.note_committed``), and still lists it about once a second and whenever the events
cannot say which pairs came (a queue overflow, another commit name), so a lost or merged event
costs at most one poll interval (:data:`WATCHED_POLL_S`).
"""

from __future__ import annotations

import os
import re
import select
import threading
import time
from pathlib import Path
from typing import NamedTuple

try:  # Linux only (a dependency there, pyproject.toml)
    import inotify_simple
except ImportError:  # pragma: no cover - not Linux
    inotify_simple = None

if inotify_simple is not None:
    _F = inotify_simple.flags
    IN_CLOSE_WRITE, IN_MOVED_TO = int(_F.CLOSE_WRITE), int(_F.MOVED_TO)
    IN_Q_OVERFLOW, IN_IGNORED = int(_F.Q_OVERFLOW), int(_F.IGNORED)
    IN_DELETE_SELF, IN_MOVE_SELF = int(_F.DELETE_SELF), int(_F.MOVE_SELF)
COMMIT_SUFFIX = b".json"
"""Names ending so are a pair's metadata: its commit marker."""
STOP_CHECK_S = 0.05
"""A long :meth:`SpoolWatch.wait` looks at its ``stop`` event this often, s."""
WATCHED_POLL_S = 0.05
"""The reader's poll interval once a watch's events announced a pair, s: only a fallback then
(an event lost to an overflowed queue is reported as one); the reader thread wakes 20 times a
second instead of every ``frames.poll_s`` (500 times), each wake a turn of the interpreter lock
taken from a measurement on the event loop's thread. A pair that a poll finds first (a file
system whose events do not come, e.g. a network share) brings ``frames.poll_s`` back."""
_COMMIT_NAME = re.compile(r"pair-([0-9]{1,18})\.json")
TMP_PREFIX = "."
"""The writer's temporary names start so (never a commit)."""


def is_commit(name: str) -> bool:
    """Whether a file name a folder event carries is a pair's commit (its metadata file)."""
    return name.endswith(".json") and not name.startswith(TMP_PREFIX)


class EventSummary(NamedTuple):
    """What one read of a folder's events says (:func:`summarize`)."""

    commit: bool
    """A commit came (or events were lost: maybe one)."""
    gone: bool
    """The folder itself went (deleted, moved, unwatched)."""
    slots: list[int] | None
    """The committed pairs (slot numbers) in event order; ``None`` when the events cannot say
    which (an overflowed queue, a commit name that is not ``pair-<digits>.json``): the reader
    must list the folder then."""


def summarize(buffer: bytes) -> EventSummary:
    """One pass over what one ``read`` of an inotify descriptor returned.

    Parameters
    ----------
    buffer : bytes
        Whole ``struct inotify_event`` records, each followed by its NUL-padded name
        (parsed by ``inotify_simple.parse_events``).
    """
    commit = gone = False
    slots: list[int] | None = []
    for event in inotify_simple.parse_events(buffer):
        mask, name = event.mask, event.name
        if mask & IN_Q_OVERFLOW:
            commit, slots = True, None
        if mask & (IN_IGNORED | IN_DELETE_SELF | IN_MOVE_SELF):
            gone = True
            commit = commit or bool(mask & IN_IGNORED)
        if is_commit(name):
            commit = True
            m = _COMMIT_NAME.fullmatch(name)
            if m is None:
                slots = None
            elif slots is not None:
                slots.append(int(m.group(1)))
    return EventSummary(commit, gone, slots)


class SpoolWatch:
    """Wake-ups on a spool folder's commits (inotify); a plain sleep where there is none.

    Parameters
    ----------
    directory : str or Path
        The spool folder (it must exist for the watch; otherwise :attr:`active` is false).
    stop : threading.Event, optional
        Set to end a :meth:`wait` early (within :data:`STOP_CHECK_S` with inotify).
    """

    def __init__(self, directory: str | Path, *, stop: threading.Event | None = None) -> None:
        self.directory = Path(directory)
        self._stop = stop if stop is not None else threading.Event()
        self._fd: int | None = None
        self._inotify = None
        self._committed: list[int] | None = []  # slots the events named; None: unknown
        if inotify_simple is None:
            return
        try:
            ino = inotify_simple.INotify(nonblocking=True)
        except OSError:
            return
        try:
            ino.add_watch(self.directory, IN_MOVED_TO | IN_CLOSE_WRITE | IN_DELETE_SELF
                          | IN_MOVE_SELF)
        except OSError:  # the folder is not there, the watch limit reached
            ino.close()
            return
        self._fd = ino.fileno()
        self._inotify = ino

    def retry(self) -> bool:
        """Whether a new watch may succeed where this one failed (inotify, and the folder now)."""
        return inotify_simple is not None and self.directory.is_dir()

    @property
    def active(self) -> bool:
        """Whether commits wake :meth:`wait` (inotify watches the folder)."""
        return self._fd is not None

    def wait(self, timeout_s: float) -> bool:
        """Wait until a pair is committed or ``timeout_s`` passed; whether one was.

        Without inotify this sleeps ``timeout_s`` (or until ``stop``) and returns ``False``.
        Events that name no commit (images, temporary files) are read and waited past.
        """
        fd = self._fd
        if fd is None:
            self._stop.wait(timeout_s)
            return False
        remaining = max(0.0, float(timeout_s))
        deadline = time.monotonic() + remaining
        while True:
            try:  # in slices: a set ``stop`` ends the wait within STOP_CHECK_S
                ready, _, _ = select.select([fd], [], [], min(remaining, STOP_CHECK_S))
            except (OSError, ValueError):  # closed meanwhile
                return False
            if ready and self._drain(fd):
                return True
            if self._fd is None:  # the folder went: poll (and watch a new one)
                return False
            remaining = deadline - time.monotonic()
            if remaining <= 0 or self._stop.is_set():
                return False

    def _drain(self, fd: int) -> bool:
        """Read every queued event; whether one names a commit (or the folder went).

        When the folder itself went (deleted, moved away) the watch closes: :attr:`active`
        is false, and the reader watches the folder made in its place (``retry``).
        """
        found = gone = False
        while True:
            try:
                buf = os.read(fd, 65536)
            except OSError:  # BlockingIOError: nothing more queued
                break
            if not buf:
                break
            events = summarize(buf)
            found, gone = found or events.commit, gone or events.gone
            if events.slots is None or self._committed is None:
                self._committed = None
            else:
                self._committed.extend(events.slots)
        if gone:
            self.close()
        return found or gone

    def take_committed(self) -> list[int] | None:
        """The pairs (slots) the events named since the last call, in order, or ``None``.

        ``None`` when some event could not say which (overflow, another commit name): list
        the folder then. Lets the reader read a committed pair without listing the folder.
        """
        out, self._committed = self._committed, []
        return out

    def close(self) -> None:
        """Stop watching (idempotent)."""
        ino, self._inotify, self._fd = self._inotify, None, None
        if ino is not None:
            ino.close()

