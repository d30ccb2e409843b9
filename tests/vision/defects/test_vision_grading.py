"""The ASTM D1666 grade rule: severities, a pair's grade, a board's grade."""

from __future__ import annotations

import pytest

from vision.defects.detect import Defect, DefectKind
from vision.defects.grading import grade_board, grade_pair, severity

K = DefectKind


def _d(kind: DefectKind, *, length=3.0, width=3.0, depth=None, conf=0.9) -> Defect:
    return Defect(kind, 10.0, 5.0, length, width, depth, conf)


@pytest.mark.parametrize("kind, length, width, depth, expected", [
    (K.CHATTER, 50, 19, 0.8, 1), (K.CHATTER, 50, 19, 1.5, 2),
    (K.CHIP_MARK, 3, 3, 40.0, 1), (K.CHIP_MARK, 3, 3, 60.0, 2), (K.CHIP_MARK, 3, 3, 120.0, 3),
    (K.KNIFE_NICK, 50, 1, -20.0, 2), (K.KNIFE_NICK, 50, 1, -30.0, 3),
    (K.RAISED_GRAIN, 50, 19, -20.0, 2), (K.RAISED_GRAIN, 50, 19, -35.0, 3),
    (K.FUZZY_GRAIN, 8, 8, None, 2), (K.FUZZY_GRAIN, 12, 12, None, 3),
    (K.SNIPE, 13, 19, 10.0, 2), (K.SNIPE, 13, 19, 25.0, 3),
    (K.TORN_GRAIN, 4, 2, None, 3), (K.TORN_GRAIN, 12, 3, None, 4), (K.TORN_GRAIN, 4, 2, 400, 4),
])
def test_severity_table(kind, length, width, depth, expected):
    assert severity(kind, length_mm=length, width_mm=width, depth_um=depth) == expected


def test_severity_refuses_what_is_not_a_kind():
    with pytest.raises(ValueError, match="kind"):
        severity("torn_grain", length_mm=1, width_mm=1, depth_um=None)  # type: ignore[arg-type]


def test_pair_grade_rules():
    assert grade_pair([]).grade == 1 and "defect-free" in grade_pair([]).reason
    assert grade_pair([_d(K.CHATTER, depth=0.8)]).grade == 2
    g = grade_pair([_d(K.CHIP_MARK, depth=120.0), _d(K.CHATTER, depth=0.8)])
    assert g.grade == 4 and "chip_mark" in g.reason
    assert grade_pair([_d(K.TORN_GRAIN, length=12.0)]).grade == 5
    # three of severity >= 2: one step worse
    three = [_d(K.CHIP_MARK, depth=60.0)] * 3
    assert grade_pair(three).grade == 4 and "one step worse" in grade_pair(three).reason
    assert grade_pair(three[:2]).grade == 3
    # capped at 5
    assert grade_pair([_d(K.TORN_GRAIN, length=12.0)] * 4).grade == 5


def test_unconfident_defects_do_not_count():
    assert grade_pair([_d(K.TORN_GRAIN, conf=0.2)]).grade == 1
    assert grade_pair([_d(K.TORN_GRAIN, conf=0.2)], min_confidence=0.1).grade == 4
    with pytest.raises(ValueError, match="min_confidence"):
        grade_pair([], min_confidence=1.5)


def test_board_grade_rules():
    clean: list[Defect] = []
    chip = [_d(K.CHIP_MARK, depth=60.0)]
    assert grade_board([clean] * 8).grade == 1
    # one pair of eight: its grade
    assert grade_board([chip] + [clean] * 7).grade == 3
    # widespread (more than a quarter of the pairs): one step worse
    g = grade_board([chip] * 3 + [clean] * 5)
    assert g.grade == 4 and "3 of 8" in g.reason
    # slight defects do not make it widespread
    assert grade_board([[_d(K.CHATTER, depth=0.8)]] * 8).grade == 2
    with pytest.raises(ValueError, match="pairs"):
        grade_board([])
