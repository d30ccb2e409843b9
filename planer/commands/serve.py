"""``planer serve``: the service beside the PLC, until stopped.

Reads image pairs from the configured frame source, measures them, closes the feed and
uniformity loops over Modbus TCP (PLC) and CAN (piezo amplifier), and appends every measurement
to the quality log. Prints where it connects, then one line per ``[log] print_every``
measurements and every change of the safe state; while it waits in the safe state (PLC not
answering, amplifier silent, no image pairs) it says so every ``--status-every`` seconds. Ctrl-C
or SIGTERM stops it cleanly. The same command runs against ``planer sim`` and against the real
machine: only ``--config`` changes (see ``docs/service.md``, "Running it").

Under systemd (``deploy/planer.service``, ``docs/deploy.md``) it speaks the notification
protocol: ``READY=1`` when it serves, ``STATUS=`` with its latest line, ``WATCHDOG=1`` from a
task on its event loop, ``STOPPING=1`` on the way out; with the journal as its output
(``JOURNAL_STREAM`` or ``INVOCATION_ID`` set) its lines carry no run times of their own and a
logged error stays on one line.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import sys
from collections.abc import Callable, Mapping
from typing import Any

from config.machine import load_machine
from controller.edge.compose import serving
from controller.opcua.compose import server_for
from controller.quality.log import log_target, vision_fields
from controller.runtime import RuntimeOptions, ServiceRuntime
from controller.sd_notify import Notifier, under_journald
from controller.service.events import EventKind
from controller.service.latency import MEASURE_NICE
from controller.service.supervisor import SafetyState
from controller.web.compose import listen_for
from core.checks import check_int
from planer.cli import output_file, output_folder


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
    parser.add_argument(
        "--workers", type=int, default=None, metavar="N",
        help="measure in N worker processes (overrides [service] workers; 0: in this process; "
        "more than the cores: a warning and one per core)",
    )
    parser.add_argument(
        "--status-every",
        type=float,
        default=5.0,
        metavar="S",
        help="while waiting in the safe state, say what is missing every S seconds (default 5)",
    )
    parser.add_argument(
        "--opcua", default=None, metavar="ENDPOINT",
        help="serve OPC UA (OPC 40550 Woodworking) at ENDPOINT, e.g. opc.tcp://127.0.0.1:4840 "
        "(overrides [opcua] endpoint; docs/opcua.md)",
    )
    parser.add_argument(
        "--http", default=None, metavar="HOST:PORT",
        help="serve the operator and quality web pages at HOST:PORT, e.g. 127.0.0.1:8080 "
        "(overrides [http] listen; docs/web.md)",
    )


_MISSING = {
    "plc": "PLC {plc} not answering",
    "can": "piezo amplifier on {can} silent",
    "measurement": "no valid image pair from {frames}",
    "machine": "machine not running (e-stop or spindle stopped)",
    "plc_data": "PLC registers implausible",
    "log": "quality log not writable",
    "service": "service error",
    "amplifier": "piezo amplifier faulted or not tracking",
}


def waiting_line(missing: tuple[str, ...], *, plc: str, can: str, frames: str) -> str:
    """One line saying why the service waits in the safe state.

    Parameters
    ----------
    missing : tuple of str
        The supervisor's missing sources (``controller.service.supervisor.SOURCES``).
    plc, can, frames : str
        Where the PLC, the CAN bus and the frames are expected, for the message.
    """
    names = {"plc": plc, "can": can, "frames": frames}
    parts = [_MISSING.get(m, m).format(**names) for m in missing]
    return "waiting in the safe state: " + ("; ".join(parts) or "confirming recovery")


def source_counts(source: Any) -> dict[str, int]:
    """What a frame source counts, for the progress lines (empty when it counts nothing).

    A camera source (``counters``: ``images``, ``pairs``, ``failed``, ``dropped``,
    ``queue_dropped`` ...) gives ``images``, ``pairs``, ``failed`` and ``dropped`` (pairs the
    pairing dropped plus frames the service did not take); a spool or queue source its
    ``received`` pairs and ``dropped`` (given up: ``abandoned``, or dropped from a full queue).
    """
    counters = getattr(source, "counters", None)
    if isinstance(counters, Mapping):
        out: dict[str, Any] = {k: counters.get(k) for k in ("images", "pairs", "failed")}
        drops = [counters.get(k) for k in ("dropped", "queue_dropped")]
        out["dropped"] = sum(d for d in drops if isinstance(d, int)) if any(
            isinstance(d, int) for d in drops) else None
    else:
        drops = [getattr(source, k, None) for k in ("abandoned", "dropped")]
        out = {"pairs": getattr(source, "received", None),
               "dropped": sum(d for d in drops if isinstance(d, int)) if any(
                   isinstance(d, int) for d in drops) else None}
    return {k: int(v) for k, v in out.items() if isinstance(v, int) and not isinstance(v, bool)}


def source_text(counts: Mapping[str, int]) -> str:
    """``"source: images 1200, pairs 600, failed 1, dropped 2"`` (``""`` for no counts)."""
    if not counts:
        return ""
    return "source: " + ", ".join(f"{k} {v}" for k, v in counts.items())


def vision_text(measurement: Any) -> str:
    """``"roll +0.42 deg, calibration applied (gain 0.897)"`` of a measurement (``""``: none)."""
    if measurement is None:
        return ""
    v = vision_fields(measurement, ok=False)
    parts = []
    if v.get("roll_deg") is not None:
        parts.append(f"roll {v['roll_deg']:+.2f} deg")
    state = v.get("calibration_state")
    if state is not None:
        gain = v.get("calibration_gain")
        parts.append(f"calibration {state}" + (f" (gain {gain:.3f})" if gain is not None else ""))
    return ", ".join(parts)


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    if args.max_frames is not None:
        check_int("--max-frames", args.max_frames, lo=1)
    if args.workers is not None:
        check_int("--workers", args.workers, lo=0)
    if not args.status_every > 0:
        raise ValueError(f"--status-every must be > 0, got {args.status_every}")
    cfg = load_machine(args.config)
    if cfg.frames.source not in ("spool", "camera"):
        raise ValueError(
            f"planer serve needs frames.source = spool or camera, got {cfg.frames.source!r} "
            "(inprocess is for tests and planer hil)"
        )
    output_folder(f"{args.config or 'config/machine.toml'}: frames.spool_dir", cfg.frames.spool_dir)
    log_opt = "--log" if args.log else f"{args.config or 'config/machine.toml'}: log.path"
    log_path = log_target(args.log or cfg.log.path,  # a postgresql:// URL or a file
                          check_file=lambda p: output_file(log_opt, p))
    journal = under_journald()
    handler = logging.StreamHandler()
    handler.setFormatter(_OneLine("%(levelname)s %(name)s: %(message)s") if journal
                         else logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    logging.basicConfig(level=logging.WARNING, handlers=[handler])
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    server_for(cfg, args.opcua)  # a bad endpoint or missing security: one line before starting
    listen_for(cfg, args.http)  # a bad address or no web packages: one line before starting
    if len(cfg.heads) > 1:  # a moulder: a service per head, one feed
        from planer.commands.serve_moulder import serve_moulder

        return asyncio.run(serve_moulder(cfg, log_path=log_path, opcua=args.opcua,
                                         http=args.http, max_frames=args.max_frames,
                                         status_every=args.status_every, say=_say,
                                         printers=(_event_printer, _progress_printer,
                                                   waiting_line), workers=args.workers))
    options = RuntimeOptions(workers=args.workers, worker_nice=MEASURE_NICE, prioritize=True,
                             realtime=True, cpu_wakeup=True)
    runtime = ServiceRuntime(cfg, options=options, log_path=log_path,
                             say=lambda line: _say(f"planer serve: {line}"))
    notifier = Notifier()  # a bad NOTIFY_SOCKET or WATCHDOG_USEC: one line before starting
    stamp = (lambda _t: "") if journal else (lambda t: f"t={t:9.3f} s  ")

    async def main() -> int:
        get = lambda: runtime.service  # noqa: E731
        async with serving(cfg, get, opcua=args.opcua, http=args.http, say=_say,
                           log=log_path) as servers, runtime:
            return await _serve(runtime, args, notifier=notifier, stamp=stamp,
                                servers_nice=None if servers is None
                                else servers.info.get("nice"))

    return asyncio.run(main())


def _say(line: str) -> None:
    print(line, flush=True)


def _frames_at(cfg: Any) -> str:
    if cfg.frames.source == "camera":
        return f"camera {cfg.frames.camera_id}"
    return f"spool {cfg.frames.spool_dir}"


class _OneLine(logging.Formatter):
    """Log records on one line each (the journal makes one entry per line)."""

    def format(self, record: logging.LogRecord) -> str:
        return " | ".join(line for line in super().format(record).splitlines() if line.strip())


async def _serve(runtime: ServiceRuntime, args: argparse.Namespace, *, notifier: Notifier,
                 stamp: Callable[[float], str], servers_nice: int | None = None) -> int:
    """Run the opened service until stopped: its lines, its events, why it waits.

    ``notifier`` tells systemd (ready, status, watchdog, stopping); ``stamp(t)`` is the run
    time's prefix of a line (empty under the journal, which stamps lines itself);
    ``servers_nice`` the nice value of the servers' process (``None``: no servers).
    """
    cfg, service = runtime.cfg, runtime.service
    assert service is not None
    if runtime.pool is not None:
        _say(f"workers: measuring in {runtime.pool.workers} process(es)")
    source = runtime.open_source()
    t0 = service.clock()
    _say(f"plc: {cfg.plc.host}:{cfg.plc.port} unit {cfg.plc.unit_id}")
    _say(f"can: {cfg.can.interface}:{cfg.can.channel}")
    frames_at = _frames_at(cfg)
    if cfg.frames.source == "camera":
        _say(f"frames: {frames_at}, trigger latches from the PLC {cfg.plc.host}:{cfg.plc.port}")
    else:
        _say(f"frames: {frames_at}")
    _say(f"log: {service.log.path}")
    _say(f"quality: {cfg.quality.class_name}, target pitch {cfg.quality.target_pitch_mm} mm, "
         f"safe state {cfg.safety.safe_state}")
    service.on_event = _event_printer(t0, stamp, notifier)
    service.on_result = _progress_printer(service, source, t0, cfg.log.print_every, stamp,
                                          notifier)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    where = {"plc": f"{cfg.plc.host}:{cfg.plc.port}",
             "can": f"{cfg.can.interface}:{cfg.can.channel}", "frames": frames_at}

    async def tell_why_waiting() -> None:
        # the service starts in SAFE and says nothing until it recovers: say what it waits for
        while not stop.is_set():
            await asyncio.sleep(args.status_every)
            status = service.status()
            if status.t_s is not None and status.state != SafetyState.RUN.value:
                line = waiting_line(tuple(status.missing), **where)
                notifier.status(line)
                _say(stamp(service.clock() - t0) + line)

    watcher = asyncio.create_task(tell_why_waiting())
    watchdog = asyncio.create_task(notifier.watchdog())  # on this loop: a stuck loop stops it
    try:
        started = asyncio.create_task(runtime.run(stop=stop, max_frames=args.max_frames))
        await asyncio.sleep(0)  # the run raised the loop's priority: say what it got
        servers = ("" if servers_nice is None
                   else f"; pages and OPC UA (their own process) at nice {servers_nice}")
        _say(f"priority: service bus {runtime.granted}; measurement and records asked for "
             f"nice {MEASURE_NICE}{servers}; CPU wake-up: {runtime.wakeup}")
        _say("ready")
        notifier.ready("serving: waiting in the safe state until every source answers")
        await started
    finally:
        watcher.cancel()
        watchdog.cancel()
        notifier.stopping("stopping")
    c = service.counters
    print(
        f"stopped: {c['frames']} pairs, {c['ok']} measured, {c['failed']} failed, "
        f"{c['safe_entries']} safe-state entries; quality log {service.log.path}",
        file=sys.stderr,
        flush=True,
    )
    return 0


_TO_STDERR = frozenset({EventKind.LOG_FAILED, EventKind.RECORDS_SAVED, EventKind.RECORDS_LOST,
                        EventKind.SERVICE_ERROR})


def _event_printer(t0: float, stamp: Callable[[float], str],
                   notifier: Notifier) -> Callable[[Any], None]:
    """The service's events as lines: the log's trouble and the service's own faults on stderr."""

    def on_event(e: Any) -> None:
        notifier.status(e.text)
        line = stamp(e.t_s - t0) + e.text
        if e.kind in _TO_STDERR:
            print(line, file=sys.stderr, flush=True)
        else:
            _say(line)

    return on_event


def _progress_printer(service: Any, source: Any, t0: float, every: int,
                      stamp: Callable[[float], str], notifier: Notifier) -> Callable[[Any], None]:
    """One line per ``every`` results: state, pitch, CV, feed, offsets, latency, counts."""
    window: list = []

    def on_result(r: Any) -> None:
        window.append(r)
        if len(window) < every:
            return
        ok = [x for x in window if x.ok]
        pitch = sum(x.measurement.pitch_mm for x in ok) / len(ok) if ok else float("nan")
        cv = sum(x.measurement.uniformity_cv for x in ok) / len(ok) if ok else float("nan")
        lat = sorted(x.latency_s for x in window)
        feed = r.feed_setpoint_mm_s
        counts = source_text(source_counts(source))
        vision = vision_text(ok[-1].measurement) if ok else ""
        line = (
            f"#{service.counters['frames']}  {r.state}  "
            f"ok {len(ok)}/{len(window)}  pitch {pitch:.3f} mm  cv {cv:.3f}  "
            f"feed {feed if feed is not None else float('nan'):.1f} mm/s  "
            f"offsets [{' '.join(f'{v:+.2f}' for v in r.offsets_um)}] µm  "
            f"latency p50 {lat[len(lat) // 2] * 1e3:.1f} ms"
            + (f"  {vision}" if vision else "") + (f"  {counts}" if counts else "")
        )
        notifier.status(line)
        _say(stamp(r.t_s - t0) + line)
        window.clear()

    return on_result
