"""The machine model's fast paths equal the reference formulas they replace.

The ``_ref_*`` functions are the model's code as it was before the speed work: per cycle the
spindle recomputed its first-order gains, the feed read its limits through the config, the
piezo actuator built a transition tuple per step, the PLC built ``MachineState`` flags per
register read and the camera copied a board's whole pass log per pair. The fast code must
give bit-identical results: unit properties over random inputs, and whole machine runs with
the reference code swapped in compared value for value.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import Phase, given, settings
from hypothesis import strategies as st

from config.sim import default_sim
from plant_sim.machine.machine import Machine
from plant_sim.machine.plc_registers import PlcRegisters
from plant_sim.model.cut_record import PassLog
from plant_sim.model.feed_drive import FeedDrive
from plant_sim.model.piezo import PiezoActuator
from plant_sim.model.spindle import BRAKE, COAST, RUN, Spindle
from plant_sim.model.surface import Passes
from plant_sim.rendering.frame_capture import FrameCapture
from protocol.registers import MachineState, PlcFault

# -- the reference code ------------------------------------------------------------------------


def _ref_spindle_start_cycle(self, t_s, dt_s, *, cutting):
    cfg = self.cfg
    self.t_c = t_s
    if self.mode == RUN:
        goal, tau = self.nominal_rev_s, cfg.spinup_tau_s
    elif self.mode == COAST:
        goal, tau = 0.0, cfg.coast_tau_s
    else:
        goal, tau = 0.0, cfg.brake_tau_s
    self.drive_rev_s += (goal - self.drive_rev_s) * (1.0 - math.exp(-dt_s / tau))
    if goal == 0.0 and self.drive_rev_s < 0.005 * self.nominal_rev_s:
        self.drive_rev_s = 0.0
    self.load += ((1.0 if cutting else 0.0) - self.load) * (1.0 - math.exp(-dt_s / 0.1))
    ripple = cfg.ripple_frac * math.sin(2.0 * math.pi * cfg.ripple_hz * t_s + self.ripple_phase)
    self.rev_s = self.drive_rev_s * (1.0 + ripple - cfg.load_droop_frac * self.load)


def _ref_spindle_running(self):
    return self.mode == RUN and self.drive_rev_s >= 0.9 * self.nominal_rev_s


def _ref_feed_start_cycle(self, t_s, dt_s):
    self.t_c = t_s
    goal = self.setpoint_mm_s if self.enabled else 0.0
    err = goal - self.v_mm_s
    amax = self.cfg.accel_max_mm_s2
    a = max(-amax, min(amax, self._k * err))
    if abs(a) * dt_s >= abs(err):
        a = err / dt_s
    self.a_mm_s2 = a


def _ref_propagate_to(self, t_s):
    tau = t_s - self.t_s
    if tau <= 0.0:
        return
    a, b, c, d = self._transition(tau)
    e = self.x_um - self.level_um
    v = self.v_um_s
    self.x_um = self.level_um + a * e + b * v
    self.v_um_s = c * e + d * v
    self.t_s = t_s


def _ref_set_flag(self, bit, on):
    if on:
        self._faults |= int(bit)
    else:
        self._faults &= ~int(bit)


def _ref_machine_state(self, t_s):
    s = self.feed.position_at(t_s)
    st_ = MachineState(0)
    if self.spindle.running:
        st_ |= MachineState.SPINDLE_RUNNING
    if self.feed.enabled:
        st_ |= MachineState.FEED_ENABLED
    if self.spindle.running and self.feed.enabled and not self.estop:
        st_ |= MachineState.RUNNING
    if self.estop:
        st_ |= MachineState.ESTOP
    if self.boards.at(s, self.L_mm)[0]:
        st_ |= MachineState.BOARD_PRESENT
    return st_


def _ref_values(self, t_s):
    s = self.feed.position_at(t_s)
    cfg = self.cfg
    last = self.capture.last_pair
    bid, _ = self.boards.at(s, self.L_mm)
    return {
        "heartbeat_service": self.heartbeat_service,
        "heartbeat_plc": self.heartbeat_plc,
        "feed_setpoint_mm_s": self.feed.setpoint_mm_s,
        "feed_min_mm_s": cfg.feed.min_mm_s,
        "feed_max_mm_s": cfg.feed.max_mm_s,
        "feed_accel_max_mm_s2": cfg.feed.accel_max_mm_s2,
        "feed_actual_mm_s": self.feed.speed_at(t_s),
        "spindle_rpm": self.spindle.rpm,
        "encoder_counts": self.encoder.read(s),
        "trigger_a_counts": last.counts_a if last else 0,
        "trigger_b_counts": last.counts_b if last else 0,
        "trigger_seq": (last.seq if last else 0) & 0xFFFF,
        "index_latch_counts": last.index_latch if last else 0,
        "machine_state": int(self.machine_state(t_s)),
        "faults": self._faults,
        "knives": self.knives,
        "cutter_to_camera_mm": self.L_mm,
        "counts_per_mm": cfg.encoder.counts_per_mm,
        "board_id": bid,
        "board_position_mm": (self.boards.length_mm - last.x_centre_mm) if last else 0.0,
        "watchdog_ms": cfg.plc.watchdog_ms,
        "cutterhead_radius_mm": self.radius_mm,
    }


def _ref_events_until(self, t1, frames):
    while True:
        la = self.latch
        tn = self.triggers.next_time()
        tb = la.t_b if la is not None else math.inf
        if tb <= t1 and tb <= tn:
            self._trigger_b(la, frames)
        elif tn <= t1:
            self.triggers.consume()
            if la is None:
                self._trigger_a(tn)
        else:
            break


def _ref_near_passes(self, log, x_centre_mm):
    return log.passes()  # the whole log: the assembler slices it itself


REFERENCE = [
    (Spindle, "start_cycle", _ref_spindle_start_cycle),
    (Spindle, "running", property(_ref_spindle_running)),
    (FeedDrive, "start_cycle", _ref_feed_start_cycle),
    (PiezoActuator, "propagate_to", _ref_propagate_to),
    (PlcRegisters, "set_flag", _ref_set_flag),
    (PlcRegisters, "machine_state", _ref_machine_state),
    (PlcRegisters, "values", _ref_values),
    (FrameCapture, "events_until", _ref_events_until),
    (FrameCapture, "_near_passes", _ref_near_passes),
]

# -- unit properties ---------------------------------------------------------------------------

finite = st.floats(-50.0, 50.0, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(x=finite, v=st.floats(-1e5, 1e5), level=finite, t0=st.floats(0.0, 10.0),
       tau=st.floats(-1e-3, 5e-3), zeta=st.floats(0.01, 0.9), f=st.floats(50.0, 5000.0))
def test_actuator_step_is_the_transition_formula_bit_for_bit(x, v, level, t0, tau, zeta, f):
    fast = PiezoActuator(resonance_hz=f, damping=zeta, hysteresis=0.0, stroke_um=20.0)
    ref = PiezoActuator(resonance_hz=f, damping=zeta, hysteresis=0.0, stroke_um=20.0)
    for a in (fast, ref):
        a.x_um, a.v_um_s, a.level_um, a.t_s = x, v, level, t0
    fast.propagate_to(t0 + tau)
    _ref_propagate_to(ref, t0 + tau)
    assert (fast.x_um, fast.v_um_s, fast.t_s) == (ref.x_um, ref.v_um_s, ref.t_s)


@settings(max_examples=100, deadline=None)
@given(steps=st.lists(st.tuples(st.sampled_from([RUN, COAST, BRAKE]), st.booleans(),
                                st.sampled_from([0.002, 0.001, 0.0005, 0.003])),
                      min_size=1, max_size=60),
       phase=st.floats(0.0, 6.3), t0=st.floats(0.0, 100.0))
def test_spindle_cycle_is_the_reference_formula_bit_for_bit(steps, phase, t0):
    cfg = default_sim().spindle
    fast, ref = Spindle(cfg, ripple_phase_rad=phase), Spindle(cfg, ripple_phase_rad=phase)
    t = t0
    for mode, cutting, dt in steps:
        fast.mode = ref.mode = mode
        fast.start_cycle(t, dt, cutting=cutting)
        _ref_spindle_start_cycle(ref, t, dt, cutting=cutting)
        assert (fast.drive_rev_s, fast.load, fast.rev_s, fast.t_c) == (
            ref.drive_rev_s, ref.load, ref.rev_s, ref.t_c)
        assert fast.running == _ref_spindle_running(ref)
        fast.end_cycle(dt)
        ref.end_cycle(dt)
        t += dt


@settings(max_examples=100, deadline=None)
@given(steps=st.lists(st.tuples(st.floats(50.0, 1000.0), st.booleans(),
                                st.sampled_from([0.002, 0.001, 0.0007])),
                      min_size=1, max_size=60))
def test_feed_cycle_is_the_reference_formula_bit_for_bit(steps):
    cfg = default_sim().feed
    fast, ref = FeedDrive(cfg), FeedDrive(cfg)
    t = 0.0
    for setpoint, enabled, dt in steps:
        for d in (fast, ref):
            d.setpoint_mm_s, d.enabled = setpoint, enabled
        fast.start_cycle(t, dt)
        _ref_feed_start_cycle(ref, t, dt)
        assert fast.a_mm_s2 == ref.a_mm_s2
        fast.end_cycle(dt)
        ref.end_cycle(dt)
        assert (fast.s_mm, fast.v_mm_s) == (ref.s_mm, ref.v_mm_s)
        t += dt


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 3000), lo=st.floats(-100.0, 4000.0), width=st.floats(0.0, 200.0),
       seed=st.integers(0, 2**16))
def test_passes_near_the_field_are_the_slice_of_the_whole_log(n, lo, width, seed):
    rng = np.random.default_rng(seed)
    log = PassLog(60.0)
    for x, b, k in zip(np.sort(rng.uniform(0.0, 4000.0, n))[::-1], rng.normal(0.0, 3.0, n),
                       rng.integers(0, 4, n), strict=True):
        log.append(float(x), float(b), int(k))
    cap = Machine(default_sim(), seed=0, render_images=False).capture
    lo_f, hi_f = cap.assembler.field_mm(lo + width)
    want = log.passes().slice(lo_f, hi_f, margin_mm=cap.assembler.MARGIN_MM)
    got = cap._near_passes(log, lo + width)
    for name in ("x_mm", "bottom_um", "knife"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype and np.array_equal(a, b)
    assert got.radius_mm == want.radius_mm


@settings(max_examples=60, deadline=None)
@given(n=st.integers(0, 50), seed=st.integers(0, 2**16), kind=st.sampled_from(["bool", "idx"]))
def test_selected_passes_equal_checked_construction(n, seed, kind):
    rng = np.random.default_rng(seed)
    p = Passes(rng.uniform(-5, 5, n), rng.normal(size=n), rng.integers(0, 4, n), 60.0)
    mask = rng.random(n) < 0.5 if kind == "bool" else rng.integers(0, max(n, 1), n // 2)
    if n == 0 and kind == "idx":
        mask = np.zeros(0, dtype=np.int64)
    got = p.select(mask)
    want = Passes(p.x_mm[mask], p.bottom_um[mask], p.knife[mask], 60.0)
    for f in dataclasses.fields(Passes):
        a, b = getattr(got, f.name), getattr(want, f.name)
        assert np.array_equal(a, b) and np.asarray(a).dtype == np.asarray(b).dtype
    assert got.x_mm.dtype == np.float64 and got.knife.dtype == np.int64 and got.x_mm.ndim == 1


def test_register_values_and_state_equal_the_reference_in_every_state():
    m = Machine(default_sim(), seed=2, render_images=False)
    seen = set()
    # (inject this fault, then run until): a feed fault while the spindle runs, a stopped
    # spindle, an e-stop, each reset
    script = [(None, 0.7), ("feed_fault", 1.0), ("reset", 1.4), ("spindle_stop", 2.2),
              ("reset", 2.6), ("estop", 3.1), ("reset", 3.5)]
    for fault, until in script:
        if fault is not None:
            m.inject(fault)
        while m.t_s < until:
            m.set_service_heartbeat(int(m.t_s * 50) % 65536)
            m.advance(0.013)
            got = m.plc.values(m.t_s)
            want = _ref_values(m.plc, m.t_s)
            assert list(got) == list(want) and got == want
            assert m.plc.machine_state(m.t_s) == _ref_machine_state(m.plc, m.t_s)
            seen.add(got["machine_state"])
    ms = MachineState
    assert {int(ms.RUNNING | ms.SPINDLE_RUNNING | ms.FEED_ENABLED | ms.BOARD_PRESENT),
            int(ms.SPINDLE_RUNNING | ms.BOARD_PRESENT)} <= seen  # running; feed drive tripped
    assert any(v & ms.ESTOP for v in seen) and any(not v & ms.SPINDLE_RUNNING for v in seen)
    plc = m.plc
    for bit in PlcFault:
        for on in (True, False, False, True):
            before = plc._faults
            plc.set_flag(bit, on)
            got = plc._faults
            plc._faults = before
            _ref_set_flag(plc, bit, on)
            assert got == plc._faults and type(got) is int


# -- whole machine runs ------------------------------------------------------------------------


def _run(seed: int, chops: list[float], events: list[tuple[int, str, object]]) -> list:
    """Trace of a machine driven like the service drives it, with faults and set-point steps."""
    m = Machine(default_sim(), seed=seed, render_images=False)
    offsets = [float(v) for v in m.standout_um()]
    trace: list = []
    by_step: dict[int, list[tuple[str, object]]] = {}
    for i, kind, arg in events:
        by_step.setdefault(i, []).append((kind, arg))
    for i, dt in enumerate(chops):
        m.piezo_command(enable=True, alive_counter=i % 256)
        m.set_service_heartbeat(i % 65536)
        for kind, arg in by_step.get(i, []):
            if kind == "offsets":
                m.set_piezo_offsets([o * float(arg) for o in offsets])  # type: ignore[arg-type]
            elif kind == "feed":
                m.set_feed_setpoint(float(arg))  # type: ignore[arg-type]
            else:
                m.inject(kind)
        frames = m.advance(dt)
        trace.append((m.t_s, m.register_values(), m.piezo_displacement_um, m.feed_position_mm,
                      m.spindle_rpm, m.amp.fault_bits))
        for f in frames:
            trace.append((f.seq, f.t_s, f.counts_a, f.counts_b, f.index_latch_counts,
                          f.board_id, f.board_position_mm, repr(f.truth)))
    bid = m.cut.latest_board()
    p = m.passes(bid)
    trace.append((bid, p.x_mm.tolist(), p.bottom_um.tolist(), p.knife.tolist()))
    return trace


@settings(max_examples=6, deadline=None, phases=[Phase.explicit, Phase.reuse, Phase.generate])
@given(seed=st.integers(0, 1000),
       chops=st.lists(st.sampled_from([0.01, 0.001, 0.0123, 0.002, 0.0371]), min_size=40,
                      max_size=90),
       events=st.lists(st.tuples(st.integers(0, 89),
                                 st.sampled_from(["offsets", "feed", "spindle_stop", "estop",
                                                  "feed_fault", "reset", "piezo_fault"]),
                                 st.floats(0.0, 1.0)), max_size=5))
def test_machine_runs_equal_the_reference_code_value_for_value(seed, chops, events):
    events = [(i, kind, (60.0 + 900.0 * a) if kind == "feed" else a) for i, kind, a in events]
    chops = [0.05] * 12 + chops  # a board reaches the camera: pairs are assembled
    events = [(i + 12, k, a) for i, k, a in events]
    fast = _run(seed, chops, events)
    with pytest.MonkeyPatch.context() as mp:
        for cls, name, ref in REFERENCE:
            mp.setattr(cls, name, ref)
        ref_trace = _run(seed, chops, events)
    assert any(len(row) == 8 for row in fast)  # frames were compared
    assert len(fast) == len(ref_trace)
    for a, b in zip(fast, ref_trace, strict=True):
        assert a == b
