"""The smart planer as a time-stepped, deterministic machine model (the ``Machine`` facade).

One object holds the spindle, the knives, the piezo actuator and its amplifier, the feed drive,
the encoder, the stream of boards, the cut and the camera. Time moves only through
:meth:`Machine.advance` (the injected clock; nothing sleeps). Inside, the PLC cycle
(``plc.cycle_s``) is the grid on which the drives are updated; between grid points the spindle
angle is linear and the feed position quadratic in time, and every event -- a knife at bottom
dead centre (BDC), the amplifier's switch to the next knife's offset, a camera trigger -- is
handled at its exact instant. The result does not depend on how a caller chops time into
``advance`` calls (up to the sensor noise drawn when a status is read).

The machine composes parts with one job each:

- the drives: :mod:`plant_sim.model.spindle`, :mod:`plant_sim.model.feed_drive` (feed, encoder,
boards),
  :mod:`plant_sim.model.piezo` (actuator and amplifier);
- :class:`plant_sim.model.cut_record.CutRecord`: the cut. At every knife's BDC the pass is
recorded for
  the board under the cutter: board coordinate of the cutter axis and ``bottom_um =
  -(runout_k + eccentricity term + drift_k(t)) +`` the actual piezo displacement at that
  instant (``drift_k``: the knives' warm-up and wear, ``[cutterhead.drift]``). The surface
  under the camera is the envelope of those passes (:mod:`plant_sim.model.surface`), so compensation
  genuinely changes the surface;
- :class:`plant_sim.rendering.frame_capture.FrameCapture`: the camera's triggers, latches and
frames;
- :class:`plant_sim.machine.plc_registers.PlcRegisters`: the PLC's flags, heartbeats, watchdog,
  interlock and register values;
- :class:`plant_sim.machine.fault_injection.FaultInjector`: the faults (kinds and parameters listed
  there), their schedule and timers.

This class steps time through them and keeps the API the PLC server, the CAN node, the runner
and the tests use.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from config.sim import DriftConfig, SimConfig
from core.checks import check_finite, check_int, check_positive
from plant_sim.machine.fault_injection import FaultInjector
from plant_sim.machine.plc_registers import PlcRegisters, register_names
from plant_sim.model.cut_record import CutRecord
from plant_sim.model.feed_drive import BoardStream, Encoder, FeedDrive
from plant_sim.model.piezo import FAULT as PIEZO_FAULT
from plant_sim.model.piezo import PiezoAmplifier, PiezoStatus
from plant_sim.model.spindle import Spindle
from plant_sim.model.surface import Cutterhead, Passes, RunoutDrift, Surface
from plant_sim.rendering.camera import Knot
from plant_sim.rendering.frame_capture import FrameCapture, build_renderer
from protocol.frames import Frame
from protocol.registers import MachineState, PlcFault

__all__ = ["Machine", "PiezoStatus", "advance_together", "register_names", "runout_drift",
           "start_cycles", "start_feed"]


_EPS_S = 1e-9


def runout_drift(cfg: DriftConfig | None) -> RunoutDrift | None:
    """The knives' warm-up and wear of ``[cutterhead.drift]`` (``None`` without the table)."""
    if cfg is None:
        return None
    return RunoutDrift(cfg.warmup_um, cfg.warmup_tau_s, cfg.wear_um_per_min)


class Machine:
    """The simulated planing machine.

    Parameters
    ----------
    cfg : config.sim.SimConfig
        Machine parameters (``config/sim.toml``); its ``[faults]`` are injected at start.
    seed : int
        Seed of everything random (load-ripple phase, sensor noise, wood texture, image noise).
    render_images : bool
        Render the camera's images; ``False`` gives frames with ``image_a = image_b = None``
        (counts and truth still there), much faster.
    feed, encoder, boards : optional
        Another machine's feed drive, encoder and boards (a moulder's heads share them): this
        machine then does not step the feed (its owner does, :func:`advance_together`) and
        :meth:`advance` is refused on it; ``boards`` may be a
        :class:`plant_sim.model.feed_drive.BoardView` (the boards seen from a head downstream).
        Default: its own.
    feed_shared : bool
        It owns a feed that machines built after it will share (a moulder's first head): its
        first cycle leaves the feed to :func:`start_feed` of all of them, called once they are
        built (the feed's interlock is every machine's).

    Attributes
    ----------
    cfg : SimConfig
        The configuration.
    head : plant_sim.model.surface.Cutterhead
        Knives, radius, runout, eccentricity and drift (warm-up and wear).
    cut : plant_sim.model.cut_record.CutRecord
        The knife passes per board and the index pulses.
    capture : plant_sim.rendering.frame_capture.FrameCapture
        The camera station (``assembler``, ``knots``, ``frames_dropped``).
    plc : plant_sim.machine.plc_registers.PlcRegisters
        The PLC's flags, heartbeats and register values.
    faults : plant_sim.machine.fault_injection.FaultInjector
        Injected faults, their schedule and timers.
    """

    def __init__(self, cfg: SimConfig, *, seed: int = 0, render_images: bool = True,
                 feed: FeedDrive | None = None, encoder: Encoder | None = None,
                 boards: BoardStream | None = None, feed_shared: bool = False) -> None:
        self.cfg = cfg
        self.seed = check_int("seed", seed, lo=0)
        self.render_images = bool(render_images)
        ss = np.random.SeedSequence(self.seed)
        r_ripple, r_sensor, r_knot, r_drop = (np.random.default_rng(s) for s in ss.spawn(4))
        ch = cfg.cutterhead
        self.knives = ch.knives
        self.head = Cutterhead(ch.knives, ch.radius_mm, tuple(ch.runout_um), ch.eccentricity_um,
                               drift=runout_drift(ch.drift))
        self._standout = [float(v) for v in self.head.standout_um()]  # at t = 0: no drift yet
        self.cycle_s = cfg.plc.cycle_s
        self.spindle = Spindle(cfg.spindle, ripple_phase_rad=float(r_ripple.uniform(0, 2 * np.pi)))
        self.owns_feed = feed is None
        self.feed = FeedDrive(cfg.feed) if feed is None else feed
        self.encoder = Encoder(cfg.encoder) if encoder is None else encoder
        self.boards = BoardStream(cfg.board) if boards is None else boards
        self.amp = PiezoAmplifier(cfg.piezo, ch.knives, r_sensor)
        self._lead = cfg.piezo.lead_fraction
        self.L_mm = cfg.camera.cutter_to_camera_mm
        self.renderer = build_renderer(cfg, seed=self.seed) if self.render_images else None
        self.cut = CutRecord(self._standout, self.head.radius_mm, boards=self.boards,
                             encoder=self.encoder, drift=self.head.drift)
        self.capture = FrameCapture(cfg, feed=self.feed, encoder=self.encoder,
                                    boards=self.boards, cut=self.cut, renderer=self.renderer)
        self.assembler = self.capture.assembler
        self.triggers = self.capture.triggers
        self.plc = PlcRegisters(cfg, spindle=self.spindle, feed=self.feed, encoder=self.encoder,
                                boards=self.boards, capture=self.capture,
                                radius_mm=self.head.radius_mm)
        self.faults = FaultInjector(cfg, spindle=self.spindle, feed=self.feed,
                                    encoder=self.encoder, boards=self.boards, amp=self.amp,
                                    plc=self.plc, capture=self.capture, knot_rng=r_knot,
                                    drop_rng=r_drop)
        # time, cycle and the next spindle events (knife count of the next BDC / next switch)
        self._t = 0.0
        self._cycle = 0
        self._next_bdc = math.floor(self.knives * self.spindle.rev) + 1
        self._next_sw = math.floor(self.knives * self.spindle.rev + self._lead) + 1
        for spec in cfg.faults:
            self.inject(spec.kind, **dict(spec.params))
        self._start_cycle(feed=self.owns_feed and not feed_shared)

    # ------------------------------------------------------------------ time
    @property
    def t_s(self) -> float:
        """Simulated time, seconds."""
        return self._t

    def advance(self, dt_s: float) -> list[Frame]:
        """Step the model by ``dt_s`` seconds; returns the frames completed in this step.

        Raises
        ------
        ValueError
            ``dt_s`` is negative or not finite.
        RuntimeError
            The machine shares another's feed (it is stepped with it: :func:`advance_together`).
        """
        if not self.owns_feed:
            raise RuntimeError("this machine shares another's feed drive: step them together "
                               "(plant_sim.machine.machine.advance_together, Moulder.advance)")
        return advance_together((self,), dt_s)[0]

    def _start_cycle(self, *, feed: bool) -> None:
        """The first PLC cycle begins; with ``feed`` its feed too (the owner of a feed alone)."""
        if feed:
            start_cycles((self,))
        else:  # the feed's start is left to its owner with every machine on it (start_feed)
            t = self._cycle * self.cycle_s
            self._begin_cycle(t)
            self._begin_amp(t)

    def _begin_cycle(self, t: float) -> None:
        """A PLC cycle begins at ``t``: faults due, the PLC's heartbeats, the spindle's speed."""
        self.faults.apply_due(t)
        self.faults.apply_at_travel(self.feed.s_mm, t)
        self.plc.start_cycle(t)
        cutting = self.boards.at(self.feed.s_mm, 0.0)[0] != 0
        self.spindle.start_cycle(t, self.cycle_s, cutting=cutting)

    def _begin_amp(self, t: float) -> None:
        """The amplifier's cycle at ``t`` (after the spindle's: it needs to know it turns)."""
        self.amp.cycle(t, self.cycle_s, spindle_turning=self.spindle.turning)
        self.plc.set_flag(PlcFault.PIEZO_AMPLIFIER, self.amp.state == PIEZO_FAULT)

    def _end_cycle(self) -> None:
        self.spindle.end_cycle(self.cycle_s)
        if self.owns_feed:
            self.feed.end_cycle(self.cycle_s)

    def _interval(self, t0: float, t1: float, frames: list[Frame]) -> None:
        """Process every event in ``(t0, t1]`` within the current cycle."""
        sp = self.spindle
        z = self.knives
        amp = self.amp
        if sp.turning:
            zr1 = z * sp.rev_at(t1)
            lead = self._lead
            while True:
                nb, ns = self._next_bdc, self._next_sw
                tb = sp.time_of_rev(nb / z) if nb <= zr1 else math.inf
                ts = sp.time_of_rev((ns - lead) / z) if ns - lead <= zr1 else math.inf
                if tb == math.inf and ts == math.inf:
                    break
                if ts <= tb:
                    ts = min(max(ts, t0), t1)
                    amp.advance_to(ts)
                    amp.switch(ns % z, ts)
                    self._next_sw = ns + 1
                else:
                    tb = min(max(tb, t0), t1)
                    amp.advance_to(tb)
                    self.cut.bdc(nb % z, self.feed.position_at(tb), amp.actuator.x_um,
                                 t_s=tb)
                    self._next_bdc = nb + 1
        amp.advance_to(t1)
        self.capture.events_until(t1, frames)

    # ------------------------------------------------------------------ PLC side
    def register_values(self) -> dict[str, float | int]:
        """Every register of ``config/registers.toml`` with its current value."""
        return self.plc.values(self._t)

    def machine_state(self) -> MachineState:
        """The ``machine_state`` register's bits."""
        return self.plc.machine_state(self._t)

    def set_feed_setpoint(self, feed_mm_s: float) -> None:
        """New feed setpoint; ``ValueError`` outside ``[feed_min, feed_max]`` (never clamped)."""
        self.feed.set_setpoint(feed_mm_s)

    @property
    def head_count(self) -> int:
        """Heads of the machine (its register blocks): one."""
        return 1

    def head_register_values(self, i: int) -> dict[str, float | int]:
        """The head fields of the PLC's register block ``i`` (only 0: the machine's one head).

        ``spindle_rpm``, ``spindle_setpoint_rpm``, ``spindle_rpm_min``, ``spindle_rpm_max``,
        ``knives``, ``cutterhead_radius_mm``, ``cutter_to_camera_mm``, ``trigger_a_counts``,
        ``trigger_b_counts``, ``trigger_seq``, ``index_latch_counts``, ``head_faults``.

        Raises
        ------
        ValueError
            ``i`` is not 0.
        """
        check_int("i", i, lo=0, hi=0)
        return self.plc.head_values(self._t, camera_silent=self.faults.camera_silent(self._t))

    def set_spindle_setpoint(self, i: int, rpm: float) -> None:
        """Spindle setpoint of head ``i`` (only 0), rpm; the drive ramps to it.

        Raises
        ------
        ValueError
            ``i`` is not 0, or ``rpm`` outside the spindle's ``[rpm_min, rpm_max]`` (a fixed
            head: anything but its speed); never clamped.
        """
        check_int("i", i, lo=0, hi=0)
        self.spindle.set_setpoint(rpm)

    def set_service_heartbeat(self, value: int) -> None:
        """The service's heartbeat; a changed value feeds the PLC's watchdog."""
        self.plc.set_service_heartbeat(value, self._t)

    @property
    def heartbeat_plc(self) -> int:
        """The PLC's heartbeat (incremented every PLC cycle, 0..65535)."""
        return self.plc.heartbeat_plc

    @property
    def heartbeat_service(self) -> int:
        """The service's heartbeat as last written (0..65535)."""
        return self.plc.heartbeat_service

    @property
    def estop(self) -> bool:
        """E-stop pressed."""
        return self.plc.estop

    @property
    def fault_bits(self) -> PlcFault:
        """The ``faults`` register's bits."""
        return self.plc.fault_bits

    # ------------------------------------------------------------------ piezo amplifier side
    def piezo_command(self, *, enable: bool, alive_counter: int, knives: int | None = None) -> None:
        """The command (RPDO3): enable and alive counter (a new counter restarts the timeout).

        Raises
        ------
        ValueError
            ``alive_counter`` outside 0..255, or ``knives`` given and not the machine's.
        """
        if knives is not None and check_int("knives", knives) != self.knives:
            raise ValueError(f"knives must be {self.knives} (the cutterhead's), got {knives}")
        check_int("alive_counter", alive_counter, lo=0, hi=255)
        if self.faults.can_frame_lost(self._t):
            return
        self.amp.command(self._t, enable=bool(enable), alive_counter=alive_counter)

    def set_piezo_offsets(self, offsets_um: Sequence[float]) -> None:
        """Per-knife offsets, um (positive: head up, knife cuts less deep).

        ``ValueError`` beyond the stroke or with fewer values than knives; values for knives
        the head does not have (up to 8, as the CAN frames carry) are checked and ignored.
        """
        if self.faults.can_frame_lost(self._t):
            self.amp.check_offsets(offsets_um)  # still validated, then lost on the bus
            return
        self.amp.set_offsets(offsets_um)

    def piezo_status(self) -> PiezoStatus:
        """The amplifier's status: sensed displacement, temperature, fault bits, state."""
        return self.amp.status(self._t)

    def eddy_current_um(self) -> float:
        """Eddy-current sensor on the spindle's vertical displacement (noise ~0.05 um rms), um."""
        return self.amp.sensor_um()

    @property
    def piezo_displacement_um(self) -> float:
        """True vertical displacement of the cutterhead now, um."""
        return self.amp.actuator.x_um

    # ------------------------------------------------------------------ faults
    def inject(self, fault: str, **params: Any) -> None:
        """Inject a fault now or at ``at_s``.

        Kinds and parameters: :mod:`plant_sim.machine.fault_injection`.

        Raises
        ------
        ValueError
            Unknown kind or parameter, or a parameter out of range.
        """
        self.faults.inject(fault, params, now_s=self._t)

    def reset_faults(self) -> None:
        """Acknowledge: clear the e-stop and the drive faults; the spindle runs up again."""
        self.faults.reset(self._t)

    def take_interface_events(self) -> list[dict[str, Any]]:
        """Interface faults that came due (``modbus_restart``, ``can_silence``); cleared on read."""
        return self.faults.take_interface_events()

    # ------------------------------------------------------------------ camera
    @property
    def knots(self) -> list[Knot]:
        """Knots placed on boards (by the ``knot`` fault)."""
        return self.capture.knots

    @property
    def frames_dropped(self) -> int:
        """Pairs that could not be assembled (no passes under the field of view)."""
        return self.capture.frames_dropped

    # ------------------------------------------------------------------ truth and state
    def passes(self, board_id: int) -> Passes:
        """Every knife pass recorded over board ``board_id`` (recent boards only)."""
        return self.cut.passes(board_id)

    def surface(self, x_lo_board_mm: float, x_hi_board_mm: float, *,
                board_id: int | None = None) -> Surface:
        """The true planed surface over a board range (board coordinate from the trailing end)."""
        lo = check_finite("x_lo_board_mm", x_lo_board_mm)
        hi = check_finite("x_hi_board_mm", x_hi_board_mm)
        if not hi > lo:
            raise ValueError("x_hi_board_mm must exceed x_lo_board_mm")
        bid = self._default_board() if board_id is None else board_id
        return self.assembler.surface(self.passes(bid), lo, hi)

    def _default_board(self) -> int:
        last = self.capture.last_pair
        if last is not None and last.board_id in self.cut.logs:
            return last.board_id
        return self.cut.latest_board()

    @property
    def feed_position_mm(self) -> float:
        """True table travel since time 0, mm."""
        return self.feed.position_at(self._t)

    @property
    def feed_speed_mm_s(self) -> float:
        """True feed speed now, mm/s."""
        return self.feed.speed_at(self._t)

    @property
    def spindle_rpm(self) -> float:
        """Spindle speed now, rpm."""
        return self.spindle.rpm

    def standout_um(self) -> list[float]:
        """True radial stand-out of each knife now (runout, eccentricity, drift), um."""
        return [self.cut.standout_um(k, self._t) for k in range(self.knives)]

    def pitch_mm(self) -> float:
        """Nominal feed per knife pass from the current speeds, mm."""
        rps = self.spindle.rev_s
        return self.feed_speed_mm_s / (rps * self.knives) if rps > 0 else math.inf


def start_cycles(machines: Sequence[Machine]) -> None:
    """A PLC cycle begins for the machines on one feed (a moulder's heads; or one machine).

    Each machine's faults due, PLC and spindle first; then the feed's owner starts the feed's
    cycle, permitted only when every machine's interlock permits it (a head's spindle stopped
    stops the feed under all); then each machine's amplifier. One machine alone: the order it
    always had.
    """
    lead = machines[0]
    t = lead._cycle * lead.cycle_s
    for m in machines:
        m._begin_cycle(t)
    start_feed(machines)
    for m in machines:
        m._begin_amp(t)


def start_feed(machines: Sequence[Machine]) -> None:
    """The shared feed's cycle begins: it runs only when every machine's interlock permits it.

    Raises
    ------
    ValueError
        None of ``machines`` owns the feed.
    """
    owner = next((m for m in machines if m.owns_feed), None)
    if owner is None:
        raise ValueError("machines: none of them owns the feed they share")
    feed = owner.feed
    feed.enabled = all(m.plc.feed_permitted() for m in machines)
    feed.start_cycle(owner._cycle * owner.cycle_s, owner.cycle_s)


def advance_together(machines: Sequence[Machine], dt_s: float) -> list[list[Frame]]:
    """Step machines that share one feed by ``dt_s`` seconds, cycle by cycle in lock-step.

    Within each PLC cycle every machine handles its events (knives, amplifier, camera) while the
    shared feed holds that cycle's motion; then the cycle ends for all and the next begins
    (:func:`start_cycles`). One machine alone is exactly :meth:`Machine.advance`.

    Parameters
    ----------
    machines : sequence of Machine
        The machines, one of them the owner of the feed the others share; all at the same
        time and PLC cycle (built together).
    dt_s : float
        Step, s (>= 0).

    Returns
    -------
    list of list of Frame
        Per machine (in order), the frames completed in this step.

    Raises
    ------
    ValueError
        ``dt_s`` negative or not finite, or the machines are not at one time.
    """
    dt = check_positive("dt_s", dt_s, allow_zero=True)
    lead = machines[0]
    if any(m._t != lead._t or m.cycle_s != lead.cycle_s for m in machines):
        raise ValueError("machines must be at one time on one PLC cycle to step together")
    target = lead._t + dt
    frames: list[list[Frame]] = [[] for _ in machines]
    cs = lead.cycle_s
    while lead._t < target - _EPS_S:
        t_end = (lead._cycle + 1) * cs
        if target >= t_end - _EPS_S:
            for m, out in zip(machines, frames, strict=True):
                m._interval(m._t, t_end, out)
            for m in machines:
                m._end_cycle()
                m._t = t_end
                m._cycle += 1
            start_cycles(machines)
        else:
            for m, out in zip(machines, frames, strict=True):
                m._interval(m._t, target, out)
                m._t = target
    for m in machines:
        if m._t < target:
            m._t = target
    return [m.faults.filter_frames(out) if out else out
            for m, out in zip(machines, frames, strict=True)]
