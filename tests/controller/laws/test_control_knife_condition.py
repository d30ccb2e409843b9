"""The knives' condition: drift fitted from the tables in force, reserve, jointing forecast."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.laws.knife_condition import JointingState, KnifeConditionTracker, Trend
from controller.laws.limits import project_zero_mean_box
from controller.laws.uniformity_loop import linear_widths_mm, width_cv

PITCH, RADIUS, CV_MAX = 1.5, 60.0, 0.05


def _feed(tracker, rates, *, until_m, start=None, step_m=0.5, stroke=20.0):
    """The loop's tables for knives drifting linearly: the needed table, projected."""
    z = len(rates)
    start = np.zeros(z) if start is None else np.asarray(start, float)
    x = 0.0
    while x <= until_m + 1e-9:
        needed = start + np.asarray(rates) * x
        table = project_zero_mean_box(needed - needed.mean(), bound=stroke)
        tracker.update(board_m=x, offsets_um=table)
        x += step_m


def _cv(needed, stroke=20.0):
    needed = needed - needed.mean()
    left = project_zero_mean_box(needed, bound=stroke) - needed
    return width_cv(linear_widths_mm(left, pitch_mm=PITCH, radius_mm=RADIUS))


def test_a_linear_wear_is_fitted_exactly_and_the_forecast_is_where_the_cv_crosses():
    t = KnifeConditionTracker(knives=4, stroke_um=20.0, window_m=10.0)
    rates = np.array([0.6, -0.2, -0.2, -0.2])  # knife 1 wears: 0.8 um/m relative
    _feed(t, rates, until_m=20.0)
    np.testing.assert_allclose(t.rates_um_per_m(), rates, atol=1e-9)
    f = t.forecast(pitch_mm=PITCH, radius_mm=RADIUS, cv_max=CV_MAX, feed_mm_s=600.0,
                   board_length_mm=2000.0)
    # the table leaves the stroke when knife 1's needed offset is 20 um: 20 / 0.6 = 33.3 m
    assert f.due_in_m is not None and 20.0 + f.due_in_m >= 20.0 / 0.6 - 1e-6
    d = 20.0 + f.due_in_m
    assert _cv(rates * d) > CV_MAX >= _cv(rates * (d - 0.1))  # to the forecast's 0.1 m
    assert f.knife == 0 and f.state is JointingState.DUE and f.trend is Trend.SIGNIFICANT
    assert f.due_in_boards == pytest.approx(f.due_in_m / 2.0)
    assert f.due_in_h == pytest.approx(f.due_in_m * 1000 / 600 / 3600)
    assert f.text.startswith("jointing due in ") and "(knife 0)" in f.text  # 0-based, as the page


def test_no_wear_no_forecast_and_the_reserve_is_the_whole_stroke():
    t = KnifeConditionTracker(knives=4, stroke_um=20.0)
    _feed(t, [0.0, 0.0, 0.0, 0.0], until_m=12.0, start=[2.0, -1.0, -1.0, 0.0])
    f = t.forecast(pitch_mm=PITCH, radius_mm=RADIUS, cv_max=CV_MAX, feed_mm_s=600.0,
                   board_length_mm=2000.0)
    assert f.due_in_m is None and "no wear trend" in f.text and "not due" in f.text
    assert f.state is JointingState.NOT_DUE and f.trend is Trend.NONE
    conds = t.conditions()
    assert [c.offset_um for c in conds] == pytest.approx([2.0, -1.0, -1.0, 0.0])
    assert conds[0].reserve_um == pytest.approx(18.0)


def test_before_the_span_no_rate_and_the_forecast_says_it_is_fitting():
    t = KnifeConditionTracker(knives=4, stroke_um=20.0, min_span_m=3.0)
    _feed(t, [0.3, -0.1, -0.1, -0.1], until_m=2.0)
    assert t.rates_um_per_m() is None
    assert all(math.isnan(c.drift_um_per_m) for c in t.conditions())
    f = t.forecast(pitch_mm=PITCH, radius_mm=RADIUS, cv_max=CV_MAX, feed_mm_s=600.0,
                   board_length_mm=2000.0)
    assert f.due_in_m is None and "fitting" in f.text and f.state is JointingState.FITTING


def test_at_the_bound_and_out_of_class_it_is_due_now():
    t = KnifeConditionTracker(knives=4, stroke_um=5.0)
    _feed(t, [0.9, -0.3, -0.3, -0.3], until_m=30.0, stroke=5.0)
    f = t.forecast(pitch_mm=PITCH, radius_mm=RADIUS, cv_max=CV_MAX, feed_mm_s=600.0,
                   board_length_mm=2000.0)
    assert f.due_in_m == 0.0 and f.knife == 0 and "due now" in f.text
    assert f.state is JointingState.DUE


@settings(max_examples=60, deadline=None)
@given(worn=st.integers(0, 3), rate=st.floats(0.2, 3.0), faster=st.floats(1.2, 3.0))
def test_a_faster_wear_is_due_sooner(worn, rate, faster):
    def due(r):
        rates = np.full(4, -r / 4)
        rates[worn] += r
        t = KnifeConditionTracker(knives=4, stroke_um=20.0)
        _feed(t, rates, until_m=5.0)
        return t.forecast(pitch_mm=PITCH, radius_mm=RADIUS, cv_max=CV_MAX, feed_mm_s=600.0,
                          board_length_mm=2000.0).due_in_m

    slow, fast = due(rate), due(rate * faster)
    assert slow is not None and fast is not None and fast <= slow


@pytest.mark.parametrize("kwargs, name", [
    (dict(knives=0, stroke_um=20.0), "knives"),
    (dict(knives=4, stroke_um=0.0), "stroke_um"),
    (dict(knives=4, stroke_um=20.0, window_m=2.0, min_span_m=3.0), "min_span_m"),
])
def test_bad_parameters_name_themselves(kwargs, name):
    with pytest.raises(ValueError, match=name):
        KnifeConditionTracker(**kwargs)


def test_bad_updates_name_the_value():
    t = KnifeConditionTracker(knives=4, stroke_um=20.0)
    t.update(board_m=1.0, offsets_um=[0, 0, 0, 0])
    with pytest.raises(ValueError, match="went back"):
        t.update(board_m=0.5, offsets_um=[0, 0, 0, 0])
    with pytest.raises(ValueError, match="4 values"):
        t.update(board_m=2.0, offsets_um=[0, 0, 0])
    with pytest.raises(ValueError, match=r"offsets_um\[2\]"):
        t.update(board_m=2.0, offsets_um=[0, 0, math.nan, 0])
