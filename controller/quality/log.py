"""The quality log: one record per measurement, appended crash-safely to an SQLite file.

Quality staff read this log (``planer report``, CSV export); the service appends to it. The
store is an embedded SQLite database in WAL mode with ``synchronous=FULL``: ``append`` returns
only after its transaction is committed, so a killed process leaves no torn record and loses
none it acknowledged. Several processes may append and read at once (one writer at a time,
readers never block). Field meanings and units: ``docs/quality_log.md``.
"""

from __future__ import annotations

import csv
import json
import math
import re
import socket
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol

from controller.quality.schema import (
    _FIELD_NAMES,
    _NAMES,
    _TUPLES,
    CALIBRATION_FIELDS,
    CALIBRATION_STATES,
    DEFAULT_HEAD,
    MACHINE_ID_MAX,
    SCHEMA_VERSION,
    SQLITE_INT_MAX,
    QualityClass,
    QualityLogError,
    QualityRecord,
    RecordRefusedError,
    Selection,
    _check_machine_id,
    _from_row,
    _json_default,
    _to_row,
    check_head,
    check_storable,
    column_names,
    create_statements,
    judge,
    quality_class_from_section,
    record_from_dict,
    record_json,
    record_to_dict,
    record_to_json,
    storable,
    utc_iso,
    vision_fields,
)
from core.checks import check_int
from core.fileio import atomic_writer

__all__ = [
    "DEFAULT_HEAD",
    "SCHEMA_VERSION",
    "CALIBRATION_STATES",
    "CALIBRATION_FIELDS",
    "vision_fields",
    "CSV_COLUMNS",
    "QualityLogError",
    "RecordRefusedError",
    "SQLITE_INT_MAX",
    "check_storable",
    "storable",
    "QualityRecord",
    "QualityClass",
    "QualityLog",
    "csv_float",
    "judge",
    "quality_class_from_section",
    "record_from_dict",
    "record_to_dict",
    "record_json",
    "record_to_json",
    "utc_iso",
    "MACHINE_ID_MAX",
    "QualityStore",
    "Selection",
    "column_names",
    "create_statements",
    "database_url",
    "default_machine_id",
    "is_database_url",
    "log_target",
    "open_quality_log",
    "quality_class_key",
]



class QualityStore(Protocol):
    """What a backend of :class:`QualityLog` does: keep rows (the log validates and converts).

    Rows are tuples in record-field order (``_to_row``); ``select`` returns ``(id, *fields)``.
    Methods raise ``OSError`` when the database cannot be reached or written,
    :class:`QualityLogError` when what it holds is unreadable, ``ValueError`` when closed.
    """

    path: Any
    name: str
    schema_version: int

    def insert(self, row: Sequence[Any], *, uid: str | None) -> int:
        """Commit one row; its id (the stored one when ``uid`` is known)."""

    def has_uid(self, uid: str) -> bool:
        """Whether a row appended with ``uid`` is stored."""

    def set_meta(self, key: str, text: str) -> None:
        """Store ``text`` under ``key``."""

    def get_meta(self, key: str) -> str | None:
        """The text under ``key`` or ``None``."""

    def select(self, selection: Selection) -> list[tuple[Any, ...]]:
        """Rows ``(id, *fields)`` in id order."""

    def last_id(self) -> int:
        """Newest id (0 when empty)."""

    def count(self) -> int:
        """Number of rows."""

    def close(self) -> None:
        """Release the file or connection (idempotent)."""

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""


_URL = re.compile(r"^(postgres(?:ql)?):/+", re.IGNORECASE)


def is_database_url(target: str | Path) -> bool:
    """Whether ``target`` names a PostgreSQL database (``postgresql://USER@HOST:PORT/DB``).

    A URL that went through ``pathlib.Path`` (``postgresql:/USER@HOST...``, one slash) counts.
    """
    return isinstance(target, (str, Path)) and _URL.match(str(target)) is not None


def database_url(target: str | Path) -> str:
    """The URL of a database target, with ``//`` restored after ``pathlib.Path`` folded it."""
    return _URL.sub(lambda m: m.group(1).lower() + "://", str(target), count=1)


def default_machine_id() -> str:
    """The machine id when none is configured: the host name (``"planer-1"`` without one)."""
    name = socket.gethostname().strip()
    return name if name and name.isprintable() and len(name) <= MACHINE_ID_MAX else "planer-1"


class QualityLog:
    """An append-only quality log: an SQLite file (default) or a PostgreSQL database.

    Parameters
    ----------
    target : str or Path
        The log file (SQLite; opening an existing log continues it), or a PostgreSQL URL
        ``postgresql://USER[:PASSWORD]@HOST:PORT/DB`` (the tables are created on first use;
        several machines and processes may write into one database).
    create : bool, keyword-only
        Create the log when it does not exist (default). With ``False`` a missing log raises
        ``FileNotFoundError`` / :class:`QualityLogError` (readers such as ``planer report``).
    timeout_s : float, keyword-only
        SQLite: how long to wait for another process's write lock. PostgreSQL: the connect
        time-out. Seconds.
    machine_id : str, keyword-only, optional
        Stamped on every appended record that names no machine (``[machine] id`` of
        machine.toml); default :func:`default_machine_id`.

    Raises
    ------
    OSError
        The file cannot be opened or created, or the database cannot be reached (one line
        naming ``host:port/db``).
    QualityLogError
        Not a quality log, corrupt, or written by a newer version.

    Notes
    -----
    One instance may be shared by threads (calls are serialised by a lock); separate
    processes open their own instances. Backends: :mod:`controller.quality.store_sqlite`,
    :mod:`controller.quality.store_postgres`.
    """

    def __init__(self, target: str | Path, *, create: bool = True, timeout_s: float = 10.0,
                 machine_id: str | None = None) -> None:
        if not isinstance(target, (str, Path)) or str(target) == "":
            raise ValueError(f"quality log must be a file path or a postgresql:// URL, got "
                             f"{target!r:.80}")
        mid = _check_machine_id("machine_id", machine_id)
        self.machine_id = default_machine_id() if mid is None else mid
        self._lock = threading.RLock()
        self._store: QualityStore
        if is_database_url(target):
            from controller.quality.store_postgres import PostgresStore

            self._store = PostgresStore(database_url(target), create=create,
                                        connect_timeout_s=timeout_s)
        else:
            from controller.quality.store_sqlite import SqliteStore

            self._store = SqliteStore(target, create=create, timeout_s=timeout_s)

    @property
    def path(self) -> Any:
        """The SQLite file (``Path``) or the database URL without password (``str``)."""
        return self._store.path

    @property
    def schema_version(self) -> int:
        """Layout version of the log as opened (older ones are read as they are)."""
        return self._store.schema_version

    def _call(self, method: str, *args: Any, **kw: Any) -> Any:
        with self._lock:
            if self._store.closed:
                raise ValueError(f"quality log {self._store.name} is closed")
            return getattr(self._store, method)(*args, **kw)

    # -- writing ------------------------------------------------------------------------------

    def append(self, record: QualityRecord, *, uid: str | None = None,
               extra_json: str | None = None) -> int:
        """Append one record; returns its id once it is committed.

        Parameters
        ----------
        record : QualityRecord
            The measurement; one naming no machine gets this log's :attr:`machine_id`.
        uid : str, keyword-only, optional
            A unique identity of the record (e.g. a UUID the journal gave it). A record whose
            ``uid`` the log already holds is not appended again: the id of the stored one is
            returned (exactly once when a journal is replayed after a crash).
        extra_json : str, keyword-only, optional
            ``record.extra`` as :func:`check_storable` (or :func:`storable`) returned it for
            this record: stored as it is, not encoded again (the journal's writer encodes a
            record once).

        Returns
        -------
        int
            The record's id (increasing in append order for one writer, never reused).

        Raises
        ------
        RecordRefusedError
            A value the schema cannot store (the error names the field; nothing written).
        ValueError
            ``record`` is not a record, or the log is closed.
        OSError
            The database cannot be written (disk full, locked beyond ``timeout_s``, I/O
            error, connection lost).
        """
        return int(self._call("insert", self._row(record, uid, extra_json), uid=uid))

    def _row(self, record: QualityRecord, uid: str | None, extra_json: str | None) -> tuple:
        """The store's row of ``record`` (checked: type, ``uid``, storable values)."""
        if not isinstance(record, QualityRecord):
            raise ValueError(f"record must be a QualityRecord, got {type(record).__name__}")
        if uid is not None and (not isinstance(uid, str) or not uid or not uid.isprintable()):
            raise ValueError(f"uid must be a non-empty printable string, got {uid!r}")
        if extra_json is not None and not isinstance(extra_json, str):
            raise ValueError(f"extra_json must be text, got {type(extra_json).__name__}")
        text = check_storable(record, extra_json=extra_json)
        return _to_row(record, extra_json=text, machine_id=self.machine_id)

    def append_many(self, records: Sequence[QualityRecord], *,
                    uids: Sequence[str | None] | None = None,
                    extra_json: Sequence[str | None] | None = None) -> list[int]:
        """Append records in one transaction (one commit, all or nothing); their ids.

        As :meth:`append` for each record (``uids`` and ``extra_json`` one per record, or
        ``None``); a record the schema refuses raises :class:`RecordRefusedError` before
        anything is written. A backend without batches appends them one after the other.
        """
        uids = [None] * len(records) if uids is None else list(uids)
        if len(uids) != len(records):
            raise ValueError(f"uids must be one per record: {len(uids)} for {len(records)}")
        texts = [None] * len(records) if extra_json is None else list(extra_json)
        if len(texts) != len(records):
            raise ValueError(f"extra_json must be one per record: {len(texts)} for "
                             f"{len(records)}")
        rows = [self._row(record, uid, text)
                for record, uid, text in zip(records, uids, texts, strict=True)]
        if not rows:
            return []
        if hasattr(self._store, "insert_many"):
            return [int(i) for i in self._call("insert_many", rows, uids)]
        return [int(self._call("insert", row, uid=uid))
                for row, uid in zip(rows, uids, strict=True)]

    def set_write_timeout(self, timeout_s: float) -> None:
        """Bound each later write to about ``timeout_s``.

        SQLite waits at most that for another writer's lock; PostgreSQL gets it as
        ``statement_timeout``, and a little later the client cuts the connection (a server that
        does not answer at all). Beyond it the write raises ``TimeoutError`` /
        ``ConnectionError`` (both ``OSError``).
        """
        setter = getattr(self._store, "set_write_timeout", None)
        if setter is not None:
            self._call("set_write_timeout", timeout_s)

    def has_uid(self, uid: str) -> bool:
        """Whether a record appended with this ``uid`` is in the log."""
        return bool(self._call("has_uid", uid))

    def set_meta(self, key: str, value: Any) -> None:
        """Store a JSON-serialisable value under ``key`` (e.g. ``"quality_class"``)."""
        if not isinstance(key, str) or not key:
            raise ValueError(f"key must be a non-empty string, got {key!r}")
        try:
            text = json.dumps(value, default=_json_default)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"value of meta key {key!r} is not JSON serialisable: {exc}") from None
        self._call("set_meta", key, text)

    def set_quality_class(self, quality_class: QualityClass, *,
                          head: str = DEFAULT_HEAD) -> None:
        """Store the quality class the records are judged against (read by ``planer report``).

        ``head``: the cutterhead whose records it judges (a moulder's heads each have their
        own; meta key ``quality_class`` for ``"main"``, ``quality_class:<head>`` for another).
        """
        if not isinstance(quality_class, QualityClass):
            raise ValueError("quality_class must be a QualityClass")
        self.set_meta(quality_class_key(head), quality_class.to_dict())

    # -- reading ------------------------------------------------------------------------------

    def get_meta(self, key: str, default: Any = None) -> Any:
        """The value stored under ``key``, or ``default``."""
        text = self._call("get_meta", key)
        if text is None:
            return default
        try:
            return json.loads(text)
        except ValueError as exc:
            raise QualityLogError(
                f"meta key {key!r} of {self._store.name} is unreadable: {exc}") from None

    def quality_class(self, head: str = DEFAULT_HEAD) -> QualityClass | None:
        """The stored quality class of ``head``'s records, or ``None`` when none was stored."""
        data = self.get_meta(quality_class_key(head))
        if data is None:
            return None
        try:
            return QualityClass.from_dict(data)
        except (TypeError, ValueError) as exc:
            raise QualityLogError(
                f"stored quality class of {self._store.name} is invalid: {exc}") from None

    def entries(
        self,
        *,
        board_id: int | None = None,
        since_seq: int | None = None,
        after_id: int | None = None,
        machine_id: str | None = None,
        head: str | None = None,
    ) -> list[tuple[int, QualityRecord]]:
        """``(id, record)`` pairs in id order; filters as :meth:`records`."""
        sel = Selection(
            board_id=None if board_id is None else check_int("board_id", board_id),
            since_seq=None if since_seq is None else check_int("since_seq", since_seq),
            after_id=None if after_id is None else check_int("after_id", after_id),
            machine_id=_check_machine_id("machine_id", machine_id),
            head=None if head is None else check_head("head", head),
        )
        return [(int(r[0]), _from_row(r)) for r in self._call("select", sel)]

    def records(
        self,
        board_id: int | None = None,
        since_seq: int | None = None,
        *,
        after_id: int | None = None,
        machine_id: str | None = None,
        head: str | None = None,
    ) -> list[QualityRecord]:
        """The records in id order.

        Parameters
        ----------
        board_id : int, optional
            Only this board's records.
        since_seq : int, optional
            Only records with ``seq >= since_seq``.
        after_id : int, keyword-only, optional
            Only records appended after the one with this id (for following a growing log).
        machine_id : str, keyword-only, optional
            Only this machine's records (a log shared by several machines).
        head : str, keyword-only, optional
            Only this cutterhead's records (a moulder's head; ``"main"`` also reads the
            records written before schema version 8).
        """
        return [r for _, r in self.entries(board_id=board_id, since_seq=since_seq,
                                           after_id=after_id, machine_id=machine_id,
                                           head=head)]

    @property
    def last_id(self) -> int:
        """Id of the newest record (0 when empty)."""
        return int(self._call("last_id"))

    def __len__(self) -> int:
        return int(self._call("count"))

    def export_csv(self, path: str | Path, *, machine_id: str | None = None,
                   head: str | None = None) -> int:
        """Write the records to a CSV file (atomically: a reader never sees a partial file).

        One row per record, columns :data:`CSV_COLUMNS` (units in the names); numbers without
        binary rounding noise (:func:`csv_float`: ``0.7``, not ``0.7000000000000001``); lists as
        semicolon-separated numbers, booleans as 1/0, missing values empty, ``extra`` as JSON
        without the bulky ``profile`` entry. The same records give the same file from either
        backend. ``machine_id``: only that machine's records; ``head``: only that head's.

        Returns
        -------
        int
            Number of rows written.
        """
        out = Path(path)
        if out.is_dir():
            raise IsADirectoryError(f"CSV path is a directory: {out}")
        if not out.parent.is_dir():
            raise FileNotFoundError(f"folder of the CSV file does not exist: {out.parent}")
        entries = self.entries(machine_id=machine_id, head=head)
        with atomic_writer(out, newline="") as fh:
            w = csv.writer(fh)
            w.writerow(CSV_COLUMNS)
            for rid, rec in entries:
                w.writerow(csv_row(rid, rec))
        return len(entries)

    # -- lifetime -----------------------------------------------------------------------------

    def close(self) -> None:
        """Close the file or connection (idempotent)."""
        with self._lock:
            self._store.close()

    def __enter__(self) -> QualityLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._store.closed else "open"
        return f"QualityLog({self._store.name!r}, {state})"


def quality_class_key(head: str = DEFAULT_HEAD) -> str:
    """The meta key of a head's quality class: ``quality_class`` or ``quality_class:<head>``."""
    name = check_head("head", head)
    return "quality_class" if name == DEFAULT_HEAD else f"quality_class:{name}"


def open_quality_log(target: str | Path, *, create: bool = True,
                     machine_id: str | None = None, timeout_s: float = 10.0) -> QualityLog:
    """Open the quality log a ``--log`` option or ``[log] path`` names: file or URL.

    The one place commands turn ``--log`` into a log (see :class:`QualityLog` for the
    parameters); ``postgresql://USER@HOST:PORT/DB`` (also after ``pathlib.Path`` folded its
    ``//``) opens PostgreSQL, anything else an SQLite file.
    """
    return QualityLog(target, create=create, machine_id=machine_id, timeout_s=timeout_s)


def log_target(text: str | Path, *, check_file: Callable[[Any], Any] | None = None
               ) -> str | Path:
    """A ``--log`` value as the commands keep it: the URL as text, a file as ``Path``.

    ``check_file`` (e.g. ``planer.cli.output_file``) is called with a file path only; a
    database URL is checked when the log is opened.
    """
    if is_database_url(text):
        return database_url(text)
    if check_file is not None:
        check_file(text)
    return Path(text)


# --------------------------------------------------------------------------------------------
# CSV layout

#: CSV header = the table's column names (schema version 4): the record id, then the
#: record's fields (``wall_time`` as ``wall_time_utc``, ``extra`` as ``extra_json``).
CSV_COLUMNS: tuple[str, ...] = (_NAMES[SCHEMA_VERSION][0],) + _NAMES[SCHEMA_VERSION][1]


#: Significant digits tried when writing a float to the CSV (see :func:`csv_float`).
CSV_SIGNIFICANT_DIGITS = 15
#: A shorter form is used only when it lies within this many units in the last place.
CSV_NOISE_ULPS = 4


def csv_float(value: float) -> str:
    """A float as CSV text without binary rounding noise (``0.7000000000000001`` -> ``0.7``).

    The value rounded to :data:`CSV_SIGNIFICANT_DIGITS` significant digits is written when it
    lies within :data:`CSV_NOISE_ULPS` units in the last place of the logged value (the noise
    sums of binary fractions leave, e.g. ``0.1 * 7``); any other value is written exactly
    (shortest round-trip form). So every number reads back as the logged double, or within a
    few units in its last place when that was noise. NaN is written ``nan``.
    """
    v = float(value)
    exact = repr(v)
    if not math.isfinite(v):
        return exact
    short = f"{v:.{CSV_SIGNIFICANT_DIGITS}g}"
    if len(short) < len(exact) and abs(float(short) - v) <= CSV_NOISE_ULPS * math.ulp(v):
        return repr(float(short))
    return exact


def _fmt(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "1" if v else "0"
    if isinstance(v, float):
        return csv_float(v)
    return str(v)


def csv_row(record_id: int, record: QualityRecord) -> list[str]:
    """One CSV row (strings) of a record, in the order of :data:`CSV_COLUMNS`."""
    row = [str(record_id)]
    for name in _FIELD_NAMES:
        v = getattr(record, name)
        if name in _TUPLES:
            row.append(";".join(csv_float(x) for x in v))
        elif name in ("defects", "board_defect_counts"):  # JSON text (schema version 7)
            row.append("" if v is None else json.dumps(list(v) if name == "defects" else v))
        elif name == "extra":
            slim = {k: val for k, val in v.items() if k != "profile"}
            row.append(json.dumps(slim, default=_json_default) if slim else "")
        else:
            row.append(_fmt(v))
    return row
