"""The board's speed history: the feed per knife pass a board at the camera was cut with."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.laws.board_speed import BoardSpeedHistory


def _ramp(h, t_end=5.0, dt=0.02):
    """800 -> 300 mm/s at 500 mm/s^2 from 1 s; 6000 rpm, 4 knives (400 passes per second)."""
    for t in np.arange(0.0, t_end + 1e-9, dt):
        v = 800.0 if t < 1.0 else max(300.0, 800.0 - 500.0 * (t - 1.0))
        h.record(float(t), v, 400.0)


def test_walking_back_the_travel_finds_the_feed_of_the_cut():
    h = BoardSpeedHistory()
    _ramp(h)
    # at 5.0 s the board has moved at 300 mm/s since 2.0 s: 300 mm back is 4.0 s -> 0.75 mm
    assert h.pass_travel_mm(5.0, back_mm=300.0) == pytest.approx(300.0 / 400.0)
    # 1500 mm back reaches into the ramp; the travel there is the integral of the samples
    t = np.arange(0.0, 5.0 + 1e-9, 0.02)
    v = np.where(t < 1.0, 800.0, np.maximum(300.0, 800.0 - 500.0 * (t - 1.0)))
    d = np.concatenate(([0.0], np.cumsum(v[:-1] * 0.02)))
    k = np.searchsorted(d, d[-1] - 1500.0, side="right") - 1
    assert h.pass_travel_mm(5.0, back_mm=1500.0) == pytest.approx(v[k] / 400.0)
    assert v[k] > 300.0  # cut faster than the feed at the pair


def test_no_answer_before_the_history_or_for_a_standing_spindle():
    h = BoardSpeedHistory()
    assert h.pass_travel_mm(1.0, back_mm=0.0) is None
    h.record(0.0, 600.0, 400.0)
    h.record(1.0, 600.0, 400.0)
    assert h.pass_travel_mm(1.0, back_mm=601.0) is None  # before the first sample
    assert h.pass_travel_mm(-0.5, back_mm=0.0) is None
    h.record(2.0, 600.0, 0.0)  # spindle stopped
    assert h.pass_travel_mm(2.5, back_mm=100.0) is None
    assert h.pass_travel_mm(2.5, back_mm=400.0) == pytest.approx(1.5)


def test_readings_that_go_back_in_time_or_make_no_sense_are_ignored_and_old_ones_dropped():
    h = BoardSpeedHistory(horizon_s=10.0)
    h.record(0.0, 600.0, 400.0)
    h.record(1.0, 900.0, 400.0)
    h.record(0.5, 100.0, 400.0)  # older: ignored
    h.record(1.0, 300.0, 400.0)  # same instant: replaces
    for bad in (float("nan"), -1.0, float("inf")):
        h.record(2.0, bad, 400.0)
    assert len(h) == 2
    assert h.pass_travel_mm(2.0, back_mm=150.0) == pytest.approx(0.75)
    for i in range(3, 40):
        h.record(float(i), 600.0, 400.0)
    assert len(h) <= 12  # the horizon keeps about 10 s
    with pytest.raises(ValueError, match="back_mm"):
        h.pass_travel_mm(39.0, back_mm=-1.0)


@settings(max_examples=50, deadline=None)
@given(speeds=st.lists(st.floats(50.0, 1000.0), min_size=2, max_size=40),
       back=st.floats(0.0, 2000.0))
def test_the_answer_is_one_of_the_recorded_feeds_per_pass(speeds, back):
    h = BoardSpeedHistory()
    for i, v in enumerate(speeds):
        h.record(0.1 * i, v, 400.0)
    got = h.pass_travel_mm(0.1 * (len(speeds) - 1), back_mm=back)
    travelled = sum(v * 0.1 for v in speeds[:-1])
    if back > travelled:
        assert got is None
    else:
        assert got is not None and any(got == pytest.approx(v / 400.0) for v in speeds)
