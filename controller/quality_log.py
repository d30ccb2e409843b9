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
import sqlite3
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from config.loading import Section
from core.checks import check_finite, check_int, check_positive
from core.errors import PlanerError
from core.fileio import atomic_writer

__all__ = [
    "SCHEMA_VERSION",
    "CSV_COLUMNS",
    "QualityLogError",
    "QualityRecord",
    "QualityClass",
    "QualityLog",
    "csv_float",
    "judge",
    "quality_class_from_section",
    "record_to_json",
    "utc_iso",
]

#: Version of the table layout this code writes; logs with a higher version are refused.
SCHEMA_VERSION = 1
#: SQLite ``application_id`` marking a file as a planer quality log ("PLQL").
APPLICATION_ID = 0x504C514C


class QualityLogError(PlanerError, ValueError):
    """The file is not a readable quality log (corrupt, foreign or from a newer version)."""


# --------------------------------------------------------------------------------------------
# time stamps


def utc_iso(epoch_s: float) -> str:
    """ISO-8601 UTC time stamp of a POSIX time, e.g. ``2026-05-09T07:35:25.123456+00:00``.

    Parameters
    ----------
    epoch_s : float
        Seconds since 1970-01-01 UTC (``time.time()`` of the injected wall clock).
    """
    v = check_finite("epoch_s", epoch_s)
    return datetime.fromtimestamp(v, tz=timezone.utc).isoformat(timespec="microseconds")


def _check_wall_time(value: str) -> str:
    if not isinstance(value, str):
        raise ValueError(f"wall_time must be an ISO-8601 UTC string, got {value!r}")
    text = value[:-1] + "+00:00" if value.endswith("Z") else value
    try:
        stamp = datetime.fromisoformat(text)
    except ValueError:
        raise ValueError(f"wall_time is not an ISO-8601 time stamp: {value!r}") from None
    if stamp.utcoffset() is None or stamp.utcoffset().total_seconds() != 0:
        raise ValueError(f"wall_time must be in UTC (offset +00:00 or Z), got {value!r}")
    return value


# --------------------------------------------------------------------------------------------
# the record


def _opt_float(name: str, value: Any) -> float | None:
    """``None`` or a finite float; NaN means "not measured" and becomes ``None``."""
    if value is None:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number or None, got {value!r}") from None
    if math.isnan(v):
        return None
    return check_finite(name, v)


def _float_tuple(name: str, values: Any) -> tuple[float, ...]:
    """A tuple of floats; NaN elements are kept (a knife whose mark was not found)."""
    if values is None:
        return ()
    if isinstance(values, (str, bytes)) or not hasattr(values, "__iter__"):
        raise ValueError(f"{name} must be a sequence of numbers, got {values!r}")
    out = []
    for i, x in enumerate(values):
        try:
            v = float(x)
        except (TypeError, ValueError):
            raise ValueError(f"{name}[{i}] must be a number, got {x!r}") from None
        if math.isinf(v):
            raise ValueError(f"{name}[{i}] must be finite or NaN, got {x!r}")
        out.append(v)
    return tuple(out)


def _opt_bool(name: str, value: Any) -> bool | None:
    """``None`` or a bool; numpy booleans are accepted, numbers and strings are not."""
    if value is None or isinstance(value, bool):
        return value
    if type(value).__name__ in ("bool_", "bool") and hasattr(value, "item"):
        return bool(value)
    raise ValueError(f"{name} must be true, false or None, got {value!r}")


@dataclass(frozen=True, kw_only=True)
class QualityRecord:
    """One measurement as the quality log stores it (all keyword arguments).

    Scalar metrics are ``None`` when not measured; NaN given for one is stored as ``None``.
    A failed measurement (``ok=False``) carries an ``error`` and no pitch, widths, uniformity,
    depth or pass/fail; it may carry the registration's ``shift_px`` and ``confidence``.
    Sequences are stored as tuples of floats.

    Attributes
    ----------
    t_s : float
        Machine time of the measurement (trigger A), seconds.
    wall_time : str
        Wall-clock time, ISO-8601 in UTC (see :func:`utc_iso`).
    seq : int
        Sequence number of the image pair, >= 0.
    board_id : int
        Board under the camera (0 when none), >= 0.
    board_position_mm : float
        Position of the imaged patch (image A's centre) from the board's leading end, mm.
    ok : bool
        Whether the measurement succeeded.
    error : str or None
        Why it failed (e.g. ``"registration failed: confidence 0.21"``); ``None`` when ok.
        The text before the first colon is the reason the report counts.
    pitch_mm : float or None
        Measured mark pitch (feed per knife), mm.
    mark_widths_mm : tuple of float, shape (Z,)
        Measured mark width per knife, mm (index = knife number; NaN = not found).
    uniformity_cv : float or None
        Coefficient of variation of the mark widths (std / mean), dimensionless.
    depth_um : float or None
        Mark depth (waviness), micrometres.
    shift_px : float or None
        Registration shift of image B against A, pixels.
    confidence : float or None
        Registration confidence, 0..1.
    feed_setpoint_mm_s : float or None
        Feed-rate setpoint in force at the measurement, mm/s.
    piezo_offsets_um : tuple of float, shape (Z,)
        Piezo offset setpoint per knife in force at the measurement, micrometres
        (> 0 lifts the cutterhead while that knife cuts).
    target_pitch_mm : float or None
        Target pitch of the quality class, mm.
    passed : bool or None
        Pass/fail against the quality class (:func:`judge`); ``None`` when not judged.
    true_pitch_mm, true_uniformity_cv : float or None
        Simulator only: the true pitch (mm) and uniformity (CV) of the imaged patch.
    extra : dict
        Free JSON-serialisable data, e.g. ``extra["profile"] = {"x_mm": [...],
        "height_um": [...]}``.
    """

    t_s: float
    wall_time: str
    seq: int
    board_id: int
    board_position_mm: float
    ok: bool
    error: str | None = None
    pitch_mm: float | None = None
    mark_widths_mm: tuple[float, ...] = ()
    uniformity_cv: float | None = None
    depth_um: float | None = None
    shift_px: float | None = None
    confidence: float | None = None
    feed_setpoint_mm_s: float | None = None
    piezo_offsets_um: tuple[float, ...] = ()
    target_pitch_mm: float | None = None
    passed: bool | None = None
    true_pitch_mm: float | None = None
    true_uniformity_cv: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        def put(name: str, value: Any) -> None:
            object.__setattr__(self, name, value)

        put("t_s", check_finite("t_s", self.t_s))
        put("wall_time", _check_wall_time(self.wall_time))
        put("seq", check_int("seq", self.seq, lo=0))
        put("board_id", check_int("board_id", self.board_id, lo=0))
        put("board_position_mm", check_finite("board_position_mm", self.board_position_mm))
        ok = _opt_bool("ok", self.ok)
        if ok is None:
            raise ValueError("ok must be true or false, got None")
        put("ok", ok)
        for name in _OPT_FLOATS:
            put(name, _opt_float(name, getattr(self, name)))
        for name in _TUPLES:
            put(name, _float_tuple(name, getattr(self, name)))
        put("passed", _opt_bool("passed", self.passed))
        if self.error is not None and not isinstance(self.error, str):
            raise ValueError(f"error must be a string or None, got {self.error!r}")
        if not isinstance(self.extra, Mapping) or not all(isinstance(k, str) for k in self.extra):
            raise ValueError(f"extra must be a dict with string keys, got {self.extra!r:.80}")
        put("extra", dict(self.extra))
        if self.ok:
            if self.error is not None:
                raise ValueError(f"error must be None for a successful measurement, got "
                                 f"{self.error!r}")
        else:
            if not self.error:
                raise ValueError("error must say why the measurement failed (ok=False)")
            carried = [n for n in ("pitch_mm", "uniformity_cv", "depth_um", "passed")
                       if getattr(self, n) is not None]
            if self.mark_widths_mm:
                carried.append("mark_widths_mm")
            if carried:
                raise ValueError(f"a failed measurement carries no metrics, got {carried[0]}")


_OPT_FLOATS = (
    "pitch_mm", "uniformity_cv", "depth_um", "shift_px", "confidence", "feed_setpoint_mm_s",
    "target_pitch_mm", "true_pitch_mm", "true_uniformity_cv",
)
_TUPLES = ("mark_widths_mm", "piezo_offsets_um")
_FIELD_NAMES = tuple(f.name for f in fields(QualityRecord))


# --------------------------------------------------------------------------------------------
# quality class and pass/fail


@dataclass(frozen=True)
class QualityClass:
    """Limits a measurement must meet to pass.

    Parameters
    ----------
    name : str
        Name of the class (e.g. ``"furniture-1.5"``).
    target_pitch_mm : float
        Target mark pitch, mm (> 0).
    pitch_tolerance : float
        Allowed relative pitch deviation, fraction of the target (0.02 = +-2 %), in [0, 1).
    uniformity_max_cv : float or None
        Largest allowed CV of the mark widths; ``None`` = not checked.
    depth_max_um : float or None
        Largest allowed mark depth, micrometres; ``None`` = not checked.
    """

    name: str
    target_pitch_mm: float
    pitch_tolerance: float
    uniformity_max_cv: float | None = None
    depth_max_um: float | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"name must be a non-empty string, got {self.name!r}")
        object.__setattr__(self, "target_pitch_mm",
                           check_positive("target_pitch_mm", self.target_pitch_mm))
        tol = check_positive("pitch_tolerance", self.pitch_tolerance, allow_zero=True)
        if tol >= 1:
            raise ValueError(f"pitch_tolerance is a fraction and must be < 1, got {tol!r}")
        object.__setattr__(self, "pitch_tolerance", tol)
        for name in ("uniformity_max_cv", "depth_max_um"):
            v = getattr(self, name)
            if v is not None:
                object.__setattr__(self, name, check_positive(name, v, allow_zero=True))

    def to_dict(self) -> dict[str, Any]:
        """The class as a JSON-ready dict (the keys of the constructor)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> QualityClass:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError``."""
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"unknown quality class key {unknown[0]!r}")
        return cls(**dict(data))


def quality_class_from_section(section: Section) -> QualityClass:
    """Read a quality class from a config table (keys as :class:`QualityClass`; errors name them).

    ``name``, ``target_pitch_mm`` and ``pitch_tolerance`` are required; ``uniformity_max_cv``
    and ``depth_max_um`` are optional (absent = not checked).
    """
    return QualityClass(
        name=section.string("name"),
        target_pitch_mm=section.number("target_pitch_mm", lo=0.0, lo_open=True),
        pitch_tolerance=section.number("pitch_tolerance", lo=0.0, hi=0.999),
        uniformity_max_cv=(section.number("uniformity_max_cv", lo=0.0)
                           if section.has("uniformity_max_cv") else None),
        depth_max_um=(section.number("depth_max_um", lo=0.0)
                      if section.has("depth_max_um") else None),
    )


def _metric(metrics: Any, name: str) -> Any:
    if isinstance(metrics, Mapping):
        return metrics.get(name)
    return getattr(metrics, name, None)


def judge(metrics: Any, quality_class: QualityClass) -> bool:
    """Whether a measurement meets a quality class (all limits inclusive).

    Parameters
    ----------
    metrics : QualityRecord, mapping or object
        Anything with ``pitch_mm``, ``uniformity_cv`` and ``depth_um`` (attributes or keys).
    quality_class : QualityClass
        The limits. Uniformity and depth are checked only when the class sets a limit.

    Returns
    -------
    bool
        ``|pitch_mm / target_pitch_mm - 1| <= pitch_tolerance`` and
        ``uniformity_cv <= uniformity_max_cv`` and ``depth_um <= depth_max_um``.

    Raises
    ------
    ValueError
        When a metric the class checks is missing or not finite (judge only successful
        measurements; a failed one has ``passed=None``).
    """
    qc = quality_class
    if not isinstance(qc, QualityClass):
        raise ValueError(f"quality_class must be a QualityClass, got {type(qc).__name__}")
    pitch = check_positive("pitch_mm", _required(metrics, "pitch_mm"))
    ok = abs(pitch / qc.target_pitch_mm - 1.0) <= qc.pitch_tolerance + 1e-9
    if qc.uniformity_max_cv is not None:
        cv = check_positive("uniformity_cv", _required(metrics, "uniformity_cv"), allow_zero=True)
        ok = ok and cv <= qc.uniformity_max_cv
    if qc.depth_max_um is not None:
        depth = check_finite("depth_um", _required(metrics, "depth_um"))
        ok = ok and depth <= qc.depth_max_um
    return bool(ok)


def _required(metrics: Any, name: str) -> Any:
    v = _metric(metrics, name)
    if v is None:
        raise ValueError(f"{name} is missing: judge only successful measurements")
    return v


# --------------------------------------------------------------------------------------------
# the store

_COLUMNS: tuple[tuple[str, str], ...] = (
    ("t_s", "REAL NOT NULL"),
    ("wall_time", "TEXT NOT NULL"),
    ("seq", "INTEGER NOT NULL"),
    ("board_id", "INTEGER NOT NULL"),
    ("board_position_mm", "REAL NOT NULL"),
    ("ok", "INTEGER NOT NULL CHECK (ok IN (0, 1))"),
    ("error", "TEXT"),
    ("pitch_mm", "REAL"),
    ("mark_widths_mm", "TEXT NOT NULL"),
    ("uniformity_cv", "REAL"),
    ("depth_um", "REAL"),
    ("shift_px", "REAL"),
    ("confidence", "REAL"),
    ("feed_setpoint_mm_s", "REAL"),
    ("piezo_offsets_um", "TEXT NOT NULL"),
    ("target_pitch_mm", "REAL"),
    ("passed", "INTEGER CHECK (passed IN (0, 1))"),
    ("true_pitch_mm", "REAL"),
    ("true_uniformity_cv", "REAL"),
    ("extra", "TEXT NOT NULL"),
)
assert tuple(c for c, _ in _COLUMNS) == _FIELD_NAMES, "schema and record differ"

_SCHEMA = (
    "CREATE TABLE schema_version (version INTEGER NOT NULL)",
    "CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
    "CREATE TABLE records (id INTEGER PRIMARY KEY AUTOINCREMENT, "
    + ", ".join(f"{c} {t}" for c, t in _COLUMNS) + ")",
    "CREATE INDEX records_board ON records (board_id)",
    "CREATE INDEX records_seq ON records (seq)",
)

_INSERT = (f"INSERT INTO records ({', '.join(_FIELD_NAMES)}) "
           f"VALUES ({', '.join('?' * len(_FIELD_NAMES))})")
_SELECT = f"SELECT id, {', '.join(_FIELD_NAMES)} FROM records"


def _json_default(obj: Any) -> Any:
    if hasattr(obj, "tolist"):  # numpy arrays and scalars
        return obj.tolist()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _list_to_json(values: tuple[float, ...]) -> str:
    return json.dumps([None if math.isnan(v) else v for v in values])


def _list_from_json(text: str) -> tuple[float, ...]:
    return tuple(math.nan if v is None else float(v) for v in json.loads(text))


def record_to_json(record: QualityRecord) -> str:
    """One record as a line of JSON (fields by name; NaN as ``null``), e.g. for a fallback file."""
    out: dict[str, Any] = {}
    for name in _FIELD_NAMES:
        v = getattr(record, name)
        if name in _TUPLES:
            v = [None if math.isnan(x) else x for x in v]
        out[name] = v
    return json.dumps(out, default=_json_default, allow_nan=False)


def _to_row(rec: QualityRecord) -> tuple[Any, ...]:
    row: list[Any] = []
    for name in _FIELD_NAMES:
        v = getattr(rec, name)
        if name in _TUPLES:
            v = _list_to_json(v)
        elif name == "extra":
            try:
                v = json.dumps(v, default=_json_default)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"extra is not JSON serialisable: {exc}") from None
        elif isinstance(v, bool):
            v = int(v)
        row.append(v)
    return tuple(row)


def _from_row(row: Sequence[Any]) -> QualityRecord:
    rid, *vals = row
    try:
        kw = dict(zip(_FIELD_NAMES, vals, strict=True))
        for name in _TUPLES:
            kw[name] = _list_from_json(kw[name])
        kw["extra"] = json.loads(kw["extra"])
        kw["ok"] = bool(kw["ok"])
        kw["passed"] = None if kw["passed"] is None else bool(kw["passed"])
        return QualityRecord(**kw)
    except (TypeError, ValueError, KeyError) as exc:
        raise QualityLogError(f"record {rid} of the quality log is unreadable: {exc}") from None


class QualityLog:
    """An append-only quality log in an SQLite file (WAL, ``synchronous=FULL``).

    Parameters
    ----------
    path : str or Path
        The log file. Opening an existing log continues it.
    create : bool, keyword-only
        Create the file when it does not exist (default). With ``False`` a missing file
        raises ``FileNotFoundError`` (readers such as ``planer report``).
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
    One instance may be shared by threads (calls are serialised by a lock); separate
    processes open their own instances on the same file.
    """

    def __init__(self, path: str | Path, *, create: bool = True, timeout_s: float = 10.0) -> None:
        self.path = Path(path)
        timeout_s = check_positive("timeout_s", timeout_s)
        self._lock = threading.RLock()
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
                f"file:{_uri_path(p)}?mode={'rwc' if create else 'rw'}", uri=True,
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
        conn = self._conn
        assert conn is not None
        p = self.path
        try:
            conn.execute(f"PRAGMA busy_timeout = {int(timeout_s * 1000)}")
            app_id = conn.execute("PRAGMA application_id").fetchone()[0]
            tables = {r[0] for r in conn.execute(
                "SELECT name FROM sqlite_master WHERE type = 'table'")}
            if tables and (app_id != APPLICATION_ID or "records" not in tables):
                raise QualityLogError(f"{p} is an SQLite file but not a quality log")
            mode = conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                raise OSError(f"cannot use write-ahead logging for {p} (journal mode {mode})")
            conn.execute("PRAGMA synchronous = FULL")
            if not tables:
                if not create:
                    raise QualityLogError(f"{p} is empty, not a quality log")
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
        self.schema_version = version

    def _create_schema(self) -> None:
        conn = self._conn
        assert conn is not None
        conn.execute("BEGIN IMMEDIATE")
        try:
            exists = conn.execute(
                "SELECT 1 FROM sqlite_master WHERE name = 'records'").fetchone()
            if not exists:  # another process may have created it while we waited
                for stmt in _SCHEMA:
                    conn.execute(stmt)
                conn.execute("INSERT INTO schema_version (version) VALUES (?)",
                             (SCHEMA_VERSION,))
                conn.execute(f"PRAGMA application_id = {APPLICATION_ID}")
            conn.execute("COMMIT")
        except BaseException:
            conn.execute("ROLLBACK")
            raise

    # -- writing ------------------------------------------------------------------------------

    def _connection(self) -> sqlite3.Connection:
        if self._conn is None:
            raise ValueError(f"quality log {self.path} is closed")
        return self._conn

    def append(self, record: QualityRecord) -> int:
        """Append one record; returns its id once it is committed to disk.

        Parameters
        ----------
        record : QualityRecord
            The measurement.

        Returns
        -------
        int
            The record's id (increasing in append order, never reused).
        """
        if not isinstance(record, QualityRecord):
            raise ValueError(f"record must be a QualityRecord, got {type(record).__name__}")
        row = _to_row(record)
        with self._lock:
            conn = self._connection()
            try:
                conn.execute("BEGIN IMMEDIATE")
                try:
                    cur = conn.execute(_INSERT, row)
                    conn.execute("COMMIT")
                except BaseException:
                    if conn.in_transaction:
                        conn.execute("ROLLBACK")
                    raise
            except sqlite3.Error as exc:
                raise OSError(f"cannot append to quality log {self.path}: {exc}") from None
            return int(cur.lastrowid)

    def set_meta(self, key: str, value: Any) -> None:
        """Store a JSON-serialisable value under ``key`` (e.g. ``"quality_class"``)."""
        if not isinstance(key, str) or not key:
            raise ValueError(f"key must be a non-empty string, got {key!r}")
        try:
            text = json.dumps(value, default=_json_default)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"value of meta key {key!r} is not JSON serialisable: {exc}") from None
        with self._lock:
            conn = self._connection()
            try:
                conn.execute("BEGIN IMMEDIATE")
                conn.execute("INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)", (key, text))
                conn.execute("COMMIT")
            except sqlite3.Error as exc:
                if conn.in_transaction:
                    conn.execute("ROLLBACK")
                raise OSError(f"cannot write to quality log {self.path}: {exc}") from None

    def set_quality_class(self, quality_class: QualityClass) -> None:
        """Store the quality class the records are judged against (read by ``planer report``)."""
        if not isinstance(quality_class, QualityClass):
            raise ValueError("quality_class must be a QualityClass")
        self.set_meta("quality_class", quality_class.to_dict())

    # -- reading ------------------------------------------------------------------------------

    def _query(self, sql: str, params: Sequence[Any] = ()) -> list[tuple[Any, ...]]:
        with self._lock:
            conn = self._connection()
            try:
                return conn.execute(sql, tuple(params)).fetchall()
            except sqlite3.DatabaseError as exc:
                raise QualityLogError(f"cannot read quality log {self.path}: {exc}") from None

    def get_meta(self, key: str, default: Any = None) -> Any:
        """The value stored under ``key``, or ``default``."""
        rows = self._query("SELECT value FROM meta WHERE key = ?", (key,))
        if not rows:
            return default
        try:
            return json.loads(rows[0][0])
        except ValueError as exc:
            raise QualityLogError(f"meta key {key!r} of {self.path} is unreadable: {exc}") from None

    def quality_class(self) -> QualityClass | None:
        """The stored quality class, or ``None`` when the writer stored none."""
        data = self.get_meta("quality_class")
        if data is None:
            return None
        try:
            return QualityClass.from_dict(data)
        except (TypeError, ValueError) as exc:
            raise QualityLogError(
                f"stored quality class of {self.path} is invalid: {exc}") from None

    def entries(
        self,
        *,
        board_id: int | None = None,
        since_seq: int | None = None,
        after_id: int | None = None,
    ) -> list[tuple[int, QualityRecord]]:
        """``(id, record)`` pairs in append order; filters as :meth:`records`."""
        where, params = [], []
        if board_id is not None:
            where.append("board_id = ?")
            params.append(check_int("board_id", board_id))
        if since_seq is not None:
            where.append("seq >= ?")
            params.append(check_int("since_seq", since_seq))
        if after_id is not None:
            where.append("id > ?")
            params.append(check_int("after_id", after_id))
        sql = _SELECT + (" WHERE " + " AND ".join(where) if where else "") + " ORDER BY id"
        return [(int(r[0]), _from_row(r)) for r in self._query(sql, params)]

    def records(
        self,
        board_id: int | None = None,
        since_seq: int | None = None,
        *,
        after_id: int | None = None,
    ) -> list[QualityRecord]:
        """The records in append order.

        Parameters
        ----------
        board_id : int, optional
            Only this board's records.
        since_seq : int, optional
            Only records with ``seq >= since_seq``.
        after_id : int, keyword-only, optional
            Only records appended after the one with this id (for following a growing log).
        """
        return [r for _, r in self.entries(board_id=board_id, since_seq=since_seq,
                                           after_id=after_id)]

    @property
    def last_id(self) -> int:
        """Id of the newest record (0 when empty)."""
        return int(self._query("SELECT COALESCE(MAX(id), 0) FROM records")[0][0])

    def __len__(self) -> int:
        return int(self._query("SELECT COUNT(*) FROM records")[0][0])

    def export_csv(self, path: str | Path) -> int:
        """Write every record to a CSV file (atomically: a reader never sees a partial file).

        One row per record, columns :data:`CSV_COLUMNS` (units in the names); numbers without
        binary rounding noise (:func:`csv_float`: ``0.7``, not ``0.7000000000000001``); lists as
        semicolon-separated numbers, booleans as 1/0, missing values empty, ``extra`` as JSON
        without the bulky ``profile`` entry.

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
        entries = self.entries()
        with atomic_writer(out, newline="") as fh:
            w = csv.writer(fh)
            w.writerow(CSV_COLUMNS)
            for rid, rec in entries:
                w.writerow(csv_row(rid, rec))
        return len(entries)

    # -- lifetime -----------------------------------------------------------------------------

    def close(self) -> None:
        """Close the file (idempotent)."""
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None

    def __enter__(self) -> QualityLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._conn is None else "open"
        return f"QualityLog({str(self.path)!r}, {state})"


def _uri_path(p: Path) -> str:
    from urllib.parse import quote

    return quote(str(p.absolute()))


# --------------------------------------------------------------------------------------------
# CSV layout

#: CSV header: the record id, then the record's fields (``wall_time`` as ``wall_time_utc``,
#: ``extra`` as ``extra_json``).
CSV_COLUMNS: tuple[str, ...] = ("record_id",) + tuple(
    {"wall_time": "wall_time_utc", "extra": "extra_json"}.get(n, n) for n in _FIELD_NAMES
)


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
        elif name == "extra":
            slim = {k: val for k, val in v.items() if k != "profile"}
            row.append(json.dumps(slim, default=_json_default) if slim else "")
        else:
            row.append(_fmt(v))
    return row
