"""One image pair through the service's stages, in order.

1. :mod:`controller.frame_intake` — sequence gaps, the camera clock mapped to service time;
2. the PLC's registers in force (:meth:`BusCycles.snapshot_for`: the cycle's read, or a fresh
   one when it is stale);
3. :mod:`controller.measurement` — the vision's Measurer (a worker thread in real time) and the
   basic plausibility of its result;
4. :mod:`controller.mark_attribution` — which knife pass cut each mark, the pitch per pass
   (checked against ``V / (n Z)``);
5. :mod:`controller.control_loops` — in RUN, both loops on the valid measurement, the offsets
   (CAN) and the feed (Modbus) out through :mod:`controller.actuators`;
6. :mod:`controller.quality_records` — the pair's record, durable (log or journal).

Every pair gets exactly one record, whatever happens: a pair that cannot be measured changes
no setpoint and is logged with ``ok = false`` and the reason; an unexpected error of the
control code goes to the supervisor boundary (safe state), and the pair is still logged.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from controller.bus_cycles import BusCycles
from controller.control_loops import ControlLoops
from controller.events import EventLog, exc_name
from controller.frame_intake import FrameIntake, finite_or_none, int_or
from controller.frame_result import FrameResult
from controller.mark_attribution import Attributed, attribute_or_reason
from controller.measurement import MeasurementStage, failure_reason
from controller.plc_client import PlcSnapshot
from controller.quality_records import QualityRecords
from controller.safety import SafetyState
from controller.service_clock import ServiceClock
from controller.supervision import SafeStateKeeper
from protocol.frames import Frame


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
        self.last: FrameResult | None = None
        """The last pair's result."""
        self.keep_results = False
        self.results: list[FrameResult] = []
        self.on_result: Callable[[FrameResult], None] | None = None

    async def handle(self, frame: Frame, now_s: float | None = None) -> FrameResult:
        """Measure one pair, control, write setpoints, log it (see the module docstring)."""
        wall0 = time.perf_counter()
        t_arr = self.clock.now(now_s)
        self.report.count("frames")
        measured_at = self.intake.arrive(frame, t_arr)
        snap = await self.cycles.snapshot_for(t_arr)
        wall_plc = time.perf_counter()
        wall_meas = wall_plc
        meas: Any = None
        att: Attributed | None = None
        if frame.error:
            error: str | None = f"unreadable pair: {frame.error}"
        elif snap is None:
            error = "no PLC data: registers never read"
        elif (problem := snap.problem()) is not None:
            error = f"no valid PLC data: {problem}"
        else:
            # a vision error of a kind nobody named (VISION_ERRORS) is a failed measurement
            # too, and a fault of the service: the boundary reports it and goes safe
            with self.keeper.boundary(t_arr, f"measurement of pair {frame.seq}") as g:
                error, meas, att = await self._measure(frame, snap)
            if g.error is not None:
                error, meas, att = failure_reason(g.error), None, None
            wall_meas = time.perf_counter()
        ok = error is None
        applied = False
        profile = None
        keeper = self.keeper
        if ok:
            self.report.count("ok")
            profile = self.records.profile_of(meas, frame)
            keeper.supervisor.measurement_valid(t_arr)
            if keeper.state is SafetyState.RUN and snap is not None:
                t_ctrl = self.clock.now() if now_s is None else t_arr  # loops need forward time
                with keeper.boundary(t_ctrl, f"control of pair {frame.seq}"):
                    applied = await self.loops.apply(att, measured_at, snap, t_ctrl)
        else:
            self.report.count("failed")
        wall1 = time.perf_counter()
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
                    "control_ms": (wall1 - wall_meas) * 1e3,
                },
                "safe_reason": keeper.safe_reason(),
                "plc_feed_setpoint_mm_s": plc_feed,  # in force before the service wrote one
                **({"passes": att.to_json()} if att is not None else {}),
                **({"profile": profile} if profile is not None else {}),
            },
        )
        rid = await self.records.append(result, frame, t_arr)
        if rid is not None:
            result = replace(result, record_id=rid)
        self.last = result
        if self.keep_results:
            self.results.append(result)
        if self.on_result is not None:
            self.on_result(result)
        return result

    async def _measure(
        self, frame: Frame, snap: PlcSnapshot
    ) -> tuple[str | None, Any, Attributed | None]:
        """Measure the pair, check it, attribute its marks: ``(error, measurement, attributed)``.

        The order: basic plausibility (marks, confidence, machine running), attribution of the
        marks to knife passes, then the pitch per knife pass against ``V / (n Z)``.
        """
        try:
            self.loops.ensure(snap)
        except (ValueError, LookupError, TypeError, ArithmeticError) as exc:
            return f"no control loops: {exc_name(exc)}: {exc}", None, None
        error, meas = await self.measurement.measure(frame, snap)
        if error is not None:
            return error, None, None
        error = self.measurement.implausible(meas, frame, snap)
        if error is not None:
            return error, meas, None
        att, error = attribute_or_reason(meas, frame, snap, self.rig)
        if att is None:
            return error, meas, None
        error = self.measurement.implausible_pitch(att.pass_pitch_mm, frame, snap)
        return error, meas, (att if error is None else None)
