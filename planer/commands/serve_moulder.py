"""``planer serve`` of a moulder (``machine.toml`` with several ``[[heads]]``): its heads, one feed.

The same command, the same lines as for one head, each naming its head: where it connects, one
progress line per head every ``[log] print_every`` pairs of that head, every change of a head's
safe state, why it waits; systemd's notifications as for one head, and as for one head no run
times of its own when its output is the journal (a line then starts with ``[<head>]``). Each head
reads its own frame source (its spool folder, ``<[frames] spool_dir>/<head>`` unless the head
names one, or its camera). Measured in ``[service] workers`` (``--workers``) worker processes the
heads share, each head's pairs with its own rig (``controller.moulder.compose.share_workers``; 0:
in the service's threads).
"""

from __future__ import annotations

import asyncio
import signal
import sys
from pathlib import Path
from typing import Any

from config.machine import MachineConfig, head_config
from controller.edge.compose import serving
from controller.sd_notify import Notifier, under_journald
from controller.service.supervisor import SafetyState
from core.realtime import BUS_RT_PRIORITY, realtime_thread


async def serve_moulder(cfg: MachineConfig, *, log_path: Path | str, opcua: str | None,
                        http: str | None, max_frames: int | None, status_every: float,
                        say: Any, printers: tuple, workers: int | None = None) -> int:
    """Open, run until SIGINT/SIGTERM (or ``max_frames`` pairs of all heads), close; exit code.

    ``printers``: ``planer serve``'s ``(event_printer, progress_printer, waiting_line)``, the
    same lines as one head's, here each with its head.
    """
    from controller.frames.source import open_frame_source
    from controller.moulder.compose import open_moulder_service, share_workers
    from controller.service.latency import MEASURE_NICE

    notifier = Notifier()
    moulder = None
    pool = None
    sources: dict[str, Any] = {}

    def get() -> Any:
        return moulder

    async with serving(cfg, get, opcua=opcua, http=http, say=say, log=log_path):
        try:
            moulder = open_moulder_service(cfg, log_path=log_path)
            n = cfg.service.workers if workers is None else workers
            if n:
                shape = cfg.frames.image_shape
                opened = moulder  # started off the event loop (each worker sets up first)
                pool, warning = await asyncio.get_running_loop().run_in_executor(
                    None, lambda: share_workers(opened, n, shape=shape, nice=MEASURE_NICE,
                                                timeout_s=cfg.safety.measurement_timeout_s))
                if warning:
                    say(f"planer serve: {warning}")
                if pool is not None:
                    say(f"planer serve: {pool.workers} measurement worker process(es) shared "
                        f"by the {len(cfg.heads)} heads")
            for hc in cfg.heads:
                sources[hc.name] = open_frame_source(head_config(cfg, hc.name).frames)
            return await _run(moulder, sources, cfg, max_frames=max_frames,
                              status_every=status_every, notifier=notifier, say=say,
                              printers=printers)
        finally:
            if moulder is not None:
                moulder.close()
            if pool is not None:
                pool.close()
            for src in sources.values():
                src.close()


async def _run(moulder: Any, sources: dict[str, Any], cfg: MachineConfig, *,
               max_frames: int | None, status_every: float, notifier: Notifier, say: Any,
               printers: tuple) -> int:
    event_printer, progress_printer, waiting_line = printers
    t0 = moulder.first.clock()
    journal = under_journald()  # the journal stamps every line itself

    def at(t: float) -> str:
        return "" if journal else f"t={t:9.3f} s  "

    say(f"plc: {cfg.plc.host}:{cfg.plc.port} unit {cfg.plc.unit_id} (the feed and "
        f"{len(moulder.heads)} head blocks)")
    for hc in cfg.heads:
        hcfg = head_config(cfg, hc.name)
        svc = moulder.heads[hc.name]
        say(f"head {hc.name}: {hc.face}, target pitch {hc.target_pitch_mm} mm, "
            f"can {hcfg.can.interface}:{hcfg.can.channel} node {hcfg.can.node_id}, frames "
            f"{hcfg.frames.spool_dir if hcfg.frames.source == 'spool' else hcfg.frames.camera_id}"
            f", log {svc.log.path}")

        def stamp(t: float, name: str = hc.name) -> str:
            return f"{at(t)}[{name}] "

        svc.on_event = event_printer(t0, stamp, notifier)
        svc.on_result = progress_printer(svc, sources[hc.name], t0, cfg.log.print_every,
                                         stamp, notifier)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)

    async def tell_why_waiting() -> None:
        while not stop.is_set():
            await asyncio.sleep(status_every)
            for name, svc in moulder.heads.items():
                status = svc.status()
                if status.t_s is not None and status.state != SafetyState.RUN.value:
                    line = f"[{name}] " + waiting_line(
                        tuple(status.missing), plc=f"{cfg.plc.host}:{cfg.plc.port}",
                        can=f"{svc.cfg.can.interface}:{svc.cfg.can.channel}",
                        frames=str(svc.cfg.frames.spool_dir))
                    notifier.status(line)
                    say(at(svc.clock() - t0) + line)

    watcher = asyncio.create_task(tell_why_waiting())
    watchdog = asyncio.create_task(notifier.watchdog())
    try:
        # the event loop (every head's buses, pairs and the feed) raised as one head's bus
        # thread is (SCHED_FIFO where permitted, else nice; the RLIMIT_RTTIME guard)
        with realtime_thread(rt_priority=BUS_RT_PRIORITY) as granted:
            started = asyncio.create_task(moulder.run(sources, stop=stop,
                                                      max_frames=max_frames))
            await asyncio.sleep(0)
            say(f"priority: service bus (every head and the feed) {granted}")
            say("ready")
            notifier.ready("serving a moulder: waiting in the safe state until every source "
                           "answers")
            await started
    finally:
        watcher.cancel()
        watchdog.cancel()
        notifier.stopping("stopping")
    for name, svc in moulder.heads.items():
        c = svc.counters
        print(f"stopped [{name}]: {c['frames']} pairs, {c['ok']} measured, {c['failed']} failed, "
              f"{c['safe_entries']} safe-state entries; quality log {svc.log.path}",
              file=sys.stderr, flush=True)
    return 0
