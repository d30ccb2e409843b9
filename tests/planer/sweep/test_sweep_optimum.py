"""The constrained-optimum reference: the best true CV a plant allows."""

from __future__ import annotations

import numpy as np
import pytest

from controller.laws.uniformity_loop import UniformityLoopConfig
from planer.hil.scenario import load_scenario
from planer.sweep.design import Point
from planer.sweep.optimum import (
    actuator_response_um,
    constrained_optimum_cv,
    steady_temperature_c,
    true_cv,
    within_temperature,
)
from planer.sweep.point import build_machine_config, build_sim_config, make_job


def _plant(values):
    job = make_job(Point(index=0, seed=0, values=values), load_scenario("default"))
    return build_sim_config(job), build_machine_config(job)


def test_the_actuator_response_is_the_table_for_a_fast_stack_and_smaller_for_a_hysteretic_one():
    sim, _ = _plant({"sim.piezo.hysteresis": 0.0})
    table = np.array([-1.0, 3.0, -3.0, 1.0])
    got = actuator_response_um(sim.piezo, table, spindle_rpm=sim.spindle.rpm)
    assert np.allclose(got - got.mean(), table, atol=0.05)
    sim3, _ = _plant({"sim.piezo.hysteresis": 0.3})
    weak = actuator_response_um(sim3.piezo, table, spindle_rpm=sim3.spindle.rpm)
    assert np.ptp(weak) < 0.4 * np.ptp(table)


def test_a_reachable_runout_has_an_optimum_near_zero():
    sim, cfg = _plant({"sim.piezo.hysteresis": 0.0})
    opt = constrained_optimum_cv(sim, cfg)
    assert opt.cv < 0.01
    assert abs(sum(opt.offsets_um)) < 1e-9
    assert max(abs(v) for v in opt.offsets_um) <= opt.limit_um + 1e-9


def test_the_saturated_plant_s_optimum_beats_the_clipped_runout():
    sim, cfg = _plant({"sim.piezo.stroke_um": 10.0, "machine.piezo.stroke_um": 10.0,
                       "runout_um": [0.0, 15.0, -8.0, 5.0]})
    opt = constrained_optimum_cv(sim, cfg)
    assert opt.limit_um == pytest.approx(10.0 - UniformityLoopConfig().margin_um)
    assert max(abs(v) for v in opt.offsets_um) <= opt.limit_um + 1e-9
    assert opt.cv < 0.85 * opt.clipped_cv
    # it is a minimum: moving along the zero-mean directions inside the box does not help
    o = np.array(opt.offsets_um)
    feed = cfg.quality.target_pitch_mm * sim.spindle.rpm / 60.0 * 4
    for d in (np.array([1.0, 0.0, 0.0, -1.0]), np.array([-1.0, 0.0, 0.0, 1.0])):
        assert true_cv(sim, o + 0.2 * d, feed_mm_s=feed) >= opt.cv - 1e-4


def _played_goal_c(piezo_cfg, table, *, rpm: float, knives: int) -> float:
    """The temperature the simulated amplifier heads for after one second of ``table``."""
    import math

    from plant_sim.model.piezo import PiezoAmplifier

    amp = PiezoAmplifier(piezo_cfg, knives, np.random.default_rng(0))
    amp.command(0.0, enable=True, alive_counter=1)
    amp.set_offsets(list(table))
    period = 60.0 / rpm / knives
    t = 0.0
    for k in range(knives):  # one revolution to settle onto the table, then count one second
        t += period
        amp.switch(k, t)
    amp.cycle(t, 1.0, spindle_turning=True)
    amp.temperature_c = piezo_cfg.ambient_c
    amp.last_command_s = math.inf  # no setpoint timeout
    start = t
    passes = round(1.0 / period)
    for i in range(passes):
        t = start + (i + 1) * period
        amp.switch((i + knives) % knives, t)
    amp.cycle(t, 1.0, spindle_turning=True)
    rise = amp.temperature_c - piezo_cfg.ambient_c
    return piezo_cfg.ambient_c + rise / (1.0 - math.exp(-1.0 / piezo_cfg.thermal_tau_s))


def test_the_steady_temperature_is_what_the_simulated_amplifier_heads_for():
    sim, _ = _plant({})
    for table in ([0.0, 4.0, -2.0, -2.0], [20.0, -20.0, 20.0, -20.0], [3.0, 1.0, -1.0, -3.0]):
        want = _played_goal_c(sim.piezo, table, rpm=sim.spindle.rpm, knives=4)
        got = steady_temperature_c(sim.piezo, table, spindle_rpm=sim.spindle.rpm)
        assert got == pytest.approx(want, rel=1e-3)
    # the alternating full stroke: 160 um per revolution, 100 rev/s -> 25 + 0.005 * 16000
    assert steady_temperature_c(sim.piezo, [20.0, -20.0, 20.0, -20.0],
                                spindle_rpm=6000.0) == pytest.approx(105.0)


def test_a_table_beyond_the_temperature_limit_is_scaled_onto_it():
    sim, _ = _plant({})
    hot = np.array([20.0, -20.0, 20.0, -20.0])
    cool = within_temperature(sim.piezo, hot, spindle_rpm=6000.0, limit_c=70.0)
    assert steady_temperature_c(sim.piezo, cool, spindle_rpm=6000.0) == pytest.approx(70.0)
    assert np.allclose(cool / hot, cool[0] / hot[0])  # the same table, smaller
    mild = np.array([1.0, -1.0, 0.0, 0.0])
    assert within_temperature(sim.piezo, mild, spindle_rpm=6000.0, limit_c=70.0) is mild
    with pytest.raises(ValueError, match="limit_c"):
        within_temperature(sim.piezo, hot, spindle_rpm=6000.0, limit_c=sim.piezo.ambient_c)


def test_the_optimum_of_a_slow_stack_keeps_the_amplifier_within_its_limit():
    """60 Hz, no hysteresis, damping 0.01: the best table regardless of the heat needs about
    92 C in steady state; the honest optimum stays within the amplifier's 70 C and is worse
    (every pattern allowed, the alternating one the loop holds included)."""
    sim, cfg = _plant({"sim.piezo.resonance_hz": 60.0, "sim.piezo.hysteresis": 0.0,
                       "sim.piezo.damping": 0.01})
    free = constrained_optimum_cv(sim, cfg, temperature_limit_c=float("inf"), gain_min=0.0)
    opt = constrained_optimum_cv(sim, cfg, gain_min=0.0)
    assert free.temperature_c > 80.0
    assert opt.temperature_limit_c == sim.piezo.max_temperature_c
    assert opt.temperature_c <= sim.piezo.max_temperature_c + 1e-9
    assert opt.temperature_c == pytest.approx(
        steady_temperature_c(sim.piezo, opt.offsets_um, spindle_rpm=sim.spindle.rpm))
    assert free.cv < opt.cv
    assert true_cv(sim, opt.offsets_um, feed_mm_s=600.0) == pytest.approx(opt.cv, abs=1e-9)


def test_the_optimum_of_a_hysteretic_stack_is_found_beyond_the_small_signal_table():
    """Hysteresis 0.35 at 2 kHz moves a 3 um table by 5 %: the small-signal QP's table is far
    off, the runout scaled up is near the optimum (about 3.3 times the runout)."""
    sim, cfg = _plant({"sim.piezo.resonance_hz": 2000.0, "sim.piezo.hysteresis": 0.35,
                       "sim.piezo.damping": 0.01})
    opt = constrained_optimum_cv(sim, cfg)
    assert opt.cv < 0.01
    assert np.ptp(opt.offsets_um) > 2.5 * np.ptp(sim.cutterhead.runout_um)
    assert opt.temperature_c <= sim.piezo.max_temperature_c


SLOW_60HZ = {"sim.piezo.resonance_hz": 60.0, "sim.piezo.hysteresis": 0.0,
             "sim.piezo.damping": 0.01}


def _mode_size(table, m: int) -> float:
    return float(abs(np.fft.fft(np.asarray(table, float))[m]))


def test_the_pattern_gains_are_the_actuator_s_per_pattern():
    """A fast linear stack moves every pattern by 1; 60 Hz moves the alternating one by about
    0.01; a hysteretic stack moves a pattern more with a larger bound (larger cycles)."""
    from planer.sweep.optimum import pattern_gains

    fast, _ = _plant({"sim.piezo.resonance_hz": 2000.0, "sim.piezo.hysteresis": 0.0})
    assert pattern_gains(fast.piezo, 4, spindle_rpm=6000.0, bound_um=10.0) == pytest.approx(
        [1.0, 1.0], abs=0.02)
    slow, _ = _plant(SLOW_60HZ)
    g = pattern_gains(slow.piezo, 4, spindle_rpm=6000.0, bound_um=17.0)
    assert g[0] > 0.3 and g[1] < 0.03
    hyst, _ = _plant({"sim.piezo.resonance_hz": 2000.0, "sim.piezo.hysteresis": 0.35})
    small = pattern_gains(hyst.piezo, 4, spindle_rpm=6000.0, bound_um=2.0)
    large = pattern_gains(hyst.piezo, 4, spindle_rpm=6000.0, bound_um=16.0)
    assert np.all(large > 2.0 * small)
    assert len(pattern_gains(slow.piezo, 8, spindle_rpm=6000.0, bound_um=4.0)) == 4


def test_the_optimum_holds_the_patterns_the_loop_cannot_move_at_zero():
    """60 Hz: the alternating pattern (gain 0.01) is below the loop's gain_min (0.1), the
    first one (0.44) above: the optimum uses the first and not the alternating one; with every
    pattern allowed it does use the alternating one; with the loop's threshold above both it
    is the zero table."""
    sim, cfg = _plant(SLOW_60HZ)
    ucfg = UniformityLoopConfig.from_mapping(dict(cfg.uniformity_loop), knives=4)
    opt = constrained_optimum_cv(sim, cfg)
    assert opt.patterns == (1,)
    assert opt.pattern_gains[1] < ucfg.gain_min <= opt.pattern_gains[0]
    assert _mode_size(opt.offsets_um, 2) < 1e-9  # the alternating pattern not used
    assert _mode_size(opt.offsets_um, 1) > 1.0  # the first one used
    feed = cfg.quality.target_pitch_mm * sim.spindle.rpm / 60.0 * 4
    zero = true_cv(sim, np.zeros(4), feed_mm_s=feed)
    assert opt.cv < zero - 0.005
    every = constrained_optimum_cv(sim, cfg, gain_min=0.0)
    assert every.patterns == (1, 2)
    assert _mode_size(every.offsets_um, 2) > 1.0
    assert every.cv < opt.cv
    with pytest.raises(ValueError, match="gain_min"):
        constrained_optimum_cv(sim, cfg, gain_min=-1.0)


def test_the_optimum_s_threshold_is_the_loop_s_configured_gain_min():
    sim, cfg = _plant({**SLOW_60HZ, "machine.uniformity_loop.gain_min": 0.5})
    opt = constrained_optimum_cv(sim, cfg)
    assert opt.patterns == ()
    assert np.allclose(opt.offsets_um, 0.0)
    feed = cfg.quality.target_pitch_mm * sim.spindle.rpm / 60.0 * 4
    assert opt.cv == pytest.approx(true_cv(sim, np.zeros(4), feed_mm_s=feed))
