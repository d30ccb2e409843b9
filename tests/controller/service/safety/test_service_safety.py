"""Safe-state supervisor: table of timeouts -> SAFE, confirmation -> RUN, safe feed ramp."""

from __future__ import annotations

import pytest

from config.machine import SafetyConfig
from controller.service.supervisor import (
    AMP_CONFIRM_S,
    AmplifierMonitor,
    SafetyState,
    Supervisor,
    amp_problem,
)

CFG = SafetyConfig(
    cycle_s=0.02,
    plc_timeout_s=0.5,
    can_timeout_s=0.3,
    measurement_timeout_s=2.0,
    recovery_s=0.25,
    safe_state="ramp_down",
    safe_feed_mm_s=100.0,
    ramp_mm_s2=500.0,
)
TIMEOUT = {"plc": 0.5, "can": 0.3, "measurement": 2.0}


def feed_all(sup, t, *, skip=()):
    if "plc" not in skip:
        sup.plc_answered(t)
    if "can" not in skip:
        sup.can_heard(t)
    if "measurement" not in skip:
        sup.measurement_valid(t)


def run_until_run(sup, t0=0.0, dt=0.02):
    t = t0
    while sup.state is not SafetyState.RUN:
        feed_all(sup, t)
        sup.step(t)
        t += dt
        assert t < t0 + 5
    return t


def test_starts_safe_and_needs_plc_and_can_then_confirmation():
    sup = Supervisor(CFG, now_s=0.0)
    st = sup.step(0.0)
    assert st.state is SafetyState.SAFE and set(st.missing) == {"plc", "can"}
    t_run = run_until_run(sup)
    # RUN only after every source stayed good for recovery_s
    assert t_run - 0.02 >= CFG.recovery_s - 1e-9
    assert t_run - 0.02 <= CFG.recovery_s + 0.02 + 1e-9


@pytest.mark.parametrize("source", ["plc", "can", "measurement"])
def test_each_source_timing_out_goes_safe_just_after_its_timeout(source):
    sup = Supervisor(CFG, now_s=0.0)
    t = run_until_run(sup)
    t_lost = t
    dt = 0.01
    while True:
        feed_all(sup, t, skip=(source,) if t > t_lost else ())
        st = sup.step(t)
        if st.state is SafetyState.SAFE:
            break
        t += dt
        assert t < t_lost + 10
    assert st.changed and st.missing == (source,)
    assert TIMEOUT[source] < t - t_lost <= TIMEOUT[source] + dt + 1e-9
    assert sup.entries == 1


def test_recovery_needs_continuous_confirmation():
    sup = Supervisor(CFG, now_s=0.0)
    t = run_until_run(sup)
    sup.step(t + 1.0)  # nothing heard for 1 s: safe
    assert sup.safe
    t += 1.0
    # sources come back but CAN flickers out once inside the confirmation window
    for i in range(10):
        tt = t + i * 0.02
        feed_all(sup, tt, skip=("can",) if i == 5 else ())
    back = t
    # a flicker of less than the CAN timeout does not restart confirmation...
    assert not sup.step(back + 0.1).changed
    # ...but a real gap (beyond the timeout) does
    sup.step(back + 0.2 + CFG.can_timeout_s + 0.01)
    assert sup.safe
    t2 = back + 0.6
    feed_all(sup, t2)
    assert sup.step(t2).state is SafetyState.SAFE
    feed_all(sup, t2 + 0.1)
    assert sup.step(t2 + 0.1).state is SafetyState.SAFE
    feed_all(sup, t2 + CFG.recovery_s)
    st = sup.step(t2 + CFG.recovery_s)
    assert st.state is SafetyState.RUN and st.changed


def test_machine_fault_and_no_board():
    sup = Supervisor(CFG, now_s=0.0)
    t = run_until_run(sup)
    sup.machine_ok(False)
    assert sup.step(t).missing == ("machine",) and sup.safe
    sup.machine_ok(True)
    # no board under the camera: measurements are not expected, the timeout rests
    for i in range(300):
        tt = t + i * 0.02
        sup.plc_answered(tt)
        sup.can_heard(tt)
        sup.measurement_not_expected(tt)
        sup.step(tt)
    assert sup.state is SafetyState.RUN


@pytest.mark.parametrize(
    "mode,current,dt,lo,hi,expected",
    [
        ("ramp_down", 600.0, 0.1, 50.0, 1000.0, 550.0),  # 500 mm/s^2 * 0.1 s
        ("ramp_down", 120.0, 0.1, 50.0, 1000.0, 100.0),  # does not overshoot the safe feed
        ("ramp_down", 80.0, 0.1, 50.0, 1000.0, 80.0),  # already below: no increase
        ("ramp_down", 600.0, 0.1, 150.0, 1000.0, 550.0),
        ("ramp_down", 160.0, 0.1, 150.0, 1000.0, 150.0),  # safe feed below the machine's min
        ("ramp_down", 20.0, 0.1, 50.0, 1000.0, 50.0),  # inside the limits
        ("hold", 600.0, 0.1, 50.0, 1000.0, 600.0),
        ("hold", 1200.0, 0.1, 50.0, 1000.0, 1000.0),
    ],
)
def test_safe_feed_table(mode, current, dt, lo, hi, expected):
    from dataclasses import replace

    sup = Supervisor(replace(CFG, safe_state=mode), now_s=0.0)
    v = sup.safe_feed(current, dt_s=dt, feed_min_mm_s=lo, feed_max_mm_s=hi)
    assert v == pytest.approx(expected)
    assert lo <= v <= hi


def test_ramp_is_rate_limited_and_monotone():
    sup = Supervisor(CFG, now_s=0.0)
    v, dt, seen = 900.0, 0.02, [900.0]
    for _ in range(200):
        v = sup.safe_feed(v, dt_s=dt, feed_min_mm_s=50.0, feed_max_mm_s=1000.0)
        seen.append(v)
    steps = [a - b for a, b in zip(seen[:-1], seen[1:], strict=True)]
    assert all(-1e-9 <= s <= CFG.ramp_mm_s2 * dt + 1e-9 for s in steps)
    assert seen[-1] == pytest.approx(CFG.safe_feed_mm_s)
    assert Supervisor.safe_offsets_um(4) == [0.0] * 4
    with pytest.raises(ValueError, match="dt_s"):
        sup.safe_feed(100.0, dt_s=-1.0, feed_min_mm_s=0.0, feed_max_mm_s=1.0)


@pytest.mark.parametrize("condition", ["machine", "plc_data", "amplifier", "log", "service"])
def test_each_condition_goes_safe_at_once_and_recovers_after_confirmation(condition):
    sup = Supervisor(CFG, now_s=0.0)
    t = run_until_run(sup)
    sup.set_ok(condition, False)
    feed_all(sup, t)
    st = sup.step(t)
    assert st.state is SafetyState.SAFE and st.changed and st.missing == (condition,)
    sup.set_ok(condition, True)
    t_back = t + 0.02
    t_run = run_until_run(sup, t_back)
    assert t_run - 0.02 - t_back >= CFG.recovery_s - 1e-9
    with pytest.raises(ValueError, match="condition"):
        sup.set_ok("disk", False)


# ------------------------------------------------------------------ the piezo amplifier's status
@pytest.mark.parametrize(
    ("state", "fault", "enable", "expected"),
    [
        (1, 0, True, None),  # enabled and tracking, as commanded
        (0, 0, False, None),  # disabled, as commanded
        (3, 0b1000, True, "overcurrent"),
        (3, 0b1000, False, "overcurrent"),  # a fault is a fault whatever is commanded
        (3, 0, False, "state 3 (fault)"),
        (1, 0b0010, True, "stroke limit"),  # offsets refused, the old table still played
        (2, 0b0100, True, "setpoint timeout"),
        (1, 0b0001, True, "over-temperature"),
        (0, 0, True, "state 0 (disabled) while enable is commanded"),
        (2, 0, True, "state 2 (ramping to zero) while enable is commanded"),
        (1, 0, False, "state 1 (enabled) while disable is commanded"),
        (7, 0, True, "state 7 (unknown)"),
    ],
)
def test_amp_problem_table(state, fault, enable, expected):
    got = amp_problem(state=state, fault=fault, enable=enable)
    if expected is None:
        assert got is None
    else:
        assert got is not None and expected in got


class Status:
    def __init__(self, state, fault, t_s):
        self.state, self.fault, self.t_s = state, fault, t_s


def _watch(mon, statuses, dt=0.01):
    """Feed (t, state, fault) statuses; return the confirmed problem after each."""
    return [mon.observe(Status(s, f, t), now_s=t) for t, s, f in statuses]


def test_amp_fault_is_confirmed_after_the_confirmation_time_only():
    mon = AmplifierMonitor(confirm_s=0.1)
    mon.commanded(True, now_s=0.0)
    out = _watch(mon, [(0.01 * i, 1, 0) for i in range(1, 6)])
    assert out == [None] * 5 and mon.problem is None
    # a fault for less than the confirmation time, then healthy again: never confirmed
    out = _watch(mon, [(0.06 + 0.01 * i, 3, 8) for i in range(9)] + [(0.15, 1, 0)])
    assert out == [None] * 10
    # a fault that lasts: confirmed once the confirmation time has passed, not before
    t0 = 0.2
    out = _watch(mon, [(t0 + 0.01 * i, 3, 8) for i in range(15)])
    first = next(i for i, p in enumerate(out) if p is not None)
    assert 0.1 - 1e-9 <= 0.01 * first <= 0.1 + 0.01 + 1e-9
    assert all(p is not None and "overcurrent" in p for p in out[first:])


def test_amp_mismatch_counts_from_the_command_and_recovers_when_healthy():
    mon = AmplifierMonitor(confirm_s=0.1)
    mon.commanded(False, now_s=0.0)
    assert _watch(mon, [(0.01, 0, 0)]) == [None]
    mon.commanded(True, now_s=0.5)
    # a status received before the command took effect is no judgement of it
    assert mon.observe(Status(0, 0, 0.45), now_s=0.5) is None
    # still disabled although enabled: only after the confirmation time from the command
    out = _watch(mon, [(0.5 + 0.02 * i, 0, 0) for i in range(1, 8)])
    assert out[:4] == [None] * 4 and out[-1] is not None and "disabled" in out[-1]
    # the service goes safe and commands disable: the old verdict stands until the amplifier
    # answers the new command, then it is healthy
    mon.commanded(False, now_s=0.7)
    assert mon.observe(Status(0, 0, 0.69), now_s=0.7) is not None
    assert mon.observe(Status(0, 0, 0.72), now_s=0.72) is None and mon.problem is None


def test_untracked_time_marks_when_the_offsets_were_not_played():
    mon = AmplifierMonitor(confirm_s=0.1)
    mon.commanded(False, now_s=0.0)
    mon.observe(Status(0, 0, 0.02), now_s=0.02)
    assert mon.untracked_s == 0.02  # disabled: offsets not played
    mon.commanded(True, now_s=0.1)
    mon.observe(Status(0, 0, 0.1), now_s=0.1)  # before the command: not yet tracking
    assert mon.untracked_s == 0.1
    mon.observe(Status(1, 0, 0.12), now_s=0.12)
    mon.observe(Status(1, 0, 0.14), now_s=0.14)
    assert mon.untracked_s == 0.1  # tracking since
    mon.observe(Status(2, 4, 0.3), now_s=0.3)  # a short ramp: never confirmed, still noted
    mon.observe(Status(1, 0, 0.32), now_s=0.32)
    assert mon.untracked_s == 0.3 and mon.problem is None
    assert AMP_CONFIRM_S < CFG.can_timeout_s
    with pytest.raises(ValueError, match="confirm_s"):
        AmplifierMonitor(confirm_s=-1.0)
