"""The service beside the PLC: image pairs in, marks measured, feed and piezo setpoints out.

This module is the composition root: :class:`Service` wires the parts, each with one job and
its own module, and owns nothing else (``docs/service.md``):

* :mod:`controller.service.clock` — service time (never backwards);
* :mod:`controller.service.intake` — sequence gaps, camera clock, frame metadata;
* :mod:`controller.service.measurement` — the vision's Measurer, failures and plausibility;
* :mod:`controller.service.attribution` — which knife cut which mark;
* :mod:`controller.service.loops` — the feed and uniformity loops;
* :mod:`controller.service.actuators` — feed setpoint and heartbeat (Modbus), offsets and commands
(CAN);
* :mod:`controller.service.safe_state` — the supervisor, the safe state, the one supervisor
boundary;
* :mod:`controller.service.bus_cycles` — the PLC's and the amplifier's cyclic work;
* :mod:`controller.service.records` — one durable record per pair (log or journal);
* :mod:`controller.service.pipeline` — a pair through those stages, in order.

The entry points, all with the time passed in: :meth:`Service.plc_cycle` (every
``safety.cycle_s``), :meth:`Service.can_cycle` (every ``can.command_period_s``, never waits),
:meth:`Service.tick` (both at one instant, simulated time), :meth:`Service.handle_frame` (one
pair), :meth:`Service.run` (real time from a frame source, one task per bus), and
:meth:`Service.close`. Later features plug in from outside: :meth:`Service.status` (a frozen
snapshot for OPC UA or a web page), ``on_event`` / ``on_result`` callbacks, and the measurer
factory (a worker-process measurer is another factory).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from config.machine import MachineConfig
from controller.fieldbus.piezo_client import PiezoClient
from controller.fieldbus.plc_client import PlcClient
from controller.quality.learned_state import learned_memory_of
from controller.service.actuators import Actuators
from controller.service.bus_cycles import BusCycles
from controller.service.clock import ServiceClock
from controller.service.events import EventKind, EventLog, ServiceEvent, exc_name
from controller.service.frame_result import FrameResult
from controller.service.intake import FrameIntake
from controller.service.loops import ControlLoops
from controller.service.measurement import MeasurementStage, VisionMeasurers
from controller.service.pipeline import PairPipeline
from controller.service.records import QualityRecords
from controller.service.safe_state import SafeStateKeeper
from controller.service.status import MeasurementSummary, ServiceStatus
from controller.service.supervisor import AmplifierMonitor, SafetyState, SafetyStatus
from protocol.frames import Frame

__all__ = ["FrameResult", "Service", "ServiceStatus", "default_log_path", "open_service"]


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
    measurer_factory : callable, optional
        ``factory(shape) -> measurer`` with ``measurer.measure(image_a, image_b, *, counts_a,
        counts_b, speed_mm_s) -> Measurement``; called once per image shape. Default
        (``None``): :class:`~controller.service.measurement.VisionMeasurers` of ``rig`` -- the
        vision's
        ``Measurer`` with the PLC's cutting radius and knives, self-calibrating per board.
    rig : Rig
        The rig (``px_per_mm``, ``cx`` for the mark-to-knife phase; field of view).
    log : QualityLog or None
        Where every measurement goes (``None``: not logged); records it cannot take wait in a
        journal beside it (``<log>.journal.jsonl``).
    clock : callable
        Monotonic seconds; default ``time.monotonic``. Simulated time in tests and HIL.
    threaded : bool
        Run the measurement and the log append in worker threads (real time). ``False`` runs
        them inline (deterministic simulated-time runs).
    pairs_per_s : float
        Nominal camera rate (sample time of the feed loop), pairs per second.
    owns_feed : bool
        Write the PLC's feed setpoint and heartbeat (a single-head machine). ``False``: one head
        of a moulder (:class:`controller.moulder.service.MoulderService` writes the one feed).
    """

    def __init__(
        self,
        cfg: MachineConfig,
        *,
        plc: PlcClient,
        piezo: PiezoClient,
        measurer_factory: Callable[..., Any] | None = None,
        rig: Any,
        log: Any = None,
        clock: Callable[[], float] = time.monotonic,
        threaded: bool = True,
        pairs_per_s: float = 10.0,
        owns_feed: bool = True,
    ) -> None:
        self.cfg = cfg
        self.plc = plc
        self.piezo = piezo
        self.rig = rig
        self.log = log
        self.clock = clock
        self.threaded = threaded
        self.pairs_per_s = float(pairs_per_s)
        self.report = EventLog()
        if measurer_factory is None:
            measurer_factory = VisionMeasurers(rig, defects=cfg.quality.defects)
        self.measurement = MeasurementStage(cfg.plausibility, measurer_factory, threaded=threaded)
        shape = cfg.frames.image_shape
        if shape is not None:
            # set-up before the first pair (imports, tables); a factory taking the machine's
            # facts builds again, once, at the first pair with the PLC's R and Z (20-60 ms, in
            # the worker thread in real time)
            self.measurement.measurer(shape)
        self.service_clock = ServiceClock(clock, self.report)
        amp_monitor = AmplifierMonitor()
        self.out = Actuators(plc, piezo, self.report, amp_monitor, stroke_um=cfg.stroke_um,
                             owns_feed=owns_feed)
        self.loops = ControlLoops(cfg, rig, self.out, self.report, amp_monitor,
                                  pairs_per_s=self.pairs_per_s)
        self.out.on_stroke = getattr(self.loops, "set_limit_um", None)  # the bound in force
        self.keeper = SafeStateKeeper(cfg.safety, self.report, self.out, amp_monitor,
                                      now_s=clock())
        self.keeper.on_recovered = lambda t: self.loops.resume(t, self.plc.last)
        self.head = cfg.heads[0].name
        """The cutterhead this service controls (``"main"``: a single-head machine)."""
        # the learnt state across restarts, per head
        self.loops.memory = learned_memory_of(log, head=self.head)
        self.loops.on_warm_start = self.keeper.supervisor.warm_start
        self.records = QualityRecords(
            cfg, log, self.report, threaded=threaded, head=self.head,
            on_health=lambda ok: self.keeper.supervisor.set_ok("log", ok),
        )
        self.quality_class = self.records.quality_class
        self.cycles = BusCycles(cfg, plc, self.keeper, self.loops, self.out, self.report)
        self.pipeline = PairPipeline(
            clock=self.service_clock, intake=FrameIntake(self.report), cycles=self.cycles,
            measurement=self.measurement, loops=self.loops, keeper=self.keeper,
            records=self.records, report=self.report, rig=rig,
        )

    # ------------------------------------------------------------------ what others read
    @property
    def state(self) -> SafetyState:
        """The supervisor's state."""
        return self.keeper.state

    @property
    def events(self) -> list[ServiceEvent]:
        """Every event so far, in order."""
        return self.report.events

    @property
    def counters(self) -> dict[str, int]:
        """The counters (``frames``, ``ok``, ``failed``, ``applied``, ``safe_entries`` ...)."""
        return self.report.counters

    @property
    def on_event(self) -> Callable[[ServiceEvent], None] | None:
        """Called with each :class:`ServiceEvent` as it happens."""
        return self.report.on_event

    @on_event.setter
    def on_event(self, fn: Callable[[ServiceEvent], None] | None) -> None:
        self.report.on_event = fn

    @property
    def on_result(self) -> Callable[[FrameResult], None] | None:
        """Called with each pair's :class:`FrameResult` once the pair is handled.

        Handled: its quality record is durable (in real time: on the event loop, milliseconds
        after the pair's setpoints went out).
        """
        return self.pipeline.on_result

    @on_result.setter
    def on_result(self, fn: Callable[[FrameResult], None] | None) -> None:
        self.pipeline.on_result = fn

    @property
    def keep_results(self) -> bool:
        """Whether :attr:`results` keeps every pair's result (HIL, benchmarks)."""
        return self.pipeline.keep_results

    @keep_results.setter
    def keep_results(self, keep: bool) -> None:
        self.pipeline.keep_results = bool(keep)

    @property
    def results(self) -> list[FrameResult]:
        """The kept results (see :attr:`keep_results`)."""
        return self.pipeline.results

    @property
    def feed_setpoint_mm_s(self) -> float | None:
        """Feed setpoint in force, mm/s."""
        return self.out.feed_setpoint_mm_s

    @property
    def offsets_um(self) -> tuple[float, ...]:
        """Piezo offsets in force, um."""
        return self.out.offsets_um

    @property
    def feed_loop(self) -> Any:
        """The feed loop (``None`` before the first valid register read)."""
        return self.loops.feed_loop

    @property
    def uniformity_loop(self) -> Any:
        """The uniformity loop (``None`` before the first valid register read)."""
        return self.loops.uniformity_loop

    def measurer(self, shape: tuple[int, int]) -> Any:
        """The measurer for images of ``shape`` (built once per shape)."""
        return self.measurement.measurer(shape)

    def status(self) -> ServiceStatus:
        """A read-only snapshot: state, safe reason, setpoints, last measurement, counters."""
        keeper = self.keeper
        snap = self.plc.last if self.plc is not None else None
        last = self.pipeline.last
        st = keeper.status
        return ServiceStatus(
            t_s=self.service_clock.last_s,
            state=keeper.state.value,
            safe_reason=keeper.safe_reason(),
            missing=() if st is None else tuple(st.missing),
            feed_setpoint_mm_s=self.out.feed_setpoint_mm_s,
            feed_actual_mm_s=None if snap is None else float(snap.feed_actual_mm_s),
            offsets_um=tuple(self.out.offsets_um),
            amplifier_enabled=bool(self.piezo.enable) if self.piezo is not None else False,
            last_measurement=None if last is None else MeasurementSummary.of(last),
            counters=ServiceStatus.freeze(self.report.counters),
            log_problem=self.records.problem,
            records_pending=self.records.pending,
            alerts=self.loops.describe_alerts(),  # the newest knife chipped or nicked
            piezo_limits=self.out.limits() if self.piezo is not None else None,
            uniformity=(None if self.loops.uniformity_loop is None
                        else self.loops.uniformity_loop.describe()),
            knife_condition=self.loops.describe_knife_condition(),
        )

    # ------------------------------------------------------------------ the control cycles
    async def tick(self, now_s: float | None = None) -> SafetyStatus:
        """One control cycle of both buses, in order (simulated time, the in-process HIL).

        The PLC's heartbeat and register read, then the CAN cycle (:meth:`can_cycle`), then the
        PLC's actions (feed-forward in RUN, hold or ramp in SAFE). :meth:`run` calls the two
        cycles from separate tasks instead, so a PLC that does not answer never holds up the
        CAN heartbeat. Never raises for what the world does nor for the service's own
        unexpected errors (the supervisor boundary: safe state, the heartbeats go on).

        Parameters
        ----------
        now_s : float, optional
            Service time; default ``clock()``.

        Returns
        -------
        SafetyStatus
            The supervisor's decision of this cycle.
        """
        t = self.service_clock.now(now_s)
        snap = None
        with self.keeper.boundary(t, "PLC cycle", part="plc") as io:
            snap = await self.cycles.plc_io(t)
        status = self._can_cycle(t)
        if io.failed:
            return status
        with self.keeper.boundary(t, "PLC cycle", part="plc") as act:
            await self.cycles.plc_actions(t, snap)
        if act.failed:
            assert act.status is not None
            return act.status
        self.keeper.clean("plc")
        return status

    async def plc_cycle(self, now_s: float | None = None) -> None:
        """The PLC's cycle (its own task in :meth:`run`): heartbeat, read, supervisor, feed.

        Only the PLC's bus is touched here (offsets are zeroed by the supervisor's state
        change, a non-blocking CAN send). Never raises.
        """
        t = self.service_clock.now(now_s)
        with self.keeper.boundary(t, "PLC cycle", part="plc") as g:
            snap = await self.cycles.plc_io(t)
            self.measurement.prepare(snap)  # set up for the PLC's R and Z before the pair
            self.keeper.step(t)
            await self.cycles.plc_actions(t, snap)
        if not g.failed:
            self.keeper.clean("plc")

    def can_cycle(self, now_s: float | None = None) -> SafetyStatus:
        """The CAN cycle (its own task in :meth:`run`): never waits for anything.

        Drains the amplifier's frames (non-blocking), judges its status, steps the supervisor,
        enables the amplifier in RUN or sends zero offsets and a disable in SAFE, and sends
        the amplifier's command (RPDO3) with a new alive counter. Never raises.
        """
        return self._can_cycle(self.service_clock.now(now_s))

    def _can_cycle(self, t: float) -> SafetyStatus:
        with self.keeper.boundary(t, "CAN cycle", part="can") as g:
            status = self.cycles.can_cycle(t)
        if g.failed:
            assert g.status is not None
            return g.status
        self.keeper.clean("can")
        return status

    async def handle_frame(self, frame: Frame, *, now_s: float | None = None) -> FrameResult:
        """Measure one pair, control, write setpoints, log it (:mod:`controller.service.pipeline`).

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
        """
        return await self.pipeline.handle(frame, now_s)

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
        that takes its full timeout never delays the amplifier's command (its setpoint
        timeout is 100 ms). The frame task awaits ``source.next()`` and calls
        :meth:`handle_frame`; the measurement runs in a worker thread. Requests to the PLC from
        the PLC task and the frame task go through the one client, one at a time.
        """
        stop = stop or asyncio.Event()
        plc_period = self.cfg.safety.cycle_s
        can_period = min(self.cfg.can.command_period_s, plc_period)
        count = FrameCount(max_frames)
        tasks = [
            asyncio.create_task(run_periodic(can_period, self.can_cycle, stop)),
            asyncio.create_task(run_periodic(plc_period, self.plc_cycle, stop)),
            asyncio.create_task(self.take_frames(source, stop, count)),
        ]
        try:
            await run_until_stopped(tasks, stop)
        finally:
            await self.finish(source)

    async def take_frames(self, source: Any, stop: asyncio.Event, count: FrameCount) -> None:
        """The frame task of :meth:`run`: each pair of ``source`` into the pipeline until stopped.

        ``count`` is shared by every frame task of a run (a moulder's heads): the pair that
        reaches its ``max_frames`` drains the pipeline and sets ``stop``.
        """
        while not stop.is_set():
            frame = await self._next_frame(source)
            if frame is None:
                continue
            t = self.service_clock.now()
            with self.keeper.boundary(t, f"pair {frame.seq}"):
                await self.pipeline.submit(frame)  # handle_frame, or to a worker process
            if count.add():
                await self.pipeline.drain()
                stop.set()

    async def finish(self, source: Any) -> None:
        """After a real-time run: the pairs still with the workers, the records, the skips."""
        await self.pipeline.drain()  # pairs still with the workers get their records
        await self.records.settle()  # ... and the last pairs are handled (journal, ms)
        self._report_skips(source)  # the run's last files too: a record or a named skip

    async def _next_frame(self, source: Any) -> Frame | None:
        """The next pair of ``source`` (``None``: none within 0.1 s, or the source failed)."""
        t = self.service_clock.now()
        frame = None
        with self.keeper.boundary(t, "frame source", part="source") as g:
            try:
                frame = await source.next(timeout_s=0.1)
            except (OSError, ValueError) as exc:  # a broken source must not stop us
                self.report.count("errors")
                self.keeper.report_once(t, EventKind.FRAME_SOURCE_FAILED,
                                        f"frame source failed: {exc_name(exc)}: {exc}")
                await asyncio.sleep(0.1)
                return None
        if g.failed:
            await asyncio.sleep(0.1)
            return None
        self.keeper.clean("source")
        self._report_skips(source)
        return frame

    def _report_skips(self, source: Any) -> None:
        """One ``SPOOL_SKIPPED`` event per spool file that gave no pair (``take_skips``)."""
        take = getattr(source, "take_skips", None)
        if take is None:
            return
        try:
            skips = take()
        except (OSError, ValueError):  # a broken source is reported by _next_frame
            return
        for skip in skips:
            self.report.count("spool_skipped", skip.pairs)
            what = (f"spool: {skip.pairs} pair(s) {skip.file}" if skip.pairs > 1
                    else f"spool: skipped {skip.file}")
            self.report.emit(self.service_clock.now(), EventKind.SPOOL_SKIPPED,
                             f"{what}: {skip.reason}")

    def close(self) -> None:
        """Leave the amplifier disabled with zero offsets, write held records, close everything.

        Records the quality log still cannot take stay in the journal beside it (named in a
        ``RECORDS_SAVED`` event); the next service on that log writes them.
        """
        t = self.service_clock.last_s if self.service_clock.last_s is not None else 0.0
        self.loops.remember(t, now=True)  # what was learnt since the last write
        if self.piezo is not None:
            problem = self.out.leave_safe(t)
            if problem is not None:
                self.report.emit(t, EventKind.CLOSE_PROBLEM,
                                 f"amplifier not disabled at close: {problem}")
        self.records.close(t)
        if self.plc is not None:
            self.plc.close()
        if self.piezo is not None:
            self.piezo.close()


class FrameCount:
    """Pairs taken by the frame tasks of one run, against its ``max_frames`` (``None``: no end)."""

    def __init__(self, max_frames: int | None) -> None:
        self.max_frames = max_frames
        self.n = 0

    def add(self) -> bool:
        """Count one pair; whether the run has taken all it was asked to."""
        self.n += 1
        return self.max_frames is not None and self.n >= self.max_frames


async def run_periodic(period: float, cycle: Callable[[], Any], stop: asyncio.Event) -> None:
    """Call ``cycle`` (a function or coroutine function) every ``period`` s until ``stop``.

    A cycle that falls more than one period behind skips ahead instead of bursting.
    """
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


async def run_until_stopped(tasks: list[asyncio.Task], stop: asyncio.Event) -> None:
    """Wait until ``stop`` is set or a task ends; a task's error is raised; all cancelled."""
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


def default_log_path(cfg: MachineConfig, log_path: Path | str | None = None) -> Path | str:
    """The quality log: ``log_path``, else ``[log] path``; a file (its folder made) or a URL."""
    from controller.quality.log import database_url, is_database_url

    where = cfg.log.path if log_path is None else log_path
    if is_database_url(where):
        return database_url(where)
    p = Path(where)
    p.parent.mkdir(parents=True, exist_ok=True)
    return p


def open_service(
    cfg: MachineConfig,
    *,
    clock: Callable[[], float] = time.monotonic,
    threaded: bool = True,
    can_bus: Any = None,
    log_path: Path | str | None = None,
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
    log_path : Path or str, optional
        Override ``[log] path`` (a file, or a ``postgresql://`` URL).
    """
    from config.machine import eds_path, registers_path, rig_path
    from config.rig import load_rig
    from controller.fieldbus.piezo_client import open_bus
    from controller.fieldbus.plc_protocol import Backoff
    from controller.quality.log import open_quality_log
    from protocol.registers import RegisterMap

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
        knives=4,  # replaced by the PLC's knives register on the first read
        node_id=cfg.can.node_id,
        eds=eds_path(cfg),
        command_period_s=cfg.can.command_period_s,
        offsets_period_s=cfg.can.offsets_period_s,
        stroke_um=cfg.stroke_um,
    )
    path = default_log_path(cfg, log_path)
    log = open_quality_log(path, machine_id=cfg.log.machine_id or None)
    service = Service(
        cfg,
        plc=plc,
        piezo=piezo,
        rig=rig,
        log=log,
        clock=clock,
        threaded=threaded,
        measurer_factory=VisionMeasurers(rig, defects=cfg.quality.defects),
        pairs_per_s=cfg.frames.pairs_per_s,
    )
    log.set_quality_class(service.quality_class, head=service.head)
    return service
