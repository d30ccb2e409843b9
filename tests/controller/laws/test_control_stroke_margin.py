"""What the uniformity loop's stroke margin protects, and that its default is enough for it.

The default ``margin_um`` covers the CAN codec's rounding: the amplifier refuses an offset beyond
its stroke and raises the stroke-limit bit when the displacement reaches it; a zero-mean table
played with the matched input shaper never moves the actuator beyond the table
(docs/control_design.md, section 3, "The stroke").
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from config.sim import default_sim
from controller.laws.limits import project_zero_mean_box
from controller.laws.uniformity_loop import DEFAULT_MARGIN_UM, UniformityLoopConfig, offset_limit_um
from plant_sim.model.piezo import FAULT_STROKE, PiezoAmplifier
from protocol.piezo_canopen import nm_from_um, um_from_nm

STEP_UM = 0.001  # the offsets' resolution on the wire (config/piezo_amp.eds: INTEGER16 nm)


def _on_the_wire(table_um):
    """The table as the amplifier decodes it (1 nm per bit, rounded to the nearest)."""
    return np.array([um_from_nm(nm_from_um(v)) for v in table_um])


def _play(piezo_cfg, tables, *, revolutions=12, rpm=6000.0, samples=25):
    """Play the tables in turn; the largest |displacement| (sampled densely) and the fault bits."""
    z = len(tables[0])
    amp = PiezoAmplifier(piezo_cfg, z, np.random.default_rng(0))
    amp.command(0.0, enable=True, alive_counter=1)
    act = amp.actuator
    period = 60.0 / rpm / z
    t, peak, faults = 0.0, 0.0, 0
    for table in tables:
        amp.set_offsets(list(table))  # raises beyond the stroke: a refused table
        for _ in range(revolutions):
            for k in range(z):
                switch = t + (1.0 - piezo_cfg.lead_fraction) * period
                amp.advance_to(switch)
                amp.switch(k, switch)
                peak = max(peak, float(np.max(np.abs(act.displacement_at(
                    np.linspace(switch, t + period, samples))))))
                t += period
                amp.advance_to(t)
                amp.cycle(t, period, spindle_turning=True)
                faults |= amp.fault_bits
            amp.last_command_s = t  # commands keep coming: no setpoint timeout
    return peak, faults


def test_the_default_margin_is_the_codec_s_rounding_with_room_to_spare():
    assert UniformityLoopConfig().margin_um == DEFAULT_MARGIN_UM
    assert 0.5 * STEP_UM < DEFAULT_MARGIN_UM <= 20 * STEP_UM


@pytest.mark.parametrize("stroke", [0.5, 7.3, 10.0, 13.7777, 20.0, 32.0])
def test_a_table_at_the_default_limit_stays_strictly_inside_the_stroke_on_the_wire(stroke):
    limit = offset_limit_um(stroke, DEFAULT_MARGIN_UM)
    table = np.array([limit, -limit, 0.37 * limit, -0.37 * limit])
    wire = _on_the_wire(table)
    assert np.allclose(wire, table, atol=0.5 * STEP_UM + 1e-12)
    assert np.max(np.abs(wire)) < stroke


def test_without_a_margin_the_wire_rounds_past_a_stroke_off_its_grid():
    stroke = 13.7777  # machine.toml may say anything; the wire carries 1 nm steps
    wire = _on_the_wire(np.array([stroke, -stroke, 0.0, 0.0]))
    assert np.max(np.abs(wire)) > stroke  # the amplifier would refuse it
    limit = offset_limit_um(stroke, DEFAULT_MARGIN_UM)
    assert np.max(np.abs(_on_the_wire(np.array([limit, -limit, 0.0, 0.0])))) < stroke


def test_without_hysteresis_a_table_at_the_stroke_raises_the_stroke_bit_and_the_margin_does_not():
    """The displacement settles on the table: at exactly the stroke the amplifier flags it."""
    cfg = dataclasses.replace(default_sim().piezo, stroke_um=10.0, hysteresis=0.0)
    at_stroke = np.array([-3.9, 10.0, -10.0, 3.9])
    _, faults = _play(cfg, [at_stroke])
    assert faults & FAULT_STROKE
    limit = offset_limit_um(10.0, DEFAULT_MARGIN_UM)
    peak, faults = _play(cfg, [at_stroke * limit / 10.0])
    assert not faults & FAULT_STROKE
    assert peak == pytest.approx(limit, abs=1e-6)  # settles on the table, no overshoot
    with pytest.raises(ValueError, match="within"):  # beyond the stroke: refused
        _play(cfg, [at_stroke * (10.0 + 2 * STEP_UM) / 10.0])


@pytest.mark.parametrize(("resonance_hz", "hysteresis"),
                         [(800.0, 0.0), (800.0, 0.03), (150.0, 0.03), (150.0, 0.3), (800.0, 0.3)])
def test_zero_mean_tables_within_the_default_limit_never_reach_the_stroke(resonance_hz,
                                                                          hysteresis):
    """Jumps between zero-mean tables at the box's edges, slow and hysteretic stacks included."""
    stroke = 10.0
    cfg = dataclasses.replace(default_sim().piezo, stroke_um=stroke, resonance_hz=resonance_hz,
                              hysteresis=hysteresis)
    limit = offset_limit_um(stroke, DEFAULT_MARGIN_UM)
    rng = np.random.default_rng(7)
    tables = [np.zeros(4)] + [project_zero_mean_box(rng.normal(0.0, 12.0, 4), bound=limit)
                              for _ in range(6)]
    assert max(float(np.max(np.abs(t))) for t in tables) == pytest.approx(limit)
    peak, faults = _play(cfg, tables, revolutions=6)
    assert peak <= limit + 1e-6
    assert not faults & FAULT_STROKE
