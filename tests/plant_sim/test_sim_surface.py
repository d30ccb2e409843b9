"""Surface kinematics: knife passes and the exact lower envelope of the tip circles."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from plant_sim.model.surface import (
    Cutterhead,
    Passes,
    concat_passes,
    envelope,
    passes_steady,
    pitch_per_pass_mm,
)

R = 60.0


def _surface(
    knives=4,
    runout=None,
    rpm=6000.0,
    feed=600.0,
    x0=0.0,
    x1=60.0,
    step=0.01,
    offsets=None,
    phase=0.0,
    ecc=0.0,
    radius=R,
):
    head = Cutterhead(knives, radius, tuple(runout or (0.0,) * knives), ecc)
    passes = passes_steady(
        head,
        spindle_rpm=rpm,
        feed_mm_s=feed,
        x_start_mm=x0,
        x_end_mm=x1,
        offsets_um=offsets,
        phase_mm=phase,
    )
    x = np.arange(x0, x1, step)
    return envelope(x, passes), passes


def _brute_height(x, passes):
    dx = x[:, None] - passes.x_mm[None, :]
    r = passes.radius_mm
    z = passes.bottom_um[None, :] + 1e3 * (r - np.sqrt(np.maximum(r * r - dx * dx, 0.0)))
    z[np.abs(dx) > r] = np.inf
    return z.min(axis=1), z.argmin(axis=1)


@pytest.mark.parametrize(
    ("knives", "rpm", "feed"),
    [
        (1, 6000.0, 150.0),
        (2, 9000.0, 300.0),
        (4, 6000.0, 600.0),
        (6, 4500.0, 1000.0),
        (3, 12000.0, 417.0),
    ],
)
def test_pitch_is_feed_per_knife_pass(knives, rpm, feed):
    surf, _ = _surface(knives=knives, rpm=rpm, feed=feed, x1=80.0)
    m = surf.metrics(5.0, 75.0)
    expect = feed / (rpm / 60.0 * knives)
    assert expect == pytest.approx(
        pitch_per_pass_mm(spindle_rpm=rpm, feed_mm_s=feed, knives=knives)
    )
    assert m["n_marks"] >= 10
    assert m["pitch_mm"] == pytest.approx(expect, rel=1e-3)


@pytest.mark.parametrize("pitch", [0.8, 1.5, 2.5])
def test_depth_is_pitch_squared_over_8r(pitch):
    feed = pitch * 6000.0 / 60.0 * 4
    surf, _ = _surface(feed=feed, x1=60.0)
    m = surf.metrics(5.0, 55.0)
    exact = 1e3 * (R - math.sqrt(R * R - (pitch / 2) ** 2))
    assert m["depth_um"] == pytest.approx(1e3 * pitch**2 / (8 * R), rel=0.02)
    assert m["depth_um"] == pytest.approx(exact, rel=1e-9)
    # the sampled profile agrees: max - min of the heights equals the depth
    sel = (surf.x_mm > 10) & (surf.x_mm < 50)
    span = surf.height_um[sel].max() - surf.height_um[sel].min()
    assert span == pytest.approx(exact, rel=0.01)


def test_zero_runout_gives_uniform_marks():
    surf, _ = _surface(knives=5)
    m = surf.metrics(2.0, 58.0)
    assert m["uniformity_cv"] < 1e-9
    assert np.ptp(m["mark_depths_um"]) < 1e-9
    assert sorted(set(m["knife"])) == [0, 1, 2, 3, 4]


@pytest.mark.parametrize("delta_um", [0.5, 1.0, 2.0])
def test_runout_widens_its_own_mark(delta_um):
    z, pitch = 4, 1.5
    surf, _ = _surface(knives=z, runout=(0.0, delta_um, 0.0, 0.0))
    widths = np.asarray(surf.widths_mm)
    knife = np.asarray(surf.knife)
    widen = 2 * R * delta_um * 1e-3 / pitch
    assert np.mean(widths[knife == 1]) == pytest.approx(pitch + widen, rel=0.01)
    # its neighbours (knives 0 and 2) each lose half of that; knife 3 is untouched
    assert np.mean(widths[knife == 0]) == pytest.approx(pitch - widen / 2, rel=0.01)
    assert np.mean(widths[knife == 2]) == pytest.approx(pitch - widen / 2, rel=0.01)
    assert np.mean(widths[knife == 3]) == pytest.approx(pitch, rel=1e-9)
    # the deeper knife's mark is also deeper
    depths = np.asarray(surf.depths_um)
    assert depths[knife == 1].mean() > depths[knife == 3].mean()


def test_offsets_equal_to_runout_make_marks_uniform():
    runout = (0.0, 3.0, -1.5, 2.2)
    bad, _ = _surface(runout=runout)
    good, passes = _surface(runout=runout, offsets=runout)
    assert bad.metrics(5, 55)["uniformity_cv"] > 0.05
    assert good.metrics(5, 55)["uniformity_cv"] < 1e-9
    assert np.allclose(passes.bottom_um, 0.0)


def test_eccentricity_acts_as_once_per_turn_runout():
    e = 2.0
    a, _ = _surface(ecc=e)
    b, _ = _surface(runout=tuple(e * math.cos(2 * math.pi * k / 4) for k in range(4)))
    assert np.allclose(a.height_um, b.height_um)


def test_one_knife_finish_threshold_two_knives():
    pitch = 1.5
    threshold_um = 1e3 * pitch**2 / (2 * R)  # the shallow knife's mark closes up
    below, _ = _surface(knives=2, runout=(0.9 * threshold_um, 0.0), feed=300.0)
    above, _ = _surface(knives=2, runout=(1.1 * threshold_um, 0.0), feed=300.0)
    assert set(below.metrics(5, 55)["knife"]) == {0, 1}
    m = above.metrics(5, 55)
    assert set(m["knife"]) == {0}
    assert m["pitch_mm"] == pytest.approx(2 * pitch, rel=1e-9)
    assert m["uniformity_cv"] < 1e-9


@pytest.mark.parametrize("delta_um", [10.0, 30.0, 60.0, 80.0, 120.0])
def test_covered_passes_leave_no_mark_as_brute_force_says(delta_um):
    surf, passes = _surface(knives=4, runout=(delta_um, 0.0, 0.0, 0.0), step=0.002)
    _, owner = _brute_height(surf.x_mm, passes)
    sel = (surf.x_mm > 10) & (surf.x_mm < 50)
    knives_seen = set(passes.knife[owner[sel]].tolist())
    assert set(surf.metrics(10, 50)["knife"]) == knives_seen
    assert np.array_equal(passes.knife[owner[sel]], passes.knife[surf.owner[sel]])


def test_one_knife_finish_four_knives():
    # knife 0 deeper than (2 p)^2 / (2 R) covers even the knife opposite to it
    surf, _ = _surface(knives=4, runout=(1.05e3 * (2 * 1.5) ** 2 / (2 * R), 0, 0, 0))
    m = surf.metrics(5, 55)
    assert set(m["knife"]) == {0}
    assert m["pitch_mm"] == pytest.approx(4 * 1.5, rel=1e-9)


def test_kinematic_metrics_count_a_vanished_knife_as_width_zero():
    # knife 2 cuts 25 um shallower than its equal neighbours (> f^2 / (2 R) = 18.75 um): no
    # mark; by symmetry knives 1 and 3 each take half of its pass, knife 0 keeps one pass
    p = 1.5
    surf, _ = _surface(knives=4, runout=(0.0, 0.0, -25.0, 0.0))
    m = surf.metrics(5, 55)
    assert 2 not in m["knife"] and m["vanished_knives"] == [2]
    assert np.allclose(m["knife_widths_mm"], [p, 1.5 * p, 0.0, 1.5 * p], rtol=1e-9)
    assert m["kinematic_cv"] == pytest.approx(math.sqrt(1.5 / 4), rel=1e-9)
    assert m["pass_pitch_mm"] == pytest.approx(p, rel=0.04)  # the ends' overhang
    assert m["pitch_mm"] == pytest.approx(4 / 3 * p, rel=0.02)  # the marks found: biased
    assert m["uniformity_cv"] < m["kinematic_cv"]
    # every knife marking: the kinematic CV is the marks' CV (per knife, whole passes)
    surf, _ = _surface(knives=4, runout=(0.0, 4.0, -2.0, 2.0))
    m = surf.metrics(5, 55)
    assert m["vanished_knives"] == [] and min(m["knife_widths_mm"]) > 0
    assert m["kinematic_cv"] == pytest.approx(m["uniformity_cv"], rel=0.05)
    assert m["pass_pitch_mm"] == pytest.approx(m["pitch_mm"], rel=1e-12)
    empty = surf.metrics(10.0, 10.5)
    assert empty["vanished_knives"] == [] and math.isnan(empty["kinematic_cv"])


def test_envelope_equals_brute_force_on_random_passes():
    rng = np.random.default_rng(7)
    n = 200
    x = np.cumsum(rng.uniform(0.0, 2.0, n))
    x[50] = x[49]  # a pass repeated at the same place (feed stopped)
    x[80] = x[79] + 1e-7
    b = rng.normal(0.0, 5.0, n)
    k = rng.integers(0, 6, n)
    order = rng.permutation(n)
    passes = Passes(x[order], b[order], k[order], 40.0)
    xs = np.linspace(x[0], x[-1], 20001)
    surf = envelope(xs, passes)
    ref, owner = _brute_height(xs, passes)
    assert np.max(np.abs(surf.height_um - ref)) < 1e-9
    same = passes.bottom_um[surf.owner] == passes.bottom_um[owner]
    assert same.mean() > 0.999  # ties only at cusps
    # every cusp is where its two circles meet
    env = surf.passes
    r = env.radius_mm
    for side in (0, 1):
        j = np.arange(surf.cusps_mm.size) + side
        dx = surf.cusps_mm - env.x_mm[j]
        h = env.bottom_um[j] + 1e3 * (r - np.sqrt(r * r - dx * dx))
        assert np.max(np.abs(h - surf.cusp_heights_um)) < 1e-7
    # ownership switches in the dense sampling agree with the exact cusps
    switches = xs[1:][surf.owner[1:] != surf.owner[:-1]]
    near = np.min(np.abs(switches[:, None] - surf.cusps_mm[None, :]), axis=1)
    assert near.max() <= xs[1] - xs[0]
    assert np.all(np.diff(surf.cusps_mm) > 0)
    assert np.allclose(surf.height_at(xs), surf.height_um)


def test_marks_follow_the_knife_sequence_and_phase():
    z, pitch, phase = 3, 1.2, 0.37
    surf, passes = _surface(knives=z, feed=pitch * 100 * z, phase=phase)
    # knife 0 passes BDC at phase_mm; later passes lie toward -x with the next knife
    j = np.round((passes.x_mm - phase) / pitch).astype(int)
    assert np.allclose(passes.x_mm, phase + j * pitch)
    assert np.array_equal(passes.knife, np.mod(-j, z))
    # a mark's lowest point is where its knife passed BDC
    assert np.allclose(surf.bottoms_mm, passes.x_mm[surf.mark_pass])
    assert np.array_equal(np.mod(np.diff(surf.knife), z), np.full(surf.knife.size - 1, z - 1))


def test_metrics_window_and_empty_window():
    surf, _ = _surface()
    m = surf.metrics(10.0, 20.0)
    assert m["n_marks"] == len(m["mark_widths_mm"]) == len(m["cusps_mm"]) - 1
    assert m["cusps_mm"][0] >= 10.0 and m["cusps_mm"][-1] <= 20.0
    assert m["n_marks"] in (5, 6)
    empty = surf.metrics(10.0, 10.5)
    assert empty["n_marks"] == 0 and math.isnan(empty["pitch_mm"])


def test_passes_helpers():
    _, a = _surface(x0=0.0, x1=10.0)
    _, b = _surface(x0=20.0, x1=30.0)
    both = concat_passes([a, b])
    assert len(both) == len(a) + len(b)
    assert len(a.concat(b)) == len(both)
    cut = both.slice(5.0, 25.0)
    assert np.all((cut.x_mm >= 5.0) & (cut.x_mm <= 25.0))
    s = b.concat(a).sorted()
    assert np.all(np.diff(s.x_mm) >= 0)
    with pytest.raises(ValueError, match="radius"):
        concat_passes([a, Passes(a.x_mm, a.bottom_um, a.knife, 30.0)])


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"knives": 0}, "knives"),
        ({"knives": 2.5}, "knives"),
        ({"radius_mm": -1.0}, "radius_mm"),
        ({"runout_um": (0.0, 1.0)}, "runout_um"),
        ({"runout_um": (0.0, float("nan"), 0.0, 0.0)}, "runout_um"),
        ({"eccentricity_um": float("inf")}, "eccentricity_um"),
    ],
)
def test_cutterhead_rejects_bad_input(kwargs, name):
    args = {"knives": 4, "radius_mm": R, "runout_um": (0.0,) * 4} | kwargs
    with pytest.raises(ValueError, match=name):
        Cutterhead(**args)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"spindle_rpm": 0.0}, "spindle_rpm"),
        ({"feed_mm_s": -5.0}, "feed_mm_s"),
        ({"feed_mm_s": 1e6}, "feed_mm_s"),
        ({"x_end_mm": -1.0}, "x_end_mm"),
        ({"x_start_mm": float("nan")}, "x_start_mm"),
        ({"offsets_um": (1.0, 2.0)}, "offsets_um"),
        ({"phase_mm": float("inf")}, "phase_mm"),
    ],
)
def test_passes_steady_rejects_bad_input(kwargs, name):
    args = {"spindle_rpm": 6000.0, "feed_mm_s": 600.0, "x_start_mm": 0.0, "x_end_mm": 10.0}
    with pytest.raises(ValueError, match=name):
        passes_steady(Cutterhead(4, R, (0.0,) * 4), **(args | kwargs))


def test_passes_and_envelope_reject_bad_input():
    with pytest.raises(ValueError, match="x_mm, bottom_um and knife"):
        Passes(np.zeros(3), np.zeros(2), np.zeros(3, int), R)
    with pytest.raises(ValueError, match="bottom_um"):
        Passes(np.zeros(2), np.array([0.0, np.nan]), np.zeros(2, int), R)
    with pytest.raises(ValueError, match="radius_mm"):
        Passes(np.zeros(2), np.zeros(2), np.zeros(2, int), 0.0)
    _, p = _surface(x0=0.0, x1=10.0)
    with pytest.raises(ValueError, match="x_mm"):
        envelope(np.array([0.0, np.nan]), p)
    with pytest.raises(ValueError, match="reach"):
        envelope(np.array([500.0]), p)
    with pytest.raises(ValueError, match="passes"):
        envelope(np.zeros(3), Passes(np.zeros(0), np.zeros(0), np.zeros(0, int), R))


@settings(max_examples=40, deadline=None)
@example(  # passes 0.1 um apart at different heights (the feed crawling to a stop)
    gaps=[2.638106176421402e-60, 1.192092896e-07], bottoms=[-3.0, -2.0] + [0.0] * 39, radius=20.0
)
@example(gaps=[2.638106176421402e-60, 1.192092896e-07], bottoms=[-4.0, -2.0] + [0.0] * 39,
         radius=20.0)
@given(
    gaps=st.lists(st.floats(0.0, 3.0), min_size=1, max_size=40),
    bottoms=st.lists(st.floats(-30.0, 30.0), min_size=41, max_size=41),
    radius=st.floats(20.0, 200.0),
)
def test_envelope_property_matches_brute_force(gaps, bottoms, radius):
    x = np.concatenate([[0.0], np.cumsum(gaps)])
    b = np.asarray(bottoms[: x.size])
    passes = Passes(x, b, np.arange(x.size) % 4, radius)
    xs = np.linspace(x[0] - 1.0, x[-1] + 1.0, 801)
    surf = envelope(xs, passes)
    ref, _ = _brute_height(xs, passes)
    assert np.max(np.abs(surf.height_um - ref)) < 1e-7
    assert np.all(np.diff(surf.cusps_mm) > 0)
    assert np.all(surf.widths_mm > 0) and np.all(surf.depths_um >= -1e-9)
    if surf.cusps_mm.size > 1:
        span = surf.cusps_mm[-1] - surf.cusps_mm[0]
        assert surf.widths_mm.sum() == pytest.approx(span)
