"""The spindle's setpoint (a moulder's variable head) and a machine's head register block."""

from __future__ import annotations

import math

import pytest

from config.sim import SpindleConfig, default_sim
from plant_sim.machine.machine import Machine
from plant_sim.model.spindle import Spindle
from protocol.registers import HeadFault, RegisterMap

CYCLE_S = 0.002


def _run(sp: Spindle, seconds: float) -> list[float]:
    """The drive's speed (rpm, without ripple and droop) at every cycle over ``seconds``."""
    out = []
    t = 0.0
    for _ in range(round(seconds / CYCLE_S)):
        sp.start_cycle(t, CYCLE_S, cutting=False)
        out.append(sp.drive_rev_s * 60.0)
        sp.end_cycle(CYCLE_S)
        t += CYCLE_S
    return out


def test_variable_spindle_ramps_to_its_setpoint_on_the_spinup_tau():
    cfg = SpindleConfig(rpm=6000.0, spinup_tau_s=1.0, rpm_min=4000.0, rpm_max=8000.0)
    sp = Spindle(cfg)
    assert sp.variable and sp.setpoint_rpm == 6000.0
    sp.set_setpoint(8000.0)
    rpm = _run(sp, 5.0)
    # first order toward 8000 with tau 1 s: 1 - exp(-1) of the step after 1 s
    at_1s = rpm[round(1.0 / CYCLE_S) - 1]
    assert at_1s == pytest.approx(6000.0 + 2000.0 * (1 - math.exp(-1.0)), rel=2e-3)
    assert all(b >= a for a, b in zip(rpm, rpm[1:], strict=False))  # no overshoot, monotone
    assert rpm[-1] == pytest.approx(8000.0, abs=2000.0 * math.exp(-4.9))
    assert sp.running  # never dropped out of "running" on the way (the feed may run)
    sp.set_setpoint(4000.0)
    rpm = _run(sp, 8.0)
    assert rpm[-1] == pytest.approx(4000.0, abs=4000.0 * math.exp(-7.9))
    assert sp.running


@pytest.mark.parametrize("bad", [3999.0, 8000.5, math.nan, math.inf])
def test_variable_spindle_refuses_a_setpoint_outside_its_range(bad):
    sp = Spindle(SpindleConfig(rpm=6000.0, rpm_min=4000.0, rpm_max=8000.0))
    with pytest.raises(ValueError, match="rpm"):
        sp.set_setpoint(bad)
    assert sp.setpoint_rpm == 6000.0


def test_fixed_spindle_takes_only_its_own_speed():
    sp = Spindle(SpindleConfig(rpm=6000.0))
    assert not sp.variable and (sp.rpm_min, sp.rpm_max) == (6000.0, 6000.0)
    sp.set_setpoint(6000.0)  # its own speed: accepted, nothing changes
    with pytest.raises(ValueError, match=r"rpm must be in \[6000.0, 6000.0\]"):
        sp.set_setpoint(6100.0)


def test_machine_head_block_zero_holds_the_head_fields():
    m = Machine(default_sim(), seed=3, render_images=False)
    m.advance(3.0)
    head = m.head_register_values(0)
    legacy = m.register_values()
    assert set(head) == set(RegisterMap.load().heads.names)  # every field of the block
    for name in ("spindle_rpm", "knives", "cutterhead_radius_mm", "cutter_to_camera_mm",
                 "trigger_a_counts", "trigger_b_counts", "trigger_seq", "index_latch_counts"):
        assert head[name] == legacy[name], name
    assert legacy["trigger_seq"] > 0  # pairs were taken: the latches are real ones
    rpm = default_sim().spindle.rpm
    assert head["spindle_setpoint_rpm"] == head["spindle_rpm_min"] == head["spindle_rpm_max"]
    assert head["spindle_rpm_max"] == rpm
    assert head["head_faults"] == 0
    m.inject("spindle_stop")
    m.inject("piezo_fault")
    m.inject("measurement_dropout", duration_s=1.0, fraction=1.0)
    m.advance(0.01)
    want = HeadFault.AMPLIFIER | HeadFault.SPINDLE | HeadFault.CAMERA_SILENT
    assert m.head_register_values(0)["head_faults"] == want
    with pytest.raises(ValueError, match="i must be"):
        m.head_register_values(1)
    with pytest.raises(ValueError, match="i must be"):
        m.set_spindle_setpoint(1, rpm)
    with pytest.raises(ValueError, match="rpm must be in"):
        m.set_spindle_setpoint(0, rpm + 100.0)


def test_machines_on_one_feed_step_together_and_the_owner_steps_it():
    from plant_sim.machine.machine import advance_together
    from plant_sim.model.feed_drive import BoardView

    cfg = default_sim()
    alone = Machine(cfg, seed=5, render_images=False)
    owner = Machine(cfg, seed=5, render_images=False)
    other = Machine(cfg, seed=6, render_images=False, feed=owner.feed, encoder=owner.encoder,
                    boards=BoardView(owner.boards, 400.0))
    assert owner.owns_feed and not other.owns_feed
    with pytest.raises(RuntimeError, match="step them together"):
        other.advance(0.01)
    frames_alone = alone.advance(2.0)
    frames_owner, frames_other = advance_together((owner, other), 2.0)
    # the owner sees exactly what it sees alone; the feed moved once, not twice
    assert [(f.seq, f.t_s, f.counts_a, f.truth) for f in frames_owner] == [
        (f.seq, f.t_s, f.counts_a, f.truth) for f in frames_alone]
    assert owner.feed_position_mm == alone.feed_position_mm == other.feed_position_mm
    assert other.t_s == owner.t_s == 2.0
    # a board reaches the head 400 mm downstream 400 mm of travel later
    b = cfg.board
    assert other.boards.at(b.first_at_mm + 399.0, 0.0)[0] == 0
    assert other.boards.at(b.first_at_mm + 401.0, 0.0) == owner.boards.at(b.first_at_mm + 1.0,
                                                                          0.0)
    # a stopped spindle on the other head stops the feed under both
    other.inject("spindle_stop")
    advance_together((owner, other), 3.0)
    assert owner.feed_speed_mm_s == 0.0
    assert not other.plc.feed_permitted() and owner.plc.feed_permitted()
