"""The feed per pass when a pair's marks were cut, and the knife-phase fit checked against it."""

from __future__ import annotations

import pytest

from config.machine import MAX_PASS_TOLERANCE, machine_from_dict
from controller.fieldbus.plc_protocol import PlcSnapshot
from controller.service.cut_feed import (
    CutFeed,
    CutFeedSource,
    PairFeedHistory,
    cut_feed,
    pass_disagreement,
)
from controller.service.pitch_check import FeedHistory
from core.errors import ConfigError

CPM = 100.0  # encoder counts per mm
BITS = 16
L_MM = 300.0


def _history(pairs):
    """Pairs ``(position_mm, pass_mm)`` noted in order (wrapped 16-bit counts)."""
    h = PairFeedHistory()
    for i, (pos, pass_mm) in enumerate(pairs):
        h.note(int(pos * CPM) % (1 << BITS), 0.1 * i, pass_mm, 4, counter_bits=BITS,
               counts_per_mm=CPM, keep_mm=L_MM)
    return h


def _cut(h, now_mm, back=(290.0, 330.0), plc=None, t_s=None):
    return cut_feed(h, plc, counts=int(now_mm * CPM) % (1 << BITS), t_s=t_s, knives=4,
                    back_mm=back, counts_per_mm=CPM, counter_bits=BITS)


def test_the_pairs_bracketing_the_cut_give_the_range():
    # a ramp: 0.4 mm per pass at the cut (0-100 mm of travel), 0.5 at the camera's pair
    pairs = [(20.0 * i, 0.4 if 20.0 * i <= 100.0 else 0.5) for i in range(25)]
    h = _history(pairs)  # 0..480 mm, the counter wraps at 655 mm
    got = _cut(h, 400.0)  # cut 70-110 mm back: the pairs at 60..120 mm bracket it
    assert got == CutFeed(0.4, 0.5, CutFeedSource.PAIRS)
    got = _cut(h, 380.0, back=(300.0, 300.0))  # the cut at 80 mm: pairs 80 (exactly)
    assert got == CutFeed(0.4, 0.4, CutFeedSource.PAIRS)


def test_the_counter_wraps():
    pairs = [(600.0 + 20.0 * i, 0.5) for i in range(30)]  # 600 .. 1180 mm: wraps at 655.36
    h = _history(pairs)
    assert _cut(h, 1180.0) == CutFeed(0.5, 0.5, CutFeedSource.PAIRS)


def test_no_pair_behind_the_cut_falls_back_on_the_plc_or_nothing():
    h = _history([(0.0, 0.5), (20.0, 0.5)])
    assert _cut(h, 40.0) is None  # nothing reaches back 290 mm, no PLC history
    plc = FeedHistory()
    for i in range(300):  # 0.6 s at 200 mm/s: 120 mm, the cut lies 1.5 s back
        plc.note(PlcSnapshot(values={
            "knives": 4, "feed_min_mm_s": 50.0, "feed_max_mm_s": 1000.0, "spindle_rpm": 6000.0,
            "cutterhead_radius_mm": 60.0, "cutter_to_camera_mm": L_MM,
            "feed_setpoint_mm_s": 200.0, "feed_actual_mm_s": 200.0}, t_s=0.02 * i))
    got = _cut(h, 40.0, plc=plc, t_s=5.9)
    assert got.source is CutFeedSource.PLC
    assert (got.lo_mm, got.hi_mm) == (pytest.approx(0.5), pytest.approx(0.5))
    assert _cut(h, 40.0, plc=plc, t_s=1.0) is None  # the PLC's history is too short


def test_a_change_of_knives_between_is_not_a_bracket():
    h = PairFeedHistory()
    for i in range(25):
        h.note(int(20.0 * i * CPM), 0.1 * i, 0.5, 4 if i < 20 else 2, counter_bits=32,
               counts_per_mm=CPM, keep_mm=L_MM)
    assert h.bracket(100.0 * CPM, 140.0 * CPM, 4) is not None
    assert h.bracket(300.0 * CPM, 420.0 * CPM, 4) is None


@pytest.mark.parametrize(
    "fit, lo, hi, refused",
    [
        (0.4996, 0.4996, 0.4996, False),
        (0.3998, 0.4996, 0.4996, True),  # 4/5 of the true travel: one pass in five miscounted
        (0.6250, 0.4996, 0.4996, True),  # 5/4
        (0.5140, 0.4996, 0.4996, False),  # +2.9 %: inside 3 %
        (0.5160, 0.4996, 0.4996, True),  # +3.3 %
        (0.4100, 0.4000, 0.5000, False),  # a ramp: inside the range
    ],
)
def test_the_fit_against_the_feed_per_pass_at_the_cut(fit, lo, hi, refused):
    why = pass_disagreement(fit, CutFeed(lo, hi, CutFeedSource.PAIRS), tolerance=0.03)
    assert (why is not None) is refused
    if refused:
        assert "when the marks were cut" in why and "pairs" in why


def test_nothing_known_nothing_checked_and_bad_arguments_refused():
    assert pass_disagreement(0.2, None, tolerance=0.03) is None
    with pytest.raises(ValueError, match="tolerance"):
        pass_disagreement(0.5, None, tolerance=0.0)
    with pytest.raises(ValueError, match="hi_mm"):
        CutFeed(0.5, 0.4, CutFeedSource.PLC)


@pytest.mark.parametrize("value", [0.0, MAX_PASS_TOLERANCE * 1.01])
def test_pass_tolerance_is_checked_on_load(value):
    with pytest.raises(ConfigError, match="pass_tolerance"):
        machine_from_dict({"plausibility": {"pass_tolerance": value}})


def test_the_bracket_is_the_scan_over_every_pair():
    """The bracketing pairs found by bisection are the straightforward scan's (the last at or
    behind the cut, the first at or ahead; positions exactly on a pair; knives changing)."""
    import random

    rng = random.Random(4)
    for _ in range(300):
        h = PairFeedHistory()
        pos = 0
        for i in range(rng.randrange(1, 60)):
            pos += rng.randrange(1, 400)
            h.note(pos % (1 << BITS), 0.01 * i, rng.uniform(0.3, 2.0),
                   4 if rng.random() < 0.9 else 2, counter_bits=BITS, counts_per_mm=CPM,
                   keep_mm=1e6)
        p, pitch, knives = list(h._pos), list(h._pitch), list(h._knives)
        for _ in range(20):
            lo = rng.choice(p) if rng.random() < 0.3 else rng.uniform(-50, p[-1] + 50)
            hi = lo + rng.choice([0.0, rng.uniform(0, 2000)])
            want = None
            if p[0] <= lo and p[-1] >= hi:
                first = max(i for i, v in enumerate(p) if v <= lo)
                last = min(i for i, v in enumerate(p) if v >= hi)
                if all(knives[i] == 4 for i in range(first, last + 1)):
                    span = pitch[first:last + 1]
                    want = (min(span), max(span))
            assert h.bracket(lo, hi, 4) == want


def test_every_source_is_one_cut_feed_gives():
    """No source named that nothing produces: the pairs' bracket, else the PLC's readings."""
    pairs = [(20.0 * i, 0.5) for i in range(25)]
    plc = FeedHistory()
    for i in range(300):
        plc.note(PlcSnapshot(values={
            "knives": 4, "feed_min_mm_s": 50.0, "feed_max_mm_s": 1000.0, "spindle_rpm": 6000.0,
            "cutterhead_radius_mm": 60.0, "cutter_to_camera_mm": L_MM,
            "feed_setpoint_mm_s": 200.0, "feed_actual_mm_s": 200.0}, t_s=0.02 * i))
    given = {_cut(_history(pairs), 400.0).source,
             _cut(_history([(0.0, 0.5), (20.0, 0.5)]), 40.0, plc=plc, t_s=5.9).source}
    assert given == set(CutFeedSource)
