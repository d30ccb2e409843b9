"""``planer sim`` for a moulder: every head behind the one PLC, the one CAN bus, its own spool.

:class:`MoulderRunner` is :class:`~plant_sim.run.runner.SimRunner` over a
:class:`~plant_sim.machine.moulder.Moulder` (a ``sim.toml`` with ``[[heads]]``): the same stepping
in scaled real time, slowing of the clock, Modbus process and CAN receive thread, with

* the driver a :class:`~plant_sim.run.driver.MoulderDriver` (faults may name their ``head``;
  ``can_drop`` / ``can_silence`` with a head strike that head's node only);
* the PLC serving the common registers and every head's block (``PlcProcess`` over the moulder:
  ``head_register_values(i)``, ``set_spindle_setpoint(i, rpm)``);
* the amplifier an :class:`~plant_sim.interfaces.amp_node.AmpNodeCore` with one node per head
  (:meth:`MoulderDriver.amp_core`), each answering as its own node id on the one bus;
* one frame sink per head (``<[frames] spool_dir>/<head name>``: the service side's default spool
  of a head, ``config.machine.head_config``) and, with images, one
  :class:`~plant_sim.run.render_worker.RenderPool` per head (its own camera, optics and seed,
  writing its own spool in order).

The banner names the heads (``heads: bottom, right, left, top``, then one ``head <name>:`` line
each with its face, node id, register block and spool); the progress lines give each head's
spindle speed and pairs.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from core.closing import close_all
from plant_sim.run.driver import MoulderDriver
from plant_sim.run.runner import CLOCK_KEY, MAX_PENDING_WRITES, MAX_RENDER_BACKLOG, SimRunner

__all__ = ["MoulderRunner", "runner_for"]


class MoulderRunner(SimRunner):
    """Runs a :class:`~plant_sim.machine.moulder.Moulder` in scaled real time.

    Parameters
    ----------
    moulder : Moulder
        The moulder (``names``, ``heads``, ``node_ids``, ``advance`` giving ``(head, frame)``).
    sinks : mapping of str to FrameSink
        Each head's frame sink, by name (every head needs one); without renderers a spool
        directory (``directory``) is written from a writer thread of its own, in order.
    renders : mapping of str to RenderPool, optional
        Each head's render pool (every head, or none): the heads' machines defer their
        rendering (``assembler.defer_rendering()``).
    **options
        As :class:`SimRunner` (``plc``, ``amp``, ``threaded_interfaces``, ``time_scale``,
        ``step_s``, ``clock``, ``sleep``, ``out``, ``progress_every_s`` ...); no ``sink`` nor
        ``render``.

    Attributes
    ----------
    frames_by_head : dict of str to int
        Pairs handed to each head's sink so far.
    """

    RUNS_HEADS = True
    """Wired by :func:`plant_sim.run.wiring.wire_moulder` (a machine of several heads)."""

    def __init__(self, moulder: Any, *, sinks: Mapping[str, Any],
                 renders: Mapping[str, Any] | None = None, **options: Any) -> None:
        for key in ("sink", "render", "sink_thread"):
            if key in options:
                raise TypeError(f"MoulderRunner takes sinks= and renders=, not {key}=")
        names = tuple(moulder.names)
        if set(sinks) != set(names):
            raise ValueError(f"sinks must name every head ({', '.join(names)}), "
                             f"got {', '.join(sinks) or 'none'}")
        if renders is not None and set(renders) != set(names):
            raise ValueError(f"renders must name every head ({', '.join(names)}) or be None, "
                             f"got {', '.join(renders) or 'none'}")
        super().__init__(moulder, sink=None, render=None, sink_thread=False, **options)
        self.names = names
        self.sinks = {n: sinks[n] for n in names}
        self.renders = None if renders is None else {n: renders[n] for n in names}
        self._writers: dict[str, ThreadPoolExecutor] = {}
        """Each spool's writer thread (no renderers): the heads' fsyncs overlap."""
        if self.renders is None:
            self._writers = {n: ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"spool-{n}")
                             for n, s in self.sinks.items() if hasattr(s, "directory")}
        self.driver = MoulderDriver(moulder, amp=self.amp, plc=self.plc, plc_switch=self,
                                    say=self.say)
        self.frames_by_head: dict[str, int] = dict.fromkeys(names, 0)

    # ------------------------------------------------------------------ start
    async def start(self) -> None:
        """Start every head's renderer, then the interfaces; print the heads (one line each)."""
        if self.renders is not None:
            loop = asyncio.get_running_loop()
            await asyncio.gather(*(loop.run_in_executor(None, r.start)
                                   for r in self.renders.values()))
        await super().start()
        m = self.machine
        blocks = getattr(self.plc, "heads", 0) if self.plc is not None else 0
        self.description["heads"] = ", ".join(self.names)
        self.say(f"heads: {self.description['heads']}")
        for i, (name, h) in enumerate(zip(self.names, m.head_configs, strict=True)):
            parts = [f"face {h.face}", f"node {m.node_ids[name]}"]
            if i < blocks:
                parts.append(f"block {i}")
            parts.append(_sink_text(self.sinks[name]))
            self.say(f"head {name}: " + ", ".join(parts))
        self.description["frames"] = _frames_text(self.sinks)
        self.say(f"frames: {self.description['frames']}")

    def _render_nice(self) -> int | None:
        if not self.renders:
            return None
        return next(iter(self.renders.values())).nice

    # ------------------------------------------------------------------ close
    async def close(self) -> None:
        """Finish every head's pending frames and writes, then close as :class:`SimRunner`."""
        try:
            if self.renders is not None:  # every head closes even when one before raised
                close_all([lambda n=name, r=r: self._finish_head(n, r)
                           for name, r in self.renders.items()])
        finally:
            try:
                if self._writers:
                    try:
                        self._collect_writes(wait_all=True)
                    finally:
                        for pool in self._writers.values():
                            pool.shutdown(wait=True)
            finally:
                await super().close()

    def _finish_head(self, name: str, render: Any) -> None:
        """Hand over a head's pairs still rendering, then close its render pool."""
        try:
            for f in render.take(wait=True):
                self._hand_over_head(name, f)
        finally:
            render.close()

    # ------------------------------------------------------------------ stepping
    def _hand_over_head(self, name: str, frame: Any) -> None:
        """One frame of head ``name`` to its sink (in order)."""
        r = self.renders[name] if self.renders is not None else None
        sink = self.sinks[name]
        if r is not None and r.writes_spool:
            pass  # its render worker wrote it
        elif name in self._writers:
            self._writes.append(self._writers[name].submit(sink.write, frame))
            self._collect_writes(limit=MAX_PENDING_WRITES * len(self._writers))
        else:
            sink.write(frame)
        self.summary.frames += 1
        self.frames_by_head[name] += 1

    def _step(self) -> None:
        pairs = self.driver.step(self.step_s, publish=False)
        self.summary.steps += 1
        for name, f in pairs:
            if isinstance(f.truth, dict):
                f.truth[CLOCK_KEY] = self.clock()
            if self.renders is not None:
                job = self.machine.heads[name].assembler.take_job(f.seq)
                self.renders[name].submit(f, job)
            else:
                self._hand_over_head(name, f)

    def _render_backlog(self) -> int:
        """Take back every head's rendered frames; the largest backlog per worker."""
        if self.renders is None:
            return 0
        worst = 0
        for name, r in self.renders.items():
            for f in r.take():
                self._hand_over_head(name, f)
            worst = max(worst, -(-r.pending // r.workers))
        return worst

    def _held(self) -> bool:
        """Whether one head has so many pairs waiting for images that the machine must wait."""
        return self.renders is not None and any(
            r.pending > 2 * MAX_RENDER_BACKLOG * r.workers for r in self.renders.values())

    def _progress_line(self) -> str:
        self._fill_summary()
        s = self.summary
        m = self.machine
        vals = self.plc.values if self.plc is not None else {}
        feed = vals.get("feed_actual_mm_s")
        parts = [f"t={float(m.t_s):.2f} s", f"rtf={s.real_time_factor:.2f}"]
        if feed is not None and math.isfinite(float(feed)):
            parts.append(f"feed={float(feed):.1f} mm/s")
        rpm = " ".join(f"{n}={m.heads[n].spindle_rpm:.0f}" for n in self.names)
        parts.append(f"spindle {rpm} rpm")
        parts.append("frames " + " ".join(f"{n}={self.frames_by_head[n]}" for n in self.names))
        if self.plc is not None:
            parts.append(f"modbus={s.modbus_requests} req/{s.modbus_refused} refused")
        if self.amp is not None:
            parts.append(f"can rx={s.can_received} tx={s.can_sent} dropped={s.can_dropped}")
            if self.amp.receiving:
                parts.append(f"command gap max={self.amp.take_command_gap() * 1e3:.0f} ms")
        return "  ".join(parts)

    def _fill_summary(self) -> None:
        super()._fill_summary()
        self.summary.frames_by_head = dict(self.frames_by_head)


def _frames_text(sinks: Mapping[str, Any]) -> str:
    """The banner's ``frames:`` of a moulder.

    ``spool <folder>/<head> keep K`` when every head's spool is ``<folder>/<its name>``, else
    each head's place.
    """
    dirs = {n: getattr(s, "directory", None) for n, s in sinks.items()}
    if all(d is None for d in dirs.values()):
        return "in-process"
    parents = {d.parent for d in dirs.values() if d is not None}
    keeps = {getattr(s, "keep", None) for s in sinks.values()}
    if (len(parents) == 1 and len(keeps) == 1
            and all(d is not None and d.name == n for n, d in dirs.items())):
        return f"spool {parents.pop()}/<head> keep {keeps.pop()}"
    return "; ".join(f"{n} {_sink_text(s)}" for n, s in sinks.items())


def _sink_text(sink: Any) -> str:
    where = getattr(sink, "directory", None)
    if where is None:
        return "frames in-process"
    return f"spool {where} keep {getattr(sink, 'keep', None)}"


def runner_for(cfg: Any, **options: Any) -> SimRunner:
    """The runner a ``SimConfig`` needs, wired as it says.

    A :class:`MoulderRunner` for ``[[heads]]`` (or a ``Moulder`` given as ``machine``), else a
    :class:`SimRunner`. The options: :func:`plant_sim.run.wiring.wire_runner`.
    """
    from plant_sim.run.wiring import wants_moulder

    heads = wants_moulder(cfg, options.get("machine"))
    return (MoulderRunner if heads else SimRunner).from_config(cfg, **options)
