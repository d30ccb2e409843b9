"""The service's lifecycle: open, start, run and close it, with one teardown for every way it runs.

``planer serve``, the cross-process HIL and the service benchmark all run the service through a
:class:`ServiceRuntime`: it opens the service (quality log, PLC client, CAN bus), starts its
measurement workers, takes or opens the frame source, tunes the process and raises the event
loop's priority while the service runs, and closes everything in one order, whatever failed
where:

1. the service (amplifier left disabled with zero offsets, held records written, buses closed);
2. the measurement workers;
3. the frame source, then what it polls (the camera's latch reader);
4. a CAN bus handed in, if the service was never opened on it.

Usage::

    async with ServiceRuntime(cfg, options=RuntimeOptions(realtime=True)) as rt:
        rt.open_source()
        await rt.run(stop=stop_event)

What the caller adds (progress lines, events, the simulator, servers) stays the caller's.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from config.machine import MachineConfig, registers_path
from controller.frames.source import open_frame_source
from controller.service.latency import prioritize, tune_for_latency
from controller.service.service import Service, open_service
from controller.workers.pool import open_worker_pool
from core.checks import check_int
from core.closing import close_all
from core.realtime import BUS_RT_PRIORITY, cpu_wakeup_latency, realtime_thread

__all__ = ["RuntimeOptions", "ServiceRuntime"]


@dataclass(frozen=True)
class RuntimeOptions:
    """How a :class:`ServiceRuntime` starts and runs the service.

    Attributes
    ----------
    workers : int or None
        Measurement worker processes (``None``: ``[service] workers``; 0: in the service's
        own process).
    min_workers : int
        At least this many workers whatever ``workers`` says (the cross-process HIL: 1).
    plan_workers : bool
        More workers than cores become one per core with a warning (``planer serve``);
        ``False`` starts exactly the number asked (the scaling benchmark).
    worker_nice : int or None
        Nice value of the worker processes (``None``: as started).
    tune : bool
        Freeze the heap and shorten the interpreter lock's switch interval before the first
        pair (:func:`controller.service.latency.tune_for_latency`).
    prioritize : bool
        The measurement thread and the records' writer at nice
        :data:`controller.service.latency.MEASURE_NICE`, the
        spool's reader thread raised with the bus thread (``planer serve``).
    realtime : bool
        The event loop's thread at real-time priority while the service runs.
    realtime_others : bool
        With ``realtime`` and workers: the service's other threads (light I/O) raised with it.
    cpu_wakeup : bool
        Keep the cores' wake-up latency at ``[service] cpu_latency_us`` while it runs.
    """

    workers: int | None = None
    min_workers: int = 0
    plan_workers: bool = True
    worker_nice: int | None = None
    tune: bool = True
    prioritize: bool = False
    realtime: bool = False
    realtime_others: bool = False
    cpu_wakeup: bool = False

    def __post_init__(self) -> None:
        if self.workers is not None:
            check_int("workers", self.workers, lo=0)
        check_int("min_workers", self.min_workers, lo=0)


class ServiceRuntime:
    """One service's lifecycle (an async context manager).

    Parameters
    ----------
    cfg : MachineConfig
        The configuration, built once by the caller.
    options : RuntimeOptions, keyword-only
        How to start and run it.
    log_path : Path or str, optional, keyword-only
        The quality log (a file or a ``postgresql://`` URL; default ``[log] path``).
    can_bus : can.BusABC, optional, keyword-only
        A CAN bus to use instead of opening ``[can]``; shut down by :meth:`close` if the
        service was never opened on it (the service's own close shuts it down otherwise).
    threaded : bool, keyword-only
        Measure and log in worker threads (real time).
    say : callable, optional, keyword-only
        ``say(line)`` for the runtime's own lines (workers started, warnings).
    """

    def __init__(self, cfg: MachineConfig, *, options: RuntimeOptions = RuntimeOptions(),
                 log_path: Path | str | None = None, can_bus: Any = None,
                 threaded: bool = True, say: Callable[[str], None] | None = None) -> None:
        if not isinstance(cfg, MachineConfig):
            raise ValueError(f"cfg must be a MachineConfig, got {type(cfg).__name__}")
        self.cfg = cfg
        self.options = options
        self.log_path = log_path
        self.can_bus = can_bus
        self.threaded = bool(threaded)
        self.say = say or (lambda _line: None)
        self.service: Service | None = None
        self.pool: Any = None
        self.source: Any = None
        self.latch_reader: Any = None
        """The camera source's reader of the PLC's trigger latches (``None`` for a spool)."""
        self._closers: list[Callable[[], Any]] = []
        self.granted = "normal"
        """The event loop thread's priority while it ran (``realtime_thread``'s words)."""
        self.others: list[threading.Thread] = []
        """The threads raised with it (``realtime_others``)."""
        self.wakeup = "as the system has it (not asked)"
        """The cores' wake-up latency while it ran (``cpu_wakeup_latency``'s words)."""
        self._closed = False

    # -- opening -------------------------------------------------------------------------------

    async def open(self) -> Service:
        """Open the service and start its workers (nothing is contacted yet)."""
        if self.service is not None:
            raise RuntimeError("the runtime's service is already open")
        try:
            self.service = open_service(self.cfg, threaded=self.threaded, log_path=self.log_path,
                                        can_bus=self.can_bus)
            await self._start_workers()
        except BaseException:
            self.close()
            raise
        return self.service

    async def _start_workers(self) -> None:
        opt = self.options
        workers = self.cfg.service.workers if opt.workers is None else opt.workers
        workers = max(workers, opt.min_workers)
        if not workers:
            return
        service = self.service
        assert service is not None
        shape = self.cfg.frames.image_shape
        cores = None if opt.plan_workers else workers
        # off the event loop: each worker sets up for the image size before it answers
        pool, warning = await asyncio.get_running_loop().run_in_executor(
            None, lambda: open_worker_pool(
                service.measurement.factory, workers, shape=shape, cores=cores,
                timeout_s=self.cfg.safety.measurement_timeout_s, nice=opt.worker_nice))
        self.pool = pool
        if warning:
            self.say(warning)
        if pool is not None:
            service.pipeline.use_workers(pool)

    def attach(self, source: Any, *, then_close: Callable[[], Any] | None = None) -> Any:
        """Use ``source`` for the pairs; closed by :meth:`close` (then ``then_close``)."""
        if self.source is not None:
            raise RuntimeError("the runtime already has a frame source")
        self.source = source
        if then_close is not None:
            self._closers.append(then_close)
        return source

    def open_source(self) -> Any:
        """Open ``[frames]``'s source (a spool, or a camera with its reader of the PLC's latches).

        With ``source = "camera"`` the pairs carry the encoder counts the PLC latched at the
        two triggers: a ``ModbusLatchReader`` of its own on ``[plc]`` (the service's client
        stays the owner of the control registers; ``docs/camera.md``), closed after the camera.
        """
        cfg = self.cfg
        latch_reader = None
        if cfg.frames.source == "camera":
            from controller.frames.camera.latches import ModbusLatchReader

            latch_reader = ModbusLatchReader(cfg.plc.host, cfg.plc.port, unit_id=cfg.plc.unit_id,
                                             registers=registers_path(cfg),
                                             timeout_s=cfg.plc.timeout_s)
        try:
            source = open_frame_source(cfg.frames, latch_reader=latch_reader)
        except BaseException:
            if latch_reader is not None:
                latch_reader.close()
            raise
        self.latch_reader = latch_reader
        return self.attach(source, then_close=None if latch_reader is None
                           else latch_reader.close)

    # -- running -------------------------------------------------------------------------------

    async def run(self, *, stop: asyncio.Event | None = None,
                  max_frames: int | None = None) -> None:
        """Run the service on the source until ``stop`` is set (or ``max_frames`` pairs).

        Tunes the process and raises the event loop's thread first, as the options say; the
        priorities are dropped again when it returns.
        """
        service, source = self.service, self.source
        if service is None or source is None:
            raise RuntimeError("open the runtime and give it a frame source before run()")
        opt = self.options
        if opt.tune:
            tune_for_latency()  # after the set-up: frozen heap, short lock switch interval
        if opt.prioritize:
            prioritize(service, source=source)  # measurement, records' writer, spool reader
        with contextlib.ExitStack() as stack:
            if opt.realtime:
                self.others = ([t for t in threading.enumerate()
                                if t is not threading.current_thread()]
                               if opt.realtime_others and self.pool is not None else [])
                self.granted = stack.enter_context(
                    realtime_thread(rt_priority=BUS_RT_PRIORITY, others=self.others))
            if opt.cpu_wakeup:
                self.wakeup = stack.enter_context(
                    cpu_wakeup_latency(self.cfg.service.cpu_latency_us))
            await service.run(source, stop=stop, max_frames=max_frames)

    # -- closing -------------------------------------------------------------------------------

    def close(self) -> None:
        """Close everything, in order, each step even when one before it failed (idempotent)."""
        if self._closed:
            return
        self._closed = True
        steps: list[Callable[[], Any]] = []
        if self.service is not None:
            steps.append(self.service.close)
        elif self.can_bus is not None:
            steps.append(self.can_bus.shutdown)
        if self.pool is not None:
            steps.append(self.pool.close)
        if self.source is not None:
            steps.append(self.source.close)
        steps.extend(self._closers)  # after the source's thread that polls them
        close_all(steps)

    async def __aenter__(self) -> ServiceRuntime:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()
