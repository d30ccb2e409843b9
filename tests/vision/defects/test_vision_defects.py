"""Planing defects on the 2-D surface map: each detector on made-up maps, then the acceptance
over boards of the independent renderer (``tests/support/defect_boards.py``, not plant_sim).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.errors import MeasurementError
from tests.support.defect_truth import (
    FIELD_WIDE,
    KINDS,
    board_spec,
    board_truth,
    cached_board,
    true_grade,
)
from vision.defects.detect import (
    Defect,
    DefectKind,
    DefectSettings,
    chatter,
    detect_defects,
    residual,
)
from vision.defects.surface_map import SurfaceMap
from vision.pipeline import Measurer

PPM = 12.5
ROWS, COLS, STEP = 48, 640, 5.0  # 0.4 mm rows, 51 mm along the feed
R_MM, PITCH = 60.0, 2.0


def _x_mm() -> np.ndarray:
    return np.arange(COLS) / PPM


def _marks() -> np.ndarray:
    x = _x_mm()
    return np.broadcast_to(((x % PITCH) - PITCH / 2) / R_MM, (ROWS, COLS))


def _smap(slope: np.ndarray, seed: int = 0, noise: float = 0.004) -> SurfaceMap:
    rng = np.random.default_rng(seed)
    p = (slope + noise * rng.standard_normal(slope.shape)).astype(np.float32)
    return SurfaceMap(p, np.ones_like(p), np.ones(p.shape, bool), col0_px=0.0,
                      row0_px=2.0, row_step_px=STEP, roll_deg=0.0, cx=(COLS - 1) / 2,
                      cy=2.0 + STEP * (ROWS - 1) / 2, px_per_mm=PPM,
                      shadow_slope=1 / math.tan(math.radians(82)))


def _grid() -> tuple[np.ndarray, np.ndarray]:
    y = (2.0 + STEP * np.arange(ROWS)) / PPM
    return _x_mm()[None, :], y[:, None]


def _dent_slope(depth_mm: float, xc: float, yc: float, sx: float, sy: float) -> np.ndarray:
    x, y = _grid()
    g = np.exp(-0.5 * (((x - xc) / sx) ** 2 + ((y - yc) / sy) ** 2))
    return depth_mm * g * (x - xc) / sx ** 2  # d/dx of -depth g


def _kinds(found: tuple[Defect, ...]) -> list[str]:
    return [d.kind.value for d in found]


@pytest.mark.parametrize("seed, noise", [(1, 0.002), (2, 0.004), (3, 0.008), (4, 0.015)])
def test_clean_maps_give_nothing(seed, noise):
    assert detect_defects(_smap(_marks(), seed, noise), pitch_mm=PITCH) == ()


def test_a_noise_free_map_marks_only_above_the_floor():
    # a faint residual (a tenth of the smallest chip's slope) on an almost noise-free map:
    # relative to its own tiny median it stands out, relative to the floor it does not
    faint = _dent_slope(0.002, 20.0, 9.0, 1.0, 1.0)
    smap = _smap(_marks() + faint, noise=0.0001)
    assert not residual(smap, DefectSettings()).marked.any()
    assert residual(smap, DefectSettings(floor_slope=1e-5)).marked.any()
    assert detect_defects(smap, pitch_mm=PITCH) == ()
    chip = _smap(_marks() + faint + _dent_slope(0.04, 40.0, 9.0, 1.0, 1.0), noise=0.0001)
    assert _kinds(detect_defects(chip, pitch_mm=PITCH)) == ["chip_mark"]


@pytest.mark.parametrize("depth_um, xc, yc, sx", [(40, 12.0, 4.0, 1.0), (100, 30.0, 12.0, 0.6),
                                                  (120, 40.0, 8.0, 1.0)])
def test_a_smooth_dent_is_a_chip_mark_where_it_is(depth_um, xc, yc, sx):
    found = detect_defects(_smap(_marks() + _dent_slope(depth_um / 1000, xc, yc, sx, sx)),
                           pitch_mm=PITCH)
    chips = [d for d in found if d.kind is DefectKind.CHIP_MARK]
    assert len(chips) == 1, found
    assert math.hypot(chips[0].x_mm - xc, chips[0].y_mm - yc) <= 2.0
    assert chips[0].depth_um is not None and chips[0].depth_um > 0.3 * depth_um


def test_a_shadowed_rough_pit_is_torn_grain():
    x, y = _grid()
    rng = np.random.default_rng(5)
    slope = _dent_slope(0.4, 25.0, 9.0, 2.0, 0.8)
    inside = (np.abs(x - 25.0) < 4) & (np.abs(y - 9.0) < 1.5)
    slope = slope + inside * 0.05 * rng.standard_normal((ROWS, COLS))
    slope = np.clip(slope, -0.13, 0.13)  # the walls' cast shadows saturate Eq. 4
    found = detect_defects(_smap(_marks() + slope), pitch_mm=PITCH)
    assert _kinds(found) == ["torn_grain"], found
    assert math.hypot(found[0].x_mm - 25.0, found[0].y_mm - 9.0) <= 2.0


def test_a_rough_patch_without_a_dent_is_fuzzy_grain():
    x, y = _grid()
    rng = np.random.default_rng(6)
    tufts = rng.standard_normal((ROWS, COLS))
    tufts = (tufts + np.roll(tufts, 1, axis=1)) / 2
    patch = ((x - 20.0) ** 2 + (y - 9.0) ** 2) < 6.0 ** 2
    found = detect_defects(_smap(_marks() + 0.06 * patch * tufts), pitch_mm=PITCH)
    assert _kinds(found) == ["fuzzy_grain"], found
    assert math.hypot(found[0].x_mm - 20.0, found[0].y_mm - 9.0) <= 2.0


def test_a_band_along_the_feed_is_a_knife_nick():
    x, y = _grid()
    # one knife of four cuts short in a 0.8 mm band: its marks' slope differs there
    nicked = ((x % (4 * PITCH)) < 2 * PITCH) * (((x % PITCH) - PITCH / 2) / R_MM) * -2.5
    band = np.abs(y - 6.0) < 0.4
    found = detect_defects(_smap(_marks() + band * nicked), pitch_mm=PITCH)
    assert _kinds(found) == ["knife_nick"], found
    assert abs(found[0].y_mm - 6.0) <= 1.0 and found[0].length_mm > 40


def test_ridges_across_the_rows_at_an_angle_are_raised_grain():
    x, y = _grid()
    angle = math.radians(40)
    across = -x * math.sin(angle) + y * math.cos(angle)
    phase = (across / 3.0) % 1.0 - 0.5
    z = 0.02 * np.exp(-0.5 * (phase * 3.0 / 0.1) ** 2)
    slope = np.gradient(z, 1 / PPM, axis=1)
    found = detect_defects(_smap(_marks() + slope), pitch_mm=PITCH)
    assert _kinds(found) == ["raised_grain"], found


def _chatter_map(amp_um: float, passes: float) -> tuple[SurfaceMap, np.ndarray]:
    x = _x_mm()
    j = np.floor(x / PITCH)
    runout = np.array([0.0, 2.0, -1.0, 1.0])[(j % 4).astype(int)]
    h_um = runout + amp_um * np.sin(2 * np.pi * (x / PITCH) / passes)
    slope = np.gradient(h_um / 1000, 1 / PPM)
    bottoms = (np.arange(1, int(x[-1] / PITCH)) + 0.5) * PITCH
    return _smap(_marks() + slope[None, :], noise=0.002), bottoms


@pytest.mark.parametrize("amp_um, passes, found", [
    (1.5, 4.7, True), (0.8, 6.3, True), (2.0, 3.4, True),
    (1.5, 4.0, False),  # the revolution's period: runout, not chatter
    (0.0, 4.7, False),
])
def test_chatter_is_a_waviness_off_the_revolution(amp_um, passes, found):
    smap, bottoms = _chatter_map(amp_um, passes)
    res = residual(smap, DefectSettings())
    got = chatter(res, bottoms, 4, DefectSettings())
    assert bool(got) is found, got
    if found:
        assert got[0].depth_um == pytest.approx(amp_um, rel=0.3)
    assert chatter(res, bottoms, None, DefectSettings()) == []  # needs the knives


@pytest.mark.parametrize("snipe_um, length_mm, found", [(100.0, 20.0, True), (60.0, 30.0, True),
                                                         (0.0, 20.0, False)])
def test_snipe_bends_the_field_and_a_tilt_does_not(snipe_um, length_mm, found):
    x = _x_mm()
    slope = snipe_um / 1000 / length_mm * np.exp(-(x + 5.0) / length_mm) + 0.003  # + a tilt
    got = [d for d in detect_defects(_smap(_marks() + slope[None, :]), pitch_mm=PITCH)
           if d.kind is DefectKind.SNIPE]
    assert bool(got) is found, got
    if found:
        assert got[0].x_mm < 15.0  # the deeper end: the field's -x side


# -- acceptance: boards of the independent renderer ----------------------------------------

N_BOARDS = 48  # six of each kind and six clean, species in turn


def _outcomes() -> list[tuple[int, list, tuple[Defect, ...] | None, int, int | None]]:
    measurers: dict[tuple[int, int], Measurer] = {}
    out = []
    for i in range(N_BOARDS):
        b = cached_board(**board_spec(i))
        m = measurers.setdefault(b.image_a.shape,
                                 Measurer(b.rig, b.image_a.shape, knives=4, defects=True))
        try:
            r = m.measure(b.image_a, b.image_b, counts_a=b.counts_a, counts_b=b.counts_b,
                          speed_mm_s=b.speed_mm_s)
            found, grade = r.defects, r.grade
        except MeasurementError:
            found, grade = None, None  # the measurement itself refused the pair
        out.append((i, list(board_truth(b)), found, true_grade(b).grade, grade))
    return out


def _matches(t, d: Defect) -> bool:
    if d.kind.value != t.kind:
        return False
    if t.kind in FIELD_WIDE:
        return True
    if t.kind == "knife_nick":
        return abs(d.y_mm - t.y_mm) <= 2.0
    return math.hypot(d.x_mm - t.x_mm, d.y_mm - t.y_mm) <= 2.0


def test_acceptance_on_independent_boards():
    rows = _outcomes()
    tp: dict[str, int] = {}
    fn: dict[str, int] = {}
    fp: dict[str, int] = {}
    clean = clean_ok = graded = grade_ok = refused = 0
    for i, truth, found, g_true, g in rows:
        if found is None:
            refused += 1  # no measurement: nothing to judge (counted below)
            continue
        if KINDS[i % len(KINDS)] == "clean":
            clean += 1
            clean_ok += found is not None and len(found) == 0
        graded += 1
        grade_ok += g is not None and abs(g - g_true) <= 1
        used: set[int] = set()
        for t in truth:
            hit = next((j for j, d in enumerate(found or ()) if j not in used
                        and _matches(t, d)), None)
            if hit is not None:
                used.add(hit)
                tp[t.kind] = tp.get(t.kind, 0) + 1
            elif t.detectable:
                fn[t.kind] = fn.get(t.kind, 0) + 1
        for j, d in enumerate(found or ()):
            if j not in used:
                fp[d.kind.value] = fp.get(d.kind.value, 0) + 1
    kinds = [k for k in KINDS if k != "clean"]
    recall = {k: tp.get(k, 0) / max(tp.get(k, 0) + fn.get(k, 0), 1) for k in kinds}
    precision = {k: tp.get(k, 0) / max(tp.get(k, 0) + fp.get(k, 0), 1) for k in kinds}
    report = (f"recall {recall}, precision {precision}, clean {clean_ok}/{clean}, "
              f"grade {grade_ok}/{graded}, refused {refused}/{len(rows)}")
    # what holds on these boards (docs/vision.md), on the pairs the measurement returns;
    # measured (2-core VM): 9 refused, clean 6/6, grade 38/39, recall >= 0.75 (torn 5/6,
    # chips 6/7, nicks 3/4, the rest 1.0), precision >= 0.71 (torn 5/7, nicks 3/4,
    # chatter 5/6, the rest 1.0)
    assert refused <= len(rows) // 4, report
    assert clean_ok == clean, report
    assert grade_ok >= 0.95 * graded, report
    for k in kinds:
        assert recall[k] >= 0.75, report
        assert precision[k] >= 0.7, report
