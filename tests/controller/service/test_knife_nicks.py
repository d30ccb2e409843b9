"""The knife nick monitor: the defect detector's ridge at one place on consecutive pairs."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from controller.service.alerts import (
    NICK_FORGET_PAIRS,
    NICK_MIN_CONFIDENCE,
    NICK_Y_TOL_MM,
    KnifeNickMonitor,
)
from controller.service.events import EventKind, EventLog


def _nick(y, depth=-12.5, confidence=1.0):
    return SimpleNamespace(kind=SimpleNamespace(value="knife_nick"), y_mm=y, depth_um=depth,
                           confidence=confidence)


def _other(y):
    return SimpleNamespace(kind=SimpleNamespace(value="torn_grain"), y_mm=y, depth_um=200.0,
                           confidence=1.0)


def _told(report):
    return [e for e in report.events if e.kind is EventKind.KNIFE_CHIPPED]


def test_a_nick_on_two_pairs_in_a_row_is_told_once_with_its_place():
    report = EventLog()
    mon = KnifeNickMonitor(report)
    assert not mon.pair(1.0, [_nick(0.5)], seq=10)  # one pair may be an odd one
    assert mon.pair(1.1, [_nick(0.9), _other(3.0)], seq=11)
    for i in range(30):  # the same nick on every pair after: said once
        assert not mon.pair(1.2 + 0.1 * i, [_nick(0.5 + 0.3 * (i % 3))], seq=12 + i)
    (e,) = _told(report)
    assert e.data == {"knife": None, "cause": "nick", "y_mm": 0.9, "ridge_um": 12.5,
                      "runout_step_um": None, "width_change_mm": None, "seq": 11, "t_s": 1.1}
    assert report.counters["knife_chips"] == 1 and mon.nicks == 1 and mon.last == e.data


def test_a_missed_pair_between_still_confirms_and_scattered_ones_do_not():
    report = EventLog()
    mon = KnifeNickMonitor(report)
    mon.pair(0.0, [_nick(5.0)])
    mon.pair(0.1, [])  # the detector missed it
    assert mon.pair(0.2, [_nick(5.4)])  # 2 of the last 3
    other = KnifeNickMonitor(EventLog())
    for i, y in enumerate((0.0, 3.0, 6.0, 9.0, -4.0)):  # ridges here and there: raised grain
        assert not other.pair(0.1 * i, [_nick(y)])
    assert not other.pair(1.0, [_nick(20.0)]) and not other.pair(1.1, [_nick(20.0 + 2.5)])
    assert NICK_Y_TOL_MM < 2.5


def test_pairs_not_looked_at_do_not_count_and_weak_detections_are_left_out():
    report = EventLog()
    mon = KnifeNickMonitor(report)
    mon.pair(0.0, [_nick(1.0)])
    for i in range(10):
        assert not mon.pair(0.1 + i, None)  # no defect list: the measurer did not look
    assert mon.pair(11.0, [_nick(1.0)])  # the window holds the pairs looked at
    weak = KnifeNickMonitor(EventLog())
    for i in range(5):
        assert not weak.pair(0.1 * i, [_nick(1.0, confidence=NICK_MIN_CONFIDENCE / 2)])


def test_a_nick_gone_for_long_is_forgotten_and_told_again_when_it_comes_back():
    report = EventLog()
    mon = KnifeNickMonitor(report)
    mon.pair(0.0, [_nick(1.0)])
    mon.pair(0.1, [_nick(1.0)])
    for i in range(NICK_FORGET_PAIRS - 1):  # a clean stretch, not long enough
        mon.pair(1.0 + i, [])
    mon.pair(100.0, [_nick(1.0)])
    mon.pair(100.1, [_nick(1.0)])
    assert len(_told(report)) == 1
    for i in range(NICK_FORGET_PAIRS):
        mon.pair(200.0 + i, [])
    mon.pair(300.0, [_nick(1.0)])
    mon.pair(300.1, [_nick(1.0)])
    assert len(_told(report)) == 2 and _told(report)[1].t_s == pytest.approx(300.1)


def test_the_status_shows_the_newest_knife_told_chipped_or_nicked():
    from tests.controller.service.test_control_loops_stage import _stage  # the loops stage

    loops = _stage()
    assert loops.describe_alerts()["knife_chipped"] is None
    loops.alerts.machine(4, 60.0)
    loops.alerts.chips.last = {"knife": 2, "cause": "runout_step", "t_s": 5.0}
    assert loops.describe_alerts()["knife_chipped"]["knife"] == 2
    loops.nicks.pair(6.0, [_nick(1.0)])
    loops.nicks.pair(6.1, [_nick(1.0)])
    assert loops.describe_alerts()["knife_chipped"]["cause"] == "nick"
    loops.alerts.chips.last = {"knife": 3, "cause": "runout_step", "t_s": 7.0}
    assert loops.describe_alerts()["knife_chipped"]["knife"] == 3
