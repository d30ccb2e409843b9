"""Mark-to-knife phase: the formula of docs/architecture.md on synthetic marks, wrap included."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.laws.knife_phase import (
    PassAttribution,
    attribute_marks,
    knives_from_passes,
    pass_numbers,
    phase_offset,
    phase_spread,
    wrapped_difference,
)

WRAP = 1 << 32


def knife_of_marks(bottom_x_mm, *, knives, align_phase=False, **kw):
    """Knife of each mark in the service's two steps: pass numbers, then knives."""
    return knives_from_passes(pass_numbers(bottom_x_mm, **kw), knives, align_phase=align_phase)


def per_knife_mean(widths_mm, knife, knives):
    """Reference: the mean width of each knife's marks, NaN for a knife without marks."""
    w = np.asarray(widths_mm, dtype=float)
    k = np.asarray(knife, dtype=int)
    return np.array([w[k == j].mean() if np.any(k == j) else math.nan for j in range(knives)])


def synthetic_marks(
    *,
    index_latch_counts,
    pitch_mm=1.5,
    knives=4,
    counts_per_mm=100.0,
    px_per_mm=10.0,
    width_px=659,
    cx_px=329.5,
    cutter_to_camera_mm=300.0,
    lead_counts=37,
):
    """Marks of the passes around the latched index pulse, seen in image A.

    Pass j (knife j mod Z) passes BDC at count ``index + j * pitch * cpm``; that board point is
    ``(counts_a - c_j) / cpm`` mm past the cutter at trigger A, i.e. at image position
    ``x = (counts_a - c_j) / cpm - L + cx / ppm``. ``counts_a`` is chosen so that the image
    centre was cut ``lead_counts`` after the index pulse (the latch is the nearest pulse).
    """
    cpm = counts_per_mm
    counts_a = (index_latch_counts + round(cutter_to_camera_mm * cpm) + lead_counts) % WRAP
    j = np.arange(-40, 41)
    c_rel = j * pitch_mm * cpm  # counts after the index pulse
    base = wrapped_difference(counts_a, index_latch_counts)
    x = (base - c_rel) / cpm - cutter_to_camera_mm + cx_px / px_per_mm
    inside = (x >= 0) & (x <= width_px / px_per_mm)
    return dict(
        x=x[inside],
        knife=np.mod(j[inside], knives),
        counts_a=counts_a,
        kw=dict(
            index_latch_counts=index_latch_counts,
            cutter_to_camera_mm=cutter_to_camera_mm,
            counts_per_mm=cpm,
            px_per_mm=px_per_mm,
            cx_px=cx_px,
            pitch_mm=pitch_mm,
        ),
    )


@pytest.mark.parametrize(
    ("a", "b", "diff"),
    [(10, 3, 7), (3, 10, -7), (5, WRAP - 5, 10), (WRAP - 5, 5, -10), (0, 0, 0)],
)
def test_wrapped_difference(a, b, diff):
    assert wrapped_difference(a, b) == diff


def test_wrapped_difference_rejects_out_of_range():
    with pytest.raises(ValueError, match="a"):
        wrapped_difference(WRAP, 0)
    with pytest.raises(ValueError, match="counter_bits"):
        wrapped_difference(1, 0, counter_bits=1)
    assert wrapped_difference(1, 65535, counter_bits=16) == 2


@pytest.mark.parametrize("index", [123_456, 0, WRAP - 30_000, WRAP - 1])
@pytest.mark.parametrize("knives", [1, 2, 4, 6])
def test_knife_of_marks_recovers_the_knives(index, knives):
    s = synthetic_marks(index_latch_counts=index, knives=knives)
    assert s["x"].size > 20
    got = knife_of_marks(s["x"], counts_a=s["counts_a"], knives=knives, **s["kw"])
    assert np.array_equal(got, s["knife"])
    n = pass_numbers(s["x"], counts_a=s["counts_a"], **s["kw"])
    assert np.allclose(n, np.rint(n), atol=1e-9)
    assert phase_spread(n) < 1e-6


def test_wrap_between_index_and_trigger_changes_nothing():
    # the counter wraps between the index latch and trigger A
    s = synthetic_marks(index_latch_counts=WRAP - 1000)
    assert s["counts_a"] < 1 << 20
    got = knife_of_marks(s["x"], counts_a=s["counts_a"], knives=4, **s["kw"])
    assert np.array_equal(got, s["knife"])


def test_later_knife_is_further_upstream():
    # knife k+1 passes BDC after knife k: its mark lies at smaller x in image A
    s = synthetic_marks(index_latch_counts=5000)
    order = np.argsort(-s["x"])  # from downstream (cut first) to upstream
    k = knife_of_marks(s["x"][order], counts_a=s["counts_a"], knives=4, **s["kw"])
    assert np.all(np.mod(np.diff(k), 4) == 1)


@settings(max_examples=50, deadline=None)
@given(
    index=st.integers(0, WRAP - 1),
    noise=st.floats(0.0, 0.3),
    seed=st.integers(0, 1000),
    pitch=st.floats(0.8, 3.0),
)
def test_robust_to_bottom_position_noise_below_half_a_pitch(index, noise, seed, pitch):
    s = synthetic_marks(index_latch_counts=index, pitch_mm=pitch)
    rng = np.random.default_rng(seed)
    x = s["x"] + rng.uniform(-noise, noise, s["x"].size) * pitch
    got = knife_of_marks(x, counts_a=s["counts_a"], knives=4, **s["kw"])
    assert np.array_equal(got, s["knife"])


def test_align_phase_removes_a_constant_latch_offset():
    s = synthetic_marks(index_latch_counts=77_000)
    shift = 0.4 * 1.5 * 100.0  # the encoder lies by 0.4 pitch (counts)
    kw = dict(s["kw"], index_latch_counts=int(s["kw"]["index_latch_counts"] + shift))
    plain = knife_of_marks(s["x"], counts_a=s["counts_a"], knives=4, **kw)
    aligned = knife_of_marks(s["x"], counts_a=s["counts_a"], knives=4, align_phase=True, **kw)
    assert np.array_equal(aligned, s["knife"])
    n = pass_numbers(s["x"], counts_a=s["counts_a"], **kw)
    assert phase_offset(n) == pytest.approx(-0.4, abs=1e-6)
    # 0.4 pitch: the plain formula still rounds right; at 0.6 it would be one knife off
    assert np.array_equal(plain, s["knife"])
    kw6 = dict(s["kw"], index_latch_counts=int(s["kw"]["index_latch_counts"] + 0.6 * 150.0))
    off = knife_of_marks(s["x"], counts_a=s["counts_a"], knives=4, **kw6)
    assert np.array_equal(off, np.mod(s["knife"] - 1, 4))


def test_phase_spread_flags_ambiguous_data():
    rng = np.random.default_rng(1)
    assert phase_spread(rng.integers(-10, 10, 30) + rng.normal(0, 0.02, 30)) < 0.05
    assert phase_spread(rng.uniform(-10, 10, 30)) > 0.2
    assert math.isnan(phase_spread(np.array([])))


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"counts_per_mm": 0.0}, "counts_per_mm"),
        ({"px_per_mm": -1.0}, "px_per_mm"),
        ({"pitch_mm": math.nan}, "pitch_mm"),
        ({"cx_px": math.inf}, "cx_px"),
        ({"counts_a": -1}, "a"),
        ({"knives": 0}, "knives"),
    ],
)
def test_knife_of_marks_rejects_bad_inputs(kwargs, name):
    args = (
        dict(
            counts_a=1000,
            index_latch_counts=0,
            cutter_to_camera_mm=300.0,
            counts_per_mm=100.0,
            px_per_mm=10.0,
            cx_px=329.5,
            pitch_mm=1.5,
            knives=4,
        )
        | kwargs
    )
    with pytest.raises(ValueError, match=name):
        knife_of_marks([1.0, 2.0], **args)


def test_knife_widths_without_missing_passes_are_the_knife_means():
    w = [1.0, 2.0, 3.0, 1.2, 2.2, 5.0]
    k = np.array([0, 1, 2, 0, 1, 2])
    # knife_widths reads the knives and the passes per knife: one mark per pass, none missing
    pa = PassAttribution(passes=-np.arange(6), knife=k, reliable=np.ones(6, bool), pass_mm=1.0,
                         phase=0.0, spread=0.0, passes_per_knife=np.bincount(k, minlength=4))
    m = pa.knife_widths(w)
    assert np.allclose(m[:3], [1.1, 2.1, 4.0])
    assert math.isnan(m[3])
    assert np.allclose(m, per_knife_mean(w, k, 4), equal_nan=True)
    with pytest.raises(ValueError, match="widths_mm"):
        pa.knife_widths(w[:2])
    with pytest.raises(ValueError, match="widths_mm"):
        pa.knife_widths([1.0, math.nan, 3.0, 1.2, 2.2, 5.0])


@pytest.mark.parametrize("align", [False, True])
def test_knives_from_passes_rounds_the_pass_numbers_mod_z(align):
    """The service computes the pass numbers once (spread check, then knives): round, mod Z."""
    rng = np.random.default_rng(4)
    x = np.sort(rng.uniform(0.0, 60.0, 25))
    kw = dict(counts_a=(2**32 - 500), index_latch_counts=1234, cutter_to_camera_mm=300.0,
              counts_per_mm=100.0, px_per_mm=10.0, cx_px=329.5, pitch_mm=1.5)
    passes = pass_numbers(x, **kw)
    got = knives_from_passes(passes, 4, align_phase=align)
    shifted = passes - (phase_offset(passes) if align else 0.0)
    assert np.array_equal(got, np.mod(np.rint(shifted).astype(int), 4))
    assert got.min() >= 0 and got.max() < 4
    with pytest.raises(ValueError, match="passes"):
        knives_from_passes(np.array([0.0, np.nan]), 4)


# ------------------------------------------------------------ strong runout: narrow and no marks
def runout_marks(
    depth_um, *, pitch_mm=1.5, radius_mm=60.0, index=7_000, counts_per_mm=20.0,
    px_per_mm=12.5, width_px=640, cx_px=320.0, cutter_to_camera_mm=300.0, lead_counts=9,
    dx_mm=0.002, min_width_mm=0.0,
):
    """The marks a vision would report on a surface cut with per-knife depths ``depth_um``.

    Every pass j (knife j mod Z) leaves the arc ``h = d_k * 1e-3 + (x - x_j)^2 / (2 R)`` around
    its BDC ``x_j`` (the formula of :func:`synthetic_marks`); the surface is their lower
    envelope. Marks are the runs of one arc on a fine grid (partial ones at the edges dropped,
    runs narrower than ``min_width_mm`` merged into the wider neighbour as a vision would);
    each mark's bottom is its arc's vertex clipped into the mark (the vision's rule).
    """
    d = np.asarray(depth_um, dtype=float)
    z = d.size
    cpm = counts_per_mm
    counts_a = (index + round(cutter_to_camera_mm * cpm) + lead_counts) % WRAP
    j = np.arange(-60, 61)
    base = wrapped_difference(counts_a, index)
    xj = (base - j * pitch_mm * cpm) / cpm - cutter_to_camera_mm + cx_px / px_per_mm
    grid = np.arange(0.0, width_px / px_per_mm, dx_mm)
    h = d[np.mod(j, z)][:, None] * 1e-3 + (grid[None, :] - xj[:, None]) ** 2 / (2 * radius_mm)
    owner = np.argmin(h, axis=0)
    edges = np.flatnonzero(np.diff(owner)) + 1
    starts = np.concatenate(([0], edges))
    ends = np.concatenate((edges, [grid.size]))
    runs = [(grid[a], grid[b - 1] + dx_mm, owner[a]) for a, b in zip(starts, ends, strict=True)]
    runs = runs[1:-1]  # partial marks at the image edges
    cusps = [r[0] for r in runs] + [runs[-1][1]]
    own = [r[2] for r in runs]
    if min_width_mm > 0:
        while True:
            w = np.diff(cusps)
            i = int(np.argmin(w))
            if w[i] >= min_width_mm:
                break
            del own[i]
            del cusps[i + 1 if i + 1 < len(cusps) - 1 else i]
    cusps = np.asarray(cusps)
    own = np.asarray(own)
    bottoms = np.clip(xj[own], cusps[:-1], cusps[1:])
    every = np.arange(own.min(), own.max() + 1)
    return dict(
        bottoms=bottoms, cusps=cusps, widths=np.diff(cusps), knife=np.mod(j[own], z),
        missing=every.size - own.size, passes_knife=np.bincount(np.mod(j[every], z), minlength=z),
        counts_a=counts_a,
        kw=dict(index_latch_counts=index, cutter_to_camera_mm=cutter_to_camera_mm,
                counts_per_mm=cpm, px_per_mm=px_per_mm, cx_px=cx_px),
    )


SCENARIO_E_DEPTHS = (-0.0, -15.0, 8.0, -5.0)  # runout [0, 15, -8, 5] um (deeper = negative)


@pytest.mark.parametrize(
    ("depth_um", "pitch_mm", "min_width_mm"),
    [
        (SCENARIO_E_DEPTHS, 1.5, 0.0),  # one narrow mark per revolution (bottom on its cusp)
        (SCENARIO_E_DEPTHS, 1.5, 0.08),  # ... which the vision does not see (no mark)
        (SCENARIO_E_DEPTHS, 1.0, 0.08),  # two knives leave no mark
        ((0.0, 12.0, 0.0, 0.0), 1.2, 0.08),  # one shallow knife
    ],
)
def test_attribute_marks_under_strong_runout(depth_um, pitch_mm, min_width_mm):
    s = runout_marks(depth_um, pitch_mm=pitch_mm, min_width_mm=min_width_mm)
    inset = np.minimum(s["bottoms"] - s["cusps"][:-1], s["cusps"][1:] - s["bottoms"])
    assert np.any(inset < 1e-9) or s["missing"] > 0  # the hard case, not the easy one
    # the old attribution (pitch = mean mark width, every bottom) fails here
    old = pass_numbers(s["bottoms"], counts_a=s["counts_a"], pitch_mm=s["widths"].mean(),
                       **s["kw"])
    old_knife = knives_from_passes(old, 4, align_phase=True)
    assert phase_spread(old) > 0.15 or not np.array_equal(old_knife, s["knife"])
    pa = attribute_marks(s["bottoms"], s["cusps"], counts_a=s["counts_a"], knives=4,
                         pass_guide_mm=pitch_mm * 1.1, min_inset_mm=0.08, **s["kw"])
    assert np.array_equal(pa.knife, s["knife"])
    assert pa.missing == s["missing"]
    assert np.array_equal(pa.passes_per_knife, s["passes_knife"])
    assert pa.pass_mm == pytest.approx(pitch_mm, rel=1e-3)
    assert pa.spread < 0.02
    assert np.all(np.diff(pa.passes) < 0)  # one pass per mark, later passes upstream
    # widths per knife and pass: a missing pass counts 0, so their mean is the pass pitch
    w = pa.knife_widths(s["widths"])
    span = s["cusps"][-1] - s["cusps"][0]
    assert np.nansum(w * pa.passes_per_knife) == pytest.approx(span)
    if s["missing"]:
        assert span / pa.n_passes == pytest.approx(pitch_mm, rel=0.05)
        assert span / s["widths"].size > 1.15 * pitch_mm  # the mean mark width is not it


def test_attribute_marks_without_missing_marks_is_the_plain_attribution():
    s = synthetic_marks(index_latch_counts=54_321)
    x = np.sort(s["x"])
    kw = {k: v for k, v in s["kw"].items() if k != "pitch_mm"}
    pa = attribute_marks(x, None, counts_a=s["counts_a"], knives=4, pass_guide_mm=1.3, **kw)
    n = pass_numbers(x, counts_a=s["counts_a"], **s["kw"])
    assert np.array_equal(pa.knife, knives_from_passes(n, 4, align_phase=True))
    assert pa.missing == 0 and pa.reliable.all()
    w = np.linspace(1.0, 2.0, x.size)
    assert np.allclose(pa.knife_widths(w), per_knife_mean(w, pa.knife, 4), equal_nan=True)


def test_knife_widths_nan_for_a_knife_without_marks():
    s = runout_marks((0.0, -3.0, 20.0, -3.0), pitch_mm=1.5, min_width_mm=0.08)
    pa = attribute_marks(s["bottoms"], s["cusps"], counts_a=s["counts_a"], knives=4,
                         pass_guide_mm=1.5, min_inset_mm=0.08, **s["kw"])
    w = pa.knife_widths(s["widths"])
    assert 2 not in set(pa.knife.tolist()) and math.isnan(w[2])
    assert np.all(np.isfinite(np.delete(w, 2)))


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (dict(pass_guide_mm=0.0), "pass_guide_mm"),
        (dict(knives=0), "knives"),
        (dict(min_inset_mm=-1.0), "min_inset_mm"),
        (dict(cusps_x_mm=[0.0, 1.0]), "cusps_x_mm"),
        (dict(min_inset_mm=10.0), "inside their marks"),
        (dict(pass_guide_mm=100.0), "one pass"),
    ],
)
def test_attribute_marks_rejects(change, match):
    s = runout_marks(SCENARIO_E_DEPTHS, min_width_mm=0.08)
    args = dict(bottom_x_mm=s["bottoms"], cusps_x_mm=s["cusps"], counts_a=s["counts_a"],
                knives=4, pass_guide_mm=1.5, min_inset_mm=0.08, **s["kw"])
    args.update(change)
    with pytest.raises(ValueError, match=match):
        attribute_marks(**args)


# ------------------------------------------- pitch 0.5 mm: a knife whose mark is gone or a sliver
# Knives 1 and 3 cut 0.25 um deeper than knife 0; knife 2 shallower by ``d2`` um: at 0.5 mm per
# pass its mark is a sliver (1.6 um: 0.056 mm, 1.8 um: 0.008 mm) or gone (2.0 um), and knife
# 0's is 0.44 mm between the 0.78 mm of knives 1 and 3 -- the states the envelope's pitch
# 0.5 mm corner crosses. The vision resolves marks of about a sample (0.08 mm at 12.5 px/mm).
@pytest.mark.parametrize(
    ("d2", "min_width_mm", "missing", "knife_2_mm"),
    [
        (2.0, 0.0, 25, 0.0),  # gone: its neighbours met
        (1.6, 0.0, 0, 0.056),  # a sliver the vision reports: its own pass, its width
        (1.8, 0.0, 0, 0.008),
        (1.6, 0.08, 25, 0.0),  # a sliver the vision does not see: the pass left no mark
    ],
)
def test_a_gone_or_sliver_mark_at_half_a_millimetre_gets_its_knife(d2, min_width_mm, missing,
                                                                   knife_2_mm):
    s = runout_marks((0.0, -0.25, d2, -0.25), pitch_mm=0.5, min_width_mm=min_width_mm)
    pa = attribute_marks(s["bottoms"], s["cusps"], counts_a=s["counts_a"], knives=4,
                         pass_guide_mm=0.5, min_inset_mm=0.08, **s["kw"])
    assert np.array_equal(pa.knife, s["knife"])
    assert pa.missing == s["missing"] == missing
    assert pa.pass_mm == pytest.approx(0.5, rel=1e-3) and pa.spread < 0.02
    w = pa.knife_widths(s["widths"])
    if missing:
        assert 2 not in set(pa.knife.tolist()) and math.isnan(w[2])  # the service sets 0
    else:
        assert w[2] == pytest.approx(knife_2_mm, abs=0.003)
    assert w[0] == pytest.approx(0.44, abs=0.01)
    assert np.nansum(w) == pytest.approx(2.0, abs=0.01)  # the marks' sum per revolution
    assert 0.74 < min(w[1], w[3]) <= max(w[1], w[3]) < 0.82  # (an unseen sliver joins one)


def test_two_reliable_bottoms_closer_than_a_pass_still_fail():
    # bottoms at knife BDCs are whole passes apart: two inside their marks (by more than the
    # inset) 0.18 mm apart are not where knives passed -- refused, not attributed
    s = runout_marks((0.0, -0.25, 2.0, -0.25), pitch_mm=0.5)
    b, c = s["bottoms"].copy(), s["cusps"]
    i = int(np.flatnonzero(s["knife"] == 0)[2])  # knife 0's narrow mark and the next one
    b[i], b[i + 1] = c[i + 1] - 0.09, c[i + 1] + 0.09
    with pytest.raises(ValueError, match="two mark bottoms"):
        attribute_marks(b, c, counts_a=s["counts_a"], knives=4, pass_guide_mm=0.5,
                        min_inset_mm=0.08, **s["kw"])
