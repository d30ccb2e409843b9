"""Service latency and measurement workers (``planer bench``, ``service`` part).

**Latency**. The simulated machine renders 659x493 pairs once (before
timing); its PLC's Modbus server runs in a process of its own
(``plant_sim.interfaces.plc_process``) on an
ephemeral 127.0.0.1 port and its piezo amplifier node answers on a virtual CAN bus, pumped every
5 ms. The service runs as ``planer serve`` does (real time, the PLC and CAN cycle tasks, the
quality log on disk, the process tuned by :func:`controller.service.latency.tune_for_latency`, its
event loop at real-time priority and the measurement at a raised nice value where permitted);
once it reported RUN the pairs are handed to its frame source at ``rate_hz`` (100 pairs/s: a
queue of :data:`QUEUE_PAIRS` that drops the oldest, or a spool folder a camera process writes)
and the run ends when it handled the last one (no fixed waits). Runs: in process, through a
spool, 1 and 2 worker processes. A pair's latency runs from the moment it is handed to the
source (or committed to the spool) to the return of the Modbus write of its feed setpoint and
the CAN send of its offsets: waiting in the source, the PLC registers, the hand-off to the
measurement and back, the vision, plausibility, knife phase, both loops and both writes. Its
record is written after that, off the control path; how long after is reported too
(``record_after_setpoint``). The breakdown says where the time goes, per pair: ``queue``
(waiting in the source), ``plc_read``, ``vision`` (the measurement's own work), ``handoff`` (to
the thread or worker process and back; near 0 for a pair measured on the event loop's own
thread, counted in ``measured_inline``), ``checks`` (plausibility, attribution of the marks to
knife passes), ``control`` (knife phase, loops, writes); plus the collector's pauses and the
commits. Through a spool the camera writes raw ``.npy`` images (:data:`SPOOL_IMAGE_FORMAT`).
The median and p99 are the steady state's: the first :data:`WARMUP_PAIRS` pairs (the first
after the idle start-up) are reported apart (``warmup_max_ms``, ``p99_all_ms``); the max counts
every pair.

**Workers**: :mod:`planer.benchmarks.scaling`.

The machine (cores, load average) is in the result: read the figures against it.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from controller.service.events import EventKind
from planer.benchmarks.figures import latency_stats
from planer.benchmarks.scaling import scaling

READY_TIMEOUT_S = 60.0
"""Deadline for the service to reach RUN before the pairs go in (a loaded machine), s."""
DRAIN_TIMEOUT_S = 30.0
"""After the last pair went in, the run ends when every pair was handled or dropped, or after
this long (a pair lost without a count: reported as ``unfinished``), s."""
RATE_HZ = 100.0
"""Camera rate of the latency runs, pairs per second."""
TARGETS = {"p99_ms": 5.0, "max_ms": 20.0, "p99_over_median": 3.0}
"""Latency targets: p99 and max on a quiet machine, p99 / median on a busy one."""
SPOOL_KEEP = 32
"""Pairs the camera keeps in the spool folder (``SpoolWriter(keep=...)``; it deletes older ones,
as a camera does: the reader scans the folder, so its size counts)."""
ONLY_VIA_ENV = "PLANER_BENCH_SERVICE_VIA"
"""Set to ``spool`` or ``queue``: :func:`run` makes only the latency runs that come so (the top
level then holds the first of them); unset: all of them."""
COMMIT_CLOCK_AT_RENAME = True
"""The bench's camera reads a pair's commit time just before the rename of its metadata file
(``False``: before that file is written, counting the camera's own write in the latency)."""
SPOOL_IMAGE_FORMAT = "npy"
"""How the benchmark's camera writes the images into the spool (``SpoolWriter(image_format=...)``):
raw ``.npy``, the fast hand-off (``"png"``: the default format, a PNG decode per image more)."""
WARMUP_PAIRS = 3
"""The run's first pairs, measured after the service idled while it came up (cold caches, the
first calls of each path: 6-13 ms): left out of the median and p99 (``warmup_pairs``,
``warmup_max_ms``; ``p99_all_ms`` counts them), never out of the max."""
QUEUE_PAIRS = 8
"""Pairs the frame source holds; a camera does not wait: when full the oldest pair is dropped
(counted in ``dropped``), so a service slower than the camera shows as drops, not as an ever
longer queue."""


def machine_description() -> dict[str, Any]:
    """Cores available, load averages (1, 5, 15 min) and the CPU model, for the figures."""
    from controller.workers.pool import available_cores

    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        load = [round(v, 2) for v in os.getloadavg()]
    except OSError:
        load = []
    return {"cores": available_cores(), "cpus": os.cpu_count(), "load_avg": load, "cpu": model}


async def _plc_for(machine: Any, *, realtime: bool = False) -> tuple[Any, Any]:
    """The simulated PLC's Modbus server (its own process if possible) and its pump.

    ``realtime``: its process at real-time priority where permitted, as a PLC is a device of
    its own that answers within its cycle however busy the PC is (the latency measured is the
    service's, not the stand-in PLC's wait for a core).
    """
    try:
        from plant_sim.interfaces.plc_process import PlcProcess

        plc = PlcProcess(machine, port=0, realtime=realtime)

        def pump() -> None:
            plc.apply_writes()
            plc.refresh()
    except ImportError:  # pragma: no cover - an older simulator
        from plant_sim.interfaces.plc_server import PlcServer

        plc = PlcServer(machine, host="127.0.0.1", port=0)

        def pump() -> None:
            plc.refresh()
    return plc, pump


async def _run(
    frames: list,
    machine: Any,
    *,
    rate_hz: float,
    workdir: Path,
    ready_timeout_s: float = READY_TIMEOUT_S,
    workers: int = 0,
    tune: bool = False,
    via: str = "queue",
    priority: bool = False,
) -> dict[str, Any]:
    """Serve ``frames`` at ``rate_hz`` once the service is in RUN; stop after the last one.

    Nothing waits a fixed time: the pairs go in when the service reports its recovery to RUN
    (``RuntimeError`` naming what it waits for if that takes longer than ``ready_timeout_s``),
    and ``Service.run`` returns as soon as it handled the last pair. ``workers`` > 0 measures
    in that many worker processes; ``tune`` calls
    :func:`controller.service.latency.tune_for_latency`
    before the first pair. ``via = "spool"`` has a camera process (:class:`_SpoolCamera`: the
    same pairs, rendered there) write the pairs into a spool folder (PNG files) that the service
    reads as ``planer serve`` does (its spool reader thread); the latency then starts when a
    pair's metadata file is committed.
    ``priority`` runs the service as ``planer serve`` does: its event loop at real-time
    priority, the measurement and the records' writer at a raised nice value, the cores' wake-up
    latency as ``[service] cpu_latency_us`` asks (:func:`core.realtime.cpu_wakeup_latency`).
    """
    from dataclasses import replace

    from config.machine import load_machine
    from controller.runtime import RuntimeOptions, ServiceRuntime
    from controller.service.latency import MEASURE_NICE, GcPauses

    plc, plc_pump = await _plc_for(machine, realtime=priority)
    host, port = await plc.start()
    h, w = frames[0].image_a.shape
    cfg = load_machine()
    cfg = cfg.with_changes(
        plc=replace(cfg.plc, host=host, port=port),
        log=replace(cfg.log, path=workdir / f"bench-{workers}.sqlite"),
        frames=replace(cfg.frames, image_width=w, image_height=h),
    )
    svc_bus, amp = _amplifier(machine, f"planer-bench-{id(frames)}-{workers}")
    runtime = ServiceRuntime(cfg, can_bus=svc_bus, options=RuntimeOptions(
        workers=workers, plan_workers=False, worker_nice=MEASURE_NICE if priority else None,
        tune=tune, prioritize=priority, realtime=priority, cpu_wakeup=priority))
    service = await runtime.open()
    # what the figures need of each result, not the results: kept whole (their measurements,
    # profiles and passes) they made every young collection walk ~300 pairs' lists, 2-4 ms
    # pauses the service as it runs (results not kept) does not have
    seen: list[SimpleNamespace] = []
    records = service.records
    stored_at: dict[int, float] = {}
    if hasattr(records, "on_stored"):
        records.on_stored = lambda seq, at: stored_at.__setitem__(int(seq), at)
    running = asyncio.Event()
    service.on_event = lambda e: running.set() if e.kind is EventKind.RECOVERED else None
    source, camera, dropped = await _bench_source(runtime, via, workdir / f"spool-{workers}",
                                                  frames, rate_hz)
    stop = asyncio.Event()
    unfinished: list[int] = []
    put_at: dict[int, float] = {}
    handled = asyncio.Event()
    n_results = 0

    def on_result(r: Any) -> None:
        nonlocal n_results
        seen.append(SimpleNamespace(
            seq=r.seq, ok=r.ok, applied=r.applied, t_s=r.t_s, latency_s=r.latency_s,
            error=r.error, extra={"timing_ms": r.extra.get("timing_ms", {})}))
        n_results += 1
        if n_results + dropped() >= len(frames):
            handled.set()

    service.on_result = on_result

    async def feed_frames() -> None:
        # the service is running (PLC and CAN heard, confirmation time passed): pairs go in
        try:
            await asyncio.wait_for(running.wait(), ready_timeout_s)
        except asyncio.TimeoutError:
            status = service.status()
            why = status.safe_reason if status.t_s is not None else "no cycle ran"
            stop.set()
            raise RuntimeError(
                f"service benchmark: service not in RUN after {ready_timeout_s:g} s ({why})"
            ) from None
        put_at.update(await _put_frames(frames, source, camera, rate_hz))
        try:  # every pair handled or dropped by the source (a backstop: never hang)
            await asyncio.wait_for(handled.wait(), DRAIN_TIMEOUT_S)
        except asyncio.TimeoutError:
            unfinished.append(len(frames) - n_results - dropped())
        stop.set()

    pump = asyncio.create_task(_pump_plant(amp, plc_pump, stop))
    feeder = asyncio.create_task(feed_frames())
    gc_pauses = GcPauses()
    try:
        with gc_pauses:
            await runtime.run(stop=stop)
        await feeder  # re-raises the deadline
    finally:
        stop.set()
        feeder.cancel()
        await asyncio.gather(pump, feeder, return_exceptions=True)
        runtime.close()
        if camera is not None:
            camera.close()
        amp.close()
        await plc.stop()
        if hasattr(plc, "close"):  # the server's process
            plc.close()
    out = _latency_figures(SimpleNamespace(results=seen, records=service.records,
                                           measurement=service.measurement),
                           put_at, stored_at, gc_pauses, frames=frames, rate_hz=rate_hz,
                           workers=workers)
    out["dropped"] = dropped()
    if unfinished:
        out["unfinished"] = unfinished[0]  # neither handled nor dropped after DRAIN_TIMEOUT_S
    return _how_it_ran(out, via=via, runtime=runtime, plc=plc, priority=priority)


def _how_it_ran(out: dict[str, Any], *, via: str, runtime: Any, plc: Any,
                priority: bool) -> dict[str, Any]:
    """The figures with how the run was made: the path of the pairs and the priorities."""
    from controller.service.latency import MEASURE_NICE

    out["via"] = via
    out["priority"] = {"service_bus": runtime.granted,
                       "measurement_nice": MEASURE_NICE if priority else None,
                       "plc_process": getattr(plc, "priority", None),
                       "cpu_wakeup": runtime.wakeup}
    if via == "spool":
        out["latency_from"] = "pair committed to the spool (its metadata file renamed)"
        out["spool_image_format"] = SPOOL_IMAGE_FORMAT
    return out


async def _bench_source(runtime: Any, via: str, spool_dir: Path, frames: list,
                        rate_hz: float) -> tuple[Any, Any, Callable[[], int]]:
    """The service's frame source (given to ``runtime``), the spool camera, the drop counter.

    ``via = "spool"``: a spool folder that a camera process (:class:`_SpoolCamera`) writes; else
    an in-process queue of :data:`QUEUE_PAIRS` pairs that drops the oldest.
    """
    from dataclasses import replace

    from controller.frames.source import QueueFrameSource, open_frame_source

    if via == "spool":
        source = runtime.attach(open_frame_source(replace(runtime.cfg.frames, source="spool",
                                                          spool_dir=spool_dir)))
        camera = await asyncio.get_running_loop().run_in_executor(
            None, _SpoolCamera, spool_dir, len(frames), rate_hz)

        def dropped() -> int:  # given up, or pruned by the camera before the reader got them
            return int(getattr(source, "abandoned", 0)) + int(getattr(source, "missed", 0))

        return source, camera, dropped
    queue = runtime.attach(QueueFrameSource(maxsize=min(QUEUE_PAIRS, len(frames))))
    return queue, None, lambda: int(queue.dropped)


async def _pump_plant(amp: Any, plc_pump: Callable[[], Any], stop: asyncio.Event) -> None:
    """Step the simulated amplifier and PLC every 5 ms until ``stop``."""
    t0 = time.monotonic()
    while not stop.is_set():
        amp.pump(time.monotonic() - t0)
        plc_pump()
        await asyncio.sleep(0.005)


async def _put_frames(frames: list, source: Any, camera: Any, rate_hz: float) -> dict[int, float]:
    """Hand the pairs in at the camera's rate (not a wait for the service); when each went in."""
    loop = asyncio.get_running_loop()
    if camera is not None:  # the camera process writes them, telling when each is there
        return await loop.run_in_executor(None, camera.run)
    put_at: dict[int, float] = {}
    t_next = loop.time()
    for f in frames:
        put_at[int(f.seq)] = time.monotonic()
        source.put(f)
        t_next += 1.0 / rate_hz
        await asyncio.sleep(max(0.0, t_next - loop.time()))
    return put_at


def _amplifier(machine: Any, channel: str) -> tuple[Any, Any]:
    """The service's end of a virtual CAN bus and the simulated amplifier on its other end."""
    import can

    from plant_sim.interfaces.amp_node import AmpNode, AmpNodeCore

    amp = AmpNode(can.Bus(interface="virtual", channel=channel),
                  AmpNodeCore(machine, knives=machine.knives), own_bus=True)
    return can.Bus(interface="virtual", channel=channel), amp


def _camera_main(conn: Any, spool_dir: str, n: int, rate_hz: float,
                 image_format: str = SPOOL_IMAGE_FORMAT, clock_at_rename: bool = True) -> None:
    """The camera process: render the pairs, then on "go" write them at ``rate_hz``.

    A pair's time is taken just before its commit, the rename of its metadata file (the last
    step of ``SpoolWriter.write``; ``clock_at_rename=False``: before that file is written, as
    until 2026-11-25 evening, which counted the camera's own write of it, 0.1-0.2 ms, more when
    this process is preempted): a clock read after the rename could come late, as the commit
    wakes the service's reader thread (real-time priority where permitted), which may take
    this process's core at once and read the pair before this process reads its clock.
    """
    import protocol.spool as spool
    from protocol.spool import SpoolWriter

    frames, _ = _frames(n)
    commit_at: list[float] = []
    write_file = spool.atomic_write_bytes

    def timed_write(path: Path, data: bytes, **kw: Any) -> None:
        if not str(path).endswith(".json"):  # an image
            write_file(path, data, **kw)
        elif clock_at_rename:  # the commit marker: written aside, the pair is there once renamed
            tmp = os.path.join(os.path.dirname(path), f".{os.path.basename(path)}.bench.tmp")
            with open(tmp, "wb") as fh:
                fh.write(data)
            commit_at.append(time.monotonic())
            os.replace(tmp, path)
        else:
            commit_at.append(time.monotonic())
            write_file(path, data, **kw)

    spool.atomic_write_bytes = timed_write  # this process only
    # the writer keeps every pair: the camera prunes to SPOOL_KEEP itself, after the commit
    # (the writer's own pruning would follow the commit inside ``write``)
    writer = SpoolWriter(Path(spool_dir), keep=n + 1, fsync=False, image_format=image_format)
    conn.send("ready")
    if conn.recv() != "go":
        return
    times = []
    t_next = time.monotonic()
    for f in frames:
        writer.write(f)  # committed: its metadata file renamed
        times.append((int(f.seq), commit_at[-1]))
        _prune_slot(Path(spool_dir), writer.next_slot - 1 - SPOOL_KEEP, image_format)
        t_next += 1.0 / rate_hz
        time.sleep(max(0.0, t_next - time.monotonic()))
    conn.send(times)


def _prune_slot(spool_dir: Path, slot: int, image_format: str = SPOOL_IMAGE_FORMAT) -> None:
    """Delete one pair's files as ``SpoolWriter`` prunes (its metadata file first).

    By their names (the camera wrote them): no listing of the folder, which would take the
    CPU just after the commit, when the service's reader and event loop need it.
    """
    if slot < 0:
        return
    stem = f"pair-{slot:012d}"
    suffix = ".npy" if image_format == "npy" else ".png"
    for name in (f"{stem}.json", f"{stem}.a{suffix}", f"{stem}.b{suffix}"):
        with contextlib.suppress(FileNotFoundError):
            os.unlink(os.path.join(spool_dir, name))


class _SpoolCamera:
    """A camera in another process writing a spool folder (monotonic clock: the host's)."""

    def __init__(self, spool_dir: Path, n: int, rate_hz: float) -> None:
        import multiprocessing

        ctx = multiprocessing.get_context("spawn")
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_camera_main, args=(child, str(spool_dir), n, rate_hz,
                                                     SPOOL_IMAGE_FORMAT,
                                                     COMMIT_CLOCK_AT_RENAME),
                                daemon=True, name="planer-bench-camera")
        self.proc.start()
        child.close()
        if not self.conn.poll(READY_TIMEOUT_S) or self.conn.recv() != "ready":
            self.close()
            raise RuntimeError("service benchmark: the camera process did not start")

    def run(self) -> dict[int, float]:
        """Write every pair; their commit times (monotonic s) by sequence number."""
        self.conn.send("go")
        return dict(self.conn.recv())

    def close(self) -> None:
        """Stop the camera process."""
        self.proc.join(1.0)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(1.0)
        self.conn.close()


def _latency_figures(service: Any, put_at: dict[int, float], stored_at: dict[int, float],
                     gc_pauses: Any, *, frames: list, rate_hz: float,
                     workers: int) -> dict[str, Any]:
    from controller.service.latency import idle_collector

    res = service.results
    applied = [r for r in res if r.applied]
    failed = [r for r in res if not r.ok]
    h, w = frames[0].image_a.shape
    out: dict[str, Any] = {
        "width": int(w),
        "height": int(h),
        "pairs": len(res),
        "applied": len(applied),
        "failed": len(failed),
        "rate_hz": rate_hz,
        "workers": workers,
        "transport": "Modbus TCP 127.0.0.1 (PLC in its own process) + virtual CAN",
        "target_p99_ms": TARGETS["p99_ms"],
        "target_max_ms": TARGETS["max_ms"],
        "target_p99_over_median": TARGETS["p99_over_median"],
        "latency_from": "pair handed to the frame source",
        "latency_to": "feed setpoint written (Modbus) and offsets sent (CAN)",
    }
    e2e, handle, parts = [], [], {k: [] for k in
                                  ("queue", "plc_read", "handoff", "vision", "checks",
                                   "control")}
    after = []
    for r in applied:
        done = r.t_s + r.latency_s  # service clock = time.monotonic
        handle.append(r.latency_s * 1e3)
        t_put = put_at.get(int(r.seq))
        if t_put is not None:
            e2e.append((done - t_put) * 1e3)
            parts["queue"].append(max(0.0, r.t_s - t_put) * 1e3)
        tm = r.extra.get("timing_ms", {})
        vision = float(tm.get("vision_ms", 0.0))
        parts["plc_read"].append(float(tm.get("plc_read_ms", 0.0)))
        parts["vision"].append(vision)
        checks = float(tm.get("checks_ms", 0.0))
        parts["checks"].append(checks)
        parts["handoff"].append(max(0.0, float(tm.get("measure_ms", 0.0)) - vision - checks))
        parts["control"].append(float(tm.get("control_ms", 0.0)))
        if int(r.seq) in stored_at:
            after.append((stored_at[int(r.seq)] - done) * 1e3)
    if put_at and applied:
        first = min(put_at.values())
        last = max(r.t_s + r.latency_s for r in applied)
        out["served_pairs_per_s"] = len(res) / (last - first) if last > first else None
    lat = e2e or handle
    if lat:
        # the first pairs after the idle start-up (cold caches, first calls) are not the
        # steady state the p99 describes: reported apart; the max counts every pair
        warm = min(WARMUP_PAIRS, len(lat) - 1)
        s = latency_stats(lat[warm:])
        every = latency_stats(lat)
        out.update(median_ms=s["median"], p99_ms=s["p99"], max_ms=every["max"],
                   warmup_pairs=warm, warmup_max_ms=max(lat[:warm], default=None),
                   p99_all_ms=every["p99"])
        out["p99_over_median"] = s["p99"] / s["median"] if s["median"] > 0 else None
        out["meets"] = {
            "p99": s["p99"] <= TARGETS["p99_ms"], "max": every["max"] <= TARGETS["max_ms"],
            "p99_over_median": out["p99_over_median"] is not None
            and out["p99_over_median"] <= TARGETS["p99_over_median"],
        }
    out["handle_ms"] = latency_stats(handle)  # from the service taking the pair (the old figure)
    out["breakdown_ms"] = {k: latency_stats(v) for k, v in parts.items()}
    out["record_after_setpoint_ms"] = latency_stats(after)
    records = service.records
    batches = getattr(records, "batches", 0)
    out["commits"] = batches
    out["pairs_per_commit"] = len(res) / batches if batches else None
    out["gc"] = gc_pauses.summary()
    out["gc"]["between_pairs"] = idle_collector() is not None  # run after a pair's record
    out["measured_inline"] = int(getattr(getattr(service, "measurement", None), "inline_count", 0))
    if failed:
        out["failed_reasons"] = sorted({str(r.error).split(":")[0] for r in failed})[:5]
    return out


# ---------------------------------------------------------------------------------------------
# workers: throughput of the measurement in processes


# ---------------------------------------------------------------------------------------------


def _frames(n: int, *, seed: int = 1) -> tuple[list, Any]:
    """``n`` rendered pairs, and a machine in its first state (no board yet) for the PLC.

    The PLC's machine is not stepped while the pairs go in: in its first state it reports the
    spindle and the feed running and no board under the camera, so the service reaches RUN
    without waiting for a measurement.
    """
    from config.sim import default_sim
    from plant_sim.machine.machine import Machine

    machine = Machine(default_sim(), seed=seed)
    frames: list = []
    while len(frames) < n:  # render before timing anything
        frames += machine.advance(0.05)
    return frames[:n], Machine(default_sim(), seed=seed, render_images=False)


def run(quick: bool = False) -> dict[str, Any]:
    """Latency at 100 pairs/s (in process and in worker processes) and the workers' scaling.

    Parameters
    ----------
    quick : bool
        Fewer pairs (60 instead of 300), the in-process latency run only, one pass of scaling.
        Every latency run is as ``planer serve`` runs: tuned, its event loop at real-time
        priority, the measurement at a raised nice value.

    Returns
    -------
    dict
        The in-process latency run's figures at the top level (``width``, ``height``,
        ``pairs``, ``applied``, ``median_ms``, ``p99_ms``, ``max_ms``, ``target_p99_ms``,
        ``breakdown_ms``, ``record_after_setpoint_ms``, ``gc`` ...), ``modes`` (the same per
        ``workers`` setting), ``scaling`` (:func:`scaling`) and ``machine``.
    """
    import logging

    from config.machine import load_machine, rig_path
    from config.rig import load_rig
    from controller.service.measurement import MachineFacts

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    n = 60 if quick else 300
    machine_before = machine_description()
    modes = []
    runs = [(0, RATE_HZ, "queue")] if quick else [
        (0, RATE_HZ, "queue"), (0, RATE_HZ, "spool"), (1, RATE_HZ, "queue"),
        (2, RATE_HZ, "queue"), (2, RATE_HZ, "spool")]
    only_via = os.environ.get(ONLY_VIA_ENV, "").strip()
    if only_via:  # e.g. repeated spool runs while working on the spool (not the CLI's contract)
        if only_via not in ("queue", "spool"):
            raise ValueError(f"{ONLY_VIA_ENV} must be 'queue' or 'spool', got {only_via!r}")
        runs = [r for r in runs if r[2] == only_via] or [(0, RATE_HZ, only_via)]
    for workers, rate, via in runs:
        frames, machine = _frames(n if rate == RATE_HZ else n // 2)
        with tempfile.TemporaryDirectory(prefix="planer-bench-") as d:
            modes.append(asyncio.run(_run(frames, machine, rate_hz=rate, workdir=Path(d),
                                          workers=workers, tune=True, via=via,
                                          priority=True)))
    regs = machine.register_values()
    facts = MachineFacts(radius_mm=float(regs["cutterhead_radius_mm"]),
                         knives=int(regs["knives"]), spindle_rpm=float(regs["spindle_rpm"]))
    rig = load_rig(rig_path(load_machine()))
    scale_frames = [f for f in frames[:40] if f.image_a is not None]
    out = dict(modes[0])
    out["modes"] = modes
    out["scaling"] = scaling(scale_frames, rig, facts, repeat=1 if quick else 3,
                             rounds=1 if quick else 5)
    out["machine"] = {**machine_before, "load_avg_after": machine_description()["load_avg"]}
    return out


def text(result: dict[str, Any]) -> str:
    """The readable lines of the service part (latency, breakdown, workers' scaling)."""

    def trio(s: dict[str, float]) -> str:
        return (f"{s['median']:.2f} / {s['p99']:.2f} / {s['max']:.2f}" if s else "-")

    m = result.get("machine", {})
    lines = [f"service ({result['width']}x{result['height']}, {result['rate_hz']:g} pairs/s, "
             f"{result['transport']}); machine: {m.get('cores')} cores, load "
             f"{m.get('load_avg')}"]
    for mode in result.get("modes", [result]):
        where = (f"{mode['workers']} worker process(es)" if mode.get("workers")
                 else "in process") + f" at {mode['rate_hz']:g} pairs/s" + (
                     f", through a spool ({mode.get('spool_image_format', 'png')})"
            if mode.get("via") == "spool" else "")
        if "p99_ms" not in mode:
            lines.append(f"  {where}: no pair applied ({mode['failed']} failed)")
            continue
        meets = mode.get("meets", {})
        verdict = ", ".join(f"{k} {'ok' if v else 'MISSED'}" for k, v in meets.items())
        lines.append(
            f"  {where}: pair -> setpoints median {mode['median_ms']:.2f} ms, p99 "
            f"{mode['p99_ms']:.2f} ms, max {mode['max_ms']:.2f} ms, p99/median "
            f"{mode['p99_over_median']:.2f} ({verdict}; targets p99 <= "
            f"{mode['target_p99_ms']:g}, max <= {mode['target_max_ms']:g}, p99/median <= "
            f"{mode['target_p99_over_median']:g}; first {mode.get('warmup_pairs', 0)} pairs "
            f"apart, max {(mode.get('warmup_max_ms') or 0):.2f} ms); "
            f"{mode['applied']}/{mode['pairs']} applied"
            f", {mode.get('dropped', 0)} dropped by the source"
            + (f", {mode['unfinished']} UNFINISHED" if mode.get("unfinished") else ""))
        parts = "; ".join(f"{k} {trio(v)}" for k, v in mode.get("breakdown_ms", {}).items())
        lines.append(f"    where it goes (median / p99 / max ms): {parts}")
        gc_ = mode.get("gc", {})
        lines.append(
            f"    record after the setpoint {trio(mode.get('record_after_setpoint_ms', {}))} ms,"
            f" {mode.get('commits')} commits ({(mode.get('pairs_per_commit') or 0):.1f} pairs "
            f"each); gc {gc_.get('collections')} collections, longest "
            f"{gc_.get('max_pause_ms', 0):.2f} ms"
            f"{' (between pairs)' if gc_.get('between_pairs') else ''}; "
            f"{mode.get('measured_inline', 0)} pairs "
            "measured on the event loop's thread")
    sc = result.get("scaling")
    if sc:
        def row(r: dict[str, Any]) -> str:
            here = r.get("ratio_to_in_process")
            vs_here = f", x{here:.2f} in process" if here is not None else ""
            return (f"{r['workers']}: {r['pairs_per_s']:.0f} pairs/s (x{r['ratio']:.2f} one "
                    f"worker, {r['per_worker']:.2f} per worker{vs_here})")

        rows = ", ".join(row(r) for r in sc["rows"])
        target = sc.get("target_per_worker", 0.8)
        lines.append(f"  workers ({sc['cores']} cores; in process, one thread: "
                     f"{sc['in_process_pairs_per_s']:.0f} pairs/s): {rows}; target "
                     f"{target:g} per worker")
    return "\n".join(lines)
