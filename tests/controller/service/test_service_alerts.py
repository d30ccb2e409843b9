"""The operator's alerts: an unreachable target, a chipped knife, failing measurements."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.laws.uniformity_loop import linear_widths_mm, width_sensitivity_mm_per_um
from controller.service.alerts import (
    CHIP_STEP_UM,
    CONFIRM_PAIRS,
    FAILING_WINDOW,
    FailureMonitor,
    KnifeChipMonitor,
    OperatorAlerts,
    TargetReach,
    _column_medians,
)
from controller.service.events import EventKind, EventLog


def _kinds(log: EventLog) -> list[EventKind]:
    return [e.kind for e in log.events]


def test_a_target_beyond_the_feed_cap_is_told_once_with_the_pitch_the_machine_holds():
    log = EventLog()
    reach = TargetReach(log, target_pitch_mm=3.0, tolerance=0.02)
    for i in range(CONFIRM_PAIRS - 1):  # not yet confirmed
        reach.update(i * 0.1, pitch_mm=2.5, feed_mm_s=1000.0, feed_limits_mm_s=(50.0, 1000.0),
                     held_pitch_mm=3.0)
    assert not log.events
    for i in range(20):
        reach.update(1 + i * 0.1, pitch_mm=2.5, feed_mm_s=1000.0,
                     feed_limits_mm_s=(50.0, 1000.0), held_pitch_mm=3.0)
    (ev,) = log.events
    assert ev.kind is EventKind.TARGET_UNREACHABLE and ev.reason == "feed at its maximum"
    assert ev.data["reachable_pitch_mm"] == pytest.approx(2.5)
    assert log.counters["targets_unreachable"] == 1
    for i in range(CONFIRM_PAIRS):  # the spindle sped up: reachable again
        reach.update(5 + i * 0.1, pitch_mm=3.0, feed_mm_s=900.0,
                     feed_limits_mm_s=(50.0, 1000.0), held_pitch_mm=3.0)
    assert _kinds(log)[-1] is EventKind.TARGET_REACHABLE and reach.active is None


def test_a_pitch_off_below_the_cap_is_the_loop_at_work_not_an_alert():
    log = EventLog()
    reach = TargetReach(log, target_pitch_mm=1.5, tolerance=0.02)
    for i in range(30):  # converging: far off, but the feed has room
        reach.update(i * 0.1, pitch_mm=2.0, feed_mm_s=700.0, feed_limits_mm_s=(50.0, 1000.0),
                     held_pitch_mm=1.5)
    assert not log.events


def test_the_depth_ceiling_and_the_feed_minimum_are_told_too():
    log = EventLog()
    reach = TargetReach(log, target_pitch_mm=3.0, tolerance=0.02)
    for i in range(CONFIRM_PAIRS):
        reach.update(i * 0.1, pitch_mm=2.19, feed_mm_s=876.0, feed_limits_mm_s=(50.0, 1000.0),
                     held_pitch_mm=2.19)
    assert log.events[-1].reason == "depth ceiling"
    log2 = EventLog()
    slow = TargetReach(log2, target_pitch_mm=0.1, tolerance=0.02)
    for i in range(CONFIRM_PAIRS):
        slow.update(i * 0.1, pitch_mm=0.5, feed_mm_s=50.0, feed_limits_mm_s=(50.0, 1000.0),
                    held_pitch_mm=0.1)
    assert log2.events[-1].reason == "feed at its minimum"


def test_failing_pairs_are_told_above_half_and_cleared_below_a_fifth():
    log = EventLog()
    mon = FailureMonitor(log)
    for i in range(FAILING_WINDOW):
        mon.pair(i * 0.1, ok=i % 3 != 0, error="x")  # a third fail: not reported
    assert not log.events
    for i in range(FAILING_WINDOW):
        mon.pair(2 + i * 0.1, ok=i % 3 == 0, error="registration failed")
    (ev,) = log.events
    assert ev.kind is EventKind.MEASUREMENTS_FAILING and ev.data["last_error"]
    for i in range(FAILING_WINDOW):
        mon.pair(4 + i * 0.1, ok=True)
    assert _kinds(log)[-1] is EventKind.MEASUREMENTS_RECOVERED


RUNOUT = np.array([0.0, 4.0, -2.0, 2.0])


def _widths(runout, offsets, pitch=1.5, rng=None):
    w = linear_widths_mm(np.asarray(offsets) - runout, pitch_mm=pitch, radius_mm=60.0)
    return w + (0 if rng is None else rng.normal(0, 0.0075, w.size))  # CV 0.005 of noise


@pytest.mark.parametrize(("knife", "step"), [(1, 6.0), (3, -2.5), (0, 2.0)])
def test_a_runout_step_of_one_knife_is_named_on_the_second_pair(knife, step):
    log = EventLog()
    mon = KnifeChipMonitor(log, knives=4, radius_mm=60.0)
    rng = np.random.default_rng(knife)
    offs = RUNOUT - RUNOUT.mean()  # the loop has converged
    mon.timeline.note(0.0, offs)
    for i in range(20):
        assert not mon.pair(i * 0.1, widths_mm=_widths(RUNOUT, offs, rng=rng), pitch_mm=1.5,
                            cut_at_s=i * 0.1 - 0.5)
    chipped = RUNOUT.copy()
    chipped[knife] += step
    got = [mon.pair(2 + i * 0.1, widths_mm=_widths(chipped, offs, rng=rng), pitch_mm=1.5,
                    cut_at_s=1.5 + i * 0.1) for i in range(5)]
    assert got == [False, True, False, False, False]
    (ev,) = log.events
    assert ev.kind is EventKind.KNIFE_CHIPPED and ev.data["knife"] == knife
    assert ev.data["runout_step_um"] == pytest.approx(step, abs=0.5)


def test_noise_and_the_loops_own_table_moves_are_no_chip():
    log = EventLog()
    mon = KnifeChipMonitor(log, knives=4, radius_mm=60.0)
    rng = np.random.default_rng(7)
    mon.timeline.note(-1.0, np.zeros(4))
    for i in range(300):  # the loop learning from zero: its tables show at the camera
        t = i * 0.1
        table = (RUNOUT - RUNOUT.mean()) * min(1.0, max(0.0, (t - 3.0) / 3.0))
        mon.timeline.note(t, table)
        mon.pair(t, widths_mm=_widths(RUNOUT, mon.timeline.at(t - 0.5), rng=rng),
                 pitch_mm=1.5, cut_at_s=t - 0.5)
    assert not log.events
    assert CHIP_STEP_UM > 5 * 0.2  # the threshold stands well above the widths' noise


def test_the_status_carries_what_is_active():
    log = EventLog()
    alerts = OperatorAlerts(log, target_pitch_mm=3.0, tolerance=0.02)
    alerts.machine(4, 60.0)
    assert alerts.describe() == {"target_unreachable": None, "measurements_failing": None,
                                 "knife_chipped": None}
    for i in range(CONFIRM_PAIRS):
        alerts.target.update(i * 0.1, pitch_mm=2.5, feed_mm_s=1000.0,
                             feed_limits_mm_s=(50.0, 1000.0), held_pitch_mm=3.0)
    assert alerts.describe()["target_unreachable"]["reason"] == "feed at its maximum"


def test_a_table_of_other_knives_or_none_is_no_comparison():
    mon = KnifeChipMonitor(EventLog(), knives=4, radius_mm=60.0)
    assert not mon.pair(0.0, widths_mm=[1.5] * 4, pitch_mm=1.5, cut_at_s=None)  # no table yet
    mon.timeline.note(0.0, ())  # an actuator that has not been told its knives
    assert not mon.pair(0.1, widths_mm=[1.5] * 4, pitch_mm=1.5, cut_at_s=0.05)


@pytest.mark.parametrize("rows", [1, 2, 4, 5, 6])
def test_column_medians_are_numpys(rows):
    """The chip reference's medians per knife: ``np.median(axis=0)``'s values (odd and even
    counts, ties; a median of zeros may differ in its sign, which the monitor's absolute
    differences do not see), NaN where a column holds one."""
    rng = np.random.default_rng(rows)
    for _ in range(200):
        z = int(rng.integers(3, 9))
        a = np.round(rng.normal(0.0, 3.0, (rows, z)), int(rng.integers(0, 4)))
        if rng.random() < 0.1:
            a[rng.integers(rows), rng.integers(z)] = np.nan
        want = np.median(a, axis=0)
        got = _column_medians(list(a))
        np.testing.assert_array_equal(np.array(got), want)


@pytest.mark.parametrize("knives", [3, 4, 6, 8])
def test_the_runout_a_pair_shows_is_the_array_formula_bit_for_bit(knives):
    """The chip monitor's runout in plain floats is ``s - s.mean()``, ``s = o - D^+ (w -
    w.mean()) / G`` on arrays (the formula it replaced), the same bits; a vanished mark (NaN)
    counts 0."""
    rng = np.random.default_rng(knives)
    mon = KnifeChipMonitor(EventLog(), knives=knives, radius_mm=60.0)
    for _ in range(300):
        pitch = float(rng.uniform(0.5, 3.0))
        widths = rng.normal(pitch, 0.05 * pitch, knives)
        if rng.random() < 0.2:
            widths[rng.integers(knives)] = np.nan
        o_cut = rng.normal(0.0, 5.0, knives)
        w = np.array([0.0 if not math.isfinite(v) else float(v) for v in widths])
        y = mon._d_pinv @ (w - w.mean()) / width_sensitivity_mm_per_um(pitch, 60.0)
        s = o_cut - y
        want = s - s.mean()
        got = mon._runout(widths.tolist(), pitch, o_cut.tolist())
        assert [v.hex() for v in got] == [float(v).hex() for v in want]
