"""One image pair through the service's stages, in order.

1. :mod:`controller.service.intake` — sequence gaps, the camera clock mapped to service time;
2. the PLC's registers in force (:meth:`BusCycles.snapshot_for`: the cycle's read, or a fresh
   one when it is stale);
3. :mod:`controller.service.measurement` — the vision's Measurer (a worker thread in real time)
and the
   basic plausibility of its result;
4. :mod:`controller.service.attribution` — which knife pass cut each mark, the pitch per pass
   (checked against ``V / (n Z)``);
5. :mod:`controller.service.loops` — in RUN, both loops on the valid measurement, the offsets
   (CAN) and the feed (Modbus) out through :mod:`controller.service.actuators`;
6. :mod:`controller.service.records` — the pair's record, durable (log or journal).

A pair is *handled* when its record is durable: only then is it counted (``ok`` / ``failed``),
shown as the last measurement and told to ``on_result``. Inline that is before
:meth:`PairPipeline.handle` returns; in real time the journal thread says so milliseconds
after the setpoints went out (the setpoints never wait for the disk).

Every pair gets exactly one record, whatever happens: a pair that cannot be measured changes
no setpoint and is logged with ``ok = false`` and the reason; an unexpected error of the
control code goes to the supervisor boundary (safe state), and the pair is still logged.

:meth:`PairPipeline.handle` takes one pair through every stage before it returns.
:meth:`PairPipeline.submit` (real time, measurement in worker processes) runs stages 1-2 and
hands the pair to a worker at once, then returns so the next pair can come while this one is
measured; stages 3-5 of the pairs run in sequence order (each waits for the pair before it
to be through its setpoints), so the loops see the pairs in order whichever worker finishes
first. What follows a pair's setpoints -- its record's profile, queueing the record, counting
it, the garbage collector -- is bookkeeping: in real time it waits in the event loop's
:class:`~controller.service.after_setpoint.AfterSetpoint` queue while a pair of any pipeline
on the loop is ready for its setpoints (the records of each pipeline in order). Everything a
record says of the service (setpoints, state, safe reason, the amplifier's fields, the knife
condition) is taken when the pair's setpoints went out, as before.
:meth:`PairPipeline.drain` waits for the pairs in flight and their bookkeeping.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from controller.fieldbus.plc_protocol import PlcSnapshot
from controller.service.after_setpoint import AfterSetpoint, after_setpoint_queue
from controller.service.attribution import Attributed, attribute_or_reason
from controller.service.bus_cycles import BusCycles
from controller.service.clock import ServiceClock
from controller.service.cut_feed import PairFeedHistory
from controller.service.events import EventKind, EventLog, exc_name
from controller.service.frame_result import FrameResult, refused_surface_of
from controller.service.intake import FrameIntake, finite_or_none, int_or
from controller.service.latency import collect_between_pairs
from controller.service.loops import ControlLoops
from controller.service.measurement import (
    MeasurementStage,
    PendingMeasurement,
    expected_pitch_mm,
    failure_reason,
)
from controller.service.records import QualityRecords
from controller.service.safe_state import SafeStateKeeper
from controller.service.supervisor import SafetyState
from protocol.frames import Frame


@dataclass
class _Pair:
    """A pair between its arrival (stages 1-2, measurement started) and its record."""

    frame: Frame
    now_s: float | None
    wall0: float
    t_arr: float
    measured_at: float
    snap: PlcSnapshot | None
    wall_plc: float
    error: str | None = None
    pending: PendingMeasurement | None = None
    passed: asyncio.Future | None = None  # real time: set once through its setpoints


class PairPipeline:
    """The stages a pair goes through, wired once by the composition root."""

    def __init__(
        self,
        *,
        clock: ServiceClock,
        intake: FrameIntake,
        cycles: BusCycles,
        measurement: MeasurementStage,
        loops: ControlLoops,
        keeper: SafeStateKeeper,
        records: QualityRecords,
        report: EventLog,
        rig: Any,
    ) -> None:
        self.clock = clock
        self.intake = intake
        self.cycles = cycles
        self.measurement = measurement
        self.loops = loops
        self.keeper = keeper
        self.records = records
        self.report = report
        self.rig = rig
        cam = getattr(rig, "camera", None)
        try:  # the optical axis in image A along the feed, mm (where a defect is on the board)
            self._frame_centre_mm = finite_or_none(cam.cx / cam.px_per_mm)
        except (AttributeError, TypeError, ZeroDivisionError):
            self._frame_centre_mm = None
        self.pair_feeds = PairFeedHistory()
        """Each pair's feed per knife pass by board position: the feed when the marks of a
        later pair were cut (:mod:`controller.service.cut_feed`)."""
        self.last: FrameResult | None = None
        """The last pair's result."""
        self.keep_results = False
        self.results: list[FrameResult] = []
        self.on_result: Callable[[FrameResult], None] | None = None
        self._tail: asyncio.Future | None = None  # the last submitted pair's `passed`
        self._before_setpoints: deque[_Pair] = deque()  # submitted, not through setpoints
        self._in_flight: set[asyncio.Task] = set()
        self._after: AfterSetpoint | None = None  # the running loop's bookkeeping queue
        records.on_handled = self._handled_later  # real time: handled once durable

    async def handle(self, frame: Frame, now_s: float | None = None) -> FrameResult:
        """Measure one pair, control, write setpoints, log it (see the module docstring)."""
        pair = await self._begin(frame, now_s)
        result, meas = await self._setpoints(pair)
        idle = self._between_pairs(pair, waiting=len(self._in_flight))
        result = await self._book(pair, result, meas)
        self._collect(idle, None)
        return result

    def _between_pairs(self, pair: _Pair, *, waiting: int) -> bool:
        """After a pair's setpoints: the knife condition's forecast when due; whether idle.

        ``waiting``: the pairs not yet through (this one and any later); idle when no later
        pair waits for this one. The forecast is renewed here, never inside a pair's control
        (:meth:`ControlLoops.between_pairs`); both paths (:meth:`handle`, real time's
        :meth:`_finish_after`) end a pair through this and :meth:`_collect`.
        """
        idle = waiting <= 1
        self.loops.between_pairs(pair.t_arr, idle=idle)
        return idle

    @staticmethod
    def _collect(idle: bool, after: AfterSetpoint | None) -> None:
        """After a pair's record: the garbage collector when due, if no later pair waits.

        At once inline (``after`` ``None``: a pause costs nothing); in real time when no pair
        of any pipeline on the loop is ready for its setpoints (:meth:`AfterSetpoint.collect`).
        """
        if not idle:
            return
        if after is None:
            collect_between_pairs()
        else:
            after.collect()

    def use_workers(self, pool: Any) -> None:
        """Measure in worker processes from the next pair on (``None``: in this process again).

        A worker that died or timed out is reported (``SERVICE_ERROR``, counter
        ``worker_restarts``); its pairs are failed records naming the reason. Several pipelines
        may share one pool (a moulder's heads): each is told of every worker's problem; given
        as :class:`controller.workers.pool.PoolForFactory` its pairs are measured with its own
        measurer factory (its rig), else with the pool's.
        """
        self.measurement.use_workers(pool)
        if pool is not None:
            listen = getattr(pool, "listen", None)
            if callable(listen):  # a pool the heads of a moulder share: each hears of it
                listen(self._worker_problem)
            else:
                pool.on_problem = self._worker_problem

    def _worker_problem(self, text: str) -> None:
        counters = self.report.counters
        counters["worker_restarts"] = counters.get("worker_restarts", 0) + 1
        t = self.clock.last_s
        self.report.emit(0.0 if t is None else t, EventKind.SERVICE_ERROR, text)

    @property
    def in_flight(self) -> int:
        """Submitted pairs whose stages 3-6 have not finished."""
        return len(self._in_flight)

    def setpoints_ready(self) -> bool:
        """Whether the next pair could go through its setpoints now (real time).

        Its measurement is back (or it has none: a pair failed on arrival) and the pairs before
        it are through theirs: :class:`~controller.service.after_setpoint.AfterSetpoint` lets it
        go before queued bookkeeping.
        """
        waiting = self._before_setpoints
        if not waiting:
            return False
        pending = waiting[0].pending
        future = None if pending is None else pending.future
        return future is None or future.done()

    async def submit(self, frame: Frame) -> None:
        """Take one pair in real time; return as soon as the next one may come.

        Without worker processes this is :meth:`handle`. With them the pair is handed to a
        worker and its later stages run after the previous pair's, in sequence order; this
        returns at once unless the workers hold as many pairs as they can
        (``MeasureWorkerPool.capacity``).
        """
        pool = self.measurement.pool
        if pool is None:
            await self.handle(frame)
            return
        pair = await self._begin(frame, None)
        loop = asyncio.get_running_loop()
        if self._after is None or self._after.loop is not loop:
            self._after = after_setpoint_queue(loop)
            self._after.register(self)
        pair.passed = loop.create_future()
        previous, self._tail = self._tail, pair.passed
        self._before_setpoints.append(pair)
        task = asyncio.ensure_future(self._finish_after(previous, pair))
        self._in_flight.add(task)
        task.add_done_callback(self._in_flight.discard)
        while len(self._in_flight) >= max(1, pool.capacity):
            await asyncio.wait(set(self._in_flight), return_when=asyncio.FIRST_COMPLETED)

    async def _finish_after(self, previous: asyncio.Future | None, pair: _Pair) -> None:
        """Real time: stages 3-5, then the bookkeeping in its turn.

        ``previous``: the ``passed`` of the pair submitted before (stages 3-5 wait for it).
        """
        if previous is not None and not previous.done():
            await asyncio.wait({previous})  # the pairs before through their setpoints
        what = f"pair {pair.frame.seq}"
        out = None
        idle = False
        try:
            with self.keeper.boundary(pair.t_arr, what):
                out = await self._setpoints(pair)
                idle = self._between_pairs(pair, waiting=len(self._before_setpoints))
        finally:
            self._passed(pair)
        if out is None:
            return
        after = self._after
        assert after is not None
        await after.turn()  # no pair of any head on the loop ready for its setpoints
        try:
            with self.keeper.boundary(pair.t_arr, what):
                await self._book(pair, *out)
        finally:
            after.done()
        self._collect(idle, after)  # no later pair of this head: when no pair on the loop is ready

    def _passed(self, pair: _Pair) -> None:
        """``pair`` is through its setpoints (or failed on the way): the next one may go."""
        waiting = self._before_setpoints
        if waiting and waiting[0] is pair:
            waiting.popleft()
        else:
            try:
                waiting.remove(pair)
            except ValueError:
                pass
        if pair.passed is not None and not pair.passed.done():
            pair.passed.set_result(None)
        if self._after is not None:
            self._after.setpoint_done()

    async def drain(self) -> None:
        """Wait until every submitted pair went through all its stages."""
        while self._in_flight:
            await asyncio.wait(set(self._in_flight))

    async def _begin(self, frame: Frame, now_s: float | None) -> _Pair:
        """Stages 1-2 and the start of the measurement (handed to a worker process at once)."""
        wall0 = time.perf_counter()
        t_arr = self.clock.now(now_s)
        self.report.count("frames")
        measured_at = self.intake.arrive(frame, t_arr)
        snap = await self.cycles.snapshot_for(t_arr)
        pair = _Pair(frame, now_s, wall0, t_arr, measured_at, snap, time.perf_counter())
        if frame.error:
            pair.error = f"unreadable pair: {frame.error}"
        elif snap is None:
            pair.error = "no PLC data: registers never read"
        elif (problem := snap.problem()) is not None:
            pair.error = f"no valid PLC data: {problem}"
        else:
            self._note_feed(frame, snap)
            with self.keeper.boundary(t_arr, f"measurement of pair {frame.seq}") as g:
                try:
                    self.loops.ensure(snap)
                except (ValueError, LookupError, TypeError, ArithmeticError) as exc:
                    pair.error = f"no control loops: {exc_name(exc)}: {exc}"
                else:
                    pair.pending = self.measurement.start(frame, snap)
            if g.error is not None:
                pair.error = failure_reason(g.error)
        return pair

    def _note_feed(self, frame: Frame, snap: PlcSnapshot) -> None:
        """Keep the pair's board position and feed per pass (a sound register read)."""
        try:
            self.pair_feeds.note(
                int(frame.counts_a), float(frame.t_s), expected_pitch_mm(frame, snap),
                snap.knives, counter_bits=self.rig.encoder.counter_bits,
                counts_per_mm=snap.counts_per_mm, keep_mm=snap.cutter_to_camera_mm)
        except (AttributeError, TypeError, ValueError, ArithmeticError):
            pass  # no position or feed of this pair: later pairs fall back on the PLC's

    async def _setpoints(self, pair: _Pair) -> tuple[FrameResult, Any]:
        """Stages 3-5: the measurement's result, attribution, control; the pair's result.

        The result (without its profile, which :meth:`_book` adds) says what the service was
        when the setpoints went out. Returns ``(result, measurement)``.
        """
        frame, now_s, wall0, t_arr = pair.frame, pair.now_s, pair.wall0, pair.t_arr
        measured_at, snap, wall_plc = pair.measured_at, pair.snap, pair.wall_plc
        wall_meas = wall_plc
        meas: Any = None
        att: Attributed | None = None
        error = pair.error
        vision_s = 0.0
        checks_s = 0.0
        if pair.pending is not None and snap is not None:
            # a vision error of a kind nobody named (VISION_ERRORS) is a failed measurement
            # too, and a fault of the service: the boundary reports it and goes safe
            with self.keeper.boundary(t_arr, f"measurement of pair {frame.seq}") as g:
                error, meas, att = await self._measured(pair.pending, frame, snap)
            if g.error is not None:
                error, meas, att = failure_reason(g.error), None, None
            wall_meas = time.perf_counter()
            vision_s = pair.pending.measure_s
            if pair.pending.finished_at > 0:
                checks_s = max(0.0, wall_meas - pair.pending.finished_at)
        ok = error is None
        applied = False
        keeper = self.keeper
        if ok:
            keeper.supervisor.measurement_valid(t_arr)
            if keeper.state is SafetyState.RUN and snap is not None:
                t_ctrl = self.clock.now() if now_s is None else t_arr  # loops need forward time
                with keeper.boundary(t_ctrl, f"control of pair {frame.seq}"):
                    applied = await self.loops.apply(att, measured_at, snap, t_ctrl)
        self.loops.alerts.failures.pair(t_arr, ok, error)  # a measurement that keeps failing
        # a nicked knife: the defect detector's ridge (when it looks), also on a pair the
        # cuttermark measurement refused (its surface was still looked at)
        surface = meas if meas is not None else refused_surface_of(error)
        if surface is not None:
            self.loops.nicks.pair(t_arr, getattr(surface, "defects", None), seq=frame.seq)
        wall1 = time.perf_counter()  # the setpoints are out: what follows is for the record
        out = self.loops.out
        plc_feed = None if snap is None else finite_or_none(snap.feed_setpoint_mm_s)
        result = FrameResult(
            seq=frame.seq,
            ok=ok,
            error=error,
            measurement=meas,
            knife_widths_mm=() if att is None else tuple(float(w) for w in att.knife_widths_mm),
            applied=applied,
            feed_setpoint_mm_s=out.feed_setpoint_mm_s,
            offsets_um=tuple(out.offsets_um),
            state=keeper.state.value,
            t_s=t_arr,
            latency_s=wall1 - wall0,
            truth=frame.truth,
            counts_a=int_or(frame.counts_a, 0),
            frame_t_s=finite_or_none(frame.t_s) or 0.0,
            extra={
                "timing_ms": {
                    "plc_read_ms": (wall_plc - wall0) * 1e3,
                    "measure_ms": (wall_meas - wall_plc) * 1e3,
                    "vision_ms": vision_s * 1e3,
                    "checks_ms": checks_s * 1e3,  # plausibility and attribution (in measure_ms)
                    "control_ms": (wall1 - wall_meas) * 1e3,
                },
                "safe_reason": keeper.safe_reason(),
                "piezo": out.record_fields(),  # limit in force, refused tables, safe entries
                "plc_feed_setpoint_mm_s": plc_feed,  # in force before the service wrote one
                "knife_condition": self.loops.describe_knife_condition(),  # the last forecast
                # the board under the camera (the page's board strip, OPC UA's board grade)
                "board_id": int_or(frame.board_id, 0),
                "board_position_mm": finite_or_none(frame.board_position_mm),
                "frame_centre_x_mm": self._frame_centre_mm,  # the optical axis in image A, mm
                **({"passes": att.to_json()} if att is not None else {}),
            },
        )
        return result, meas

    async def _book(self, pair: _Pair, result: FrameResult, meas: Any) -> FrameResult:
        """Stage 6: the record (its profile, every tenth pair's: up to 0.5 ms), the count.

        Nothing here waits before the record is queued (only after, for the journal's room):
        bookkeeping released together queues its records in the order it was released.
        """
        frame = pair.frame
        if result.ok:
            profile = self.records.profile_of(meas, frame)
            if profile is not None:  # the last key of the record's extra, as it always was
                result.extra["profile"] = profile
        rid = await self.records.append(result, frame, pair.t_arr)
        if rid is not None:
            result = replace(result, record_id=rid)
        if not self.records.defers_handling:  # the record is durable (or there is no log)
            self._handled(result)
        return result

    def _handled(self, result: FrameResult) -> None:
        """The pair is handled (its record durable): count it, show it, tell ``on_result``."""
        self.report.count("ok" if result.ok else "failed")
        self.last = result
        if self.keep_results:
            self.results.append(result)
        if self.on_result is not None:
            self.on_result(result)

    def _handled_later(self, result: FrameResult) -> None:
        """Real time: :meth:`_handled` when the journal says the record is durable."""
        with self.keeper.boundary(result.t_s, f"result of pair {result.seq}"):
            self._handled(result)

    async def _measured(
        self, pending: PendingMeasurement, frame: Frame, snap: PlcSnapshot
    ) -> tuple[str | None, Any, Attributed | None]:
        """The pair measured, checked, its marks attributed: ``(error, measurement, attributed)``.

        The order: basic plausibility (marks, confidence, machine running), attribution of the
        marks to knife passes, then the pitch per knife pass against ``V / (n Z)``.
        """
        error, meas = await self.measurement.finish(pending)
        pending.finished_at = time.perf_counter()
        if error is not None:
            return error, None, None
        error = self.measurement.implausible(meas, frame, snap)
        if error is not None:
            return error, meas, None
        att, error = attribute_or_reason(
            meas, frame, snap, self.rig, pairs=self.pair_feeds,
            plc=self.measurement.feed_history,
            pass_tolerance=self.measurement.plausibility.pass_tolerance)
        if att is None:
            return error, meas, None
        error = self.measurement.implausible_pitch(att.pass_pitch_mm, frame, snap)
        return error, meas, (att if error is None else None)
