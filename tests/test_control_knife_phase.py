"""Mark-to-knife phase: the formula of docs/architecture.md on synthetic marks, wrap included."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.knife_phase import (
    knife_means,
    knife_of_marks,
    knives_from_passes,
    pass_numbers,
    phase_offset,
    phase_spread,
    wrapped_difference,
)

WRAP = 1 << 32


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


def test_knife_means():
    w = [1.0, 2.0, 3.0, 1.2, 2.2, 5.0]
    k = [0, 1, 2, 0, 1, 2]
    m = knife_means(w, k, 4)
    assert np.allclose(m[:3], [1.1, 2.1, 4.0])
    assert math.isnan(m[3])
    assert np.all(np.isnan(knife_means([], np.array([], dtype=int), 3)))
    with pytest.raises(ValueError, match="knife_of_mark"):
        knife_means(w, [0, 1, 2, 0, 1, 4], 4)
    with pytest.raises(ValueError, match="knife_of_mark"):
        knife_means(w, [0, 1], 4)
    with pytest.raises(ValueError, match="widths_mm"):
        knife_means([1.0, math.nan], [0, 1], 4)


@pytest.mark.parametrize("align", [False, True])
def test_knives_from_passes_is_knife_of_marks_in_two_steps(align):
    """The service computes the pass numbers once (spread check, then knives): same answer."""
    rng = np.random.default_rng(4)
    x = np.sort(rng.uniform(0.0, 60.0, 25))
    kw = dict(counts_a=(2**32 - 500), index_latch_counts=1234, cutter_to_camera_mm=300.0,
              counts_per_mm=100.0, px_per_mm=10.0, cx_px=329.5, pitch_mm=1.5)
    passes = pass_numbers(x, **kw)
    got = knives_from_passes(passes, 4, align_phase=align)
    assert np.array_equal(got, knife_of_marks(x, knives=4, align_phase=align, **kw))
    assert got.min() >= 0 and got.max() < 4
    with pytest.raises(ValueError, match="passes"):
        knives_from_passes(np.array([0.0, np.nan]), 4)
