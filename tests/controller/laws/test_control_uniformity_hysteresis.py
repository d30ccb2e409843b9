"""A hysteretic stack: the gain grows with the amplitude, the loop plans at the step's amplitude.

The actuator is the simulator's (``plant_sim.model.piezo.PiezoAmplifier``: Bouc-Wen hysteresis
0.35 before a 2 kHz resonance), played knife by knife and revolution by revolution; the board is
the linear width model seen through the camera's transport delay (300 mm at 600 mm/s: five
pairs). A 1 um cycle moves the cut by 0.05 um per um, a 15 um one by 0.4-0.7.
"""

from __future__ import annotations

import math
import types

import numpy as np
import pytest

from controller.laws.actuator_id import ActuatorIdentifier
from controller.laws.uniformity_loop import (
    UniformityLoop,
    UniformityLoopConfig,
    linear_widths_mm,
    width_cv,
)
from plant_sim.model.piezo import PiezoAmplifier

RUNOUT = np.array([0.0, 4.0, -2.0, 2.0])
FEED_MM_S, PITCH_MM, R_MM, TS_S, CAMERA_MM, WINDOW_MM = 600.0, 1.5, 60.0, 0.1, 300.0, 40.0
PIEZO = types.SimpleNamespace(
    resonance_hz=2000.0, damping=0.01, hysteresis=0.35, stroke_um=20.0, input_shaper=True,
    lead_fraction=0.75, timeout_s=0.1, ramp_um_s=50.0, sensor_noise_um=0.0, ambient_c=25.0,
    thermal_tau_s=60.0, heating_c_per_um_s=0.005, max_temperature_c=70.0)


def hysteretic_loop(loop: UniformityLoop, *, pairs: int = 110, seed: int = 0):
    """The loop against the simulated amplifier; (board travel mm, true CV) per pair."""
    z = RUNOUT.size
    amp = PiezoAmplifier(PIEZO, z, np.random.default_rng(seed))
    amp.command(0.0, enable=True, alive_counter=1)
    rng = np.random.default_rng(seed)
    period = 60.0 / 6000.0 / z
    delay, half = CAMERA_MM / FEED_MM_S, 0.5 * WINDOW_MM / FEED_MM_S
    bdc: list[tuple[float, int, float]] = []
    pending: list[tuple[float, list[float]]] = []
    t_amp, knife, out = 0.0, 0, []
    for i in range(pairs + int(round(delay / TS_S))):
        t = (i + 1) * TS_S
        while t_amp + period <= t:
            t_bdc = t_amp + period
            switch = t_bdc - PIEZO.lead_fraction * period
            while pending and pending[0][0] <= switch:
                amp.set_offsets(pending.pop(0)[1])
            amp.advance_to(switch)
            amp.switch(knife, switch)
            amp.advance_to(t_bdc)
            amp.last_command_s = t_bdc
            bdc.append((t_bdc, knife, amp.actuator.x_um))
            t_amp, knife = t_bdc, (knife + 1) % z
        cut = t - delay
        if cut - half < 0.0:
            continue
        disp, n = np.zeros(z), np.zeros(z)
        for tb, k, x in bdc:
            if cut - half <= tb <= cut + half:
                disp[k] += x
                n[k] += 1
        w = linear_widths_mm(disp / np.maximum(n, 1) - RUNOUT, pitch_mm=PITCH_MM, radius_mm=R_MM)
        out.append((cut * FEED_MM_S, width_cv(np.maximum(w, 0.0))))
        meas = w + 0.002 * rng.standard_normal(z)
        offs = loop.update(knife_widths_mm=np.where(meas > 0, meas, np.nan), pitch_mm=PITCH_MM,
                           now_s=t, cut_at_s=cut - half, cut_until_s=cut + half)
        pending.append((t + 0.02, offs.tolist()))
    return out


def settled_from_mm(trace, limit=0.03):
    """Board travel from which every true CV is within ``limit`` (None: not at the end)."""
    if trace[-1][1] > limit:
        return None
    bad = [d for d, cv in trace if cv > limit]
    return max(bad) if bad else 0.0


def test_the_hysteretic_stack_converges_within_3_m_planned_at_the_step_s_amplitude():
    """CV <= 0.03 from 2.2 m of board (the seed changes only the measurement noise). With
    one gain per pattern whatever the amplitude, a difference taken at a larger amplitude was
    an outlier to the gain learnt on small ones: the loop overshot, the guard undid, 3.6 m."""
    loop = UniformityLoop(UniformityLoopConfig())
    trace = hysteretic_loop(loop)
    at = settled_from_mm(trace)
    assert at is not None and at <= 3000.0, at
    assert trace[-1][1] < 0.005
    assert loop.identifier.amplitude_dependent()


def test_the_identified_gain_grows_with_the_amplitude_of_a_hysteretic_stack():
    loop = UniformityLoop(UniformityLoopConfig())
    hysteretic_loop(loop, pairs=80)
    ident = loop.identifier
    small = ident.gains_at(np.full(4, 2.0))
    large = ident.gains_at(np.full(4, 20.0))
    for m in (1, 2):
        slope, _ = ident.amplitude_slope(m)
        assert slope != 0
        assert abs(large[m]) > 1.5 * abs(small[m])


def _transient(ident, gain_of_amplitude, *, noise_um=0.05, seed=0, steps=80):
    """A table growing toward twice the runout, answered mode by mode with ``g(|O_m|) O_m``
    (``g`` the secant gain from zero; the identifier finds the incremental one)."""
    rng = np.random.default_rng(seed)
    target = np.array([-6.0, 16.0, -16.0, 6.0])
    s = np.array([-1.0, 3.0, -3.0, 1.0])
    o = np.zeros(4)
    for _ in range(steps):
        o = o + 0.08 * (target - o)
        om = np.fft.fft(o, norm="ortho")
        resp = np.real(np.fft.ifft(gain_of_amplitude(np.abs(om)) * om, norm="ortho"))
        y = resp - s
        ident.add(o, y - y.mean() + noise_um * rng.standard_normal(4))


def test_an_amplitude_dependent_gain_is_found_and_a_constant_one_is_not():
    """Response ``0.05 A + 0.015 A^2`` per mode: the incremental gain ``0.05 + 0.03 A``."""
    ident = ActuatorIdentifier(4)
    _transient(ident, lambda a: 0.05 + 0.015 * a, noise_um=0.01)
    for m in (1, 2):
        amps = ident.mode_amplitudes(np.array([-6.0, 16.0, -16.0, 6.0]))
        want = 0.05 + 0.03 * amps[m]
        assert abs(ident.gains_at(amps)[m]) == pytest.approx(want, rel=0.25)
        assert abs(ident.amplitude_slope(m)[0]) == pytest.approx(0.03, rel=0.3)
    # the same transient on a linear actuator (seeds fixed: the test is at two standard errors)
    for seed in range(3):
        lin = ActuatorIdentifier(4)
        _transient(lin, lambda a: np.full_like(a, 0.6), seed=seed)
        assert not lin.amplitude_dependent()
        assert np.allclose(lin.gains_at(np.full(4, 30.0)), lin.mode_gains)


def test_gains_at_stay_within_the_amplitudes_seen_and_the_bounds():
    ident = ActuatorIdentifier(4, gain_max=2.0)
    _transient(ident, lambda a: 0.05 + 0.015 * a)
    hi = ident.mode_amplitudes(np.array([-6.0, 16.0, -16.0, 6.0]))
    beyond = ident.gains_at(hi * 10.0)
    at_hi = ident.gains_at(hi * 1.2)  # the transient stops short of its target: hi is the top
    assert np.allclose(beyond, at_hi)
    assert np.all(np.abs(beyond) <= 2.0 + 1e-12)
    assert beyond[0] == 1.0 and np.isclose(beyond[3], np.conj(beyond[1]))
    with pytest.raises(ValueError, match="amplitudes_um"):
        ident.gains_at([1.0, math.nan, 0.0, 0.0])
