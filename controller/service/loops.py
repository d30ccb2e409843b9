"""The loops stage: the feed loop and the uniformity loop, fed by the pipeline and the PLC cycle.

:class:`ControlLoops` builds both loops for the machine the PLC describes (and rebuilds them when
its geometry or limits change), runs them on each valid, attributed measurement
(:meth:`ControlLoops.apply`) and between measurements lets the feed-forward follow the spindle
(:meth:`ControlLoops.feed_forward`). The laws themselves are in ``controller/laws/feed_loop.py`` and
``controller/laws/uniformity_loop.py`` (pure); what goes on the wire goes through
:class:`~controller.service.actuators.Actuators`.
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from config.loading import naming_file
from config.machine import MachineConfig
from controller.fieldbus.plc_protocol import PlcSnapshot
from controller.laws.board_speed import BoardSpeedHistory
from controller.laws.feed_loop import FeedLoop, FeedLoopConfig
from controller.laws.knife_condition import KnifeConditionTracker
from controller.laws.limits import project_zero_mean_box
from controller.laws.uniformity_loop import UniformityLoop, UniformityLoopConfig
from controller.quality.learned_state import KnifeSet, LearnedMemory, LearnedState
from controller.service.actuators import Actuators
from controller.service.alerts import KnifeNickMonitor, OperatorAlerts
from controller.service.attribution import Attributed
from controller.service.events import EventKind, EventLog
from controller.service.supervisor import AmplifierMonitor
from core.errors import FieldbusError
from protocol.registers import MachineState

FEED_WRITE_DEADBAND_MM_S = 0.5
"""Feed-forward changes smaller than this between measurements are not written, mm/s."""
PASS_TOL = 0.2
"""The travel per pass the attribution fitted to the mark bottoms must lie within this factor
(``1 / (1 + tol)`` to ``1 + tol``) of the feed per pass the measured board was cut with, else its
pass counts (so the widths per knife) are not trusted and the uniformity loop skips the pair
(:meth:`ControlLoops.attribution_trusted`). A wrong count is off by at least 4/3 (three passes
for four) and mostly by 2 (two for one)."""


CONDITION_EVERY_S = 2.0
"""The knife condition's forecast is renewed at most this often (1-2 ms of CPU each, between
pairs: :meth:`KnifeConditionWatch.renew`)."""
CONDITION_LATE_S = 10.0
"""A forecast this overdue is renewed after a pair even when the next pair already waits."""
JOINTING_WARN_BOARDS = 20.0
"""The operator is told (``JOINTING_DUE``) when the finish leaves its class within this many
boards at the knives' present wear."""


def plc_accel_mm_s2(snap: PlcSnapshot) -> float | None:
    """The feed drive's acceleration limit the PLC reports, mm/s^2 (``None``: not reported)."""
    accel = float(snap.values.get("feed_accel_max_mm_s2", 0.0) or 0.0)
    return accel if math.isfinite(accel) and accel > 0.0 else None


def check_loop_tables(cfg: MachineConfig) -> None:
    """Build the loops' configurations once with defaults: ``ConfigError`` names a bad key."""
    with naming_file(cfg.source):  # "machine.toml: unknown key feed_loop.x"
        FeedLoopConfig.from_mapping(dict(cfg.feed_loop))
        UniformityLoopConfig.from_mapping(dict(cfg.uniformity_loop), stroke_um=cfg.stroke_um)


class ControlLoops:
    """Both control loops of one service.

    Parameters
    ----------
    cfg : MachineConfig
        ``[quality]`` (target pitch, depth ceiling), ``[feed_loop]``, ``[uniformity_loop]``,
        ``stroke_um``.
    rig : Rig
        The camera's field of view (the feed loop's window).
    actuators : Actuators
        The writes (feed setpoint, offsets).
    report : EventLog
        Events and counters.
    amp_monitor : AmplifierMonitor
        When the amplifier last did not play the offsets (no learning from that board).
    pairs_per_s : float
        Nominal camera rate (the feed loop's default sample time), pairs per second.
    """

    def __init__(
        self,
        cfg: MachineConfig,
        rig: Any,
        actuators: Actuators,
        report: EventLog,
        amp_monitor: AmplifierMonitor,
        *,
        pairs_per_s: float,
    ) -> None:
        check_loop_tables(cfg)  # a bad [feed_loop] / [uniformity_loop] key fails now
        self.cfg = cfg
        self.rig = rig
        self.out = actuators
        self._writes_feed = bool(getattr(actuators, "owns_feed", True))
        """Whether a pair's feed goes to the PLC (a moulder's head: the coordinator writes)."""
        self._report = report
        self._amp_monitor = amp_monitor
        self.pairs_per_s = float(pairs_per_s)
        self.feed_loop: Any = None
        self.uniformity_loop: Any = None
        self._key: tuple | None = None
        self._accel: float | None = None
        self._snap: PlcSnapshot | None = None
        self.memory: LearnedMemory | None = None
        """Where the learnt state is kept across restarts (``None``: not kept)."""
        self.on_warm_start: Callable[[float], Any] | None = None
        """Called when a remembered state was resumed on a running machine (the supervisor
        holds the feed while starting up: :meth:`Supervisor.warm_start`)."""
        self.resumed: LearnedState | None = None
        """The remembered state the loops started from (``None``: they learnt afresh)."""
        self.alerts = OperatorAlerts(report, target_pitch_mm=cfg.quality.target_pitch_mm,
                                     tolerance=cfg.quality.tolerance)
        """What the operator is told: an unreachable target, a chipped knife, failing pairs."""
        self.nicks = KnifeNickMonitor(report)
        """A nicked knife, from the defect detector's ridges (``KNIFE_CHIPPED`` too)."""
        self._learned_offsets: np.ndarray | None = None
        self._stroke_limit_um: float | None = None
        self._t_loops = -math.inf
        self.board_speed = BoardSpeedHistory()
        """The PLC's actual feed and knife passing rate (the feed per pass at a cut)."""
        self.condition = KnifeConditionWatch(cfg, report)
        """The knives' wear and the jointing forecast (:class:`KnifeConditionWatch`)."""
        self._lock: asyncio.Lock | None = None
        self._lock_loop: Any = None

    @property
    def ready(self) -> bool:
        """Whether the loops are built (a valid register read happened)."""
        return self.feed_loop is not None

    def ensure(self, snap: PlcSnapshot) -> None:
        """Build (or rebuild when the machine's geometry or limits change) the control loops."""
        key = (
            snap.knives,
            round(snap.feed_min_mm_s, 3),
            round(snap.feed_max_mm_s, 3),
            round(float(snap["cutterhead_radius_mm"]), 3),
            round(snap.cutter_to_camera_mm, 3),
        )
        self._snap = snap
        if key == self._key:
            if plc_accel_mm_s2(snap) != self._accel:
                self._new_feed_rate(snap)
            return
        first = self._key is None
        q = self.cfg.quality
        cam = self.rig.camera
        overrides: dict[str, Any] = {
            "target_pitch_mm": q.target_pitch_mm,
            "depth_max_um": q.depth_max_um,
            "knives": snap.knives,
            "radius_mm": float(snap["cutterhead_radius_mm"]),
            "feed_min_mm_s": snap.feed_min_mm_s,
            "feed_max_mm_s": snap.feed_max_mm_s,
            "cutter_to_camera_mm": snap.cutter_to_camera_mm,
            "window_mm": 2.0 * cam.cx / cam.px_per_mm,
        }
        fl_map = dict(self.cfg.feed_loop)
        fl_map.setdefault("sample_time_s", 1.0 / self.pairs_per_s)
        accel = plc_accel_mm_s2(snap)
        if accel is not None:  # the PLC's own limit rules, whatever machine.toml says
            rate = float(fl_map.get("rate_max_mm_s2", FeedLoopConfig.rate_max_mm_s2))
            fl_map["rate_max_mm_s2"] = min(rate, accel)
        self._accel = accel
        self.feed_loop = FeedLoop(FeedLoopConfig.from_mapping(fl_map, **overrides))
        lo, hi = snap.feed_min_mm_s, snap.feed_max_mm_s
        self.feed_loop.reset(feed_mm_s=min(max(snap.feed_setpoint_mm_s, lo), hi))
        self.uniformity_loop = UniformityLoop(UniformityLoopConfig.from_mapping(
            dict(self.cfg.uniformity_loop),
            knives=snap.knives,
            radius_mm=float(snap["cutterhead_radius_mm"]),
            stroke_um=self.cfg.stroke_um,
        ))
        if self._stroke_limit_um is not None:
            self.uniformity_loop.set_limit_um(self._stroke_limit_um)
        self._learned_offsets = np.zeros(snap.knives)
        self.out.set_knives(snap.knives)
        self.alerts.machine(snap.knives, float(snap["cutterhead_radius_mm"]))
        self._key = key
        if first and self.memory is not None:
            self._resume_memory(snap)

    # ------------------------------------------------------------------ memory
    def knife_set(self, snap: PlcSnapshot) -> KnifeSet:
        """The knife set the PLC's registers and the amplifier describe now."""
        amp = self.out.piezo.limit.amp
        return KnifeSet(knives=int(snap.knives), radius_mm=float(snap["cutterhead_radius_mm"]),
                        spindle_rpm=max(float(snap.spindle_rpm), 0.0),
                        stroke_um=None if amp is None else float(amp.stroke_um))

    def _resume_memory(self, snap: PlcSnapshot) -> None:
        """Start the loops from the remembered state when it is this machine's and knives'."""
        mem = self.memory
        assert mem is not None
        t = float(snap.t_s)
        state, problem = mem.load()
        why = problem if state is None else mem.judge(state, self.knife_set(snap))
        if state is None or why is not None:
            if why is not None:
                self._report.emit(t, EventKind.LEARNED_STATE_DISCARDED,
                                  f"learnt state not used, learning afresh: {why}", reason=why,
                                  data={"path": str(mem.path)})
            return
        fl, uni = self.feed_loop, self.uniformity_loop
        corr = min(max(state.feed_correction, fl.cfg.correction_min), fl.cfg.correction_max)
        fl.reset(feed_mm_s=fl.feed_mm_s, correction=corr)
        offs = project_zero_mean_box(np.asarray(state.offsets_um, float), bound=uni.limit_um)
        uni.reset(offs, forget=True)  # its first pairs check the table against the board
        self._learned_offsets = offs.copy()  # what the return to RUN sends
        self.resumed = state
        running = MachineState.RUNNING in snap.machine_state and snap.feed_actual_mm_s > 0
        age = mem.wall_clock() - state.saved_at_unix
        self._report.emit(
            t, EventKind.LEARNED_STATE_RESUMED,
            f"resuming the learnt state of {age:.0f} s ago (offsets "
            f"[{' '.join(f'{v:+.2f}' for v in offs)}] µm, feed correction {corr:.4f})"
            + ("; the machine runs: feed held while starting up" if running else ""),
            data={"path": str(mem.path), "age_s": age, "offsets_um": offs.tolist(),
                  "feed_correction": corr, "warm": running})
        if running and self.on_warm_start is not None:
            self.on_warm_start(t)

    def learned_state(self) -> LearnedState | None:
        """What the loops have learnt now, for the memory (``None`` before they exist)."""
        if self.memory is None or self._snap is None or self.feed_loop is None:
            return None
        uni = self.uniformity_loop
        offs = self._learned_offsets
        if offs is None or len(offs) != uni.cfg.knives:
            return None
        est = uni.runout_estimate_um
        return self.memory.make(self.knife_set(self._snap), offs.tolist(),
                                feed_correction=self.feed_loop.correction,
                                runout_estimate_um=None if est is None else est.tolist(),
                                mode_gains=list(uni.mode_gains))

    def remember(self, t: float, *, now: bool = False) -> None:
        """Offer the learnt state to the memory: written if due and changed.

        ``now``: written if changed, whatever the interval (e.g. at a clean stop).
        """
        mem = self.memory
        if mem is None:
            return
        if now:
            state = self.learned_state()
            if state is not None and mem.changed(state):
                mem.save(state, t)
        else:
            mem.offer(self.learned_state, t)

    def _new_feed_rate(self, snap: PlcSnapshot) -> None:
        """The PLC's acceleration limit changed: the feed loop again, its learning kept."""
        old = self.feed_loop
        accel = plc_accel_mm_s2(snap)
        rate = float(dict(self.cfg.feed_loop).get("rate_max_mm_s2",
                                                  FeedLoopConfig.rate_max_mm_s2))
        cfg = dataclasses.replace(old.cfg, rate_max_mm_s2=rate if accel is None
                                  else min(rate, accel))
        self.feed_loop = FeedLoop(cfg)
        self.feed_loop.reset(feed_mm_s=old.feed_mm_s, now_s=self._t_loops
                             if math.isfinite(self._t_loops) else None,
                             correction=old.correction)
        self._accel = accel

    def set_limit_um(self, stroke_um: float, t: float) -> np.ndarray | None:
        """The stroke the uniformity loop plans within from now on (e.g. the amplifier's).

        Kept for loops built later (a new machine geometry). Returns the offsets to apply now
        (re-planned when the table in force does not fit; ``None`` before the loops exist);
        sending them is the caller's business.
        """
        self._stroke_limit_um = float(stroke_um)
        if self.uniformity_loop is None:
            return None
        offs = self.uniformity_loop.set_limit_um(stroke_um, now_s=self.loop_time(t))
        self._learned_offsets = offs.copy()  # what a recovery restores: inside the new limit
        return offs

    def loop_time(self, t: float) -> float:
        """Time for the control loops: never earlier than their last call.

        In real time the cycles and the frame task interleave at awaits, so a time read before
        an await may be older than one another task already used.
        """
        t = max(t, self._t_loops)
        self._t_loops = t
        return t

    def _feed_lock(self) -> asyncio.Lock:
        """Held from a feed loop update to the end of its write (and its reject).

        In real time the PLC cycle's feed-forward and a pair's update interleave at the write's
        await; the lock keeps each setpoint's update, write and reject together, so a reject
        always takes back its own setpoint.
        """
        loop = asyncio.get_running_loop()
        if self._lock is None or self._lock_loop is not loop:
            self._lock = asyncio.Lock()
            self._lock_loop = loop
        return self._lock

    async def feed_forward(self, t: float, snap: PlcSnapshot) -> None:
        """Between measurements the feed loop's feed-forward follows the spindle speed.

        No measurement enters here (the learnt correction is held); the setpoint is written only
        when it moved by more than ``FEED_WRITE_DEADBAND_MM_S`` (e.g. ramping back after a
        recovery), so spindle ripple does not flood the bus. A setpoint not written (deadband,
        refused, failed) is taken back from the loop's history: it learns against the feed
        that really was in force.
        """
        async with self._feed_lock():
            self._record_speed(t, snap)
            loop = self.feed_loop
            feed = loop.update(
                measured_pitch_mm=None, spindle_rpm=snap.spindle_rpm, now_s=self.loop_time(t)
            )
            feed = min(max(float(feed), snap.feed_min_mm_s), snap.feed_max_mm_s)
            current = self.out.feed_setpoint_mm_s
            if current is None:
                current = snap.feed_setpoint_mm_s
            if abs(feed - current) <= FEED_WRITE_DEADBAND_MM_S:
                loop.defer()  # too small to write: it adds up with the next steps
            elif not await self.out.write_feed(feed, t):
                loop.reject()

    async def apply(
        self, att: Attributed | None, measured_at: float, snap: PlcSnapshot, t: float
    ) -> bool:
        """Both loops on one valid measurement; the feed (Modbus) and the offsets (CAN) go out.

        Both get the pitch per knife pass (:attr:`Attributed.pass_pitch_mm`), not the mean mark
        width: with a knife that leaves no mark the latter is a multiple of the feed per knife,
        and slowing the feed would not bring the mark back (the uniformity loop does).

        The feed loop's update is cheap and its setpoint goes on the wire first; while the PLC
        answers the write (a round trip, 0.3-0.6 ms), the uniformity loop's update (0.05 ms)
        runs and its offsets go out on CAN (:meth:`_feed_write`), so the pair's control costs
        the longer of the two instead of their sum. It returns when the PLC took the feed and
        the offsets were sent.

        The uniformity loop learns only from board cut while the amplifier played the offsets
        (:meth:`amp_tracked`); a feed setpoint the PLC did not take is taken back from the feed
        loop's history (:meth:`FeedLoop.reject`). Returns whether a setpoint went out.
        """
        if att is None:
            return False
        lo, hi = snap.feed_min_mm_s, snap.feed_max_mm_s
        pitch = float(att.pass_pitch_mm)
        applied = False
        async with self._feed_lock():
            t = self.loop_time(t)
            self._record_speed(t, snap)
            measured_at = min(measured_at, t)
            loop = self.feed_loop
            feed = loop.update(
                measured_pitch_mm=pitch,
                spindle_rpm=snap.spindle_rpm,
                now_s=t,
                measured_at_s=measured_at,
            )
            feed = min(max(float(feed), lo), hi)
            write = await self._feed_write(feed, t)
            self.alerts.target.update(t, pitch_mm=pitch, feed_mm_s=feed, feed_limits_mm_s=(lo, hi),
                                      held_pitch_mm=loop.pitch_setpoint_mm)
            try:
                widths = np.asarray(att.knife_widths_mm, dtype=float).tolist()  # both loops'
                if any(map(math.isfinite, widths)):
                    interval = loop.cut_interval_s(measured_at)
                    cut = None if interval is None else (min(interval[0], t),
                                                         min(interval[1], t))
                    if self.attribution_trusted(att, measured_at, snap.cutter_to_camera_mm):
                        applied = self._learn_offsets(widths, pitch, cut, t)
                    else:
                        self._report.count("uniformity_skipped")
            finally:
                if not write.done():  # the PLC's answer; whatever the uniformity loop did
                    await asyncio.wait({write})
                failed = None if write.cancelled() else write.exception()
                taken = not write.cancelled() and failed is None and bool(write.result())
                if not taken:
                    loop.reject()  # the feed in force stays the one the PLC has
            if failed is not None:
                raise failed
            applied = applied or taken
        if applied:
            self._report.count("applied")
            self.remember(t)
        return applied

    async def _feed_write(self, feed_mm_s: float, t: float) -> asyncio.Future:
        """Start writing the feed setpoint; the write's task (its result: whether it was taken).

        The task runs until it waits for the PLC's answer (the request is on the wire, or waits
        for the bus behind the PLC cycle's request) before this returns: one turn of the event
        loop. Awaiting it later gives the same result as awaiting the write here.

        A moulder's head writes no feed (:attr:`Actuators.owns_feed` false: the coordinator
        writes the one feed, :meth:`Actuators.write_feed` takes it at once): a finished write,
        without a task or a turn of the loop in the middle of the pair.
        """
        if not self._writes_feed:
            taken = asyncio.get_running_loop().create_future()
            taken.set_result(True)  # (write_feed's answer for a head that owns no feed)
            return taken
        write = asyncio.ensure_future(self.out.write_feed(feed_mm_s, t))
        await asyncio.sleep(0)  # the write's task runs up to its first wait
        return write

    def _record_speed(self, t: float, snap: PlcSnapshot) -> None:
        self.condition.travel(t, snap)
        self.board_speed.record(t, snap.feed_actual_mm_s, snap.spindle_rpm / 60.0 * snap.knives)
        if self.feed_loop is not None:  # the feed loop learns against what the drive did
            self.feed_loop.observe_drive(now_s=t, feed_actual_mm_s=snap.feed_actual_mm_s,
                                         spindle_rpm=snap.spindle_rpm)

    def attribution_trusted(self, att: Attributed, measured_at: float, back_mm: float) -> bool:
        """Whether the attribution counted the knife passes the measured board was cut with.

        The attribution counts the passes between mark bottoms with the guide ``V / (n Z)`` at
        the pair (:attr:`Attributed.feed_per_pass_mm`); the board was cut ``L / V`` earlier.
        During a fast feed change (e.g. the start-up ramp of a two-knife head, 800 to
        300 mm/s) the two differ by up to a factor 2, the gaps count two passes where there
        was one, and every other knife looks vanished (width 0). The travel per pass it then
        fits to the bottoms (:attr:`Attributed.bdc_pitch_mm`) is off by the same factor from
        the feed per pass the board was cut with: the PLC's actual feed over the knife passing
        rate when the board was ``back_mm`` (the cutter-to-camera distance) short of where it
        was at ``measured_at`` (:attr:`board_speed`). Within :data:`PASS_TOL` the count holds;
        without history reaching back that far it is trusted.
        """
        fitted = float(att.bdc_pitch_mm)
        if not (math.isfinite(fitted) and fitted > 0):
            return True
        at_cut = self.board_speed.pass_travel_mm(measured_at, back_mm=back_mm)
        if at_cut is None:
            return True
        return 1.0 / (1.0 + PASS_TOL) <= fitted / at_cut <= 1.0 + PASS_TOL

    def _learn_offsets(
        self, widths: list[float], pitch: float, cut: tuple[float, float] | None, t: float
    ) -> bool:
        """One uniformity-loop update and its offsets on CAN; whether they were sent.

        ``cut``: when the first and the last mark of the measured window were cut (the loop
        learns against the table in force then), ``None`` when the feed history is too short.
        """
        cut_at = None if cut is None else cut[0]
        if not self.amp_tracked(cut_at, t):
            self._report.count("uniformity_skipped")
            return False
        chips = self.alerts.chips
        if chips is not None:  # the board was cut with the table the service sent
            chips.timeline.note(t, self.out.offsets_um)
            chips.pair(t, widths_mm=widths, pitch_mm=pitch,
                       cut_at_s=None if cut is None else 0.5 * (cut[0] + cut[1]))
        uni = self.uniformity_loop
        offs = uni.update(
            knife_widths_mm=widths, pitch_mm=pitch, now_s=t, cut_at_s=cut_at,
            cut_until_s=None if cut is None else cut[1],
        )
        try:
            sent = self.out.set_offsets(offs, t)
        except FieldbusError as exc:
            uni.reject()  # the table in force stays the one the board is cut with
            self._report.count("can_errors")
            self._report.emit(t, EventKind.OFFSETS_NOT_SENT, f"piezo offsets not sent: {exc}")
            return False
        self._learned_offsets = np.asarray(sent, dtype=float)
        self.condition.note(t, sent, limit_um=self.uniformity_loop.limit_um)
        if chips is not None:
            chips.timeline.note(t, sent)
        for note in uni.take_notices():  # the actuator cannot help: said once
            self._report.emit(t, EventKind.UNIFORMITY_NO_AUTHORITY, note.text, data=note.data)
        return True

    @property
    def board_travel_m(self) -> float:
        """Board travelled under the cutter since the service started (the PLC's feed), m."""
        return self.condition.board_travel_m

    def describe_knife_condition(self) -> dict[str, Any] | None:
        """The knives' condition for displays (:meth:`KnifeConditionWatch.describe`)."""
        return self.condition.describe()

    def describe_alerts(self) -> dict[str, Any]:
        """The alerts for the status (:meth:`OperatorAlerts.describe`).

        ``knife_chipped``: the newest knife told, chipped (a runout step) or nicked
        (:class:`KnifeNickMonitor`).
        """
        out = self.alerts.describe()
        nick = self.nicks.last
        chip = out.get("knife_chipped")
        if nick is not None and (chip is None or nick["t_s"] >= chip.get("t_s", -math.inf)):
            out["knife_chipped"] = dict(nick)
        return out

    def between_pairs(self, t: float, *, idle: bool) -> None:
        """Work that must not delay a pair, done after a pair's setpoints, before its record.

        ``idle``: no later pair waits for this one. The knife condition's forecast is renewed
        here when due (:meth:`KnifeConditionWatch.renew`), never inside a pair's control.
        """
        self.condition.renew(t, idle=idle)

    def amp_tracked(self, cut_at_s: float | None, t: float) -> bool:
        """Whether the board a measurement shows was cut while the amplifier played the offsets.

        The amplifier was last seen not tracking (disabled, ramping, faulted, refusing the
        table, or an enable not yet confirmed) at ``untracked_s``; board cut before that plus
        the offsets' settling time shows offsets that were not applied. Without a cut time
        (the feed loop's history is too short) the uniformity loop's hold-off is used instead.
        """
        last = self._amp_monitor.untracked_s
        if last is None:
            return True
        ucfg = self.uniformity_loop.cfg
        if cut_at_s is None:
            return t - ucfg.holdoff_s > last
        return cut_at_s - ucfg.settle_s > last

    def resume(self, t: float, snap: PlcSnapshot | None) -> None:
        """Back to RUN: restart the feed loop from the feed in force, restore learnt offsets."""
        t = self.loop_time(t)
        out = self.out
        if snap is not None and snap.problem() is None and self.feed_loop is not None:
            lo, hi = snap.feed_min_mm_s, snap.feed_max_mm_s
            feed = min(max(snap.feed_setpoint_mm_s, lo), hi)
            self.feed_loop.reset(feed_mm_s=feed, now_s=t, correction=self.feed_loop.correction)
            out.feed_setpoint_mm_s = feed
        out.enable(True, t)
        learned = self._learned_offsets
        uni = self.uniformity_loop
        if learned is not None and len(learned) == out.piezo.knives:
            if uni is not None and len(learned) == uni.cfg.knives:
                learned = uni.recovery_table_um(learned)  # the best, if the last was worse
            if self.alerts.chips is not None:  # board cut in the safe state is not compared
                self.alerts.chips.reset()
                self.alerts.chips.timeline.note(t, learned)
            try:
                out.offsets_um = out.piezo.set_offsets(learned, now_s=t)
                if self.uniformity_loop is not None:
                    self.uniformity_loop.reset(learned, now_s=t)
            except FieldbusError:
                self._report.count("can_errors")


class KnifeConditionWatch:
    """The knives' wear from the tables in force against the board travelled, and when to joint.

    Parameters
    ----------
    cfg : MachineConfig
        ``[quality]``: the target pitch, ``uniformity_max_cv``, ``board_length_mm``.
    report : EventLog
        Where ``JOINTING_DUE`` is said.
    """

    def __init__(self, cfg: MachineConfig, report: EventLog) -> None:
        self.cfg = cfg
        self._report = report
        self.tracker: KnifeConditionTracker | None = None
        self.board_travel_m = 0.0
        """Board travelled under the cutter since the service started (the PLC's feed), m."""
        self._travel_t: float | None = None
        self._snap: PlcSnapshot | None = None
        self._said = False
        self._condition: dict[str, Any] | None = None
        self._condition_t = -math.inf
        self._due_since: float | None = None  # a new table waits for its forecast since then

    def travel(self, t: float, snap: PlcSnapshot) -> None:
        """Add the board travelled since the last call at the PLC's actual feed."""
        if self._travel_t is not None and t > self._travel_t:
            self.board_travel_m += max(float(snap.feed_actual_mm_s), 0.0) * (
                t - self._travel_t) * 1e-3
        self._travel_t = t
        self._snap = snap

    def note(self, t: float, table: Any, *, limit_um: float) -> None:
        """The table in force now (cheap: the forecast is :meth:`renew`'s, between pairs)."""
        kc = self.tracker
        table = [float(v) for v in table]
        if kc is None or kc.knives != len(table) or kc.stroke_um != limit_um:
            kc = self.tracker = KnifeConditionTracker(knives=len(table), stroke_um=limit_um)
            self._said = False
        kc.update(board_m=self.board_travel_m, offsets_um=table)
        if self._due_since is None:
            self._due_since = t

    @property
    def due(self) -> bool:
        """Whether a table came since the last forecast (:meth:`renew` would compute one)."""
        return self._due_since is not None

    def renew(self, t: float, *, idle: bool = True) -> bool:
        """Renew the forecast when due; whether it was computed (1-2 ms).

        Due: a table came since the last one and :data:`CONDITION_EVERY_S` passed. Computed
        only when ``idle`` (no pair waits), or when it is :data:`CONDITION_LATE_S` overdue.
        """
        since = self._due_since
        if since is None or t - self._condition_t < CONDITION_EVERY_S:
            return False
        if not idle and t - max(since, self._condition_t + CONDITION_EVERY_S) < CONDITION_LATE_S:
            return False
        self._condition_t = t
        self._due_since = None
        self._condition = self._forecast(t)
        return True

    def describe(self) -> dict[str, Any] | None:
        """Each knife's offset, wear and reserve, and the jointing forecast (for displays).

        The last forecast :meth:`renew` computed, at most :data:`CONDITION_EVERY_S` plus a pair
        old while tables come (``None`` before the first table was applied).
        """
        return None if self._condition is None else dict(self._condition)

    def _forecast(self, t: float) -> dict[str, Any] | None:
        """The knives' condition now.

        ``state`` (:class:`~controller.laws.knife_condition.JointingState`'s value) and
        ``trend`` (:class:`~controller.laws.knife_condition.Trend`'s: ``none`` is not due for
        want of a significant wear trend, and gives no figures). Says ``JOINTING_DUE`` once
        when it comes within :data:`JOINTING_WARN_BOARDS` boards.
        """
        kc, snap = self.tracker, self._snap
        if kc is None or snap is None:
            return None
        q = self.cfg.quality
        fc = kc.forecast(pitch_mm=q.target_pitch_mm,
                         radius_mm=float(snap["cutterhead_radius_mm"]),
                         cv_max=q.uniformity_max_cv,
                         feed_mm_s=max(float(snap.feed_actual_mm_s), 1.0),
                         board_length_mm=q.board_length_mm)
        if (fc.due_in_boards is not None and fc.due_in_boards <= JOINTING_WARN_BOARDS
                and not self._said):
            self._said = True
            self._report.emit(t, EventKind.JOINTING_DUE, fc.text, data={
                "knife": fc.knife, "due_in_m": fc.due_in_m, "due_in_boards": fc.due_in_boards,
                "due_in_h": fc.due_in_h})
        return {
            "board_travel_m": self.board_travel_m,
            "knives": [{"knife": c.knife, "offset_um": c.offset_um,
                        "drift_um_per_m": None if math.isnan(c.drift_um_per_m)
                        else c.drift_um_per_m, "reserve_um": c.reserve_um}
                       for c in kc.conditions()],
            "due_in_m": fc.due_in_m, "due_in_boards": fc.due_in_boards,
            "due_in_h": fc.due_in_h, "knife": fc.knife, "text": fc.text,
            "state": fc.state.value, "trend": fc.trend.value, "t_s": t,
        }
