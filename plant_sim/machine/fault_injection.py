"""Fault injection into the machine model: validation, the schedule, each fault's effect, timers.

Faults (:meth:`plant_sim.machine.machine.Machine.inject`, or ``[faults] inject`` in
``config/sim.toml``), each with an optional ``at_s`` (absolute simulated time; default now;
applied on the PLC-cycle grid). Parameter names, defaults and ranges come from the registry
(:mod:`config.faults`); the ranges that depend on the machine are checked here.

- ``belt_slip`` (``px`` or ``counts``): between triggers A and B of the next pair the encoder
  gains ``counts = round(px / px_per_count)`` counts that the board did not travel; the
  counter stays off by that much afterwards (the vision registration sees the lie).
- ``encoder_wrap`` (``counts_before_wrap``, default 2000): the counter is preset so that it wraps
  that many counts from now (index latches already recorded are shifted alike).
- ``encoder_fault``: the counter stops (faults bit 2) until a reset.
- ``knot`` (``board_id``, ``at_mm`` from the leading end, ``length_mm``, ``width_mm``, ``y_mm``,
  ``darkness``, ``roughness_um``): a dark, rough patch on a board.
- ``spindle_stop``: the spindle drive trips and coasts down (faults bit 1, state bit 3 off); the
  PLC's interlock stops the feed.
- ``estop``: e-stop (state bit 2): spindle braked, feed stopped, piezo amplifier powered off.
- ``feed_fault``: the feed drive trips (faults bit 0) and stops.
- ``piezo_fault`` (``bit``, default 3 overcurrent): amplifier fault, state 3 (faults bit 4).
- ``can_drop`` (``duration_s``, ``fraction`` default 1): that fraction of the piezo commands
  and offset tables is lost on the bus for a while (drawn from the seed;
  :meth:`FaultInjector.can_frame_lost`).
- ``modbus_restart``, ``can_silence`` (``duration_s``): interface faults; only queued for the
  runner (:meth:`FaultInjector.take_interface_events`).
- ``reset``: acknowledge (:meth:`FaultInjector.reset`).
- ``knife_chip`` (``knife``, ``step_um``, ``at_s`` and/or ``at_travel_mm``): the knife's runout
  steps by ``step_um`` from then on (every later pass of it cuts that much deeper); at a time,
  or once the table has travelled ``at_travel_mm`` (and ``at_s`` has come, when given both;
  :meth:`FaultInjector.apply_at_travel`).
- ``species_change`` (``species``, ``board_id`` default the next board): the boards from that
  one on are of another wood; the renderer changes when that board reaches the cutter (the
  gap between boards is longer than the cutter-to-camera distance, so no pair shows two woods).
  Only the images change: without rendering (``render_images=False``) it has no effect. Render
  workers of ``planer sim`` render the configured species (they are not told).
- ``camera_silent`` (``duration_s``): the camera sends no pair at all meanwhile (a whole
  ``measurement_dropout``; a moulder's head names it with ``head``).
- ``measurement_dropout`` (``duration_s``, ``fraction`` default 0.5, ``spoil`` default 0): that
  share of the pairs captured meanwhile is lost (``spoil = 0``: never delivered, counted in
  :attr:`FaultInjector.pairs_dropped`) or delivered spoiled (``spoil = 1``: light B did not
  fire, image B is black; without images the pair carries an ``error``), drawn from the seed
  (:meth:`FaultInjector.filter_frames`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from config.faults import FaultKind
from config.sim import FAULT_KINDS, SimConfig
from core.checks import check_finite, check_int, check_positive
from plant_sim.machine.plc_registers import PlcRegisters
from plant_sim.model.feed_drive import BoardStream, Encoder, FeedDrive
from plant_sim.model.piezo import PiezoAmplifier
from plant_sim.model.spindle import BRAKE, COAST, RUN, Spindle
from plant_sim.rendering.camera import Knot
from plant_sim.rendering.frame_capture import FrameCapture
from protocol.frames import Frame
from protocol.registers import PlcFault

__all__ = ["FaultInjector"]

_EPS_S = 1e-9


def _param(fault: str, params: dict[str, Any], name: str) -> float:
    """A fault parameter: given, else the registry's default (``config.faults``, written once)."""
    value = FaultKind(fault).value_of(params, name)
    if value is None or isinstance(value, str):
        raise ValueError(f"{fault}.{name} is required as a number, got {value!r}")
    return value


class FaultInjector:
    """Applies faults to the machine's parts, now or at a scheduled time.

    Parameters
    ----------
    cfg : config.sim.SimConfig
        The configuration (the rig's ``px_per_count`` for ``belt_slip``).
    spindle, feed, encoder, boards, amp : the machine's parts
        What the faults act on.
    plc : plant_sim.machine.plc_registers.PlcRegisters
        The PLC's fault bits and e-stop.
    capture : plant_sim.rendering.frame_capture.FrameCapture
        The camera station (pending slip, latches in flight, knots).
    knot_rng, drop_rng : numpy.random.Generator
        Draw the knots' texture seeds and the lost CAN frames.
    """

    def __init__(self, cfg: SimConfig, *, spindle: Spindle, feed: FeedDrive, encoder: Encoder,
                 boards: BoardStream, amp: PiezoAmplifier, plc: PlcRegisters,
                 capture: FrameCapture, knot_rng: np.random.Generator,
                 drop_rng: np.random.Generator) -> None:
        self.px_per_count = cfg.camera.rig.encoder.px_per_count
        self.spindle = spindle
        self.feed = feed
        self.encoder = encoder
        self.boards = boards
        self.amp = amp
        self.plc = plc
        self.capture = capture
        self._knot_rng = knot_rng
        self._drop_rng = drop_rng
        self._scheduled: list[tuple[float, int, str, dict[str, Any]]] = []
        self._n_sched = 0
        self._can_drop_until = -math.inf
        self._can_drop_fraction = 1.0
        self._interface_events: list[dict[str, Any]] = []
        self._cfg = cfg
        self._by_travel: list[tuple[float, int, str, dict[str, Any]]] = []
        self._species: list[tuple[int, str]] = []  # (first board id, species), in order
        self._renderers: dict[str, Any] = {}
        self.species_now = cfg.camera.species
        """The wood the renderer shows now."""
        self._dropout_until = -math.inf
        self._dropout = (0.5, False)  # fraction, spoil
        self._dropout_rng: np.random.Generator | None = None
        self.pairs_dropped = 0
        """Pairs a ``measurement_dropout`` lost."""
        self.pairs_spoiled = 0
        """Pairs a ``measurement_dropout`` spoiled."""
        self.chips: list[dict[str, Any]] = []
        """Every ``knife_chip`` applied: ``t_s``, ``travel_mm``, ``knife``, ``step_um``."""
        self.other_captures: list[FrameCapture] = []
        """Camera stations of other machines on the same encoder (a moulder's heads): an
        ``encoder_wrap`` preset shifts their pairs in flight too."""

    def inject(self, fault: str, params: dict[str, Any], *, now_s: float) -> None:
        """Inject ``fault`` now (``now_s``) or at ``params["at_s"]`` if that is later.

        Raises
        ------
        ValueError
            Unknown kind or parameter, or a parameter out of range.
        """
        if fault not in FAULT_KINDS:
            raise ValueError(f"fault must be one of {', '.join(FAULT_KINDS)}; got {fault!r}")
        params = dict(params)
        at = params.pop("at_s", None)
        self._validate(fault, params)
        travel = params.pop("at_travel_mm", None)
        if travel is not None:  # when the table has travelled that far (and at_s has come)
            self._n_sched += 1
            not_before = now_s if at is None else max(float(at), now_s)
            self._by_travel.append((float(travel), self._n_sched, fault,
                                    {**params, "_not_before_s": not_before}))
            self._by_travel.sort()
            return
        if at is not None and check_finite("at_s", at) > now_s:
            self._n_sched += 1
            self._scheduled.append((float(at), self._n_sched, fault, params))
            self._scheduled.sort()
            return
        self._apply(fault, params, now_s)

    def _validate(self, fault: str, params: dict[str, Any]) -> None:
        # names, required ones, numbers, ranges: the registry (config.faults; ConfigError)
        FaultKind(fault).check(params)
        ranges = {  # the ranges that depend on this machine
            "counts_before_wrap": (1, self.encoder.modulus - 1),
            "at_mm": (0.0, self.boards.length_mm),
        }
        knives = self._cfg.cutterhead.knives
        if fault == "knife_chip" and int(params.get("knife", 0)) >= knives:
            raise ValueError(f"knife_chip.knife must be in [0, {knives - 1}], "
                             f"got {params['knife']!r}")
        for k, v in params.items():
            if isinstance(v, str):
                continue  # a name: the registry checked it
            lo, hi = ranges.get(k, (-math.inf, math.inf))
            if not lo <= float(v) <= hi:
                raise ValueError(f"{fault}.{k} must be in [{lo}, {hi}], got {v!r}")

    def apply_due(self, t_s: float) -> None:
        """Apply the scheduled faults due at ``t_s`` (a PLC-cycle grid point)."""
        while self._scheduled and self._scheduled[0][0] <= t_s + _EPS_S:
            _, _, fault, params = self._scheduled.pop(0)
            self._apply(fault, params, t_s)

    def apply_at_travel(self, s_mm: float, t_s: float) -> None:
        """Apply the faults due at table travel ``s_mm`` (``at_travel_mm``), time ``t_s``."""
        due = [x for x in self._by_travel
               if x[0] <= s_mm and x[3]["_not_before_s"] <= t_s + _EPS_S]
        for item in due:
            self._by_travel.remove(item)
            _, _, fault, params = item
            self._apply(fault, {k: v for k, v in params.items() if k != "_not_before_s"}, t_s)
        self._change_wood(s_mm)

    def filter_frames(self, frames: list[Frame]) -> list[Frame]:
        """The pairs a ``measurement_dropout`` leaves: some lost, some spoiled, the rest."""
        if not frames or frames[0].t_s >= self._dropout_until:
            return frames
        frac, spoil = self._dropout
        if self._dropout_rng is None:
            self._dropout_rng = np.random.default_rng(int(self._drop_rng.integers(2**31)))
        out = []
        for fr in frames:
            hit = fr.t_s < self._dropout_until and float(self._dropout_rng.random()) < frac
            if not hit:
                out.append(fr)
            elif not spoil:
                self.pairs_dropped += 1
            else:
                self.pairs_spoiled += 1
                out.append(_spoiled(fr))
        return out

    def _change_wood(self, s_mm: float) -> None:
        """The renderer of the wood of the board under the cutter (``species_change``)."""
        if not self._species:
            return
        bid, _ = self.boards.at(s_mm, 0.0)
        want = None
        for first, species in self._species:
            if bid >= first:
                want = species
        if want is None or want == self.species_now:
            return
        self.species_now = want
        asm = self.capture.assembler
        if asm.renderer is None:
            return  # no images: nothing shows the wood
        if want not in self._renderers:
            from plant_sim.rendering.frame_capture import build_renderer

            cfg = dataclasses.replace(self._cfg, camera=dataclasses.replace(
                self._cfg.camera, species=want))
            self._renderers[want] = build_renderer(cfg, seed=asm.renderer.seed)
        asm.renderer = self._renderers[want]

    def _apply(self, fault: str, p: dict[str, Any], t: float) -> None:
        s = self.feed.position_at(t)
        plc = self.plc
        if fault == "belt_slip":
            if "counts" in p:
                n = check_int("belt_slip.counts", int(p["counts"]))
            else:
                px = _param("belt_slip", p, "px")
                n = int(round(px / self.px_per_count))
            self.capture.pending_slip = n
        elif fault == "encoder_wrap":
            n = int(_param("encoder_wrap", p, "counts_before_wrap"))
            old = self.encoder.start
            self.encoder.preset_before_wrap(s, n)
            # latches already recorded are shifted alike (as if the counter had started there)
            for capture in (self.capture, *self.other_captures):
                capture.shift_latch(self.encoder.start - old)
        elif fault == "encoder_fault":
            self.encoder.freeze(s)
            plc.set_flag(PlcFault.ENCODER, True)
        elif fault == "knot":
            self._add_knot(s, p)
        elif fault == "spindle_stop":
            if self.spindle.mode == RUN:
                self.spindle.mode = COAST
            plc.set_flag(PlcFault.SPINDLE_STOPPED, True)
        elif fault == "estop":
            plc.estop = True
            self.spindle.mode = BRAKE
            self.amp.power_off(t, True)
        elif fault == "feed_fault":
            plc.set_flag(PlcFault.FEED_DRIVE, True)
        elif fault == "piezo_fault":
            bit = check_int("piezo_fault.bit", int(_param("piezo_fault", p, "bit")), lo=0, hi=7)
            self.amp.inject_fault(t, 1 << bit)
        elif fault == "can_drop":
            self._can_drop_until = t + check_positive("can_drop.duration_s",
                                                      _param("can_drop", p, "duration_s"))
            frac = check_finite("can_drop.fraction", _param("can_drop", p, "fraction"))
            if not 0.0 < frac <= 1.0:
                raise ValueError(f"can_drop.fraction must be in (0, 1], got {frac}")
            self._can_drop_fraction = frac
        elif fault in ("modbus_restart", "can_silence"):
            self._interface_events.append({"kind": fault, "t_s": t, **p})
        elif fault == "reset":
            self.reset(t)
        elif fault == "knife_chip":
            k = int(_param("knife_chip", p, "knife"))
            step = float(_param("knife_chip", p, "step_um"))
            self.capture.cut.step_standout(k, step)
            self.chips.append({"t_s": t, "travel_mm": s, "knife": k, "step_um": step})
        elif fault == "species_change":
            self._add_species(s, p)
        elif fault == "camera_silent":  # every pair lost: a whole dropout
            self._dropout_until = t + float(_param("camera_silent", p, "duration_s"))
            self._dropout = (1.0, False)
        elif fault == "measurement_dropout":
            self._dropout_until = t + float(_param("measurement_dropout", p, "duration_s"))
            self._dropout = (float(_param("measurement_dropout", p, "fraction")),
                             bool(int(_param("measurement_dropout", p, "spoil"))))

    def _add_species(self, s: float, p: dict[str, Any]) -> None:
        b = self.boards
        if "board_id" in p:
            bid = check_int("species_change.board_id", int(p["board_id"]), lo=1)
        else:  # the next board to reach the cutter
            cur, _ = b.at(s, 0.0)
            bid = cur + 1 if cur else max(1, math.floor((s - b.first_at_mm) / b.period_mm) + 2)
        self._species.append((bid, str(p["species"])))
        self._species.sort()
        self._change_wood(s)

    def _add_knot(self, s: float, p: dict[str, Any]) -> None:
        b = self.boards
        if "board_id" in p:
            bid = check_int("knot.board_id", int(p["board_id"]), lo=1)
        else:
            cur, _ = b.at(s, 0.0)
            bid = cur + 1 if cur else max(1, math.floor((s - b.first_at_mm) / b.period_mm) + 2)
        at = check_finite("knot.at_mm", _param("knot", p, "at_mm"))
        if not 0.0 <= at <= b.length_mm:
            raise ValueError(f"knot.at_mm must be on the board (0..{b.length_mm}), got {at}")
        knot = Knot(
            board_id=bid,
            x_mm=b.length_mm - at,
            y_mm=check_finite("knot.y_mm", _param("knot", p, "y_mm")),
            length_mm=check_positive("knot.length_mm", _param("knot", p, "length_mm")),
            width_mm=check_positive("knot.width_mm", _param("knot", p, "width_mm")),
            darkness=min(max(check_finite("knot.darkness", _param("knot", p, "darkness")), 0.0),
                         1.0),
            roughness_um=check_positive("knot.roughness_um", _param("knot", p, "roughness_um"),
                                        allow_zero=True),
            seed=int(self._knot_rng.integers(0, 2**31)),
        )
        self.capture.knots.append(knot)

    def reset(self, t_s: float) -> None:
        """Acknowledge at ``t_s``: clear the e-stop and the drive faults; the spindle runs up."""
        s = self.feed.position_at(t_s)
        self.plc.estop = False
        self.spindle.mode = RUN
        self.amp.power_off(t_s, False)
        if self.encoder.frozen is not None:
            self.encoder.unfreeze(s)
        self.plc.set_flag(PlcFault.FEED_DRIVE | PlcFault.SPINDLE_STOPPED | PlcFault.ENCODER,
                          False)

    def camera_silent(self, t_s: float) -> bool:
        """Whether the camera sends nothing at ``t_s`` (a whole ``measurement_dropout``)."""
        frac, spoil = self._dropout
        return t_s < self._dropout_until and frac >= 1.0 and not spoil

    def can_frame_lost(self, t_s: float) -> bool:
        """Whether a CAN frame to the amplifier at ``t_s`` is lost (``can_drop`` fault)."""
        if t_s >= self._can_drop_until:
            return False
        f = self._can_drop_fraction
        return f >= 1.0 or float(self._drop_rng.random()) < f

    def take_interface_events(self) -> list[dict[str, Any]]:
        """Interface faults that came due (``modbus_restart``, ``can_silence``); cleared on read."""
        out, self._interface_events = self._interface_events, []
        return out


def _spoiled(frame: Frame) -> Frame:
    """The pair as it arrives when light B did not fire: image B black (or an error)."""
    if frame.image_b is None:
        return dataclasses.replace(frame, error="spoiled pair: light B did not fire "
                                   "(simulated measurement dropout)")
    return dataclasses.replace(frame, image_b=np.zeros_like(frame.image_b))
