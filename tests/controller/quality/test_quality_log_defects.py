"""Quality log, schema version 7: planing defects and the D1666 grade with every record.

A pair measured with ``[quality] defects = true`` carries its defects (the contract's objects),
its grade and reason; every record of a board carries the board's grade and defect counts over
its pairs so far (the board's last record: the whole board's). A log of schema version 6 (SQLite
and PostgreSQL) is read as it is by a reader and brought to version 7 by a writer, its old
records reading no defects.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sqlite3
from types import SimpleNamespace

import numpy as np
import pytest

from controller.quality.defect_fields import (
    DEFECT_KEYS,
    DEFECT_KINDS,
    BoardGrades,
    count_kinds,
    defects_of,
    pair_fields,
)
from controller.quality.log import CSV_COLUMNS, SCHEMA_VERSION, QualityLog, QualityRecord, utc_iso
from controller.quality.schema import (
    ADDED_IN_V7,
    columns_added_since,
    record_from_dict,
    record_to_dict,
    storable,
)
from tests.support import pg_support
from tests.support.old_logs import old_log
from vision.defects.detect import Defect, DefectKind
from vision.defects.grading import grade_board, grade_pair, judge_snipe

pg_server = pg_support.pg_server  # the fixtures
fresh_db = pg_support.fresh_db

TORN = Defect(DefectKind.TORN_GRAIN, 12.0, 8.5, 12.5, 3.0, 180.0, 0.9)  # severity 4
NICK = Defect(DefectKind.KNIFE_NICK, 20.0, 4.0, 30.0, 0.4, 8.0, 0.7)  # severity 2
CHATTER = Defect(DefectKind.CHATTER, 16.0, 10.0, 32.0, 20.0, None, 0.5)  # no depth, sev 1


def _fields(found: list[Defect]) -> dict:
    g = grade_pair(found)
    return {"defects": tuple(d.to_json() for d in found), "grade": g.grade,
            "grade_reason": g.reason}


def _rec(i: int = 0, board: int = 1, **kw) -> QualityRecord:
    base = dict(t_s=0.1 * i, wall_time=utc_iso(1.7e9 + 0.1 * i), seq=i, board_id=board,
                board_position_mm=40.0 * i, ok=True, pitch_mm=1.5, uniformity_cv=0.01,
                mark_widths_mm=[1.5, 1.5, 1.5, 1.5], depth_um=4.0, machine_id="planer-t")
    base.update(kw)
    return QualityRecord(**base)


def _key(rec: QualityRecord) -> tuple:
    return tuple((k, tuple("nan" if isinstance(x, float) and math.isnan(x) else x for x in v)
                  if isinstance(v, tuple) else v) for k, v in vars(rec).items())


def test_version_7_adds_the_defect_columns_last():
    assert SCHEMA_VERSION >= 7
    names = ("defects", "grade", "grade_reason", "board_grade", "board_grade_reason",
             "board_defect_counts")
    assert tuple(n for n, _, _ in ADDED_IN_V7) == names
    later = len(columns_added_since(7))  # version 8's column follows
    assert CSV_COLUMNS[-len(names) - later:-later] == names
    assert DEFECT_KINDS == ("torn_grain", "raised_grain", "fuzzy_grain", "chip_mark",
                            "knife_nick", "chatter", "snipe")
    assert set(TORN.to_json()) == set(DEFECT_KEYS)


def test_a_measurement_gives_the_contract_objects_and_its_grade():
    m = SimpleNamespace(defects=(TORN, CHATTER), grade=5, grade_reason="grade 5: worst ...")
    f = pair_fields(m)
    assert f["grade"] == 5 and f["grade_reason"] == "grade 5: worst ..."
    assert f["defects"][0] == {"kind": "torn_grain", "x_mm": 12.0, "y_mm": 8.5,
                               "length_mm": 12.5, "width_mm": 3.0, "depth_um": 180.0,
                               "confidence": 0.9}
    assert f["defects"][1]["depth_um"] is None
    assert pair_fields(SimpleNamespace(defects=None, grade=None)) == {}  # not looked for
    assert pair_fields(SimpleNamespace()) == {}
    clean = pair_fields(SimpleNamespace(defects=(), grade=1, grade_reason="defect-free"))
    assert clean["defects"] == () and clean["grade"] == 1


@pytest.mark.parametrize("kw, message", [
    ({"defects": ()}, "go together"),                                     # no grade
    ({"grade": 2, "grade_reason": "x"}, "go together"),                   # no defects
    ({"defects": (), "grade": 6, "grade_reason": "x"}, "grade must be a D1666 grade"),
    ({"defects": (), "grade": True, "grade_reason": "x"}, "grade must be a D1666 grade"),
    ({"defects": ({**TORN.to_json(), "kind": "knot"},), "grade": 5, "grade_reason": "x"},
     "defects[0].kind must be one of"),
    ({"defects": ({**TORN.to_json(), "x_mm": math.inf},), "grade": 5, "grade_reason": "x"},
     "defects[0].x_mm must be finite"),
    ({"defects": ({**TORN.to_json(), "confidence": 1.5},), "grade": 5, "grade_reason": "x"},
     "defects[0].confidence must be in"),
    ({"defects": ({k: v for k, v in TORN.to_json().items() if k != "y_mm"},), "grade": 5,
      "grade_reason": "x"}, "'y_mm' is missing"),
    ({"defects": "torn", "grade": 5, "grade_reason": "x"}, "defects must be a list"),
    ({"board_grade": 3}, "go together"),
    ({"board_grade": 3, "board_grade_reason": "x",
      "board_defect_counts": {"torn_grain": 1}}, "a count for each of"),
    ({"board_grade": 3, "board_grade_reason": "x", "board_id": 0,
      "board_defect_counts": dict.fromkeys(DEFECT_KINDS, 0)}, "board_id must be > 0"),
    ({"board_grade": 3, "board_grade_reason": "x",
      "board_defect_counts": {**dict.fromkeys(DEFECT_KINDS, 0), "snipe": -1}},
     "board_defect_counts['snipe'] must be a count"),
])
def test_invalid_defect_fields_are_refused_naming_them(kw, message):
    board = kw.pop("board_id", 1)
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("(", r"\(")):
        _rec(0, board=board, **kw)


def test_the_board_grade_is_the_grading_rule_over_the_boards_pairs_so_far():
    pairs = [[], [NICK], [], [TORN, NICK], [CHATTER], [], [NICK]]
    grades = BoardGrades()
    for i, found in enumerate(pairs):
        f = grades.add(7, tuple(d.to_json() for d in found))
        want = grade_board(pairs[:i + 1])
        assert (f["board_grade"], f["board_grade_reason"]) == (want.grade, want.reason)
    # the whole board: the torn pit's pair (grade 5) is its worst
    assert f["board_grade"] == 5
    assert f["board_defect_counts"] == {**dict.fromkeys(DEFECT_KINDS, 0), "torn_grain": 1,
                                        "knife_nick": 3, "chatter": 1}
    # the next board starts afresh; pairs not looked for or on no board add nothing
    assert grades.add(8, None) == {}
    assert grades.add(0, ()) == {}
    f = grades.add(8, ())
    assert f["board_grade"] == 1 and sum(f["board_defect_counts"].values()) == 0


def test_widespread_defects_make_the_board_one_step_worse():
    grades = BoardGrades()
    for _ in range(3):  # a nick on every pair: moderate (3), on more than a quarter: 4
        f = grades.add(2, (NICK.to_json(),))
    assert f["board_grade"] == 4 and "one step worse" in f["board_grade_reason"]


def _board_records() -> list[QualityRecord]:
    grades = BoardGrades()
    recs = []
    for i, found in enumerate([[TORN], [], [CHATTER, NICK]]):
        pf = _fields(found)
        recs.append(_rec(i, **pf, **grades.add(1, pf["defects"])))
    recs.append(_rec(3))  # a pair the defects were not looked for on
    return recs


def test_records_round_trip_through_the_log_the_json_and_the_csv(tmp_path):
    recs = _board_records()
    assert [record_from_dict(json.loads(json.dumps(record_to_dict(r)))) for r in recs] == recs
    with QualityLog(tmp_path / "q.sqlite") as log:
        for r in recs:
            log.append(r)
        back = log.records()
        log.export_csv(tmp_path / "q.csv")
    assert [_key(r) for r in back] == [_key(r) for r in recs]
    assert back[0].defects[0]["kind"] == "torn_grain" and back[1].defects == ()
    assert back[3].defects is None and back[3].board_grade is None
    assert back[2].board_defect_counts["knife_nick"] == 1
    import csv

    rows = list(csv.DictReader((tmp_path / "q.csv").open()))
    assert json.loads(rows[2]["defects"])[1]["kind"] == "knife_nick"
    assert rows[2]["grade"] == str(recs[2].grade) and rows[3]["defects"] == ""
    assert json.loads(rows[2]["board_defect_counts"])["torn_grain"] == 1
    with sqlite3.connect(tmp_path / "q.sqlite") as conn, pytest.raises(sqlite3.IntegrityError):
        conn.execute("UPDATE records SET grade = 6")  # the column's check is in the file



def test_version_6_log_is_read_as_is_and_migrated_by_a_writer(tmp_path):
    path = tmp_path / "q.sqlite"
    old = [_rec(i) for i in range(3)]
    old_log(path, old, 6)
    with QualityLog(path, create=False) as reader:
        assert reader.schema_version == 6
        assert [_key(r) for r in reader.records()] == [_key(r) for r in old]
    new = _board_records()[0]
    with QualityLog(path) as writer:
        assert writer.schema_version == SCHEMA_VERSION
        writer.append(new)
        back = writer.records()
    assert [_key(r) for r in back] == [_key(r) for r in old + [new]]
    with sqlite3.connect(path) as conn:
        cols = tuple(r[1] for r in conn.execute("PRAGMA table_info(records)"))
    assert cols == CSV_COLUMNS


def test_version_6_database_is_migrated_by_a_writer_and_round_trips(fresh_db):

    old = [_rec(i) for i in range(2)]
    old_log(fresh_db, old, 6)
    with QualityLog(fresh_db, create=False) as reader:
        assert reader.schema_version == 6
        assert [_key(r) for r in reader.records()] == [_key(r) for r in old]
    recs = _board_records()
    with QualityLog(fresh_db) as writer:
        assert writer.schema_version == SCHEMA_VERSION
        for r in recs:
            writer.append(r)
        back = writer.records()
    assert [_key(r) for r in back] == [_key(r) for r in old + recs]
    assert count_kinds([r.defects for r in back if r.defects]) == back[-2].board_defect_counts


def _random_defect(rng: np.random.Generator) -> Defect:
    kind = DefectKind(DEFECT_KINDS[rng.integers(len(DEFECT_KINDS))])
    depth = None if rng.random() < 0.2 else float(rng.uniform(0.5, 400.0))
    return Defect(kind, float(rng.uniform(0, 45)), float(rng.uniform(0, 40)),
                  float(rng.uniform(0.2, 20)), float(rng.uniform(0.2, 15)), depth,
                  float(rng.uniform(0.1, 1.0)))  # some below the grade's 0.3


@pytest.mark.parametrize("seed", range(40))
def test_the_running_grade_is_grade_board_of_the_whole_list(seed):
    """Kept up pair by pair, the board's grade and reason are ``grade_board``'s every time."""
    rng = np.random.default_rng(seed)
    grades, pairs = BoardGrades(), []
    for _ in range(int(rng.integers(1, 60))):
        n = int(rng.choice([0, 0, 0, 1, 1, 2, 4]))
        objs = tuple(_random_defect(rng).to_json() for _ in range(n))  # as the log has them
        pairs.append(defects_of(objs))
        f = grades.add(3, objs)
        want = grade_board(pairs)
        assert (f["board_grade"], f["board_grade_reason"]) == (want.grade, want.reason)
    assert f["board_defect_counts"] == count_kinds([[d.to_json() for d in p] for p in pairs])


def _random_placed_pair(rng: np.random.Generator, bow_um: float) -> tuple[Defect, ...]:
    found = [_random_defect(rng) for _ in range(int(rng.choice([0, 0, 1, 2])))]
    found = [d for d in found if d.kind is not DefectKind.SNIPE]
    if rng.random() < 0.9:  # the rig's bow, now and then a deeper one (snipe, or a pit's)
        sag = bow_um + float(rng.normal(0, 1.0)) + (float(rng.uniform(0, 60))
                                                     if rng.random() < 0.15 else 0.0)
        if sag >= 3.0:
            found.append(Defect(DefectKind.SNIPE, 6.4, 19.5, 12.8, 39.2, sag,
                                min(1.0, sag / 6.0)))
    return tuple(found)


@pytest.mark.parametrize("seed", range(40))
def test_the_running_grade_judges_snipe_as_grade_board_with_the_places(seed):
    """With the pairs' places the running grade, reason and counts are ``grade_board``'s.

    Snipe judged on the board (:func:`vision.defects.grading.judge_snipe`): boards of 0.1-4 m,
    pairs 20-80 mm apart, a rig bow of 0-90 um, some pairs without a place, now and then one
    out of order; the counts' snipes are the judged ones, the other kinds as reported.
    """
    rng = np.random.default_rng(1000 + seed)
    grades, pairs, places = BoardGrades(), [], []
    bow = float(rng.choice([0.0, 20.0, 86.0]))
    pos = float(rng.uniform(20, 80))
    for _ in range(int(rng.integers(1, 70))):
        objs = tuple(d.to_json() for d in _random_placed_pair(rng, bow))
        place = None if rng.random() < 0.05 else pos - (30.0 if rng.random() < 0.05 else 0.0)
        pairs.append(defects_of(objs))
        places.append(place)
        f = grades.add(3, objs, place)
        want = grade_board(pairs, positions_mm=places)
        assert (f["board_grade"], f["board_grade_reason"]) == (want.grade, want.reason)
        judged, _ = judge_snipe(pairs, places)
        assert f["board_defect_counts"] == count_kinds([[d.to_json() for d in p]
                                                        for p in judged])
        pos += float(rng.uniform(20, 80))


def test_a_board_bent_by_the_rig_alone_grades_one_and_counts_no_snipe():
    """The simulator's lights bend every field 86 um: not snipe on the board."""
    grades = BoardGrades()
    bend = Defect(DefectKind.SNIPE, 6.4, 19.5, 12.8, 39.2, 86.0, 1.0).to_json()
    for i in range(66):
        f = grades.add(1, (bend,), 70.0 + 60.0 * i)
        if i >= 6:  # three pairs past the leading end's 200 mm and the newest 200 mm
            assert f["board_grade"] == 1, (i, f["board_grade_reason"])
    assert f["board_defect_counts"] == dict.fromkeys(DEFECT_KINDS, 0)
    grades = BoardGrades()  # without places the raw bends count: every pair sniped
    for _ in range(66):
        f = grades.add(1, (bend,))
    assert f["board_grade"] == 5 and f["board_defect_counts"]["snipe"] == 66


def test_a_refused_record_keeps_its_defects_and_drops_a_board_it_cannot_store(tmp_path):
    rec = _board_records()[0]
    huge = dataclasses.replace(rec, board_id=2**64)  # beyond SQLite's integers
    kept = storable(huge)[0]
    assert not kept.ok and kept.error.startswith("record refused: board_id")
    assert kept.board_id == 0 and kept.board_grade is None and kept.board_defect_counts is None
    assert kept.defects == rec.defects and kept.grade == rec.grade
    odd = storable(dataclasses.replace(rec, grade_reason="worst \udc80"))[0]
    assert odd.grade_reason == "worst \\udc80" and odd.board_grade == rec.board_grade
    with QualityLog(tmp_path / "q.sqlite") as log:
        log.append(kept)
        log.append(odd)
        assert [r.defects for r in log.records()] == [rec.defects, rec.defects]
