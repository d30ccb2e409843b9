"""Quality log, schema version 8: the cutterhead (``head``) on every record.

A moulder's heads write their records into one log, each record naming its head; a single-head
planer writes ``"main"``. A log of schema version 7 (SQLite and PostgreSQL) is read as it is by
a reader (its records are head ``"main"``'s) and brought to version 8 by a writer, the rows
before it reading ``"main"``.
"""

from __future__ import annotations

import json
import math
import sqlite3

import pytest

from controller.quality.journal import RecordSink, default_journal_path, read_journal
from controller.quality.log import (
    CSV_COLUMNS,
    DEFAULT_HEAD,
    SCHEMA_VERSION,
    QualityClass,
    QualityLog,
    QualityRecord,
    quality_class_key,
    record_from_dict,
    record_to_dict,
    utc_iso,
)
from controller.quality.schema import ADDED_IN_V8, storable
from tests.support import pg_support
from tests.support.old_logs import downgrade, old_log

pg_server = pg_support.pg_server  # the fixtures
fresh_db = pg_support.fresh_db

HEADS = ("bottom", "top")


def _rec(i: int, head: str = DEFAULT_HEAD, **kw) -> QualityRecord:
    base = dict(t_s=0.1 * i, wall_time=utc_iso(1.7e9 + 0.1 * i), seq=i, board_id=1 + i // 4,
                board_position_mm=40.0 * i, ok=True, pitch_mm=1.5 + 0.01 * i,
                uniformity_cv=0.01, mark_widths_mm=[1.5, 1.5], depth_um=4.0,
                machine_id="planer-t", head=head)
    base.update(kw)
    return QualityRecord(**base)


def _key(rec: QualityRecord) -> tuple:
    return tuple((k, tuple("nan" if isinstance(x, float) and math.isnan(x) else x for x in v)
                  if isinstance(v, tuple) else v) for k, v in vars(rec).items())


def _two_heads(n: int = 6) -> list[QualityRecord]:
    """Records of two heads interleaved as a moulder's services append them."""
    return [_rec(i, HEADS[i % 2], pitch_mm=(1.5 if i % 2 == 0 else 1.0) + 0.001 * i)
            for i in range(n)]


# --------------------------------------------------------------------------------------------
# the field


def test_head_is_the_column_version_8_added_last():
    assert SCHEMA_VERSION == 8
    assert tuple(n for n, _, _ in ADDED_IN_V8) == ("head",)
    assert CSV_COLUMNS[-1] == "head"
    assert all("NOT NULL DEFAULT 'main'" in t for _, s, p in ADDED_IN_V8 for t in (s, p))


def test_a_record_names_its_head_and_is_main_by_default():
    assert _rec(0).head == "main"
    assert QualityRecord(t_s=0.0, wall_time=utc_iso(0.0), seq=0, board_id=0,
                         board_position_mm=0.0, ok=False, error="x").head == "main"
    assert _rec(0, "top_2").head == "top_2"


@pytest.mark.parametrize("bad", ["", "Top", "2nd", "top-1", "top head", "a" * 33, None, 3])
def test_a_head_that_is_not_a_name_is_refused_naming_it(bad):
    with pytest.raises(ValueError, match=r"head must be a head name.*got"):
        _rec(0, bad)


def test_head_round_trips_through_json_and_old_json_reads_main():
    rec = _rec(1, "bottom")
    d = record_to_dict(rec)
    assert d["head"] == "bottom"
    assert _key(record_from_dict(json.loads(json.dumps(d)))) == _key(rec)
    d.pop("head")  # a journal line written before schema version 8
    assert record_from_dict(d).head == "main"


def test_a_refused_record_keeps_its_head():
    rec = _rec(2, "top", extra={"bad": object()})
    out = storable(rec)[0]
    assert not out.ok and "extra" in out.error and out.head == "top"


# --------------------------------------------------------------------------------------------
# two heads in one log


def _check_two_heads(log: QualityLog) -> None:
    recs = _two_heads()
    for r in recs:
        log.append(r)
    back = log.records()
    assert [_key(r) for r in back] == [_key(r) for r in recs]
    for head in HEADS:
        mine = log.records(head=head)
        assert [r.seq for r in mine] == [r.seq for r in recs if r.head == head]
        assert {r.head for r in mine} == {head}
    assert log.records(head="left") == []
    assert [r.seq for r in log.records(board_id=1, head="top")] == [1, 3]
    with pytest.raises(ValueError, match="head must be a head name"):
        log.records(head="Top")


def test_two_heads_records_written_and_read_back_sqlite(tmp_path):
    path = tmp_path / "q.sqlite"
    with QualityLog(path) as log:
        _check_two_heads(log)
        assert log.export_csv(tmp_path / "q.csv") == 6
    rows = (tmp_path / "q.csv").read_text().splitlines()
    assert rows[0].split(",")[-1] == "head"
    assert [row.rsplit(",", 1)[1] for row in rows[1:]] == [HEADS[i % 2] for i in range(6)]


def test_two_heads_records_written_and_read_back_postgres(fresh_db):
    with QualityLog(fresh_db) as log:
        _check_two_heads(log)


def test_each_head_keeps_its_quality_class(tmp_path):
    bottom = QualityClass("bottom-1.5", 1.5, 0.05, uniformity_max_cv=0.03)
    top = QualityClass("top-1.0", 1.0, 0.03)
    with QualityLog(tmp_path / "q.sqlite") as log:
        log.set_quality_class(bottom, head="bottom")
        log.set_quality_class(top, head="top")
        assert log.quality_class() is None  # the single head's key was not written
        assert log.quality_class("bottom") == bottom and log.quality_class("top") == top
        log.set_quality_class(top)
        assert log.quality_class("main") == top
    assert quality_class_key() == "quality_class"
    assert quality_class_key("top") == "quality_class:top"


def test_each_head_other_than_main_has_its_own_journal(tmp_path):
    log_path = tmp_path / "run.db"
    assert default_journal_path(log_path) == tmp_path / "run.db.journal.jsonl"
    assert default_journal_path(log_path, head="main") == tmp_path / "run.db.journal.jsonl"
    assert default_journal_path(log_path, head="top") == tmp_path / "run.db.top.journal.jsonl"
    url = "postgresql://qa@db.example:5433/planer"
    want = "qa@db.example_5433_planer.top.journal.jsonl"
    assert default_journal_path(url, head="top").name == want
    with pytest.raises(ValueError, match="head"):
        default_journal_path(log_path, head="../x")


def test_a_journalled_record_keeps_its_head(tmp_path):
    class Refusing:  # a log that takes nothing: the records stay in the journal
        path = tmp_path / "run.db"

        def append(self, record, *, uid=None):
            raise OSError("disk full")

    journal = default_journal_path(tmp_path / "run.db", head="top")
    sink = RecordSink(Refusing(), journal_path=journal)
    sink.append(_rec(0, "top"))
    sink.append(_rec(1, "top"))
    held, bad = read_journal(journal)
    assert bad == 0 and [r.head for r in held] == ["top", "top"]
    sink.close()


# --------------------------------------------------------------------------------------------
# migration from version 7


def test_version_7_log_is_read_as_main_and_migrated_by_a_writer(tmp_path):
    path = tmp_path / "q.sqlite"
    old = [_rec(i) for i in range(3)]
    with QualityLog(path) as log:
        for r in old:
            log.append(r)
    with sqlite3.connect(path) as conn:
        assert downgrade(conn.execute, 7) == ("head",)
    with QualityLog(path, create=False) as reader:  # a reader changes nothing
        assert reader.schema_version == 7
        assert [_key(r) for r in reader.records()] == [_key(r) for r in old]
        assert [r.seq for r in reader.records(head="main")] == [0, 1, 2]
        assert reader.records(head="top") == []
    with sqlite3.connect(path) as conn:
        assert "head" not in {r[1] for r in conn.execute("PRAGMA table_info(records)")}
    new = _rec(3, "top")
    with QualityLog(path) as writer:
        assert writer.schema_version == SCHEMA_VERSION
        writer.append(new)
        back = writer.records()
        assert [r.seq for r in writer.records(head="main")] == [0, 1, 2]
    assert [r.head for r in back] == ["main", "main", "main", "top"]
    assert [_key(r) for r in back] == [_key(r) for r in old + [new]]
    with sqlite3.connect(path) as conn:
        cols = tuple(r[1] for r in conn.execute("PRAGMA table_info(records)"))
        heads = [r[0] for r in conn.execute("SELECT head FROM records ORDER BY record_id")]
    assert cols == CSV_COLUMNS
    assert heads == ["main", "main", "main", "top"]  # stored, not only read so


def test_version_7_database_is_read_as_main_and_migrated_by_a_writer(fresh_db):
    import psycopg

    old = [_rec(i) for i in range(3)]
    old_log(fresh_db, old, 7)
    with QualityLog(fresh_db, create=False) as reader:
        assert reader.schema_version == 7
        assert [_key(r) for r in reader.records()] == [_key(r) for r in old]
        assert reader.records(head="bottom") == []
    recs = [_rec(3, "bottom"), _rec(4, "top")]
    with QualityLog(fresh_db) as writer:
        assert writer.schema_version == SCHEMA_VERSION
        writer.append_many(recs)
        back = writer.records()
        assert [r.seq for r in writer.records(head="bottom")] == [3]
    assert [_key(r) for r in back] == [_key(r) for r in old + recs]
    with psycopg.connect(fresh_db, autocommit=True) as conn:
        heads = [r[0] for r in conn.execute("SELECT head FROM records ORDER BY record_id")]
        nullable = conn.execute("SELECT is_nullable FROM information_schema.columns WHERE "
                                "table_name = 'records' AND column_name = 'head'").fetchone()
    assert heads == ["main", "main", "main", "bottom", "top"]
    assert nullable == ("NO",)

