"""Nothing lost: a durable local journal for the quality records the log cannot take.

:class:`RecordSink` stands between the service and the :class:`~controller.quality.log.QualityLog`.
``append`` returns only when the record is durable: committed to the log, or written and
fsync'ed to a local append-only journal (JSON lines) when the log cannot take it (database
error, disk full, file locked, log closed). Journalled records are written to the log in their
order by :meth:`RecordSink.retry` (called by the service, and every few appends by the sink
itself); :meth:`RecordSink.close` writes what it can and leaves the rest in the journal file,
whose path it returns (for the service to name on stderr). The next sink opened on the same
journal replays it.

A record holding a value the log's schema refuses (``seq`` = 10**20, text that is not Unicode,
an ``extra`` that is not JSON) is never dropped: it is rewritten as a failed record naming the
field (:func:`controller.quality.log.storable`).

Exactly once: each record gets a UUID when it is appended to the sink; the log stores it in
the same transaction as the record (``QualityLog.append(record, uid=...)``) and skips a
record whose UUID it already holds. So replaying a journal after a crash between the log's
commit and the journal's rewrite appends no record twice. Journal format and guarantees:
``docs/quality_log.md``.
"""

from __future__ import annotations

import contextlib
import inspect
import json
import os
import re
import sys
import threading
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from controller.quality.log import (
    DEFAULT_HEAD,
    QualityLog,
    QualityRecord,
    RecordRefusedError,
    database_url,
    is_database_url,
    record_from_dict,
    record_json,
    storable,
)
from controller.quality.schema import check_head
from core.fileio import atomic_write_text, fsync_dir

__all__ = [
    "JOURNAL_VERSION",
    "RETRY_EVERY_APPENDS",
    "JournalEntry",
    "RecordSink",
    "bare_failed",
    "checked_log",
    "checked_sink_args",
    "default_journal_path",
    "log_unavailable",
    "one_line",
    "parse_line",
    "read_journal",
    "takes_keyword",
]

#: Version written in each journal line (``"v"``).
JOURNAL_VERSION = 1
#: While records wait in the journal, ``append`` retries the log every this many appends.
RETRY_EVERY_APPENDS = 8


def default_journal_path(log_path: str | Path, *, head: str = DEFAULT_HEAD) -> Path:
    """The journal of a quality log, on local disk.

    Beside an SQLite file: ``run.db`` -> ``run.db.journal.jsonl``. For a PostgreSQL URL
    (``postgresql://USER@HOST:PORT/DB``): ``$XDG_STATE_HOME/planer/`` (``~/.local/state``
    without it) ``USER@HOST_PORT_DB.journal.jsonl``; the password is never part of the name.
    The folder is created when the first record is journalled. ``head``: a moulder's head
    other than ``"main"`` keeps its own journal, ``run.db.<head>.journal.jsonl`` (each head's
    records stage writes its own).
    """
    name = check_head("head", head)
    path = _journal_path(log_path)
    if name == DEFAULT_HEAD:
        return path
    return path.with_name(path.name.removesuffix(".journal.jsonl") + f".{name}.journal.jsonl")


def _journal_path(log_path: str | Path) -> Path:
    if is_database_url(log_path):
        from urllib.parse import urlsplit

        parts = urlsplit(database_url(log_path))
        try:
            port = parts.port or 5432
        except ValueError:
            port = 0
        user = f"{parts.username}@" if parts.username else ""
        name = f"{user}{parts.hostname or 'localhost'}_{port}_{parts.path.strip('/')}"
        name = re.sub(r"[^A-Za-z0-9@._-]+", "_", name)
        state = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
        return Path(state) / "planer" / f"{name}.journal.jsonl"
    p = Path(log_path)
    return p.with_name(p.name + ".journal.jsonl")


def read_journal(path: str | Path) -> tuple[list[QualityRecord], int]:
    """The records a journal holds, read only (nothing replayed); for reports.

    Returns
    -------
    records : list of QualityRecord
        The journalled records, oldest first (some may already be in the log after a crash).
    bad : int
        Lines that are not records (a torn last line included).

    Raises
    ------
    OSError
        The journal cannot be read (``FileNotFoundError`` when there is none).
    """
    records: list[QualityRecord] = []
    bad = 0
    for raw in Path(path).read_bytes().split(b"\n"):
        if not raw.strip():
            continue
        try:
            obj = json.loads(raw.decode("utf-8"))
            records.append(record_from_dict(obj["record"]))
        except (ValueError, KeyError, TypeError, RecursionError):
            bad += 1
    return records, bad


def log_unavailable(exc: BaseException) -> bool:
    """Whether a log error only says the log did not answer in time or cannot be reached.

    ``TimeoutError`` (another writer holds the lock beyond the write timeout, a statement
    timed out) and ``ConnectionError`` (the database server is gone or does not answer): the
    records wait on local disk and go in later. Any other error (disk full, I/O error, a
    damaged file) means the log refuses them.
    """
    return isinstance(exc, (TimeoutError, ConnectionError))


def parse_line(raw: bytes) -> JournalEntry:
    """The entry of one journal line (without its newline).

    Raises
    ------
    ValueError
        The line is not a journal record (``KeyError``/``TypeError`` turned into it).
    """
    try:
        obj = json.loads(raw.decode("utf-8", "backslashreplace"))
        uid = obj["uid"]
        if not isinstance(uid, str) or not uid:
            raise ValueError("uid must be a non-empty string")
        return JournalEntry(uid, *storable(record_from_dict(obj["record"])))
    except (KeyError, TypeError, RecursionError, AttributeError) as exc:
        raise ValueError(f"not a journal record: {exc}") from None


@dataclass(frozen=True)
class JournalEntry:
    """One journalled record and its identity (the uid the log stores with it).

    ``extra_json``: the record's ``extra`` as the log stores it (:func:`storable`'s text),
    when known: the journal line and the log's row reuse it (a record is encoded once).
    """

    uid: str
    record: QualityRecord
    extra_json: str | None = field(default=None, compare=False, repr=False)

    def line(self) -> str:
        """The journal line (a record that cannot be JSON becomes a failed one saying why)."""
        head = f'{{"v":{JOURNAL_VERSION},"uid":{json.dumps(self.uid)},"record":'
        try:
            rec = record_json(self.record, extra_json=self.extra_json)
        except (TypeError, ValueError, RecursionError) as exc:
            rec = record_json(bare_failed(self.record, exc))
        return f"{head}{rec}}}\n"


def bare_failed(record: QualityRecord, exc: BaseException) -> QualityRecord:
    """A failed record the log surely stores, for one it refused although it looked storable."""
    return QualityRecord(
        t_s=record.t_s, wall_time=record.wall_time, seq=0, board_id=0, board_position_mm=0.0,
        ok=False, error=f"record refused: {one_line(exc)}", head=record.head,
        extra={"refused": {"record": repr(record)[:2000]}},
    )


def one_line(exc: BaseException) -> str:
    """An error as one line of storable text (at most 300 characters)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    text = text.encode("utf-8", "backslashreplace").decode("utf-8")  # storable text
    return text if len(text) <= 300 else text[:297] + "..."


def checked_sink_args(log: Any, journal_path: str | Path) -> tuple[bool, Path]:
    """A sink's log and journal checked: whether the log stores uids, the journal's path.

    Raises
    ------
    ValueError
        ``log`` has no ``append``.
    IsADirectoryError
        ``journal_path`` is a folder.
    """
    uid_ok = checked_log(log)
    path = Path(journal_path)
    if path.is_dir():
        raise IsADirectoryError(f"journal path is a directory: {path}")
    return uid_ok, path


def checked_log(log: Any) -> bool:
    """A writer's log checked (the one place): whether it stores records' uids.

    A log without identities (a test double) still works, without exactly-once.

    Raises
    ------
    ValueError
        ``log`` has no ``append``.
    """
    if not hasattr(log, "append"):
        raise ValueError(f"log must be a QualityLog, got {type(log).__name__}")
    return takes_keyword(log.append, "uid")


def takes_keyword(method: Any, name: str) -> bool:
    """Whether ``method`` takes the keyword argument ``name`` (a log's ``uid``, ...)."""
    try:
        return name in inspect.signature(method).parameters
    except (TypeError, ValueError):
        return False


class RecordSink:
    """Appends quality records to the log, or durably to a local journal when it cannot.

    Parameters
    ----------
    log : QualityLog
        The quality log (not owned: the caller closes it after :meth:`close`).
    journal_path : Path, keyword-only
        The journal file (JSON lines). An existing journal (left by a crash or by a close while
        the log was failing) is read and its records are written to the log by the next
        :meth:`retry` (or :meth:`append`, :meth:`close`); records the log already holds are
        not written again.

    Raises
    ------
    OSError
        The journal exists but cannot be read.

    Notes
    -----
    Thread-safe (one lock). One sink per journal file at a time. A record is *acknowledged*
    when :meth:`append` returns without the record being in :attr:`unsaved`: it is then
    committed to the log or fsync'ed to the journal and survives SIGKILL and power loss.
    """

    def __init__(self, log: QualityLog, *, journal_path: Path) -> None:
        self.log = log
        self._uid_ok, self.journal_path = checked_sink_args(log, journal_path)
        self._text_ok = takes_keyword(log.append, "extra_json")
        self._many_text_ok = takes_keyword(getattr(log, "append_many", None), "extra_json")
        self._lock = threading.RLock()
        self._entries: list[JournalEntry] = []  # in the journal file, not known to be in the log
        self._bad_lines: list[str] = []  # journal lines that are not records (kept, never lost)
        self._unsaved: list[JournalEntry] = []  # neither the log nor the journal took them (memory)
        self._stale = False  # the journal file holds entries already written to the log
        self._log_error: str | None = None
        self._log_unavailable = False  # the log's trouble is only that it does not answer
        self._journal_error: str | None = None
        self._since_retry = 0
        #: Counts: ``logged`` (written to the log), ``journalled`` (written to the journal),
        #: ``rewritten`` (refused values turned into failed records), ``replayed_known``
        #: (journalled records the log already held).
        self.counters = {"logged": 0, "journalled": 0, "rewritten": 0, "replayed_known": 0}
        self._load()

    # -- the journal file ---------------------------------------------------------------------

    def _load(self) -> None:
        p = self.journal_path
        try:
            data = p.read_bytes()
        except (FileNotFoundError, NotADirectoryError):  # no journal (yet)
            return
        end = data.rfind(b"\n") + 1
        if end < len(data):
            # a torn last line: its append never returned (not acknowledged); cut it off
            with open(p, "r+b") as fh:
                fh.truncate(end)
                os.fsync(fh.fileno())
        seen: set[str] = set()
        for raw in data[:end].split(b"\n"):
            if not raw.strip():
                continue
            try:
                entry = parse_line(raw)
            except ValueError:
                self._bad_lines.append(raw.decode("utf-8", "backslashreplace"))
                continue
            if entry.uid not in seen:
                seen.add(entry.uid)
                self._entries.append(entry)
        if self._bad_lines:
            self._journal_error = (f"{len(self._bad_lines)} line(s) of journal {p} are not "
                                   "records (kept in the journal)")
        keep = []
        for e in self._entries:  # a crash after the log's commit, before the journal's rewrite
            try:
                known = self._uid_ok and bool(self.log.has_uid(e.uid))
            except (OSError, ValueError):  # the log's trouble: retry decides later
                known = False
            if known:
                self.counters["replayed_known"] += 1
                self._stale = True
            else:
                keep.append(e)
        self._entries = keep

    def _write_lines(self, entries: list[JournalEntry]) -> None:
        """Append entries to the journal and fsync it; on failure leave the file as it was."""
        p = self.journal_path
        body = "".join(e.line() for e in entries).encode("utf-8")
        if not p.parent.is_dir():  # a database log's journal folder (state folder)
            p.parent.mkdir(parents=True, exist_ok=True)
        created = not p.exists()
        fd = os.open(p, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC, 0o666)
        try:
            start = os.fstat(fd).st_size
            try:
                view = memoryview(body)
                while view:
                    n = os.write(fd, view)
                    view = view[n:]
                os.fsync(fd)
            except OSError:
                with contextlib.suppress(OSError):
                    os.ftruncate(fd, start)  # no torn line left behind
                raise
        finally:
            os.close(fd)
        if created:
            fsync_dir(p.parent)

    def _rewrite(self) -> None:
        """Make the journal file hold exactly the waiting entries (and the bad lines)."""
        p = self.journal_path
        if not self._entries and not self._bad_lines:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(p)
                fsync_dir(p.parent)
        else:
            atomic_write_text(p, "".join(e.line() for e in self._entries)
                              + "".join(b + "\n" for b in self._bad_lines))
        self._stale = False

    def _journal(self, entries: list[JournalEntry]) -> None:
        try:
            self._write_lines(entries)
        except OSError as exc:
            self._unsaved.extend(entries)
            self._journal_error = f"journal {self.journal_path} not writable: {one_line(exc)}"
            return
        self._entries.extend(entries)
        self.counters["journalled"] += len(entries)
        if not self._bad_lines:
            self._journal_error = None

    # -- the log ------------------------------------------------------------------------------

    def _to_log(self, entry: JournalEntry) -> bool:
        """Write one entry to the log; ``False`` (and the reason noted) when it cannot."""
        record = entry.record
        kw: dict[str, Any] = {"extra_json": entry.extra_json} if self._text_ok else {}
        for attempt in (0, 1):
            try:
                if self._uid_ok:
                    self.log.append(record, uid=entry.uid, **kw)
                else:
                    self.log.append(record, **kw)
            except RecordRefusedError as exc:
                if attempt == 1:  # even the bare record refused: the log's trouble
                    self._log_error = f"quality log refused a record: {one_line(exc)}"
                    return False
                record = bare_failed(record, exc)  # never blocks the records behind it
                kw = {}
                self.counters["rewritten"] += 1
                continue
            except (OSError, ValueError) as exc:  # the log's trouble: the journal keeps it
                self._log_error = f"quality log write failed: {one_line(exc)}"
                self._log_unavailable = log_unavailable(exc)
                return False
            break
        self._log_error = None
        self.counters["logged"] += 1
        return True

    def _retry_locked(self) -> int:
        self._since_retry = 0
        if self._unsaved:
            waiting, self._unsaved = self._unsaved, []
            self._journal(waiting)
        written = 0
        while self._entries:
            if not self._to_log(self._entries[0]):
                break
            self._entries.pop(0)
            self._stale = True
            written += 1
        if self._stale:
            try:
                self._rewrite()
            except OSError as exc:  # replay skips what the log holds: no duplicate
                self._journal_error = (f"journal {self.journal_path} not rewritten: "
                                       f"{one_line(exc)}")
        if self._unsaved and not self._entries:  # the journal still refuses: try the log
            while self._unsaved and self._to_log(self._unsaved[0]):
                self._unsaved.pop(0)
                written += 1
        if not self._unsaved and not self._bad_lines and not self._stale:
            self._journal_error = None
        return written

    # -- public -------------------------------------------------------------------------------

    def append(self, record: QualityRecord) -> None:
        """Store one record durably: in the log, or (when the log fails) in the journal.

        Never raises for log or journal trouble (see :attr:`problem`). While records wait in
        the journal, a new one goes there too (the log keeps the records' order); every
        :data:`RETRY_EVERY_APPENDS` appends the log is tried again.

        Parameters
        ----------
        record : QualityRecord
            The measurement. A value the log refuses makes it a failed record naming the field.

        Raises
        ------
        ValueError
            ``record`` is not a :class:`QualityRecord` (a programming error).
        """
        if not isinstance(record, QualityRecord):
            raise ValueError(f"record must be a QualityRecord, got {type(record).__name__}")
        rec, text = storable(record)
        entry = JournalEntry(uuid.uuid4().hex, rec, text)
        with self._lock:
            if rec is not record:
                self.counters["rewritten"] += 1
            if self._entries or self._unsaved:
                self._since_retry += 1
                if self._since_retry >= RETRY_EVERY_APPENDS:
                    self._retry_locked()
            if not self._entries and not self._unsaved and self._to_log(entry):
                return
            self._journal([entry])

    def append_many(self, records: list[QualityRecord]) -> list[int | None]:
        """Store records durably, in order, with one commit: as :meth:`append` for each.

        Records waiting in the journal are tried first (a batch is a retry); while nothing
        waits the records go to the log in one transaction (:meth:`QualityLog.append_many`);
        when the log cannot take them they go to the journal together (one fsync). A record
        the log refuses makes the batch go record by record.

        Returns
        -------
        list of int or None
            Each record's id in the log (``None``: in the journal, or the log gives no ids).
        """
        for record in records:
            if not isinstance(record, QualityRecord):
                raise ValueError(f"record must be a QualityRecord, got {type(record).__name__}")
        batch = getattr(self.log, "append_many", None)
        with self._lock:
            if self._entries or self._unsaved:
                self._retry_locked()
            if self._entries or self._unsaved or batch is None or len(records) < 2:
                for record in records:
                    self.append(record)
                return [None] * len(records)
            made = [storable(r) for r in records]
            entries = [JournalEntry(uuid.uuid4().hex, r, text) for r, text in made]
            self.counters["rewritten"] += sum(
                m[0] is not o for m, o in zip(made, records, strict=True))
            kw: dict[str, Any] = {}
            if self._uid_ok:
                kw["uids"] = [e.uid for e in entries]
            if self._many_text_ok:
                kw["extra_json"] = [e.extra_json for e in entries]
            try:
                ids = batch([e.record for e in entries], **kw)
            except RecordRefusedError:  # one record refused: record by record, rewritten
                for e in entries:
                    if self._entries or self._unsaved or not self._to_log(e):
                        self._journal([e])
                return [None] * len(records)
            except (OSError, ValueError) as exc:  # the log's trouble: the journal keeps them
                self._log_error = f"quality log write failed: {one_line(exc)}"
                self._log_unavailable = log_unavailable(exc)
                self._journal(entries)
                return [None] * len(records)
            self._log_error = None
            self.counters["logged"] += len(entries)
            return [int(i) if isinstance(i, int) else None for i in ids]

    def retry(self) -> int:
        """Write the journalled records to the log, oldest first, until it refuses one.

        Returns
        -------
        int
            Records written to the log by this call.
        """
        with self._lock:
            return self._retry_locked()

    @property
    def problem(self) -> str | None:
        """The log's (or journal's) trouble in one line; ``None`` when all records are logged."""
        with self._lock:
            parts = []
            if self._log_error and (self._entries or self._unsaved):
                parts.append(self._log_error)
            if self._entries:
                parts.append(f"{len(self._entries)} record(s) kept in journal {self.journal_path}")
            if self._unsaved:
                parts.append(f"{len(self._unsaved)} record(s) NOT durable (held in memory)")
            if self._journal_error:
                parts.append(self._journal_error)
            return "; ".join(parts) or None

    @property
    def failing(self) -> bool:
        """Whether control must stop for the log: records not durable, or the log refuses them.

        A log that only does not answer (locked, server gone: :func:`log_unavailable`) while
        the journal keeps every record is not failing: the records go in later.
        """
        with self._lock:
            if self._unsaved:
                return True
            return bool(self._log_error and self._entries and not self._log_unavailable)

    @property
    def pending(self) -> int:
        """Records waiting for the log (in the journal, or held in memory)."""
        with self._lock:
            return len(self._entries) + len(self._unsaved)

    @property
    def unsaved(self) -> int:
        """Records neither the log nor the journal took (not durable; retried)."""
        with self._lock:
            return len(self._unsaved)

    def close(self) -> Path | None:
        """Write what the log takes; the journal left behind, or ``None`` when nothing is left.

        Records that neither the log nor the journal takes are printed to stderr as JSON lines
        (``unsaved quality record: {...}``), the last place left. The log is not closed.
        """
        with self._lock:
            self._retry_locked()
            if self._unsaved:
                for e in self._unsaved:
                    print(f"unsaved quality record: {e.line()}", end="", file=sys.stderr)
                sys.stderr.flush()
                self._unsaved.clear()
            if self._entries or self._bad_lines:
                return self.journal_path
            if self.journal_path.exists():  # nothing left in it (blank lines, known records)
                try:
                    self._rewrite()
                except OSError:
                    return self.journal_path  # could not be removed: name it
            return None

    def __repr__(self) -> str:
        return f"RecordSink({self.journal_path}, pending={self.pending})"
