"""The service beside the PLC: image pairs in, marks measured, feed and piezo setpoints out.

One :class:`Service` owns the two buses (a :class:`~controller.plc_client.PlcClient` and a
:class:`~controller.piezo_client.PiezoClient`), the quality log, the control loops and the
safe-state supervisor. Two entry points do all the work, both with the time passed in:

* :meth:`Service.tick` — one control cycle (every ``safety.cycle_s``): heartbeat to the PLC
  (Modbus register) and to the amplifier (CAN alive counter), read the PLC's registers, drain
  the amplifier's frames, step the supervisor; in the safe state hold or ramp the feed down and
  send zero offsets with the amplifier disabled; on recovery re-enable and resume.
* :meth:`Service.handle_frame` — one image pair: take the PLC's registers (the tick's read of
  at most two cycles ago, else a fresh read), measure (in a worker thread in
  real time so the heartbeats keep going), check plausibility, find which knife cut which mark,
  update the feed loop and the uniformity loop, clamp to the limits, write the setpoints
  (Modbus and CAN) and append the quality record — every measurement, failed ones included; a
  failed or implausible measurement changes no setpoint.

:meth:`Service.run` drives both in real time from a frame source until stopped
(``planer serve``); the in-process HIL and the tests call them step by step on simulated time.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from config.machine import MachineConfig
from controller.piezo_client import PiezoClient
from controller.plc_client import PlcClient, PlcSnapshot
from controller.safety import SafetyState, SafetyStatus, Supervisor
from planer.errors import FieldbusError, MeasurementError, ModbusRefused
from planer.protocol.frames import Frame

PLC_SNAPSHOT_MAX_AGE_CYCLES = 2.0
"""A pair uses the registers the tick read if they are at most this many cycles old."""
FEED_WRITE_DEADBAND_MM_S = 0.5
"""Feed-forward changes smaller than this between measurements are not written, mm/s."""
MAX_PHASE_SPREAD = 0.15
"""Marks whose pass numbers spread more than this (in passes) are not attributed to knives."""


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
        self.feed_loop: Any = None
        self.uniformity_loop: Any = None
        self._loop_key: tuple | None = None
        self.feed_setpoint_mm_s: float | None = None
        self.offsets_um: tuple[float, ...] = ()
        self._learned_offsets: np.ndarray | None = None
        self._last_tick_s: float | None = None
        self._state = SafetyState.SAFE
        self._machine_offset_s: float | None = None  # service clock minus machine time
        self._t_loops = -math.inf
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
        }
        self.events: list[tuple[float, str]] = []
        self.on_result: Callable[[FrameResult], None] | None = None
        self.on_event: Callable[[float, str], None] | None = None

    # ------------------------------------------------------------------ helpers
    def _event(self, t: float, text: str) -> None:
        self.events.append((t, text))
        if self.on_event is not None:
            self.on_event(t, text)

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
        self.uniformity_loop = _make_uniformity_loop(self.cfg, snap, self.pairs_per_s)
        self._learned_offsets = np.zeros(snap.knives)
        if self.piezo.knives != snap.knives:
            self.piezo.set_knives(snap.knives)
        self.offsets_um = (0.0,) * snap.knives
        self._loop_key = key

    # ------------------------------------------------------------------ the control cycle
    async def tick(self, now_s: float | None = None) -> SafetyStatus:
        """One control cycle: heartbeats, PLC and CAN status, supervisor, safe actions.

        Parameters
        ----------
        now_s : float, optional
            Service time; default ``clock()``.

        Returns
        -------
        SafetyStatus
            The supervisor's decision of this cycle.
        """
        t = self.clock() if now_s is None else float(now_s)
        dt = 0.0 if self._last_tick_s is None else max(0.0, t - self._last_tick_s)
        self._last_tick_s = t
        self.heartbeat = (self.heartbeat + 1) & 0xFFFF
        sup = self.supervisor
        snap: PlcSnapshot | None = None
        try:
            await self.plc.write_heartbeat(self.heartbeat)
            snap = await self.plc.read()
        except FieldbusError:
            self.counters["plc_errors"] += 1
        if self.plc.last_ok_s is not None:
            sup.plc_answered(min(self.plc.last_ok_s, t))
        if snap is not None:
            self._ensure_loops(snap)
            sup.machine_ok(not snap.estop and snap.spindle_running)
            if not snap.board_present:
                sup.measurement_not_expected(t)
        try:
            self.piezo.poll(now_s=t)
        except FieldbusError:
            self.counters["can_errors"] += 1
        if self.piezo.last_heard_s is not None:
            sup.can_heard(self.piezo.last_heard_s)
        status = sup.step(t)
        self.status = status
        if status.changed:
            if status.state is SafetyState.SAFE:
                self.counters["safe_entries"] += 1
                self._event(t, f"safe state: {', '.join(status.missing) or 'start'} gone")
            else:
                self.counters["recoveries"] += 1
                self._event(t, "recovered: control resumed")
                self._resume(t)
        if status.state is SafetyState.SAFE:
            await self._safe_actions(t, dt, snap)
        else:
            self.piezo.set_enable(True, now_s=t)
            if snap is not None and self.feed_loop is not None:
                await self._feed_forward(t, snap)
        try:
            self.piezo.tick(alive_counter=self.heartbeat & 0xFF, now_s=t)
        except FieldbusError:
            self.counters["can_errors"] += 1
        return status

    async def _safe_actions(self, t: float, dt: float, snap: PlcSnapshot | None) -> None:
        sup = self.supervisor
        if self.piezo.knives:
            try:
                self.piezo.set_enable(False, now_s=t)
                self.offsets_um = self.piezo.set_offsets(
                    sup.safe_offsets_um(self.piezo.knives), now_s=t
                )
            except FieldbusError:
                self.counters["can_errors"] += 1
        if snap is None:
            return  # the PLC is gone: its own watchdog acts on the missing heartbeat
        current = snap.feed_setpoint_mm_s
        lo, hi = snap.feed_min_mm_s, snap.feed_max_mm_s
        if not (current == current):  # NaN guard
            return
        target = sup.safe_feed(current, dt_s=dt, feed_min_mm_s=lo, feed_max_mm_s=hi)
        if abs(target - current) > 1e-3:
            await self._write_feed(target, t)
        else:
            self.feed_setpoint_mm_s = current

    def _loop_time(self, t: float) -> float:
        """Time for the control loops: never earlier than their last call.

        In real time the tick and the frame task interleave at awaits, so a time read before an
        await may be older than one the other task already used.
        """
        t = max(t, self._t_loops)
        self._t_loops = t
        return t

    async def _feed_forward(self, t: float, snap: PlcSnapshot) -> None:
        """Between measurements the feed loop's feed-forward follows the spindle speed.

        No measurement enters here (the learnt correction is held); the setpoint is written only
        when it moved by more than ``FEED_WRITE_DEADBAND_MM_S`` (e.g. ramping back after a
        recovery), so spindle ripple does not flood the bus.
        """
        feed = self.feed_loop.update(
            measured_pitch_mm=None, spindle_rpm=snap.spindle_rpm, now_s=self._loop_time(t)
        )
        feed = min(max(float(feed), snap.feed_min_mm_s), snap.feed_max_mm_s)
        current = self.feed_setpoint_mm_s
        if current is None:
            current = snap.feed_setpoint_mm_s
        if abs(feed - current) > FEED_WRITE_DEADBAND_MM_S:
            await self._write_feed(feed, t)

    async def _write_feed(self, feed: float, t: float) -> bool:
        try:
            await self.plc.write_feed(feed)
        except ModbusRefused as exc:
            self.counters["setpoint_refused"] += 1
            self._event(t, f"feed setpoint refused: {exc}")
            return False
        except FieldbusError:
            self.counters["plc_errors"] += 1
            return False
        except ValueError as exc:  # outside the limits the PLC reported: never sent
            self.counters["setpoint_refused"] += 1
            self._event(t, f"feed setpoint not sent: {exc}")
            return False
        self.feed_setpoint_mm_s = feed
        return True

    def _resume(self, t: float) -> None:
        """Back to RUN: restart the feed loop from the feed in force, restore learnt offsets."""
        t = self._loop_time(t)
        snap = self.plc.last
        if snap is not None and self.feed_loop is not None:
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
        t_arr = self.clock() if now_s is None else float(now_s)
        self.counters["frames"] += 1
        # machine time -> service time (lowest observed latency; exact in simulated time)
        off = t_arr - frame.t_s
        if self._machine_offset_s is None or off < self._machine_offset_s:
            self._machine_offset_s = off
        snap: PlcSnapshot | None = self.plc.last
        max_age = PLC_SNAPSHOT_MAX_AGE_CYCLES * self.cfg.safety.cycle_s
        if snap is None or self.clock() - snap.t_s > max_age:
            try:  # the tick's snapshot is stale (PLC slow or gone): ask now
                snap = await self.plc.read()
                self.supervisor.plc_answered(t_arr)
            except FieldbusError:
                self.counters["plc_errors"] += 1
                snap = self.plc.last
        wall_plc = time.perf_counter()
        wall_meas = wall_plc
        error: str | None = None
        meas: Any = None
        widths = ()
        if snap is None:
            error = "no PLC data: registers never read"
        else:
            self._ensure_loops(snap)
            try:
                meas = await self._call(
                    self.measurer(tuple(np.shape(frame.image_a))).measure,
                    frame.image_a,
                    frame.image_b,
                    counts_a=frame.counts_a,
                    counts_b=frame.counts_b,
                    speed_mm_s=frame.speed_mm_s if frame.speed_mm_s > 0 else None,
                )
            except (MeasurementError, ValueError) as exc:
                error = _reason(exc)
            wall_meas = time.perf_counter()
            if error is None:
                error = self._implausible(meas, frame, snap)
            if error is None:
                try:
                    widths = self._knife_widths(meas, frame, snap)
                except ValueError as exc:
                    error = f"knife phase failed: {exc}"
        ok = error is None
        applied = False
        if ok:
            self.counters["ok"] += 1
            self.supervisor.measurement_valid(t_arr)
            if self.supervisor.state is SafetyState.RUN and snap is not None:
                t_ctrl = self.clock() if now_s is None else t_arr  # loops need forward time
                applied = await self._apply(meas, widths, frame, snap, t_ctrl)
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
            knife_widths_mm=tuple(float(w) for w in widths),
            applied=applied,
            feed_setpoint_mm_s=self.feed_setpoint_mm_s,
            offsets_um=tuple(self.offsets_um),
            state=self.supervisor.state.value,
            t_s=t_arr,
            latency_s=latency_s,
            truth=frame.truth,
            counts_a=int(frame.counts_a),
            frame_t_s=float(frame.t_s),
            extra={"timing_ms": timing},
        )
        rid = await self._log(result, frame, snap)
        if rid is not None:
            result = _with(result, record_id=rid)
        if self.keep_results:
            self.results.append(result)
        if self.on_result is not None:
            self.on_result(result)
        return result

    def _implausible(self, meas: Any, frame: Frame, snap: PlcSnapshot) -> str | None:
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
        expected = speed / (n_rev_s * snap.knives)
        ratio = pitch / expected
        if not pl.pitch_ratio_min <= ratio <= pl.pitch_ratio_max:
            return (
                f"implausible: pitch {pitch:.3f} mm vs {expected:.3f} mm expected from "
                f"V/(nZ) (ratio {ratio:.2f})"
            )
        return None

    def _knife_widths(self, meas: Any, frame: Frame, snap: PlcSnapshot) -> np.ndarray:
        """Mean mark width per knife (NaN where no mark of that knife was seen), mm.

        Raises
        ------
        ValueError
            The marks do not line up with the knife passes (phase spread too large).
        """
        from controller import knife_phase

        cam = self.rig.camera
        kw = {
            "counts_a": int(frame.counts_a),
            "index_latch_counts": int(frame.index_latch_counts),
            "cutter_to_camera_mm": snap.cutter_to_camera_mm,
            "counts_per_mm": snap.counts_per_mm,
            "px_per_mm": cam.px_per_mm,
            "cx_px": cam.cx,
            "pitch_mm": float(meas.pitch_mm),
            "counter_bits": self.rig.encoder.counter_bits,
        }
        bottoms = np.asarray(meas.bottoms_mm, dtype=float)
        widths = np.asarray(meas.mark_widths_mm, dtype=float)
        if bottoms.shape != widths.shape:
            raise ValueError(f"{bottoms.size} mark bottoms for {widths.size} widths")
        spread = knife_phase.phase_spread(knife_phase.pass_numbers(bottoms, **kw))
        if not spread <= MAX_PHASE_SPREAD:
            raise ValueError(f"marks off the knife passes (phase spread {spread:.2f})")
        knife = knife_phase.knife_of_marks(bottoms, knives=snap.knives, align_phase=True, **kw)
        return knife_phase.knife_means(widths, knife, snap.knives)

    async def _apply(
        self, meas: Any, widths: np.ndarray, frame: Frame, snap: PlcSnapshot, t: float
    ) -> bool:
        lo, hi = snap.feed_min_mm_s, snap.feed_max_mm_s
        pitch = float(meas.pitch_mm)
        t = self._loop_time(t)
        measured_at = frame.t_s + (self._machine_offset_s or 0.0)
        feed = self.feed_loop.update(
            measured_pitch_mm=pitch,
            spindle_rpm=snap.spindle_rpm,
            now_s=t,
            measured_at_s=min(measured_at, t),
        )
        feed = min(max(float(feed), lo), hi)
        new_offsets = None
        if np.any(np.isfinite(widths)):
            interval = self.feed_loop.cut_interval_s(min(measured_at, t))
            offs = self.uniformity_loop.update(
                knife_widths_mm=widths,
                pitch_mm=pitch,
                now_s=t,
                cut_at_s=None if interval is None else min(interval[0], t),
            )
            s = self.cfg.stroke_um
            new_offsets = np.clip(np.asarray(offs, dtype=float), -s, s)
        applied = await self._write_feed(feed, t)
        if new_offsets is not None:
            try:
                self.offsets_um = self.piezo.set_offsets(new_offsets, now_s=t)
                self._learned_offsets = np.asarray(self.offsets_um, dtype=float)
                applied = True
            except FieldbusError as exc:
                self.counters["can_errors"] += 1
                self._event(t, f"piezo offsets not sent: {exc}")
        if applied:
            self.counters["applied"] += 1
        return applied

    async def _log(self, r: FrameResult, frame: Frame, snap: PlcSnapshot | None) -> int | None:
        if self.log is None:
            return None
        from controller.quality_log import QualityRecord, judge, utc_iso

        m = r.measurement
        truth = frame.truth or {}
        fields: dict[str, Any] = {
            "t_s": float(frame.t_s),
            "wall_time": utc_iso(time.time()),
            "seq": int(frame.seq),
            "board_id": int(frame.board_id),
            "board_position_mm": float(frame.board_position_mm),
            "ok": r.ok,
            "error": r.error,
            "feed_setpoint_mm_s": r.feed_setpoint_mm_s,
            "piezo_offsets_um": tuple(r.offsets_um),
            "target_pitch_mm": self.cfg.quality.target_pitch_mm,
            "true_pitch_mm": _opt(truth.get("pitch_mm")),
            "true_uniformity_cv": _opt(truth.get("uniformity_cv")),
            "extra": {
                "state": r.state,
                "applied": r.applied,
                "latency_ms": r.latency_s * 1e3,
                "timing_ms": r.extra.get("timing_ms", {}),
                "knife_widths_mm": [None if not math.isfinite(w) else w
                                    for w in r.knife_widths_mm],
            },
        }
        if m is not None:
            fields["shift_px"] = _opt(getattr(m, "shift_px", None))
            fields["confidence"] = _opt(getattr(m, "confidence", None))
        if r.ok:
            fields.update(
                pitch_mm=float(m.pitch_mm),
                mark_widths_mm=tuple(float(w) for w in r.knife_widths_mm)
                if r.knife_widths_mm
                else tuple(float(w) for w in m.mark_widths_mm),
                uniformity_cv=_opt(getattr(m, "uniformity_cv", None)),
                depth_um=_opt(getattr(m, "depth_um", None)),
            )
            fields["extra"]["marks_mm"] = [float(w) for w in m.mark_widths_mm]
            try:
                fields["passed"] = judge(fields, self.quality_class)
            except ValueError:
                fields["passed"] = None
        rec = QualityRecord(**fields)
        try:
            return int(await self._call(self.log.append, rec))
        except OSError as exc:  # disk full, log locked: control goes on, the loss is reported
            self.counters["log_errors"] += 1
            self._event(self.clock(), f"quality record of pair {frame.seq} NOT logged: {exc}")
            return None

    # ------------------------------------------------------------------ real time
    async def run(
        self,
        source: Any,
        *,
        stop: asyncio.Event | None = None,
        max_frames: int | None = None,
    ) -> None:
        """Run in real time until ``stop`` is set (or ``max_frames`` pairs were handled).

        A periodic task calls :meth:`tick` every ``safety.cycle_s``; the frame task awaits
        ``source.next()`` and calls :meth:`handle_frame`. Both share the event loop; the
        measurement runs in a worker thread so the heartbeats never wait for it.
        """
        stop = stop or asyncio.Event()
        cycle = self.cfg.safety.cycle_s

        async def ticker() -> None:
            loop = asyncio.get_running_loop()
            nxt = loop.time()
            while not stop.is_set():
                await self.tick()
                nxt += cycle
                delay = nxt - loop.time()
                if delay < -cycle:  # fell behind: skip, do not burst
                    nxt = loop.time()
                    delay = 0.0
                await asyncio.sleep(max(0.0, delay))

        async def frames() -> None:
            n = 0
            while not stop.is_set():
                frame = await source.next(timeout_s=0.1)
                if frame is None:
                    continue
                try:
                    await self.handle_frame(frame)
                except (ValueError, ArithmeticError) as exc:  # one bad pair must not stop us
                    self.counters["errors"] += 1
                    self._event(self.clock(), f"pair {frame.seq} dropped: {exc}")
                n += 1
                if max_frames is not None and n >= max_frames:
                    stop.set()

        tasks = [asyncio.create_task(ticker()), asyncio.create_task(frames())]
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
        """Close the buses and the log."""
        self.plc.close()
        self.piezo.close()
        if self.log is not None:
            self.log.close()


# ---------------------------------------------------------------------------------- helpers
def _opt(v: Any) -> float | None:
    if v is None:
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _reason(exc: BaseException) -> str:
    name = type(exc).__name__
    text = str(exc).splitlines()[0] if str(exc) else name
    if name == "RegistrationError":
        return f"registration failed: {text}"
    return f"measurement failed: {text}"


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


def _make_uniformity_loop(cfg: MachineConfig, snap: PlcSnapshot, pairs_per_s: float) -> Any:
    from controller.uniformity_loop import UniformityLoop, UniformityLoopConfig

    overrides = {"knives": snap.knives, "stroke_um": cfg.stroke_um}
    build = getattr(UniformityLoopConfig, "from_mapping", None)
    if build is not None:
        ucfg = build(dict(cfg.uniformity_loop), **overrides)
    else:  # pragma: no cover
        ucfg = UniformityLoopConfig(**{**dict(cfg.uniformity_loop), **overrides})
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
    from planer.protocol.piezo_can import PiezoCodec
    from planer.protocol.registers import RegisterMap
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
