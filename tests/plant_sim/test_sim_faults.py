"""Injected faults: each does to the simulated machine what it would do to a real one."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from config.sim import FaultSpec, load_sim
from plant_sim.machine.machine import Machine

MOD32 = 1 << 32


@pytest.fixture(scope="module")
def cfg():
    return load_sim()


def alive(m: Machine, duration_s: float, offsets=None, step_s: float = 0.01):
    frames = []
    for i in range(int(round(duration_s / step_s))):
        m.piezo_command(enable=True, alive_counter=(i + 1) % 256)
        if offsets is not None:
            m.set_piezo_offsets(offsets)
        frames += m.advance(step_s)
    return frames


def knife_of(f, x_mm, cfg):
    """The architecture's mark-to-knife formula, with wrapping counter arithmetic."""
    rig = cfg.camera.rig
    cpm = cfg.encoder.counts_per_mm
    back = (cfg.camera.cutter_to_camera_mm + x_mm - rig.camera.cx / rig.camera.px_per_mm) * cpm
    d = (f.counts_a - f.index_latch_counts) % MOD32
    d = d - MOD32 if d >= MOD32 // 2 else d
    return round((d - back) / (f.truth["feed_per_knife_mm"] * cpm)) % cfg.cutterhead.knives


def test_encoder_wrap_between_triggers_and_after(cfg):
    m = Machine(cfg, seed=0, render_images=False)
    m.advance(0.9995)
    s0 = m.feed_position_mm
    # the counter wraps 20 counts from now: trigger A (t = 1.0) before, B (2 ms later) after
    m.inject("encoder_wrap", counts_before_wrap=20)
    assert m.register_values()["encoder_counts"] == MOD32 - 20
    frames = m.advance(1.0)
    f = frames[0]
    assert f.t_s == pytest.approx(1.0)
    assert f.counts_a > MOD32 - 100 and f.counts_b < 100  # wrapped between A and B
    shift_counts = (f.counts_b - f.counts_a) % MOD32
    assert shift_counts * 0.625 == pytest.approx(f.truth["shift_px"], abs=0.7)
    assert abs(f.truth["encoder_error_px"]) < 0.7
    # the index latch was recorded before the wrap; the knife formula still holds
    for fr in frames:
        for x_mm, k in zip(fr.truth["bottoms_mm"], fr.truth["knife"], strict=True):
            assert knife_of(fr, x_mm, cfg) == k
    counts = m.register_values()["encoder_counts"]
    assert counts == (math.floor(m.feed_position_mm * 20 + 1e-9) - math.floor(s0 * 20 + 1e-9)
                      - 20) % MOD32


def test_encoder_wrap_from_config_start_counts(cfg):
    c = dataclasses.replace(
        cfg, encoder=dataclasses.replace(cfg.encoder, start_counts=MOD32 - 16000))
    m = Machine(c, seed=0, render_images=False)
    frames = m.advance(1.6)
    assert any(f.counts_a > MOD32 // 2 for f in frames) and any(f.counts_a < 1e5 for f in frames)
    for fr in frames:
        for x_mm, k in zip(fr.truth["bottoms_mm"], fr.truth["knife"], strict=True):
            assert knife_of(fr, x_mm, cfg) == k


@pytest.mark.parametrize("px", [12.0, -8.0])
def test_belt_slip_the_encoder_lies_by_n_px(cfg, px):
    m = Machine(cfg, seed=0, render_images=False)
    m.advance(0.95)
    before = m.register_values()["encoder_counts"] - int(m.feed_position_mm * 20)
    m.inject("belt_slip", px=px)
    frames = m.advance(0.5)
    slip_counts = round(px / 0.625)
    errors = [f.truth["encoder_error_px"] for f in frames]
    # the pair during which the belt slipped counts the lie; the others count true shifts
    assert errors[0] == pytest.approx(slip_counts * 0.625, abs=0.65)
    assert np.all(np.abs(errors[1:]) < 0.65)
    assert frames[0].counts_b - frames[0].counts_a == pytest.approx(
        frames[0].truth["shift_px"] / 0.625 + slip_counts, abs=1)
    # and the counter stays off by the slip from then on
    after = m.register_values()["encoder_counts"] - int(m.feed_position_mm * 20)
    assert after - before == pytest.approx(slip_counts, abs=1)


def test_belt_slip_from_config_at_time(cfg):
    c = dataclasses.replace(cfg, faults=(FaultSpec("belt_slip", {"at_s": 1.25, "counts": 30}),))
    m = Machine(c, seed=0, render_images=False)
    frames = m.advance(1.6)
    lied = [f for f in frames if abs(f.truth["encoder_error_px"]) > 1]
    assert len(lied) == 1 and lied[0].t_s == pytest.approx(1.3)
    assert lied[0].truth["encoder_error_px"] == pytest.approx(30 * 0.625, abs=0.65)


def test_knot_is_a_dark_rough_patch_in_the_images(cfg):
    # board 1's point 240 mm from its leading end passes the camera at t = (100+300+240)/800
    def frames(with_knot):
        m = Machine(cfg, seed=3, render_images=True)
        if with_knot:
            m.inject("knot", board_id=1, at_mm=240.0, length_mm=30.0, width_mm=25.0,
                     darkness=0.6, roughness_um=5.0)
        m.advance(0.65)
        return m.advance(0.2)

    knotted, clean = frames(True), frames(False)
    f = next(f for f in knotted if abs(f.board_position_mm - 240.0) < 20.0)
    g = next(g for g in clean if g.seq == f.seq)
    assert f.truth["knot"] and not g.truth["knot"]
    assert not any(h.truth["knot"] for h in knotted if abs(h.board_position_mm - 240.0) > 60.0)
    # where the knot is in image A: column of board point at_mm (image x runs to the leading end)
    ppm, cx, cy = 12.5, 329.0, 246.0
    col = int(round(cx + (f.board_position_mm - 240.0) * ppm))
    win = (slice(int(cy) - 40, int(cy) + 40), slice(max(col - 60, 0), min(col + 60, 659)))
    ratio = f.image_a[win].mean() / g.image_a[win].mean()
    assert ratio < 0.75
    far = (slice(0, 60), slice(0, 659))  # outside the patch the images agree
    assert f.image_a[far].mean() == pytest.approx(g.image_a[far].mean(), rel=0.03)
    # rough: the knot adds fine height texture, so the normalised image varies more there
    rel_a = f.image_a[win].astype(float) / f.image_a[win].mean()
    rel_clean = g.image_a[win].astype(float) / g.image_a[win].mean()
    assert np.std(np.diff(rel_a, axis=1)) > 1.05 * np.std(np.diff(rel_clean, axis=1))


def test_spindle_stop_coasts_down_and_stops_the_feed(cfg):
    m = Machine(cfg, seed=0, render_images=False)
    m.advance(1.0)
    vals = m.register_values()
    assert vals["machine_state"] & 0b11001 == 0b11001 and not vals["faults"] & 0b10
    m.inject("spindle_stop")
    rpm, feed = [], []
    for _ in range(200):
        m.advance(0.1)
        v = m.register_values()
        rpm.append(v["spindle_rpm"])
        feed.append(v["feed_actual_mm_s"])
    v = m.register_values()
    assert v["faults"] & 0b10  # spindle stopped
    assert not v["machine_state"] & 0b1001  # neither running nor spindle running
    assert not v["machine_state"] & 0b10000  # interlock: feed disabled
    assert rpm[-1] == 0.0
    assert np.all(np.diff(rpm) <= 1.0)  # coasting: it only slows down (ripple aside)
    # coast-down time constant: after one tau about 37 % of the speed is left
    tau = cfg.spindle.coast_tau_s
    assert rpm[int(tau / 0.1) - 1] == pytest.approx(0.37 * cfg.spindle.rpm, rel=0.1)
    # the feed ramps down at the acceleration limit
    assert feed[-1] == 0.0
    stop_s = 800.0 / cfg.feed.accel_max_mm_s2
    assert feed[int(stop_s / 0.1) - 2] > 100.0  # still braking at the limit
    assert feed[int(stop_s / 0.1) + 4] < 0.01  # then the velocity loop settles at standstill
    # no knife passes once stopped; the board stands still
    n = len(m.passes(1))
    s = m.feed_position_mm
    m.advance(1.0)
    assert len(m.passes(1)) == n and m.feed_position_mm == s
    # reset: the spindle runs up again, then the feed restarts
    m.reset_faults()
    m.advance(3.0)
    v = m.register_values()
    assert v["faults"] & 0b10 == 0 and v["machine_state"] & 0b11001 == 0b11001
    assert v["feed_actual_mm_s"] == pytest.approx(800.0)


def test_dropped_piezo_commands_ramp_to_zero(cfg):
    m = Machine(cfg, seed=0, render_images=False)
    offsets = [3.0] * 4
    alive(m, 0.2, offsets)
    assert m.piezo_status().state == 1
    m.inject("can_drop", duration_s=0.4)
    states, disp = [], []
    for i in range(40):  # the service keeps sending; the bus loses everything
        m.piezo_command(enable=True, alive_counter=100 + i)
        m.set_piezo_offsets([5.0] * 4)
        m.advance(0.01)
        states.append(m.piezo_status().state)
        disp.append(m.piezo_displacement_um)
    assert states[5] == 1 and 2 in states
    assert abs(disp[-1]) < 0.2  # ramped down to zero (hysteresis remnant aside)
    alive(m, 0.1)  # frames get through again (no new table: the lost one never arrived)
    st = m.piezo_status()
    assert st.state == 1 and st.fault == 0
    assert m.piezo_displacement_um == pytest.approx(3.0, rel=0.1)


def test_estop(cfg):
    m = Machine(cfg, seed=0, render_images=False)
    alive(m, 0.5, [2.0] * 4)
    m.inject("estop")
    rpm = []
    for _ in range(40):
        m.piezo_command(enable=True, alive_counter=len(rpm) % 256)
        m.advance(0.1)
        rpm.append(m.spindle_rpm)
    v = m.register_values()
    assert v["machine_state"] & 0b100  # e-stop
    assert not v["machine_state"] & 0b11001
    assert v["feed_actual_mm_s"] == 0.0 and v["spindle_rpm"] == 0.0
    # braked: much faster than coasting
    tau = cfg.spindle.brake_tau_s
    assert rpm[int(2 * tau / 0.1) - 1] < 0.2 * cfg.spindle.rpm
    # the piezo amplifier is powered off and ignores enable
    assert m.piezo_status().state == 0 and abs(m.piezo_displacement_um) < 0.2
    m.set_feed_setpoint(500.0)  # the PLC still takes setpoints
    m.reset_faults()
    alive(m, 3.0, [2.0] * 4)
    v = m.register_values()
    assert not v["machine_state"] & 0b100 and v["machine_state"] & 0b11001 == 0b11001
    assert v["feed_actual_mm_s"] == pytest.approx(500.0)
    assert m.piezo_status().state == 1


def test_feed_fault_and_encoder_fault_and_piezo_fault(cfg):
    m = Machine(cfg, seed=0, render_images=False)
    alive(m, 0.3, [1.0] * 4)
    m.inject("feed_fault")
    m.inject("encoder_fault")
    m.inject("piezo_fault", bit=3)
    c0 = m.register_values()["encoder_counts"]
    m.advance(1.0)
    v = m.register_values()
    assert v["faults"] & 0b10101 == 0b10101  # feed drive, encoder, piezo amplifier
    assert v["encoder_counts"] == c0  # counter stopped
    assert v["feed_actual_mm_s"] == 0.0 and not v["machine_state"] & 0b10000
    st = m.piezo_status()
    assert st.state == 3 and st.fault & 0b1000
    m.piezo_command(enable=False, alive_counter=1)  # a disable clears the amplifier fault
    assert m.piezo_status().state == 0
    m.reset_faults()
    m.advance(1.0)
    v = m.register_values()
    assert v["faults"] & 0b10111 == 0
    assert v["encoder_counts"] > c0  # counts on from where it stopped
    assert v["encoder_counts"] - c0 < m.feed_position_mm * 20 - 0.3 * 800 * 20


def test_interface_faults_are_queued_for_the_runner(cfg):
    c = dataclasses.replace(cfg, faults=(
        FaultSpec("modbus_restart", {"at_s": 0.5, "duration_s": 1.0}),
        FaultSpec("can_silence", {"at_s": 0.8, "duration_s": 0.5}),
    ))
    m = Machine(c, seed=0, render_images=False)
    m.advance(0.4)
    assert m.take_interface_events() == []
    m.advance(0.2)
    ev = m.take_interface_events()
    assert [e["kind"] for e in ev] == ["modbus_restart"]
    assert ev[0]["duration_s"] == 1.0 and ev[0]["t_s"] == pytest.approx(0.5, abs=0.003)
    assert m.take_interface_events() == []
    m.advance(0.3)
    assert [e["kind"] for e in m.take_interface_events()] == ["can_silence"]


@pytest.mark.parametrize(
    ("kind", "params"),
    [("gremlins", {}), ("belt_slip", {"px": 1.0, "counts": 2}), ("estop", {"px": 1.0}),
     ("belt_slip", {"px": float("nan")}), ("knot", {"at_mm": -5.0}),
     ("can_drop", {"fraction": 1.5}), ("encoder_wrap", {"counts_before_wrap": 0}),
     ("piezo_fault", {"bit": 2.5}), ("knot", {"at_mm": 100.0, "at_s": 1.0, "darkness": 2.0})],
)
def test_bad_faults_raise(cfg, kind, params):
    m = Machine(cfg, seed=0, render_images=False)
    with pytest.raises(ValueError):
        m.inject(kind, **params)
