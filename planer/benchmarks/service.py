"""Service latency: from a frame's arrival to its setpoints on the wire (``planer bench``).

Set-up: the simulated machine renders 659x493 pairs once (before timing); its PLC Modbus
server listens on an ephemeral 127.0.0.1 port and its piezo amplifier node answers on a virtual
CAN bus, pumped every 10 ms. The service runs exactly as ``planer serve`` does (real time, the
measurement in a worker thread, the PLC and CAN cycle tasks beside it, quality log on disk); the
frames are handed over through an in-process queue at ``rate_hz`` once the service reported RUN,
and the run ends when the service handled the last pair (no fixed waits). The latency of a pair is
measured by the service itself: wall time from the start of ``handle_frame`` (the pair taken
from the source) to the return of the Modbus write of the feed setpoint and the CAN send of the
offsets, i.e. PLC read + measurement + plausibility + knife phase + both loops + both writes.
The quality log append comes after and is not counted.
"""

from __future__ import annotations

import asyncio
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from controller.events import EventKind

READY_TIMEOUT_S = 60.0
"""Deadline for the service to reach RUN before the pairs go in (a loaded machine), s."""


async def _run(
    frames: list,
    machine: Any,
    *,
    rate_hz: float,
    workdir: Path,
    ready_timeout_s: float = READY_TIMEOUT_S,
) -> dict[str, Any]:
    """Serve ``frames`` at ``rate_hz`` once the service is in RUN; stop after the last one.

    Nothing waits a fixed time: the pairs go in when the service reports its recovery to RUN
    (``RuntimeError`` naming what it waits for if that takes longer than ``ready_timeout_s``),
    and ``Service.run`` returns as soon as it handled the last pair.
    """
    from dataclasses import replace

    import can

    from config.machine import load_machine
    from controller.frame_source import QueueFrameSource
    from controller.service import open_service
    from plant_sim.amp_node import AmpNode, AmpNodeCore
    from plant_sim.plc_server import PlcServer
    from protocol.piezo_can import PiezoCodec

    server = PlcServer(machine, host="127.0.0.1", port=0)
    host, port = await server.start()
    cfg = load_machine()
    cfg = cfg.with_changes(
        plc=replace(cfg.plc, host=host, port=port),
        log=replace(cfg.log, path=workdir / "bench.sqlite"),
    )
    channel = f"planer-bench-{id(frames)}"
    svc_bus = can.Bus(interface="virtual", channel=channel)
    amp = AmpNode(
        can.Bus(interface="virtual", channel=channel),
        AmpNodeCore(machine, PiezoCodec.load(), knives=machine.knives),
        own_bus=True,
    )
    service = open_service(cfg, can_bus=svc_bus)
    service.keep_results = True
    running = asyncio.Event()
    service.on_event = lambda e: running.set() if e.kind is EventKind.RECOVERED else None
    source = QueueFrameSource(maxsize=len(frames))
    stop = asyncio.Event()

    async def pump_amp() -> None:
        t0 = time.monotonic()
        while not stop.is_set():
            now = time.monotonic() - t0
            amp.pump(now)
            server.refresh()
            await asyncio.sleep(0.01)

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
        for f in frames:  # the camera's rate, not a wait for the service
            source.put(f)
            await asyncio.sleep(1.0 / rate_hz)

    pump = asyncio.create_task(pump_amp())
    feeder = asyncio.create_task(feed_frames())
    try:
        await service.run(source, stop=stop, max_frames=len(frames))
        await feeder  # re-raises the deadline
    finally:
        stop.set()
        feeder.cancel()
        await asyncio.gather(pump, feeder, return_exceptions=True)
        service.close()
        amp.close()
        await server.stop()
    res = service.results
    applied = [r.latency_s * 1e3 for r in res if r.applied]
    failed = [r.latency_s * 1e3 for r in res if not r.ok]
    h, w = frames[0].image_a.shape
    out: dict[str, Any] = {
        "width": int(w),
        "height": int(h),
        "pairs": len(res),
        "applied": len(applied),
        "failed": len(failed),
        "rate_hz": rate_hz,
        "transport": "Modbus TCP 127.0.0.1 + virtual CAN",
        "target_p99_ms": 20.0,
    }
    if applied:
        out.update(
            median_ms=float(np.median(applied)),
            p99_ms=float(np.percentile(applied, 99)),
            max_ms=float(np.max(applied)),
        )
    if failed:
        out["failed_median_ms"] = float(np.median(failed))
    return out


def run(quick: bool = False) -> dict[str, Any]:
    """Latency of the service at 659x493 (median and p99 over the pairs whose setpoints went out).

    Parameters
    ----------
    quick : bool
        Fewer pairs (about 30 instead of 150).

    Returns
    -------
    dict
        ``width``, ``height``, ``pairs``, ``applied``, ``median_ms``, ``p99_ms``, ``max_ms``,
        ``target_p99_ms`` ...
    """
    import logging

    from config.sim import default_sim
    from plant_sim.machine import Machine

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    n = 30 if quick else 150
    cfg = default_sim()
    machine = Machine(cfg, seed=1)
    frames: list = []
    while len(frames) < n:  # render before timing anything
        frames += machine.advance(0.05)
    frames = frames[:n]
    with tempfile.TemporaryDirectory(prefix="planer-bench-") as d:
        return asyncio.run(_run(frames, machine, rate_hz=25.0, workdir=Path(d)))
