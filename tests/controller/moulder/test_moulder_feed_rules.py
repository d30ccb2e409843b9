"""The coordinator's rules, pure parts: which speed range it may use, where the law restarts,
a refused speed retried."""

from __future__ import annotations

import math

import pytest

from config.heads import HeadConfig
from controller.fieldbus.plc_protocol import PlcSnapshot
from controller.laws.moulder_feed import HeadFeed, MoulderFeedConfig, MoulderFeedLaw
from controller.moulder.feed import _feed_in_force, _speed_range


def _head(**kw) -> HeadConfig:
    return HeadConfig(name="top", face="top", node_id=5, target_pitch_mm=1.0, **kw)


def _snap(rpm=6000.0, lo=None, hi=None, **values) -> PlcSnapshot:
    v = {"spindle_rpm": rpm, "feed_setpoint_mm_s": 600.0, "feed_actual_mm_s": 598.0,
         "feed_min_mm_s": 50.0, "feed_max_mm_s": 1000.0, **values}
    if lo is not None:
        v["spindle_rpm_min"], v["spindle_rpm_max"] = lo, hi
    return PlcSnapshot(values=v, t_s=0.0)


@pytest.mark.parametrize("head, snap, expected", [
    # configured fixed: never a speed write, whatever range the drive reports
    (dict(rpm=6000.0), _snap(6010.0, 3000.0, 12000.0), (6010.0, 6010.0)),
    # configured range within the drive's: the configured one
    (dict(rpm=6000.0, rpm_min=4000.0, rpm_max=8000.0), _snap(6000.0, 3000.0, 12000.0),
     (4000.0, 8000.0)),
    # the drive narrower: the common part
    (dict(rpm=6000.0, rpm_min=4000.0, rpm_max=8000.0), _snap(6000.0, 5000.0, 12000.0),
     (5000.0, 8000.0)),
    # the drive reports nonsense: the configured range
    (dict(rpm=6000.0, rpm_min=4000.0, rpm_max=8000.0), _snap(6000.0, 3000.0, math.inf),
     (4000.0, 8000.0)),
    (dict(rpm=6000.0, rpm_min=4000.0, rpm_max=8000.0), _snap(6000.0, 0.0, 9000.0),
     (4000.0, 8000.0)),
    # nothing in common: fixed at its measured speed
    (dict(rpm=4500.0, rpm_min=4000.0, rpm_max=5000.0), _snap(5500.0, 6000.0, 9000.0),
     (5500.0, 5500.0)),
    # the speed left to the PLC: the drive's range, or fixed without one
    (dict(), _snap(6000.0, 3000.0, 9000.0), (3000.0, 9000.0)),
    (dict(), _snap(6000.0), (6000.0, 6000.0)),
])
def test_the_speed_range_is_the_configured_one_within_the_drives(head, snap, expected):
    assert _speed_range(_head(**head), snap) == expected


@pytest.mark.parametrize("values, expected", [
    ({}, 600.0),
    ({"feed_setpoint_mm_s": 0.0}, 598.0),  # a PLC just restarted: its actual feed
    ({"feed_setpoint_mm_s": 0.0, "feed_actual_mm_s": 0.0}, 50.0),  # standing: the floor
    ({"feed_setpoint_mm_s": 1500.0}, 1000.0),  # never outside the limits
])
def test_the_law_restarts_from_the_feed_in_force_within_the_limits(values, expected):
    assert _feed_in_force(_snap(**values)) == expected


def test_a_speed_not_written_is_commanded_again():
    law = MoulderFeedLaw(MoulderFeedConfig())
    heads = [HeadFeed(name="bottom", knives=4, target_pitch_mm=1.5, rpm_min=6000.0,
                      rpm_max=6000.0, spindle_rpm=6000.0),
             HeadFeed(name="top", knives=6, target_pitch_mm=1.0, rpm_min=4000.0,
                      rpm_max=8000.0, spindle_rpm=6000.0)]
    law.reset(feed_mm_s=600.0, now_s=0.0)
    first = law.update(heads, now_s=0.02, feed_min_mm_s=50.0, feed_max_mm_s=1000.0)
    assert "top" in first.spindle_setpoints_rpm
    again = law.update(heads, now_s=0.04, feed_min_mm_s=50.0, feed_max_mm_s=1000.0)
    assert again.spindle_setpoints_rpm == {}  # within the deadband: not again
    law.forget_setpoint("top")  # the write was refused or lost
    retry = law.update(heads, now_s=0.06, feed_min_mm_s=50.0, feed_max_mm_s=1000.0)
    assert retry.spindle_setpoints_rpm.keys() == {"top"}
