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

__all__ = ["Machine", "PiezoStatus", "register_names", "runout_drift"]


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

    def __init__(self, cfg: SimConfig, *, seed: int = 0, render_images: bool = True) -> None:
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
        self.feed = FeedDrive(cfg.feed)
        self.encoder = Encoder(cfg.encoder)
        self.boards = BoardStream(cfg.board)
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
        self._start_cycle()

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
        """
        dt = check_positive("dt_s", dt_s, allow_zero=True)
        target = self._t + dt
        frames: list[Frame] = []
        cs = self.cycle_s
        while self._t < target - _EPS_S:
            t_end = (self._cycle + 1) * cs
            if target >= t_end - _EPS_S:
                self._interval(self._t, t_end, frames)
                self._end_cycle()
                self._t = t_end
                self._cycle += 1
                self._start_cycle()
            else:
                self._interval(self._t, target, frames)
                self._t = target
        if self._t < target:
            self._t = target
        return self.faults.filter_frames(frames) if frames else frames

    def _start_cycle(self) -> None:
        t = self._cycle * self.cycle_s
        cs = self.cycle_s
        self.faults.apply_due(t)
        self.faults.apply_at_travel(self.feed.s_mm, t)
        self.plc.start_cycle(t)
        cutting = self.boards.at(self.feed.s_mm, 0.0)[0] != 0
        self.spindle.start_cycle(t, cs, cutting=cutting)
        self.feed.enabled = self.plc.feed_permitted()
        self.feed.start_cycle(t, cs)
        self.amp.cycle(t, cs, spindle_turning=self.spindle.turning)
        self.plc.set_flag(PlcFault.PIEZO_AMPLIFIER, self.amp.state == PIEZO_FAULT)

    def _end_cycle(self) -> None:
        self.spindle.end_cycle(self.cycle_s)
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
