"""The quality log's fleet store: a PostgreSQL database shared by several machines (psycopg 3).

:class:`PostgresStore` keeps the same tables and columns as the SQLite file
(:func:`controller.quality.schema.create_statements`), with PostgreSQL's types (``DOUBLE
PRECISION``, ``BIGINT``, ``BOOLEAN``). Each insert is one transaction, committed before it
returns; the record's ``uid`` goes into ``record_uids`` (primary key) in the same transaction,
so a record replayed from the journal after a lost connection is stored once
(``ON CONFLICT DO NOTHING``), even when two writers race. A lost connection is re-opened by the
next call; until then calls raise ``OSError`` naming ``host:port/db``, and the
:class:`~controller.quality.journal.RecordSink` keeps the records on local disk.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from controller.quality.schema import (
    SCHEMA_VERSION,
    QualityLogError,
    RecordRefusedError,
    Selection,
    column_names,
    columns_added_since,
    create_statements,
)
from core.checks import check_positive

__all__ = ["RECONNECT_TIMEOUT_S", "PostgresStore", "describe_url"]

#: Time limit of a re-connection (after a lost connection) and of a send on a dead link, s.
RECONNECT_TIMEOUT_S = 2.0
#: A call with a write timeout set is cut off this long after the server's own
#: ``statement_timeout`` (a server that does not answer at all, e.g. stopped), s.
CLIENT_MARGIN_S = 2.0
#: Advisory lock key serialising schema creation by several first writers ("PLQL").
_SCHEMA_LOCK = 0x504C514C
#: Text fields PostgreSQL's TEXT cannot hold with a NUL character (SQLite can).
_NUL_CHECKED = ("error", "flag_reason")
#: Columns that are BOOLEAN in PostgreSQL (0/1 integers in SQLite).
_BOOLEANS = ("ok", "passed")
#: Layout versions read in PostgreSQL (3 to 7 are brought to the current one by a writer; a
#: reader reads them as they are).
_READABLE = (3, 4, 5, 6, 7, SCHEMA_VERSION)


def describe_url(url: str) -> str:
    """``postgresql://USER@HOST:PORT/DB`` without the password (for messages and ``path``)."""
    import psycopg
    from psycopg.conninfo import conninfo_to_dict

    try:
        info = conninfo_to_dict(url)
    except (ValueError, psycopg.Error):  # a malformed URL: show only its scheme
        return "postgresql://?"
    user = f"{info['user']}@" if info.get("user") else ""
    host = str(info.get("host") or "localhost")
    port = str(info.get("port") or 5432)
    return f"postgresql://{user}{host}:{port}/{info.get('dbname') or ''}"


def _cut(conn: Any) -> None:
    """Shut the connection's socket down: a call blocked on it fails at once."""
    import psycopg

    try:
        fd = conn.pgconn.socket
        with socket.fromfd(fd, socket.AF_INET, socket.SOCK_STREAM) as sock:
            sock.shutdown(socket.SHUT_RDWR)
    except (OSError, ValueError, AttributeError, psycopg.Error):  # closed: nothing to cut
        pass


def _one_line(exc: BaseException) -> str:
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    text = lines[0] if lines else type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."


class PostgresStore:
    """Rows of the quality log in a PostgreSQL database.

    Parameters
    ----------
    url : str
        ``postgresql://USER[:PASSWORD]@HOST:PORT/DB`` (libpq URL; ``?host=/socket/dir`` works).
    create : bool, keyword-only
        Create the tables when the database has none (default). With ``False`` a database
        without a quality log raises :class:`QualityLogError` (readers).
    connect_timeout_s : float, keyword-only
        Time limit of one connection attempt, seconds (libpq rounds up to whole seconds).
    retry_after_s : float, keyword-only
        After a failed connection attempt, calls within this time fail at once instead of
        trying again (the service's loop is not held up), seconds; 0 = always try.
    clock : callable, keyword-only
        Monotonic clock for ``retry_after_s`` (injected by tests).

    Raises
    ------
    OSError
        The database cannot be reached at start: one line naming ``host:port/db``.
    QualityLogError
        The database holds tables that are not a quality log, or a newer layout.
    """

    def __init__(self, url: str, *, create: bool = True, connect_timeout_s: float = 5.0,
                 retry_after_s: float = 5.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        import psycopg

        self._psycopg = psycopg
        self._url = url
        self.path = describe_url(url)
        self.name = self.path
        self._timeout_s = check_positive("connect_timeout_s", connect_timeout_s)
        self._retry_after_s = check_positive("retry_after_s", retry_after_s, allow_zero=True)
        self._clock = clock
        self._conn: Any = None
        self._closed = False
        self._failed_at: float | None = None
        self._last_error = ""
        self._opened = False
        self._write_timeout_s: float | None = None
        self._connect()
        self._opened = True
        try:
            self.schema_version = self._open_schema(create=create)
        except BaseException:
            self.close()
            raise

    # -- the connection -----------------------------------------------------------------------

    def _connect(self) -> Any:
        if self._closed:
            raise ValueError(f"quality log {self.name} is closed")
        if self._conn is not None and not self._conn.closed and not self._conn.broken:
            return self._conn
        self._drop()
        now = self._clock()
        if self._failed_at is not None and now - self._failed_at < self._retry_after_s:
            raise ConnectionError(f"quality log database {self.name} unreachable: "
                                  f"{self._last_error} (retrying)")
        # the first connection waits connect_timeout_s; a re-connection from the loop at most
        # RECONNECT_TIMEOUT_S, and a dead link under an open connection fails within it too
        limit_s = self._timeout_s if self._opened is False else min(self._timeout_s,
                                                                    RECONNECT_TIMEOUT_S)
        try:
            self._conn = self._psycopg.connect(
                self._url, autocommit=True, connect_timeout=max(2, round(limit_s)),
                application_name="planer quality log", keepalives=1, keepalives_idle=5,
                keepalives_interval=2, keepalives_count=2,
                tcp_user_timeout=int(1000 * max(limit_s, RECONNECT_TIMEOUT_S)),
                **({} if self._write_timeout_s is None else {
                    "options": f"-c statement_timeout={int(self._write_timeout_s * 1000)}"}))
        except self._psycopg.Error as exc:
            self._failed_at = now
            self._last_error = _one_line(exc)
            raise ConnectionError(f"cannot connect to quality log database {self.name}: "
                                  f"{self._last_error}") from None
        self._failed_at = None
        return self._conn

    def _drop(self) -> None:
        conn, self._conn = self._conn, None
        if conn is not None:
            try:
                conn.close()
            except (OSError, self._psycopg.Error):  # a broken connection may refuse to close
                pass

    def _run(self, work: Callable[[Any], Any], *, what: str) -> Any:
        """``work(connection)``; a database error becomes ``OSError`` / ``QualityLogError``."""
        conn = self._connect()
        pg = self._psycopg
        guard = None
        if self._write_timeout_s is not None:  # a server that never answers: cut the link
            guard = threading.Timer(self._write_timeout_s + CLIENT_MARGIN_S, _cut, (conn,))
            guard.daemon = True
            guard.start()
        try:
            return work(conn)
        except (pg.OperationalError, pg.InterfaceError) as exc:
            self._drop()  # re-opened by the next call
            raise ConnectionError(f"quality log database {self.name}: {what} failed: "
                                  f"{_one_line(exc)}") from None
        except pg.DataError as exc:
            raise RecordRefusedError("record", f"record refused by {self.name}: "
                                     f"{_one_line(exc)}") from None
        except pg.Error as exc:
            raise QualityLogError(f"quality log database {self.name}: {what} failed: "
                                  f"{_one_line(exc)}") from None
        finally:
            if guard is not None:
                guard.cancel()

    def set_write_timeout(self, timeout_s: float) -> None:
        """Bound every later call to ``timeout_s`` (``ConnectionError`` beyond).

        ``statement_timeout`` on the server, and on the client ``timeout_s`` +
        :data:`CLIENT_MARGIN_S`, after which the connection is cut (a server that does not
        answer at all, e.g. stopped).
        """
        self._write_timeout_s = check_positive("timeout_s", timeout_s)
        self._drop()  # the next call connects with the timeout

    # -- the schema ---------------------------------------------------------------------------

    def _open_schema(self, *, create: bool) -> int:
        def work(conn: Any) -> int:
            with conn.transaction():
                if create:  # two first writers: one creates, the other waits and finds them
                    conn.execute("SELECT pg_advisory_xact_lock(%s)", (_SCHEMA_LOCK,))
                tables = {r[0] for r in conn.execute(
                    "SELECT table_name FROM information_schema.tables "
                    "WHERE table_schema = current_schema()").fetchall()}
                if "records" not in tables or "schema_version" not in tables:
                    if tables & {"records", "schema_version", "meta", "record_uids"}:
                        raise QualityLogError(
                            f"{self.name} holds tables that are not a planer quality log")
                    if not create:
                        raise QualityLogError(f"{self.name} holds no quality log")
                    for stmt in create_statements("postgresql"):
                        conn.execute(stmt)
                    conn.execute("INSERT INTO schema_version (version) VALUES (%s)",
                                 (SCHEMA_VERSION,))
                rows = conn.execute("SELECT version FROM schema_version").fetchall()
                if len(rows) != 1 or rows[0][0] not in _READABLE:
                    found = rows[0][0] if len(rows) == 1 else None
                    raise QualityLogError(
                        f"{self.name}: quality log schema version {found} is not supported "
                        f"(this planer reads versions {min(_READABLE)}..{SCHEMA_VERSION} in "
                        "PostgreSQL)")
                version = int(rows[0][0])
                if version < SCHEMA_VERSION and create:
                    # v4: orientation, self-calibration, depths; v5: flag_reason; v6: the
                    # knife condition; v7: the planing defects and grades; v8: the head
                    # (NOT NULL DEFAULT 'main': the rows before it are the single head's)
                    for name, _, pg_type in columns_added_since(version):
                        conn.execute(f"ALTER TABLE records ADD COLUMN IF NOT EXISTS {name} "
                                     f"{pg_type}")
                    conn.execute("UPDATE schema_version SET version = %s", (SCHEMA_VERSION,))
                    version = SCHEMA_VERSION
            return version

        return int(self._run(work, what="opening"))

    # -- writing ------------------------------------------------------------------------------

    def _values(self, row: Sequence[Any]) -> tuple:
        """``row`` as PostgreSQL takes it (booleans; a NUL in text refused naming the field)."""
        cols = column_names(self.schema_version)[1]  # a reader's v3: what it has
        values = tuple(bool(v) if name in _BOOLEANS and v is not None else v
                       for name, v in zip(cols, tuple(row)[:len(cols)], strict=True))
        for i, name in enumerate(cols):
            if name in _NUL_CHECKED and isinstance(values[i], str) and "\x00" in values[i]:
                raise RecordRefusedError(
                    name, f"{name} holds a NUL character, which PostgreSQL text cannot store")
        return values

    def _insert_sql(self) -> str:
        rid_col, cols = column_names(self.schema_version)
        return (f"INSERT INTO records ({', '.join(cols)}) VALUES "
                f"({', '.join(['%s'] * len(cols))}) RETURNING {rid_col}")

    def insert(self, row: Sequence[Any], *, uid: str | None) -> int:
        """Commit one row (field order); its id, or the stored one of a known ``uid``."""
        values, sql = self._values(row), self._insert_sql()

        def work(conn: Any) -> int:
            if uid is not None:
                known = conn.execute("SELECT record_id FROM record_uids WHERE uid = %s",
                                     (uid,)).fetchone()
                if known is not None:
                    return int(known[0])
            try:
                with conn.transaction():
                    rid = int(conn.execute(sql, values).fetchone()[0])
                    if uid is not None:
                        took = conn.execute(
                            "INSERT INTO record_uids (uid, record_id) VALUES (%s, %s) "
                            "ON CONFLICT (uid) DO NOTHING RETURNING record_id",
                            (uid, rid)).fetchone()
                        if took is None:  # a racing writer stored it first: roll back ours
                            raise _AlreadyStored
            except _AlreadyStored:
                return int(conn.execute("SELECT record_id FROM record_uids WHERE uid = %s",
                                        (uid,)).fetchone()[0])
            return rid

        return int(self._run(work, what="append"))

    def insert_many(self, rows: Sequence[Sequence[Any]],
                    uids: Sequence[str | None]) -> list[int]:
        """Insert rows in one transaction (one commit); their ids (stored ones for known uids).

        All or nothing: on any error none of them is stored. A racing writer that stores one of
        the uids first rolls the batch back; the rows then go one by one (:meth:`insert`).
        """
        if len(rows) != len(uids):
            raise ValueError(f"uids must match rows: {len(uids)} uid(s) for {len(rows)} row(s)")
        prepared, sql = [self._values(row) for row in rows], self._insert_sql()

        def work(conn: Any) -> list[int]:
            ids: list[int] = []
            with conn.transaction():
                for values, uid in zip(prepared, uids, strict=True):
                    if uid is not None:
                        known = conn.execute("SELECT record_id FROM record_uids WHERE uid = %s",
                                             (uid,)).fetchone()
                        if known is not None:
                            ids.append(int(known[0]))
                            continue
                    rid = int(conn.execute(sql, values).fetchone()[0])
                    if uid is not None and conn.execute(
                            "INSERT INTO record_uids (uid, record_id) VALUES (%s, %s) "
                            "ON CONFLICT (uid) DO NOTHING RETURNING record_id",
                            (uid, rid)).fetchone() is None:
                        raise _AlreadyStored
                    ids.append(rid)
            return ids

        if not prepared:
            return []
        try:
            return list(self._run(work, what="append"))
        except _AlreadyStored:  # a racing writer: one by one, each finds its stored id
            return [self.insert(row, uid=uid) for row, uid in zip(rows, uids, strict=True)]

    def has_uid(self, uid: str) -> bool:
        """Whether a record appended with this ``uid`` is in the log."""
        return bool(self._run(lambda c: c.execute(
            "SELECT 1 FROM record_uids WHERE uid = %s", (uid,)).fetchone() is not None,
            what="reading"))

    def set_meta(self, key: str, text: str) -> None:
        """Store ``text`` under ``key`` (replacing)."""
        self._run(lambda c: c.execute(
            "INSERT INTO meta (key, value) VALUES (%s, %s) "
            "ON CONFLICT (key) DO UPDATE SET value = EXCLUDED.value", (key, text)),
            what="writing")

    # -- reading ------------------------------------------------------------------------------

    def _query(self, sql: str, params: Sequence[Any] = ()) -> list[tuple[Any, ...]]:
        return list(self._run(lambda c: c.execute(sql, tuple(params)).fetchall(),
                              what="reading"))

    def get_meta(self, key: str) -> str | None:
        """The text stored under ``key``, or ``None``."""
        rows = self._query("SELECT value FROM meta WHERE key = %s", (key,))
        return rows[0][0] if rows else None

    def select(self, selection: Selection) -> list[tuple[Any, ...]]:
        """Rows ``(id, *fields)`` in id order (columns a version 3 log lacks read NULL)."""
        rid, cols = column_names(self.schema_version)
        fitted = selection.fit(cols)  # a layout before heads: only head "main"
        if fitted is None:
            return []
        selection = fitted
        exprs = list(cols) + ["NULL"] * (len(column_names(SCHEMA_VERSION)[1]) - len(cols))
        where, params = selection.where(rid, "%s")
        sql = (f"SELECT {rid}, {', '.join(exprs)} FROM records"
               + (" WHERE " + " AND ".join(where) if where else "") + f" ORDER BY {rid}")
        return self._query(sql, params)

    def last_id(self) -> int:
        """Id of the newest record (0 when empty)."""
        return int(self._query("SELECT COALESCE(MAX(record_id), 0) FROM records")[0][0])

    def count(self) -> int:
        """Number of records."""
        return int(self._query("SELECT COUNT(*) FROM records")[0][0])

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    def close(self) -> None:
        """Close the connection (idempotent)."""
        self._closed = True
        self._drop()


class _AlreadyStored(Exception):
    """Raised inside the insert transaction to roll it back (the uid was stored meanwhile)."""
