"""Four heads at 100 pairs/s each through the moulder's service (``planer bench``, ``moulder``).

What ``planer serve`` runs for a moulder, on this machine: :class:`controller.moulder.service.
MoulderService` opened by :func:`controller.moulder.compose.open_moulder_service` from
``config/machine_moulder.toml`` (a ``Service(owns_feed=False)`` per head, each from
``config.machine.head_config``, and the :class:`~controller.moulder.feed.MoulderFeed` coordinator
writing the one feed and the top head's speed), its heads' amplifiers on ONE CAN connection
(one CANopen master), the machine-wide registers read once per PLC cycle for every head, and
ONE pool of measurement worker processes the heads share
(:func:`controller.moulder.compose.share_workers`: each head's pairs with its own rig),
run by :meth:`MoulderService.run` (one PLC task, one CAN task, a frame task per head) on one
event loop. The simulated moulder (:class:`plant_sim.machine.moulder.Moulder`,
``config/sim_moulder.toml``) stands in for the machine: its PLC's Modbus server in its own
process on 127.0.0.1 serving the common registers and every head's block, every head's
amplifier node on the one virtual CAN bus (``MoulderDriver.amp_core``), pumped every 10 ms
(their status period; the PLC's registers every PLC cycle: :func:`_pump_plant`).

Each head's pairs are rendered by the simulated moulder before timing (its camera's, 659 x 493)
and go to the head's frame source (an in-process queue of
:data:`planer.benchmarks.service.QUEUE_PAIRS` that drops the oldest pair, as a camera does not
wait): once all heads report RUN, head ``i`` gets its pairs at ``rate_hz`` starting
``i / (heads * rate_hz)`` after the first head (the cameras are triggered by the encoder at
each head's position, not together: 400 pairs/s spread evenly). A pair's latency runs from its
hand-off to its head's source to the return of its offsets' CAN send (the coordinator writes
the feed on the PLC's cycle). Per head and over all heads: pairs in, handled (a result),
measured (a valid measurement), applied (its setpoints went out), failed, dropped by the
source, p50 / p99 / max latency of the applied pairs (the first
:data:`planer.benchmarks.service.WARMUP_PAIRS` of each head apart from the p50 and p99, never
from the max); the CPU time per pair of the service's process, of the workers and of the PLC's
process; the workers used; the machine's cores and load average before and after.
"""

from __future__ import annotations

import asyncio
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from controller.service.events import EventKind
from planer.benchmarks.figures import latency_stats, proc_cpu_s
from planer.benchmarks.service import (
    DRAIN_TIMEOUT_S,
    QUEUE_PAIRS,
    READY_TIMEOUT_S,
    WARMUP_PAIRS,
    _latency_figures,
    _plc_for,
    machine_description,
)
from protocol.piezo_canopen import STATUS_PERIOD_S

RATE_HZ = 100.0
"""Pairs per second of each head's camera."""
WORKERS = 2
"""Measurement worker processes the four heads share (one per core on this 2-core machine)."""
TARGET_P99_MS = 10.0
"""Frame-to-setpoint p99 target, ms (over all heads' pairs)."""
PAIRS_PER_HEAD = 600
"""Pairs each head gets in a full run (6 s at 100 pairs/s); ``quick``: :data:`QUICK_PAIRS`."""
QUICK_PAIRS = 150
"""Pairs per head of a quick run."""
SLOWEST = 5
"""The slowest pairs reported per head (``slowest``: ``[pair's place in the run, ms]``)."""
AMP_PUMP_S = STATUS_PERIOD_S
"""Period of the simulated amplifiers' pump, s: their status period
(``protocol.piezo_canopen.STATUS_PERIOD_S``)."""


class _CpuMeter:
    """CPU seconds of this process, the workers and the PLC's process between two readings.

    ``cpu_ms_per_pair`` is the service's: this process (less the stand-ins' pump) and the
    workers; the PLC's process and the stand-ins in this process are reported apart. The
    service process's is split into its event loop's thread (``service_loop``: read on the
    loop, where both readings are taken) and its other threads (the quality log's writers).
    """

    def __init__(self, pool: Any, plc: Any) -> None:
        self.pool, self.plc = pool, plc
        self.start: dict[str, float] = {}
        self.stand_in = [0.0]
        """CPU s of the simulated amplifiers and PLC pump in this process (:func:`_pump_plant`)."""

    def _now(self) -> dict[str, float]:
        t = os.times()
        pids = [] if self.pool is None else list(self.pool.pids)
        proc = getattr(self.plc, "_proc", None)
        return {"service": t.user + t.system - self.stand_in[0],
                "service_loop": time.thread_time() - self.stand_in[0],
                "stand_ins": self.stand_in[0],
                "workers": sum(proc_cpu_s(p) for p in pids),
                "plc": proc_cpu_s(getattr(proc, "pid", None))}

    def begin(self) -> None:
        """Take the first reading (when the first pair goes in)."""
        self.start = self._now()

    def per_pair_ms(self, pairs: int, wall_s: float) -> dict[str, Any]:
        """CPU ms per pair of each part since :meth:`begin`, and the cores they kept busy."""
        end = self._now()
        used = {k: max(0.0, end[k] - self.start.get(k, 0.0)) for k in end}
        service = used["service"] + used["workers"]
        n = max(1, pairs)
        return {
            "cpu_ms_per_pair": service * 1e3 / n,
            "service_cpu_ms_per_pair": used["service"] * 1e3 / n,
            "service_loop_cpu_ms_per_pair": used["service_loop"] * 1e3 / n,
            "service_threads_cpu_ms_per_pair": (used["service"] - used["service_loop"]) * 1e3 / n,
            "workers_cpu_ms_per_pair": used["workers"] * 1e3 / n,
            "plc_cpu_ms_per_pair": used["plc"] * 1e3 / n,
            "stand_in_cpu_ms_per_pair": used["stand_ins"] * 1e3 / n,
            "cores_busy": service / wall_s if wall_s > 0 else None,
            "cores_busy_with_stand_ins": ((service + used["plc"] + used["stand_ins"]) / wall_s
                                          if wall_s > 0 else None),
            "wall_s": wall_s,
        }


MOULDER_CONFIG = "machine_moulder.toml"
"""The moulder's service configuration (``config/``)."""
MOULDER_SIM = "sim_moulder.toml"
"""The simulated moulder (``config/``)."""


def moulder_heads() -> tuple[tuple[str, int], ...]:
    """The moulder's heads: name and amplifier node id, in order (:data:`MOULDER_CONFIG`'s)."""
    from config.loading import default_path
    from config.machine import load_machine

    return tuple((h.name, h.node_id)
                 for h in load_machine(default_path(MOULDER_CONFIG)).heads)


def _moulder_frames(n: int, *, seed: int = 1) -> tuple[dict[str, list], Any]:
    """``n`` rendered pairs of every head, and the moulder in its first state for the PLC.

    The PLC's moulder is not stepped while the pairs go in: in its first state it reports the
    spindles and the feed running and no board under a camera, so every head reaches RUN
    without waiting for a measurement.
    """
    from config.loading import default_path
    from config.sim import load_sim
    from plant_sim.machine.moulder import Moulder

    sim = load_sim(default_path(MOULDER_SIM))
    moulder = Moulder(sim, seed=seed)
    frames: dict[str, list] = {h.name: [] for h in sim.heads}
    while min(len(v) for v in frames.values()) < n:  # render before timing anything
        for head, frame in moulder.advance(0.05):
            frames[head].append(frame)
    return ({k: v[:n] for k, v in frames.items()},
            Moulder(sim, seed=seed, render_images=False))


def _machine_config(host: str, port: int, shape: tuple[int, int], workdir: Path,
                    heads: int | None) -> Any:
    """``machine_moulder.toml`` for the bench.

    With the simulated PLC's port, the images' size, its first ``heads`` heads and a quality
    log in ``workdir``.
    """
    from config.loading import default_path
    from config.machine import load_machine

    cfg = load_machine(default_path(MOULDER_CONFIG))
    h, w = shape
    return cfg.with_changes(plc=replace(cfg.plc, host=host, port=port),
                            frames=replace(cfg.frames, image_width=w, image_height=h),
                            log=replace(cfg.log, path=workdir / "moulder.sqlite"),
                            declared_heads=cfg.declared_heads[:heads])


async def _pump_plant(amp: Any, plc_pump: Any, stop: asyncio.Event, spent: list[float], *,
                      plc_period_s: float) -> None:
    """Step the simulated amplifiers and PLC until ``stop``.

    The amplifiers every :data:`AMP_PUMP_S` on a fixed schedule (their status period: each
    node's TPDO1 leaves on its 10 ms, its heartbeat on its 100 ms, what the master sent is taken
    within 10 ms); the PLC (its writes applied, its registers published) every
    ``plc_period_s``, the service's PLC cycle: the moulder is not stepped while the pairs go
    in, so its registers change only by the service's writes, which the PLC serves from the
    moment it takes them. The CPU time
    it takes in this process (the stand-ins for the amplifiers and the PLC's register image,
    not the service) is added to ``spent[0]``, s.
    """
    t0 = time.monotonic()
    next_amp = next_plc = t0
    while not stop.is_set():
        c0 = time.thread_time()
        now = time.monotonic()
        amp.pump(now - t0)
        if now >= next_plc:
            plc_pump()
            next_plc = max(next_plc + plc_period_s, now)
        spent[0] += time.thread_time() - c0
        # on a fixed schedule (a late pump does not push the next ones back: each node's
        # status leaves 100 times a second), started again from now after a longer stall
        next_amp += AMP_PUMP_S
        now = time.monotonic()
        if next_amp < now - AMP_PUMP_S:
            next_amp = now
        await asyncio.sleep(max(0.0, next_amp - now))


class _Head:
    """One head in the bench: its service, source and what came back of its pairs."""

    def __init__(self, name: str, service: Any, n_pairs: int) -> None:
        from controller.frames.source import QueueFrameSource

        self.name = name
        self.service = service
        self.source = QueueFrameSource(maxsize=min(QUEUE_PAIRS, n_pairs))
        self.n_pairs = n_pairs
        self.seen: list[SimpleNamespace] = []
        self.put_at: dict[int, float] = {}
        self.stored_at: dict[int, float] = {}
        self.running = asyncio.Event()
        self.handled = asyncio.Event()
        self.wire()

    def wire(self) -> None:
        """Listen to the service: RUN reached, each pair's result, each record stored."""
        service = self.service
        records = service.records
        if hasattr(records, "on_stored"):
            records.on_stored = lambda seq, at: self.stored_at.__setitem__(int(seq), at)
        service.on_event = (lambda e: self.running.set()
                            if e.kind is EventKind.RECOVERED else None)

        def on_result(r: Any) -> None:
            self.seen.append(SimpleNamespace(
                seq=r.seq, ok=r.ok, applied=r.applied, t_s=r.t_s, latency_s=r.latency_s,
                error=r.error, extra={"timing_ms": r.extra.get("timing_ms", {})}))
            if len(self.seen) + self.source.dropped >= self.n_pairs:
                self.handled.set()

        service.on_result = on_result

    def latencies_ms(self) -> list[float]:
        """Frame-to-setpoint latency of each applied pair, ms, in the order handled."""
        out = []
        for r in self.seen:
            t_put = self.put_at.get(int(r.seq))
            if r.applied and t_put is not None:
                out.append((r.t_s + r.latency_s - t_put) * 1e3)
        return out


async def _feed(heads: list[_Head], frames: dict[str, list], rate_hz: float) -> None:
    """Hand each head its pairs at ``rate_hz``, the heads' cameras spread over the period."""
    loop = asyncio.get_running_loop()
    period = 1.0 / rate_hz
    step = period / len(heads)
    t0 = loop.time()
    for k in range(min(len(frames[h.name]) for h in heads)):
        for i, head in enumerate(heads):
            f = frames[head.name][k]
            delay = t0 + k * period + i * step - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            head.put_at[int(f.seq)] = time.monotonic()
            head.source.put(f)


async def _serve(moulder: Any, heads: list[_Head], stop: asyncio.Event, *,
                 priority: bool) -> str:
    """``MoulderService.run`` on every head's source until ``stop`` (as ``planer serve``)."""
    import contextlib

    from controller.service.latency import prioritize
    from core.realtime import BUS_RT_PRIORITY, realtime_thread

    granted = "normal"
    with contextlib.ExitStack() as stack:
        if priority:
            for head in heads:
                prioritize(head.service, source=head.source)
            granted = stack.enter_context(realtime_thread(rt_priority=BUS_RT_PRIORITY))
        await moulder.run({h.name: h.source for h in heads}, stop=stop)
    return str(granted)


async def _run(
    frames: dict[str, list],
    machine: Any,
    *,
    rate_hz: float = RATE_HZ,
    workdir: Path,
    workers: int = WORKERS,
    heads: int | None = None,
    ready_timeout_s: float = READY_TIMEOUT_S,
    priority: bool = False,
    depth: int | None = None,
) -> dict[str, Any]:
    """Serve every head's ``frames`` at ``rate_hz`` once all are in RUN; their figures.

    ``machine``: the simulated moulder the PLC serves. ``workers`` > 0: one pool of that many
    measurement processes shared by the heads (0: each head measures in the service's
    process). ``priority`` as ``planer serve`` runs: the event loop at real-time priority where
    permitted, the measurement at a raised nice value. ``RuntimeError`` naming what a head
    waits for when one is not in RUN after ``ready_timeout_s``.
    """
    import can

    from controller.moulder.compose import open_moulder_service, share_workers
    from controller.service.latency import MEASURE_NICE, GcPauses, tune_for_latency
    from plant_sim.interfaces.amp_node import AmpNode
    from plant_sim.run.driver import MoulderDriver

    plc, plc_pump = await _plc_for(machine, realtime=priority)
    host, port = await plc.start()
    first = next(iter(frames.values()))
    shape = first[0].image_a.shape
    cfg = _machine_config(host, port, shape, workdir, heads)
    channel = f"planer-moulder-{os.getpid()}-{id(frames)}"
    amp = AmpNode(can.Bus(interface="virtual", channel=channel),
                  MoulderDriver.amp_core(machine), own_bus=True)
    moulder = None
    pool = None
    bench: list[_Head] = []
    stop = asyncio.Event()
    unfinished: dict[str, int] = {}
    meter = _CpuMeter(None, plc)
    wall = [0.0, 0.0]
    granted = "normal"
    try:
        moulder = open_moulder_service(cfg, can_bus=can.Bus(interface="virtual",
                                                            channel=channel))
        bench = [_Head(name, svc, len(frames[name])) for name, svc in moulder.heads.items()]
        if workers:
            pool, _ = await asyncio.get_running_loop().run_in_executor(
                None, lambda: share_workers(
                    moulder, workers, shape=shape, cores=workers,
                    nice=MEASURE_NICE if priority else None,
                    timeout_s=cfg.safety.measurement_timeout_s, depth=depth))
        meter.pool = pool

        async def feed_frames() -> None:
            for head in bench:
                try:
                    await asyncio.wait_for(head.running.wait(), ready_timeout_s)
                except asyncio.TimeoutError:
                    status = head.service.status()
                    why = status.safe_reason if status.t_s is not None else "no cycle ran"
                    stop.set()
                    raise RuntimeError(f"moulder benchmark: head {head.name} not in RUN after "
                                       f"{ready_timeout_s:g} s ({why})") from None
            meter.begin()
            wall[0] = time.monotonic()
            await _feed(bench, frames, rate_hz)
            for head in bench:
                try:
                    await asyncio.wait_for(head.handled.wait(), DRAIN_TIMEOUT_S)
                except asyncio.TimeoutError:
                    unfinished[head.name] = (head.n_pairs - len(head.seen)
                                             - head.source.dropped)
            wall[1] = time.monotonic()
            stop.set()

        pump = asyncio.create_task(_pump_plant(amp, plc_pump, stop, meter.stand_in,
                                               plc_period_s=cfg.safety.cycle_s))
        feeder = asyncio.create_task(feed_frames())
        tune_for_latency()  # once for every head, after their set-up (its collection not timed)
        gc_pauses = GcPauses()
        try:
            with gc_pauses:
                granted = await _serve(moulder, bench, stop, priority=priority)
            await feeder
        finally:
            stop.set()
            feeder.cancel()
            await asyncio.gather(pump, feeder, return_exceptions=True)
        cpu = meter.per_pair_ms(sum(len(hd.seen) for hd in bench), wall[1] - wall[0])
        feed = moulder.feed.describe()
        sharing = list(moulder.sharing_common)
    finally:
        stop.set()
        if moulder is not None:
            moulder.close()
        if pool is not None:
            pool.close()
        amp.close()
        await plc.stop()
        if hasattr(plc, "close"):
            plc.close()
    out = _figures(bench, first, rate_hz=rate_hz, workers=0 if pool is None else pool.workers,
                   cpu=cpu, unfinished=unfinished, gc_pauses=gc_pauses,
                   priority={"service_bus": granted, "plc_process": getattr(plc, "priority",
                                                                            None)})
    out["feed"] = feed
    out["common_read_shared_by"] = sharing
    return out


def _figures(bench: list[_Head], frames: list, *, rate_hz: float, workers: int,
             cpu: dict[str, Any], unfinished: dict[str, int], gc_pauses: Any,
             priority: dict[str, Any]) -> dict[str, Any]:
    """Per head and over all heads: counts, latency, CPU per pair."""
    h, w = frames[0].image_a.shape
    per_head: dict[str, Any] = {}
    steady: list[float] = []
    every: list[float] = []
    for head in bench:
        fig = _latency_figures(SimpleNamespace(results=head.seen, records=head.service.records,
                                               measurement=head.service.measurement),
                               head.put_at, head.stored_at, _NoGc(), frames=frames,
                               rate_hz=rate_hz, workers=workers)
        lat = head.latencies_ms()
        warm = min(WARMUP_PAIRS, max(0, len(lat) - 1))
        steady += lat[warm:]
        every += lat
        s = latency_stats(lat[warm:], middle="p50")
        per_head[head.name] = {
            "node_id": int(head.service.cfg.can.node_id),
            "writes_feed": bool(getattr(head.service.out, "owns_feed", True)),
            "pairs_in": len(head.put_at),
            "handled": len(head.seen),
            "measured": len(head.seen) - fig["failed"],
            "applied": fig["applied"],
            "failed": fig["failed"],
            "dropped": int(head.source.dropped),
            "unfinished": unfinished.get(head.name, 0),
            "p50_ms": s.get("p50"), "p99_ms": s.get("p99"),
            "max_ms": latency_stats(lat, middle="p50").get("max"),
            "slowest": [[k, round(v, 2)] for k, v in sorted(
                enumerate(lat), key=lambda kv: -kv[1])[:SLOWEST]],
            "breakdown_ms": fig["breakdown_ms"],
            "record_after_setpoint_ms": fig["record_after_setpoint_ms"],
            "state": head.service.state.value,
            "safe_reason": head.service.keeper.safe_reason(),
            "events": [e.text for e in head.service.events][:12],
            "safe_entries": int(head.service.counters.get("safe_entries", 0)),
            **({"failed_reasons": fig["failed_reasons"],
                "failed_examples": sorted({str(r.error) for r in head.seen
                                           if not r.ok})[:3]}
               if "failed_reasons" in fig else {}),
        }
    s_all = latency_stats(steady, middle="p50")
    totals = {k: sum(int(p[k]) for p in per_head.values())
              for k in ("pairs_in", "handled", "measured", "applied", "failed", "dropped",
                        "unfinished")}
    overall = {**totals, "p50_ms": s_all.get("p50"), "p99_ms": s_all.get("p99"),
               "max_ms": latency_stats(every, middle="p50").get("max"), **cpu}
    overall["pairs_per_s"] = (totals["handled"] / cpu["wall_s"]
                              if cpu.get("wall_s") else None)
    # every pair handled: none dropped by a source nor left unfinished (a pair the checks
    # refused, e.g. flagged, is handled: its record says why; ``failed`` counts them)
    meets = {"p99": s_all.get("p99") is not None and s_all["p99"] <= TARGET_P99_MS,
             "nothing_dropped": totals["dropped"] == 0 and totals["unfinished"] == 0
             and totals["handled"] == totals["pairs_in"]}
    return {
        "heads": per_head,
        "overall": overall,
        "meets": meets,
        "target_p99_ms": TARGET_P99_MS,
        "at_target_rate": rate_hz >= RATE_HZ and len(bench) == len(moulder_heads()),
        "width": int(w), "height": int(h),
        "rate_hz_per_head": rate_hz,
        "pairs_per_head": len(frames),
        "workers": workers,
        "workers_shared": True,
        "warmup_pairs_per_head": WARMUP_PAIRS,
        "gc": gc_pauses.summary(),
        "priority": priority,
        "transport": "Modbus TCP 127.0.0.1 (one PLC process; the coordinator's client and one "
                     "per head) + one virtual CAN bus, one master (amplifier nodes " + ", ".join(
                         str(p["node_id"]) for p in per_head.values()) + ")",
        "service": "MoulderService (machine_moulder.toml, open_moulder_service)",
        "latency_from": "pair handed to its head's frame source",
        "latency_to": "offsets sent (CAN); the coordinator writes the feed each PLC cycle",
    }


class _NoGc:
    """The collector's pauses are measured once for all heads (``gc`` of the result)."""

    def summary(self) -> dict[str, Any]:
        return {}


def run(quick: bool = False, *, workers: int = WORKERS, rate_hz: float = RATE_HZ,
        heads: int | None = None, depth: int | None = None) -> dict[str, Any]:
    """Four heads at :data:`RATE_HZ` pairs/s each, one shared pool of ``workers`` processes.

    Parameters
    ----------
    quick : bool
        :data:`QUICK_PAIRS` pairs per head instead of :data:`PAIRS_PER_HEAD`.
    workers : int
        Measurement worker processes shared by the heads (0: in the service's process).
    rate_hz : float
        Pairs per second of each head (what fits: a sweep below the target rate).
    heads : int, optional
        The first this many of :func:`moulder_heads` (1: a single head through the same
        bench); default all of them.
    depth : int, optional
        Pairs a worker holds at once (default
        :data:`controller.workers.pool.DEFAULT_DEPTH`).

    Returns
    -------
    dict
        ``heads`` (per head: ``pairs_in``, ``handled``, ``measured``, ``applied``, ``failed``,
        ``dropped``, ``p50_ms``, ``p99_ms``, ``max_ms``, ``breakdown_ms`` ...), ``overall`` (the
        same summed and over all pairs, with ``cpu_ms_per_pair`` and its parts, ``cores_busy``,
        ``pairs_per_s``), ``meets`` (``p99``, ``nothing_dropped``), ``workers``, ``machine``
        (cores, load average before and after).
    """
    import logging

    from core.checks import check_int, check_positive

    check_int("workers", workers, lo=0)
    every = len(moulder_heads())
    heads = every if heads is None else check_int("heads", heads, lo=1, hi=every)
    check_positive("rate_hz", rate_hz)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    n = QUICK_PAIRS if quick else PAIRS_PER_HEAD
    n = max(QUICK_PAIRS, round(n * min(1.0, rate_hz / RATE_HZ)))  # a slower run no longer
    frames, machine = _moulder_frames(n)
    frames = {k: v for k, v in list(frames.items())[:heads]}
    before = machine_description()
    with tempfile.TemporaryDirectory(prefix="planer-moulder-") as d:
        out = asyncio.run(_run(frames, machine, workdir=Path(d), workers=workers,
                               rate_hz=rate_hz, heads=heads, depth=depth, priority=True))
    out["machine"] = {**before, "load_avg_after": machine_description()["load_avg"]}
    return out


def text(result: dict[str, Any]) -> str:
    """The readable lines of the moulder part."""
    o = result["overall"]
    m = result.get("machine", {})
    meets = result.get("meets", {})

    def ms(v: Any) -> str:
        return "-" if v is None else f"{v:.2f}"

    lines = [
        f"moulder ({len(result['heads'])} heads x {result['rate_hz_per_head']:g} pairs/s, "
        f"{result['width']}x{result['height']}, {result['workers']} shared worker process(es); "
        f"{result['transport']}); machine: {m.get('cores')} cores, load {m.get('load_avg')} "
        f"-> {m.get('load_avg_after')}",
        f"  all heads: {o['handled']}/{o['pairs_in']} handled, {o['measured']} measured "
        f"({o['applied']} applied), "
        f"{o['failed']} failed, {o['dropped']} dropped"
        + (f", {o['unfinished']} UNFINISHED" if o.get("unfinished") else "")
        + f"; pair -> setpoints p50 {ms(o['p50_ms'])} ms, p99 {ms(o['p99_ms'])} ms, max "
        f"{ms(o['max_ms'])} ms (p99 {'ok' if meets.get('p99') else 'MISSED'}, target <= "
        f"{result['target_p99_ms']:g}; nothing dropped "
        f"{'ok' if meets.get('nothing_dropped') else 'MISSED'})",
        f"  service CPU per pair {o['cpu_ms_per_pair']:.2f} ms (service process "
        f"{o['service_cpu_ms_per_pair']:.2f}: event loop "
        f"{o.get('service_loop_cpu_ms_per_pair', 0):.2f}, other threads "
        f"{o.get('service_threads_cpu_ms_per_pair', 0):.2f}; workers "
        f"{o['workers_cpu_ms_per_pair']:.2f}; "
        f"{o['cores_busy'] or 0:.2f} cores busy); stand-ins apart: PLC process "
        f"{o['plc_cpu_ms_per_pair']:.2f}, amplifiers {o['stand_in_cpu_ms_per_pair']:.2f} ms "
        f"({o['cores_busy_with_stand_ins'] or 0:.2f} cores busy with them); "
        f"{o['pairs_per_s'] or 0:.0f} pairs/s served",
    ]
    for name, hd in result["heads"].items():
        lines.append(
            f"  {name} (node {hd['node_id']}): {hd['handled']}/{hd['pairs_in']} handled, "
            f"{hd['measured']} measured, {hd['failed']} failed, {hd['dropped']} dropped; p50 "
            f"{ms(hd['p50_ms'])} ms, p99 {ms(hd['p99_ms'])} ms, max {ms(hd['max_ms'])} ms")
    return "\n".join(lines)
