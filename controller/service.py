"""The service beside the PLC: image pairs in, marks measured, feed and piezo setpoints out.

One :class:`Service` owns the two buses (a :class:`~controller.plc_client.PlcClient` and a
:class:`~controller.piezo_client.PiezoClient`), the quality log, the control loops and the
safe-state supervisor. The entry points, all with the time passed in:

* :meth:`Service.plc_cycle` — the PLC's cycle (every ``safety.cycle_s``): heartbeat register,
  one read of every register, supervisor; feed-forward in RUN, hold or ramp down in SAFE.
* :meth:`Service.can_cycle` — the amplifier's cycle (every ``can.command_period_s``, never
  waits): drain its frames, judge its status, supervisor, enable or zero offsets and disable,
  ``PIEZO_COMMAND`` with a new alive counter.
* :meth:`Service.tick` — both at one instant, in order (simulated time).
* :meth:`Service.handle_frame` — one image pair: take the PLC's registers (the cycle's read of
  at most two cycles ago, else a fresh read), measure (in a worker thread in
  real time so the heartbeats keep going), check plausibility, find which knife cut which mark,
  update the feed loop and the uniformity loop, clamp to the limits, write the setpoints
  (CAN and Modbus) and append the quality record — every measurement, failed ones included; a
  failed or implausible measurement changes no setpoint.

:meth:`Service.run` drives them in real time from a frame source until stopped (``planer
serve``), one task per bus so a PLC that does not answer never delays the CAN heartbeat; the
in-process HIL and the tests call :meth:`tick` and :meth:`handle_frame` step by step on
simulated time.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from config.machine import MachineConfig
from controller.events import EventKind, ServiceEvent
from controller.piezo_client import PiezoClient
from controller.plc_client import PlcClient, PlcSnapshot
from controller.safety import AmplifierMonitor, SafetyState, SafetyStatus, Supervisor
from core.errors import FieldbusError, ModbusRefused, RegistrationError
from protocol.frames import Frame

PLC_SNAPSHOT_MAX_AGE_CYCLES = 2.0
"""A pair uses the registers the tick read if they are at most this many cycles old."""
FEED_WRITE_DEADBAND_MM_S = 0.5
"""Feed-forward changes smaller than this between measurements are not written, mm/s."""
MAX_PHASE_SPREAD = 0.15
"""Marks whose pass numbers spread more than this (in passes) are not attributed to knives."""
MIN_BOTTOM_INSET_SAMPLES = 1.0
"""A mark bottom closer than this (in profile samples, ``1 / px_per_mm``) to a cusp of its mark
was clipped there by the vision (narrow mark, BDC outside it) and does not set the phase."""
MAX_PENDING_RECORDS = 10_000
"""Quality records held in memory while the log cannot be written (about 17 min at 10 pairs/s);
beyond that the oldest are saved to a JSON-lines file beside the log."""
PROFILE_EVERY = 10
"""Every this many successful measurements (and the first of each board) a record carries the
surface profile (``extra["profile"]``, drawn by ``planer report``)."""
PROFILE_MAX_POINTS = 800
"""Most points of a stored profile (about 6 kB of JSON)."""
_REASONS = {
    "plc": "plc gone",
    "can": "can gone",
    "measurement": "measurement gone",
    "machine": "machine not running",
    "plc_data": "plc data invalid",
    "amplifier": "piezo amplifier not tracking",
    "log": "quality log failing",
    "service": "service error",
}


@dataclass(frozen=True)
class FrameResult:
    """What the service did with one image pair.

    Attributes
    ----------
    seq : int
        The pair's sequence number.
    ok : bool
        Whether the measurement succeeded and passed the plausibility checks.
    error : str or None
        Why not (``"registration failed: ..."``, ``"implausible: ..."``).
    measurement : object or None
        The vision result (``x_mm``, ``pitch_mm``, ``mark_widths_mm``, ...).
    knife_widths_mm : tuple of float
        Mean mark width per knife, mm (NaN where no mark of that knife was seen).
    applied : bool
        Whether setpoints were updated from it (``ok`` and state ``RUN``).
    feed_setpoint_mm_s : float or None
        Feed setpoint in force after the pair, mm/s.
    offsets_um : tuple of float
        Piezo offsets in force after the pair, um.
    state : str
        Supervisor state after the pair (``"run"`` / ``"safe"``).
    t_s : float
        Service time when the pair arrived, s.
    latency_s : float
        Wall-clock seconds from the pair's arrival (the call of :meth:`Service.handle_frame`)
        to its setpoints on the wire (or to the decision not to send any).
    truth : dict or None
        The simulator's truth of the imaged patch (``Frame.truth``).
    counts_a : int
        Encoder counts at trigger A (board travel).
    frame_t_s : float
        Machine time of the pair (trigger A), s.
    record_id : int or None
        Id of the quality record.
    """

    seq: int
    ok: bool
    error: str | None
    measurement: Any
    knife_widths_mm: tuple[float, ...]
    applied: bool
    feed_setpoint_mm_s: float | None
    offsets_um: tuple[float, ...]
    state: str
    t_s: float
    latency_s: float
    truth: dict[str, Any] | None = None
    counts_a: int = 0
    frame_t_s: float = 0.0
    record_id: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Attributed:
    """The marks of one valid pair attributed to knife passes (what the loops get).

    Attributes
    ----------
    knife_widths_mm : ndarray, shape (Z,)
        Width per knife and pass, a pass without a mark counting 0; NaN for a knife that
        left no mark in the field, mm.
    pass_pitch_mm : float
        Board travel per knife pass: the marks' width sum over the knife passes they span
        (the measured mean mark width when no knife is missing), mm. The feed loop holds this
        at the target; the uniformity loop scales its steps by it.
    missing_passes : int
        Knife passes in that span that left no mark.
    spread : float
        Phase spread of the reliable bottoms, passes.
    reliable_marks : int
        Marks whose bottoms lie inside them (these set the phase).
    """

    knife_widths_mm: np.ndarray
    pass_pitch_mm: float
    missing_passes: int
    spread: float
    reliable_marks: int

    def to_json(self) -> dict[str, Any]:
        """Plain-JSON summary for the quality record's ``extra["passes"]``."""
        return {
            "pass_pitch_mm": self.pass_pitch_mm,
            "missing_passes": self.missing_passes,
            "phase_spread": self.spread,
            "reliable_marks": self.reliable_marks,
        }


class Service:
    """The closed loop around the PLC, the piezo amplifier and the camera.

    Parameters
    ----------
    cfg : MachineConfig
        The service's configuration.
    plc : PlcClient
        The one PLC connection.
    piezo : PiezoClient
        The one CAN connection to the amplifier.
    measurer_factory : callable
        ``factory(shape) -> measurer`` with ``measurer.measure(image_a, image_b, *, counts_a,
        counts_b, speed_mm_s) -> Measurement``; called once per image shape.
    rig : Rig
        The rig (``px_per_mm``, ``cx`` for the mark-to-knife phase; field of view).
    log : QualityLog or None
        Where every measurement goes (``None``: not logged).
    clock : callable
        Monotonic seconds; default ``time.monotonic``. Simulated time in tests and HIL.
    threaded : bool
        Run the measurement and the log append in worker threads (real time). ``False`` runs
        them inline (deterministic simulated-time runs).
    pairs_per_s : float
        Nominal camera rate (sample time of the feed loop), pairs per second.
    """

    def __init__(
        self,
        cfg: MachineConfig,
        *,
        plc: PlcClient,
        piezo: PiezoClient,
        measurer_factory: Callable[[tuple[int, int]], Any],
        rig: Any,
        log: Any = None,
        clock: Callable[[], float] = time.monotonic,
        threaded: bool = True,
        pairs_per_s: float = 10.0,
    ) -> None:
        self.cfg = cfg
        self.plc = plc
        self.piezo = piezo
        self.rig = rig
        self.log = log
        self.clock = clock
        self.threaded = threaded
        self.pairs_per_s = float(pairs_per_s)
        self._measurer_factory = measurer_factory
        self._measurers: dict[tuple[int, int], Any] = {}
        fr = cfg.frames
        if fr.image_width > 0 and fr.image_height > 0:  # set-up once, before the first pair
            self.measurer((fr.image_height, fr.image_width))
        self.quality_class = _quality_class(cfg)
        _check_loop_tables(cfg)  # a bad [feed_loop] / [uniformity_loop] key fails now, not later
        t0 = clock()
        self.supervisor = Supervisor(cfg.safety, now_s=t0)
        self.heartbeat = 0
        """The PLC heartbeat register's value (16 bits), one step per PLC cycle."""
        self.alive = 0
        """The CAN alive counter (8 bits), one step per ``PIEZO_COMMAND``."""
        self.amp_monitor = AmplifierMonitor()
        self._amp_problem: str | None = None
        self._faulty: set[str] = set()  # parts whose last cycle raised: "plc", "can", "pair"
        self._feed_refused = False
        self._feed_lock_obj: asyncio.Lock | None = None
        self._feed_lock_loop: Any = None
        self._ok_count = 0  # successful measurements so far (profile every PROFILE_EVERY-th)
        self._profile_board: int | None = None
        self.feed_loop: Any = None
        self.uniformity_loop: Any = None
        self._loop_key: tuple | None = None
        self.feed_setpoint_mm_s: float | None = None
        self.offsets_um: tuple[float, ...] = ()
        self._learned_offsets: np.ndarray | None = None
        self._last_plc_actions_s: float | None = None
        self._machine_offset_s: float | None = None  # service clock minus machine time
        self._last_frame_t: float | None = None
        self._last_seq: int | None = None
        self._t_loops = -math.inf
        self._t_now: float | None = None  # last service time handed out (never decreases)
        self._clock_shift = 0.0  # added to the clock after it went backwards
        self._snap_t = -math.inf  # service time of the last good register read
        self._plc_problem: str | None = None
        self._last_error: str | None = None
        self._pending: deque[Any] = deque()  # quality records not yet in the log, in order
        self._log_failing = False
        self.status: SafetyStatus | None = None
        self.results: list[FrameResult] = []
        self.keep_results = False
        self.counters = {
            "frames": 0,
            "ok": 0,
            "failed": 0,
            "applied": 0,
            "safe_entries": 0,
            "recoveries": 0,
            "plc_errors": 0,
            "can_errors": 0,
            "setpoint_refused": 0,
            "log_errors": 0,
            "errors": 0,
            "missed": 0,
            "amp_faults": 0,
            "uniformity_skipped": 0,
        }
        self.events: list[ServiceEvent] = []
        self.on_result: Callable[[FrameResult], None] | None = None
        self.on_event: Callable[[ServiceEvent], None] | None = None

    # ------------------------------------------------------------------ helpers
    def _event(self, t: float, kind: EventKind, text: str) -> None:
        event = ServiceEvent(t, kind, text)
        self.events.append(event)
        if self.on_event is not None:
            self.on_event(event)

    def _now(self, now_s: float | None = None) -> float:
        """Service time: ``now_s`` or the clock, never decreasing.

        A clock that jumps backwards (a badly set system clock, a restarted time source) would
        blind every timeout and stop the cyclic frames; the service time then continues from
        where it was and advances with the clock from there (the jump is reported once).
        """
        raw = self.clock() if now_s is None else float(now_s)
        if not math.isfinite(raw):
            raise ValueError(f"now_s must be finite, got {raw!r}")
        t = raw + self._clock_shift
        last = self._t_now
        if last is not None and t < last:
            self._clock_shift += last - t
            self._event(last, EventKind.CLOCK_WENT_BACK,
                        f"clock went back by {last - t:.3f} s: service time continues")
            t = last
        self._t_now = t
        return t

    def _describe(self, missing: Sequence[str]) -> str:
        parts = []
        for m in missing:
            text = _REASONS.get(m, f"{m} gone")
            if m == "plc_data" and self._plc_problem:
                text += f" ({self._plc_problem})"
            if m == "amplifier" and self._amp_problem:
                text += f" ({self._amp_problem})"
            parts.append(text)
        return ", ".join(parts) or "start"

    def measurer(self, shape: tuple[int, int]) -> Any:
        """The measurer for images of ``shape`` (built once per shape)."""
        m = self._measurers.get(shape)
        if m is None:
            m = self._measurer_factory(shape)
            self._measurers[shape] = m
        return m

    @property
    def state(self) -> SafetyState:
        """The supervisor's state."""
        return self.supervisor.state

    def _ensure_loops(self, snap: PlcSnapshot) -> None:
        """Build (or rebuild when the machine's geometry or limits change) the control loops."""
        from controller.feed_loop import FeedLoop, FeedLoopConfig

        key = (
            snap.knives,
            round(snap.feed_min_mm_s, 3),
            round(snap.feed_max_mm_s, 3),
            round(float(snap["cutterhead_radius_mm"]), 3),
            round(snap.cutter_to_camera_mm, 3),
        )
        if key == self._loop_key:
            return
        q = self.cfg.quality
        cam = self.rig.camera
        window_mm = 2.0 * cam.cx / cam.px_per_mm
        overrides: dict[str, Any] = {
            "target_pitch_mm": q.target_pitch_mm,
            "depth_max_um": q.depth_max_um,
            "knives": snap.knives,
            "radius_mm": float(snap["cutterhead_radius_mm"]),
            "feed_min_mm_s": snap.feed_min_mm_s,
            "feed_max_mm_s": snap.feed_max_mm_s,
            "cutter_to_camera_mm": snap.cutter_to_camera_mm,
            "window_mm": window_mm,
        }
        fl_map = dict(self.cfg.feed_loop)
        fl_map.setdefault("sample_time_s", 1.0 / self.pairs_per_s)
        accel = float(snap.values.get("feed_accel_max_mm_s2", 0.0) or 0.0)
        if accel > 0 and "rate_max_mm_s2" in fl_map:
            fl_map["rate_max_mm_s2"] = min(float(fl_map["rate_max_mm_s2"]), accel)
        fcfg = FeedLoopConfig.from_mapping(fl_map, **overrides)
        self.feed_loop = FeedLoop(fcfg)
        lo, hi = snap.feed_min_mm_s, snap.feed_max_mm_s
        self.feed_loop.reset(feed_mm_s=min(max(snap.feed_setpoint_mm_s, lo), hi))
        self.uniformity_loop = _make_uniformity_loop(self.cfg, snap)
        self._learned_offsets = np.zeros(snap.knives)
        if self.piezo.knives != snap.knives:
            self.piezo.set_knives(snap.knives)
        self.offsets_um = (0.0,) * snap.knives
        self._loop_key = key

    # ------------------------------------------------------------------ the control cycles
    async def tick(self, now_s: float | None = None) -> SafetyStatus:
        """One control cycle of both buses, in order (simulated time, the in-process HIL).

        The PLC's heartbeat and register read (:meth:`plc_cycle`'s I/O), then the CAN cycle
        (:meth:`can_cycle`: the amplifier's frames, the supervisor, enable or zero offsets,
        ``PIEZO_COMMAND``), then the PLC's actions (feed-forward in RUN, hold or ramp in SAFE).
        :meth:`run` calls the two cycles from separate tasks instead, so a PLC that does not
        answer never holds up the CAN heartbeat.

        Never raises for what the world does (buses gone, garbage registers) nor for the
        service's own unexpected errors: those are reported as events, put the machine in the
        safe state (offsets 0, amplifier disabled) and the heartbeats go on.

        Parameters
        ----------
        now_s : float, optional
            Service time; default ``clock()``.

        Returns
        -------
        SafetyStatus
            The supervisor's decision of this cycle.
        """
        t = self._now(now_s)
        try:
            snap = await self._plc_io(t)
        except Exception as exc:  # noqa: BLE001 - a bug must not stop the heartbeats
            self._internal_error(t, "PLC cycle", exc, part="plc")
            return self._can_cycle_guarded(t)
        status = self._can_cycle_guarded(t)
        try:
            await self._plc_actions(t, snap)
        except Exception as exc:  # noqa: BLE001
            return self._internal_error(t, "PLC cycle", exc, part="plc")
        self._clean("plc")
        return status

    async def plc_cycle(self, now_s: float | None = None) -> None:
        """The PLC's cycle (its own task in :meth:`run`): heartbeat, read, supervisor, feed.

        Writes the heartbeat register, reads every register (one request), checks them, steps
        the supervisor and, in RUN, lets the feed-forward follow the spindle; in SAFE it holds
        or ramps the feed down. Only the PLC's bus is touched here (offsets are zeroed by the
        supervisor's state change, a non-blocking CAN send). Never raises.
        """
        t = self._now(now_s)
        try:
            snap = await self._plc_io(t)
            self._step_supervisor(t)
            await self._plc_actions(t, snap)
        except Exception as exc:  # noqa: BLE001 - a bug must not stop the heartbeats
            self._internal_error(t, "PLC cycle", exc, part="plc")
            return
        self._clean("plc")

    def can_cycle(self, now_s: float | None = None) -> SafetyStatus:
        """The CAN cycle (its own task in :meth:`run`): never waits for anything.

        Drains the amplifier's frames (non-blocking), judges its status, steps the supervisor,
        enables the amplifier in RUN or sends zero offsets and a disable in SAFE, and sends
        ``PIEZO_COMMAND`` with a new alive counter. Never raises.

        Returns
        -------
        SafetyStatus
            The supervisor's decision of this cycle.
        """
        return self._can_cycle_guarded(self._now(now_s))

    def _can_cycle_guarded(self, t: float) -> SafetyStatus:
        try:
            status = self._can_cycle(t)
        except Exception as exc:  # noqa: BLE001 - a bug must not stop the heartbeats
            return self._internal_error(t, "CAN cycle", exc, part="can")
        self._clean("can")
        return status

    async def _plc_io(self, t: float) -> PlcSnapshot | None:
        """Heartbeat and one read of every register; the snapshot if it makes sense."""
        self.heartbeat = (self.heartbeat + 1) & 0xFFFF
        sup = self.supervisor
        snap: PlcSnapshot | None = None
        try:
            await self.plc.write_heartbeat(self.heartbeat)
            snap = await self.plc.read()
        except FieldbusError:
            self.counters["plc_errors"] += 1
        if snap is not None:
            sup.plc_answered(t)  # a read answered: refusals and bare writes do not count
            self._snap_t = t
            snap = self._check_snapshot(snap, t)
        if snap is not None:
            self._ensure_loops(snap)
            sup.machine_ok(not snap.estop and snap.spindle_running)
            if not snap.board_present:
                sup.measurement_not_expected(t)
        return snap

    async def _plc_actions(self, t: float, snap: PlcSnapshot | None) -> None:
        """The feed in the supervisor's state: feed-forward (RUN) or hold / ramp down (SAFE)."""
        last = self._last_plc_actions_s
        dt = 0.0 if last is None else max(0.0, t - last)
        self._last_plc_actions_s = t
        if self.supervisor.state is SafetyState.SAFE:
            await self._safe_actions(t, dt, snap)
        elif snap is not None and self.feed_loop is not None:
            await self._feed_forward(t, snap)

    def _can_cycle(self, t: float) -> SafetyStatus:
        try:
            self.piezo.poll(now_s=t)
        except FieldbusError:
            self.counters["can_errors"] += 1
        if self.piezo.last_heard_s is not None:
            self.supervisor.can_heard(self.piezo.last_heard_s)
        self._observe_amplifier(t)
        status = self._step_supervisor(t)
        if status.state is SafetyState.SAFE:
            try:
                self._zero_offsets(t)
            except FieldbusError:
                self.counters["can_errors"] += 1
        else:
            self.piezo.set_enable(True, now_s=t)
        self._send_piezo_command(t)
        return status

    def _observe_amplifier(self, t: float) -> None:
        """Judge the amplifier's last status; a confirmed problem fails the condition."""
        problem = self.amp_monitor.observe(self.piezo.status, now_s=t)
        if problem is not None and self._amp_problem is None:
            self.counters["amp_faults"] += 1
            self._event(t, EventKind.AMPLIFIER_PROBLEM, f"piezo amplifier: {problem}")
        elif problem is None and self._amp_problem is not None:
            self._event(t, EventKind.AMPLIFIER_HEALTHY, "piezo amplifier healthy again")
        self._amp_problem = problem
        self.supervisor.set_ok("amplifier", problem is None)

    def _clean(self, part: str) -> None:
        """A cycle of ``part`` ran without an unexpected error (clears it and a pair's)."""
        self._faulty.discard(part)
        self._faulty.discard("pair")
        self.supervisor.set_ok("service", not self._faulty)

    def _check_snapshot(self, snap: PlcSnapshot, t: float) -> PlcSnapshot | None:
        """``snap`` if its registers make sense, else ``None`` (reported, supervisor told)."""
        problem = snap.problem()
        if problem != self._plc_problem:
            if problem is not None:
                self._event(t, EventKind.PLC_DATA_INVALID, f"PLC data invalid: {problem}")
            elif self._plc_problem is not None:
                self._event(t, EventKind.PLC_DATA_VALID, "PLC data valid again")
        self._plc_problem = problem
        self.supervisor.set_ok("plc_data", problem is None)
        return snap if problem is None else None

    def _step_supervisor(self, t: float) -> SafetyStatus:
        status = self.supervisor.step(t)
        self.status = status
        if status.changed:
            if status.state is SafetyState.SAFE:
                self.counters["safe_entries"] += 1
                self._event(t, EventKind.SAFE_STATE,
                            f"safe state: {self._describe(status.missing)}")
                try:  # at once, whichever cycle noticed (a non-blocking CAN send)
                    self._zero_offsets(t)
                except FieldbusError:
                    self.counters["can_errors"] += 1
            else:
                self.counters["recoveries"] += 1
                self._event(t, EventKind.RECOVERED, "recovered: control resumed")
                self._resume(t)
        return status

    def _send_piezo_command(self, t: float) -> None:
        """``PIEZO_COMMAND`` with a new alive counter (the amplifier's setpoint timeout)."""
        self.amp_monitor.commanded(self.piezo.enable, now_s=t)
        self.alive = (self.alive + 1) & 0xFF
        try:
            self.piezo.tick(alive_counter=self.alive, now_s=t)
        except FieldbusError:
            self.counters["can_errors"] += 1

    def _internal_error(
        self, t: float, where: str, exc: BaseException, *, part: str = "pair"
    ) -> SafetyStatus:
        """An unexpected error of the service's own code: report it, go safe, keep the beat.

        ``part`` (``"plc"``, ``"can"``, ``"pair"``) is cleared by the next clean cycle of that
        part (a pair's error by any clean cycle); until then the ``service`` condition fails.
        """
        self.counters["errors"] += 1
        self._faulty.add(part)
        self.supervisor.set_ok("service", False)
        text = f"service error in {where}: {_exc_name(exc)}: {exc}"
        if text != self._last_error:  # the same error every cycle is reported once
            self._event(t, EventKind.SERVICE_ERROR, text)
            self._last_error = text
        try:
            status = self._step_supervisor(t)
        except Exception:  # noqa: BLE001 - the supervisor itself failed: safe regardless
            status = SafetyStatus(SafetyState.SAFE, ("service",), False, t)
        try:
            self._zero_offsets(t)
        except Exception as exc2:  # noqa: BLE001
            self.counters["can_errors"] += 1
            self._event(t, EventKind.OFFSETS_NOT_ZEROED,
                        f"piezo offsets could not be zeroed: {_exc_name(exc2)}: {exc2}")
        try:
            self._send_piezo_command(t)
        except Exception:  # noqa: BLE001 - the amplifier's own timeout ramps to zero
            self.counters["can_errors"] += 1
        return status

    def _zero_offsets(self, t: float) -> None:
        """Disable the amplifier and send zero offsets (the safe piezo state)."""
        if not self.piezo.knives:
            return
        self.piezo.set_enable(False, now_s=t)
        self.offsets_um = self.piezo.set_offsets(
            self.supervisor.safe_offsets_um(self.piezo.knives), now_s=t
        )

    async def _safe_actions(self, t: float, dt: float, snap: PlcSnapshot | None) -> None:
        if snap is None:
            return  # PLC gone or talking nonsense: no feed write; its watchdog and limits act
        current = snap.feed_setpoint_mm_s
        lo, hi = snap.feed_min_mm_s, snap.feed_max_mm_s
        target = self.supervisor.safe_feed(current, dt_s=dt, feed_min_mm_s=lo, feed_max_mm_s=hi)
        if abs(target - current) > 1e-3:
            await self._write_feed(target, t)
        else:
            self.feed_setpoint_mm_s = current

    def _loop_time(self, t: float) -> float:
        """Time for the control loops: never earlier than their last call.

        In real time the cycles and the frame task interleave at awaits, so a time read before
        an await may be older than one another task already used.
        """
        t = max(t, self._t_loops)
        self._t_loops = t
        return t

    async def _feed_forward(self, t: float, snap: PlcSnapshot) -> None:
        """Between measurements the feed loop's feed-forward follows the spindle speed.

        No measurement enters here (the learnt correction is held); the setpoint is written only
        when it moved by more than ``FEED_WRITE_DEADBAND_MM_S`` (e.g. ramping back after a
        recovery), so spindle ripple does not flood the bus. A setpoint not written (deadband,
        refused, failed) is taken back from the loop's history: it learns against the feed
        that really was in force.
        """
        async with self._feed_lock():
            loop = self.feed_loop
            feed = loop.update(
                measured_pitch_mm=None, spindle_rpm=snap.spindle_rpm, now_s=self._loop_time(t)
            )
            feed = min(max(float(feed), snap.feed_min_mm_s), snap.feed_max_mm_s)
            current = self.feed_setpoint_mm_s
            if current is None:
                current = snap.feed_setpoint_mm_s
            if abs(feed - current) <= FEED_WRITE_DEADBAND_MM_S or not await self._write_feed(
                feed, t
            ):
                loop.reject()

    def _feed_lock(self) -> asyncio.Lock:
        """Held from a feed loop update to the end of its write (and its reject).

        In real time the PLC cycle's feed-forward and a pair's update interleave at the write's
        await; the lock keeps each setpoint's update, write and reject together, so a reject
        always takes back its own setpoint.
        """
        loop = asyncio.get_running_loop()
        if self._feed_lock_obj is None or self._feed_lock_loop is not loop:
            self._feed_lock_obj = asyncio.Lock()
            self._feed_lock_loop = loop
        return self._feed_lock_obj

    async def _write_feed(self, feed: float, t: float) -> bool:
        """Write the feed setpoint; whether the PLC took it (a refusal is reported once)."""
        try:
            await self.plc.write_feed(feed)
        except ModbusRefused as exc:
            self._feed_not_taken(t, f"feed setpoint refused: {exc}")
            return False
        except FieldbusError:
            self.counters["plc_errors"] += 1
            return False
        except ValueError as exc:  # outside the limits the PLC reported: never sent
            self._feed_not_taken(t, f"feed setpoint not sent: {exc}")
            return False
        if self._feed_refused:
            self._feed_refused = False
            self._event(t, EventKind.FEED_ACCEPTED, "feed setpoint accepted again")
        self.feed_setpoint_mm_s = feed
        return True

    def _feed_not_taken(self, t: float, text: str) -> None:
        self.counters["setpoint_refused"] += 1
        if not self._feed_refused:  # once until a write goes through again
            self._feed_refused = True
            self._event(t, EventKind.FEED_REFUSED, text)

    def _resume(self, t: float) -> None:
        """Back to RUN: restart the feed loop from the feed in force, restore learnt offsets."""
        t = self._loop_time(t)
        snap = self.plc.last
        if snap is not None and snap.problem() is None and self.feed_loop is not None:
            lo, hi = snap.feed_min_mm_s, snap.feed_max_mm_s
            feed = min(max(snap.feed_setpoint_mm_s, lo), hi)
            self.feed_loop.reset(feed_mm_s=feed, now_s=t, correction=self.feed_loop.correction)
            self.feed_setpoint_mm_s = feed
        self.piezo.set_enable(True, now_s=t)
        if self._learned_offsets is not None and len(self._learned_offsets) == self.piezo.knives:
            try:
                self.offsets_um = self.piezo.set_offsets(self._learned_offsets, now_s=t)
                if self.uniformity_loop is not None:
                    self.uniformity_loop.reset(self._learned_offsets, now_s=t)
            except FieldbusError:
                self.counters["can_errors"] += 1

    # ------------------------------------------------------------------ one image pair
    async def _call(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        if self.threaded:
            return await asyncio.to_thread(fn, *args, **kwargs)
        return fn(*args, **kwargs)

    async def handle_frame(self, frame: Frame, *, now_s: float | None = None) -> FrameResult:
        """Measure one pair, control, write setpoints, log it.

        Every pair gets exactly one quality record, whatever happens: a pair that cannot be
        measured (unreadable, registration failed, any exception of the vision, implausible
        result, no valid PLC data) changes no setpoint and is logged with ``ok = false`` and
        the reason; an unexpected error of the control code puts the machine in the safe state.

        Parameters
        ----------
        frame : Frame
            The image pair with its latched counts.
        now_s : float, optional
            Service time of the pair's arrival; default ``clock()``.

        Returns
        -------
        FrameResult
        """
        wall0 = time.perf_counter()
        t_arr = self._now(now_s)
        self.counters["frames"] += 1
        measured_at = self._machine_to_service(frame, t_arr)
        snap = await self._snapshot_for(t_arr)
        wall_plc = time.perf_counter()
        wall_meas = wall_plc
        error: str | None = None
        meas: Any = None
        att: Attributed | None = None
        if frame.error:
            error = f"unreadable pair: {frame.error}"
        elif snap is None:
            error = "no PLC data: registers never read"
        elif (problem := snap.problem()) is not None:
            error = f"no valid PLC data: {problem}"
        else:
            error, meas, att = await self._measure(frame, snap)
            wall_meas = time.perf_counter()
        ok = error is None
        applied = False
        profile = None
        if ok:
            self.counters["ok"] += 1
            profile = self._profile_of(meas, frame)
            self.supervisor.measurement_valid(t_arr)
            if self.supervisor.state is SafetyState.RUN and snap is not None:
                t_ctrl = self._now() if now_s is None else t_arr  # loops need forward time
                try:
                    applied = await self._apply(att, measured_at, snap, t_ctrl)
                except Exception as exc:  # noqa: BLE001 - a bug: safe state, pair still logged
                    self._internal_error(t_ctrl, f"control of pair {frame.seq}", exc)
        else:
            self.counters["failed"] += 1
        wall1 = time.perf_counter()
        latency_s = wall1 - wall0
        timing = {
            "plc_read_ms": (wall_plc - wall0) * 1e3,
            "measure_ms": (wall_meas - wall_plc) * 1e3,
            "control_ms": (wall1 - wall_meas) * 1e3,
        }
        result = FrameResult(
            seq=frame.seq,
            ok=ok,
            error=error,
            measurement=meas,
            knife_widths_mm=() if att is None else tuple(float(w) for w in att.knife_widths_mm),
            applied=applied,
            feed_setpoint_mm_s=self.feed_setpoint_mm_s,
            offsets_um=tuple(self.offsets_um),
            state=self.supervisor.state.value,
            t_s=t_arr,
            latency_s=latency_s,
            truth=frame.truth,
            counts_a=_int_or(frame.counts_a, 0),
            frame_t_s=_opt(frame.t_s) or 0.0,
            extra={
                "timing_ms": timing,
                "safe_reason": self._safe_reason(),
                **({"passes": att.to_json()} if att is not None else {}),
                **({"profile": profile} if profile is not None else {}),
            },
        )
        rid = await self._log(result, frame, t_arr)
        if rid is not None:
            result = _with(result, record_id=rid)
        if self.keep_results:
            self.results.append(result)
        if self.on_result is not None:
            self.on_result(result)
        return result

    def _profile_of(self, meas: Any, frame: Frame) -> dict[str, list[float]] | None:
        """The decimated profile of a successful measurement if this one carries it.

        The first successful measurement of each board and every ``PROFILE_EVERY``-th one
        (counted over the run) do; ``None`` for the others or without a usable profile.
        """
        self._ok_count += 1
        board = _int_or(getattr(frame, "board_id", 0), 0)
        first_of_board = board != self._profile_board
        self._profile_board = board
        if not (first_of_board or (self._ok_count - 1) % PROFILE_EVERY == 0):
            return None
        try:
            return decimated_profile(meas.x_mm, meas.height_um)
        except (AttributeError, TypeError, ValueError):
            return None

    def _safe_reason(self) -> str | None:
        """Why the service is in the safe state now (``None`` in RUN)."""
        if self.supervisor.state is not SafetyState.SAFE:
            return None
        missing = self.status.missing if self.status is not None else ()
        return self._describe(missing) if missing else "confirming recovery"

    def _machine_to_service(self, frame: Frame, t_arr: float) -> float:
        """Service time of the pair's trigger A (its machine time mapped onto the service clock).

        The offset is the lowest arrival delay seen (exact in simulated time). When the camera's
        clock goes backwards (a restarted camera or simulator) the mapping starts afresh;
        otherwise every later pair would look ages old and the feed loop would never learn
        again.
        """
        self._note_seq(frame, t_arr)
        ft = _opt(frame.t_s)
        if ft is None:
            return t_arr
        if self._last_frame_t is not None and ft < self._last_frame_t:
            self._machine_offset_s = None
            self._event(t_arr, EventKind.CAMERA_CLOCK_WENT_BACK,
                        f"camera clock went back by {self._last_frame_t - ft:.3f} s")
        self._last_frame_t = ft
        off = t_arr - ft
        if self._machine_offset_s is None or off < self._machine_offset_s:
            self._machine_offset_s = off
        return min(ft + self._machine_offset_s, t_arr)

    def _note_seq(self, frame: Frame, t: float) -> None:
        """Report pairs that never reached the service (a gap in the camera's sequence)."""
        try:
            seq = int(frame.seq)
        except (TypeError, ValueError):
            return
        last, self._last_seq = self._last_seq, seq
        if last is not None and seq > last + 1:
            n = seq - last - 1
            self.counters["missed"] += n
            self._event(t, EventKind.PAIRS_MISSED,
                        f"{n} pair(s) never reached the service (seq {last + 1}..{seq - 1})")

    async def _snapshot_for(self, t: float) -> PlcSnapshot | None:
        """The tick's registers if at most two cycles old, else a fresh read (else the last)."""
        snap: PlcSnapshot | None = self.plc.last
        max_age = PLC_SNAPSHOT_MAX_AGE_CYCLES * self.cfg.safety.cycle_s
        if snap is None or t - self._snap_t > max_age:
            try:  # the tick's snapshot is stale (PLC slow or gone): ask now
                snap = await self.plc.read()
                self.supervisor.plc_answered(t)
                self._snap_t = t
            except FieldbusError:
                self.counters["plc_errors"] += 1
                snap = self.plc.last
        return snap

    async def _measure(
        self, frame: Frame, snap: PlcSnapshot
    ) -> tuple[str | None, Any, Attributed | None]:
        """Measure the pair, check it, attribute its marks: ``(error, measurement, attributed)``.

        Any exception of the vision (``cv2.error``, ``IndexError``, ``FloatingPointError``...)
        is a failed measurement, not a crash of the service. The order: basic plausibility
        (marks, confidence, machine running), attribution of the marks to knife passes, then
        the pitch per knife pass against ``V / (n Z)``.
        """
        try:
            self._ensure_loops(snap)
        except Exception as exc:  # noqa: BLE001 - the loops cannot be built from these registers
            return f"no control loops: {_exc_name(exc)}: {exc}", None, None
        try:
            meas = await self._call(
                self.measurer(tuple(np.shape(frame.image_a))).measure,
                frame.image_a,
                frame.image_b,
                counts_a=frame.counts_a,
                counts_b=frame.counts_b,
                speed_mm_s=frame.speed_mm_s if frame.speed_mm_s > 0 else None,
            )
        except Exception as exc:  # noqa: BLE001 - whatever the vision raises
            return _reason(exc), None, None
        try:
            error = self._implausible(meas, frame, snap)
        except Exception as exc:  # noqa: BLE001 - a measurement without the expected fields
            error = f"implausible: {_exc_name(exc)}: {exc}"
        if error is not None:
            return error, meas, None
        try:
            att = self._attribute(meas, frame, snap)
        except Exception as exc:  # noqa: BLE001
            text = str(exc) if isinstance(exc, ValueError) else f"{_exc_name(exc)}: {exc}"
            return f"knife phase failed: {text}", meas, None
        error = self._implausible_pitch(att.pass_pitch_mm, frame, snap)
        return error, meas, (att if error is None else None)

    def _expected_pitch_mm(self, frame: Frame, snap: PlcSnapshot) -> float:
        """Board travel per knife pass from the encoder speed and the spindle, ``V / (n Z)``."""
        speed = frame.speed_mm_s if frame.speed_mm_s > 0 else snap.feed_actual_mm_s
        return speed / (snap.spindle_rpm / 60.0 * snap.knives)

    def _implausible_pitch(self, pitch: float, frame: Frame, snap: PlcSnapshot) -> str | None:
        """The pitch per knife pass against ``V / (n Z)`` (``None`` if within the ratios)."""
        pl = self.cfg.plausibility
        expected = self._expected_pitch_mm(frame, snap)
        ratio = pitch / expected
        if not pl.pitch_ratio_min <= ratio <= pl.pitch_ratio_max:
            return (
                f"implausible: pitch {pitch:.3f} mm vs {expected:.3f} mm expected from "
                f"V/(nZ) (ratio {ratio:.2f})"
            )
        return None

    def _implausible(self, meas: Any, frame: Frame, snap: PlcSnapshot) -> str | None:
        """Basic plausibility: a pitch, enough marks, confidence, spindle and feed running."""
        pl = self.cfg.plausibility
        pitch = float(getattr(meas, "pitch_mm", math.nan))
        widths = np.asarray(getattr(meas, "mark_widths_mm", ()), dtype=float)
        conf = getattr(meas, "confidence", None)
        if not math.isfinite(pitch) or pitch <= 0:
            return f"implausible: pitch {pitch}"
        if widths.size < pl.min_marks:
            return f"implausible: {widths.size} complete marks, need {pl.min_marks}"
        if conf is not None and float(conf) < pl.min_confidence:
            return f"implausible: confidence {float(conf):.2f} < {pl.min_confidence}"
        n_rev_s = snap.spindle_rpm / 60.0
        speed = frame.speed_mm_s if frame.speed_mm_s > 0 else snap.feed_actual_mm_s
        if n_rev_s <= 0 or speed <= 0:
            return "implausible: spindle or feed stopped"
        return None

    def _attribute(self, meas: Any, frame: Frame, snap: PlcSnapshot) -> Attributed:
        """Attribute the marks to knife passes: widths per knife, pitch per knife pass.

        The phase and the travel per pass come from the bottoms that lie inside their marks
        (:func:`controller.knife_phase.attribute_marks`, guided by ``V / (n Z)``); a narrow mark
        whose bottom sits on its cusp and a knife that left no mark do not spoil them.

        Raises
        ------
        ValueError
            The marks do not line up with the knife passes (phase spread too large, two marks
            on one pass, too few bottoms inside their marks).
        """
        from controller import knife_phase

        cam = self.rig.camera
        bottoms = np.asarray(meas.bottoms_mm, dtype=float)
        widths = np.asarray(meas.mark_widths_mm, dtype=float)
        if bottoms.shape != widths.shape:
            raise ValueError(f"{bottoms.size} mark bottoms for {widths.size} widths")
        cusps = getattr(meas, "cusps_mm", None)
        if cusps is not None:
            cusps = np.asarray(cusps, dtype=float)
            if cusps.shape != (widths.size + 1,):
                cusps = None  # not the cusps of these marks: every bottom counts
        pa = knife_phase.attribute_marks(
            bottoms,
            cusps,
            counts_a=int(frame.counts_a),
            index_latch_counts=int(frame.index_latch_counts),
            cutter_to_camera_mm=snap.cutter_to_camera_mm,
            counts_per_mm=snap.counts_per_mm,
            px_per_mm=cam.px_per_mm,
            cx_px=cam.cx,
            pass_guide_mm=self._expected_pitch_mm(frame, snap),
            knives=snap.knives,
            min_inset_mm=MIN_BOTTOM_INSET_SAMPLES / cam.px_per_mm,
            counter_bits=self.rig.encoder.counter_bits,
        )
        if not pa.spread <= MAX_PHASE_SPREAD:
            raise ValueError(f"marks off the knife passes (phase spread {pa.spread:.2f})")
        if pa.missing == 0:
            pitch = float(meas.pitch_mm)  # the mean mark width, as measured
        else:
            pitch = float(widths.sum()) / pa.n_passes
        return Attributed(
            knife_widths_mm=pa.knife_widths(widths),
            pass_pitch_mm=pitch,
            missing_passes=pa.missing,
            spread=float(pa.spread),
            reliable_marks=int(pa.reliable.sum()),
        )

    async def _apply(
        self, att: Attributed | None, measured_at: float, snap: PlcSnapshot, t: float
    ) -> bool:
        """Both loops on one valid measurement; the offsets (CAN) go out first, then the feed.

        Both get the pitch per knife pass (:attr:`Attributed.pass_pitch_mm`), not the mean mark
        width: with a knife that leaves no mark the latter is a multiple of the feed per knife,
        and slowing the feed would not bring the mark back (the uniformity loop does).

        The uniformity loop learns only from board cut while the amplifier played the offsets
        (:meth:`_amp_tracked`); a feed setpoint the PLC did not take is taken back from the feed
        loop's history (:meth:`FeedLoop.reject`).
        """
        if att is None:
            return False
        lo, hi = snap.feed_min_mm_s, snap.feed_max_mm_s
        pitch = float(att.pass_pitch_mm)
        widths = att.knife_widths_mm
        applied = False
        async with self._feed_lock():
            t = self._loop_time(t)
            measured_at = min(measured_at, t)
            loop = self.feed_loop
            feed = loop.update(
                measured_pitch_mm=pitch,
                spindle_rpm=snap.spindle_rpm,
                now_s=t,
                measured_at_s=measured_at,
            )
            feed = min(max(float(feed), lo), hi)
            if np.any(np.isfinite(widths)):
                interval = loop.cut_interval_s(measured_at)
                cut_at = None if interval is None else min(interval[0], t)
                applied = self._learn_offsets(widths, pitch, cut_at, t)
            if await self._write_feed(feed, t):
                applied = True
            else:
                loop.reject()
        if applied:
            self.counters["applied"] += 1
        return applied

    def _learn_offsets(
        self, widths: np.ndarray, pitch: float, cut_at: float | None, t: float
    ) -> bool:
        """One uniformity-loop update and its offsets on CAN; whether they were sent."""
        if not self._amp_tracked(cut_at, t):
            self.counters["uniformity_skipped"] += 1
            return False
        offs = self.uniformity_loop.update(
            knife_widths_mm=widths, pitch_mm=pitch, now_s=t, cut_at_s=cut_at
        )
        s = self.cfg.stroke_um
        try:
            self.offsets_um = self.piezo.set_offsets(
                np.clip(np.asarray(offs, dtype=float), -s, s), now_s=t
            )
        except FieldbusError as exc:
            self.counters["can_errors"] += 1
            self._event(t, EventKind.OFFSETS_NOT_SENT, f"piezo offsets not sent: {exc}")
            return False
        self._learned_offsets = np.asarray(self.offsets_um, dtype=float)
        return True

    def _amp_tracked(self, cut_at_s: float | None, t: float) -> bool:
        """Whether the board a measurement shows was cut while the amplifier played the offsets.

        The amplifier was last seen not tracking (disabled, ramping, faulted, refusing the
        table, or an enable not yet confirmed) at ``untracked_s``; board cut before that plus
        the offsets' settling time shows offsets that were not applied. Without a cut time
        (the feed loop's history is too short) the uniformity loop's hold-off is used instead.
        """
        last = self.amp_monitor.untracked_s
        if last is None:
            return True
        ucfg = self.uniformity_loop.cfg
        if cut_at_s is None:
            return t - ucfg.holdoff_s > last
        return cut_at_s - ucfg.settle_s > last

    def _record(self, r: FrameResult, frame: Frame) -> Any:
        """The quality record of a result (never raises: odd metadata is noted, not fatal)."""
        from controller.quality_log import QualityRecord, judge, utc_iso

        m = r.measurement
        truth = frame.truth or {}
        meta, odd = _frame_metadata(frame)
        fields: dict[str, Any] = {
            **meta,
            "wall_time": utc_iso(time.time()),
            "ok": r.ok,
            "error": r.error,
            "feed_setpoint_mm_s": r.feed_setpoint_mm_s,
            "piezo_offsets_um": tuple(r.offsets_um),
            "target_pitch_mm": self.cfg.quality.target_pitch_mm,
            "true_pitch_mm": _opt(truth.get("pitch_mm")),
            "true_uniformity_cv": _opt(truth.get("uniformity_cv")),
            "extra": {
                "state": r.state,
                "safe_reason": r.extra.get("safe_reason"),
                "applied": r.applied,
                "latency_ms": r.latency_s * 1e3,
                "timing_ms": r.extra.get("timing_ms", {}),
                "knife_widths_mm": [None if not math.isfinite(w) else w
                                    for w in r.knife_widths_mm],
                **({"frame_metadata_invalid": odd} if odd else {}),
                **({"passes": r.extra["passes"]} if "passes" in r.extra else {}),
                **({"profile": r.extra["profile"]} if "profile" in r.extra else {}),
            },
        }
        if m is not None:
            fields["shift_px"] = _opt(getattr(m, "shift_px", None))
            fields["confidence"] = _opt(getattr(m, "confidence", None))
        if r.ok:
            fields.update(
                pitch_mm=_opt(getattr(m, "pitch_mm", None)),
                mark_widths_mm=tuple(float(w) for w in r.knife_widths_mm),
                uniformity_cv=_opt(getattr(m, "uniformity_cv", None)),
                depth_um=_opt(getattr(m, "depth_um", None)),
            )
            try:
                fields["extra"]["marks_mm"] = [float(w) for w in m.mark_widths_mm]
                fields["passed"] = judge(fields, self.quality_class)
            except (TypeError, ValueError):
                fields["passed"] = None
        try:
            return QualityRecord(**fields)
        except (TypeError, ValueError) as exc:  # keep the pair: a record that says why
            return QualityRecord(
                **meta,
                wall_time=fields["wall_time"],
                ok=False,
                error=f"record invalid: {exc}" if r.ok else f"{r.error} (record invalid: {exc})",
                extra={"state": r.state, "safe_reason": r.extra.get("safe_reason"),
                       "applied": r.applied},
            )

    async def _log(self, r: FrameResult, frame: Frame, t: float) -> int | None:
        """Append the pair's record (after any held back); its id, or ``None`` if held back."""
        if self.log is None:
            return None
        self._pending.append(self._record(r, frame))
        return await self._flush_log(t)

    async def _flush_log(self, t: float) -> int | None:
        """Write the held records in order; return the id of the last one if all went in.

        While the log cannot be written (disk full, file locked) the records stay in memory, in
        order, the supervisor's ``log`` condition fails (safe state: no control without a
        record of it) and the failure is reported; they are written as soon as the log takes
        them again. Beyond ``MAX_PENDING_RECORDS`` the oldest are saved beside the log.
        """
        rid: int | None = None
        while self._pending:
            rec = self._pending[0]
            try:
                rid = int(await self._call(self.log.append, rec))
            except OSError as exc:
                self.counters["log_errors"] += 1
                if not self._log_failing:
                    self._log_failing = True
                    self.supervisor.set_ok("log", False)
                    self._event(t, EventKind.LOG_FAILED,
                                f"quality log write failed: {exc}; records held in memory")
                if len(self._pending) > MAX_PENDING_RECORDS:
                    n = len(self._pending) - MAX_PENDING_RECORDS // 2
                    self._spill([self._pending.popleft() for _ in range(n)], t)
                return None
            except ValueError as exc:  # this record can never go in (log closed, bad record)
                self.counters["log_errors"] += 1
                self._event(t, EventKind.LOG_REFUSED_RECORD,
                            f"quality record of pair {rec.seq} refused by the log: {exc}")
                self._spill([self._pending.popleft()], t)
                continue
            self._pending.popleft()
        if self._log_failing:
            self._log_failing = False
            self.supervisor.set_ok("log", True)
            self._event(t, EventKind.LOG_RECOVERED,
                        "quality log writable again: held records written")
        return rid

    def _spill(self, records: Sequence[Any], t: float) -> None:
        """Save records the log cannot take as JSON lines beside it (never silently dropped)."""
        from controller.quality_log import record_to_json, utc_iso
        from core.fileio import atomic_write_text

        if not records:
            return
        base = Path(getattr(self.log, "path", None) or self.cfg.log.path)
        stamp = utc_iso(time.time()).replace(":", "").replace("+0000", "Z")
        path = base.with_name(f"{base.name}.unlogged-{stamp}-{records[0].seq}.jsonl")
        try:
            atomic_write_text(path, "".join(record_to_json(r) + "\n" for r in records))
        except (OSError, ValueError) as exc:
            self._event(t, EventKind.RECORDS_LOST,
                        f"{len(records)} quality records LOST (NOT in the quality log, "
                           f"cannot be saved to {path}: {exc})")
            return
        self._event(t, EventKind.RECORDS_SAVED,
                    f"{len(records)} quality records NOT in the quality log: saved to {path}")

    # ------------------------------------------------------------------ real time
    async def run(
        self,
        source: Any,
        *,
        stop: asyncio.Event | None = None,
        max_frames: int | None = None,
    ) -> None:
        """Run in real time until ``stop`` is set (or ``max_frames`` pairs were handled).

        One owner per bus, no coupling: a PLC task calls :meth:`plc_cycle` every
        ``safety.cycle_s`` and a CAN task :meth:`can_cycle` every ``can.command_period_s`` (at
        most ``safety.cycle_s``), each on its own schedule, so a Modbus connect or request
        that takes its full timeout never delays ``PIEZO_COMMAND`` (the amplifier's setpoint
        timeout is 100 ms). The frame task awaits ``source.next()`` and calls
        :meth:`handle_frame`; the measurement runs in a worker thread. Requests to the PLC from
        the PLC task and the frame task go through the one client, one at a time.
        """
        stop = stop or asyncio.Event()
        plc_period = self.cfg.safety.cycle_s
        can_period = min(self.cfg.can.command_period_s, plc_period)

        async def periodic(period: float, cycle: Callable[[], Any]) -> None:
            loop = asyncio.get_running_loop()
            nxt = loop.time()
            while not stop.is_set():
                out = cycle()
                if asyncio.iscoroutine(out):
                    await out
                nxt += period
                delay = nxt - loop.time()
                if delay < -period:  # fell behind: skip, do not burst
                    nxt = loop.time()
                    delay = 0.0
                await asyncio.sleep(max(0.0, delay))

        async def frames() -> None:
            n = 0
            while not stop.is_set():
                try:
                    frame = await source.next(timeout_s=0.1)
                except Exception as exc:  # noqa: BLE001 - a broken source must not stop us
                    self.counters["errors"] += 1
                    text = f"frame source failed: {_exc_name(exc)}: {exc}"
                    if text != self._last_error:
                        self._last_error = text
                        self._event(self._now(), EventKind.FRAME_SOURCE_FAILED, text)
                    await asyncio.sleep(0.1)
                    continue
                if frame is None:
                    continue
                try:
                    await self.handle_frame(frame)
                except Exception as exc:  # noqa: BLE001 - handle_frame logs; this is a last resort
                    self._internal_error(self._now(), f"pair {frame.seq}", exc)
                n += 1
                if max_frames is not None and n >= max_frames:
                    stop.set()

        tasks = [
            asyncio.create_task(periodic(can_period, self.can_cycle)),
            asyncio.create_task(periodic(plc_period, self.plc_cycle)),
            asyncio.create_task(frames()),
        ]
        try:
            done, _ = await asyncio.wait(
                tasks + [asyncio.create_task(stop.wait())], return_when=asyncio.FIRST_COMPLETED
            )
            for d in done:
                if d in tasks and d.exception() is not None:
                    raise d.exception()  # type: ignore[misc]
        finally:
            stop.set()
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    def close(self) -> None:
        """Leave the amplifier disabled with zero offsets, write held records, close everything.

        Records the quality log still cannot take are saved beside it (JSON lines) and reported.
        """
        t = self._t_now if self._t_now is not None else 0.0
        if self.piezo is not None:
            try:
                self._zero_offsets(t)
                self.alive = (self.alive + 1) & 0xFF
                self.piezo.send_command(alive_counter=self.alive, now_s=t)
            except Exception as exc:  # noqa: BLE001 - closing must go on; the amplifier times out
                self._event(t, EventKind.CLOSE_PROBLEM,
                            f"amplifier not disabled at close: {_exc_name(exc)}: {exc}")
        if self.log is not None:
            while self._pending:  # a last attempt, then the rest beside the log
                try:
                    self.log.append(self._pending[0])
                except (OSError, ValueError):
                    break
                self._pending.popleft()
            self._spill(list(self._pending), t)
            self._pending.clear()
        if self.plc is not None:
            self.plc.close()
        if self.piezo is not None:
            self.piezo.close()
        if self.log is not None:
            self.log.close()


# ---------------------------------------------------------------------------------- helpers
def decimated_profile(
    x_mm: Any, height_um: Any, *, max_points: int = PROFILE_MAX_POINTS
) -> dict[str, list[float]] | None:
    """A profile small enough for every tenth quality record: samples, rounded.

    Parameters
    ----------
    x_mm, height_um : array_like, shape (n,)
        Positions along the feed (mm) and heights (um) of the measured profile.
    max_points : int
        Most samples kept (evenly spaced in index, the first and last always; samples, not
        averages, so the marks' cusps stay sharp).

    Returns
    -------
    dict or None
        ``{"x_mm": [...], "height_um": [...]}`` rounded to 0.001 mm and 0.1 um, or ``None``
        when fewer than two finite samples of equal-length 1-D arrays are given.
    """
    try:
        x = np.asarray(x_mm, dtype=float)
        h = np.asarray(height_um, dtype=float)
    except (TypeError, ValueError):
        return None
    if x.ndim != 1 or x.shape != h.shape:
        return None
    good = np.isfinite(x) & np.isfinite(h)
    x, h = x[good], h[good]
    if x.size < 2:
        return None
    if x.size > max_points:
        idx = np.unique(np.round(np.linspace(0, x.size - 1, max_points)).astype(int))
        x, h = x[idx], h[idx]
    return {
        "x_mm": [round(float(v), 3) for v in x],
        "height_um": [round(float(v), 1) for v in h],
    }


def _opt(v: Any) -> float | None:
    if v is None:
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _int_or(v: Any, default: int) -> int:
    try:
        return int(v)
    except (TypeError, ValueError, OverflowError):
        return default


def _exc_name(exc: BaseException) -> str:
    """``IndexError``, ``cv2.error``: the exception's type as a reader recognises it."""
    cls = type(exc)
    mod = cls.__module__
    return cls.__qualname__ if mod in ("builtins", "__main__") else f"{mod}.{cls.__qualname__}"


def _reason(exc: BaseException) -> str:
    """The logged reason of a measurement that raised ``exc``."""
    first = str(exc).splitlines()[0] if str(exc) else ""
    if isinstance(exc, RegistrationError):
        return f"registration failed: {first or _exc_name(exc)}"
    if isinstance(exc, ValueError) and first:  # MeasurementError and the vision's checks
        return f"measurement failed: {first}"
    return f"measurement failed: {_exc_name(exc)}: {first}"


def _frame_metadata(frame: Frame) -> tuple[dict[str, Any], dict[str, Any]]:
    """The record's frame fields, made valid (``t_s``, ``seq``, ``board_*``), and the odd ones."""
    out: dict[str, Any] = {}
    odd: dict[str, Any] = {}
    for name, kind, default in (
        ("t_s", float, 0.0),
        ("seq", int, 0),
        ("board_id", int, 0),
        ("board_position_mm", float, 0.0),
    ):
        raw = getattr(frame, name, None)
        try:
            v = kind(raw)
            good = math.isfinite(v) if kind is float else v >= 0
        except (TypeError, ValueError, OverflowError):
            good = False
        if good:
            out[name] = v
        else:
            out[name] = default
            odd[name] = repr(raw)
    return out, odd


def _with(r: FrameResult, **changes: Any) -> FrameResult:
    from dataclasses import replace

    return replace(r, **changes)


def _quality_class(cfg: MachineConfig) -> Any:
    from controller.quality_log import QualityClass

    q = cfg.quality
    return QualityClass(
        name=q.class_name,
        target_pitch_mm=q.target_pitch_mm,
        pitch_tolerance=q.tolerance,
        uniformity_max_cv=q.uniformity_max_cv,
        depth_max_um=q.depth_max_um,
    )


def _check_loop_tables(cfg: MachineConfig) -> None:
    """Build the loops' configurations once with defaults: ``ConfigError`` names a bad key."""
    from controller.feed_loop import FeedLoopConfig
    from controller.uniformity_loop import UniformityLoopConfig

    FeedLoopConfig.from_mapping(dict(cfg.feed_loop))
    UniformityLoopConfig.from_mapping(dict(cfg.uniformity_loop), stroke_um=cfg.stroke_um)


def _make_uniformity_loop(cfg: MachineConfig, snap: PlcSnapshot) -> Any:
    """The uniformity loop for the machine the PLC describes (knives, radius) and the stroke."""
    from controller.uniformity_loop import UniformityLoop, UniformityLoopConfig

    ucfg = UniformityLoopConfig.from_mapping(
        dict(cfg.uniformity_loop),
        knives=snap.knives,
        radius_mm=float(snap["cutterhead_radius_mm"]),
        stroke_um=cfg.stroke_um,
    )
    return UniformityLoop(ucfg)


def offsets_tuple(values: Sequence[float]) -> tuple[float, ...]:
    """Offsets as a tuple of floats."""
    return tuple(float(v) for v in values)


def default_log_path(cfg: MachineConfig) -> Path:
    """The quality log path of a configuration (its folder is created)."""
    p = Path(cfg.log.path)
    p.parent.mkdir(parents=True, exist_ok=True)
    return p


def open_service(
    cfg: MachineConfig,
    *,
    clock: Callable[[], float] = time.monotonic,
    threaded: bool = True,
    can_bus: Any = None,
    log_path: Path | None = None,
) -> Service:
    """A service wired as ``machine.toml`` says: Modbus TCP client, CAN bus, rig, quality log.

    Nothing is contacted yet: the PLC connection is opened by the first request (and reopened
    with back-off), the CAN bus is opened here (``FieldbusError`` if it cannot be).

    Parameters
    ----------
    cfg : MachineConfig
        The configuration.
    clock : callable
        Monotonic seconds.
    threaded : bool
        Measure and log in worker threads (real time).
    can_bus : can.BusABC, optional
        Use this bus instead of opening ``[can]``.
    log_path : Path, optional
        Override ``[log] path``.
    """
    from config.machine import dbc_path, registers_path, rig_path
    from config.rig import load_rig
    from controller.piezo_client import open_bus
    from controller.plc_client import Backoff
    from controller.quality_log import QualityLog
    from protocol.piezo_can import PiezoCodec
    from protocol.registers import RegisterMap
    from vision.pipeline import Measurer

    rig = load_rig(rig_path(cfg))
    regmap = RegisterMap.load(registers_path(cfg))
    plc = PlcClient.tcp(
        cfg.plc.host,
        cfg.plc.port,
        unit_id=cfg.plc.unit_id,
        timeout_s=cfg.plc.timeout_s,
        regmap=regmap,
        backoff=Backoff(cfg.plc.backoff_initial_s, cfg.plc.backoff_max_s),
        clock=clock,
    )
    bus = can_bus if can_bus is not None else open_bus(
        cfg.can.interface, cfg.can.channel, dict(cfg.can.options)
    )
    piezo = PiezoClient(
        bus,
        PiezoCodec.load(dbc_path(cfg)),
        knives=4,  # replaced by the PLC's knives register on the first read
        command_period_s=cfg.can.command_period_s,
        offsets_period_s=cfg.can.offsets_period_s,
        stroke_um=cfg.stroke_um,
    )
    path = Path(log_path) if log_path is not None else default_log_path(cfg)
    path.parent.mkdir(parents=True, exist_ok=True)
    log = QualityLog(path)
    service = Service(
        cfg,
        plc=plc,
        piezo=piezo,
        rig=rig,
        log=log,
        clock=clock,
        threaded=threaded,
        measurer_factory=lambda shape: Measurer(rig, shape),
        pairs_per_s=cfg.frames.pairs_per_s,
    )
    log.set_quality_class(service.quality_class)
    return service
