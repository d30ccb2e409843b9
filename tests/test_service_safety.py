"""Safe-state supervisor: table of timeouts -> SAFE, confirmation -> RUN, safe feed ramp."""

from __future__ import annotations

import pytest

from config.machine import SafetyConfig
from controller.safety import SafetyState, Supervisor

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


@pytest.mark.parametrize("condition", ["machine", "plc_data", "log", "service"])
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
