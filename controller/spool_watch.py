"""A spool folder's commits as they happen: Linux inotify, so the reader wakes without polling.

A :class:`~protocol.frames.SpoolWriter` commits a pair by renaming its metadata file
(``pair-<slot>.json``) into the folder, last (``docs/frames.md``). :class:`SpoolWatch` asks the
kernel for the folder's renames-in and closed writes (``IN_MOVED_TO``, ``IN_CLOSE_WRITE``) and
:meth:`SpoolWatch.wait` returns as soon as one of them names a metadata file: the spool reader
thread (:class:`controller.frame_source.SpoolFrameSource`) reads the pair at once instead of at
its next poll (``frames.poll_s``, 2 ms: 1 ms on average lost per pair, 2 ms at worst). The
images renamed in before it and the writer's temporary files do not wake it.

Where inotify is missing (not Linux, no ``libc``, the folder not there, the watch limit reached)
:attr:`SpoolWatch.active` is false and :meth:`wait` just sleeps its timeout: the reader polls as
before. The events also name the committed pairs (:func:`committed_slots`,
:meth:`SpoolWatch.take_committed`): the reader reads those without listing the folder
(``SpoolReader.note_committed``), and still lists it about once a second and whenever the events
cannot say which pairs came (a queue overflow, another commit name), so a lost or merged event
costs at most one poll interval (:data:`WATCHED_POLL_S`).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os
import re
import select
import struct
import threading
import time
from pathlib import Path

IN_CLOSE_WRITE = 0x00000008
IN_MOVED_TO = 0x00000080
IN_Q_OVERFLOW = 0x00004000
IN_IGNORED = 0x00008000
IN_DELETE_SELF = 0x00000400
IN_MOVE_SELF = 0x00000800
IN_NONBLOCK = 0o4000
IN_CLOEXEC = 0o2000000
_EVENT = struct.Struct("iIII")  # wd, mask, cookie, len (then len bytes of name)
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
_COMMIT_NAME = re.compile(rb"pair-([0-9]{1,18})\.json")
TMP_PREFIX = b"."
"""The writer's temporary names start so (never a commit)."""


@functools.lru_cache(maxsize=1)
def _libc() -> ctypes.CDLL | None:
    """The C library if it offers inotify (this process's symbols first, then ``libc``)."""
    for name in (None, "find"):
        if name == "find":  # only if needed: it may run ldconfig
            name = ctypes.util.find_library("c")
        try:
            lib = ctypes.CDLL(name, use_errno=True)
            lib.inotify_init1  # noqa: B018 - present?
            lib.inotify_add_watch  # noqa: B018
        except (OSError, AttributeError, TypeError):
            continue
        return lib
    return None


def is_commit(name: bytes) -> bool:
    """Whether a file name a folder event carries is a pair's commit (its metadata file)."""
    return name.endswith(COMMIT_SUFFIX) and not name.startswith(TMP_PREFIX)


def commits_in(buffer: bytes) -> bool:
    """Whether the inotify events in ``buffer`` name a commit (or overflowed: maybe one).

    Parameters
    ----------
    buffer : bytes
        What one ``read`` of an inotify descriptor returned: whole ``struct inotify_event``
        records, each followed by its NUL-padded name.
    """
    pos, n = 0, len(buffer)
    while pos + _EVENT.size <= n:
        _wd, mask, _cookie, length = _EVENT.unpack_from(buffer, pos)
        name = buffer[pos + _EVENT.size: pos + _EVENT.size + length].rstrip(b"\0")
        pos += _EVENT.size + length
        if mask & (IN_Q_OVERFLOW | IN_IGNORED) or is_commit(name):
            return True
    return False


def committed_slots(buffer: bytes) -> list[int] | None:
    """The pairs (slot numbers) whose commit the events in ``buffer`` name, in event order.

    ``None`` when the events cannot say which (an overflowed queue, a commit name that is not
    ``pair-<digits>.json``): the reader must list the folder then.
    """
    out: list[int] = []
    pos, n = 0, len(buffer)
    while pos + _EVENT.size <= n:
        _wd, mask, _cookie, length = _EVENT.unpack_from(buffer, pos)
        name = buffer[pos + _EVENT.size: pos + _EVENT.size + length].rstrip(b"\0")
        pos += _EVENT.size + length
        if mask & IN_Q_OVERFLOW:
            return None
        if is_commit(name):
            m = _COMMIT_NAME.fullmatch(name)
            if m is None:
                return None
            out.append(int(m.group(1)))
    return out


def watch_gone(buffer: bytes) -> bool:
    """Whether the events in ``buffer`` say the folder itself went (deleted, moved, unwatched)."""
    pos, n = 0, len(buffer)
    while pos + _EVENT.size <= n:
        _wd, mask, _cookie, length = _EVENT.unpack_from(buffer, pos)
        pos += _EVENT.size + length
        if mask & (IN_IGNORED | IN_DELETE_SELF | IN_MOVE_SELF):
            return True
    return False


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
        self._committed: list[int] | None = []  # slots the events named; None: unknown
        lib = _libc()
        if lib is None:
            return
        fd = int(lib.inotify_init1(IN_NONBLOCK | IN_CLOEXEC))
        if fd < 0:
            return
        wd = int(lib.inotify_add_watch(fd, os.fsencode(self.directory),
                                       IN_MOVED_TO | IN_CLOSE_WRITE | IN_DELETE_SELF
                                       | IN_MOVE_SELF))
        if wd < 0:
            os.close(fd)
            return
        self._fd = fd

    def retry(self) -> bool:
        """Whether a new watch may succeed where this one failed (inotify, and the folder now)."""
        return _libc() is not None and self.directory.is_dir()

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
            found = commits_in(buf) or found
            gone = watch_gone(buf) or gone
            slots = committed_slots(buf)
            if slots is None or self._committed is None:
                self._committed = None
            else:
                self._committed.extend(slots)
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
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)

