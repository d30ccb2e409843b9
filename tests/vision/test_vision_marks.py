"""Cuttermark metrics on analytic profiles: cusps, widths, depths, pitch, uniformity, per knife."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.errors import MeasurementError
from vision.marks import (
    corr2,
    cusp_steps,
    dominant_period_px,
    find_marks,
    knife_means,
    repeat_period_px,
    without_false_cusps,
)

DX = 0.08  # mm per sample (12.5 px/mm)
RADIUS = 60.0


def _arcs(feed_mm: float, runout_um: tuple[float, ...], *, phase: float = 0.31,
          length_mm: float = 52.0):
    """Lower envelope of tip circles (parabolas) of knives k at x = phase + i feed, i = 0, 1, ..."""
    z = len(runout_um)
    centres = phase + feed_mm * np.arange(-3, int(length_mm / feed_mm) + 4)
    drop = np.array([runout_um[i % z] for i in range(-3, centres.size - 3)]) / 1000.0

    def height_mm(x: np.ndarray) -> np.ndarray:
        arcs = (x[None, :] - centres[:, None]) ** 2 / (2 * RADIUS) - drop[:, None]
        return arcs.min(axis=0)

    # exact cusps: where neighbouring arcs meet (every knife here leaves a mark)
    c0, c1, d0, d1 = centres[:-1], centres[1:], drop[:-1], drop[1:]
    cusps = 0.5 * (c0 + c1) + RADIUS * (d0 - d1) / (c1 - c0)
    bottoms = centres
    return height_mm, cusps, bottoms, drop


def _sampled(height_mm, n: int = 650):
    x = np.arange(n) * DX
    h = height_mm(x) * 1000.0
    slope = (height_mm(x + DX / 2) - height_mm(x - DX / 2)) / DX  # a pixel's mean slope
    return x, h, slope


@pytest.mark.parametrize(
    "feed, runout",
    [
        (1.5, (0.0,)),
        (2.5, (0.0,)),
        (1.0, (0.0, 2.0, 0.5, 1.5, 1.0, 2.5)),
        (1.6, (3.0, -2.0, 1.0)),
        (1.2, (0.0, 4.0)),
    ],
)
def test_marks_of_analytic_arcs(feed, runout):
    height_mm, true_cusps, true_bottoms, drop = _arcs(feed, runout)
    x, h, p = _sampled(height_mm)
    m = find_marks(x, h, slope=p)
    # every detected cusp is a true cusp, to a small fraction of a pixel
    idx = np.array([np.argmin(np.abs(true_cusps - c)) for c in m.cusps_mm])
    assert np.all(np.diff(idx) == 1)  # consecutive true cusps: no mark missed or split
    np.testing.assert_allclose(m.cusps_mm, true_cusps[idx], atol=0.15 * DX)
    true_widths = np.diff(true_cusps[idx])
    np.testing.assert_allclose(m.widths_mm, true_widths, atol=0.3 * DX)
    assert m.pitch_mm == pytest.approx(true_widths.mean(), rel=2e-3)
    assert m.uniformity_cv == pytest.approx(true_widths.std() / true_widths.mean(), abs=0.01)
    # depths: mean cusp height minus the arc's lowest point
    cusp_h = np.interp(true_cusps[idx], x, h)
    lows = -drop[idx[:-1] + 1] * 1000.0
    true_depths = 0.5 * (height_mm(true_cusps[idx[:-1]]) + height_mm(true_cusps[idx[1:]])) * 1000
    true_depths -= lows
    np.testing.assert_allclose(m.depths_um, true_depths, rtol=0.03, atol=0.05)
    assert m.depth_um == pytest.approx(true_depths.mean(), rel=0.02)
    np.testing.assert_allclose(m.bottoms_mm, true_bottoms[idx[:-1] + 1], atol=0.5 * DX)
    assert cusp_h.size == m.cusp_heights_um.size
    # nearly the whole profile is covered by complete marks
    assert m.cusps_mm[0] - x[0] < 2 * feed and x[-1] - m.cusps_mm[-1] < 2 * feed


def test_marks_survive_noise():
    height_mm, true_cusps, _, _ = _arcs(1.5, (0.0, 1.5, 0.5, 1.0))
    x, h, p = _sampled(height_mm)
    rng = np.random.default_rng(3)
    noisy_p = p + 0.0004 * rng.standard_normal(p.size)  # ~3 % of the slope range
    noisy_h = h + 0.05 * rng.standard_normal(h.size)
    m = find_marks(x, noisy_h, slope=noisy_p)
    idx = np.array([np.argmin(np.abs(true_cusps - c)) for c in m.cusps_mm])
    assert np.all(np.diff(idx) == 1)
    np.testing.assert_allclose(m.cusps_mm, true_cusps[idx], atol=0.5 * DX)


def _owner_gaps(feed_mm: float, runout_um: tuple[float, ...], n: int = 650):
    """Slope, its cumulative sum and the true cusps to a sample (where the lowest arc changes)."""
    height_mm, _, _, _ = _arcs(feed_mm, runout_um)
    x, h, p = _sampled(height_mm)
    z = len(runout_um)
    centres = 0.31 + feed_mm * np.arange(-3, int(52.0 / feed_mm) + 4)
    drop = np.array([runout_um[i % z] for i in range(-3, centres.size - 3)]) / 1000.0
    owner = np.argmin((x[None, :] - centres[:, None]) ** 2 / (2 * RADIUS) - drop[:, None], axis=0)
    gaps = np.flatnonzero(np.diff(owner) != 0) + 0.5
    return p, np.concatenate(([0.0], np.cumsum(p))), gaps, owner


@pytest.mark.parametrize("feed, runout", [
    (1.5, (0.0, 4.0, -2.0, 2.0)),  # the shipped plant
    (1.2, (0.0, 8.0)),  # a narrow mark whose lowest point lies outside it
    (0.5, (0.0, 4.0, -2.0, 2.0)),  # 0.5 mm: knives 0 and 2 leave no mark (their passes vanish)
    (0.5, (0.0, 0.9, -0.3, 0.4)),  # 0.5 mm, narrow marks of 1-4 samples
])
def test_true_cusps_are_kept(feed, runout):
    p, cum_p, gaps, owner = _owner_gaps(feed, runout)
    if feed == 0.5 and runout[1] == 4.0:
        assert set(owner.tolist()) & {3 + k for k in range(0, 200, 4)} == set()  # vanished
    np.testing.assert_array_equal(without_false_cusps(p, gaps, cum_p), gaps)


def test_false_cusps_inside_marks_are_dropped():
    p, cum_p, gaps, _ = _owner_gaps(1.5, (0.0, 4.0, -2.0, 2.0))
    # one mark split in the middle, one 3 samples after its left cusp, one 2 before its right
    extra = [0.5 * (gaps[5] + gaps[6]), gaps[12] + 3.0, gaps[21] - 2.0, gaps[0] - 4.0]
    noisy = np.sort(np.concatenate((gaps, extra)))
    np.testing.assert_array_equal(without_false_cusps(p, noisy, cum_p), gaps)
    # and with the noise of 30 DN on the slope (its sample-to-sample noise ~ 1/8 of the fall)
    rng = np.random.default_rng(11)
    p_noisy = p + 0.003 * rng.standard_normal(p.size)
    cum = np.concatenate(([0.0], np.cumsum(p_noisy)))
    np.testing.assert_array_equal(without_false_cusps(p_noisy, noisy, cum), gaps)


@pytest.mark.parametrize("feed, runout", [(1.5, (0.0, 4.0, -2.0, 2.0)), (1.2, (0.0, 8.0))])
def test_read_noise_does_not_split_marks(feed, runout):
    """Slope noise (1/8 of the fall at a cusp at 1.5 mm) that makes a fall of two samples'
    means pass for a cusp now and then (before: 4 and 16 of 40 profiles had a mark split in
    two) leaves every mark whole."""
    height_mm, true_cusps, _, _ = _arcs(feed, runout)
    x, h, p = _sampled(height_mm)
    split = 0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        m = find_marks(x, h, slope=p + 0.003 * rng.standard_normal(p.size))
        idx = np.array([np.argmin(np.abs(true_cusps - c)) for c in m.cusps_mm])
        split += not np.all(np.diff(idx) == 1)
    assert split == 0


def _scattered(p: np.ndarray, length_mm: float) -> np.ndarray:
    """The slope spread along the feed by a two-sided exponential (subsurface scattering)."""
    k = np.arange(-15, 16)
    w = np.exp(-np.abs(k) * DX / length_mm)
    return np.convolve(np.pad(p, 15, mode="edge"), w / w.sum(), mode="same")[15:-15]


@pytest.mark.parametrize("runout", [(0.0, 2.25, 1.75, 2.0), (0.0, 2.5, 2.0, 2.0)])
def test_narrow_marks_beside_a_vanished_knife_are_found(runout):
    """0.5 mm per pass, knife 0 vanished, a 0.41-0.44 mm mark of 5 samples between its
    neighbours; 0.2 mm of scattering. The narrow mark's falls measure ~0.18 of the vanished
    knife's two-pass fall (the typical one): before, only that fall was a cusp (one mark per
    revolution, 25 marks); the arc model adds the narrow mark's cusps."""
    p, _, gaps, _ = _owner_gaps(0.5, runout)
    height_mm, _, _, _ = _arcs(0.5, runout)
    x, h, _ = _sampled(height_mm)
    m = find_marks(x, h, slope=_scattered(p, 0.2))
    true = gaps * DX  # the true cusps to a sample
    assert m.cusps_mm.size == true.size  # every cusp, none added
    # (the arc model places them from the unscattered height: up to 2 samples off here)
    np.testing.assert_allclose(m.cusps_mm, true, atol=2.5 * DX)
    assert m.widths_mm.size == 77 and m.widths_mm.min() > 0.2


def test_marks_without_slope_use_the_height_gradient():
    height_mm, true_cusps, _, _ = _arcs(2.0, (0.0,))
    x, h, _ = _sampled(height_mm)
    m = find_marks(x, h)
    assert m.pitch_mm == pytest.approx(2.0, rel=0.005)


def test_unrefined_marks_sit_on_samples():
    height_mm, _, _, _ = _arcs(1.5, (0.0,))
    x, h, p = _sampled(height_mm)
    m = find_marks(x, h, slope=p, refine=False)
    np.testing.assert_allclose(m.cusps_mm / DX, np.round(m.cusps_mm / DX), atol=1e-9)
    assert m.pitch_mm == pytest.approx(1.5, rel=0.01)


def test_too_few_marks_is_an_error():
    x = np.arange(200) * DX
    flat = np.zeros_like(x)
    with pytest.raises(MeasurementError, match="too few cuttermarks"):
        find_marks(x, flat, slope=flat)
    height_mm, _, _, _ = _arcs(6.0, (0.0,))
    x, h, p = _sampled(height_mm, n=120)  # 9.6 mm of 6 mm marks: at most one complete mark
    with pytest.raises(MeasurementError, match="too few"):
        find_marks(x, h, slope=p)


def test_find_marks_checks_its_input():
    with pytest.raises(ValueError, match="1-D"):
        find_marks(np.arange(10.0), np.zeros(11))
    with pytest.raises(ValueError, match="increase"):
        find_marks(np.zeros(10), np.zeros(10))


def test_cusp_steps_see_the_slope_falls():
    p = np.tile(np.linspace(-1, 1, 10), 5)
    steps = cusp_steps(p)
    falls = np.flatnonzero(steps < -1.0)
    np.testing.assert_array_equal(falls, np.arange(9, 49, 10))


def test_periods():
    height_mm, _, _, _ = _arcs(1.5, (0.0, 3.0, 1.0))
    _, _, p = _sampled(height_mm)
    assert dominant_period_px(p) == pytest.approx(1.5 / DX, rel=0.01)
    # with runout the pattern repeats after a revolution of 3 knives
    assert repeat_period_px(p) == pytest.approx(3 * 1.5 / DX, rel=0.01)
    height_mm, _, _, _ = _arcs(1.5, (0.0,))
    _, _, p = _sampled(height_mm)
    assert repeat_period_px(p) == pytest.approx(1.5 / DX, rel=0.01)
    assert math.isnan(dominant_period_px(np.zeros(5)))


def test_corr2_is_matlab_corr2():
    rng = np.random.default_rng(0)
    a = rng.standard_normal((20, 30))
    b = 0.3 * a + rng.standard_normal((20, 30))
    assert corr2(a, b) == pytest.approx(np.corrcoef(a.ravel(), b.ravel())[0, 1])
    assert corr2(a, a) == pytest.approx(1.0)
    assert corr2(a, -2 * a + 7) == pytest.approx(-1.0)
    assert corr2(a, 5 * b - 3) == pytest.approx(corr2(a, b))
    assert math.isnan(corr2(np.ones(5), np.arange(5.0)))
    with pytest.raises(ValueError, match="shape"):
        corr2(np.ones(5), np.ones(6))


def test_knife_means_table():
    values = np.arange(1.0, 8.0)  # marks 0..6
    # mark i -> knife (phase + i) mod 3: knives of the marks are 1 2 0 1 2 0 1
    np.testing.assert_allclose(knife_means(values, knives=3, phase=1), [4.5, 4.0, 3.5])
    np.testing.assert_allclose(knife_means(values, knives=3, phase=-2), [4.5, 4.0, 3.5])
    np.testing.assert_allclose(knife_means(values, knives=1, phase=5), [4.0])
    many = knife_means(values[:2], knives=4, phase=3)  # marks 0, 1 -> knives 3, 0
    np.testing.assert_allclose(many[[3, 0]], [1.0, 2.0])
    assert np.isnan(many[1]) and np.isnan(many[2])
    with pytest.raises(ValueError, match="knives"):
        knife_means(values, knives=0, phase=0)


def test_compiled_cusp_choice_is_the_composed_one():
    """marks_kernels.cusp_gaps (what find_marks calls) gives the cusps of the composition of
    without_false_cusps and with_narrow_marks, exactly: noisy profiles that drop false cusps,
    narrow marks beside a vanished knife that add weak ones, runout, several noise levels."""
    from vision import kernels
    from vision.marks import _cusp_gaps, _cusp_gaps_composed

    cases = [(1.5, (0.0,)), (1.0, (0.0, 2.0, 0.5, 1.5, 1.0, 2.5)), (0.5, (0.0, 2.25, 1.75, 2.0)),
             (0.5, (0.0, 2.5, 2.0, 2.0)), (1.6, (3.0, -2.0, 1.0))]
    tried = added = dropped = 0
    for feed, runout in cases:
        height_mm, _, _, _ = _arcs(feed, runout)
        _, _, p0 = _sampled(height_mm)
        for seed in range(12):
            rng = np.random.default_rng(seed)
            p = _scattered(p0, 0.2) if feed == 0.5 else p0
            p = np.ascontiguousarray(p + (0.001 * seed) * rng.standard_normal(p.size))
            cum_p, cand, size, noise, typical, _ = kernels.cusp_candidates(p)
            for min_step in (0.35, 0.6):
                got = _cusp_gaps(p, cum_p, cand, size, typical, noise, min_step=min_step,
                                 guard=2, refine=True)
                want = _cusp_gaps_composed(p, cum_p, cand, size, typical, noise,
                                           min_step=min_step, guard=2, refine=True)
                np.testing.assert_array_equal(got, want, f"{feed} {runout} {seed} {min_step}")
                strong = np.count_nonzero(size >= min_step * typical)
                tried += 1
                added += want.size > strong
                dropped += want.size < strong
    # both of the choice's steps were exercised
    assert tried == 120 and added > 0 and dropped > 0
