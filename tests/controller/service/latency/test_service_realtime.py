"""The service in real time (``Service.run``) against the real Modbus server and a CAN node.

Nothing here waits a fixed wall time for the world: the pairs go in once the service reported
its recovery to RUN, and ``run`` stops by itself after the last pair was handled; the wall-clock
limits are generous backstops for a loaded machine, not timings.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import replace

from controller.service.events import EventKind

N_PAIRS = 6


async def _run(frames, machine, tmp_path):
    import can

    from config.machine import load_machine
    from controller.frames.source import QueueFrameSource
    from controller.service.service import open_service
    from plant_sim.interfaces.amp_node import AmpNode, AmpNodeCore
    from plant_sim.interfaces.plc_server import PlcServer

    server = PlcServer(machine, host="127.0.0.1", port=0)
    host, port = await server.start()
    cfg = load_machine()
    cfg = cfg.with_changes(
        plc=replace(cfg.plc, host=host, port=port),
        log=replace(cfg.log, path=tmp_path / "rt.sqlite"),
    )
    channel = f"planer-rt-{id(frames)}"
    amp = AmpNode(
        can.Bus(interface="virtual", channel=channel),
        AmpNodeCore(machine, knives=machine.knives),
        own_bus=True,
    )
    service = open_service(cfg, can_bus=can.Bus(interface="virtual", channel=channel))
    service.keep_results = True
    running = asyncio.Event()
    service.on_event = lambda e: running.set() if e.kind is EventKind.RECOVERED else None
    source = QueueFrameSource(maxsize=N_PAIRS)
    stop = asyncio.Event()

    async def pump_amp() -> None:
        t0 = time.monotonic()
        while not stop.is_set():
            amp.pump(time.monotonic() - t0)
            server.refresh()
            await asyncio.sleep(0.005)

    async def feed_frames() -> None:
        await asyncio.wait_for(running.wait(), timeout=60.0)
        for f in frames:
            source.put(f)
            await asyncio.sleep(0.04)  # 25 pairs/s; the queue holds them all anyway

    pump = asyncio.create_task(pump_amp())
    feeder = asyncio.create_task(feed_frames())
    try:
        await asyncio.wait_for(service.run(source, stop=stop, max_frames=N_PAIRS), 240.0)
        await feeder  # re-raises a timeout waiting for RUN
    finally:
        stop.set()
        feeder.cancel()
        await asyncio.gather(pump, feeder, return_exceptions=True)
        service.close()
        amp.close()
        await server.stop()
    return service


def test_run_in_real_time_applies_every_pair(tmp_path):
    from config.sim import default_sim
    from controller.quality.log import QualityLog
    from plant_sim.machine.machine import Machine

    machine = Machine(default_sim(), seed=3)
    frames: list = []
    while len(frames) < N_PAIRS:
        frames += machine.advance(0.05)
    service = asyncio.run(_run(frames[:N_PAIRS], machine, tmp_path))
    res = service.results
    assert [r.seq for r in res] == [f.seq for f in frames[:N_PAIRS]]
    assert frames[0].image_a.shape == (493, 659)
    applied = [r for r in res if r.applied]
    assert len(applied) >= 4 and all(r.ok for r in applied)
    assert all(r.latency_s > 0 for r in res)
    assert service.counters["errors"] == 0
    # every pair was logged by the real-time path (worker-thread append), in order
    with QualityLog(tmp_path / "rt.sqlite", create=False) as log:
        assert [r.seq for r in log.records()] == [r.seq for r in res]
