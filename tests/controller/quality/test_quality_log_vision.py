"""Quality log, schema version 4: orientation, self-calibration and kinematic depth columns.

Tables of records and of vision results: validation, the fields a measurement gives, SQLite and
CSV round trips with the same names everywhere, the journal's JSON, the migration of a
version 3 log (read as it is by a reader, brought to version 4 by a writer).
"""

from __future__ import annotations

import csv
import dataclasses
import math
import sqlite3
from pathlib import Path
from types import SimpleNamespace

import pytest

from controller.quality.log import (
    CALIBRATION_FIELDS,
    CALIBRATION_STATES,
    CSV_COLUMNS,
    SCHEMA_VERSION,
    QualityLog,
    QualityRecord,
    record_from_dict,
    record_to_dict,
    record_to_json,
    storable,
    utc_iso,
    vision_fields,
)
from controller.quality.schema import ADDED_IN_V4, columns_added_since
from tests.support.old_logs import downgrade

NEW = ("roll_deg", "roll_confidence", "calibration_state", *CALIBRATION_FIELDS,
       "kinematic_depth_um", "uncalibrated_depth_um")


def _rec(i: int = 0, **kw) -> QualityRecord:
    base = dict(
        t_s=0.1 * i, wall_time=utc_iso(1.7e9 + 0.1 * i), seq=i, board_id=1 + i // 4,
        board_position_mm=40.0 * i, ok=True, pitch_mm=1.5, mark_widths_mm=[1.5, 1.5, 1.5, 1.5],
        uniformity_cv=0.01, depth_um=4.7, shift_px=42.5, confidence=0.9, machine_id="planer-t",
    )
    base.update(kw)
    return QualityRecord(**base)


def _vision(i: int) -> dict:
    """Vision fields of record ``i``: every state, values of varied size, some missing."""
    state = CALIBRATION_STATES[i % 3]
    out = {"roll_deg": 0.4 - 0.013 * i, "roll_confidence": (0.97, None)[i % 2],
           "calibration_state": state}
    if state != "off":
        out.update(calibration_gain=0.7 + 0.01 * i, calibration_gain_confidence=0.1 * (i % 10),
                   calibration_scatter_mm=(0.25, None)[i % 2], calibration_scatter_fraction=0.5,
                   calibration_scatter_confidence=0.3)
        out.update(kinematic_depth_um=4.69 + 0.001 * i, uncalibrated_depth_um=3.1 + 0.1 * i)
    return out


def _key(rec: QualityRecord) -> tuple:
    return tuple((k, tuple("nan" if math.isnan(x) else x for x in v) if isinstance(v, tuple)
                  else v) for k, v in vars(rec).items())


# --------------------------------------------------------------------------------------------
# the record


def test_new_fields_are_columns_and_csv_names_in_field_order():
    assert SCHEMA_VERSION >= 4
    added_later = len(columns_added_since(4))  # 5, 6, ... follow
    assert CSV_COLUMNS[-len(NEW) - added_later:-added_later] == NEW
    assert tuple(name for name, _, _ in ADDED_IN_V4) == NEW
    assert {f.name for f in dataclasses.fields(QualityRecord)} >= set(NEW)


@pytest.mark.parametrize(
    "kw, name",
    [
        (dict(calibration_state="on"), "calibration_state"),
        (dict(calibration_state="Applied"), "calibration_state"),
        (dict(calibration_state=1), "calibration_state"),
        (dict(calibration_gain=0.9), "calibration_gain"),  # a value without a state
        (dict(calibration_state="off", calibration_scatter_mm=0.2), "calibration_scatter_mm"),
        (dict(calibration_state="applied", calibration_gain=float("inf")), "calibration_gain"),
        (dict(roll_deg="0.4deg"), "roll_deg"),
        (dict(roll_confidence=float("-inf")), "roll_confidence"),
        (dict(kinematic_depth_um=[4.0]), "kinematic_depth_um"),
        (dict(ok=False, error="implausible: pitch", pitch_mm=None, mark_widths_mm=(),
              uniformity_cv=None, depth_um=None, kinematic_depth_um=4.0), "kinematic_depth_um"),
        (dict(ok=False, error="implausible: pitch", pitch_mm=None, mark_widths_mm=(),
              uniformity_cv=None, depth_um=None, uncalibrated_depth_um=4.0),
         "uncalibrated_depth_um"),
    ],
)
def test_bad_vision_fields_are_refused_naming_the_field(kw, name):
    with pytest.raises(ValueError, match=name):
        _rec(**kw)


@pytest.mark.parametrize("state", CALIBRATION_STATES)
def test_good_vision_fields_and_nan_as_not_measured(state):
    values = {} if state == "off" else {n: 0.5 for n in CALIBRATION_FIELDS}
    r = _rec(roll_deg=-2.5, roll_confidence=float("nan"), calibration_state=state,
             kinematic_depth_um=float("nan"), **values)
    assert r.roll_deg == -2.5 and r.roll_confidence is None and r.kinematic_depth_um is None
    assert r.calibration_state == state
    assert all(getattr(r, n) == (None if state == "off" else 0.5) for n in CALIBRATION_FIELDS)
    # a failed pair keeps its orientation and calibration (diagnostics), no depths
    f = _rec(ok=False, error="implausible: 1 complete marks", pitch_mm=None, mark_widths_mm=(),
             uniformity_cv=None, depth_um=None, roll_deg=0.4, calibration_state=state, **values)
    assert f.roll_deg == 0.4 and f.calibration_state == state


def test_a_refused_record_keeps_its_orientation_and_calibration():
    r = _rec(board_id=2**64, **_vision(1))
    out = storable(r)[0]
    assert not out.ok and "board_id" in out.error
    for name in ("roll_deg", "roll_confidence", "calibration_state", *CALIBRATION_FIELDS):
        assert getattr(out, name) == getattr(r, name)
    assert out.kinematic_depth_um is None  # a failed record carries no metrics


# --------------------------------------------------------------------------------------------
# what a measurement gives


def _cal(trusted, **kw):
    base = dict(gain=0.8, gain_confidence=0.9, scatter_mm=0.3, scatter_fraction=0.5,
                scatter_confidence=0.7, trusted=trusted, deblurred=False)
    base.update(kw)
    return SimpleNamespace(**base)


@pytest.mark.parametrize(
    "meas, ok, expected",
    [
        # the self-calibration off (no cutting radius): state off, no values
        (SimpleNamespace(roll_deg=0.41, roll_confidence=0.93, calibration=None,
                         kinematic_depth_um=math.nan, uncalibrated_depth_um=math.nan), True,
         dict(roll_deg=0.41, roll_confidence=0.93, calibration_state="off",
              kinematic_depth_um=None, uncalibrated_depth_um=None)),
        (SimpleNamespace(roll_deg=-1.0, roll_confidence=0.5, calibration=_cal(True),
                         kinematic_depth_um=4.7, uncalibrated_depth_um=3.3), True,
         dict(roll_deg=-1.0, roll_confidence=0.5, calibration_state="applied",
              calibration_gain=0.8, calibration_gain_confidence=0.9,
              calibration_scatter_mm=0.3, calibration_scatter_fraction=0.5,
              calibration_scatter_confidence=0.7, kinematic_depth_um=4.7,
              uncalibrated_depth_um=3.3)),
        (SimpleNamespace(roll_deg=0.0, roll_confidence=math.nan,
                         calibration=_cal(False, scatter_mm=math.nan), kinematic_depth_um=4.7,
                         uncalibrated_depth_um=3.3), False,  # failed: no depths
         dict(roll_deg=0.0, roll_confidence=None, calibration_state="untrusted",
              calibration_gain=0.8, calibration_gain_confidence=0.9,
              calibration_scatter_mm=None, calibration_scatter_fraction=0.5,
              calibration_scatter_confidence=0.7)),
        (SimpleNamespace(pitch_mm=1.5), True, {}),  # a measurer without these: nothing
    ],
)
def test_vision_fields_of_a_measurement(meas, ok, expected):
    got = vision_fields(meas, ok=ok)
    assert got == expected
    fields = dict(ok=True) if ok else dict(ok=False, error="implausible: x", pitch_mm=None,
                                            mark_widths_mm=(), uniformity_cv=None, depth_um=None)
    _rec(**fields, **got)  # the record takes them


# --------------------------------------------------------------------------------------------
# storage


def test_sqlite_csv_and_journal_round_trip_the_new_fields(tmp_path):
    recs = [_rec(i, **_vision(i)) for i in range(9)]
    recs.append(_rec(9, ok=False, error="registration failed: confidence 0.1", pitch_mm=None,
                     mark_widths_mm=(), uniformity_cv=None, depth_um=None,
                     roll_deg=0.38, calibration_state="untrusted", calibration_gain=2.0))
    path = tmp_path / "q.sqlite"
    with QualityLog(path) as log:
        for r in recs:
            log.append(r)
        back = log.records()
        assert log.export_csv(tmp_path / "q.csv") == len(recs)
    assert [_key(r) for r in back] == [_key(r) for r in recs]
    assert [_key(record_from_dict(record_to_dict(r))) for r in recs] == [_key(r) for r in recs]
    with (tmp_path / "q.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == CSV_COLUMNS
    for row, r in zip(rows, recs, strict=True):
        for name in NEW:
            v = getattr(r, name)
            if v is None:
                assert row[name] == ""
            elif isinstance(v, str):
                assert row[name] == v
            else:
                assert float(row[name]) == pytest.approx(v, rel=1e-14)
    # a journal line written before version 4 (no such keys) reads back with None
    old = record_to_dict(recs[0])
    for name in NEW:
        old.pop(name)
    assert all(getattr(record_from_dict(old), n) is None for n in NEW)
    assert '"calibration_state": "off"' in record_to_json(recs[0])


def test_the_database_refuses_a_state_it_does_not_know(tmp_path):
    path = tmp_path / "q.sqlite"
    QualityLog(path).close()
    with sqlite3.connect(path) as conn, pytest.raises(sqlite3.IntegrityError):
        conn.execute("INSERT INTO records (t_s, wall_time_utc, seq, board_id, "
                     "board_position_mm, ok, mark_widths_mm, piezo_offsets_um, extra_json, "
                     "calibration_state) VALUES (0, 'x', 0, 0, 0, 1, '[]', '[]', '{}', 'on')")


def make_v3_log(path: Path, recs: list[QualityRecord]) -> None:
    """A log of schema version 3 holding ``recs`` (their version 4 fields are not kept)."""
    with QualityLog(path) as log:
        for r in recs:
            log.append(r)
    with sqlite3.connect(path) as conn:
        downgrade(conn.execute, 3)


def test_version_3_log_is_read_as_is_and_migrated_by_a_writer(tmp_path):
    path = tmp_path / "q.sqlite"
    old = [_rec(i) for i in range(3)]
    make_v3_log(path, old)
    with QualityLog(path, create=False) as reader:  # a reader changes nothing
        assert reader.schema_version == 3
        assert [_key(r) for r in reader.records()] == [_key(r) for r in old]
    new = _rec(3, **_vision(4))
    with QualityLog(path) as writer:
        assert writer.schema_version == SCHEMA_VERSION
        writer.append(new)
        back = writer.records()
        assert writer.export_csv(tmp_path / "q.csv") == 4
    assert [_key(r) for r in back] == [_key(r) for r in old + [new]]
    assert all(getattr(r, n) is None for r in back[:3] for n in NEW)
    with sqlite3.connect(path) as conn:
        cols = tuple(r[1] for r in conn.execute("PRAGMA table_info(records)"))
    assert cols == CSV_COLUMNS
    header = (tmp_path / "q.csv").read_text().splitlines()[0]
    assert header == ",".join(CSV_COLUMNS)
