"""Recovery from the safe state: hysteresis, a growing and bounded back-off, reset after a good
period; a refused table alone is confirmed later than other amplifier faults."""

from __future__ import annotations

import pytest

from config.machine import SafetyConfig
from controller.service.supervisor import (
    AMP_CONFIRM_S,
    AMP_REFUSAL_CONFIRM_S,
    AmplifierMonitor,
    SafetyState,
    Supervisor,
)
from protocol.piezo_canopen import AmpFault, AmpState

FAULT_OVERCURRENT, FAULT_STROKE_LIMIT = int(AmpFault.OVERCURRENT), int(AmpFault.STROKE_LIMIT)
STATE_ENABLED, STATE_FAULT = int(AmpState.ENABLED), int(AmpState.FAULT)

CFG = SafetyConfig(cycle_s=0.02, plc_timeout_s=0.5, can_timeout_s=0.3,
                   measurement_timeout_s=2.0, recovery_s=0.25)
DT = 0.02


def _feed(sup, t, *, can=True):
    sup.plc_answered(t)
    sup.measurement_valid(t)
    if can:
        sup.can_heard(t)


def _run_until(sup, t, state, *, limit_s=30.0):
    """Step every source healthy until ``state``; the time it was reached."""
    end = t + limit_s
    while sup.state is not state:
        _feed(sup, t)
        sup.step(t)
        if sup.state is state:
            return t
        t += DT
        assert t < end, f"{state} not reached"
    return t


def _flap(sup, t):
    """One short failure of a condition: SAFE at once; the time it became SAFE."""
    sup.set_ok("amplifier", False)
    _feed(sup, t)
    st = sup.step(t)
    assert st.state is SafetyState.SAFE and st.changed
    sup.set_ok("amplifier", True)
    return t


@pytest.mark.parametrize(
    ("factor", "max_factor", "expected"),
    [
        (2.0, 8.0, [1, 2, 4, 8, 8, 8]),
        (3.0, 10.0, [1, 3, 9, 10, 10, 10]),
        (1.0, 1.0, [1, 1, 1, 1, 1, 1]),  # no back-off
    ],
)
def test_back_off_grows_with_each_quick_relapse_and_is_bounded(factor, max_factor, expected):
    sup = Supervisor(CFG, now_s=0.0, backoff_factor=factor, backoff_max_factor=max_factor)
    t = _run_until(sup, 0.0, SafetyState.RUN)
    waits = []
    for _ in expected:
        t_safe = _flap(sup, t + DT)
        t = _run_until(sup, t_safe + DT, SafetyState.RUN)
        waits.append(t - t_safe)
        assert sup.recovery_required_s == pytest.approx(
            CFG.recovery_s * min(factor ** (sup.backoff_level - 1), max_factor))
    for wait, k in zip(waits, expected, strict=True):
        need = CFG.recovery_s * k
        assert need - 1e-9 <= wait <= need + 2 * DT + 1e-9


def test_back_off_resets_after_a_good_period():
    sup = Supervisor(CFG, now_s=0.0, backoff_reset_s=5.0)
    t = _run_until(sup, 0.0, SafetyState.RUN)
    for _ in range(3):
        t = _run_until(sup, _flap(sup, t + DT) + DT, SafetyState.RUN)
    assert sup.backoff_level == 3 and sup.recovery_required_s == pytest.approx(4 * CFG.recovery_s)
    # RUN a little shorter than the reset period: the next relapse waits longer still
    t_end = t + 4.9
    while t < t_end:
        t += DT
        _feed(sup, t)
        sup.step(t)
    t_safe = _flap(sup, t + DT)
    assert sup.backoff_level == 4
    t = _run_until(sup, t_safe + DT, SafetyState.RUN)
    assert t - t_safe >= 8 * CFG.recovery_s - 1e-9
    # a good period: the next entry waits recovery_s again
    t_end = t + 5.0 + DT
    while t < t_end:
        t += DT
        _feed(sup, t)
        sup.step(t)
    assert sup.backoff_level == 0
    t_safe = _flap(sup, t + DT)
    t = _run_until(sup, t_safe + DT, SafetyState.RUN)
    assert sup.backoff_level == 1
    assert CFG.recovery_s - 1e-9 <= t - t_safe <= CFG.recovery_s + 2 * DT + 1e-9


@pytest.mark.parametrize(
    ("kwargs", "needle"),
    [
        ({"backoff_factor": 0.5}, "backoff_factor"),
        ({"backoff_max_factor": 0.0}, "backoff_max_factor"),
        ({"backoff_reset_s": -1.0}, "backoff_reset_s"),
        ({"fresh_fraction": 0.0}, "fresh_fraction"),
        ({"fresh_fraction": 1.5}, "fresh_fraction"),
    ],
)
def test_bad_back_off_parameters(kwargs, needle):
    with pytest.raises(ValueError, match=needle):
        Supervisor(CFG, now_s=0.0, **kwargs)


@pytest.mark.parametrize(
    ("gap_s", "recovers"),
    [
        (0.10, True),  # heard well within half the 0.3 s CAN timeout
        (0.14, True),
        (0.20, False),  # within the timeout (not gone) but not clearly back: no recovery
        (0.28, False),
    ],
)
def test_recovery_needs_sources_clearly_back(gap_s, recovers):
    """Hysteresis: RUN is left at the whole timeout, re-entered only within half of it."""
    sup = Supervisor(CFG, now_s=0.0)
    t = _run_until(sup, 0.0, SafetyState.RUN)
    t = _flap(sup, t + DT)
    last_can = t
    end = t + 2.0
    while t < end:
        t += DT
        if t - last_can >= gap_s - 1e-9:  # the amplifier heard only every gap_s
            last_can = t
        _feed(sup, t, can=False)
        sup.can_heard(last_can)
        st = sup.step(t)
        assert "can" not in st.missing  # never gone: the gap is inside the timeout
    assert (sup.state is SafetyState.RUN) is recovers


class _Status:
    def __init__(self, state, fault, t_s):
        self.state, self.fault, self.t_s = state, fault, t_s


@pytest.mark.parametrize(
    ("state", "fault", "confirm"),
    [
        (STATE_ENABLED, FAULT_STROKE_LIMIT, AMP_REFUSAL_CONFIRM_S),  # a refusal: re-planned first
        (STATE_ENABLED, FAULT_STROKE_LIMIT | FAULT_OVERCURRENT, AMP_CONFIRM_S),
        (STATE_FAULT, FAULT_STROKE_LIMIT, AMP_CONFIRM_S),
        (STATE_FAULT, FAULT_OVERCURRENT, AMP_CONFIRM_S),
    ],
)
def test_a_refused_table_alone_is_confirmed_later(state, fault, confirm):
    mon = AmplifierMonitor()
    mon.commanded(True, now_s=0.0)
    t, first_bad = 0.01, None
    while mon.problem is None:
        mon.observe(_Status(state, fault, t), now_s=t)
        first_bad = t if first_bad is None else first_bad
        t = round(t + 0.01, 6)
        assert t < 2.0
    took = t - 0.01 - first_bad
    assert confirm - 1e-9 <= took <= confirm + 0.01 + 1e-9
    assert mon.untracked_s is not None  # never learnt from meanwhile
