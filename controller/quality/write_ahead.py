"""Write-ahead: every quality record on local disk first, the database after, off the loop.

:class:`WriteAheadSink` is the real-time service's way into the quality log. Two threads, and
nothing the caller's thread (the event loop) can be held up by:

* the **journal thread** takes what :meth:`WriteAheadSink.put` queued, makes the records
  (``make``), appends them to the journal (``<log>.journal.jsonl``, JSON lines) with one
  ``fsync`` (``fdatasync``) per batch, says so (``on_durable``) and hands them on. It appends
  at most once per :data:`JOURNAL_WAIT_S` (what comes meanwhile joins the next batch; the
  first record after a pause, and a full batch, go at once) and never waits for the
  database: a record is durable on local disk once the rest of that wait (or the append on
  its way, when it takes longer) and its own fsync are over, whatever the log does. A batch
  the journal could not take is answered ``on_durable(items, False)`` and, once its records
  are durable after all (the journal's retry, or the log took them), answered again with
  ``True`` (always after the ``False``: the database thread gets them only then): every item
  is answered durable exactly once, or never (nowhere durable at
  :meth:`~WriteAheadSink.close`).
* the **database thread** writes the journalled records to the log, in order, each batch in
  one transaction with the records' UUIDs (the log skips a uid it holds, so a journal that
  still holds logged records is replayed safely), at most one transaction per
  :data:`DB_WAIT_S` (unless a full batch or a backlog on disk waits). A failed write is
  tried again after a back-off (0.2 s doubling to 5 s). Every call has a time limit
  (:data:`DB_TIMEOUT_S`, :meth:`QualityLog.set_write_timeout`); a call that never returns
  (a PostgreSQL server stopped) holds up only this thread.

The two threads are a :class:`WriterGroup`'s: a sink given a plain log makes a group of its
own; a moulder's heads share one (:meth:`WriterGroup.head_log`), whose journal thread appends
every head's batch to that head's journal and whose database thread writes every head's
records in one transaction on the one connection (each head's in its order).

A record is encoded once: the journal line and the log's row share the JSON text of its
``extra`` (:func:`~controller.quality.schema.storable`). Neither thread waits for more records
while :meth:`~WriteAheadSink.close` or :meth:`~WriteAheadSink.wait_logged` waits for them.

The journal is truncated when everything in it is logged and it has grown beyond
:data:`COMPACT_BYTES` or nothing came for :data:`COMPACT_IDLE_S` (not per batch: the steady
state costs one fsync per batch). While the database is stuck the backlog waits on disk: at
most :data:`MAX_IN_MEMORY` records wait in memory, the rest are read back from the journal.

Readers on any thread see :attr:`WriteAheadSink.state`, a frozen :class:`SinkState` the
writer threads replace after every step (a plain attribute: no lock, no I/O). The only lock
the caller's thread takes (in :meth:`~WriteAheadSink.put`) guards two queues and is never
held across I/O.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from itertools import islice
from pathlib import Path
from types import MappingProxyType
from typing import Any

from controller.quality.journal import (
    JournalEntry,
    bare_failed,
    checked_log,
    checked_sink_args,
    log_unavailable,
    one_line,
    parse_line,
    takes_keyword,
)
from controller.quality.log import QualityRecord, RecordRefusedError, storable, utc_iso
from core.fileio import atomic_write_text, fsync_dir

__all__ = [
    "CLOSE_TIMEOUT_S",
    "COMPACT_BYTES",
    "COMPACT_IDLE_S",
    "DB_TIMEOUT_S",
    "MAX_IN_MEMORY",
    "SharedLog",
    "SinkState",
    "WriteAheadSink",
    "WriterGroup",
]

DB_TIMEOUT_S = 2.0
"""Time limit of one database write (SQLite busy timeout; PostgreSQL statement timeout), s."""
JOURNAL_BATCH_MAX = 500
"""Most records per journal append (one fsync)."""
DB_BATCH_MAX = 500
"""Most records per database transaction."""
MAX_IN_MEMORY = 2000
"""Most journalled records kept in memory for the database thread; the rest are read back from
the journal when it catches up."""
COMPACT_BYTES = 1 << 20
"""The journal is truncated once everything in it is logged and it is this large, bytes ..."""
COMPACT_IDLE_S = 1.0
"""... or once everything in it is logged and nothing came for this long, s."""
RETRY_INITIAL_S = 0.2
RETRY_MAX_S = 5.0
"""Back-off between failed database writes: from the first to the last value, doubling, s."""
CLOSE_TIMEOUT_S = 5.0
"""How long :meth:`WriteAheadSink.close` waits for the database by default, s."""
JOURNAL_WAIT_S = 0.04
"""At most one journal append (one fsync) per this long, s: the records that come meanwhile
wait for the next (at 100 pairs/s about four a batch). The first after a pause (or the start)
and a full batch (:data:`JOURNAL_BATCH_MAX`) go at once."""
DB_WAIT_S = 0.25
"""At most one database transaction per this long, s (the records are durable in the journal
meanwhile). Neither wait holds up :meth:`WriteAheadSink.close` or
:meth:`~WriteAheadSink.wait_logged`."""
_READ_CHUNK = 1 << 20
_datasync = getattr(os, "fdatasync", os.fsync)
"""Flush an append's data and the size it needs to be read back (the same durability as fsync
for a journal that is only appended to; fsync where there is no fdatasync)."""


@dataclass(frozen=True)
class SinkState:
    """What the writer threads last published (read without a lock, on any thread).

    Attributes
    ----------
    problem : str or None
        The log's or the journal's trouble in one line; ``None`` when all is logged.
    pending : int
        Records handed in and not yet in the log (queued, in the journal, or in memory).
    unsaved : int
        Records neither the journal nor the log took (held in memory: not durable).
    failing : bool
        Control must stop for the log: records not durable, or the log refuses them (a log
        that only does not answer while the journal keeps every record is not failing).
    counters : Mapping[str, int]
        ``journalled``, ``logged``, ``rewritten`` (refused values made failed records),
        ``batches`` (journal appends), ``db_batches`` (database transactions), ``compactions``.
    """

    problem: str | None = None
    pending: int = 0
    unsaved: int = 0
    failing: bool = False
    counters: Mapping[str, int] = field(default_factory=lambda: MappingProxyType({}))


def _parse_lines(data: bytes, start: int) -> tuple[list[JournalEntry], list[str], int, int]:
    """The whole lines of a journal chunk read from offset ``start`` (at most a memory's).

    Returns ``(entries, lines that are not records, blank lines, the offset after the last line
    taken)``; at most :data:`MAX_IN_MEMORY` entries.
    """
    entries: list[JournalEntry] = []
    bad: list[str] = []
    blank, pos = 0, start
    for raw in data.split(b"\n")[:-1]:  # whole lines only
        pos += len(raw) + 1
        if not raw.strip():
            blank += 1
        else:
            try:
                entries.append(parse_line(raw))
            except ValueError:
                bad.append(raw.decode("utf-8", "backslashreplace"))
        if len(entries) >= MAX_IN_MEMORY:
            break
    return entries, bad, blank, pos


def _append_synced(fd: int, body: bytes) -> int:
    """Write ``body`` at the end of the file ``fd`` and flush it; its offset.

    Raises ``OSError`` with nothing of ``body`` left behind (no torn line).
    """
    start = os.fstat(fd).st_size
    try:
        view = memoryview(body)
        while view:
            view = view[os.write(fd, view):]
        _datasync(fd)
    except OSError:
        with contextlib.suppress(OSError):
            os.ftruncate(fd, start)
        raise
    return start


def _empty_journal(path: Path, fd: int | None, bad: str, *, remove: bool) -> None:
    """Leave the journal holding only ``bad`` (its lines that are not records), durably.

    Without them: truncated through ``fd`` (or the path), or ``remove``d (at close).
    """
    if bad:
        atomic_write_text(path, bad)
    elif remove:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
            fsync_dir(path.parent)
    elif fd is not None:
        os.ftruncate(fd, 0)
        os.fsync(fd)
    else:
        with open(path, "r+b") as fh:
            fh.truncate(0)
            os.fsync(fh.fileno())


def _tail_of(path: Path) -> tuple[int, int]:
    """``(end of the last whole line, lines)`` of a journal; a torn last line is cut off."""
    try:
        fh = open(path, "r+b")  # noqa: SIM115 - closed below
    except (FileNotFoundError, NotADirectoryError):
        return 0, 0
    with fh:
        size = os.fstat(fh.fileno()).st_size
        pos, end, lines = 0, 0, 0
        while pos < size:
            chunk = fh.read(_READ_CHUNK)
            if not chunk:
                break
            n = chunk.count(b"\n")
            if n:
                lines += n
                end = pos + chunk.rfind(b"\n") + 1
            pos += len(chunk)
        if end < size:  # a torn last line: its append never returned (not acknowledged)
            fh.truncate(end)
            os.fsync(fh.fileno())
    return end, lines


class WriterGroup:
    """The two writer threads of one log, for one sink or for every head's sink of a moulder.

    A :class:`WriteAheadSink` given a plain log makes a group of its own. A moulder's heads
    share one (:meth:`head_log` gives each head its view of the one log): each head's sink
    keeps its journal file, its items and answers and its :class:`SinkState`, while ONE
    journal thread appends every head's batch (each to its journal, each fsync'ed) and ONE
    database thread writes every head's journalled records in one transaction on the one
    connection. A head's records reach the log in its order.

    Parameters
    ----------
    log : QualityLog
        The log the database thread writes. Its write timeout is set to ``db_timeout_s``.
    db_timeout_s : float, keyword-only
        Time limit of one database write.
    """

    def __init__(self, log: Any, *, db_timeout_s: float = DB_TIMEOUT_S) -> None:
        self._uid_ok = checked_log(log)
        self.log = log
        self._many = getattr(log, "append_many", None)
        self._text_ok = self._many is not None and takes_keyword(self._many, "extra_json")
        self._one_text_ok = takes_keyword(log.append, "extra_json")
        setter = getattr(log, "set_write_timeout", None)
        if setter is not None:
            with contextlib.suppress(OSError, ValueError):
                setter(db_timeout_s)
        self.lock = threading.RLock()  # every member's queues; never held across I/O
        self.journal_cv = threading.Condition(self.lock)  # the journal thread waits for items
        self.db_cv = threading.Condition(self.lock)  # the database thread waits for records
        self.members: list[WriteAheadSink] = []
        # the last journal append, database write: none yet (the first goes at once, however
        # long the clock has run)
        self.journal_at = self.db_at = -math.inf
        # a thread that waits for its first record (no timed wait for more): a record woken
        # for; one that waits for more until its time, or writes, finds them when it looks
        self.journal_idle = self.db_idle = False
        self._journal_thread = threading.Thread(target=self._run, args=(self._journal_loop,),
                                                daemon=True, name="quality-journal")
        self._db_thread = threading.Thread(target=self._run, args=(self._db_loop,),
                                           daemon=True, name="quality-database")
        self._started = False
        self._closed = False
        self._writing = False  # the database thread is inside a write
        self.transactions = 0
        """Database transactions the group wrote (each with records of one or more sinks)."""

    def head_log(self) -> SharedLog:
        """A head's view of the group's log: a sink given it joins this group."""
        return SharedLog(self.log, self)

    def join(self, sink: WriteAheadSink) -> None:
        """Take ``sink`` in (before its first item; with :attr:`lock` held or not)."""
        with self.lock:
            if self._closed or (self._started and not self.members):
                raise ValueError("the writer group is closed")
            self.members.append(sink)

    def leave(self, sink: WriteAheadSink) -> None:
        """Let ``sink`` go (closed): the threads end once no sink is left."""
        with self.lock:
            if sink in self.members:
                self.members.remove(sink)
            self.wake()

    def start(self) -> None:
        """Start the two threads (with :attr:`lock` held; from a sink's first item)."""
        if not self._started:
            self._started = True
            self._journal_thread.start()
            self._db_thread.start()

    def wake(self) -> None:
        """Wake both threads (:attr:`lock` held)."""
        self.journal_cv.notify_all()
        self.db_cv.notify_all()

    @property
    def journal_alive(self) -> bool:
        """Whether the journal thread runs."""
        return self._journal_thread.is_alive()

    @property
    def database_alive(self) -> bool:
        """Whether the database thread runs."""
        return self._db_thread.is_alive()

    def close(self) -> None:
        """Close the log (every sink closed first) unless a write of it never returned."""
        with self.lock:
            self._closed = True
            members = list(self.members)
            self.wake()
        for sink in members:  # a head whose service never closed (an error while opening)
            sink.close()
        with self.lock:
            hung = self._writing and self._db_thread.is_alive()
        if not hung:  # a call that never returns holds the log: leave it to the exit
            self.log.close()

    def _run(self, loop: Callable[[], None]) -> None:
        with self.lock:
            setups = [m.thread_setup for m in self.members if m.thread_setup is not None]
        if setups:
            setups[0]()
        loop()

    def _wait_left(self, until: float, waiting: int, most: int) -> float:
        """How long a writer thread still waits for more records (:attr:`lock` held), s."""
        if waiting >= most or any(m._closing or m._stop_db or m._hurry for m in self.members):
            return 0.0
        return until - time.monotonic()

    # -- the journal thread -------------------------------------------------------------------

    def _journal_loop(self) -> None:
        while True:
            with self.lock:
                while not self._inbox_most() and not self._all_closing():
                    unsaved = any(m._unsaved for m in self.members)
                    self.journal_idle = True
                    self.journal_cv.wait(1.0 if unsaved else None)
                    self.journal_idle = False
                    if unsaved and not self._inbox_most():
                        break  # try the journal again for the records only in memory
                while (n := self._inbox_most()) and (left := self._wait_left(
                        self.journal_at + JOURNAL_WAIT_S, n, JOURNAL_BATCH_MAX)) > 0:
                    self.journal_cv.wait(left)  # more records for this append (one fsync)
                if not self._inbox_most() and self._all_closing():
                    return
                work = [w for m in self.members if (w := m._take_inbox()) is not None]
                self.journal_at = time.monotonic()
            for sink, items, retry in work:
                sink._journal_batch(items, retry)

    def _inbox_most(self) -> int:
        return max((len(m._inbox) for m in self.members), default=0)

    def _all_closing(self) -> bool:
        return all(m._closing for m in self.members)

    # -- the database thread ------------------------------------------------------------------

    def _db_loop(self) -> None:
        delay = RETRY_INITIAL_S
        while True:
            with self.lock:
                active = self._db_wait()
                if not active:
                    return
                spills = [(m, m._spill) for m in active if m._spill is not None and not m._todo]
                batch: list[tuple[WriteAheadSink, JournalEntry]] = []
                for m in active if not spills else ():
                    batch += [(m, e) for e in islice(m._todo, DB_BATCH_MAX - len(batch))]
                for m in {m: None for m, _ in batch}:
                    m._db_in_call = True
                self._writing = bool(batch)
            if spills:
                for m, spill in spills:
                    m._read_back(spill)
                continue
            if not batch:
                for m in active:
                    m._compact(force=False)
                continue
            self.db_at = time.monotonic()
            written = self._write(batch)
            if self._after_write(batch, written):
                delay = RETRY_INITIAL_S
                continue
            with self.lock:
                if any(not m._db_done for m, _ in batch):
                    self.db_cv.wait(delay)  # a close wakes it
                    delay = min(2 * delay, RETRY_MAX_S)

    def _db_wait(self) -> list[WriteAheadSink]:
        """Wait for records (and a transaction's worth); the sinks still written (``lock``)."""
        while True:
            active = self._db_active()
            if not active:
                return []
            if any(m._todo or m._spill is not None for m in active):
                break
            if any(m._compact_due() for m in active):
                return active
            self.db_idle = True
            self.db_cv.wait(COMPACT_IDLE_S)
            self.db_idle = False
        while (n := sum(len(m._todo) for m in active)) and not any(
                m._spill is not None for m in active) and (left := self._wait_left(
                self.db_at + DB_WAIT_S, n, DB_BATCH_MAX)) > 0:
            self.db_cv.wait(left)  # more records for this transaction
            active = self._db_active()
        return active

    def _db_active(self) -> list[WriteAheadSink]:
        """The sinks the database thread still writes (``lock``): the others are told done."""
        active = []
        for m in self.members:
            if not m._db_done and (m._abandoned or (
                    m._stop_db and not m._todo and m._spill is None)):
                m._db_done = True
                m._cond.notify_all()
            if not m._db_done:
                active.append(m)
        return active

    def _after_write(self, batch: list[tuple[WriteAheadSink, JournalEntry]],
                     written: int) -> bool:
        """What went in leaves the sinks' queues; whether all did."""
        late: dict[WriteAheadSink, list[Any]] = {}
        with self.lock:
            self._writing = False
            logged: dict[WriteAheadSink, int] = {m: 0 for m, _ in batch}
            for m, e in batch[:written]:
                m._todo.popleft()
                logged[m] += 1
                if m._unsaved.pop(e.uid, None) is not None:
                    late.setdefault(m, []).extend(m._take_unsaved_items([e]))
            for m, n in logged.items():
                m._db_in_call = False
                m._pending -= n
                m._counts["logged"] += n
                if written == len(batch):
                    m._log_error = None
                elif m._stop_db:
                    m._db_done = True  # closing: what is left stays in the journal
                m._publish()
        for m, items in late.items():
            if m._on_durable is not None:
                m._on_durable(items, True)  # in the log: durable at last (no lock held)
        if written < len(batch):
            return False
        for m in logged:
            with self.lock:
                idle = not m._todo and m._spill is None
            if idle:
                m._compact(force=False)
        return True

    def _write(self, batch: list[tuple[WriteAheadSink, JournalEntry]]) -> int:
        """Write entries to the log, in order: how many went in (the rest wait)."""
        many = self._many
        if many is not None:
            kw: dict[str, Any] = {}
            if self._uid_ok:
                kw["uids"] = [e.uid for _, e in batch]
            if self._text_ok:
                kw["extra_json"] = [e.extra_json for _, e in batch]
            try:
                many([e.record for _, e in batch], **kw)
                self._count_transaction(batch)
                return len(batch)
            except RecordRefusedError:
                pass  # record by record below: the refused one rewritten
            except (OSError, ValueError) as exc:
                self._note_log_error(batch, exc)
                return 0
        for n, (m, e) in enumerate(batch):
            if not self._write_one(batch, m, e):
                return n
        self._count_transaction(batch)
        return len(batch)

    def _count_transaction(self, batch: list[tuple[WriteAheadSink, JournalEntry]]) -> None:
        with self.lock:
            self.transactions += 1
            for m in {m: None for m, _ in batch}:
                m._counts["db_batches"] += 1

    def _write_one(self, batch: list[tuple[WriteAheadSink, JournalEntry]],
                   sink: WriteAheadSink, entry: JournalEntry) -> bool:
        record = entry.record
        kw: dict[str, Any] = {"uid": entry.uid} if self._uid_ok else {}
        if self._one_text_ok:
            kw["extra_json"] = entry.extra_json
        for attempt in (0, 1):
            try:
                self.log.append(record, **kw)
                return True
            except RecordRefusedError as exc:
                if attempt == 1:  # even the bare record refused: the log's trouble
                    with self.lock:
                        for m in {m: None for m, _ in batch}:
                            m._log_error = f"quality log refused a record: {one_line(exc)}"
                            m._log_unavailable = False
                    return False
                record = bare_failed(record, exc)  # never blocks the records behind it
                kw.pop("extra_json", None)
                with self.lock:
                    sink._counts["rewritten"] += 1
            except (OSError, ValueError) as exc:
                self._note_log_error(batch, exc)
                return False
        return False

    def _note_log_error(self, batch: list[tuple[WriteAheadSink, JournalEntry]],
                        exc: BaseException) -> None:
        with self.lock:
            for m in {m: None for m, _ in batch}:
                m._log_error = f"quality log write failed: {one_line(exc)}"
                m._log_unavailable = log_unavailable(exc)


class SharedLog:
    """A head's view of the one quality log a moulder's heads share (see :class:`WriterGroup`).

    Everything is the log's but :meth:`close`, which does nothing: the group closes the log
    after every head (:meth:`WriterGroup.close`). A :class:`WriteAheadSink` given this view
    joins the group.
    """

    def __init__(self, log: Any, group: WriterGroup) -> None:
        self._log = log
        self.writer_group = group

    def close(self) -> None:
        """Nothing: the group closes the log after every head (:meth:`WriterGroup.close`)."""

    def __len__(self) -> int:
        return len(self._log)

    def __getattr__(self, name: str) -> Any:
        if name == "_log":  # not set yet (a copy being made)
            raise AttributeError(name)
        return getattr(self._log, name)

    def __repr__(self) -> str:
        return f"SharedLog({self._log!r})"


class WriteAheadSink:
    """Journal first (fsync), database after; two threads, none waits for the other.

    Parameters
    ----------
    log : QualityLog or SharedLog
        The quality log (not owned). Its write timeout is set to :data:`DB_TIMEOUT_S`. A
        head's view of a moulder's shared log (:meth:`WriterGroup.head_log`): this sink's
        records go through that group's two threads, with every other head's.
    journal_path : Path, keyword-only
        The journal. One left by an earlier run (a crash, a log that was down at close) is
        written to the log first, in order (a torn last line is cut off).
    make : callable, keyword-only
        ``make(item) -> QualityRecord``, called on the journal thread for each item
        :meth:`put` queued (default: the item is the record).
    on_durable : callable, keyword-only, optional
        ``on_durable(items, durable)`` on the journal thread after each batch: ``durable`` is
        ``False`` when the journal could not be written (the records are then only in memory
        until the log takes them). Items answered ``False`` are answered again, ``True``, once
        their records are durable (on the journal thread after a journal retry, or on the
        database thread when the log took them); no lock of the sink is held during the call.
    db_timeout_s : float, keyword-only
        Time limit of one database write (of a group of its own).
    """

    def __init__(self, log: Any, *, journal_path: Path,
                 make: Callable[[Any], QualityRecord] | None = None,
                 on_durable: Callable[[list[Any], bool], None] | None = None,
                 db_timeout_s: float = DB_TIMEOUT_S) -> None:
        self.log = log
        _, self.journal_path = checked_sink_args(log, journal_path)
        group = getattr(log, "writer_group", None)
        self._group = group if isinstance(group, WriterGroup) else WriterGroup(
            log, db_timeout_s=db_timeout_s)
        self._make = make or (lambda item: item)
        self._on_durable = on_durable
        end, lines = _tail_of(self.journal_path)
        self._cond = threading.Condition(self._group.lock)  # who waits for the state
        self._inbox: deque[Any] = deque()  # put, not yet with the journal thread
        self._todo: deque[JournalEntry] = deque()  # for the database thread, in order
        self._spill: tuple[int, int] | None = (0, end) if end else None  # journal bytes
        self._unsaved: dict[str, JournalEntry] = {}  # not journalled, not logged (memory)
        self._unsaved_items: dict[str, Any] = {}  # their items, answered when durable at last
        self._bad_lines: list[str] = []
        self._pending = lines  # handed in (or left in the journal), not yet logged
        self._in_journal = 0  # with the journal thread now
        self._in_hand = False  # the journal thread works on this sink's batch (till answered)
        self._db_in_call = False  # the database thread is inside a write of its records
        self._db_done = False  # the database thread writes no more of its records (closing)
        self._file_lock = threading.Lock()  # the journal file (local disk I/O only)
        self._fd: int | None = None
        self._size = end  # bytes in the journal
        self._compact_failed_at: float | None = None
        self._compact_error: str | None = None
        self._log_error: str | None = None
        self._log_unavailable = False
        self._journal_error: str | None = None
        self._last_put = time.monotonic()
        self._hurry = 0  # callers of wait_logged: no waiting for more records meanwhile
        self._closing = False
        self._stop_db = False
        self._abandoned = False
        self._counts = {"journalled": 0, "logged": 0, "rewritten": 0, "batches": 0,
                        "db_batches": 0, "compactions": 0}
        self.state = SinkState()
        """The last published :class:`SinkState` (read it, never lock it)."""
        with self._cond:
            self._publish()
        self.thread_setup: Callable[[], None] | None = None
        """Called first on each of the two threads (e.g. to lower their priority; of a
        shared group, the first head's)."""
        self._group.join(self)

    def _start(self) -> None:
        """Start the group's threads (with ``_cond`` held; from the first :meth:`put`)."""
        self._group.start()

    # -- the caller's side --------------------------------------------------------------------

    def put(self, item: Any) -> None:
        """Queue one item (its record is made and journalled on the journal thread)."""
        with self._cond:
            if self._closing:
                raise ValueError("the record sink is closed")
            self._inbox.append(item)
            self._pending += 1
            self._start()
            group = self._group
            if (len(self._inbox) == 1 and group.journal_idle) or \
                    len(self._inbox) >= JOURNAL_BATCH_MAX:
                group.journal_cv.notify()  # else it waits for more until its time anyway

    @property
    def queued(self) -> int:
        """Items not yet journalled (queued or with the journal thread now)."""
        return len(self._inbox) + self._in_journal

    def _wake(self) -> None:
        """Wake both writer threads and who waits for the state (``_cond`` held)."""
        for cv in (self._cond, self._group.journal_cv, self._group.db_cv):
            cv.notify_all()

    def _publish(self) -> None:
        """Replace :attr:`state` and wake who waits for it (called with ``_cond`` held)."""
        parts = []
        waiting = self._pending
        if self._log_error and waiting:
            parts.append(self._log_error)
        journalled = waiting - len(self._unsaved) - len(self._inbox) - self._in_journal
        if self._log_error and journalled > 0:
            parts.append(f"{journalled} record(s) kept in journal {self.journal_path}")
        if self._unsaved:
            parts.append(f"{len(self._unsaved)} record(s) NOT durable (held in memory)")
        parts += [e for e in (self._journal_error, self._compact_error) if e]
        if self._bad_lines:
            parts.append(f"{len(self._bad_lines)} line(s) of journal {self.journal_path} are "
                         "not records (kept in the journal)")
        refusing = bool(self._log_error and waiting and not self._log_unavailable)
        self.state = SinkState(problem="; ".join(parts) or None, pending=waiting,
                               unsaved=len(self._unsaved),
                               failing=bool(self._unsaved) or refusing,
                               counters=MappingProxyType(dict(self._counts)))
        self._cond.notify_all()

    # -- on the journal thread ----------------------------------------------------------------

    def _take_inbox(self) -> tuple[WriteAheadSink, list[Any], list[JournalEntry]] | None:
        """A batch for the journal thread (with the group's lock held), or ``None``."""
        items = [self._inbox.popleft()
                 for _ in range(min(len(self._inbox), JOURNAL_BATCH_MAX))]
        retry = list(self._unsaved.values())
        if not items and not retry:
            return None
        self._in_journal = len(items)
        self._in_hand = True
        return self, items, retry

    def _journal_batch(self, items: list[Any], retry: list[JournalEntry]) -> None:
        """Make, journal and answer one batch (the journal thread, no lock held)."""
        try:
            entries = [self._entry(item) for item in items]
            ok, late = self._journal(retry, entries, items)
            try:
                if self._on_durable is not None:
                    if items:
                        self._on_durable(items, ok)
                    if late:
                        self._on_durable(late, True)
            finally:
                if not ok and entries:  # answered False first: the log's True comes after
                    with self._cond:
                        self._todo.extend(entries)  # the log may still take them
                        self._group.db_cv.notify()
        finally:
            with self._cond:
                self._in_hand = False
                self._cond.notify_all()

    def _entry(self, item: Any) -> JournalEntry:
        try:
            record = self._make(item)
        except (ValueError, TypeError, ArithmeticError, AttributeError, LookupError) as exc:
            # odd values in a result: a failed record that says why, never a lost pair
            record = bare_failed(QualityRecord(t_s=0.0, wall_time=utc_iso(time.time()),
                                               seq=0, board_id=0, board_position_mm=0.0,
                                               ok=False), exc)
        rec, text = storable(record)
        if rec is not record:
            with self._cond:
                self._counts["rewritten"] += 1
        return JournalEntry(uuid.uuid4().hex, rec, text)

    def _journal(self, retry: list[JournalEntry], entries: list[JournalEntry],
                 items: list[Any]) -> tuple[bool, list[Any]]:
        """Append and fsync; hand the entries to the database thread when that worked.

        Returns whether it worked, and the items of ``retry`` now durable at last. Entries the
        journal could not take are kept in memory (``_unsaved``); the caller hands them on
        after answering them ``False``.
        """
        lines = [e.line().encode("utf-8") for e in retry + entries]
        with self._file_lock:
            try:
                start = self._append(b"".join(lines))
                ok = True
            except (OSError, ValueError) as exc:  # the records stay in memory, said
                ok = False
                err = f"journal {self.journal_path} not writable: {one_line(exc)}"
            with self._cond:
                self._in_journal = 0
                late: list[Any] = []
                if ok:
                    self._journal_error = None
                    for e in retry:
                        if self._unsaved.pop(e.uid, None) is not None:
                            late += self._take_unsaved_items([e])
                    first = start + sum(len(b) for b in lines[:len(retry)])
                    end = start + sum(len(b) for b in lines)
                    self._counts["journalled"] += len(entries) + len(retry)
                    self._counts["batches"] += 1
                    idle = not self._todo and self._spill is None
                    if self._spill is None and len(self._todo) + len(entries) <= MAX_IN_MEMORY:
                        self._todo.extend(entries)
                    elif entries:  # the backlog waits on disk, read back later
                        self._spill = (self._spill[0] if self._spill else first, end)
                    if (idle and self._group.db_idle) or len(self._todo) >= DB_BATCH_MAX:
                        self._group.db_cv.notify()  # else it waits for more until its time anyway
                else:
                    self._journal_error = err
                    for e, item in zip(entries, items, strict=True):
                        self._unsaved[e.uid] = e
                        self._unsaved_items[e.uid] = item
                self._last_put = time.monotonic()
                self._publish()
        return ok, late

    def _take_unsaved_items(self, entries: list[JournalEntry]) -> list[Any]:
        """The items of entries that were only in memory and are durable now (``_cond``)."""
        return [self._unsaved_items.pop(e.uid) for e in entries if e.uid in self._unsaved_items]

    def _append(self, body: bytes) -> int:
        """Write ``body`` at the journal's end and fsync; its offset. Nothing torn on failure."""
        created = False
        if self._fd is None:
            p = self.journal_path
            if not p.parent.is_dir():  # a database log's journal folder (state folder)
                p.parent.mkdir(parents=True, exist_ok=True)
            created = not p.exists()
            self._fd = os.open(p, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC, 0o666)
        start = _append_synced(self._fd, body)
        if created:
            fsync_dir(self.journal_path.parent)
        self._size = start + len(body)
        return start

    # -- on the database thread ---------------------------------------------------------------

    def _read_back(self, spill: tuple[int, int]) -> None:
        """Read journalled entries the memory had no room for (``spill``: byte range)."""
        start, end = spill
        try:
            with open(self.journal_path, "rb") as fh:
                fh.seek(start)
                data = fh.read(min(end - start, 16 * _READ_CHUNK))
        except OSError as exc:
            with self._cond:
                self._journal_error = f"journal {self.journal_path} not readable: {one_line(exc)}"
                self._publish()
                self._group.db_cv.wait(RETRY_MAX_S)
            return
        entries, bad, blank, pos = _parse_lines(data, start)
        with self._cond:
            self._todo.extend(entries)
            self._bad_lines.extend(bad)
            self._pending -= len(bad) + blank
            cur = self._spill
            if cur is not None:
                self._spill = None if pos >= cur[1] else (pos, cur[1])
            self._publish()

    def _compact_due(self) -> bool:
        """Everything journalled is logged and the journal is worth truncating (``_cond``)."""
        if self._todo or self._spill is not None or self._inbox or self._in_journal:
            return False
        now = time.monotonic()
        if self._compact_failed_at is not None and now - self._compact_failed_at < RETRY_MAX_S:
            return False
        idle = now - self._last_put >= COMPACT_IDLE_S
        size = self._size
        bad = sum(len(b.encode("utf-8")) + 1 for b in self._bad_lines)  # kept in it
        return size > bad and (idle or size >= COMPACT_BYTES)

    def _compact(self, *, force: bool) -> None:
        """Truncate the journal (keep lines that are not records) if everything is logged."""
        with self._file_lock:  # the journal thread appends nothing meanwhile
            with self._cond:
                if (self._abandoned and not force) or self._todo or self._spill is not None \
                        or self._unsaved:
                    return
                if not force and not self._compact_due():
                    return
                bad = "".join(b + "\n" for b in self._bad_lines)
            try:  # no lock the caller's thread takes is held here
                if bad or force:
                    self._close_fd()
                _empty_journal(self.journal_path, self._fd, bad, remove=force)
            except OSError as exc:  # replay skips what the log holds: no duplicate
                with self._cond:
                    self._compact_failed_at = time.monotonic()
                    self._compact_error = (f"journal {self.journal_path} not rewritten: "
                                           f"{one_line(exc)}")
                    self._publish()
                return
            with self._cond:
                self._size = len(bad.encode("utf-8"))
                self._compact_failed_at = None
                self._compact_error = None
                self._counts["compactions"] += 1
                self._publish()

    def _close_fd(self) -> None:
        fd, self._fd = self._fd, None
        if fd is not None:
            with contextlib.suppress(OSError):
                os.close(fd)

    # -- closing ------------------------------------------------------------------------------

    def close(self, timeout_s: float = CLOSE_TIMEOUT_S) -> Path | None:
        """Journal what is queued, wait at most ``timeout_s`` for the log; the journal left.

        Returns
        -------
        Path or None
            The journal still holding records the log has not taken (named by the caller), or
            ``None`` when every record is in the log (the journal is removed). Records neither
            the journal nor the log took are printed on stderr (``unsaved quality record:``).
        """
        group = self._group
        with self._cond:
            if self._abandoned:  # closed before
                return self._left()
            self._closing = True
            self._start()  # a journal left by an earlier run is replayed even without pairs
            self._wake()
            while (self._inbox or self._in_hand) and group.journal_alive:
                self._cond.wait(0.1)  # local disk only
        deadline = time.monotonic() + max(0.0, timeout_s)
        with self._cond:  # the log gets what is left, but not forever
            while (self._todo or self._spill is not None) and group.database_alive:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(min(left, 0.1))
            self._stop_db = True
            self._wake()
            until = max(deadline, time.monotonic()) + 0.05
            while not self._db_done and group.database_alive and (
                    left := until - time.monotonic()) > 0:
                self._cond.wait(min(left, 0.1))
            self._abandoned = True
            self._wake()
        if not self._db_in_call and not self._pending:
            self._compact(force=True)
        with self._file_lock:
            self._close_fd()
        with self._cond:
            for e in self._unsaved.values():
                print(f"unsaved quality record: {e.line()}", end="", file=sys.stderr)
            sys.stderr.flush()
            self._pending -= len(self._unsaved)
            self._unsaved.clear()
            self._unsaved_items.clear()  # never answered durable: never handled
            self._publish()
        group.leave(self)
        return self._left()

    def _left(self) -> Path | None:
        """The journal still holding records the log has not taken, or ``None``."""
        with self._cond:
            left = self._pending > 0 or bool(self._bad_lines)
        return self.journal_path if left and self.journal_path.exists() else None

    def wait_logged(self, timeout_s: float) -> bool:
        """Block until every record handed in is in the log, at most ``timeout_s``.

        For tests and tools, never the event loop. Returns whether everything is logged.
        """
        deadline = time.monotonic() + timeout_s
        with self._cond:
            if self._pending:
                self._start()
            self._hurry += 1
            self._wake()
            try:
                while self._pending and not self._abandoned:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        return False
                    self._cond.wait(min(left, 0.1))
                return not self._pending
            finally:
                self._hurry -= 1

    @property
    def database_busy(self) -> bool:
        """Whether the database thread is still inside a write of this sink's records."""
        return self._db_in_call and self._group.database_alive

    def __repr__(self) -> str:
        return f"WriteAheadSink({self.journal_path}, pending={self.state.pending})"
