"""The ``planer sim`` runner: the machine stepped in scaled real time behind its interfaces.

One asyncio task owns the :class:`~plant_sim.machine.Machine` and steps it so that machine time
follows ``time_scale`` x wall time (clock and sleep injected, so tests run on simulated time).
Around it: the PLC's Modbus TCP server (:mod:`plant_sim.plc_server`), the piezo amplifier's CAN
node (:mod:`plant_sim.amp_node`) and the frame sink (a spool directory or an in-process source,
:mod:`protocol.frames`).

Per loop iteration: received CAN frames go to the amplifier (at the current machine time); the
machine advances by whole steps up to the time due (each step: frames to the sink, status and
heartbeat frames due to the bus); the Modbus registers are refreshed; then the loop sleeps until
the next step is due, and the Modbus server answers requests meanwhile.

Faults: the machine injects every ``[faults] inject`` entry itself (at its ``at_s``), and hands
the interface faults due to the runner (``machine.take_interface_events()``): ``modbus_restart``
(the server closes, dropping every client, and listens again ``duration_s`` machine seconds later)
and ``can_silence`` (the amplifier node sends nothing for ``duration_s``). The runner plays them.
``SimRunner.inject`` also takes ``can_drop`` (``fraction``, ``duration_s``: the node drops that
fraction of received frames) for tests; any other kind goes to ``machine.inject``.
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import logging
import math
import time
from collections import deque
from collections.abc import Awaitable, Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from plant_sim.amp_node import AmpNode, AmpNodeCore
from plant_sim.plc_server import PlcServer
from protocol.can_transport import bus_from_config, describe_bus
from protocol.piezo_can import PiezoCodec
from protocol.registers import RegisterMap

log = logging.getLogger(__name__)

INTERFACE_FAULTS = ("modbus_restart", "can_drop", "can_silence")
MAX_PENDING_WRITES = 8
"""Frames queued for the writer thread before the runner waits for it."""
MAX_STEPS_PER_ITERATION = 200
"""Steps done before yielding to the event loop when the machine runs late."""


@dataclass
class RunSummary:
    """What a run did.

    Attributes
    ----------
    sim_time_s : float
        Machine time simulated by this run.
    wall_time_s : float
        Wall (injected clock) time it took.
    steps, frames : int
        Machine steps and image pairs handed to the sink.
    modbus_requests, modbus_refused : int
        Requests the Modbus server served / refused with an exception.
    can_received, can_sent, can_dropped : int
        Frames the amplifier node received, sent, dropped by the fault.
    faults : list of str
        Interface faults played, ``"<kind>@<t_s>"``.
    """

    sim_time_s: float = 0.0
    wall_time_s: float = 0.0
    steps: int = 0
    frames: int = 0
    modbus_requests: int = 0
    modbus_refused: int = 0
    can_received: int = 0
    can_sent: int = 0
    can_dropped: int = 0
    faults: list[str] | None = None

    @property
    def real_time_factor(self) -> float:
        """Simulated seconds per wall second."""
        return self.sim_time_s / self.wall_time_s if self.wall_time_s > 0 else math.inf


class FrameSink(Protocol):
    """Anything with ``write(frame)``: ``SpoolWriter`` or ``InProcessSource``."""

    def write(self, frame: Any) -> Any: ...  # noqa: D102


class SimRunner:
    """Runs a machine in scaled real time behind its Modbus server, CAN node and frame sink.

    Parameters
    ----------
    machine : Machine
        The machine model (``t_s``, ``advance``, ``register_values`` ... see architecture.md).
    plc : PlcServer, optional
        The Modbus server (not started yet); ``None`` runs without one.
    amp : AmpNode, optional
        The amplifier node on its bus; ``None`` runs without CAN.
    sink : FrameSink, optional
        Where captured frames go; ``None`` drops them.
    sink_thread : bool, optional
        Write frames from one worker thread (in order) so PNG encoding and fsync do not stall
        the event loop; default: when the sink is a spool directory (has ``directory``).
    time_scale : float
        Simulated seconds per wall second (> 0); ``math.inf`` runs as fast as possible.
    step_s : float
        Machine step, seconds.
    clock : callable, optional
        Wall clock in seconds (default ``time.monotonic``).
    sleep : callable, optional
        ``async sleep(seconds)`` (default ``asyncio.sleep``).
    out : callable, optional
        Prints one line (banner and progress); default ``print`` with flush; ``None`` silent.
    progress_every_s : float
        Machine time between progress lines.
    """

    def __init__(
        self,
        machine: Any,
        *,
        plc: PlcServer | None = None,
        amp: AmpNode | None = None,
        sink: FrameSink | None = None,
        sink_thread: bool | None = None,
        time_scale: float = 1.0,
        step_s: float = 0.001,
        clock: Callable[[], float] | None = None,
        sleep: Callable[[float], Awaitable[Any]] | None = None,
        out: Callable[[str], None] | None = print,
        progress_every_s: float = 1.0,
    ) -> None:
        if not time_scale > 0:
            raise ValueError(f"time_scale must be > 0, got {time_scale!r}")
        if not (step_s > 0 and math.isfinite(step_s)):
            raise ValueError(f"step_s must be a finite number > 0, got {step_s!r}")
        self.machine = machine
        self.plc = plc
        self.amp = amp
        self.sink = sink
        if sink_thread is None:
            sink_thread = sink is not None and hasattr(sink, "directory")
        self._pool = ThreadPoolExecutor(max_workers=1) if sink_thread else None
        self._writes: deque[Future] = deque()
        self.time_scale = float(time_scale)
        self.step_s = float(step_s)
        self.clock = clock or time.monotonic
        self.sleep = sleep or asyncio.sleep
        self._out = out
        self.progress_every_s = float(progress_every_s)
        self.summary = RunSummary(faults=[])
        self._stop = asyncio.Event()
        self._pending_stop = False
        self._schedule: list[tuple[float, int, str, dict[str, Any]]] = []
        self._tie = itertools.count()
        self._plc_up_at: float | None = None
        self.description: dict[str, str] = {}

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_config(
        cls,
        cfg: Any,
        *,
        machine: Any = None,
        seed: int = 0,
        render_images: bool = True,
        time_scale: float | None = None,
        modbus_port: int | None = None,
        spool_dir: str | Path | None = None,
        sink: FrameSink | None = None,
        can_bus: Any = None,
        **kwargs: Any,
    ) -> SimRunner:
        """A runner wired as a ``SimConfig`` says: ``[modbus]``, ``[can]``, ``[frames]``, ``[run]``.

        Parameters
        ----------
        cfg : config.sim.SimConfig
            The simulator configuration.
        machine : Machine, optional
            Default: ``plant_sim.machine.Machine(cfg, seed=seed, render_images=render_images)``.
        time_scale, modbus_port, spool_dir : optional
            Override ``[run] time_scale``, ``[modbus] port``, ``[frames] spool_dir``.
        sink : FrameSink, optional
            Use this sink instead of a spool directory.
        can_bus : can.BusABC, optional
            Use this bus instead of opening ``[can]``.
        **kwargs
            Passed to the constructor (``clock``, ``sleep``, ``out``...).
        """
        from protocol.frames import SpoolWriter

        if machine is None:
            from plant_sim.machine import Machine

            machine = Machine(cfg, seed=seed, render_images=render_images)
        rmap = RegisterMap.load()
        plc = PlcServer(
            machine,
            register_map=rmap,
            host=cfg.modbus.host,
            port=cfg.modbus.port if modbus_port is None else modbus_port,
            unit_id=cfg.modbus.unit_id,
        )
        own_bus = can_bus is None
        bus = bus_from_config(cfg.can) if own_bus else can_bus
        try:  # a failure from here on (unusable spool folder, bad option) closes our bus
            core = AmpNodeCore(machine, PiezoCodec.load(), knives=cfg.cutterhead.knives,
                               seed=seed)
            amp = AmpNode(bus, core, own_bus=own_bus)
            if sink is None:
                directory = Path(spool_dir if spool_dir is not None else cfg.frames.spool_dir)
                sink = SpoolWriter(directory, keep=cfg.frames.keep)
            runner = cls(
                machine,
                plc=plc,
                amp=amp,
                sink=sink,
                time_scale=cfg.run.time_scale if time_scale is None else time_scale,
                step_s=cfg.run.step_s,
                **kwargs,
            )
        except BaseException:
            if own_bus:
                bus.shutdown()
            raise
        runner.description["can"] = describe_bus(cfg.can.interface, cfg.can.channel)
        return runner

    # ------------------------------------------------------------------ faults
    def schedule(self, at_s: float, fault: str, **params: Any) -> None:
        """Play an interface fault at machine time ``at_s`` (see :meth:`inject`)."""
        heapq.heappush(self._schedule, (float(at_s), next(self._tie), fault, params))

    def inject(self, fault: str, **params: Any) -> None:
        """Inject a fault now.

        ``modbus_restart`` (``duration_s``, default 0: the server is closed, dropping every
        client, and listens again ``duration_s`` machine seconds later); ``can_drop``
        (``fraction``, ``duration_s``); ``can_silence`` (``duration_s``); any other kind goes to
        ``machine.inject``.
        """
        now = float(self.machine.t_s)
        if fault == "modbus_restart":
            if self.plc is None:
                raise ValueError("modbus_restart: the runner has no Modbus server")
            down = float(params.get("duration_s", params.get("down_s", 0.0)))
            self._plc_up_at = now + max(down, 0.0)
            self._pending_stop = True
        elif fault in ("can_drop", "can_silence"):
            if self.amp is None:
                raise ValueError(f"{fault}: the runner has no CAN node")
            kind = "drop_rx" if fault == "can_drop" else "silence"
            p = {k: float(v) for k, v in params.items() if k in ("fraction", "duration_s")}
            self.amp.core.inject(kind, start_s=now, **p)
        else:
            self.machine.inject(fault, **params)
            return
        self.summary.faults.append(f"{fault}@{now:.3f}")  # type: ignore[union-attr]

    async def _play_faults(self) -> None:
        now = float(self.machine.t_s)
        take = getattr(self.machine, "take_interface_events", None)
        for event in take() if take is not None else ():
            ev = dict(event)
            kind = ev.pop("kind")
            ev.pop("t_s", None)
            if kind in INTERFACE_FAULTS:
                self.inject(kind, **ev)
        while self._schedule and self._schedule[0][0] <= now + 1e-12:
            _at, _n, fault, params = heapq.heappop(self._schedule)
            self.inject(fault, **params)
        if self._pending_stop and self.plc is not None:
            self._pending_stop = False
            await self.plc.stop()
            self.say(f"fault: modbus server down at t={now:.3f} s")
        if self._plc_up_at is not None and now >= self._plc_up_at - 1e-12 and self.plc:
            self._plc_up_at = None
            await self.plc.start()
            self.say(f"fault: modbus server up again at t={now:.3f} s")

    # ------------------------------------------------------------------ running
    def say(self, line: str) -> None:
        """Print one line (banner, progress)."""
        if self._out is not None:
            self._out(line)

    def request_stop(self) -> None:
        """Ask the run to end after the current iteration (signal handlers call this)."""
        self._stop.set()

    async def start(self) -> None:
        """Start the interfaces and print where they listen (one line each)."""
        if self.plc is not None:
            host, port = await self.plc.start()
            self.description["modbus"] = f"{host}:{port}"
            self.say(f"modbus: {host}:{port} unit {self.plc.unit_id}")
        if self.amp is not None:
            self.description.setdefault("can", type(self.amp.bus).__name__)
            self.say(f"can: {self.description['can']}")
        if self.sink is not None:
            where = getattr(self.sink, "directory", None)
            keep = getattr(self.sink, "keep", None)
            desc = f"spool {where} keep {keep}" if where is not None else "in-process"
            self.description["frames"] = desc
            self.say(f"frames: {desc}")

    async def close(self) -> None:
        """Finish pending frame writes, stop the server and close the bus.

        Each step runs even when an earlier one fails; that error is raised afterwards.
        """
        try:
            if self._pool is not None:
                try:
                    self._collect_writes(wait_all=True)
                finally:
                    self._pool.shutdown(wait=True)
        finally:
            try:
                if self.plc is not None:
                    await self.plc.stop()
            finally:
                if self.amp is not None:
                    self.amp.close()

    def _collect_writes(self, *, wait_all: bool = False) -> None:
        """Drop finished writes (raising a failed one's error); wait when too many are queued."""
        while self._writes and (
            self._writes[0].done() or wait_all or len(self._writes) > MAX_PENDING_WRITES
        ):
            self._writes.popleft().result()

    def _step(self) -> None:
        m = self.machine
        frames = m.advance(self.step_s)
        self.summary.steps += 1
        if frames:
            for f in frames:
                if self._pool is not None:
                    self._writes.append(self._pool.submit(self.sink.write, f))  # type: ignore[union-attr]
                    self._collect_writes()
                elif self.sink is not None:
                    self.sink.write(f)
                self.summary.frames += 1
        if self.amp is not None:
            self.amp.transmit(float(m.t_s))

    async def run(self, *, duration_s: float | None = None) -> RunSummary:
        """Run until :meth:`request_stop` or ``duration_s`` of machine time; returns the summary.

        Starts and stops the interfaces itself.
        """
        if duration_s is not None and not duration_s >= 0:
            raise ValueError(f"duration_s must be >= 0, got {duration_s!r}")
        try:
            await self.start()
        except BaseException:  # e.g. Modbus cannot listen: nothing stays open (CAN bus)
            await self.close()
            raise
        try:
            await self._loop(duration_s)
        finally:
            await self.close()
            self._fill_summary()
        return self.summary

    async def _loop(self, duration_s: float | None) -> None:
        m = self.machine
        wall0 = self.clock()
        sim0 = float(m.t_s)
        end = math.inf if duration_s is None else sim0 + duration_s
        next_progress = sim0 + self.progress_every_s
        tol = 1e-6 * self.step_s
        self.say("ready")
        while not self._stop.is_set():
            now_sim = float(m.t_s)
            if self.amp is not None:
                self.amp.receive(now_sim)
            if math.isinf(self.time_scale):
                target = now_sim + self.step_s * MAX_STEPS_PER_ITERATION
            else:
                target = sim0 + (self.clock() - wall0) * self.time_scale
            target = min(target, end)
            steps = 0
            while float(m.t_s) + self.step_s <= target + tol and steps < MAX_STEPS_PER_ITERATION:
                self._step()
                steps += 1
            if self.plc is not None:
                self.plc.refresh()
            await self._play_faults()
            now_sim = float(m.t_s)
            self.summary.sim_time_s = now_sim - sim0
            self.summary.wall_time_s = self.clock() - wall0
            if now_sim >= next_progress:
                next_progress = now_sim + self.progress_every_s
                self.say(self._progress_line())
            if now_sim + self.step_s > end + tol:
                break
            if math.isinf(self.time_scale) or steps >= MAX_STEPS_PER_ITERATION:
                await self.sleep(0)
            else:
                due = wall0 + (now_sim + self.step_s - sim0) / self.time_scale
                await self.sleep(max(0.0, due - self.clock()))

    def _fill_summary(self) -> None:
        s = self.summary
        if self.plc is not None:
            s.modbus_requests, s.modbus_refused = self.plc.requests, self.plc.refused
        if self.amp is not None:
            c = self.amp.core
            s.can_received, s.can_sent, s.can_dropped = c.received, c.sent, c.dropped

    def _progress_line(self) -> str:
        self._fill_summary()
        s = self.summary
        vals = self.plc.values if self.plc is not None else {}
        feed = vals.get("feed_actual_mm_s")
        rpm = vals.get("spindle_rpm")
        parts = [f"t={float(self.machine.t_s):.2f} s", f"rtf={s.real_time_factor:.2f}"]
        if feed is not None:
            parts.append(f"feed={float(feed):.1f} mm/s")
        if rpm is not None:
            parts.append(f"spindle={float(rpm):.0f} rpm")
        parts.append(f"frames={s.frames}")
        if self.plc is not None:
            parts.append(f"modbus={s.modbus_requests} req/{s.modbus_refused} refused")
        if self.amp is not None:
            parts.append(f"can rx={s.can_received} tx={s.can_sent} dropped={s.can_dropped}")
        return "  ".join(parts)


def parse_banner(lines: Iterable[str]) -> dict[str, str]:
    """Where a ``planer sim`` listens, from its first output lines (up to ``ready``).

    Returns
    -------
    dict
        ``{"modbus": "127.0.0.1:5020", "can": "udp_multicast:239.74.163.2",
        "frames": "spool runs/spool keep 50"}`` (keys present as printed).
    """
    out: dict[str, str] = {}
    for line in lines:
        line = line.strip()
        if line == "ready":
            break
        key, sep, rest = line.partition(": ")
        if sep and key in ("modbus", "can", "frames"):
            out[key] = rest.split(" unit ")[0] if key == "modbus" else rest
    return out
