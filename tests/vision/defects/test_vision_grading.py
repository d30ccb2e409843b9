"""The ASTM D1666 grade rule: severities, a pair's grade, a board's grade, snipe on a board."""

from __future__ import annotations

import pytest

from vision.defects.detect import Defect, DefectKind
from vision.defects.grading import (
    SNIPE_MIN_MIDDLE,
    end_of_board,
    grade_board,
    grade_pair,
    judged_pair,
    pair_grade,
    severity,
    snipe_margin_um,
)

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


def test_a_pairs_own_grade_leaves_snipe_to_its_board():
    """One pair cannot tell snipe from the rig's bow: its own grade counts every other kind
    and names the raw bend it left (the simulator's clean pairs: ~86 um, grade 1)."""
    bend = _d(K.SNIPE, length=13.0, width=39.0, depth=85.8, conf=1.0)
    assert grade_pair([bend]).grade == 4  # the rule on the raw bend: a severe snipe
    g = pair_grade([bend])
    assert g.grade == 1 and g.reason.startswith("defect-free"), g.reason
    assert "snipe" not in g.reason and "85.8 µm" in g.reason, g.reason
    chip = _d(K.CHIP_MARK, depth=60.0)
    g = pair_grade([bend, chip])
    assert (g.grade, g.reason.split("; a bend")[0]) == (grade_pair([chip]).grade,
                                                         grade_pair([chip]).reason)
    assert "85.8 µm" in g.reason
    # the other kinds exactly as grade_pair counts them; no bend: the same reason too
    for found in ([], [chip], [chip, _d(K.TORN_GRAIN, length=12.0)], [_d(K.CHATTER, depth=0.8)]):
        assert pair_grade(found) == grade_pair(found)
    # a bend below the confidence that counts is not named
    assert pair_grade([_d(K.SNIPE, depth=50.0, conf=0.2)]) == grade_pair([])
    with pytest.raises(ValueError, match="min_confidence"):
        pair_grade([], min_confidence=-0.1)
    # the board still judges it: the pair's raw bend stays in its defects
    pairs, pos = _board([86.0] * 20)
    pairs[0] = _sag(86.0 + 40.0)
    assert pair_grade(pairs[0]).grade == 1
    assert grade_board(pairs, positions_mm=pos).grade == 4


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


def _sag(um: float) -> list[Defect]:
    """A pair whose detector reported a raw bend of ``um`` of sag (nothing below 3 um)."""
    return [_d(K.SNIPE, length=13.0, width=39.0, depth=um, conf=min(1.0, um / 6.0))] \
        if um >= 3.0 else []


def _board(sags: list[float], step_mm: float = 60.0) -> tuple[list[list[Defect]], list[float]]:
    """A board's pairs ``step_mm`` apart from 70 mm after its leading end."""
    return [_sag(s) for s in sags], [70.0 + step_mm * i for i in range(len(sags))]


def test_the_rigs_bow_on_every_pair_is_not_snipe():
    """A bend in every pair of a board, its middle too, is the optics (the simulator's 86 um)."""
    pairs, pos = _board([86.0] * 40)
    assert grade_board(pairs).grade == 5  # each pair alone: a severe snipe, on every pair
    g = grade_board(pairs, positions_mm=pos)
    assert g.grade == 1 and "bow of 86.0 µm (" in g.reason, g.reason
    # the bow varies a little (85-89 um on the simulator's first board): within the margin
    pairs, pos = _board([85.2, 88.7, 93.0] + [86.0] * 34 + [90.0, 86.0, 85.0])
    assert grade_board(pairs, positions_mm=pos).grade == 1


@pytest.mark.parametrize("where", ["leading", "trailing"])
def test_an_end_bending_beyond_the_boards_middle_is_snipe_of_the_excess(where):
    sags = [86.0] * 40
    ends = [0, 1] if where == "leading" else [38, 39]
    for i in ends:
        sags[i] = 86.0 + 40.0
    pairs, pos = _board(sags)
    g = grade_board(pairs, positions_mm=pos)
    # a 40 um snipe (severe: 3) on 2 of 40 pairs: grade 4, not widespread
    assert g.grade == 4 and "snipe" in g.reason and "40.0 µm" in g.reason, g.reason
    # without a bow of the rig an end pair's sag is all snipe
    sags = [0.0] * 40
    sags[ends[0]] = 50.0
    pairs, pos = _board(sags)
    g = grade_board(pairs, positions_mm=pos)
    assert g.grade == 4 and "50.0 µm" in g.reason, g.reason


def test_a_bend_beyond_the_middles_away_from_the_ends_is_not_snipe():
    sags = [86.0] * 40
    sags[20] = 140.0
    pairs, pos = _board(sags)
    assert grade_board(pairs, positions_mm=pos).grade == 1


def test_the_margin_is_three_um_or_a_tenth_of_the_bow():
    assert snipe_margin_um(0.0) == 3.0 and snipe_margin_um(86.0) == pytest.approx(8.6)
    for excess, grade in ((8.0, 1), (9.5, 3)):  # 9.5 um: moderate snipe (2), pair grade 3
        sags = [86.0] * 20
        sags[0] = 86.0 + excess
        pairs, pos = _board(sags)
        assert grade_board(pairs, positions_mm=pos).grade == grade, excess
    sags = [0.0] * 20
    sags[0] = 3.5  # no bow: 3 um
    pairs, pos = _board(sags)
    assert grade_board(pairs, positions_mm=pos).grade == 3


def test_snipe_is_not_judged_without_enough_middle_pairs():
    """A board under ~0.5 m (or the first pairs of one): no reference bow, no snipe."""
    pairs, pos = _board([86.0 + 50.0, 86.0, 86.0, 86.0, 86.0, 86.0], step_mm=60.0)
    assert sum(not end_of_board(p, pos[-1]) for p in pos) < SNIPE_MIN_MIDDLE
    g = grade_board(pairs, positions_mm=pos)
    assert g.grade == 1 and "snipe not judged" in g.reason, g.reason
    # the other kinds count as ever
    pairs[2] = pairs[2] + [_d(K.CHIP_MARK, depth=60.0)]
    assert grade_board(pairs, positions_mm=pos).grade == 3


def test_pairs_without_a_place_keep_their_raw_snipe():
    pairs, pos = _board([86.0] * 20)
    assert grade_board(pairs, positions_mm=[None] * 20).grade == 5
    assert grade_board(pairs, positions_mm=[float("nan")] * 20) == grade_board(pairs)
    mixed = list(pos)
    mixed[10] = None  # one unplaced pair in the middle: its raw 86 um snipe counts
    g = grade_board(pairs, positions_mm=mixed)
    assert g.grade == 4 and "worst pair 10" in g.reason, g.reason
    with pytest.raises(ValueError, match="positions_mm"):
        grade_board(pairs, positions_mm=pos[:-1])


def test_judged_pair_keeps_the_other_defects_and_places_the_snipe_where_reported():
    chip = _d(K.CHIP_MARK, depth=60.0)
    raw = [chip, *_sag(120.0)]
    assert judged_pair(raw, end=False, reference_um=86.0) == [chip]
    assert judged_pair(raw, end=True, reference_um=None) == [chip]
    out = judged_pair(raw, end=True, reference_um=86.0)
    assert out[0] == chip and out[1].kind is K.SNIPE and out[1].depth_um == pytest.approx(34.0)
    assert (out[1].x_mm, out[1].length_mm) == (raw[1].x_mm, raw[1].length_mm)
