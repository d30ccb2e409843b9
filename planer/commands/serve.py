"""``planer serve``: the service beside the PLC, until stopped.

Reads image pairs from the configured frame source, measures them, closes the feed and
uniformity loops over Modbus TCP (PLC) and CAN (piezo amplifier), and appends every measurement
to the quality log. Prints where it connects, then one line per ``[log] print_every``
measurements and every change of the safe state. Ctrl-C or SIGTERM stops it cleanly. The same
command runs against ``planer sim`` and against the real machine: only ``--config`` changes.
"""

from __future__ import annotations

import argparse

HELP = "run the service beside the PLC (measure, control, log) until stopped"


def configure(parser: argparse.ArgumentParser) -> None:
    """Add this command's arguments."""
    parser.add_argument(
        "--config", default=None, help="service config (default: the shipped config/machine.toml)"
    )
    parser.add_argument("--log", default=None, metavar="PATH", help="quality log (overrides [log])")
    parser.add_argument(
        "--max-frames",
        type=int,
        default=None,
        metavar="N",
        help="stop after N image pairs (default: run until stopped)",
    )


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    import asyncio
    import logging
    import signal
    import sys
    from pathlib import Path

    from config.machine import load_machine
    from controller.frame_source import open_frame_source
    from controller.service import open_service
    from planer.checks import check_int

    if args.max_frames is not None:
        check_int("--max-frames", args.max_frames, lo=1)
    cfg = load_machine(args.config)
    if cfg.frames.source != "spool":
        raise ValueError("planer serve needs frames.source = spool (inprocess: tests and HIL)")
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)

    def say(line: str) -> None:
        print(line, flush=True)

    async def main() -> int:
        service = open_service(cfg, log_path=Path(args.log) if args.log else None)
        source = open_frame_source(cfg.frames)
        t0 = service.clock()
        say(f"plc: {cfg.plc.host}:{cfg.plc.port} unit {cfg.plc.unit_id}")
        say(f"can: {cfg.can.interface}:{cfg.can.channel}")
        say(f"frames: {cfg.frames.source} {cfg.frames.spool_dir}")
        say(f"log: {service.log.path}")
        say(
            f"quality: {cfg.quality.class_name}, target pitch {cfg.quality.target_pitch_mm} mm, "
            f"safe state {cfg.safety.safe_state}"
        )
        service.on_event = lambda t, e: say(f"t={t - t0:9.3f} s  {e}")
        every = cfg.log.print_every
        window: list = []

        def on_result(r) -> None:
            window.append(r)
            if len(window) < every:
                return
            ok = [x for x in window if x.ok]
            pitch = sum(x.measurement.pitch_mm for x in ok) / len(ok) if ok else float("nan")
            cv = sum(x.measurement.uniformity_cv for x in ok) / len(ok) if ok else float("nan")
            lat = sorted(x.latency_s for x in window)
            feed = r.feed_setpoint_mm_s
            say(
                f"t={r.t_s - t0:9.3f} s  #{service.counters['frames']}  {r.state}  "
                f"ok {len(ok)}/{len(window)}  pitch {pitch:.3f} mm  cv {cv:.3f}  "
                f"feed {feed if feed is not None else float('nan'):.1f} mm/s  "
                f"offsets [{' '.join(f'{v:+.2f}' for v in r.offsets_um)}] um  "
                f"latency p50 {lat[len(lat) // 2] * 1e3:.1f} ms"
            )
            window.clear()

        service.on_result = on_result
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        say("ready")
        try:
            await service.run(source, stop=stop, max_frames=args.max_frames)
        finally:
            service.close()
            source.close()
        c = service.counters
        print(
            f"stopped: {c['frames']} pairs, {c['ok']} measured, {c['failed']} failed, "
            f"{c['safe_entries']} safe-state entries; quality log {service.log.path}",
            file=sys.stderr,
            flush=True,
        )
        return 0

    return asyncio.run(main())
