"""Boards with wood defects: measured right, or flagged -- never a confident wrong pitch.

Boards from the independent renderer ``tests/support/defect_boards.py`` (a 2-D height field with
cast shadows; no ``plant_sim``): torn grain, raised grain, fuzzy grain, chip marks, knife nicks,
chatter and snipe over the issue's ranges, on pine, oak and beech, at 50 mm/s to 2 m/s, roll
within +-3 deg, 4 knives at 2.0 mm.  Criteria: profile correlation with the cuttermarks >= 0.95
(cubic trend removed), pitch within 1 %, uniformity CV within 0.03, depth within 15 %, shift
within 0.5 px on >= 95 % of the boards; every other board flagged (confidence <= 0.3 with a
reason); never a pitch more than 2 % off at a confidence above 0.5.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from core.errors import MeasurementError
from tests.support.defect_boards import Defects, render_defect_board
from vision.marks import corr2
from vision.pipeline import Measurer
from vision.registration.consistency import (
    honest_confidence,
    marks_shading_agreement,
    shift_within_slip,
    shifts_agree,
)
from vision.registration.defect_rows import (
    RowMask,
    clean_columns,
    defect_mask,
    defect_rows,
    masked_pair,
    ridged_rows,
    row_window,
    weighted_profile,
)

SPECIES = ("pine", "oak", "beech")
KINDS = ("torn along", "torn across", "raised", "fuzzy", "chips", "nick", "chatter", "snipe",
         "torn + chips", "clean")


def board_spec(i: int) -> dict:
    """The i-th random board: its defect kind in turn, everything else drawn from seed i."""
    rng = np.random.default_rng(1000 + i)
    kind = KINDS[i % len(KINDS)]
    torn_along = (rng.uniform(0.05, 1.0), rng.uniform(2, 15), rng.uniform(1.5, 4.0),
                  rng.uniform(-10, 10))
    torn_across = (rng.uniform(0.05, 1.0), rng.uniform(2, 15), rng.uniform(1.5, 4.0),
                   90 + rng.uniform(-10, 10))
    defects = {
        "torn along": Defects(torn=(torn_along,)),
        "torn across": Defects(torn=(torn_across,)),
        "raised": Defects(raised_um=rng.uniform(10, 50)),
        "fuzzy": Defects(fuzzy_um=rng.uniform(10, 30)),
        "chips": Defects(chips_um=tuple(rng.uniform(30, 150, int(rng.integers(1, 4))))),
        "nick": Defects(nick_um=rng.uniform(10, 40), nick_mm=rng.uniform(0.3, 1.0)),
        "chatter": Defects(chatter_um=rng.uniform(0.5, 2.5),
                           chatter_passes=rng.uniform(3.3, 7.7)),
        "snipe": Defects(snipe_um=rng.uniform(50, 200), snipe_mm=rng.uniform(20, 60)),
        "torn + chips": Defects(torn=(torn_along,), chips_um=(rng.uniform(30, 150),)),
        "clean": Defects(),
    }[kind]
    ring = rng.uniform(0, 90) if kind == "raised" else rng.uniform(-20, 20)
    return dict(
        seed=2000 + i, kind=kind, species=SPECIES[i % 3], defects=defects,
        ring_angle_deg=float(ring),
        speed_mm_s=float(np.exp(rng.uniform(math.log(50), math.log(2000)))),
        roll_deg=float(rng.uniform(-3, 3)), shift_px=float(rng.uniform(12, 36)),
        slip_px=float(rng.uniform(-4, 4)), imbalance=float(rng.uniform(-0.05, 0.05)),
    )


N_BOARDS = 40


@dataclass(frozen=True)
class Outcome:
    kind: str
    species: str
    ok: bool  # every metric within the criteria
    marks_ok: bool  # every metric but the profile correlation within the criteria
    flagged: bool
    confidence: float
    pitch_err: float  # relative
    shift_err_px: float
    corr: float
    cv_err: float
    depth_err: float  # relative
    reason: str | None


def _truth_metrics(board, m):
    tc = board.cusps_mm
    i0 = int(np.argmin(np.abs(tc - m.cusps_mm[0])))
    i1 = int(np.argmin(np.abs(tc - m.cusps_mm[-1])))
    widths = np.diff(tc[i0: i1 + 1])
    return widths.mean(), widths.std() / widths.mean(), board.depths_um[i0:i1].mean()


def measure_board(i: int) -> Outcome:
    spec = board_spec(i)
    kind = spec.pop("kind")
    board = render_defect_board(spec.pop("seed"), **spec)
    measurer = Measurer(board.rig, board.image_a.shape, radius_mm=board.radius_mm,
                        knives=board.knives)
    try:
        m = measurer.measure(board.image_a, board.image_b, counts_a=board.counts_a,
                             counts_b=board.counts_b, speed_mm_s=board.speed_mm_s)
    except MeasurementError as exc:  # a refusal names its reason: a flag without a profile
        return Outcome(kind, board.species, False, False, True, 0.0, math.nan, math.nan, math.nan,
                       math.nan, math.nan, str(exc))
    truth = np.interp(m.x_mm, board.x_mm, board.height_um)
    truth = truth - np.polyval(np.polyfit(m.x_mm, truth, 3), m.x_mm)
    corr = corr2(m.height_um, truth)
    pitch, cv, depth = _truth_metrics(board, m)
    pitch_err = m.pitch_mm / pitch - 1
    depth_err = m.depth_um / depth - 1
    shift_err = m.shift_px - board.shift_px
    marks_ok = (abs(pitch_err) <= 0.01 and abs(m.uniformity_cv - cv) <= 0.03
                and abs(depth_err) <= 0.15 and abs(shift_err) <= 0.5)
    ok = marks_ok and corr >= 0.95
    return Outcome(kind, board.species, bool(ok), bool(marks_ok), m.flagged,
                   float(m.confidence), pitch_err, shift_err, corr, m.uniformity_cv - cv,
                   depth_err, m.flag_reason)


@pytest.fixture(scope="module")
def outcomes() -> list[Outcome]:
    return [measure_board(i) for i in range(N_BOARDS)]


def test_the_boards_cover_every_defect_species_and_range():
    specs = [board_spec(i) for i in range(N_BOARDS)]
    assert {s["kind"] for s in specs} == set(KINDS)
    assert {s["species"] for s in specs} == set(SPECIES)
    speeds = [s["speed_mm_s"] for s in specs]
    assert min(speeds) < 100 and max(speeds) > 1000
    rolls = [s["roll_deg"] for s in specs]
    assert min(rolls) < -2 and max(rolls) > 2


def test_never_a_confident_wrong_pitch(outcomes):
    for o in outcomes:
        if not (math.isfinite(o.pitch_err) and abs(o.pitch_err) <= 0.02):
            assert o.confidence <= 0.5, o
        if not o.marks_ok:  # every board off the mark criteria is flagged, with its reason
            assert o.flagged and o.confidence <= 0.3 and o.reason, o


def test_the_marks_are_right_on_every_board_not_flagged(outcomes):
    # as measured on the 40 boards (2-core VM): 38 unflagged, all within every criterion
    # (a defect's rows left out of the column profiles, the row bins Hann-weighted, a pit
    # over most rows of its columns left out with its columns); 2 flagged or refused
    assert sum(o.marks_ok and not o.flagged for o in outcomes) >= 38
    assert sum(o.ok for o in outcomes) >= 38


def test_torn_grain_and_chips_leave_the_profile_of_the_cuttermarks(outcomes):
    # the rows of a pit or chip are left out of the column profiles: every unflagged torn-grain
    # and chip-mark board within all the criteria (before: profile correlation 0.39-0.94)
    kinds = ("torn along", "torn across", "chips", "torn + chips")
    for o in outcomes:
        if o.kind in kinds and not o.flagged:
            assert o.ok, o


def test_at_least_95_percent_of_the_boards_are_measured_within_the_criteria(outcomes):
    # as measured (2-core VM): 38 of 40; the two left are flagged or refused (raised beech
    # grain at 80 deg, nearly along the marks, over the whole field; a fuzzy patch where
    # neither the texture nor the profiles give a confident peak)
    good = sum(o.ok for o in outcomes)
    assert good >= math.ceil(0.95 * len(outcomes)), [o for o in outcomes if not o.ok]


# -- the checks themselves ----------------------------------------------------------------------


def _sawtooth_logs(cusps, bottoms, x, light_gain=7.0):
    p = np.full_like(x, np.nan)
    for c0, c1, b in zip(cusps[:-1], cusps[1:], bottoms, strict=True):
        inside = (x >= c0) & (x < c1)
        p[inside] = (x[inside] - b) / 60.0
    p = np.nan_to_num(p)
    return -light_gain * p, light_gain * p


def test_the_true_marks_explain_both_images_and_half_marks_do_not():
    x = np.arange(0, 40, 0.08)
    cusps = np.arange(1.0, 39.0, 2.0)
    bottoms = 0.5 * (cusps[1:] + cusps[:-1])
    log_a, log_b = _sawtooth_logs(cusps, bottoms, x)
    good = marks_shading_agreement(log_a, log_b, x, cusps, bottoms)
    assert good.score > 0.99
    half = np.sort(np.concatenate([cusps, bottoms]))
    bad = marks_shading_agreement(log_a, log_b, x, half, 0.5 * (half[1:] + half[:-1]))
    assert bad.score < 0.6
    # B registered half a mark off: A still agrees, B does not
    shifted = np.interp(x + 1.0, x, log_b)
    off = marks_shading_agreement(log_a, shifted, x, cusps, bottoms)
    assert off.score_a > 0.99 and off.score_b < 0


def test_agreement_validates_its_inputs():
    x = np.arange(10.0)
    with pytest.raises(ValueError, match="log_a"):
        marks_shading_agreement(x, x[:5], x, np.array([0.0, 5.0]), np.array([2.0]))
    with pytest.raises(ValueError, match="cusps_mm"):
        marks_shading_agreement(x, x, x, np.array([0.0, 5.0]), np.array([2.0, 3.0]))
    assert math.isnan(marks_shading_agreement(x, x, x, np.array([0.0, 5.0]),
                                              np.array([2.0])).score)


def test_the_confidence_rule_caps_a_failed_check_and_names_it():
    assert honest_confidence(0.9, []) == (0.9, None)
    conf, reason = honest_confidence(0.9, ["two shifts disagree", "slip"])
    assert conf == 0.3 and reason == "two shifts disagree; slip"
    assert honest_confidence(0.2, ["x"])[0] == 0.2
    assert honest_confidence(0.9, ["x"], flagged_confidence=0.1)[0] == 0.1
    with pytest.raises(ValueError, match="flagged_confidence"):
        honest_confidence(0.9, ["x"], flagged_confidence=1.5)
    assert shift_within_slip(20.0, 18.0, max_slip_px=3.0)
    assert not shift_within_slip(20.0, 14.0, max_slip_px=3.0)
    assert shifts_agree(20.0, 20.4, tolerance_px=0.5)
    assert not shifts_agree(20.0, 26.0, tolerance_px=0.5)
    assert shifts_agree(20.0, math.nan, tolerance_px=0.5)


def test_a_torn_pit_that_fooled_the_texture_is_registered_from_the_profiles():
    board = render_defect_board(1, defects=Defects(torn=((0.4, 11.0, 3.6, 0.0),)))
    m = Measurer(board.rig, board.image_a.shape, radius_mm=60.0, knives=4).measure(
        board.image_a, board.image_b, counts_a=board.counts_a, counts_b=board.counts_b,
        speed_mm_s=board.speed_mm_s)
    assert m.registration_source == "profile"  # the texture's shift was rejected
    assert abs(m.shift_px - board.shift_px) < 0.5
    assert m.pitch_mm == pytest.approx(2.0, rel=0.01)
    assert m.marks_agreement >= 0.7 and not m.flagged
    data = m.to_json()
    assert data["flag_reason"] is None and data["registration_source"] == "profile"


def test_a_pair_whose_checks_disagree_is_flagged_with_its_reason():
    board = render_defect_board(1, defects=Defects(torn=((0.4, 11.0, 3.6, 0.0),)))
    # the encoder's slip bound set too tight for the encoder's own error: flagged
    m = Measurer(board.rig, board.image_a.shape, max_slip_px=0.0).measure(
        board.image_a, board.image_b, counts_a=board.counts_a + 3, counts_b=board.counts_b,
        speed_mm_s=board.speed_mm_s)
    assert m.flagged and m.confidence <= 0.3 and "slip bound" in m.flag_reason
    assert m.to_json()["flag_reason"] == m.flag_reason


def test_a_pit_is_left_out_of_the_profile_and_a_clean_pair_is_not_touched():
    board = render_defect_board(3, defects=Defects(chips_um=(120.0,)), species="oak")
    measurer = Measurer(board.rig, board.image_a.shape, radius_mm=60.0, knives=4)
    m = measurer.measure(board.image_a, board.image_b, counts_a=board.counts_a,
                         counts_b=board.counts_b, speed_mm_s=board.speed_mm_s)
    truth = np.interp(m.x_mm, board.x_mm, board.height_um)
    truth = truth - np.polyval(np.polyfit(m.x_mm, truth, 3), m.x_mm)
    assert corr2(m.height_um, truth) >= 0.95
    # the same rows of the same pair: the mask finds the chip, not the clean board
    front = measurer.front
    rows = [front.profile_rows(front.bin(img, "x"), 0.0)[0]
            for img in (board.image_a, board.image_b)]
    d = m.shift_px
    assert defect_rows(measurer.width, *rows, d, 0) is not None
    clean = render_defect_board(3, species="oak")
    rows = [front.profile_rows(front.bin(img, "x"), 0.0)[0]
            for img in (clean.image_a, clean.image_b)]
    assert defect_rows(measurer.width, *rows, clean.shift_px, 0) is None


def test_masked_profiles_cancel_the_albedo_of_the_rows_kept():
    rng = np.random.default_rng(0)
    n, w, d = 12, 300, 7.0
    shading = 1.0 + 0.1 * np.sin(np.arange(w + 20) / 4.0)
    albedo = 1.0 + 0.2 * rng.random((n, w + 20))
    a = 100 * albedo[:, :w] * shading[:w]
    b = 100 * albedo[:, :w] * shading[:w] ** 2  # B at u + 7 sees A's board point u
    b = np.concatenate([np.ones((n, 7)), b], axis=1)[:, :w]
    a[3:5, 100:140] *= 0.3  # a pit's shadow in A only
    mask = defect_mask(a, b, d, u0=10, u1=280)
    assert mask is not None and mask.mask[3:5, 95:125].all() and mask.fraction < 0.05
    pa, pb = masked_pair(a, b, 1, mask)
    ratio = (pb / pa)[12:278]
    assert np.allclose(ratio, shading[12:278], rtol=1e-6)
    with pytest.raises(ValueError, match="rows_a"):
        defect_mask(a, b[:, :10], d, u0=10, u1=280)


def test_a_pit_over_most_rows_leaves_its_columns_out():
    mask = np.zeros((10, 200), dtype=bool)
    mask[1:9, 120:140] = True  # 8 of 10 bins: the pit's columns
    mask[2:4, 30:50] = True  # 2 of 10: a chip, its columns kept
    rm = RowMask(mask, u0=5, u1=205, shift_px=12.0)
    assert clean_columns(rm) == (5, 125)  # the longer clean stretch, in A's columns
    assert clean_columns(rm, min_width=130) is None  # too narrow to measure on
    mask[:, 120:140] = False
    assert clean_columns(RowMask(mask, 5, 205, 12.0)) is None  # every column keeps its rows


def test_ridges_at_an_angle_taper_the_bins_and_agreeing_bins_do_not():
    w = row_window(8)
    assert w.sum() == pytest.approx(8) and np.allclose(w, w[::-1])
    assert w[0] < 0.6 < w[3] and np.all(row_window(2) == 1.0)
    rng = np.random.default_rng(3)
    u = np.arange(400.0)
    marks = np.exp(0.1 * ((u % 25) / 25 - 0.5))  # the same sawtooth in every bin
    noise = 1.0 + 0.01 * rng.standard_normal((8, 400))
    a = 100 * marks[None, :] * noise
    b = 100 / marks[None, :] * noise
    assert ridged_rows(400, a, b, 0.0, 4) is None
    ridge = np.exp(0.4 * np.sin(2 * np.pi * (u[None, :] + 15 * np.arange(8)[:, None]) / 60))
    assert ridged_rows(400, a * ridge, b / ridge, 0.0, 4) is not None
    p = weighted_profile(a, 1, row_window(8))
    assert p.shape == (400,) and np.allclose(p, (row_window(8) @ a) / 8)


def test_a_pit_across_the_feed_does_not_pull_the_roll():
    spec = board_spec(31)  # a pit 11 mm long at 86 deg: 4 deg from the marks
    spec.pop("kind")
    board = render_defect_board(spec.pop("seed"), **spec)
    m = Measurer(board.rig, board.image_a.shape)
    est = m.orientation(m._binned(board.image_a, "a"), m._binned(board.image_b, "b"))
    assert abs(est.roll_deg - board.roll_deg) < 0.5  # 3.3 deg off before the clip
