"""Online identification of the actuator's gain per knife mode; the table history."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.laws import actuator_id
from controller.laws.actuator_id import ActuatorIdentifier, circulant_from_mode_gains
from controller.laws.offset_history import OffsetHistory

# a 150 Hz piezo at 400 Hz knife frequency (plant_sim.model.piezo, measured at the knives' BDC): a
# unit offset on knife 0 moves knife 0 by 0.355 um and spills 0.105 um into knife 1
SLOW_COLUMN = np.array([0.355, 0.105, -0.23, -0.23])


def circulant(col):
    z = len(col)
    return np.array([[col[(i - j) % z] for j in range(z)] for i in range(z)])


def transient(ident, a, runout, target, *, steps=60, noise_um=0.05, seed=0, gain=0.1):
    """Offsets moving toward ``target`` as a learning loop would; y = A o - s plus noise."""
    rng = np.random.default_rng(seed)
    o = np.zeros(len(runout))
    for _ in range(steps):
        o = o + gain * (target - o)
        y = a @ o - runout
        ident.add(o, y - y.mean() + noise_um * rng.standard_normal(o.size))
    return o


@settings(max_examples=30, deadline=None)
@given(gains=st.lists(st.complex_numbers(min_magnitude=0.2, max_magnitude=1.8), min_size=1,
                      max_size=3), knives=st.integers(2, 7))
def test_circulant_from_mode_gains_has_those_gains(gains, knives):
    g = np.ones(knives, complex)
    for m in range(1, knives // 2 + 1):
        v = gains[(m - 1) % len(gains)]
        g[m] = v.real if 2 * m == knives else v
        g[knives - m] = np.conj(g[m])
    a = circulant_from_mode_gains(g)
    assert np.all(np.isreal(a))
    v = np.random.default_rng(knives).normal(size=knives)
    assert np.allclose(a @ v, np.real(np.fft.ifft(g * np.fft.fft(v))), atol=1e-12)


def test_recovers_a_slow_actuator_from_one_learning_transient():
    a = circulant(SLOW_COLUMN)
    truth = np.fft.fft(SLOW_COLUMN)
    ident = ActuatorIdentifier(4)
    s = np.array([-1.0, 3.0, -3.0, 1.0])
    transient(ident, a, s, np.array([-8.0, 12.0, -10.0, 6.0]))
    got = ident.mode_gains
    assert got[0] == 1.0
    assert abs(got[2] - truth[2]) < 0.03  # the alternating mode, real
    assert abs(got[1] - truth[1]) < 0.1 and np.isclose(got[3], np.conj(got[1]))
    # the matrix predicts the actuator's response to any table (its mean aside)
    v = np.array([1.0, -2.0, 0.5, 0.5])
    err = ident.matrix() @ v - a @ v
    assert np.max(np.abs(err - err.mean())) < 0.15


def test_a_hysteretic_actuator_is_a_small_gain():
    ident = ActuatorIdentifier(4)
    transient(ident, 0.18 * np.eye(4), np.array([-1.0, 3.0, -3.0, 1.0]),
              np.array([-6.0, 16.0, -16.0, 6.0]))
    g = ident.mode_gains[1:]
    # the prior (gain 1) pulls a little: toward the safe side (a loop gain below 1)
    assert np.all(np.abs(g - 0.18) < 0.05) and np.all(g.real >= 0.18 - 0.01)


def test_nothing_moved_keeps_the_prior():
    ident = ActuatorIdentifier(4)
    for _ in range(50):
        ident.add(np.array([1.0, -1.0, 0.0, 0.0]), np.array([0.2, -0.1, 0.0, -0.1]))
    assert np.allclose(ident.mode_gains, 1.0)
    assert np.allclose(ident.excitation_um2, 0.0)


def test_a_slow_drift_the_loop_follows_does_not_pass_for_a_small_gain():
    """In closed loop y stays near 0 while o tracks a drifting runout: no information."""
    ident = ActuatorIdentifier(4)
    transient(ident, np.eye(4), np.array([-1.0, 3.0, -3.0, 1.0]), np.array([-1.0, 3.0, -3.0, 1.0]))
    before = ident.mode_gains
    rng = np.random.default_rng(2)
    drift = np.array([0.5, -0.2, 0.3, -0.6])
    o = np.array([-1.0, 3.0, -3.0, 1.0])
    for k in range(600):  # 1 min: the runout drifts by 3 um per knife, the loop tracks it
        s = np.array([-1.0, 3.0, -3.0, 1.0]) + drift * k / 100.0
        o = s - s.mean()
        y = o - s
        ident.add(o, y - y.mean() + 0.05 * rng.standard_normal(4))
    assert np.allclose(ident.mode_gains, before, atol=0.02)


def test_a_step_of_the_runout_does_not_corrupt_the_gain():
    """A knife changed: the differences across the step disagree with the confident estimate
    (whatever their phase) and are left out."""
    ident = ActuatorIdentifier(4)
    s0 = np.array([-1.0, 3.0, -3.0, 1.0])
    transient(ident, np.eye(4), s0, np.array([-8.0, 12.0, -10.0, 6.0]))  # every mode learnt
    assert ident.mode_states() == ("usable",) * 4
    o = transient(ident, np.eye(4), s0, s0)
    s1 = np.array([0.0, 40.0, 0.0, 0.0])
    for _ in range(10):
        o = o + 0.3 * (np.clip(s1 - s1.mean(), -18, 18) - o)
        y = o - s1
        ident.add(o, y - y.mean())
    assert np.all(np.abs(ident.mode_gains - 1.0) < 0.15)


def test_gains_stay_within_their_bounds():
    """The planning gains are bounded (magnitude always, phase when asked to)."""
    ident = ActuatorIdentifier(4, gain_min=0.1, gain_max=2.0, phase_max_deg=60.0)
    transient(ident, 0.02 * np.eye(4), np.zeros(4), np.array([-10.0, 10.0, -10.0, 10.0]),
              noise_um=0.0)
    g = ident.mode_gains[1:]
    assert np.all(np.abs(g) >= 0.1 - 1e-12) and np.all(np.abs(g) <= 2.0 + 1e-12)
    assert np.all(np.abs(np.angle(g)) <= math.radians(60.0) + 1e-12)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [({"lag_pairs": 0}, "lag_pairs"), ({"min_step_um": 0.0}, "min_step_um"),
     ({"memory": 0.5}, "memory"), ({"prior_um2": 0.0}, "prior_um2"),
     ({"gain_min": 0.0}, "gain_min"), ({"gain_max": 0.5}, "gain_max")],
)
def test_bad_parameters_are_refused(kwargs, name):
    with pytest.raises(ValueError, match=name):
        ActuatorIdentifier(4, **kwargs)


def test_bad_samples_are_refused():
    ident = ActuatorIdentifier(3)
    with pytest.raises(ValueError, match="offsets_um"):
        ident.add([0.0, 1.0], [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="finite"):
        ident.add([0.0, 1.0, math.nan], [0.0, 0.0, 0.0])


# -- the table history ---------------------------------------------------------------------------
def test_history_gives_the_table_in_force_and_time_weighted_means():
    h = OffsetHistory(2, horizon_s=100.0)
    h.restart([0.0, 0.0])  # always in force
    h.append([2.0, -2.0], 10.0)
    h.append([4.0, -4.0], 11.0)
    assert np.allclose(h.mean_over(5.0, 6.0), [0.0, 0.0])
    assert np.allclose(h.mean_over(10.5, 10.5), [2.0, -2.0])
    assert np.allclose(h.mean_over(9.0, 11.0), [1.0, -1.0])  # half zero, half (2, -2)
    assert np.allclose(h.mean_over(10.0, 12.0), [3.0, -3.0])
    assert np.allclose(h.mean_over(12.0, 10.0), [3.0, -3.0])  # order does not matter
    h.pop()
    assert np.allclose(h.latest(), [2.0, -2.0])


def test_history_before_its_start_is_unknown_and_old_tables_go():
    h = OffsetHistory(1, horizon_s=5.0)
    h.restart([1.0], at_s=0.0)
    assert h.mean_over(-1.0, 0.5) is None
    for k in range(1, 20):
        h.append([float(k)], float(k))
    assert len(h) <= 7 and h.start_s <= 19.0 - 5.0
    assert np.allclose(h.mean_over(14.5, 14.5), [14.0])  # the one in force at the horizon
    with pytest.raises(ValueError, match="at_s"):
        h.append([0.0], 3.0)


def test_history_same_instant_replaces_and_pop_puts_it_back():
    h = OffsetHistory(2, horizon_s=100.0)
    h.restart([0.0, 0.0])
    assert h.append([1.0, -1.0], 5.0) is None
    replaced = h.append([2.0, -2.0], 5.0)
    assert np.allclose(replaced, [1.0, -1.0]) and len(h) == 2
    h.pop(replaced)
    assert np.allclose(h.latest(), [1.0, -1.0]) and len(h) == 2
    h.pop()
    assert np.allclose(h.latest(), [0.0, 0.0]) and len(h) == 1
    h.pop()  # the oldest entry stays
    assert len(h) == 1


# ------------------------------------------------------------- the whole phase circle

def _modal_actuator(mode1: complex, mode2: float) -> np.ndarray:
    """A 4-knife circulant actuator with these gains on modes 1 (and 3) and 2."""
    return circulant_from_mode_gains(np.array([1.0, mode1, mode2, np.conj(mode1)]))


# a 100 Hz piezo at 400 knife passes per second (plant_sim.model.piezo at the knives' BDC):
# the first pattern lags by 63 deg, the alternating one is turned around
RESONANT_100HZ = (0.69 * np.exp(-1j * np.radians(63.0)), -0.23)


def test_a_turned_actuator_is_identified_over_the_whole_phase_circle():
    a = _modal_actuator(*RESONANT_100HZ)
    ident = ActuatorIdentifier(4)
    transient(ident, a, np.array([-1.0, 3.0, -3.0, 1.0]), np.array([-2.0, 14.0, -10.0, -2.0]))
    g = ident.mode_gains
    assert abs(g[1] - RESONANT_100HZ[0]) < 0.05 and abs(g[2] - RESONANT_100HZ[1]) < 0.03
    assert ident.mode_states() == ("usable",) * 4
    assert np.all(ident.confidence()[1:] > 0.5)


@settings(max_examples=40, deadline=None)
@given(mag=st.floats(0.15, 1.8), phase=st.floats(-179.0, 179.0), alt=st.floats(-1.8, 1.8),
       seed=st.integers(0, 1000))
def test_any_gain_within_the_envelope_is_identified(mag, phase, alt, seed):
    """Any complex gain of the first pattern and any real one of the alternating pattern
    (above the authority threshold) is found from one learning transient."""
    mode1 = mag * np.exp(1j * np.radians(phase))
    alt = alt if abs(alt) >= 0.15 else 0.15
    ident = ActuatorIdentifier(4)
    rng = np.random.default_rng(seed)
    # a learning transient that moves both patterns by several um
    turn = np.exp(1j * rng.uniform(0.0, 2.0 * np.pi))
    target = np.real(np.fft.ifft(np.array([0.0, 16.0 * turn, 16.0, 16.0 * np.conj(turn)])))
    transient(ident, _modal_actuator(mode1, alt), rng.normal(0.0, 3.0, 4), target, seed=seed)
    raw = ident.raw_gains
    assert ident.mode_states() == ("usable",) * 4
    for m, truth in ((1, mode1), (2, alt)):
        # the prior (gain 1, weight prior_um2) pulls by its share of the excitation
        pull = ident.prior_um2 * abs(1.0 - truth) / (ident.excitation_um2[m] + ident.prior_um2)
        assert abs(raw[m] - truth) < 0.02 + 0.03 * abs(truth) + pull, (m, raw[m], truth)
        assert abs(raw[m] - truth) <= 3.0 * ident.gain_stderr()[m] + 0.01  # honest uncertainty


def test_an_actuator_that_barely_moves_a_pattern_has_no_authority_there():
    """A hysteretic stack moves small cycles by a few per cent: said, not divided by."""
    a = _modal_actuator(0.6 * np.exp(-0.3j), 0.03)
    ident = ActuatorIdentifier(4, gain_min=0.1)
    transient(ident, a, np.array([-1.0, 3.0, -3.0, 1.0]), np.array([-8.0, 12.0, -10.0, 6.0]))
    assert ident.mode_states() == ("usable", "usable", "no_authority", "usable")
    assert abs(ident.raw_gains[2] - 0.03) < 0.02
    assert abs(ident.mode_gains[2]) == pytest.approx(0.1)  # planned with the bound, then held


def test_a_pattern_never_moved_stays_unknown_and_unconfident():
    ident = ActuatorIdentifier(4)
    transient(ident, np.eye(4), np.zeros(4), np.array([3.0, -3.0, 3.0, -3.0]))  # mode 2 only
    st_ = ident.mode_states()
    assert st_[2] == "usable" and st_[1] == "unknown" and ident.confidence()[1] == 0.0


def test_an_unconfirmed_small_gain_is_planned_with_a_cautious_bound():
    ident = ActuatorIdentifier(4, min_samples=50, unidentifiable_samples=60,
                               unconfirmed_gain_min=0.5)
    transient(ident, 0.05 * np.eye(4), np.zeros(4), np.array([-8.0, 12.0, -10.0, 6.0]),
              steps=12)
    assert np.all(np.abs(ident.raw_gains[1:]) < 0.3)
    assert np.all(np.abs(ident.mode_gains[1:]) >= 0.5 - 1e-12)


def test_an_actuator_that_changes_is_learnt_afresh():
    """Confident at gain 1, the actuator turns (a resonance moved): the disagreeing
    differences are outliers at first, then the pattern is learnt again."""
    ident = ActuatorIdentifier(4)
    s = np.array([-1.0, 3.0, -3.0, 1.0])
    transient(ident, np.eye(4), s, np.array([-8.0, 12.0, -10.0, 6.0]))
    assert np.allclose(ident.mode_gains[1:], 1.0, atol=0.05)
    turned = _modal_actuator(*RESONANT_100HZ)
    rng = np.random.default_rng(1)
    for _ in range(120):  # the loop keeps stepping between tables
        o = rng.normal(0.0, 6.0, 4)
        y = turned @ o - s
        ident.add(o, y - y.mean())
    assert abs(ident.mode_gains[2] - RESONANT_100HZ[1]) < 0.05
    assert abs(ident.mode_gains[1] - RESONANT_100HZ[0]) < 0.08


def test_a_jump_with_the_table_steady_starts_the_differences_again():
    ident = ActuatorIdentifier(4, lag_pairs=3)
    o = np.array([1.0, -1.0, 2.0, -2.0])
    for _ in range(4):
        ident.add(o, o - o.mean())
    ident.add(o, o - np.array([0.0, 20.0, 0.0, -20.0]))  # the runout stepped, table steady
    assert ident.samples == 5
    assert len(ident._past) == 1  # only the measurement after the jump
    ident.interrupt()
    assert len(ident._past) == 0


def test_large_moves_that_move_nothing_are_no_authority_without_a_fit():
    """A 60 Hz piezo barely moves the alternating pattern (about 1 %): below the ratio gate no
    difference enters the fit, and the moves that moved nothing are the finding."""
    a = _modal_actuator(0.42 * np.exp(-2.2j), 0.01)
    ident = ActuatorIdentifier(4)
    o = np.zeros(4)
    rng = np.random.default_rng(3)
    for k in range(40):  # a loop that keeps pushing the alternating pattern
        o = np.array([1.0, -1.0, 1.0, -1.0]) * 0.5 * k
        y = a @ o - np.array([0.0, 4.0, -2.0, 2.0])
        ident.add(o, y - y.mean() + 0.02 * rng.standard_normal(4))
    assert ident.differences[2] == 0  # nothing entered the fit
    assert ident.mode_states()[2] == "no_authority"


def _states_by_arrays(ident):
    """``mode_states`` from the public ``gain_stderr`` and ``confidence`` (numpy arrays)."""
    se, conf = ident.gain_stderr(), ident.confidence()
    out = ["usable"]
    for m in range(1, ident.knives):
        mag = abs(complex(ident.raw_gains[m]))
        n = ident.differences[m]
        if ((n >= ident.min_samples - 1e-9 and mag + 2.0 * se[m] < ident.gain_min)
                or ident._still[m] >= ident.still_samples):
            out.append("no_authority")
        elif conf[m] > 0.0 and mag >= ident.gain_min:
            out.append("usable")
        elif n >= ident.unidentifiable_samples - 1e-9:
            out.append("unidentifiable")
        else:
            out.append("unknown")
    return tuple(out)


def test_mode_states_agree_with_the_stderr_and_confidence_arrays():
    """The states judged per mode in plain floats are those of ``gain_stderr`` and
    ``confidence``, along learning transients of actuators strong, weak, turned and still."""
    rng = np.random.default_rng(8)
    seen = set()
    for case in range(40):
        z = int(rng.integers(2, 8))
        col = rng.normal(0.0, 1.0, z) * rng.choice([0.02, 0.3, 1.0])
        col[0] += rng.choice([0.0, 0.5, 1.0])
        ident = ActuatorIdentifier(z, gain_min=0.1, min_samples=3, unidentifiable_samples=6)
        o = np.zeros(z)
        target = rng.normal(0.0, 6.0, z)
        for _ in range(40):
            o = o + 0.15 * (target - o) + rng.normal(0.0, 0.3, z)
            y = circulant(col) @ o - np.linspace(-1.0, 1.0, z)
            ident.add(o, y - y.mean() + 0.05 * rng.standard_normal(z))
            states = ident.mode_states()
            assert states == _states_by_arrays(ident), case
            seen.update(states)
    assert {"usable", "no_authority", "unknown"} <= seen


def test_the_judgements_kept_between_changes_are_those_computed_afresh():
    """``mode_states`` and ``amplitude_dependent`` are kept while the fit does not change:
    along runs that hold the table (kept), move it, meet outliers and runout steps, push a
    pattern the actuator barely moves (moves that move nothing, then one that does), and
    move a hysteretic actuator by small and large cycles, both equal what the fit gives
    afresh after every pair (and they were kept for most of the held pairs)."""
    rng = np.random.default_rng(11)
    kept = 0
    for case in range(45):
        kind = case % 3
        z = 4 if kind == 2 else int(rng.integers(2, 8))
        if kind == 2:  # the alternating pattern barely moves (a 60 Hz piezo)
            a = _modal_actuator(0.42 * np.exp(-2.2j), 0.01)
        else:
            col = rng.normal(0.0, 1.0, z) * rng.choice([0.05, 0.5, 1.0])
            col[0] += rng.choice([0.3, 1.0])
            a = circulant(col)
        ident = ActuatorIdentifier(z, gain_min=0.1, min_samples=3, unidentifiable_samples=6)
        runout = rng.normal(0.0, 3.0, z)
        o = np.zeros(z)
        for k in range(80):
            phase = (k // 10) % 3
            if phase == 1 and kind == 2:  # push the alternating pattern, now and then moved
                o = np.array([1.0, -1.0, 1.0, -1.0]) * 0.5 * k
                if k >= 40 and rng.random() < 0.3:  # (the first push: no authority found)
                    a = _modal_actuator(0.42 * np.exp(-2.2j), 0.5)
            elif phase == 1:  # a move: large or small cycles (a hysteretic stack scales them)
                o = o + rng.normal(0.0, rng.choice([0.3, 3.0]), z)
            if rng.random() < 0.05:
                runout = runout + rng.normal(0.0, 2.0, z)  # a knife stepped
            scale = 1.0 if kind == 2 or np.abs(o).max() > 2.0 else 0.4  # gain grows with size
            y = scale * a @ o - runout
            before = ident._states is not None
            ident.add(o, y - y.mean() + 0.02 * rng.standard_normal(z))
            kept += before and ident._states is not None
            assert ident.mode_states() == actuator_id._mode_states_now(ident), (case, k)
            assert ident.amplitude_dependent() == any(
                ident.amplitude_slope(m)[0] != 0 for m in range(1, z // 2 + 1)), (case, k)
    assert kept > 500
