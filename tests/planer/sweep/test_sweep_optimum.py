"""The constrained-optimum reference: the best true CV a plant allows."""

from __future__ import annotations

import numpy as np
import pytest

from controller.laws.uniformity_loop import UniformityLoopConfig
from planer.hil.scenario import load_scenario
from planer.sweep.design import Point
from planer.sweep.optimum import actuator_response_um, constrained_optimum_cv, true_cv
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
