"""The service's check of a measured pitch against the feed per pass the PLC reports.

A table of good and bad inputs through :class:`MeasurementStage` (the PLC's readings every
cycle as the service gives them, then the pair's pitch), the history's edge cases, the vision's
own flag, and the flagged pair's record.
"""

from __future__ import annotations

import math
import random
from types import SimpleNamespace

import pytest

from config.machine import PlausibilityConfig, machine_from_dict
from controller.fieldbus.plc_protocol import PlcSnapshot
from controller.service.measurement import MeasurementStage
from controller.service.pitch_check import (
    LATENCY_S,
    CuttingFeed,
    FeedHistory,
    Flagged,
    flag_reason_of,
    pitch_disagreement,
)
from core.errors import ConfigError
from protocol.frames import Frame

CYCLE_S = 0.02
L_MM = 300.0


def _snap(t_s: float, feed: float = 600.0, rpm: float = 6000.0, knives: int = 4) -> PlcSnapshot:
    return PlcSnapshot(values={
        "knives": knives, "feed_min_mm_s": 50.0, "feed_max_mm_s": 1000.0, "spindle_rpm": rpm,
        "cutterhead_radius_mm": 60.0, "cutter_to_camera_mm": L_MM, "feed_setpoint_mm_s": feed,
        "feed_actual_mm_s": feed,
    }, t_s=t_s)


def _frame(speed: float = 600.0) -> Frame:
    return Frame(seq=1, t_s=0.0, image_a=None, image_b=None, counts_a=0, counts_b=0,
                 speed_mm_s=speed)


def _stage(tolerance: float = 0.01) -> MeasurementStage:
    return MeasurementStage(PlausibilityConfig(pitch_tolerance=tolerance),
                            lambda shape: None, threaded=False)


def _feed_at(profile, t):
    """The feed of ``profile`` (list of (from_s, feed)) at ``t``."""
    feed = profile[0][1]
    for t0, f in profile:
        if t >= t0:
            feed = f
    return feed


# (name, feed profile over the 2 s before the pair: [(from_s, mm/s)], rpm, pitch, flagged?)
CASES = [
    ("steady, exact", [(0.0, 600.0)], 6000.0, 1.500, False),
    ("steady, within the tolerance", [(0.0, 600.0)], 6000.0, 1.512, False),
    ("steady, just below it", [(0.0, 600.0)], 6000.0, 1.486, False),
    ("steady, 2 % long: a defect taken for marks", [(0.0, 600.0)], 6000.0, 1.530, True),
    ("steady, 3 % short", [(0.0, 600.0)], 6000.0, 1.455, True),
    ("steady, another spindle speed", [(0.0, 600.0)], 4500.0, 2.000, False),
    ("steady, 1.5 mm at 4500 rpm is wrong", [(0.0, 600.0)], 4500.0, 1.500, True),
    ("feed stepped after the cut: not known, not checked", [(0.0, 800.0), (1.5, 600.0)],
     6000.0, 1.900, False),
    ("feed stepped before the cut: known again", [(0.0, 800.0), (0.5, 600.0)],
     6000.0, 1.900, True),
    ("feed ripple of 0.2 % is steady", [(0.0, 600.0), (1.0, 601.2), (1.5, 600.0)],
     6000.0, 1.545, True),
]


@pytest.mark.parametrize("name, profile, rpm, pitch, flagged", CASES, ids=[c[0] for c in CASES])
def test_pitch_against_the_cutting_feed(name, profile, rpm, pitch, flagged):
    stage = _stage()
    t_pair = 2.0
    for i in range(int(t_pair / CYCLE_S) + 1):  # the PLC cycles, as the service calls prepare
        t = i * CYCLE_S
        stage.prepare(_snap(t, _feed_at(profile, t), rpm))
    snap = _snap(t_pair, _feed_at(profile, t_pair), rpm)
    error = stage.implausible_pitch(pitch, _frame(snap.feed_actual_mm_s), snap)
    assert (error is not None) == flagged, error
    if flagged:
        assert isinstance(error, Flagged) and error.startswith("flagged: pitch")
        assert flag_reason_of(error) == error.removeprefix("flagged: ")
        assert f"{pitch:.3f} mm" in error and "tolerance 1 %" in error
    assert flag_reason_of("implausible: x") is None


def test_the_wide_ratios_come_first_and_are_not_a_flag():
    stage = _stage()
    snap = _snap(2.0)
    error = stage.implausible_pitch(3.2, _frame(), snap)  # ratio 2.1
    assert error.startswith("implausible: pitch") and not isinstance(error, Flagged)


def test_no_history_back_to_the_cut_is_not_checked():
    stage = _stage()
    for i in range(10):  # 0.2 s of readings: the cut was 0.55 s + latency ago
        stage.prepare(_snap(i * CYCLE_S))
    assert stage.implausible_pitch(1.7, _frame(), _snap(10 * CYCLE_S)) is None
    h = FeedHistory()
    assert h.cutting_feed(1.0, travel_mm=330.0) is None  # nothing at all
    h.note(None)
    h.note(_snap(0.0, rpm=0.0))  # spindle stopped: not a reading to check against
    h.note(_snap(0.1, feed=math.nan))
    assert len(h) == 0


def test_the_window_reaches_back_over_the_travel_at_the_slowest_feed():
    h = FeedHistory()
    for i in range(201):
        h.note(_snap(i * CYCLE_S, feed=300.0))
    # 330 mm at 300 mm/s = 1.1 s (+ latency) back from 4.0 s: inside the history
    got = h.cutting_feed(4.0, travel_mm=330.0)
    assert got is not None and got.pitch_mm == pytest.approx(0.75)
    assert got.spread == 0.0 and got.knives == 4
    # just before 1.1 s + latency the history (from 0 s) does not reach back to the cut
    assert h.cutting_feed(1.1 + LATENCY_S - 0.01, travel_mm=330.0) is None
    assert h.cutting_feed(1.1 + LATENCY_S + 0.01, travel_mm=330.0) is not None


def test_a_change_of_knives_is_not_known():
    h = FeedHistory()
    for i in range(101):
        h.note(_snap(i * CYCLE_S, knives=4 if i < 80 else 2))
    assert h.cutting_feed(2.0, travel_mm=330.0) is None


def test_pitch_disagreement_checks_its_arguments():
    steady = CuttingFeed(feed_mm_s=600.0, spindle_rpm=6000.0, knives=4, spread=0.0)
    assert pitch_disagreement(1.5, steady, tolerance=0.01) is None
    assert pitch_disagreement(1.6, None, tolerance=0.01) is None
    with pytest.raises(ValueError, match="tolerance"):
        pitch_disagreement(1.5, steady, tolerance=0.0)
    with pytest.raises(ValueError, match="pitch_mm"):
        pitch_disagreement(math.nan, steady, tolerance=0.01)


def test_the_vision_flag_is_a_flagged_pair():
    stage = _stage()
    meas = SimpleNamespace(pitch_mm=1.5, mark_widths_mm=[1.5] * 8, confidence=0.3,
                           flag_reason="marks explain the shading of A poorly (0.41)")
    error = stage.implausible(meas, _frame(), _snap(1.0))
    assert isinstance(error, Flagged)
    assert error == "flagged: marks explain the shading of A poorly (0.41)"
    assert error.flag_reason == meas.flag_reason
    assert stage.implausible(SimpleNamespace(**{**vars(meas), "flag_reason": None}),
                             _frame(), _snap(1.0)) is None


def test_pitch_tolerance_is_a_checked_config_key():
    assert machine_from_dict({}).plausibility.pitch_tolerance == 0.01
    cfg = machine_from_dict({"plausibility": {"pitch_tolerance": 0.02}})
    assert cfg.plausibility.pitch_tolerance == 0.02
    for bad in (0.0, -0.01, 0.9, "x"):
        with pytest.raises(ConfigError, match="plausibility.pitch_tolerance"):
            machine_from_dict({"plausibility": {"pitch_tolerance": bad}})


def _cutting_feed_by_scan(h: FeedHistory, t: float, travel: float):
    """The straightforward scan over every reading: what ``cutting_feed`` must give."""
    ts, feed, rpm = list(h._t), list(h._feed), list(h._rpm)
    knives, pitch = list(h._knives), list(h._pitch)
    idx = [i for i, ti in enumerate(ts) if ti <= t]
    if not idx:
        return None
    t0 = t - travel / min(feed[i] for i in idx) - LATENCY_S
    if ts[0] > t0:
        return None
    span = range(max(i for i in idx if ts[i] <= t0), idx[-1] + 1)
    if len({knives[i] for i in span}) != 1:
        return None
    p = [pitch[i] for i in span]
    n = len(p)
    return CuttingFeed(feed_mm_s=sum(feed[i] for i in span) / n,
                       spindle_rpm=sum(rpm[i] for i in span) / n, knives=knives[idx[-1]],
                       spread=(max(p) - min(p)) / (sum(p) / n))


def test_the_cutting_feed_is_the_scan_over_every_reading():
    """Readings found by bisection are the scan's, bit for bit: feeds, speeds and knives that
    change, times asked between, on and beyond the readings."""
    import random

    rng = random.Random(5)
    for _ in range(200):
        h = FeedHistory(history_s=rng.choice([1.0, 10.0]))
        t = 0.0
        for _ in range(rng.randrange(1, 400)):
            t += rng.choice([0.005, 0.02, 0.05])
            h.note(_snap(t, feed=rng.uniform(100.0, 900.0), rpm=rng.uniform(3000.0, 8000.0),
                         knives=4 if rng.random() < 0.97 else 2))
        ts = list(h._t)
        for _ in range(20):
            at = rng.choice(ts) if rng.random() < 0.3 else rng.uniform(ts[0] - 0.5, t + 0.5)
            travel = rng.uniform(10.0, 600.0)
            assert h.cutting_feed(at, travel_mm=travel) == _cutting_feed_by_scan(h, at, travel)


def _pitch_range_as_scanned(h: FeedHistory, t: float, travel: float, knives: int):
    """:meth:`FeedHistory.pitch_range` as it scanned every reading (the formula it keeps)."""
    ts, kn, fd, pt = list(h._t), list(h._knives), list(h._feed), list(h._pitch)
    idx = [i for i, ti in enumerate(ts) if ti <= t and kn[i] == knives]
    if not idx:
        return None
    t0 = t - travel / min(fd[i] for i in idx) - LATENCY_S
    back = [i for i in idx if ts[i] <= t0]
    first = back[-1] if back else idx[0]
    pitches = [pt[i] for i in idx if i >= first]
    return min(pitches), max(pitches), bool(back) and ts[0] <= t0


@pytest.mark.parametrize("seed", range(8))
def test_pitch_range_is_the_scan_of_every_reading(seed):
    """Random feeds and spindles, knife changes or none, times inside, before and after."""
    rng = random.Random(seed)
    h = FeedHistory(history_s=rng.choice([0.5, 3.0, 10.0]))
    t = 0.0
    change = rng.random() < 0.5
    for i in range(rng.randint(0, 600)):
        t += rng.uniform(0.001, 0.03)
        knives = rng.choice([2, 4]) if change and rng.random() < 0.05 else 4
        h.note(_snap(t, feed=rng.uniform(100.0, 900.0), rpm=rng.uniform(3000, 9000),
                     knives=knives))
        if i % 7 == 0:
            for _ in range(3):
                q = rng.uniform(-0.5, t + 0.5)
                travel = rng.choice([1e-9, rng.uniform(0.1, 400.0), 5000.0])
                for z in (2, 4, 6):
                    assert h.pitch_range(q, travel_mm=travel, knives=z) == \
                        _pitch_range_as_scanned(h, q, travel, z)


@pytest.mark.parametrize("seed", range(6))
def test_the_slowest_feed_kept_is_the_minimum_of_the_readings_kept(seed):
    """Kept as the readings come and go (expiry, equal feeds, readings refused): after every
    reading the slowest of all of them and of the first few is the scan's ``min``."""
    rng = random.Random(seed)
    h = FeedHistory(history_s=rng.choice([0.2, 1.0, 10.0]))
    t = 0.0
    for _ in range(rng.randint(50, 700)):
        t += rng.choice([0.0, 0.004, 0.02, 0.05])  # 0.0: the same read again (refused)
        h.note(_snap(t, feed=rng.choice([300.0, rng.uniform(100.0, 900.0)])))
        feeds = list(h._feed)
        assert h._slowest(len(feeds)) == min(feeds)
        upto = rng.randint(1, len(feeds))
        assert h._slowest(upto) == min(feeds[:upto])
