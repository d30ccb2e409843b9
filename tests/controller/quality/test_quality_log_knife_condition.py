"""Quality log, schema version 6: the knife condition with every record.

Each record carries the service's knife condition in force when it was made: the board
travelled, each knife's wear (drift of its offset per metre of board) and offset-table reserve,
and the jointing forecast (state; when due, in m, boards and hours, and the knife). A log of
schema version 5 (SQLite and PostgreSQL) is read as it is by a reader and brought to version 6
by a writer, its old records reading no knife condition.
"""

from __future__ import annotations

import dataclasses
import math
import sqlite3

import pytest

from controller.laws.knife_condition import JointingState
from controller.quality.log import CSV_COLUMNS, SCHEMA_VERSION, QualityLog, QualityRecord, utc_iso
from controller.quality.schema import (
    ADDED_IN_V6,
    JOINTING_STATES,
    KNIFE_CONDITION_FIELDS,
    columns_added_since,
    knife_condition_fields,
    record_from_dict,
    record_to_dict,
    storable,
)
from tests.support import pg_support
from tests.support.old_logs import old_log

pg_server = pg_support.pg_server  # the fixtures
fresh_db = pg_support.fresh_db

#: What ``KnifeConditionWatch.describe()`` gives (knife 1 wears back, due in 12.5 boards).
DESCRIBED = {
    "board_travel_m": 21.25,
    "knives": [
        {"knife": 0, "offset_um": -4.1, "drift_um_per_m": -0.21, "reserve_um": 1.9},
        {"knife": 1, "offset_um": 1.3, "drift_um_per_m": 0.07, "reserve_um": 4.7},
        {"knife": 2, "offset_um": 1.4, "drift_um_per_m": 0.07, "reserve_um": 4.6},
        {"knife": 3, "offset_um": 1.4, "drift_um_per_m": 0.07, "reserve_um": 4.6},
    ],
    "due_in_m": 50.0, "due_in_boards": 12.5, "due_in_h": 0.0231, "knife": 0,
    "text": "jointing due in 12 boards / 0.02 h at this feed (knife 1)",
    "state": "due", "t_s": 35.2,
}


def _rec(i: int = 0, **kw) -> QualityRecord:
    base = dict(t_s=0.1 * i, wall_time=utc_iso(1.7e9 + 0.1 * i), seq=i, board_id=1,
                board_position_mm=40.0 * i, ok=True, pitch_mm=1.5, uniformity_cv=0.01,
                mark_widths_mm=[1.5, 1.5, 1.5, 1.5], depth_um=4.0, machine_id="planer-t")
    base.update(kw)
    return QualityRecord(**base)


def _key(rec: QualityRecord) -> tuple:
    return tuple((k, tuple("nan" if math.isnan(x) else x for x in v) if isinstance(v, tuple)
                  else v) for k, v in vars(rec).items())


def test_the_states_are_the_forecasts_and_the_columns_come_in_version_6():
    assert SCHEMA_VERSION >= 6
    assert JOINTING_STATES == tuple(s.value for s in JointingState)
    assert tuple(n for n, _, _ in ADDED_IN_V6) == KNIFE_CONDITION_FIELDS
    later = len(columns_added_since(6))  # version 7's and 8's columns follow
    assert CSV_COLUMNS[-len(KNIFE_CONDITION_FIELDS) - later:-later] == KNIFE_CONDITION_FIELDS


def test_the_described_condition_becomes_the_record_fields():
    f = knife_condition_fields(DESCRIBED)
    assert f == {
        "board_travel_m": 21.25,
        "knife_drift_um_per_m": (-0.21, 0.07, 0.07, 0.07),
        "knife_reserve_um": (1.9, 4.7, 4.6, 4.6),
        "jointing_state": "due", "jointing_due_m": 50.0, "jointing_due_boards": 12.5,
        "jointing_due_h": 0.0231, "jointing_knife": 0,
    }
    assert knife_condition_fields(None) == {}  # no table applied yet: no field


def test_while_fitting_the_drift_is_nan_and_no_figure_is_given():
    fitting = {**DESCRIBED, "state": "fitting", "due_in_m": None, "due_in_boards": None,
               "due_in_h": None, "knife": None,
               "knives": [{**k, "drift_um_per_m": None} for k in DESCRIBED["knives"]]}
    f = knife_condition_fields(fitting)
    assert f["jointing_state"] == "fitting" and "jointing_due_m" not in f
    assert all(math.isnan(v) for v in f["knife_drift_um_per_m"])
    rec = _rec(**f)  # a valid record
    assert rec.jointing_due_m is None and rec.knife_reserve_um == (1.9, 4.7, 4.6, 4.6)


@pytest.mark.parametrize("kw, name", [
    ({"jointing_state": "soon"}, "jointing_state"),
    ({"jointing_state": "not_due", "jointing_due_m": 3.0}, "jointing_due_m"),
    ({"jointing_knife": 1}, "jointing_knife"),  # a knife named, no forecast
    ({"jointing_state": "due", "jointing_knife": 9}, "jointing_knife"),
    ({"jointing_state": "due", "jointing_due_h": -1.0}, "jointing_due_h"),
    ({"knife_reserve_um": "1;2"}, "knife_reserve_um"),
])
def test_bad_knife_condition_fields_are_refused_naming_the_field(kw, name):
    with pytest.raises(ValueError, match=name):
        _rec(**kw)


def test_a_failed_pair_carries_the_condition_in_force_and_it_round_trips(tmp_path):
    cond = knife_condition_fields(DESCRIBED)
    recs = [_rec(0, **cond),
            _rec(1, ok=False, error="registration failed: confidence 0.2", pitch_mm=None,
                 uniformity_cv=None, mark_widths_mm=(), depth_um=None, **cond),
            _rec(2)]  # before the first table: none
    assert [record_from_dict(record_to_dict(r)) for r in recs] == recs
    assert storable(recs[1])[0] is recs[1]
    path = tmp_path / "q.sqlite"
    with QualityLog(path) as log:
        for r in recs:
            log.append(r)
        back = log.records()
        assert log.export_csv(tmp_path / "q.csv") == 3
    assert [_key(r) for r in back] == [_key(r) for r in recs]
    assert back[2].knife_drift_um_per_m == () and back[2].jointing_state is None
    header, first, *_ = (tmp_path / "q.csv").read_text().splitlines()
    row = dict(zip(header.split(","), first.split(","), strict=False))
    assert row["knife_drift_um_per_m"] == "-0.21;0.07;0.07;0.07"
    assert row["jointing_due_boards"] == "12.5" and row["jointing_state"] == "due"



def test_version_5_log_is_read_as_is_and_migrated_by_a_writer(tmp_path):
    path = tmp_path / "q.sqlite"
    old = [_rec(i) for i in range(3)]
    old_log(path, old, 5)
    with QualityLog(path, create=False) as reader:  # a reader changes nothing
        assert reader.schema_version == 5
        assert [_key(r) for r in reader.records()] == [_key(r) for r in old]
    new = _rec(3, **knife_condition_fields(DESCRIBED))
    with QualityLog(path) as writer:
        assert writer.schema_version == SCHEMA_VERSION
        writer.append(new)
        back = writer.records()
    assert [_key(r) for r in back] == [_key(r) for r in old + [new]]
    with sqlite3.connect(path) as conn:
        cols = tuple(r[1] for r in conn.execute("PRAGMA table_info(records)"))
        # the column's check holds in the file itself, not only in the record
        with pytest.raises(sqlite3.IntegrityError):
            conn.execute("UPDATE records SET jointing_state = 'soon'")
    assert cols == CSV_COLUMNS


def test_version_5_database_is_migrated_by_a_writer_and_round_trips(fresh_db):

    old = [_rec(i) for i in range(3)]
    old_log(fresh_db, old, 5)
    with QualityLog(fresh_db, create=False) as reader:
        assert reader.schema_version == 5
        assert [_key(r) for r in reader.records()] == [_key(r) for r in old]
    new = _rec(3, **knife_condition_fields(DESCRIBED))
    with QualityLog(fresh_db) as writer:
        assert writer.schema_version == SCHEMA_VERSION
        writer.append(new)
        back = writer.records()
    assert [_key(r) for r in back[:3]] == [_key(r) for r in old]
    assert back[3] == dataclasses.replace(new, machine_id=back[3].machine_id)
    assert back[3].jointing_knife == 0 and back[3].knife_reserve_um == (1.9, 4.7, 4.6, 4.6)
