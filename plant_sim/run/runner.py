"""The ``planer sim`` runner: the machine stepped in scaled real time behind its interfaces.

Threads and processes (``SimRunner.from_config``, as ``planer sim`` runs it):

* the **stepping thread** (the runner's asyncio loop) owns the
:class:`~plant_sim.machine.machine.Machine`
  and drives it through the one :class:`~plant_sim.run.driver.PlantDriver`: so that machine time
  follows ``time_scale`` x wall time (clock and sleep injected: tests run on simulated time);
* the **PLC process** (:class:`~plant_sim.interfaces.plc_process.PlcProcess`, at real-time
priority where
  permitted, like the CAN receive thread: :func:`core.realtime.raise_priority`, guarded by
  :func:`core.realtime.guard_realtime`; the banner's ``priority:`` line says what they got)
  serves Modbus TCP: it reads
  the register snapshot the stepping thread publishes every iteration (shared memory, sequence
  lock) and sends accepted writes back, which the driver applies in order before the next step;
  the amplifier node (:mod:`plant_sim.interfaces.amp_node`) reads its CAN bus on a thread of its
  own;
* the **render worker** (:class:`~plant_sim.run.render_worker.RenderPool`, a process)
renders the
  images of each pair and writes the pairs to the spool directory, in order (PNG encoding and
  fsync stay out of this process); for an in-process sink (:mod:`protocol.frames`) the workers
  hand the images back, in order. Without images, frames go to the sink from a writer thread.

When the host cannot keep up (the render backlog grows, or stepping falls behind the wall clock),
the runner does not catch up in bursts nor skip frames: the simulated clock slows itself (the
interfaces keep answering), and the runner says so once, with the factor achieved. Machine time
never runs ahead of ``time_scale`` x wall time by more than :data:`MAX_LAG_S` (the catch-up
after a short stall), so a fault of ``duration_s`` machine seconds (``modbus_restart``,
``can_silence``) lasts at least that long on the wall clock (less at most ``MAX_LAG_S``), as a
real one would, and CAN frames reach the amplifier at the machine time they arrived
(:meth:`plant_sim.interfaces.amp_node.AmpNode.set_timebase`).

Faults: the machine injects every ``[faults] inject`` entry itself (at its ``at_s``), and hands
the interface faults due to the driver (``machine.take_interface_events()``): ``modbus_restart``
(the server closes, dropping every client, and listens again ``duration_s`` machine seconds later)
and ``can_silence`` (the amplifier node sends nothing for ``duration_s``). ``SimRunner.inject``
also takes ``can_drop`` (``fraction``, ``duration_s``: the node drops that fraction of received
frames) for tests; any other kind goes to ``machine.inject``.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import deque
from collections.abc import Awaitable, Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Protocol

from core.realtime import guard_realtime
from plant_sim.interfaces.amp_node import AmpNode
from plant_sim.interfaces.plc_process import PlcProcess
from plant_sim.interfaces.plc_server import PlcServer
from plant_sim.interfaces.thread import InterfaceLoop, ServedPlc
from plant_sim.run.driver import INTERFACE_FAULTS, PlantDriver

log = logging.getLogger(__name__)

__all__ = ["CLOCK_KEY", "INTERFACE_FAULTS", "RunSummary", "SimRunner", "parse_banner"]

MAX_PENDING_WRITES = 8
"""Frames queued for the writer thread before the runner waits for it."""
MAX_STEPS_PER_ITERATION = 200
"""Steps done before yielding to the event loop when the machine runs late."""
MAX_LAG_S = 0.05
"""Wall seconds the machine may fall behind its clock and catch up (at most
:data:`MAX_STEPS_PER_ITERATION` steps at a time); further behind, the clock slows instead. Was
1.0: after a one-second stall a starved stepping thread caught up in a burst, squeezing a
1.5 s ``modbus_restart`` below the service's 0.5 s PLC timeout and delivering a stall's CAN
commands at one instant followed by a gap the amplifier's 0.1 s setpoint timeout judged as
silence (measured under six CPU hogs; docs/reliability.md). Well below that timeout."""
MAX_RENDER_BACKLOG = 3
"""Pairs waiting for their images (per worker) above which the machine goes slower (twice
as many: it waits)."""
BACKLOG_RATE = 0.25
"""Pace of the machine (fraction of the time scale) while the renderer is behind."""
SLOW_REPORT_AFTER_S = 3.0
"""Wall seconds after the first slow-down over which the achieved time scale is measured."""
SLOW_REPORT_BELOW = 0.9
"""A slow-down is reported when the achieved time scale is below this fraction of the asked one."""
CLOCK_KEY = "sim_clock_s"
"""Key of ``Frame.truth`` stamped with the runner's clock (default ``time.monotonic``: on one
host the service's clock too) when the step that captured the pair ran: maps the camera's
machine time onto the service's clock exactly, however much the simulated clock slowed (the
HIL summary judges the faults' timing with it)."""
TICK_S = 0.002
"""Machine time stepped per wake-up at most as often (fewer wake-ups on a busy host), s."""


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
    slowed_s : float
        Wall seconds by which the clock was slowed because the host could not keep up.
    frames_by_head : dict of str to int or None
        A moulder's pairs per head (:class:`~plant_sim.run.moulder_runner.MoulderRunner`);
        ``None`` for one machine.
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
    slowed_s: float = 0.0
    frames_by_head: dict[str, int] | None = None

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
    plc : PlcServer or PlcProcess, optional
        The Modbus server (not started yet); ``None`` runs without one. A ``PlcProcess``
        serves from its own process.
    amp : AmpNode, optional
        The amplifier node on its bus; ``None`` runs without CAN.
    sink : FrameSink, optional
        Where captured frames go; ``None`` drops them.
    sink_thread : bool, optional
        Write frames from one worker thread (in order) so PNG encoding and fsync do not stall
        the event loop; default: when the sink is a spool directory (has ``directory``).
    render : RenderPool, optional
        Renders the frames' images in worker processes (the machine then defers its rendering:
        ``machine.assembler.defer_rendering()``); started with the runner.
    threaded_interfaces : bool
        Read CAN on the node's own thread and serve a ``PlcServer`` from an
        :class:`~plant_sim.interfaces.thread.InterfaceLoop` (its own thread; it must queue its
        writes). Default: a ``PlcServer`` listens on the runner's loop.
    realtime_interfaces : bool
        The CAN receive thread asks for real-time scheduling (a ``PlcProcess`` asks for it
        when built with ``realtime``); :meth:`start` prints a ``priority:`` line.
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
        plc: PlcServer | PlcProcess | None = None,
        amp: AmpNode | None = None,
        sink: FrameSink | None = None,
        sink_thread: bool | None = None,
        render: Any = None,
        threaded_interfaces: bool = False,
        realtime_interfaces: bool = False,
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
        if threaded_interfaces and plc is not None and not plc.queue_writes:
            raise ValueError("threaded_interfaces needs a PlcServer with queue_writes=True")
        self.machine = machine
        self.plc = plc
        self.amp = amp
        self.sink = sink
        self.render = render
        self.threaded_interfaces = bool(threaded_interfaces)
        self.realtime_interfaces = bool(realtime_interfaces)
        self._io: InterfaceLoop | None = None
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
        self.driver = PlantDriver(machine, amp=amp, plc=plc, plc_switch=self, say=self.say)
        self.description: dict[str, str] = {}
        self._anchor: tuple[float, float] | None = None  # (wall, machine) the clock runs from
        self.achieved_scale: float | None = None
        """The time scale achieved over a slow-down, once said (``None``: never slowed)."""

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_config(cls, cfg: Any, **options: Any) -> SimRunner:
        """A runner wired as a ``SimConfig`` says: ``[modbus]``, ``[can]``, ``[frames]``, ``[run]``.

        The options and their defaults: :func:`plant_sim.run.wiring.wire_runner`.
        """
        from plant_sim.run.wiring import wire_runner

        return wire_runner(cls, cfg, **options)

    # ------------------------------------------------------------------ faults
    def schedule(self, at_s: float, fault: str, **params: Any) -> None:
        """Play an interface fault at machine time ``at_s`` (see :meth:`inject`)."""
        self.driver.schedule(at_s, fault, **params)

    def inject(self, fault: str, **params: Any) -> None:
        """Inject a fault now (:meth:`plant_sim.run.driver.PlantDriver.inject`).

        ``modbus_restart`` (``duration_s``, default 0: the server is closed, dropping every
        client, and listens again ``duration_s`` machine seconds later); ``can_drop``
        (``fraction``, ``duration_s``); ``can_silence`` (``duration_s``); any other kind goes to
        ``machine.inject``.
        """
        self.driver.inject(fault, **params)

    def set_up(self, up: bool) -> None:
        """Switch the Modbus server on or off (the driver's ``modbus_restart``; synchronous)."""
        if self.plc is None:
            return
        if isinstance(self.plc, PlcProcess):
            self.plc.set_up(up)
        elif self._io is not None:
            ServedPlc(self.plc, self._io).set_up(up)
        elif up:  # on this loop: listening before the next request can be served
            asyncio.get_running_loop().create_task(self.plc.start())
        else:
            self.plc.close_now()

    # ------------------------------------------------------------------ running
    def say(self, line: str) -> None:
        """Print one line (banner, progress)."""
        if self._out is not None:
            self._out(line)

    def request_stop(self) -> None:
        """Ask the run to end after the current iteration (signal handlers call this)."""
        self._stop.set()

    async def start(self) -> None:
        """Start the renderers and interfaces and print where they listen (one line each)."""
        if self.render is not None:
            await asyncio.get_running_loop().run_in_executor(None, self.render.start)
        if self.plc is not None:
            if self.threaded_interfaces and not isinstance(self.plc, PlcProcess):
                self._io = InterfaceLoop()
                host, port = await self._io.run_async(self.plc.start())
            else:
                host, port = await self.plc.start()
            self.description["modbus"] = f"{host}:{port}"
            self.say(f"modbus: {host}:{port} unit {self.plc.unit_id}")
        if self.amp is not None:
            if self.threaded_interfaces:
                if not math.isinf(self.time_scale):
                    self.amp.set_timebase(self.clock, self.machine_time_at)
                self.amp.start_receiving(realtime=self.realtime_interfaces)
                if self.realtime_interfaces and (self.amp.rx_priority or "").startswith(
                        "SCHED_FIFO"):
                    guard_realtime()  # a spinning receive thread drops to normal scheduling
            self.description.setdefault("can", type(self.amp.bus).__name__)
            self.say(f"can: {self.description['can']}")
        line = self._priority_line()
        if line is not None:
            self.description["priority"] = line
            self.say(f"priority: {line}")
        if self.sink is not None:
            where = getattr(self.sink, "directory", None)
            keep = getattr(self.sink, "keep", None)
            desc = f"spool {where} keep {keep}" if where is not None else "in-process"
            self.description["frames"] = desc
            self.say(f"frames: {desc}")

    def machine_time_at(self, wall_s: float) -> float:
        """Machine time the clock assigns to wall time ``wall_s`` (``-inf`` before the run).

        The mapping in force now: ``time_scale`` x wall time from the current anchor (moved
        whenever the clock slowed itself); a frame that arrived before the anchor maps to
        before the machine's present and is handed over at once.
        """
        anchor = self._anchor
        if anchor is None:
            return -math.inf
        wall0, sim0 = anchor
        return sim0 + (wall_s - wall0) * self.time_scale

    def _priority_line(self) -> str | None:
        """What the interfaces and workers were granted (``None``: nothing was asked)."""
        asked = []
        if isinstance(self.plc, PlcProcess) and self.plc.realtime:
            asked.append(("modbus", self.plc.priority or "unknown"))
        if self.amp is not None and self.realtime_interfaces and self.threaded_interfaces:
            asked.append(("can receive", self.amp.rx_priority or "unknown"))
        if not asked:
            return None
        parts = [f"{who} {what}" for who, what in asked]
        nice = self._render_nice()
        if nice is not None:
            parts.append(f"render workers nice {nice}")
        line = ", ".join(parts)
        if any(not what.startswith(("SCHED_FIFO", "nice")) for _, what in asked):
            line += ("; not permitted to raise it: on a busy host the interfaces may answer "
                     "late")
        return line

    def _render_nice(self) -> int | None:
        """Nice value of the render workers (``None``: none, or as this process)."""
        return getattr(self.render, "nice", None)

    async def close(self) -> None:
        """Finish pending frames and writes, stop the server and close the bus and workers.

        Each step runs even when an earlier one fails; that error is raised afterwards.
        """
        try:
            try:
                if self.render is not None:
                    try:
                        for f in self.render.take(wait=True):
                            self._hand_over(f)
                    finally:
                        self.render.close()
            finally:
                if self._pool is not None:
                    try:
                        self._collect_writes(wait_all=True)
                    finally:
                        self._pool.shutdown(wait=True)
        finally:
            try:
                if isinstance(self.plc, PlcProcess):
                    self.plc.close()
                elif self.plc is not None:
                    if self._io is not None:
                        await self._io.run_async(self.plc.stop())
                    else:
                        await self.plc.stop()
            finally:
                try:
                    if self.amp is not None:
                        self.amp.close()
                finally:
                    if self._io is not None:
                        self._io.close()

    def _collect_writes(self, *, wait_all: bool = False,
                        limit: int = MAX_PENDING_WRITES) -> None:
        """Drop finished writes (raising a failed one's error); wait while over ``limit`` queued."""
        while self._writes and (
            self._writes[0].done() or wait_all or len(self._writes) > limit
        ):
            self._writes.popleft().result()

    def _hand_over(self, frame: Any) -> None:
        """One frame to the sink (in order; from the writer thread for a spool)."""
        if self.render is not None and self.render.writes_spool:
            pass  # the render worker wrote it
        elif self._pool is not None:
            self._writes.append(self._pool.submit(self.sink.write, frame))  # type: ignore[union-attr]
            self._collect_writes()
        elif self.sink is not None:
            self.sink.write(frame)
        self.summary.frames += 1

    def _step(self) -> None:
        frames = self.driver.step(self.step_s, publish=False)
        self.summary.steps += 1
        for f in frames:
            if isinstance(f.truth, dict):  # when, on this host's clock, the pair was taken
                f.truth[CLOCK_KEY] = self.clock()
            if self.render is not None:
                self.render.submit(f, self.machine.assembler.take_job(f.seq))
            else:
                self._hand_over(f)

    def _render_backlog(self) -> int:
        """Take back rendered frames; how many pairs still wait for their images (per worker)."""
        if self.render is None:
            return 0
        for f in self.render.take():
            self._hand_over(f)
        return -(-self.render.pending // self.render.workers)

    def _held(self) -> bool:
        """Whether so many pairs wait for their images that the machine must wait."""
        r = self.render
        return r is not None and r.pending > 2 * MAX_RENDER_BACKLOG * r.workers

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
        """Step in scaled real time; the clock slows itself when the host cannot keep up.

        Machine time follows ``time_scale`` x wall time from an anchor. While more than
        :data:`MAX_RENDER_BACKLOG` pairs wait for their images the machine steps at only
        :data:`BACKLOG_RATE` of that pace (it keeps moving, so the amplifier's frames keep
        coming); above twice that it waits. A machine behind its clock catches up in slices of
        at most :data:`MAX_STEPS_PER_ITERATION` steps, so a short stall leaves machine time on
        the wall clock; more than :data:`MAX_LAG_S` behind, the clock goes on from where the
        machine is (it has slowed) and the runner says so once.
        """
        m = self.machine
        wall0 = wall_anchor = prev_wall = self.clock()
        sim0 = sim_anchor = float(m.t_s)
        self._anchor = (wall_anchor, sim_anchor)
        end = math.inf if duration_s is None else sim0 + duration_s
        next_progress = sim0 + self.progress_every_s
        tol = 1e-6 * self.step_s
        scale = self.time_scale
        slow_since: tuple[float, float] | None = None  # (wall, sim) at the first slow-down
        said = False
        self.driver.publish()
        self.say("ready")
        while not self._stop.is_set():
            now_sim = float(m.t_s)
            now_wall = self.clock()
            backlog = self._render_backlog()
            if math.isinf(scale):
                target = now_sim + self.step_s * MAX_STEPS_PER_ITERATION
            else:
                target = sim_anchor + (now_wall - wall_anchor) * scale
                lag = target - now_sim
                if lag > MAX_LAG_S * scale:  # far behind: the clock goes on from here
                    self.summary.slowed_s += lag / scale
                    sim_anchor, wall_anchor, target = now_sim, now_wall, now_sim
                    self._anchor = (wall_anchor, sim_anchor)
                    if slow_since is None and not said:
                        slow_since = (now_wall, now_sim)
                if backlog > MAX_RENDER_BACKLOG:  # the renderer is behind: go slower
                    target = min(target, now_sim + (now_wall - prev_wall) * scale * BACKLOG_RATE)
            prev_wall = now_wall
            hold = self._held()
            if hold:
                target = now_sim
            target = min(target, end)
            steps = 0
            while (float(m.t_s) + self.step_s <= target + tol and steps < MAX_STEPS_PER_ITERATION
                   and not self._held()):
                self._step()
                steps += 1
            if steps:
                self.driver.publish()
            now_sim = float(m.t_s)
            self.summary.sim_time_s = now_sim - sim0
            self.summary.wall_time_s = self.clock() - wall0
            if slow_since is not None:
                span = self.clock() - slow_since[0]
                if span >= SLOW_REPORT_AFTER_S:
                    achieved = (now_sim - slow_since[1]) / span
                    if achieved < SLOW_REPORT_BELOW * self.time_scale:
                        self.achieved_scale = achieved
                        self.say(
                            f"slow host: the simulated clock slowed itself to {achieved:.2f} "
                            f"simulated s per wall s (asked {self.time_scale:g}); Modbus and "
                            "CAN keep answering"
                        )
                        said = True
                    slow_since = None  # said, or a hiccup
            if now_sim >= next_progress:
                next_progress = now_sim + self.progress_every_s
                self.say(self._progress_line())
            if now_sim + self.step_s > end + tol:
                break
            if hold or backlog > MAX_RENDER_BACKLOG:
                await self.sleep(TICK_S)
            elif math.isinf(scale) or steps >= MAX_STEPS_PER_ITERATION:
                await self.sleep(0)
            else:
                ahead = max(self.step_s, TICK_S * min(scale, 1.0))
                due = wall_anchor + (now_sim + ahead - sim_anchor) / scale
                await self.sleep(max(0.0, due - self.clock()))

    def _fill_summary(self) -> None:
        s = self.summary
        s.faults = list(self.driver.faults)
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
            if self.amp.receiving:  # the service's commands, as they arrived
                parts.append(f"command gap max={self.amp.take_command_gap() * 1e3:.0f} ms")
        return "  ".join(parts)


def parse_banner(lines: Iterable[str]) -> dict[str, str]:
    """Where a ``planer sim`` listens, from its first output lines (up to ``ready``).

    Returns
    -------
    dict
        ``{"modbus": "127.0.0.1:5020", "can": "udp_multicast:239.74.163.2",
        "frames": "spool runs/spool keep 50"}`` (keys present as printed); a moulder's adds
        ``"heads": "bottom, right, left, top"`` and gives ``"frames": "spool runs/spool/<head>
        keep 50"`` (each head's spool: that folder, the head's name).
    """
    out: dict[str, str] = {}
    for line in lines:
        line = line.strip()
        if line == "ready":
            break
        key, sep, rest = line.partition(": ")
        if sep and key in ("modbus", "can", "frames", "heads"):
            out[key] = rest.split(" unit ")[0] if key == "modbus" else rest
    return out
