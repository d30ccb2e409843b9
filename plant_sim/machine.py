"""The smart planer as a time-stepped, deterministic machine model (the ``Machine`` facade).

One object holds the spindle, the knives, the piezo actuator and its amplifier, the feed drive,
the encoder, the stream of boards, the cut and the camera. Time moves only through
:meth:`Machine.advance` (the injected clock; nothing sleeps). Inside, the PLC cycle
(``plc.cycle_s``) is the grid on which the drives are updated; between grid points the spindle
angle is linear and the feed position quadratic in time, and every event -- a knife at bottom
dead centre (BDC), the amplifier's switch to the next knife's offset, a camera trigger -- is
handled at its exact instant. The result does not depend on how a caller chops time into
``advance`` calls (up to the sensor noise drawn when a status is read).

The cut: at every knife's BDC the pass is recorded for the board under the cutter: board
coordinate of the cutter axis and ``bottom_um = -(runout_k + eccentricity term) +`` the actual
piezo displacement at that instant. The surface under the camera is the envelope of those
passes (:mod:`plant_sim.surface`), so compensation genuinely changes the surface.

Faults (:meth:`Machine.inject`, or ``[faults] inject`` in ``config/sim.toml``), each with an
optional ``at_s`` (absolute simulated time; default now):

- ``belt_slip`` (``px`` or ``counts``): between triggers A and B of the next pair the encoder
  gains ``counts = round(px / px_per_count)`` counts that the board did not travel; the
  counter stays off by that much afterwards (the vision registration sees the lie).
- ``encoder_wrap`` (``counts_before_wrap``, default 2000): the counter is preset so that it wraps
  that many counts from now (index latches already recorded are shifted alike).
- ``encoder_fault``: the counter stops (faults bit 2) until :meth:`reset_faults`.
- ``knot`` (``board_id``, ``at_mm`` from the leading end, ``length_mm``, ``width_mm``, ``y_mm``,
  ``darkness``, ``roughness_um``): a dark, rough patch on a board.
- ``spindle_stop``: the spindle drive trips and coasts down (faults bit 1, state bit 3 off); the
  PLC's interlock stops the feed.
- ``estop``: e-stop (state bit 2): spindle braked, feed stopped, piezo amplifier powered off.
- ``feed_fault``: the feed drive trips (faults bit 0) and stops.
- ``piezo_fault`` (``bit``, default 3 overcurrent): amplifier fault, state 3 (faults bit 4).
- ``can_drop`` (``duration_s``, ``fraction`` default 1): that fraction of the piezo commands
  and offset tables is lost on the bus for a while (drawn from the seed).
- ``modbus_restart``, ``can_silence`` (``duration_s``): interface faults; the machine only queues
  them for the runner (:meth:`Machine.take_interface_events`).
- ``reset``: same as :meth:`reset_faults`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from config.loading import default_path, load_toml
from config.sim import FAULT_KINDS, SimConfig
from core.checks import check_finite, check_int, check_positive
from plant_sim.camera import FrameAssembler, Knot, Latch, TriggerClock
from plant_sim.feed_drive import BoardStream, Encoder, FeedDrive
from plant_sim.piezo import FAULT as PIEZO_FAULT
from plant_sim.piezo import PiezoAmplifier, PiezoStatus
from plant_sim.spindle import BRAKE, COAST, RUN, Spindle
from plant_sim.surface import Cutterhead, Passes, Surface
from protocol.frames import Frame

__all__ = ["Machine", "PiezoStatus", "register_names"]

# machine_state bits
ST_RUNNING, ST_BOARD, ST_ESTOP, ST_SPINDLE, ST_FEED = 1, 2, 4, 8, 16
# faults bits
F_FEED, F_SPINDLE, F_ENCODER, F_HEARTBEAT, F_PIEZO = 1, 2, 4, 8, 16

_EPS_S = 1e-9
_INDEX_RING = 4096


def register_names(path: Any = None) -> list[str]:
    """Names of every register in the register map (``config/registers.toml`` by default)."""
    data = load_toml(path if path is not None else default_path("registers.toml"))
    return [str(r["name"]) for r in data.get("register", [])]


class _PassLog:
    """Growing arrays of the knife passes over one board."""

    def __init__(self, radius_mm: float) -> None:
        self.radius_mm = radius_mm
        self.n = 0
        self.x = np.empty(1024)
        self.bottom = np.empty(1024)
        self.knife = np.empty(1024, dtype=np.int64)

    def append(self, x_mm: float, bottom_um: float, knife: int) -> None:
        if self.n == self.x.size:
            self.x = np.concatenate([self.x, np.empty(self.n)])
            self.bottom = np.concatenate([self.bottom, np.empty(self.n)])
            self.knife = np.concatenate([self.knife, np.empty(self.n, dtype=np.int64)])
        i = self.n
        self.x[i] = x_mm
        self.bottom[i] = bottom_um
        self.knife[i] = knife
        self.n = i + 1

    def passes(self) -> Passes:
        n = self.n
        return Passes(self.x[:n].copy(), self.bottom[:n].copy(), self.knife[:n].copy(),
                      self.radius_mm)


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
    head : plant_sim.surface.Cutterhead
        Knives, radius, runout and eccentricity.
    frames_dropped : int
        Pairs that could not be assembled (no passes under the field of view).
    """

    def __init__(self, cfg: SimConfig, *, seed: int = 0, render_images: bool = True) -> None:
        self.cfg = cfg
        self.seed = check_int("seed", seed, lo=0)
        self.render_images = bool(render_images)
        ss = np.random.SeedSequence(self.seed)
        r_ripple, r_sensor, r_knot, r_drop = (np.random.default_rng(s) for s in ss.spawn(4))
        ch = cfg.cutterhead
        self.knives = ch.knives
        self.head = Cutterhead(ch.knives, ch.radius_mm, tuple(ch.runout_um), ch.eccentricity_um)
        self._standout = [float(v) for v in self.head.standout_um()]
        self.cycle_s = cfg.plc.cycle_s
        self.spindle = Spindle(cfg.spindle, ripple_phase_rad=float(r_ripple.uniform(0, 2 * np.pi)))
        self.feed = FeedDrive(cfg.feed)
        self.encoder = Encoder(cfg.encoder)
        self.boards = BoardStream(cfg.board)
        self.amp = PiezoAmplifier(cfg.piezo, ch.knives, r_sensor)
        self._knot_rng = r_knot
        self._drop_rng = r_drop
        self._lead = cfg.piezo.lead_fraction
        cam = cfg.camera
        self.L_mm = cam.cutter_to_camera_mm
        renderer = None
        if self.render_images:
            from config.wood import SPECIES
            from plant_sim.optics import Optics, Renderer

            o = cam.optics
            optics = Optics(
                width=o.width,
                height=o.height,
                led_imbalance=o.imbalance,
                falloff=o.falloff,
                read_noise_dn=o.noise,
                dt_ab_s=cam.dt_ab_s,
                counts_per_mm=cfg.encoder.counts_per_mm,
            )
            renderer = Renderer(cam.rig, optics, SPECIES[cam.species], seed=self.seed)
        self.renderer = renderer
        self.assembler = FrameAssembler(
            cam.rig, width=cam.optics.width, counter_bits=cfg.encoder.counter_bits,
            renderer=renderer,
        )
        self._fov_lo, self._fov_hi = self.assembler.x_lo_mm, self.assembler.x_hi_mm
        self.triggers = TriggerClock(cam.pairs_per_s)
        self._register_names = register_names()
        # time and cycle
        self._t = 0.0
        self._cycle = 0
        self.heartbeat_plc = 0
        # cut and camera state
        self._logs: dict[int, _PassLog] = {}
        self._next_bdc = math.floor(self.knives * self.spindle.rev) + 1
        self._next_sw = math.floor(self.knives * self.spindle.rev + self._lead) + 1
        self._idx_s = np.full(_INDEX_RING, np.nan)
        self._idx_raw = np.zeros(_INDEX_RING, dtype=np.int64)
        self._idx_n = 0
        self._latch: Latch | None = None
        self._seq = 0
        self._last_pair: Latch | None = None
        self.knots: list[Knot] = []
        self.frames_dropped = 0
        # PLC state
        self.estop = False
        self.fault_bits = 0
        self.heartbeat_service = 0
        self._hb_changed_s = 0.0
        self._scheduled: list[tuple[float, int, str, dict[str, Any]]] = []
        self._n_sched = 0
        self._pending_slip: int | None = None
        self._can_drop_until = -math.inf
        self._can_drop_fraction = 1.0
        self._interface_events: list[dict[str, Any]] = []
        self._amp_cmd_knives: int | None = None
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
        return frames

    def _start_cycle(self) -> None:
        t = self._cycle * self.cycle_s
        cs = self.cycle_s
        self._apply_scheduled(t)
        s = self.feed.s_mm
        # watchdog on the service heartbeat
        if t - self._hb_changed_s > self.cfg.plc.watchdog_ms * 1e-3:
            self.fault_bits |= F_HEARTBEAT
        else:
            self.fault_bits &= ~F_HEARTBEAT
        cutting = self.boards.at(s, 0.0)[0] != 0
        self.spindle.start_cycle(t, cs, cutting=cutting)
        self.feed.enabled = (
            not self.estop and self.spindle.running and not (self.fault_bits & F_FEED)
        )
        self.feed.start_cycle(t, cs)
        self.amp.cycle(t, cs, spindle_turning=self.spindle.turning)
        if self.amp.state == PIEZO_FAULT:
            self.fault_bits |= F_PIEZO
        else:
            self.fault_bits &= ~F_PIEZO
        self.heartbeat_plc = (self.heartbeat_plc + 1) & 0xFFFF

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
                    self._bdc(nb % z, tb)
                    self._next_bdc = nb + 1
        amp.advance_to(t1)
        # camera triggers
        while True:
            la = self._latch
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

    # ------------------------------------------------------------------ the cut
    def _bdc(self, knife: int, t: float) -> None:
        s = self.feed.position_at(t)
        if knife == 0:
            i = self._idx_n % _INDEX_RING
            self._idx_s[i] = s
            self._idx_raw[i] = self.encoder.raw(s)
            self._idx_n += 1
        bid, x = self.boards.at(s, 0.0, margin_mm=5.0)
        if bid == 0:
            return
        log = self._logs.get(bid)
        if log is None:
            log = self._logs[bid] = _PassLog(self.head.radius_mm)
            for old in [k for k in self._logs if k < bid - 3]:
                del self._logs[old]
        log.append(x, self.amp.actuator.x_um - self._standout[knife], knife)

    # ------------------------------------------------------------------ the camera
    def _trigger_a(self, t: float) -> None:
        s = self.feed.position_at(t)
        bid, x = self.boards.at(s, self.L_mm)
        if bid == 0:
            return
        length = self.boards.length_mm
        if x + self._fov_lo < 5.0 or x + self._fov_hi > length - 5.0:
            return
        raw = self.encoder.raw(s)
        self._seq += 1
        self._latch = Latch(
            seq=self._seq,
            t_a=t,
            s_a=s,
            counts_a=self.encoder.wrap(raw),
            v_a=self.feed.speed_at(t),
            board_id=bid,
            x_centre_mm=x,
            index_latch=self._index_latch(s - self.L_mm),
            t_b=t + self.cfg.camera.dt_ab_s,
        )
        if self._pending_slip is not None:
            self._latch.slip_counts = self._pending_slip
            self.encoder.add_slip(self._pending_slip)
            self._pending_slip = None

    def _index_latch(self, s_cut: float) -> int:
        n = min(self._idx_n, _INDEX_RING)
        if n == 0:
            return self.encoder.wrap(0)
        d = np.abs(self._idx_s[:n] - s_cut)
        i = int(np.nanargmin(d))
        return self.encoder.wrap(int(self._idx_raw[i]))

    def _trigger_b(self, la: Latch, frames: list[Frame]) -> None:
        self._latch = None
        la.s_b = self.feed.position_at(la.t_b)
        la.counts_b = self.encoder.read(la.s_b)
        self._last_pair = la
        log = self._logs.get(la.board_id)
        if log is None or log.n == 0:
            self.frames_dropped += 1
            return
        try:
            frame = self.assembler.assemble(
                la, log.passes(), self.knots, board_length_mm=self.boards.length_mm
            )
        except ValueError:
            self.frames_dropped += 1
            return
        frames.append(frame)

    # ------------------------------------------------------------------ PLC side
    def register_values(self) -> dict[str, float | int]:
        """Every register of ``config/registers.toml`` with its current value."""
        t = self._t
        s = self.feed.position_at(t)
        cfg = self.cfg
        last = self._last_pair
        bid, _ = self.boards.at(s, self.L_mm)
        values: dict[str, float | int] = {
            "heartbeat_service": self.heartbeat_service,
            "heartbeat_plc": self.heartbeat_plc,
            "feed_setpoint_mm_s": self.feed.setpoint_mm_s,
            "feed_min_mm_s": cfg.feed.min_mm_s,
            "feed_max_mm_s": cfg.feed.max_mm_s,
            "feed_accel_max_mm_s2": cfg.feed.accel_max_mm_s2,
            "feed_actual_mm_s": self.feed.speed_at(t),
            "spindle_rpm": self.spindle.rpm,
            "encoder_counts": self.encoder.read(s),
            "trigger_a_counts": last.counts_a if last else 0,
            "trigger_b_counts": last.counts_b if last else 0,
            "trigger_seq": (last.seq if last else 0) & 0xFFFF,
            "index_latch_counts": last.index_latch if last else 0,
            "machine_state": self.machine_state(),
            "faults": self.fault_bits,
            "knives": self.knives,
            "cutter_to_camera_mm": self.L_mm,
            "counts_per_mm": cfg.encoder.counts_per_mm,
            "board_id": bid,
            "board_position_mm": (self.boards.length_mm - last.x_centre_mm) if last else 0.0,
            "watchdog_ms": cfg.plc.watchdog_ms,
            "cutterhead_radius_mm": self.head.radius_mm,
        }
        missing = [n for n in self._register_names if n not in values]
        if missing:
            raise RuntimeError(f"machine has no value for registers {missing}")
        return values

    def machine_state(self) -> int:
        """The ``machine_state`` register's bits."""
        s = self.feed.position_at(self._t)
        st = 0
        if self.spindle.running:
            st |= ST_SPINDLE
        if self.feed.enabled:
            st |= ST_FEED
        if self.spindle.running and self.feed.enabled and not self.estop:
            st |= ST_RUNNING
        if self.estop:
            st |= ST_ESTOP
        if self.boards.at(s, self.L_mm)[0]:
            st |= ST_BOARD
        return st

    def set_feed_setpoint(self, feed_mm_s: float) -> None:
        """New feed setpoint; ``ValueError`` outside ``[feed_min, feed_max]`` (never clamped)."""
        self.feed.set_setpoint(feed_mm_s)

    def set_service_heartbeat(self, value: int) -> None:
        """The service's heartbeat; a changed value feeds the PLC's watchdog."""
        v = check_int("value", value, lo=0, hi=0xFFFF)
        if v != self.heartbeat_service:
            self._hb_changed_s = self._t
            self.fault_bits &= ~F_HEARTBEAT
        self.heartbeat_service = v

    # ------------------------------------------------------------------ piezo amplifier side
    def piezo_command(self, *, enable: bool, alive_counter: int, knives: int | None = None) -> None:
        """PIEZO_COMMAND: enable and alive counter (a new counter restarts the timeout).

        Raises
        ------
        ValueError
            ``alive_counter`` outside 0..255, or ``knives`` given and not the machine's.
        """
        if knives is not None and check_int("knives", knives) != self.knives:
            raise ValueError(f"knives must be {self.knives} (the cutterhead's), got {knives}")
        check_int("alive_counter", alive_counter, lo=0, hi=255)
        if self._dropped():
            return
        self.amp.command(self._t, enable=bool(enable), alive_counter=alive_counter)

    def set_piezo_offsets(self, offsets_um: Sequence[float]) -> None:
        """Per-knife offsets, um (positive: head up, knife cuts less deep).

        ``ValueError`` beyond the stroke or with fewer values than knives; values for knives
        the head does not have (up to 8, as the CAN frames carry) are checked and ignored.
        """
        if self._dropped():
            self.amp.check_offsets(offsets_um)  # still validated, then lost on the bus
            return
        self.amp.set_offsets(offsets_um)

    def _dropped(self) -> bool:
        """Whether a CAN frame to the amplifier is lost now (``can_drop`` fault)."""
        if self._t >= self._can_drop_until:
            return False
        f = self._can_drop_fraction
        return f >= 1.0 or float(self._drop_rng.random()) < f

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
        """Inject a fault now or at ``at_s`` (see the module docstring for kinds and parameters).

        Raises
        ------
        ValueError
            Unknown kind or parameter, or a parameter out of range.
        """
        if fault not in FAULT_KINDS:
            raise ValueError(f"fault must be one of {', '.join(FAULT_KINDS)}; got {fault!r}")
        params = dict(params)
        at = params.pop("at_s", None)
        self._validate_fault(fault, params)
        if at is not None and check_finite("at_s", at) > self._t:
            self._n_sched += 1
            self._scheduled.append((float(at), self._n_sched, fault, params))
            self._scheduled.sort()
            return
        self._apply(fault, params)

    _PARAMS: dict[str, tuple[str, ...]] = {
        "belt_slip": ("px", "counts"),
        "encoder_wrap": ("counts_before_wrap",),
        "encoder_fault": (),
        "knot": ("board_id", "at_mm", "length_mm", "width_mm", "y_mm", "darkness", "roughness_um"),
        "spindle_stop": (),
        "estop": (),
        "feed_fault": (),
        "piezo_fault": ("bit",),
        "can_drop": ("duration_s", "fraction"),
        "modbus_restart": ("duration_s",),
        "can_silence": ("duration_s",),
        "reset": (),
    }

    def _validate_fault(self, fault: str, params: dict[str, Any]) -> None:
        allowed = self._PARAMS[fault]
        for k, v in params.items():
            if k not in allowed:
                raise ValueError(
                    f"{fault}: unknown parameter {k!r} (allowed: {', '.join(allowed) or 'none'})"
                )
            check_finite(f"{fault}.{k}", v)
        if fault == "belt_slip" and "px" in params and "counts" in params:
            raise ValueError("belt_slip: give px or counts, not both")
        ranges = {
            "counts_before_wrap": (1, self.encoder.modulus - 1),
            "fraction": (1e-9, 1.0),
            "duration_s": (0.0, math.inf),
            "bit": (0, 7),
            "at_mm": (0.0, self.boards.length_mm),
            "board_id": (1, math.inf),
            "length_mm": (1e-3, math.inf),
            "width_mm": (1e-3, math.inf),
            "darkness": (0.0, 1.0),
            "roughness_um": (0.0, math.inf),
        }
        for k, v in params.items():
            lo, hi = ranges.get(k, (-math.inf, math.inf))
            if not lo <= float(v) <= hi:
                raise ValueError(f"{fault}.{k} must be in [{lo}, {hi}], got {v!r}")
            if k in ("counts", "counts_before_wrap", "bit", "board_id") and float(v) != int(v):
                raise ValueError(f"{fault}.{k} must be an integer, got {v!r}")

    def _apply_scheduled(self, t: float) -> None:
        while self._scheduled and self._scheduled[0][0] <= t + _EPS_S:
            _, _, fault, params = self._scheduled.pop(0)
            self._apply(fault, params)

    def _apply(self, fault: str, p: dict[str, Any]) -> None:
        t = self._t
        s = self.feed.position_at(t)
        if fault == "belt_slip":
            if "counts" in p:
                n = check_int("belt_slip.counts", int(p["counts"]))
            else:
                px = float(p.get("px", 12.0))
                n = int(round(px / self.cfg.camera.rig.encoder.px_per_count))
            self._pending_slip = n
        elif fault == "encoder_wrap":
            n = int(p.get("counts_before_wrap", 2000))
            old = self.encoder.start
            self.encoder.preset_before_wrap(s, n)
            # latches already recorded are shifted alike (as if the counter had started there)
            delta = self.encoder.start - old
            if self._latch is not None:
                self._latch.counts_a = (self._latch.counts_a + delta) % self.encoder.modulus
                self._latch.index_latch = (self._latch.index_latch + delta) % self.encoder.modulus
        elif fault == "encoder_fault":
            self.encoder.freeze(s)
            self.fault_bits |= F_ENCODER
        elif fault == "knot":
            self._add_knot(s, p)
        elif fault == "spindle_stop":
            if self.spindle.mode == RUN:
                self.spindle.mode = COAST
            self.fault_bits |= F_SPINDLE
        elif fault == "estop":
            self.estop = True
            self.spindle.mode = BRAKE
            self.amp.power_off(t, True)
        elif fault == "feed_fault":
            self.fault_bits |= F_FEED
        elif fault == "piezo_fault":
            bit = check_int("piezo_fault.bit", int(p.get("bit", 3)), lo=0, hi=7)
            self.amp.inject_fault(t, 1 << bit)
        elif fault == "can_drop":
            self._can_drop_until = t + check_positive("can_drop.duration_s",
                                                      p.get("duration_s", 0.5))
            frac = check_finite("can_drop.fraction", p.get("fraction", 1.0))
            if not 0.0 < frac <= 1.0:
                raise ValueError(f"can_drop.fraction must be in (0, 1], got {frac}")
            self._can_drop_fraction = frac
        elif fault in ("modbus_restart", "can_silence"):
            self._interface_events.append({"kind": fault, "t_s": t, **p})
        elif fault == "reset":
            self.reset_faults()

    def _add_knot(self, s: float, p: dict[str, Any]) -> None:
        b = self.boards
        if "board_id" in p:
            bid = check_int("knot.board_id", int(p["board_id"]), lo=1)
        else:
            cur, _ = b.at(s, 0.0)
            bid = cur + 1 if cur else max(1, math.floor((s - b.first_at_mm) / b.period_mm) + 2)
        at = check_finite("knot.at_mm", p.get("at_mm", 1000.0))
        if not 0.0 <= at <= b.length_mm:
            raise ValueError(f"knot.at_mm must be on the board (0..{b.length_mm}), got {at}")
        knot = Knot(
            board_id=bid,
            x_mm=b.length_mm - at,
            y_mm=check_finite("knot.y_mm", p.get("y_mm", 0.0)),
            length_mm=check_positive("knot.length_mm", p.get("length_mm", 40.0)),
            width_mm=check_positive("knot.width_mm", p.get("width_mm", 30.0)),
            darkness=min(max(check_finite("knot.darkness", p.get("darkness", 0.6)), 0.0), 1.0),
            roughness_um=check_positive("knot.roughness_um", p.get("roughness_um", 4.0),
                                        allow_zero=True),
            seed=int(self._knot_rng.integers(0, 2**31)),
        )
        self.knots.append(knot)

    def reset_faults(self) -> None:
        """Acknowledge: clear the e-stop and the drive faults; the spindle runs up again."""
        s = self.feed.position_at(self._t)
        self.estop = False
        self.spindle.mode = RUN
        self.amp.power_off(self._t, False)
        if self.encoder.frozen is not None:
            self.encoder.unfreeze(s)
        self.fault_bits &= ~(F_FEED | F_SPINDLE | F_ENCODER)

    def take_interface_events(self) -> list[dict[str, Any]]:
        """Interface faults that came due (``modbus_restart``, ``can_silence``); cleared on read."""
        out, self._interface_events = self._interface_events, []
        return out

    # ------------------------------------------------------------------ truth and state
    def passes(self, board_id: int) -> Passes:
        """Every knife pass recorded over board ``board_id`` (recent boards only)."""
        log = self._logs.get(check_int("board_id", board_id, lo=1))
        if log is None:
            raise ValueError(f"board_id {board_id}: no passes recorded (not cut yet or too old)")
        return log.passes()

    def surface(self, x_lo_board_mm: float, x_hi_board_mm: float, *,
                board_id: int | None = None) -> Surface:
        """The true planed surface over a board range (board coordinate from the trailing end)."""
        lo = check_finite("x_lo_board_mm", x_lo_board_mm)
        hi = check_finite("x_hi_board_mm", x_hi_board_mm)
        if not hi > lo:
            raise ValueError("x_hi_board_mm must exceed x_lo_board_mm")
        bid = self._default_board() if board_id is None else board_id
        return self.assembler.surface(self.passes(bid), lo, hi)

    def true_metrics(self, x_lo_board_mm: float, x_hi_board_mm: float, *,
                     board_id: int | None = None) -> dict[str, Any]:
        """True mark metrics over a board range (board coordinate ``x`` from the trailing end).

        Returns
        -------
        dict
            As :meth:`plant_sim.surface.Surface.metrics`: ``pitch_mm``, ``uniformity_cv``,
            ``depth_um``, ``mark_widths_mm``, ``knife``, ... of the complete marks inside.
        """
        surf = self.surface(x_lo_board_mm, x_hi_board_mm, board_id=board_id)
        return surf.metrics(x_lo_board_mm, x_hi_board_mm)

    def _default_board(self) -> int:
        if self._last_pair is not None and self._last_pair.board_id in self._logs:
            return self._last_pair.board_id
        if not self._logs:
            raise ValueError("no board has been cut yet")
        return max(self._logs)

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

    def board_under_cutter(self) -> tuple[int, float]:
        """``(board_id, x_mm)`` of the board under the cutter axis (``(0, nan)`` if none)."""
        return self.boards.at(self.feed_position_mm, 0.0)

    def board_under_camera(self) -> tuple[int, float]:
        """``(board_id, x_mm)`` of the board under the optical axis (``(0, nan)`` if none)."""
        return self.boards.at(self.feed_position_mm, self.L_mm)

    def standout_um(self) -> list[float]:
        """True radial stand-out of each knife (runout plus eccentricity), um."""
        return list(self._standout)

    def pitch_mm(self) -> float:
        """Nominal feed per knife pass from the current speeds, mm."""
        rps = self.spindle.rev_s
        return self.feed_speed_mm_s / (rps * self.knives) if rps > 0 else math.inf
