"""Planing defects on the 2-D surface map: each detector on made-up maps, then the acceptance
over boards of the independent renderer (``tests/support/defect_boards.py``, not plant_sim).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from tests.support.defect_truth import KINDS, measure_boards, score
from vision.defects.detect import (
    Blob,
    Defect,
    DefectKind,
    DefectSettings,
    chatter,
    detect_defects,
    pits,
    residual,
)
from vision.defects.surface_map import SurfaceMap

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


def _arcs_slope(raised_um: float, knife: int, band: np.ndarray) -> np.ndarray:
    """Slope of the marks' arcs (4 knives), one knife cutting ``raised_um`` short in ``band``."""
    x = _x_mm()
    centres = (np.arange(-2, int(x[-1] / PITCH) + 3) + 0.5) * PITCH
    out = np.empty((ROWS, COLS))
    for rows, lift in ((~band, 0.0), (band, raised_um / 1000)):
        low = np.where(np.arange(centres.size) % 4 == knife, lift, 0.0)
        z = np.min((x[None, :] - centres[:, None]) ** 2 / (2 * R_MM) + low[:, None], axis=0)
        out[rows] = np.gradient(z, 1 / PPM)[None, :]
    return out


@pytest.mark.parametrize("nick_um, band_mm", [(12.0, 0.4), (30.0, 0.8)])
def test_one_knife_cutting_short_in_a_band_is_a_knife_nick(nick_um, band_mm):
    _, y = _grid()
    band = (np.abs(y - 9.0) < band_mm / 2)[:, 0]
    slope = _arcs_slope(nick_um, 1, band)
    found = detect_defects(_smap(slope, noise=0.004), pitch_mm=PITCH, knives=4)
    assert _kinds(found) == ["knife_nick"], found
    assert abs(found[0].y_mm - 9.0) <= 1.0 and found[0].length_mm > 40
    assert found[0].depth_um is not None and -found[0].depth_um > 0.4 * nick_um
    clean = detect_defects(_smap(_arcs_slope(0.0, 1, band), noise=0.004), pitch_mm=PITCH,
                           knives=4)
    assert clean == ()


def test_a_chip_in_a_few_rows_is_no_knife_nick():
    # a dent within one revolution repeats in no other: the median over revolutions drops it
    slope = _arcs_slope(0.0, 0, np.zeros(ROWS, bool)) + _dent_slope(0.08, 20.0, 9.0, 0.6, 0.5)
    found = detect_defects(_smap(slope, noise=0.004), pitch_mm=PITCH, knives=4)
    assert _kinds(found) == ["chip_mark"], found


def test_a_deep_smooth_dent_that_casts_shadows_is_a_chip_mark():
    # 150 um over sigma 0.45 mm: its walls (slope up to 0.2) saturate Eq. 4 like a torn pit's,
    # but its bottom is smooth
    dent = np.clip(_dent_slope(0.15, 30.0, 9.0, 0.45, 0.6), -0.13, 0.13)
    found = detect_defects(_smap(_marks() + dent), pitch_mm=PITCH)
    assert _kinds(found) == ["chip_mark"], found
    assert math.hypot(found[0].x_mm - 30.0, found[0].y_mm - 9.0) <= 2.0


def test_a_torn_pit_across_most_rows_does_not_move_the_marks_profile():
    # 12 of the field's 19 mm across the feed: the column median would sit in the pit
    x, y = _grid()
    rng = np.random.default_rng(7)
    inside = (np.abs(x - 25.0) < 1.5) & (np.abs(y - 9.6) < 6.0)
    walls = np.where(np.abs(x - 23.5) < 0.25, -0.13, 0.0) + np.where(
        np.abs(x - 26.5) < 0.25, 0.13, 0.0)
    pit = np.where(np.abs(y - 9.6) < 6.0, walls, 0.0) + inside * 0.04 * rng.standard_normal(
        (ROWS, COLS))
    found = detect_defects(_smap(_marks() + np.clip(pit, -0.13, 0.13)), pitch_mm=PITCH)
    assert _kinds(found) == ["torn_grain"], found
    assert math.hypot(found[0].x_mm - 25.0, found[0].y_mm - 9.6) <= 2.0
    assert found[0].width_mm <= 14.0  # the pit's rows, not the whole field's


def test_the_two_ends_of_a_long_torn_pit_are_one_defect():
    # a long pit's flat bottom leaves no residual between its walls: two blobs, one pit
    res = residual(_smap(_marks()), DefectSettings())

    def torn(c0: int, c1: int, r0: int, r1: int) -> Blob:
        return Blob((c0, c1), (r0, r1), 5.0, 0.8, 150.0, 0.3, 0.2, 500.0, 0.4)

    chip = Blob((300, 330), (10, 20), 5.0, 0.8, 60.0, 0.02, 0.0, 300.0, 0.02)
    found = pits(res, [torn(100, 160, 10, 20), torn(190, 210, 14, 24), chip,
                       torn(400, 420, 10, 20), torn(500, 520, 30, 40)], DefectSettings())
    # 30 columns (2.4 mm) apart on common rows: joined; 190 apart, or on other rows: not
    assert _kinds(found) == ["torn_grain", "chip_mark", "torn_grain", "torn_grain"], found
    centres = [d.x_mm * PPM for d in found]  # map column (c0 + c1 - 1) / 2
    assert centres == pytest.approx([154.5, 314.5, 409.5, 509.5])
    assert found[0].length_mm == pytest.approx(110 / PPM)
    assert found[0].width_mm == pytest.approx(14 * STEP / PPM)


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


def test_the_profiles_random_walk_is_rarely_chatter():
    # white noise in the marks' slope profile integrates to a random walk of the heights
    # (here ~2 um over the field): red, so a long sinusoid fits it well; its steps from one
    # mark to the next are white.  Measured: 1 of 200 walks reported as chatter.
    smap, bottoms = _chatter_map(0.0, 4.7)
    settings = DefectSettings()
    false = 0
    for seed in range(60):
        rng = np.random.default_rng(seed)
        walk = np.cumsum(rng.standard_normal(COLS)) * 0.15 / 1000 * PPM / np.sqrt(COLS)
        p = smap.slope_along_feed + np.gradient(walk, 1 / PPM).astype(np.float32)[None, :]
        res = residual(dataclasses.replace(smap, slope_along_feed=p), settings)
        false += bool(chatter(res, bottoms, 4, settings))
    assert false <= 2


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

# six of each kind and six clean from the tuning split, three of each from the held-out one
ACCEPTANCE = (range(0, 48), range(1000, 1024))


def test_acceptance_on_independent_boards():
    sc = score([o for idx in ACCEPTANCE for o in measure_boards(idx)])
    report = sc.table()
    # what holds on these boards (docs/vision.md), on the pairs the measurement returns;
    # measured (2-core VM): 16 of 72 refused, their defects found all the same; every kind
    # 1.00 / 1.00 over its 9 boards, clean 9/9, grade 72/72 (the 240-board tables: every
    # kind >= 0.97 on the tuning and held-out splits, >= 0.90 on the fresh one)
    assert sc.refused <= 0.3 * sc.boards, report
    # a refused pair's defects come with the refusal: every board of every kind is judged
    assert sc.refused_mapped == sc.refused, report
    assert all(sc.judged.get(k, 0) == 9 for k in KINDS), report
    assert sc.clean_ok == sc.clean, report
    assert sc.grade_ok >= 0.95 * sc.graded, report
    kinds = [k for k in KINDS if k != "clean"]
    for k in kinds:
        assert sc.recall(k) >= 0.8, report
        assert sc.precision(k) >= 0.8, report
    found = sum(sc.tp.values())
    assert found >= 0.95 * (found + sum(sc.fn.values())), report
    assert found >= 0.95 * (found + sum(sc.fp.values())), report


@pytest.mark.parametrize("n", [17, 50, 331])
def test_snipes_fit_and_sag_as_polyfit_and_dense_sampling(n):
    from vision.defects import kernels
    from vision.defects.detect import _sag_um

    rng = np.random.default_rng(n)
    y = 0.002 * rng.standard_normal(n) + 1e-4 * np.arange(n) ** 2 / n
    dx = 0.16
    x = (np.arange(n) - 0.5 * (n - 1)) * dx
    c2, c1, _ = np.polyfit(x, y, 2)
    padded = np.r_[9.0, 9.0, y, 9.0]  # the columns outside [c0, c1) are not read
    got = kernels.snipe_fit(padded, 2, 2 + n, 0, dx)
    assert got == pytest.approx((c2, c1), rel=1e-9, abs=1e-15)
    # smoothed over k columns first (np.convolve's moving average), k < a third of them
    k = max(1, n // 4 - 1)
    ys = np.convolve(y, np.ones(k) / k, mode="valid")
    xs_ = (np.arange(ys.size) - 0.5 * (ys.size - 1)) * dx
    s2, s1, _ = np.polyfit(xs_, ys, 2)
    assert kernels.snipe_fit(padded, 2, 2 + n, k, dx) == pytest.approx((s2, s1), rel=1e-9,
                                                                       abs=1e-15)
    assert kernels.snipe_fit(padded, 2, 2 + n, n // 3, dx) == pytest.approx(got)  # too wide
    half = 0.5 * n * dx
    for a, b in ((c1, c2), (0.001, 0.0003), (-0.002, 1e-4), (0.003, 0.0)):
        xs = np.linspace(-half, half, 100001)
        hz = 1000.0 * (a * xs ** 2 / 2 + b * xs ** 3 / 3)
        dev = hz - (hz[0] + (hz[-1] - hz[0]) * (xs + half) / (2 * half))
        sag, dip = _sag_um(a, b, half)
        scale = max(abs(dev).max(), 1e-9)
        assert sag == pytest.approx(max(dev.max(), 0.0), abs=1e-6 * scale)
        assert dip == pytest.approx(min(dev.min(), 0.0), abs=1e-6 * scale)
