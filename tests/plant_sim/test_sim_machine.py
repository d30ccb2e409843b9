"""The machine model: drives, encoder, piezo, the cut, the camera, registers, determinism."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from config.loading import default_path, load_toml
from config.sim import default_sim, load_sim, sim_from_dict
from core.errors import ConfigError
from plant_sim.machine.machine import Machine
from plant_sim.model.piezo import PiezoActuator


@pytest.fixture(scope="module")
def cfg():
    return load_sim()


def replace(cfg, **tables):
    """A copy of ``cfg`` with some fields of some tables replaced: replace(cfg, piezo={...})."""
    out = {}
    for name, fields in tables.items():
        out[name] = dataclasses.replace(getattr(cfg, name), **fields)
    return dataclasses.replace(cfg, **out)


def keep_piezo_alive(m: Machine, duration_s: float, offsets=None, step_s: float = 0.01):
    """Advance while sending commands (and offsets) like the service would."""
    frames = []
    n = int(round(duration_s / step_s))
    for i in range(n):
        m.piezo_command(enable=True, alive_counter=(i + 1) % 256)
        if offsets is not None:
            m.set_piezo_offsets(offsets)
        frames += m.advance(step_s)
    return frames


# ---------------------------------------------------------------- configuration


def test_shipped_config_loads_and_matches_defaults(cfg):
    d = default_sim()
    for table in ("spindle", "cutterhead", "piezo", "feed", "encoder", "plc", "run",
                  "modbus", "frames"):
        assert getattr(cfg, table) == getattr(d, table), table
    b, db = cfg.board, d.board  # [board] also holds the realistic rig's wood effects
    assert (b.length_mm, b.gap_mm, b.first_at_mm, b.count) == (
        db.length_mm, db.gap_mm, db.first_at_mm, db.count)
    assert cfg.modbus.host == "127.0.0.1"
    assert cfg.camera.rig_path.name == "rig.toml"
    # initial feed is the pitch-2.0 mm equivalent so the controller has work to do
    pitch = cfg.feed.initial_mm_s / (cfg.spindle.rpm / 60 * cfg.cutterhead.knives)
    assert pitch == pytest.approx(2.0)


@pytest.mark.parametrize(
    ("doc", "key"),
    [
        ({"piezo": {"stroke_um": -1.0}}, "piezo.stroke_um"),
        ({"feed": {"min_mm_s": 500.0, "max_mm_s": 100.0}}, "feed.max_mm_s"),
        ({"cutterhead": {"knives": 4, "runout_um": [1.0, 2.0]}}, "cutterhead.runout_um"),
        ({"encoder": {"counter_bits": 24}}, "encoder.counter_bits"),
        # the service unwraps the latches with the rig's width: the two must agree
        ({"encoder": {"counter_bits": 16}}, "encoder.counter_bits"),
        ({"encoder": {"counts_per_mm": 10.0}}, "encoder.counts_per_mm"),
        ({"can": {"channel": ""}}, "can.channel"),
        ({"modbus": {"port": 70000}}, "modbus.port"),
        ({"camera": {"species": "balsa"}}, "camera.species"),
        ({"can": {"interface": "serial"}}, "can.interface"),
        ({"spindle": {"rmp": 6000.0}}, "spindle.rmp"),
        ({"faults": {"inject": [{"kind": "gremlins"}]}}, "faults.inject[0].kind"),
        ({"faults": {"inject": [{"kind": "belt_slip", "px": "x"}]}}, "faults.inject[0].px"),
    ],
)
def test_config_errors_name_the_key(doc, key):
    with pytest.raises(ConfigError, match=key.replace("[", r"\[").replace("]", r"\]")):
        sim_from_dict(doc)


# ---------------------------------------------------------------- feed drive and encoder


def test_feed_step_respects_acceleration_limit_and_settles(cfg):
    m = Machine(cfg, seed=0, render_images=False)
    amax = cfg.feed.accel_max_mm_s2
    dt = 0.001
    for target in (1000.0, 100.0):
        m.set_feed_setpoint(target)
        v = [m.feed_speed_mm_s]
        for _ in range(1500):
            m.advance(dt)
            v.append(m.feed_speed_mm_s)
        v = np.asarray(v)
        assert np.max(np.abs(np.diff(v))) <= amax * dt * (1 + 1e-9)
        assert np.max(np.abs(np.diff(v))) > 0.9 * amax * dt  # the limit is actually reached
        lo, hi = sorted((v[0], target))
        assert np.all((v >= lo - 1e-9) & (v <= hi + 1e-9))  # no overshoot
        assert v[-1] == pytest.approx(target, abs=0.01)
        assert m.register_values()["feed_actual_mm_s"] == pytest.approx(target, abs=0.01)


@pytest.mark.parametrize("bad", [49.9, 1000.5, -5.0, math.nan, math.inf])
def test_out_of_range_feed_setpoint_raises_and_keeps_the_old_one(cfg, bad):
    m = Machine(cfg, seed=0, render_images=False)
    m.set_feed_setpoint(600.0)
    with pytest.raises(ValueError, match="feed_mm_s"):
        m.set_feed_setpoint(bad)
    assert m.register_values()["feed_setpoint_mm_s"] == 600.0
    m.set_feed_setpoint(cfg.feed.min_mm_s)  # the limits themselves are accepted
    m.set_feed_setpoint(cfg.feed.max_mm_s)


@pytest.mark.parametrize("bits", [16, 32])
def test_encoder_counts_follow_position_and_wrap(cfg, bits):
    start = (1 << bits) - 5000
    c = replace(cfg, encoder={"counter_bits": bits, "start_counts": start})
    m = Machine(c, seed=0, render_images=False)
    cpm = c.encoder.counts_per_mm
    seen_wrap = False
    prev = m.register_values()["encoder_counts"]
    for _ in range(60):
        m.advance(0.0137)
        counts = m.register_values()["encoder_counts"]
        expect = (start + math.floor(m.feed_position_mm * cpm + 1e-9)) % (1 << bits)
        assert counts == expect
        assert 0 <= counts < (1 << bits)
        seen_wrap |= counts < prev
        prev = counts
    assert seen_wrap


# ---------------------------------------------------------------- piezo


def test_piezo_step_response_rings_at_the_resonance_and_matches_the_ode():
    f0, zeta = 800.0, 0.2
    act = PiezoActuator(resonance_hz=f0, damping=zeta, hysteresis=0.0, stroke_um=20.0)
    act.drive(10.0)
    t = np.linspace(0.0, 0.01, 4001)
    x = act.displacement_at(t)
    wn = 2 * np.pi * f0
    ode = solve_ivp(
        lambda _t, y: [y[1], wn * wn * (10.0 - y[0]) - 2 * zeta * wn * y[1]],
        (0.0, 0.01), [0.0, 0.0], t_eval=t, rtol=1e-10, atol=1e-12,
    )
    assert np.max(np.abs(x - ode.y[0])) < 1e-6
    # ringing frequency and overshoot of a second-order system
    e = x - 10.0
    crossings = t[1:][np.diff(np.sign(e)) != 0]
    f_ring = 1.0 / (2 * np.mean(np.diff(crossings[:6])))
    assert f_ring == pytest.approx(f0 * math.sqrt(1 - zeta**2), rel=0.01)
    overshoot = math.exp(-zeta * math.pi / math.sqrt(1 - zeta**2))
    assert x.max() - 10.0 == pytest.approx(10.0 * overshoot, rel=0.01)
    # settled after 4 time constants (2 % band) and propagation agrees with evaluation
    tau = 1.0 / (zeta * wn)
    assert np.all(np.abs(e[t > 4 * tau]) < 0.2)
    act.propagate_to(0.003)
    assert act.x_um == pytest.approx(float(np.interp(0.003, t, x)), abs=1e-3)


def test_piezo_hysteresis_is_a_few_percent():
    stroke, hyst = 20.0, 0.03
    act = PiezoActuator(resonance_hz=800.0, damping=0.2, hysteresis=hyst, stroke_um=stroke)
    u = np.concatenate([np.linspace(0, stroke, 200), np.linspace(stroke, -stroke, 400),
                        np.linspace(-stroke, stroke, 400), np.linspace(stroke, -stroke, 400)])
    levels = []
    for v in u:  # quasi-static: the level after each small step
        act.drive(float(v))
        levels.append(act.level_um)
    levels = np.asarray(levels)
    down = slice(1000, 1400)
    up = slice(600, 1000)
    y_up = np.interp(0.0, u[up], levels[up])
    y_down = np.interp(0.0, u[down][::-1], levels[down][::-1])
    width = y_down - y_up  # falling branch above the rising one
    rel = width / (2 * stroke)
    assert rel == pytest.approx(hyst, rel=0.15)
    assert 0.01 < rel < 0.06
    # no hysteresis: the level is the command
    act0 = PiezoActuator(resonance_hz=800.0, damping=0.2, hysteresis=0.0, stroke_um=stroke)
    act0.drive(7.0)
    assert act0.level_um == 7.0


def test_piezo_offsets_beyond_stroke_raise(cfg):
    m = Machine(cfg, seed=0, render_images=False)
    stroke = cfg.piezo.stroke_um
    m.set_piezo_offsets([stroke, -stroke, 0.0, 0.0])
    for bad in ([stroke + 0.01, 0, 0, 0], [0, 0, -stroke - 1, 0], [1.0, 2.0], [0, 0, math.nan, 0],
                [0.0] * 9):
        with pytest.raises(ValueError, match="offsets_um"):
            m.set_piezo_offsets(bad)


def test_piezo_setpoint_timeout_ramps_to_zero(cfg):
    m = Machine(cfg, seed=0, render_images=False)
    offsets = [4.0, 4.0, 4.0, 4.0]  # a constant lift: the displacement is easy to follow
    keep_piezo_alive(m, 0.2, offsets)
    st = m.piezo_status()
    assert st.state == 1 and st.fault == 0
    assert m.piezo_displacement_um == pytest.approx(4.0, rel=0.1)
    # commands stop: within the timeout nothing happens, then ramp at ramp_um_s
    t_last = m.t_s
    m.advance(cfg.piezo.timeout_s * 0.8)
    assert m.piezo_status().state == 1
    disp = []
    for _ in range(40):
        m.advance(0.005)
        disp.append(m.piezo_displacement_um)
    st = m.piezo_status()
    assert st.state == 2 and st.fault & 0b100
    assert m.amp.output_um == 0.0
    assert abs(disp[-1]) < 0.15  # the hysteresis' remnant only
    assert np.all(np.diff(disp) < 0.02)  # decreasing (up to residual ringing)
    ramp_s = 4.0 / cfg.piezo.ramp_um_s
    t_zero = t_last + cfg.piezo.timeout_s + ramp_s
    # not a jump: halfway through the ramp the head is still about half up
    m2 = Machine(cfg, seed=0, render_images=False)
    keep_piezo_alive(m2, 0.2, offsets)
    m2.advance(t_zero - m2.t_s - ramp_s / 2)
    assert 1.0 < m2.piezo_displacement_um < 3.0
    # commands resume: tracking again
    keep_piezo_alive(m, 0.05, offsets)
    st = m.piezo_status()
    assert st.state == 1 and not st.fault & 0b100
    assert m.piezo_displacement_um == pytest.approx(4.0, rel=0.1)


def test_repeated_alive_counter_does_not_keep_the_amplifier_alive(cfg):
    m = Machine(cfg, seed=0, render_images=False)
    m.set_piezo_offsets([3.0] * 4)
    disp = []
    for _ in range(40):
        m.piezo_command(enable=True, alive_counter=7)  # a hung service repeating itself
        m.advance(0.01)
        disp.append(m.piezo_displacement_um)
    assert m.piezo_status().state == 2
    assert max(disp) > 2.5 and abs(disp[-1]) < 0.15
    assert np.all(np.diff(disp[15:]) < 0.02)  # the stale frames do not restart the ramp


def test_eddy_current_sensor_noise(cfg):
    m = Machine(cfg, seed=0, render_images=False)
    keep_piezo_alive(m, 0.1, [2.0] * 4)
    x = m.piezo_displacement_um
    r = np.array([m.eddy_current_um() for _ in range(2000)])
    assert r.mean() == pytest.approx(x, abs=0.01)
    assert r.std() == pytest.approx(cfg.piezo.sensor_noise_um, rel=0.1)


# ---------------------------------------------------------------- the cut


def run_frames(m: Machine, duration_s: float, offsets=None):
    return keep_piezo_alive(m, duration_s, offsets)


def test_piezo_off_surface_shows_kinematic_pitch_and_depth(cfg):
    r_mm = cfg.cutterhead.radius_mm
    flat = replace(cfg, cutterhead={"runout_um": (0.0,) * 4, "eccentricity_um": 0.0})
    for c in (cfg, flat):
        for feed in (800.0, 600.0):
            m = Machine(c, seed=1, render_images=False)
            m.set_feed_setpoint(feed)
            frames = m.advance(2.0)[-5:]
            assert frames
            for f in frames:
                tr = f.truth
                pitch = feed / (m.spindle_rpm / 60 * c.cutterhead.knives)
                w = np.asarray(tr["mark_widths_mm"])
                assert tr["feed_per_knife_mm"] == pytest.approx(pitch, rel=0.005)
                assert tr["pitch_mm"] == pytest.approx(pitch, rel=0.02)
                assert tr["shift_px"] == pytest.approx(feed * c.camera.dt_ab_s * 12.5, rel=1e-6)
                if c is flat:
                    assert tr["depth_um"] == pytest.approx(1e3 * pitch**2 / (8 * r_mm), rel=0.01)
                    assert tr["uniformity_cv"] < 0.005
                else:  # each mark about as deep as its width predicts; uneven widths
                    assert tr["depth_um"] == pytest.approx(
                        1e3 * np.mean(w**2) / (8 * r_mm), rel=0.05)
                    assert tr["uniformity_cv"] >= 0.10


def test_default_runout_gives_cv_at_least_0_10_at_pitch_1_5(cfg):
    m = Machine(cfg, seed=0, render_images=False)
    m.set_feed_setpoint(1.5 * 400)
    f = m.advance(1.5)[-1]
    assert f.truth["feed_per_knife_mm"] == pytest.approx(1.5, rel=0.01)
    assert f.truth["uniformity_cv"] >= 0.10


def test_offsets_equal_to_runout_make_marks_uniform(cfg):
    m = Machine(cfg, seed=1, render_images=False)
    standout = m.standout_um()
    before = m.advance(0.9)[-1].truth["uniformity_cv"]
    frames = run_frames(m, 0.8, standout)
    after = frames[-1].truth
    assert before >= 0.10
    assert after["uniformity_cv"] < 0.02
    # in step with the spindle: shifting the table by one knife does not equalise
    m2 = Machine(cfg, seed=1, render_images=False)
    m2.advance(0.9)
    shifted = run_frames(m2, 0.8, np.roll(standout, 1))[-1].truth
    assert shifted["uniformity_cv"] > 0.10
    # sign: lifting one knife (positive offset) makes its marks narrower
    m3 = Machine(cfg, seed=1, render_images=False)
    m3.advance(0.9)
    lift = np.zeros(4)
    lift[2] = 3.0
    tr = run_frames(m3, 0.8, lift)[-1].truth
    w, k = np.asarray(tr["mark_widths_mm"]), np.asarray(tr["knife"])
    m4 = Machine(cfg, seed=1, render_images=False)
    tr0 = m4.advance(1.7)[-1].truth
    w0, k0 = np.asarray(tr0["mark_widths_mm"]), np.asarray(tr0["knife"])
    assert w[k == 2].mean() < w0[k0 == 2].mean() - 0.1


def test_each_pass_cuts_at_its_knifes_offset(cfg):
    """Without hysteresis the shaped table puts every knife exactly at its offset at BDC."""
    offsets = [1.5, -2.0, 3.0, 0.25]
    errs = {}
    for shaper in (True, False):
        c = replace(cfg, piezo={"hysteresis": 0.0, "input_shaper": shaper})
        m = Machine(c, seed=0, render_images=False)
        keep_piezo_alive(m, 0.5, offsets)
        p = m.passes(1)
        k = p.knife[-200:]
        got = p.bottom_um[-200:] + np.asarray(m.standout_um())[k]
        errs[shaper] = np.max(np.abs(got - np.asarray(offsets)[k]))
    assert errs[True] < 1e-6
    assert errs[False] > 0.05  # unshaped steps ring into the cut


@pytest.mark.parametrize(("factor", "one_knife"), [(1.3, True), (0.7, False)])
def test_one_knife_finish_once_runout_exceeds_pitch2_over_2r(cfg, factor, one_knife):
    # two knives: the other knife's marks vanish once the runout exceeds p^2 / (2 R)
    pitch, r_mm = 2.0, cfg.cutterhead.radius_mm
    runout = factor * 1e3 * pitch**2 / (2 * r_mm)
    c = replace(cfg, cutterhead={"knives": 2, "runout_um": (0.0, runout), "eccentricity_um": 0.0},
                spindle={"ripple_frac": 0.0, "load_droop_frac": 0.0})
    m = Machine(c, seed=0, render_images=False)
    m.set_feed_setpoint(pitch * 100 * 2)
    tr = m.advance(1.5)[-1].truth
    knives = set(tr["knife"])
    if one_knife:
        assert knives == {1}
        assert tr["pitch_mm"] == pytest.approx(2 * pitch, rel=0.01)
    else:
        assert knives == {0, 1}


def test_transport_delay_feed_change_shows_after_l_over_v(cfg):
    m = Machine(cfg, seed=2, render_images=False)
    m.advance(1.5)
    s0, t0 = m.feed_position_mm, m.t_s
    m.set_feed_setpoint(400.0)
    frames = m.advance(2.5)
    L = cfg.camera.cutter_to_camera_mm
    half_fov = 27.0
    cpm = cfg.encoder.counts_per_mm
    old, new = 0, 0
    for f in frames:
        s_a = f.counts_a / cpm
        p = f.truth["feed_per_knife_mm"]
        if s_a - L + half_fov < s0:  # every point imaged was cut before the change
            assert p == pytest.approx(2.0, rel=0.01)
            assert f.t_s >= t0  # these frames come after the change: the delay is real
            old += 1
        elif s_a - L - half_fov > s0 + 150.0:  # cut after the feed settled at 400
            assert p == pytest.approx(1.0, rel=0.01)
            new += 1
    assert old >= 2 and new >= 3
    # the first frame with the new pitch comes no earlier than (L - field) / V after the change
    first_new = min(f.t_s for f in frames if f.truth["feed_per_knife_mm"] < 1.9)
    assert first_new - t0 >= (L - half_fov) / 800.0


def test_index_latch_gives_the_knife_of_each_mark(cfg):
    m = Machine(cfg, seed=4, render_images=False)
    rig = cfg.camera.rig
    ppm, cx = rig.camera.px_per_mm, rig.camera.cx
    L, cpm, z = cfg.camera.cutter_to_camera_mm, cfg.encoder.counts_per_mm, cfg.cutterhead.knives
    for feed in (800.0, 520.0):
        m.set_feed_setpoint(feed)
        m.advance(1.0)
        frames = m.advance(1.0)
        assert len(frames) >= 8
        n = 0
        for f in frames:
            tr = f.truth
            p = tr["feed_per_knife_mm"]
            for x_mm, knife in zip(tr["bottoms_mm"], tr["knife"], strict=True):
                c = f.counts_a - (L + x_mm - cx / ppm) * cpm
                assert round((c - f.index_latch_counts) / (p * cpm)) % z == knife
                n += 1
        assert n > 100
        vals = m.register_values()
        assert vals["index_latch_counts"] == frames[-1].index_latch_counts
        assert vals["trigger_a_counts"] == frames[-1].counts_a
        assert vals["trigger_b_counts"] == frames[-1].counts_b
        assert vals["trigger_seq"] == frames[-1].seq % 65536


def test_frames_while_board_under_camera_only(cfg):
    c = replace(cfg, board={"length_mm": 600.0, "gap_mm": 400.0})
    m = Machine(c, seed=0, render_images=False)
    frames = m.advance(3.0)
    assert frames
    seqs = [f.seq for f in frames]
    assert seqs == list(range(1, len(frames) + 1))
    assert {f.board_id for f in frames} >= {1, 2}
    for f in frames:
        assert f.image_a is None and f.image_b is None
        half = 659 / 2 / 12.5
        assert half <= f.board_position_mm <= 600.0 - half
        assert f.truth["n_marks"] > 10
    gaps = np.diff([f.t_s for f in frames])
    assert np.max(gaps) > 0.3  # none while the gap passes
    assert np.min(gaps) == pytest.approx(1 / c.camera.pairs_per_s)


# ---------------------------------------------------------------- registers, determinism


def test_register_values_cover_the_map(cfg):
    from protocol.registers import RegisterMap

    m = Machine(cfg, seed=0, render_images=False)
    m.set_service_heartbeat(5)
    m.advance(1.2)
    vals = m.register_values()
    names = [r["name"] for r in load_toml(default_path("registers.toml"))["register"]]
    assert sorted(vals) == sorted(names)
    RegisterMap.load().encode_block(vals)  # every value fits its register type
    assert vals["heartbeat_plc"] == round(1.2 / cfg.plc.cycle_s) + 1
    assert vals["heartbeat_service"] == 5
    assert vals["knives"] == cfg.cutterhead.knives
    assert vals["machine_state"] & 0b11011 == 0b11011  # running, board, spindle, feed
    assert vals["faults"] == 0b1000  # heartbeat not renewed within watchdog_ms
    m.set_service_heartbeat(6)
    assert m.register_values()["faults"] == 0
    assert vals["spindle_rpm"] == pytest.approx(cfg.spindle.rpm, rel=0.005)
    assert vals["board_id"] == 1
    assert vals["board_position_mm"] == pytest.approx(
        m.feed_position_mm - 0.1 * 800 - cfg.board.first_at_mm - 300, abs=1.0)


def test_state_and_fault_registers_use_the_register_maps_flags(cfg):
    from protocol.registers import WRITE_DISPATCH, MachineState, PlcFault, apply_writes

    m = Machine(cfg, seed=0, render_images=False)
    m.advance(1.2)
    state = MachineState(m.register_values()["machine_state"])
    assert state == m.machine_state()
    assert MachineState.RUNNING in state and MachineState.ESTOP not in state
    assert type(m.register_values()["faults"]) is int  # plain ints on the wire side
    m.inject("estop")
    m.advance(0.1)
    v = m.register_values()
    assert MachineState(v["machine_state"]) & (MachineState.ESTOP | MachineState.RUNNING) == (
        MachineState.ESTOP
    )
    m.inject("feed_fault")
    m.advance(0.1)
    assert PlcFault.FEED_DRIVE in PlcFault(m.register_values()["faults"])
    # the machine is a complete target of the PLC's write dispatch
    feed = 0.5 * (cfg.feed.min_mm_s + cfg.feed.max_mm_s)
    writes = {"heartbeat_service": 42, "feed_setpoint_mm_s": feed}
    assert set(writes) == set(WRITE_DISPATCH)
    apply_writes(m, writes)
    v = m.register_values()
    assert (v["heartbeat_service"], v["feed_setpoint_mm_s"]) == (42, feed)


def test_watchdog(cfg):
    m = Machine(cfg, seed=0, render_images=False)
    wd = cfg.plc.watchdog_ms * 1e-3
    for i in range(20):
        m.set_service_heartbeat(i)
        m.advance(wd / 4)
    assert not m.register_values()["faults"] & 8
    m.set_service_heartbeat(19)  # same value: not a heartbeat
    m.advance(wd * 1.1)
    assert m.register_values()["faults"] & 8
    with pytest.raises(ValueError, match="value"):
        m.set_service_heartbeat(70000)


def test_deterministic_for_a_seed_and_independent_of_step_size(cfg):
    def run(seed, steps):
        m = Machine(cfg, seed=seed, render_images=False)
        frames = []
        for dt in steps:
            m.piezo_command(enable=True, alive_counter=len(frames) % 256)
            m.set_piezo_offsets([1.0, -1.0, 2.0, 0.5])
            frames += m.advance(dt)
        return m, frames

    coarse = [0.05] * 30
    m1, f1 = run(7, coarse)
    m2, f2 = run(7, coarse)
    m3, f3 = run(7, [0.0123] * 122)  # different chopping, same 1.5 s (commands alter timing)
    m4, f4 = run(8, coarse)
    assert [f.truth for f in f1] == [f.truth for f in f2]
    assert m1.register_values() == m2.register_values()
    p1, p2 = m1.passes(1), m2.passes(1)
    assert np.array_equal(p1.bottom_um, p2.bottom_um)
    assert [f.counts_a for f in f1] == [f.counts_a for f in f3]
    assert m1.passes(1).x_mm[:50] == pytest.approx(m3.passes(1).x_mm[:50])
    assert [f.truth["pitch_mm"] for f in f1] != [f.truth["pitch_mm"] for f in f4]


def test_images_rendered_with_counts(cfg):
    m = Machine(cfg, seed=0, render_images=True)
    m.advance(0.55)
    frames = m.advance(0.25)
    assert frames
    f = frames[0]
    h, w = cfg.camera.optics.height, cfg.camera.optics.width
    assert f.image_a.shape == (h, w) and f.image_b.shape == (h, w)
    assert 40 < f.image_a.mean() < 200
    assert not np.array_equal(f.image_a, f.image_b)
    assert (f.counts_b - f.counts_a) * 0.625 == pytest.approx(f.truth["shift_px"], abs=0.7)


def test_fault_parameters_default_to_the_registry(cfg):
    """Defaults of fault parameters are written once, in config.faults (not in the machine)."""
    from config.faults import FaultKind

    m = Machine(cfg, seed=0, render_images=False)
    m.inject("belt_slip")
    px = FaultKind.BELT_SLIP.value_of({}, "px")
    assert m.capture.pending_slip == round(px / cfg.camera.rig.encoder.px_per_count)
    m.inject("piezo_fault")
    bit = int(FaultKind.PIEZO_FAULT.value_of({}, "bit"))
    assert m.piezo_status().fault & (1 << bit)
    m.inject("knot", board_id=3)
    knot = m.knots[-1]
    d = {p.name: p.default for p in FaultKind.KNOT.params}
    assert (knot.length_mm, knot.width_mm, knot.darkness) == (
        d["length_mm"], d["width_mm"], d["darkness"]
    )
    assert knot.x_mm == m.boards.length_mm - d["at_mm"]
