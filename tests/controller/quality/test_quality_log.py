"""Quality log: record validation, SQLite round trip, crash safety, CSV export, pass/fail."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import random
import signal
import sqlite3
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from config.loading import Section
from controller.quality.log import (
    CSV_COLUMNS,
    CSV_NOISE_ULPS,
    CSV_SIGNIFICANT_DIGITS,
    SCHEMA_VERSION,
    QualityClass,
    QualityLog,
    QualityLogError,
    QualityRecord,
    csv_float,
    judge,
    quality_class_from_section,
    utc_iso,
)
from controller.quality.schema import (
    ADDED_IN_V4,
    ADDED_IN_V5,
    ADDED_IN_V6,
    ADDED_IN_V7,
    ADDED_IN_V8,
)
from core.errors import ConfigError
from tests.support.old_logs import downgrade

REPO = Path(__file__).resolve().parents[3]


def _rec(i: int = 0, **kw) -> QualityRecord:
    base = dict(
        t_s=0.1 * i, wall_time=utc_iso(1.7e9 + 0.1 * i), seq=i, board_id=1 + i // 10,
        board_position_mm=40.0 * (i % 10), ok=True, pitch_mm=1.5 + 0.001 * i,
        mark_widths_mm=[1.4, 1.5, 1.6, 1.5], uniformity_cv=0.05, depth_um=4.7, shift_px=42.5,
        confidence=0.93, feed_setpoint_mm_s=600.0, piezo_offsets_um=[1.0, -2.0, 0.5, 0.0],
        target_pitch_mm=1.5, passed=True, machine_id="planer-test",
    )
    base.update(kw)
    return QualityRecord(**base)


def _key(rec: QualityRecord) -> tuple:
    """A comparable form of a record in which NaN equals NaN."""
    out = []
    for name, v in vars(rec).items():
        if isinstance(v, tuple):
            v = tuple("nan" if math.isnan(x) else x for x in v)
        out.append((name, v))
    return tuple(out)


# --------------------------------------------------------------------------------------------
# the record


def test_record_normalises_types_and_nan():
    r = _rec(mark_widths_mm=[1, float("nan"), 2], uniformity_cv=float("nan"), depth_um=None)
    assert r.mark_widths_mm[0] == 1.0 and math.isnan(r.mark_widths_mm[1])
    assert isinstance(r.mark_widths_mm, tuple)
    assert r.uniformity_cv is None  # NaN scalar = not measured
    assert r.depth_um is None


@pytest.mark.parametrize(
    "kw, name",
    [
        (dict(t_s=float("inf")), "t_s"),
        (dict(wall_time="yesterday"), "wall_time"),
        (dict(wall_time="2026-01-01T10:00:00+02:00"), "wall_time"),
        (dict(wall_time="2026-01-01T10:00:00"), "wall_time"),
        (dict(seq=-1), "seq"),
        (dict(seq=1.5), "seq"),
        (dict(board_id=-3), "board_id"),
        (dict(ok=None), "ok"),
        (dict(ok="yes"), "ok"),
        (dict(passed=1), "passed"),
        (dict(pitch_mm="wide"), "pitch_mm"),
        (dict(depth_um=float("inf")), "depth_um"),
        (dict(mark_widths_mm=[1.0, float("inf")]), "mark_widths_mm[1]"),
        (dict(mark_widths_mm="1;2"), "mark_widths_mm"),
        (dict(error="should be None"), "error"),
        (dict(ok=False, error=None, pitch_mm=None, mark_widths_mm=(), uniformity_cv=None,
              depth_um=None, passed=None), "error"),
        (dict(ok=False, error="registration failed"), "pitch_mm"),
        (dict(extra=[1, 2]), "extra"),
        (dict(extra={1: "x"}), "extra"),
    ],
)
def test_record_rejects_bad_values(kw, name):
    with pytest.raises(ValueError, match=name.replace("[", r"\[").replace("]", r"\]")):
        _rec(**kw)


def test_failed_record_may_carry_registration_diagnostics():
    r = _rec(ok=False, error="registration failed: confidence 0.2", pitch_mm=None,
             mark_widths_mm=(), uniformity_cv=None, depth_um=None, passed=None, confidence=0.2)
    assert r.confidence == 0.2 and r.pitch_mm is None


def test_utc_iso_parses_back():
    from datetime import datetime, timezone

    s = utc_iso(1_700_000_000.25)
    d = datetime.fromisoformat(s)
    assert d.tzinfo is not None and d.utcoffset().total_seconds() == 0
    assert d.timestamp() == pytest.approx(1_700_000_000.25, abs=1e-6)
    assert d == datetime.fromtimestamp(1_700_000_000.25, tz=timezone.utc)


# --------------------------------------------------------------------------------------------
# round trip

_num = st.floats(-1e6, 1e6, allow_nan=False)
_opt = st.one_of(st.none(), st.just(float("nan")), _num)
_widths = st.lists(st.one_of(_num, st.just(float("nan"))), max_size=6)
_json = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6), _num, st.text(max_size=8)),
    lambda c: st.one_of(st.lists(c, max_size=4), st.dictionaries(st.text(max_size=5), c,
                                                                max_size=4)),
    max_leaves=12,
)


@st.composite
def records(draw):
    ok = draw(st.booleans())
    kw = dict(
        t_s=draw(_num), wall_time=utc_iso(draw(st.floats(0, 4e9))),
        seq=draw(st.integers(0, 2**40)), board_id=draw(st.integers(0, 10**6)),
        board_position_mm=draw(_num), ok=ok, shift_px=draw(_opt), confidence=draw(_opt),
        feed_setpoint_mm_s=draw(_opt), piezo_offsets_um=draw(_widths),
        target_pitch_mm=draw(_opt), true_pitch_mm=draw(_opt), true_uniformity_cv=draw(_opt),
        extra=draw(st.dictionaries(st.text(max_size=6), _json, max_size=3)),
        machine_id=draw(st.sampled_from(["planer-1", "Hobel 7 \u00fc", "m"])),
    )
    if ok:
        kw.update(pitch_mm=draw(_opt), mark_widths_mm=draw(_widths), uniformity_cv=draw(_opt),
                  depth_um=draw(_opt), passed=draw(st.one_of(st.none(), st.booleans())))
    else:
        kw["error"] = draw(st.text(min_size=1, max_size=40))
    return QualityRecord(**kw)


@settings(max_examples=40, deadline=None)
@given(st.lists(records(), min_size=1, max_size=5))
def test_round_trip(recs):
    with tempfile.TemporaryDirectory() as d:
        with QualityLog(Path(d) / "q.db") as log:
            ids = [log.append(r) for r in recs]
            back = log.entries()
        assert ids == sorted(ids) and len(set(ids)) == len(ids)
        assert [i for i, _ in back] == ids
        assert [_key(r) for _, r in back] == [_key(r) for r in recs]


def test_numpy_values_are_stored_as_numbers(tmp_path):
    import numpy as np

    r = _rec(pitch_mm=np.float32(1.5), mark_widths_mm=np.array([1.0, 2.0]), passed=np.bool_(True),
             extra={"profile": {"x_mm": np.linspace(0, 1, 3), "height_um": np.zeros(3)}})
    with QualityLog(tmp_path / "q.db") as log:
        log.append(r)
        (back,) = log.records()
    assert back.passed is True and back.pitch_mm == 1.5
    assert back.extra["profile"]["x_mm"] == [0.0, 0.5, 1.0]


def test_persists_across_reopen_and_filters(tmp_path):
    p = tmp_path / "q.db"
    qc = QualityClass("c", 1.5, 0.02, 0.05, 8.0)
    with QualityLog(p) as log:
        first = [log.append(_rec(i)) for i in range(15)]
        log.set_quality_class(qc)
    with QualityLog(p) as log:
        assert len(log) == 15
        more = [log.append(_rec(i)) for i in range(15, 25)]
        assert min(more) > max(first)
        assert log.quality_class() == qc
        assert log.last_id == max(more)
        recs = log.records()
        assert [r.seq for r in recs] == list(range(25))
        assert {r.board_id for r in log.records(board_id=2)} == {2}
        assert len(log.records(board_id=2)) == sum(r.board_id == 2 for r in recs)
        assert [r.seq for r in log.records(since_seq=20)] == list(range(20, 25))
        assert [r.seq for r in log.records(after_id=first[-1])] == list(range(15, 25))
        assert log.get_meta("missing", 7) == 7
    with sqlite3.connect(p) as conn:
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_closed_log_refuses(tmp_path):
    log = QualityLog(tmp_path / "q.db")
    log.close()
    log.close()
    with pytest.raises(ValueError, match="closed"):
        log.append(_rec())


# --------------------------------------------------------------------------------------------
# bad paths and files


def _one_line(exc: BaseException) -> bool:
    return "\n" not in str(exc) and str(exc) != ""


def test_bad_paths(tmp_path):
    for path, exc in [(tmp_path / "nope" / "q.db", FileNotFoundError),
                      (tmp_path, IsADirectoryError)]:
        with pytest.raises(exc) as info:
            QualityLog(path)
        assert _one_line(info.value) and isinstance(info.value, OSError)
    with pytest.raises(FileNotFoundError):
        QualityLog(tmp_path / "absent.db", create=False)
    assert not (tmp_path / "absent.db").exists()


def test_corrupt_and_foreign_files(tmp_path):
    junk = tmp_path / "junk.db"
    junk.write_bytes(random.Random(3).randbytes(8192))
    foreign = tmp_path / "foreign.db"
    with sqlite3.connect(foreign) as conn:
        conn.execute("CREATE TABLE t (x)")
    empty = tmp_path / "empty.db"
    empty.write_bytes(b"")
    for path, kw in [(junk, {}), (foreign, {}), (empty, {"create": False})]:
        with pytest.raises(QualityLogError) as info:
            QualityLog(path, **kw)
        assert _one_line(info.value) and isinstance(info.value, ValueError)
    QualityLog(empty).close()  # an empty file may become a new log when creating is allowed


def test_newer_schema_is_refused(tmp_path):
    p = tmp_path / "q.db"
    QualityLog(p).close()
    with sqlite3.connect(p) as conn:
        conn.execute("UPDATE schema_version SET version = ?", (SCHEMA_VERSION + 1,))
    with pytest.raises(QualityLogError, match=f"version {SCHEMA_VERSION + 1}") as info:
        QualityLog(p)
    assert _one_line(info.value)


def test_table_columns_are_the_csv_header(tmp_path):
    p = tmp_path / "q.db"
    QualityLog(p).close()
    with sqlite3.connect(p) as conn:
        cols = tuple(r[1] for r in conn.execute("PRAGMA table_info(records)"))
    assert cols == CSV_COLUMNS and SCHEMA_VERSION == 8 and cols[-1] == "head"
    renamed = {"wall_time": "wall_time_utc", "extra": "extra_json"}
    assert cols[1:] == tuple(renamed.get(f.name, f.name) for f in dataclasses.fields(QualityRecord))


def _make_v1_log(p: Path, n: int) -> list[QualityRecord]:
    recs = [_rec(i) for i in range(n)]
    with QualityLog(p) as log:
        for r in recs:
            log.append(r)
    with sqlite3.connect(p) as conn:  # the layout of version 1: the record's field names
        for old, new in (("record_id", "id"), ("wall_time_utc", "wall_time"),
                         ("extra_json", "extra")):
            conn.execute(f"ALTER TABLE records RENAME COLUMN {old} TO {new}")
        conn.execute("DROP INDEX records_machine_time")
        downgrade(conn.execute, 3)
        conn.execute("ALTER TABLE records DROP COLUMN machine_id")
        conn.execute("UPDATE schema_version SET version = 1")
    return [dataclasses.replace(r, machine_id=None) for r in recs]


def test_version_1_log_is_read_as_is_and_migrated_by_a_writer(tmp_path):
    p = tmp_path / "q.db"
    recs = _make_v1_log(p, 3)
    with QualityLog(p, create=False) as reader:  # a reader changes nothing
        assert reader.schema_version == 1 and reader.last_id == 3
        assert [_key(r) for r in reader.records()] == [_key(r) for r in recs]
        assert [r.seq for r in reader.records(after_id=1)] == [1, 2]
    with QualityLog(p) as writer:
        assert writer.schema_version == SCHEMA_VERSION
        writer.append(_rec(3))
        assert [r.machine_id for r in writer.records()] == [None, None, None, "planer-test"]
        assert [r.seq for r in writer.records()] == [0, 1, 2, 3]
        assert writer.export_csv(tmp_path / "q.csv") == 4
    with sqlite3.connect(p) as conn:
        cols = tuple(r[1] for r in conn.execute("PRAGMA table_info(records)"))
    assert cols == CSV_COLUMNS


def test_unreadable_row_names_the_record(tmp_path):
    p = tmp_path / "q.db"
    with QualityLog(p) as log:
        log.append(_rec(0))
        rid = log.append(_rec(1))
    with sqlite3.connect(p) as conn:
        conn.execute("UPDATE records SET mark_widths_mm = '[1, ' WHERE record_id = ?", (rid,))
    with QualityLog(p) as log, pytest.raises(QualityLogError, match=f"record {rid}"):
        log.records()


# --------------------------------------------------------------------------------------------
# crash safety and several processes

# The record generator is shared as source so that the child needs no pytest/hypothesis import.
_GEN = textwrap.dedent("""
    import random
    from controller.quality.log import QualityRecord, utc_iso

    def expected_record(run, i):
        rng = random.Random(run * 1_000_003 + i)
        ok = rng.random() > 0.1
        kw = dict(t_s=i * 0.05, wall_time=utc_iso(1.7e9 + i), seq=i, board_id=run,
                  machine_id=f"planer-{run}",
                  board_position_mm=rng.uniform(0, 4000), ok=ok, confidence=rng.random(),
                  feed_setpoint_mm_s=rng.uniform(100, 900),
                  piezo_offsets_um=[rng.uniform(-20, 20) for _ in range(4)],
                  extra={"run": run, "i": i,
                         "profile": {"x_mm": [rng.random() for _ in range(200)],
                                     "height_um": [rng.random() for _ in range(200)]}})
        if ok:
            kw.update(pitch_mm=rng.uniform(1, 2), mark_widths_mm=[rng.random() for _ in range(4)],
                      uniformity_cv=rng.random(), depth_um=rng.random() * 10,
                      passed=rng.random() < 0.5)
        else:
            kw["error"] = "registration failed: confidence low"
        return QualityRecord(**kw)
""")

_CHILD = _GEN + textwrap.dedent("""
    import sys
    from controller.quality.log import QualityLog
    run, n = int(sys.argv[2]), int(sys.argv[3])
    with QualityLog(sys.argv[1]) as log:
        for i in range(n):
            rid = log.append(expected_record(run, i))
            sys.stdout.write(f"{rid} {i}\\n")
            sys.stdout.flush()
""")

_ns: dict = {}
exec(compile(_GEN, "<record generator>", "exec"), _ns)
expected_record = _ns["expected_record"]


def _child(path: Path, run: int, n: int) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.Popen([sys.executable, "-c", _CHILD, str(path), str(run), str(n)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=REPO, env=env)


def test_sigkill_loses_no_acknowledged_record(tmp_path):
    p = tmp_path / "q.db"
    rng = random.Random(20240611)
    kills, lost, extra_rows = 6, 0, 0
    for run in range(kills):
        child = _child(p, run, 10**9)
        wanted = rng.randint(1, 120)
        acked: list[tuple[int, int]] = []
        while len(acked) < wanted:
            line = child.stdout.readline()
            assert line, child.stderr.read()
            acked.append(tuple(map(int, line.split())))
        child.send_signal(signal.SIGKILL)  # lands at an arbitrary point of the append loop
        rest, _ = child.communicate()
        acked += [tuple(map(int, ln.split())) for ln in rest.split("\n")[:-1]]
        assert child.returncode == -signal.SIGKILL

        with QualityLog(p) as log:  # opens fine after the kill
            entries = dict(log.entries())
            mine = {rid: r for rid, r in entries.items() if r.board_id == run}
        # every acknowledged record is there and intact
        for rid, i in acked:
            if rid not in entries:
                lost += 1
                continue
            assert _key(entries[rid]) == _key(expected_record(run, i))
        # every stored record of this run is complete (none torn) and they are contiguous
        got_i = sorted(r.extra["i"] for r in mine.values())
        assert got_i == list(range(len(got_i)))
        for r in mine.values():
            assert _key(r) == _key(expected_record(run, r.extra["i"]))
        extra_rows += len(mine) - len(acked)
        assert len(mine) >= len(acked)
    assert lost == 0


def test_two_writers_and_a_reader(tmp_path):
    p = tmp_path / "q.db"
    QualityLog(p).close()
    children = [_child(p, run, 40) for run in (1, 2)]
    seen = 0
    with QualityLog(p, create=False) as reader:
        while any(c.poll() is None for c in children):
            n = len(reader.records())  # reading while both write: never an error
            assert n >= seen
            seen = n
    acked = []
    for c in children:
        out, err = c.communicate()
        assert c.returncode == 0, err
        acked += [int(ln.split()[0]) for ln in out.splitlines()]
    with QualityLog(p) as log:
        entries = dict(log.entries())
    assert len(acked) == 80 and set(acked) == set(entries)
    for run in (1, 2):
        assert sorted(r.seq for r in entries.values() if r.board_id == run) == list(range(40))


# --------------------------------------------------------------------------------------------
# CSV


def _parse_float(s: str):
    return None if s == "" else float(s)


def _reads_back(text: str, logged: float) -> bool:
    """CSV text reads back as the logged double, or as its noise-free 15-digit form."""
    v = float(text)
    if v == logged or (math.isnan(v) and math.isnan(logged)):
        return True
    return (v == float(f"{logged:.{CSV_SIGNIFICANT_DIGITS}g}")
            and abs(v - logged) <= CSV_NOISE_ULPS * math.ulp(logged))


def test_csv_round_trip(tmp_path):
    recs = [expected_record(7, i) for i in range(30)]
    recs.append(_rec(99, mark_widths_mm=[1.0, float("nan")], passed=None, extra={}))
    with QualityLog(tmp_path / "q.db") as log:
        ids = [log.append(r) for r in recs]
        n = log.export_csv(tmp_path / "q.csv")
    assert n == len(recs)
    assert not [f for f in os.listdir(tmp_path) if f.endswith(".tmp")]
    with open(tmp_path / "q.csv", newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        assert tuple(reader.fieldnames) == CSV_COLUMNS
        rows = list(reader)
    assert len(rows) == len(recs)
    for rid, rec, row in zip(ids, recs, rows, strict=True):
        assert int(row["record_id"]) == rid
        assert _reads_back(row["t_s"], rec.t_s) and row["wall_time_utc"] == rec.wall_time
        assert row["t_s"] == repr(round(rec.t_s, 2))  # 0.15000000000000002 is written 0.15
        assert int(row["seq"]) == rec.seq and int(row["board_id"]) == rec.board_id
        assert row["ok"] == ("1" if rec.ok else "0")
        assert row["passed"] == {None: "", True: "1", False: "0"}[rec.passed]
        assert (row["error"] or None) == rec.error
        for name in ("board_position_mm", "pitch_mm", "uniformity_cv", "depth_um", "shift_px",
                     "confidence", "feed_setpoint_mm_s", "target_pitch_mm", "true_pitch_mm",
                     "true_uniformity_cv"):
            logged = getattr(rec, name)
            assert (row[name] == "") if logged is None else _reads_back(row[name], logged), name
        for name in ("mark_widths_mm", "piezo_offsets_um"):
            texts = row[name].split(";") if row[name] else []
            assert len(texts) == len(getattr(rec, name))
            assert all(_reads_back(t, v) for t, v in zip(texts, getattr(rec, name), strict=True))
        slim = {k: v for k, v in rec.extra.items() if k != "profile"}
        assert (json.loads(row["extra_json"]) if row["extra_json"] else {}) == slim


@pytest.mark.parametrize("value, text", [
    (0.1 * 7, "0.7"), (0.1 + 0.2, "0.3"), (1.1 * 3, "3.3"),
    (2.0000000000000004, "2.0"), (600.0, "600.0"), (1 / 3, repr(1 / 3)),
    (1.2345678901234567, "1.2345678901234567"), (240.00000000000455, "240.00000000000455"),
    (5e-324, "5e-324"), (-0.0, "-0.0"), (float("nan"), "nan"), (1e22, "1e+22"),
])
def test_csv_float_drops_noise_only(value, text):
    assert csv_float(value) == text


@settings(max_examples=300, deadline=None)
@given(st.floats(allow_nan=False, allow_infinity=False))
def test_csv_float_reads_back_as_logged(value):
    text = csv_float(value)
    assert _reads_back(text, value)
    assert len(text) <= len(repr(value))
    decimal = float(f"{value:.12g}")  # a value born as a short decimal is written exactly
    assert float(csv_float(decimal)) == decimal


def test_csv_bad_path(tmp_path):
    with QualityLog(tmp_path / "q.db") as log:
        with pytest.raises(FileNotFoundError):
            log.export_csv(tmp_path / "nope" / "x.csv")
        with pytest.raises(IsADirectoryError):
            log.export_csv(tmp_path)


# --------------------------------------------------------------------------------------------
# quality class and judge

QC = QualityClass("furniture", target_pitch_mm=1.5, pitch_tolerance=0.02,
                  uniformity_max_cv=0.05, depth_max_um=8.0)


@pytest.mark.parametrize(
    "pitch, cv, depth, passed",
    [
        (1.5, 0.01, 4.0, True),
        (1.53, 0.01, 4.0, True),     # +2 % exactly: inclusive
        (1.47, 0.01, 4.0, True),     # -2 % exactly
        (1.5301, 0.01, 4.0, False),
        (1.4699, 0.01, 4.0, False),
        (1.5, 0.05, 4.0, True),      # CV at the limit
        (1.5, 0.0501, 4.0, False),
        (1.5, 0.0, 8.0, True),       # depth at the limit
        (1.5, 0.01, 8.01, False),
        (2.0, 0.2, 20.0, False),
    ],
)
def test_judge_table(pitch, cv, depth, passed):
    m = {"pitch_mm": pitch, "uniformity_cv": cv, "depth_um": depth}
    assert judge(m, QC) is passed
    assert judge(_rec(pitch_mm=pitch, uniformity_cv=cv, depth_um=depth), QC) is passed


def test_judge_optional_limits_and_missing_metrics():
    pitch_only = QualityClass("p", 1.5, 0.02)
    assert judge({"pitch_mm": 1.5}, pitch_only) is True
    assert judge({"pitch_mm": 1.5, "uniformity_cv": 0.9, "depth_um": 99}, pitch_only) is True
    with pytest.raises(ValueError, match="uniformity_cv"):
        judge({"pitch_mm": 1.5, "depth_um": 1.0}, QC)
    with pytest.raises(ValueError, match="pitch_mm"):
        judge(_rec(pitch_mm=None), QC)


@pytest.mark.parametrize(
    "kw, name",
    [(dict(name=""), "name"), (dict(target_pitch_mm=0), "target_pitch_mm"),
     (dict(pitch_tolerance=-0.1), "pitch_tolerance"), (dict(pitch_tolerance=1.0),
                                                       "pitch_tolerance"),
     (dict(uniformity_max_cv=-1), "uniformity_max_cv"), (dict(depth_max_um=float("nan")),
                                                         "depth_max_um")],
)
def test_quality_class_rejects(kw, name):
    base = dict(name="c", target_pitch_mm=1.5, pitch_tolerance=0.02)
    with pytest.raises(ValueError, match=name):
        QualityClass(**{**base, **kw})


def test_quality_class_from_config():
    qc = quality_class_from_section(Section(
        {"name": "c", "target_pitch_mm": 1.5, "pitch_tolerance": 0.02, "depth_max_um": 8},
        "quality"))
    assert qc == QualityClass("c", 1.5, 0.02, None, 8.0)
    assert QualityClass.from_dict(qc.to_dict()) == qc
    with pytest.raises(ConfigError, match="quality.target_pitch_mm"):
        quality_class_from_section(Section({"name": "c", "pitch_tolerance": 0.02}, "quality"))


# --------------------------------------------------------------------------------------------
# machine ids


def test_record_without_machine_id_gets_the_logs_and_filters_by_machine(tmp_path):
    from controller.quality.log import default_machine_id

    with QualityLog(tmp_path / "q.db", machine_id="planer-5") as log:
        log.append(_rec(0, machine_id=None))
        log.append(_rec(1, machine_id="planer-6"))
        assert [r.machine_id for r in log.records()] == ["planer-5", "planer-6"]
        assert [r.seq for r in log.records(machine_id="planer-6")] == [1]
        assert log.export_csv(tmp_path / "m.csv", machine_id="planer-5") == 1
    with QualityLog(tmp_path / "d.db") as log:
        log.append(_rec(0, machine_id=None))
        assert log.records()[0].machine_id == default_machine_id() == log.machine_id
    assert default_machine_id() and default_machine_id().isprintable()


@pytest.mark.parametrize("bad", ["", " x", "a\nb", "x" * 65, 7])
def test_bad_machine_ids_are_refused_naming_them(tmp_path, bad):
    with pytest.raises(ValueError, match="machine_id"):
        _rec(machine_id=bad)
    with pytest.raises(ValueError, match="machine_id"):
        QualityLog(tmp_path / "q.db", machine_id=bad)


def test_machine_toml_machine_id():
    from config.machine import machine_from_dict

    assert machine_from_dict({}).log.machine_id == ""  # "" = the host name
    assert machine_from_dict({"machine": {"id": "planer-7"}}).log.machine_id == "planer-7"
    for bad, key in [({"id": " x"}, "machine.id"), ({"id": 3}, "machine.id"),
                     ({"name": "x"}, "machine.name")]:
        with pytest.raises(ConfigError, match=key):
            machine_from_dict({"machine": bad})


@pytest.mark.parametrize("version", [3, 4, 5, 6, 7, 8])
def test_columns_added_since_a_version_are_the_later_versions_columns_in_order(version):
    from controller.quality.schema import SCHEMA_VERSION, columns_added_since

    by_version = {4: ADDED_IN_V4, 5: ADDED_IN_V5, 6: ADDED_IN_V6, 7: ADDED_IN_V7,
                  8: ADDED_IN_V8}
    want = tuple(c for v in range(version + 1, SCHEMA_VERSION + 1) for c in by_version[v])
    assert columns_added_since(version) == want
    assert len({name for name, _, _ in want}) == len(want)  # each column added once


@pytest.mark.parametrize("version", [0, 1, 2, 9, -1])
def test_columns_added_since_refuses_a_version_it_cannot_migrate_from(version):
    from controller.quality.schema import columns_added_since

    with pytest.raises(ValueError, match="version must be in 3..8"):
        columns_added_since(version)
