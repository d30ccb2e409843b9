"""Quality log, schema version 5: the ``flag_reason`` of a pair kept out of the control loops.

A flagged pair is a failed record (``ok=False``) that names why it was flagged; a log of schema
version 4 (SQLite and PostgreSQL) is read as it is by a reader and brought to version 5 by a
writer, its old records reading ``flag_reason = None``.
"""

from __future__ import annotations

import dataclasses
import math
import sqlite3

import pytest

from controller.quality.log import CSV_COLUMNS, SCHEMA_VERSION, QualityLog, QualityRecord, utc_iso
from controller.quality.schema import (
    ADDED_IN_V5,
    RecordRefusedError,
    check_storable,
    columns_added_since,
    record_from_dict,
    record_to_dict,
    storable,
)
from tests.support import pg_support
from tests.support.old_logs import old_log

pg_server = pg_support.pg_server  # the fixtures
fresh_db = pg_support.fresh_db

REASON = "pitch 1.62 mm is 8.0 % off V/(nZ) 1.500 mm (tolerance 1.2 %)"


def _rec(i: int = 0, **kw) -> QualityRecord:
    base = dict(t_s=0.1 * i, wall_time=utc_iso(1.7e9 + 0.1 * i), seq=i, board_id=1,
                board_position_mm=40.0 * i, ok=True, pitch_mm=1.5, uniformity_cv=0.01,
                mark_widths_mm=[1.5, 1.5], depth_um=4.0, machine_id="planer-t")
    base.update(kw)
    return QualityRecord(**base)


def _flagged(i: int, reason: str = REASON) -> QualityRecord:
    return _rec(i, ok=False, error=f"flagged: {reason}", pitch_mm=None, uniformity_cv=None,
                mark_widths_mm=(), depth_um=None, shift_px=20.1, confidence=0.3,
                flag_reason=reason)


def _key(rec: QualityRecord) -> tuple:
    return tuple((k, tuple("nan" if math.isnan(x) else x for x in v) if isinstance(v, tuple)
                  else v) for k, v in vars(rec).items())


def test_flag_reason_is_the_column_version_5_added():
    assert SCHEMA_VERSION >= 5
    assert tuple(n for n, _, _ in ADDED_IN_V5) == ("flag_reason",)
    assert CSV_COLUMNS[-1 - len(columns_added_since(5))] == "flag_reason"  # 6.. follow


@pytest.mark.parametrize("kw, message", [
    ({"flag_reason": REASON}, "ok must be false"),                      # flagged yet ok
    ({"ok": False, "error": "flagged: x", "flag_reason": ""}, "flag_reason"),
    ({"ok": False, "error": "flagged: x", "flag_reason": 3}, "flag_reason"),
])
def test_bad_flag_reasons_are_refused_naming_the_field(kw, message):
    metrics = {} if kw.get("ok", True) else dict(pitch_mm=None, uniformity_cv=None,
                                                  mark_widths_mm=(), depth_um=None)
    with pytest.raises(ValueError, match=message):
        _rec(**{**metrics, **kw})


def test_flagged_record_round_trips_through_json_and_the_log(tmp_path):
    rec = _flagged(2)
    assert record_from_dict(record_to_dict(rec)) == rec
    with QualityLog(tmp_path / "q.sqlite") as log:
        log.append(_rec(1))
        log.append(rec)
        back = log.records()
        assert log.export_csv(tmp_path / "q.csv") == 2
    assert [r.flag_reason for r in back] == [None, REASON]
    assert back[1].error == f"flagged: {REASON}" and not back[1].ok
    header = (tmp_path / "q.csv").read_text().splitlines()[0].split(",")
    assert "flag_reason" in header


def test_flag_reason_that_is_not_unicode_is_refused_and_kept_escaped():
    rec = dataclasses.replace(_flagged(0), flag_reason="bad \udcff text")
    with pytest.raises(RecordRefusedError) as info:
        check_storable(rec)
    assert info.value.field == "flag_reason"
    kept = storable(rec)[0]
    check_storable(kept)
    assert kept.flag_reason == "bad \\udcff text" and "flag_reason" in kept.extra["refused"]


def _make_v4_log(path, recs) -> None:
    old_log(path, recs, 4)


def test_version_4_log_is_read_as_is_and_migrated_by_a_writer(tmp_path):
    path = tmp_path / "q.sqlite"
    old = [_rec(i) for i in range(3)]
    _make_v4_log(path, old)
    with QualityLog(path, create=False) as reader:  # a reader changes nothing
        assert reader.schema_version == 4
        assert [_key(r) for r in reader.records()] == [_key(r) for r in old]
    with QualityLog(path) as writer:
        assert writer.schema_version == SCHEMA_VERSION
        writer.append(_flagged(3))
        back = writer.records()
    assert [r.flag_reason for r in back] == [None, None, None, REASON]
    with sqlite3.connect(path) as conn:
        cols = tuple(r[1] for r in conn.execute("PRAGMA table_info(records)"))
    assert cols == CSV_COLUMNS


def test_version_4_database_is_migrated_by_a_writer(fresh_db):

    old = [_rec(i) for i in range(3)]
    old_log(fresh_db, old, 4)
    with QualityLog(fresh_db, create=False) as reader:
        assert reader.schema_version == 4
        assert [_key(r) for r in reader.records()] == [_key(r) for r in old]
    with QualityLog(fresh_db) as writer:
        assert writer.schema_version == SCHEMA_VERSION
        writer.append(_flagged(3))
        back = writer.records()
    assert [_key(r) for r in back[:3]] == [_key(r) for r in old]
    assert back[3] == dataclasses.replace(_flagged(3), machine_id=back[3].machine_id)
