"""The quality log's embedded store: one SQLite file (WAL, ``synchronous=FULL``).

:class:`SqliteStore` is the default backend of :class:`controller.quality.log.QualityLog`: the
log validates and converts records, the store keeps rows. ``insert`` returns only after its
transaction is committed, so a killed process leaves no torn record and loses none it
acknowledged. Several processes may append and read at once (one writer at a time, readers
never block). Table layout: ``docs/quality_log.md``.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from controller.quality.schema import (
    APPLICATION_ID,
    SCHEMA_VERSION,
    QualityLogError,
    RecordRefusedError,
    Selection,
    column_names,
    columns_added_since,
    create_statements,
)
from core.checks import check_positive

__all__ = ["SqliteStore"]

#: Identities of records appended with a ``uid`` (journal replays append each only once).
#: Created on first use, so logs written before it need no migration.
_UIDS_TABLE = ("CREATE TABLE IF NOT EXISTS record_uids "
               "(uid TEXT PRIMARY KEY, record_id INTEGER NOT NULL)")
_UIDS_PER_QUERY = 500
"""Most uids one ``IN (...)`` query looks up (well below SQLite's 999 parameters)."""

#: Column renames of version 1 -> 2 (the CSV header's names).
_RENAMES_V2 = (("id", "record_id"), ("wall_time", "wall_time_utc"), ("extra", "extra_json"))


#: SQLite's result codes of a lock held by another connection (``SQLITE_BUSY``, ``_LOCKED``).
_BUSY_CODES = (5, 6)


def _write_error(what: str, exc: sqlite3.Error) -> OSError:
    """The ``OSError`` of a failed write: ``TimeoutError`` when another writer held the lock."""
    code = getattr(exc, "sqlite_errorcode", None)
    if isinstance(code, int) and (code & 0xFF) in _BUSY_CODES:
        return TimeoutError(f"{what}: {exc} (held by another connection)")
    return OSError(f"{what}: {exc}")


def _uri_path(p: Path) -> str:
    from urllib.parse import quote

    return quote(str(p.absolute()))


class SqliteStore:
    """Rows of the quality log in an SQLite file.

    Parameters
    ----------
    path : str or Path
        The log file. Opening an existing log continues it.
    create : bool, keyword-only
        Create the file when it does not exist, and bring an older layout to the current one.
        With ``False`` the file is opened read-only (SQLite ``mode=ro``: readers such as
        ``planer report`` never write to it), a missing file raises ``FileNotFoundError`` and
        an older layout is read as it is.
    timeout_s : float, keyword-only
        How long to wait for another process's write lock, seconds.

    Raises
    ------
    OSError
        The file cannot be opened or created (missing folder, a directory, no permission).
    QualityLogError
        The file is not a quality log, is corrupt, or was written by a newer version.

    Notes
    -----
    Not thread-safe by itself: :class:`~controller.quality.log.QualityLog` serialises calls.
    """

    def __init__(self, path: str | Path, *, create: bool = True, timeout_s: float = 10.0) -> None:
        self.path = Path(path)
        self.name = str(self.path)
        timeout_s = check_positive("timeout_s", timeout_s)
        self._conn: sqlite3.Connection | None = None
        p = self.path
        if p.is_dir():
            raise IsADirectoryError(f"quality log path is a directory: {p}")
        if not p.exists():
            if not create:
                raise FileNotFoundError(f"quality log not found: {p}")
            if not p.parent.is_dir():
                raise FileNotFoundError(f"folder of the quality log does not exist: {p.parent}")
        try:
            conn = sqlite3.connect(
                # create=False: only read (planer report, the web page): mode=ro, the file is
                # never written (an empty or foreign file stays what it is)
                f"file:{_uri_path(p)}?mode={'rwc' if create else 'ro'}", uri=True,
                timeout=timeout_s, isolation_level=None, check_same_thread=False,
            )
        except sqlite3.Error as exc:
            raise OSError(f"cannot open quality log {p}: {exc}") from None
        try:
            self._conn = conn
            self._open(timeout_s, create=create)
        except BaseException:
            self._conn = None
            conn.close()
            raise

    # -- opening ------------------------------------------------------------------------------

    def _open(self, timeout_s: float, *, create: bool) -> None:
        conn = self._connection()
        p = self.path
        try:
            conn.execute(f"PRAGMA busy_timeout = {int(timeout_s * 1000)}")
            app_id = conn.execute("PRAGMA application_id").fetchone()[0]
            tables = {r[0] for r in conn.execute(
                "SELECT name FROM sqlite_master WHERE type = 'table'")}
            if tables and (app_id != APPLICATION_ID or "records" not in tables):
                raise QualityLogError(f"{p} is an SQLite file but not a quality log")
            if not tables and not create:
                raise QualityLogError(f"{p} is empty, not a quality log")
            if create:
                mode = conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
                if str(mode).lower() != "wal":
                    raise OSError(f"cannot use write-ahead logging for {p} (journal mode {mode})")
                conn.execute("PRAGMA synchronous = FULL")
            if not tables:
                self._create_schema()
            rows = conn.execute("SELECT version FROM schema_version").fetchall()
        except sqlite3.DatabaseError as exc:
            msg = str(exc)
            if isinstance(exc, sqlite3.OperationalError) and "unable to open" in msg:
                raise OSError(f"cannot open quality log {p}: {msg}") from None
            raise QualityLogError(f"{p} is not a readable quality log: {msg}") from None
        if len(rows) != 1:
            raise QualityLogError(f"{p}: quality log has no valid schema version")
        version = rows[0][0]
        if not isinstance(version, int) or version > SCHEMA_VERSION or version < 1:
            raise QualityLogError(
                f"{p}: quality log schema version {version} is not supported "
                f"(this planer reads versions 1..{SCHEMA_VERSION}; update planer)")
        if version < SCHEMA_VERSION and create:
            version = self._migrate()
        self.schema_version = int(version)

    def _migrate(self) -> int:
        """Bring an older log to the current layout.

        v2: the CSV header's names; v3: ``machine_id``; v4: orientation, self-calibration and
        kinematic depth (records before it read ``None`` there); v5: ``flag_reason``; v6: the
        knife condition; v7: the planing defects and grades; v8: ``head`` (``'main'`` in the
        rows before it).
        """
        conn = self._connection()
        try:
            conn.execute("BEGIN IMMEDIATE")
            try:
                version = conn.execute("SELECT version FROM schema_version").fetchone()[0]
                if version == 1:  # another process may have migrated it while we waited
                    for old, new in _RENAMES_V2:
                        conn.execute(f"ALTER TABLE records RENAME COLUMN {old} TO {new}")
                    version = 2
                if version == 2:
                    conn.execute("ALTER TABLE records ADD COLUMN machine_id TEXT")
                    conn.execute("CREATE INDEX IF NOT EXISTS records_machine_time "
                                 "ON records (machine_id, wall_time_utc)")
                    version = 3
                # v4: orientation, self-calibration, depths; v5: flag_reason; v6: the knife
                # condition; v7: the planing defects and grades; v8: the head ('main')
                for name, sqlite_type, _ in columns_added_since(version):
                    conn.execute(f"ALTER TABLE records ADD COLUMN {name} {sqlite_type}")
                version = SCHEMA_VERSION
                conn.execute("UPDATE schema_version SET version = ?", (version,))
                conn.execute("COMMIT")
            except BaseException:
                if conn.in_transaction:
                    conn.execute("ROLLBACK")
                raise
        except sqlite3.Error as exc:
            raise OSError(f"cannot update quality log {self.path} to schema version "
                          f"{SCHEMA_VERSION}: {exc}") from None
        return int(version)

    def _create_schema(self) -> None:
        conn = self._connection()
        conn.execute("BEGIN IMMEDIATE")
        try:
            exists = conn.execute(
                "SELECT 1 FROM sqlite_master WHERE name = 'records'").fetchone()
            if not exists:  # another process may have created it while we waited
                for stmt in create_statements("sqlite"):
                    conn.execute(stmt)
                conn.execute("INSERT INTO schema_version (version) VALUES (?)",
                             (SCHEMA_VERSION,))
                conn.execute(f"PRAGMA application_id = {APPLICATION_ID}")
            conn.execute("COMMIT")
        except BaseException:
            conn.execute("ROLLBACK")
            raise

    def _connection(self) -> sqlite3.Connection:
        if self._conn is None:
            raise ValueError(f"quality log {self.path} is closed")
        return self._conn

    # -- writing ------------------------------------------------------------------------------

    def insert(self, row: Sequence[Any], *, uid: str | None) -> int:
        """Insert one row (field order, current layout); its id, or the stored one of ``uid``."""
        return self.insert_many([row], [uid])[0]

    def insert_many(self, rows: Sequence[Sequence[Any]],
                    uids: Sequence[str | None]) -> list[int]:
        """Insert rows in one transaction (one commit); their ids (stored ones for known uids).

        All or nothing: on any error none of them is stored.
        """
        if len(rows) != len(uids):
            raise ValueError(f"uids must be one per row: {len(uids)} for {len(rows)}")
        conn = self._connection()
        cols = column_names(self.schema_version)[1]
        sql = f"INSERT INTO records ({', '.join(cols)}) VALUES ({', '.join('?' * len(cols))})"
        try:
            conn.execute("BEGIN IMMEDIATE")
            try:
                ids = self._insert_rows(conn, sql, len(cols), rows, uids)
                conn.execute("COMMIT")
            except BaseException:
                if conn.in_transaction:
                    conn.execute("ROLLBACK")
                raise
        except OverflowError as exc:  # check_storable should have caught it
            raise RecordRefusedError("record", f"record refused by the log: {exc}") from None
        except sqlite3.Error as exc:
            raise _write_error(f"cannot append to quality log {self.path}", exc) from None
        return ids

    @staticmethod
    def _insert_rows(conn: sqlite3.Connection, sql: str, width: int,
                     rows: Sequence[Sequence[Any]], uids: Sequence[str | None]) -> list[int]:
        """Insert inside the open transaction: the new rows with one ``executemany``.

        A uid the log (or an earlier row of the batch) holds gives that record's id and adds
        no row. The new rows' ids are consecutive (the write lock is held; ``AUTOINCREMENT``);
        were they not, the batch is inserted row by row instead (:meth:`_insert_each`).
        """
        if any(u is not None for u in uids):
            conn.execute(_UIDS_TABLE)
        known: dict[str, int] = {}
        wanted = list(dict.fromkeys(u for u in uids if u is not None))
        for i in range(0, len(wanted), _UIDS_PER_QUERY):
            part = wanted[i:i + _UIDS_PER_QUERY]
            known.update(conn.execute(
                f"SELECT uid, record_id FROM record_uids WHERE uid IN "
                f"({', '.join('?' * len(part))})", part).fetchall())
        new: list[tuple[Any, ...]] = []
        where: list[int | str] = []  # per row: its index in ``new``, or a known uid
        first_of: dict[str, int] = {}  # uid -> index in ``new`` of its row in this batch
        for row, uid in zip(rows, uids, strict=True):
            if uid is not None and (uid in known or uid in first_of):
                where.append(uid)
                continue
            if uid is not None:
                first_of[uid] = len(new)
            where.append(len(new))
            new.append(tuple(row)[:width])
        if not new:
            return [int(known[u]) for u in where]  # type: ignore[index]
        conn.execute("SAVEPOINT batch")
        before = conn.execute("SELECT COALESCE(MAX(rowid), 0) FROM records").fetchone()[0]
        conn.executemany(sql, new)
        last = conn.execute("SELECT last_insert_rowid()").fetchone()[0]
        if last != before + len(new):  # ids not consecutive: one by one, as they come
            conn.execute("ROLLBACK TO batch")
            conn.execute("RELEASE batch")
            return SqliteStore._insert_each(conn, sql, width, rows, uids)
        conn.execute("RELEASE batch")
        new_uids = [(u, before + 1 + k) for u, k in first_of.items()]
        if new_uids:
            conn.executemany("INSERT INTO record_uids (uid, record_id) VALUES (?, ?)", new_uids)
        known.update(new_uids)  # a uid repeated in the batch: its first row's id
        return [int(before + 1 + w) if isinstance(w, int) else int(known[w]) for w in where]

    @staticmethod
    def _insert_each(conn: sqlite3.Connection, sql: str, width: int,
                     rows: Sequence[Sequence[Any]], uids: Sequence[str | None]) -> list[int]:
        """Insert inside the open transaction, row by row (a uid the log holds: its id)."""
        ids: list[int] = []
        for row, uid in zip(rows, uids, strict=True):
            found = None if uid is None else conn.execute(
                "SELECT record_id FROM record_uids WHERE uid = ?", (uid,)).fetchone()
            if found is not None:
                ids.append(int(found[0]))
                continue
            rid = int(conn.execute(sql, tuple(row)[:width]).lastrowid)
            if uid is not None:
                conn.execute("INSERT INTO record_uids (uid, record_id) VALUES (?, ?)",
                             (uid, rid))
            ids.append(rid)
        return ids

    def set_write_timeout(self, timeout_s: float) -> None:
        """Wait at most ``timeout_s`` for another connection's lock (``TimeoutError`` after)."""
        timeout_s = check_positive("timeout_s", timeout_s)
        self._connection().execute(f"PRAGMA busy_timeout = {int(timeout_s * 1000)}")

    def has_uid(self, uid: str) -> bool:
        """Whether a record appended with this ``uid`` is in the log."""
        conn = self._connection()
        try:
            exists = conn.execute(
                "SELECT 1 FROM sqlite_master WHERE name = 'record_uids'").fetchone()
            if not exists:
                return False
            return conn.execute("SELECT 1 FROM record_uids WHERE uid = ?",
                                (uid,)).fetchone() is not None
        except sqlite3.DatabaseError as exc:
            raise QualityLogError(f"cannot read quality log {self.path}: {exc}") from None

    def set_meta(self, key: str, text: str) -> None:
        """Store ``text`` under ``key`` (replacing)."""
        conn = self._connection()
        try:
            conn.execute("BEGIN IMMEDIATE")
            conn.execute("INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)", (key, text))
            conn.execute("COMMIT")
        except sqlite3.Error as exc:
            if conn.in_transaction:
                conn.execute("ROLLBACK")
            raise OSError(f"cannot write to quality log {self.path}: {exc}") from None

    # -- reading ------------------------------------------------------------------------------

    def _query(self, sql: str, params: Sequence[Any] = ()) -> list[tuple[Any, ...]]:
        conn = self._connection()
        try:
            return conn.execute(sql, tuple(params)).fetchall()
        except sqlite3.DatabaseError as exc:
            raise QualityLogError(f"cannot read quality log {self.path}: {exc}") from None

    def get_meta(self, key: str) -> str | None:
        """The text stored under ``key``, or ``None``."""
        rows = self._query("SELECT value FROM meta WHERE key = ?", (key,))
        return rows[0][0] if rows else None

    def select(self, selection: Selection) -> list[tuple[Any, ...]]:
        """Rows ``(id, *fields)`` in id order (a layout before ``machine_id`` reads NULL)."""
        rid, cols = column_names(self.schema_version)
        if selection.machine_id is not None and "machine_id" not in cols:
            return []  # a layout before machine ids: no record names a machine
        fitted = selection.fit(cols)  # a layout before heads: only head "main"
        if fitted is None:
            return []
        selection = fitted
        exprs = list(cols) + ["NULL"] * (len(column_names(SCHEMA_VERSION)[1]) - len(cols))
        where, params = selection.where(rid, "?")
        sql = (f"SELECT {rid}, {', '.join(exprs)} FROM records"
               + (" WHERE " + " AND ".join(where) if where else "") + f" ORDER BY {rid}")
        return self._query(sql, params)

    def last_id(self) -> int:
        """Id of the newest record (0 when empty)."""
        rid = column_names(self.schema_version)[0]
        return int(self._query(f"SELECT COALESCE(MAX({rid}), 0) FROM records")[0][0])

    def count(self) -> int:
        """Number of records."""
        return int(self._query("SELECT COUNT(*) FROM records")[0][0])

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._conn is None

    def close(self) -> None:
        """Close the file (idempotent)."""
        if self._conn is not None:
            self._conn.close()
            self._conn = None
