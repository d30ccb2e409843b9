"""``planer hil``: the service closed around the simulated planer, with a summary at the end.

By default the simulator runs as a separate ``planer sim`` process: ``planer hil`` re-executes
itself inside a private network namespace (``unshare -rn``) so that CAN can go over python-can's
``udp_multicast`` on the namespace's loopback, and Modbus over 127.0.0.1. Where that is not
possible (no unprivileged namespaces, no ``msgpack``), or with ``--in-process``, the simulator
and the service run in one process on simulated time with the virtual CAN bus; the reason is
printed. Progress goes to stderr; the summary (or with ``--json`` one strict JSON object: no
NaN, a missing number is ``null`` with its reason in ``null_reasons``) to stdout.
The report's figures of the run (``controller/quality/report.py``: pitch and uniformity along the
boards, setpoints, a profile) are written next to the quality log and their paths printed
(``figures`` in the JSON object). Exit code 0 when every check of the summary's ``done`` table
passed, 1 otherwise; a run that a limit cut before its distance (the scenario's ``max_sim_s``)
fails its ``distance_reached`` check and says so.

With ``--http`` or ``--opcua`` the simulated run is paced at real time (``--pace FACTOR``:
simulated seconds per wall second; without servers the run goes as fast as it can unless
``--pace`` is given), and when it ends the summary is printed and the servers keep serving
its final state until Ctrl-C (or SIGTERM); the exit code is then still the summary's.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import Any


def _shipped_scenarios() -> str:
    """The scenario names of ``config/hil.toml``, for the help (the file is the one list)."""
    from config.loading import default_path, load_toml
    from core.errors import ConfigError

    try:
        return ", ".join(load_toml(default_path("hil.toml")))
    except (ConfigError, OSError) as exc:  # the help still prints; running names the problem
        return f"unreadable: {exc}"


def configure(parser: argparse.ArgumentParser) -> None:
    """Add this command's arguments."""
    parser.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    parser.add_argument(
        "--scenario",
        default="default",
        help=f"scenario name in config/hil.toml ({_shipped_scenarios()}) or FILE.toml[:NAME]",
    )
    parser.add_argument(
        "--distance-m", type=float, default=None, metavar="D", help="metres of board to run"
    )
    parser.add_argument(
        "--log", default=None, metavar="PATH", help="quality log (default runs/hil-<time>.sqlite)"
    )
    parser.add_argument("--seed", type=int, default=None, help="simulator seed")
    parser.add_argument(
        "--opcua", default=None, metavar="ENDPOINT",
        help="serve OPC UA (OPC 40550 Woodworking) at ENDPOINT during the run (paced at real "
        "time) and its final state after it until Ctrl-C, e.g. opc.tcp://127.0.0.1:4840 "
        "(docs/opcua.md)",
    )
    parser.add_argument(
        "--http", default=None, metavar="HOST:PORT",
        help="serve the operator and quality web pages at HOST:PORT during the run (paced at "
        "real time) and its final state after it until Ctrl-C, e.g. 127.0.0.1:8080 (runs the "
        "simulator in this process; docs/web.md)",
    )
    parser.add_argument(
        "--pace", type=float, default=None, metavar="FACTOR",
        help="simulated seconds per wall second (1: real time; default with --http or --opcua, "
        "else as fast as it goes; cross-process: the simulator's time scale)",
    )
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument(
        "--in-process",
        action="store_true",
        help="run the simulator in this process on simulated time (virtual CAN)",
    )
    mode.add_argument(
        "--cross-process",
        action="store_true",
        help="require the separate simulator process (error if not possible here)",
    )
    parser.add_argument(
        "--no-realtime",
        action="store_true",
        help="in-process: leave the paced run's loop at normal priority (by default it is "
        "raised as planer serve raises its bus thread: SCHED_FIFO where permitted; "
        "docs/deploy.md, Priority)",
    )
    parser.add_argument(
        "--plc",
        choices=("tcp", "direct"),
        default="tcp",
        help="in-process: reach the PLC over the real Modbus server on 127.0.0.1 (tcp, default) "
        "or directly (direct)",
    )


def _human(summary: dict) -> str:
    from planer.hil.run_end import run_end_text

    if summary.get("machine") == "moulder":
        from planer.hil.moulder import human_text

        return human_text(summary)

    init, fin, conv = summary["initial"], summary["final"], summary["converged"]
    lines = [
        f"planer hil: scenario {summary.get('scenario')} ({summary.get('mode')}), "
        f"{summary['counts']['measurements']} measurements "
        f"({summary['counts']['failed']} failed)",
        f"  target pitch      {summary['target_pitch_mm']:.3f} mm",
    ]

    def f(v: object, fmt: str) -> str:
        return "-" if v is None else format(v, fmt)

    lines.append(
        f"  true uniformity   {f(init.get('uniformity_cv'), '.3f')} -> "
        f"{f(fin.get('uniformity_cv'), '.3f')} (CV of the mark widths)"
    )
    p0, p1 = f(init.get("pitch_mm"), ".3f"), f(fin.get("pitch_mm"), ".3f")
    lines.append(f"  true pitch        {p0} -> {p1} mm")
    lines.append(
        f"  settled after     uniformity {f(conv.get('uniformity_settled_after_mm'), '.0f')} mm, "
        f"pitch {f(conv.get('pitch_settled_after_mm'), '.0f')} mm of board after "
        f"{conv.get('reference', 'loop closed')}"
    )
    lim = summary["limits"]
    rng = lim.get("feed_setpoint_range_mm_s")
    feed = "-" if not rng else f"{rng[0]:.1f}..{rng[1]:.1f}"
    lines.append(
        f"  setpoints         feed {feed} mm/s within "
        f"[{f(lim['feed_min_mm_s'], 'g')}, {f(lim['feed_max_mm_s'], 'g')}], offsets |max| "
        f"{lim['max_abs_offset_um']:.2f} µm within {lim['stroke_um']:g}"
    )
    end = summary.get("run_end")
    if end and not summary["done"].get("distance_reached", True):
        lines.append(f"  run cut short     {run_end_text(end)}")
    for why in lim.get("reasons") or ():
        lines.append(f"                    NOT OK: {why}")
    lat = summary.get("latency_ms")
    if lat:
        lines.append(
            f"  latency           median {lat['median']:.2f} ms, p99 {lat['p99']:.2f} ms "
            "(frame to setpoints)"
        )
    for fault in summary.get("faults", []):
        if "safe_after_s" in fault:
            after = ""
            if "recovered_after_end_s" in fault:
                after = (f", recovered {f(fault['recovered_after_end_s'], '.2f')} s after it "
                         f"ended, {fault['resumed_measurements']} measurements applied after")
            lines.append(
                f"  fault {fault['kind']} at {fault['at_s']:g} s: safe after "
                f"{f(fault['safe_after_s'], '.2f')} s ({fault.get('safe_reason') or '-'}; "
                f"should trip {fault['trips']}){after} -> "
                f"{'ok' if fault['handled'] else 'NOT HANDLED'}"
            )
    safe = summary.get("safe_entries")
    if safe:
        lines.append(f"  safe-state entries {safe['count']} ({safe['unexplained']} not explained "
                     "by an injected fault)")
        for e in safe["entries"][:20]:
            lines.append(f"                    t={e['t_s']:.2f} s  {e['reason']}  "
                         f"<- {e['fault'] or 'NO FAULT'}")
        if len(safe["entries"]) > 20:
            lines.append(f"                    ... {len(safe['entries']) - 20} more")
    texts = summary.get("checks") or {}
    for key, ok in summary["done"].items():
        lines.append(f"  [{'x' if ok else ' '}] {texts.get(key, {}).get('text') or key}")
    lines.append(f"  quality log       {summary['quality_log']['path']} "
                 f"({summary['quality_log']['records']} records)")
    for path in (summary.get("figures") or {}).values():
        lines.append(f"  figure            {path}")
    lines.append("PASSED" if summary["passed"] else "NOT PASSED")
    return "\n".join(lines)


def _terminate_as_interrupt(signum: int, frame: object) -> None:
    """SIGTERM handler: stop like Ctrl-C (simulator stopped, temporary files removed)."""
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    import json
    import logging
    import math
    import os
    import signal
    import sys
    import time
    from dataclasses import replace

    from controller.quality.log import is_database_url, log_target
    from core.errors import FieldbusError
    from planer import hil
    from planer.cli import output_file
    from protocol import can_transport

    scenario = hil.load_scenario(args.scenario)
    if args.distance_m is not None:
        if not (math.isfinite(args.distance_m) and args.distance_m > 0):
            raise ValueError(f"--distance-m must be a number > 0, got {args.distance_m}")
        scenario = replace(scenario, distance_m=float(args.distance_m))
    if args.seed is not None:
        if args.seed < 0:
            raise ValueError(f"--seed must be >= 0, got {args.seed}")
        scenario = replace(scenario, seed=int(args.seed))
    serving_asked = bool(getattr(args, "http", None) or getattr(args, "opcua", None))
    pace = getattr(args, "pace", None)
    if pace is not None and not (math.isfinite(pace) and pace > 0):
        raise ValueError(f"--pace must be a number > 0, got {pace}")
    if pace is None and serving_asked:
        pace = 1.0  # real time: the pages and OPC UA clients follow the run as it happens
    if pace is not None:
        scenario = replace(scenario, time_scale=float(pace))  # the cross-process simulator's
    log_path = Path(args.log) if args.log else Path("runs") / time.strftime(
        "hil-%Y%m%d-%H%M%S.sqlite"
    )
    if args.log is None and "PLANER_HIL_LOG" in os.environ:
        log_path = Path(os.environ["PLANER_HIL_LOG"])
    log_path = Path(log_target(log_path, check_file=lambda p: output_file("--log", p)))
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    signal.signal(signal.SIGTERM, _terminate_as_interrupt)  # clean up as on Ctrl-C
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)

    def progress(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    if getattr(args, "http", None) and not (args.in_process or args.cross_process
                                            or can_transport.in_private_netns()):
        # the cross-process run lives in a private network namespace no browser outside reaches
        progress("planer hil: --http: running the simulator in this process so that a browser "
                 "on this machine can reach the pages")
        args.in_process = True
    if getattr(args, "opcua", None) and not (args.in_process or args.cross_process
                                             or can_transport.in_private_netns()):
        # the cross-process run lives in a private network namespace no client outside reaches
        progress("planer hil: --opcua: running the simulator in this process so that OPC UA "
                 "clients on this machine can reach the server")
        args.in_process = True
    cross = False
    moulder = len(hil.machine_config_for(scenario).heads) > 1
    if moulder and not args.in_process:
        if args.cross_process:
            raise ValueError(f"--cross-process: scenario {scenario.name} is a moulder "
                             f"({len(hil.machine_config_for(scenario).heads)} heads), which "
                             "runs in-process only")
        progress(f"planer hil: scenario {scenario.name} is a moulder: the simulator runs in "
                 "this process (simulated time, virtual CAN)")
        args.in_process = True
    if not args.in_process:
        ok, why = hil.cross_process_possible()
        if ok:
            if not can_transport.in_private_netns():
                # the same command again, inside a private network namespace (never returns);
                # the log path is fixed now so both sides agree on it
                os.environ["PLANER_HIL_LOG"] = str(log_path)
                progress("planer hil: entering a private network namespace "
                         f"({' '.join(can_transport.netns_argv(['-'])[:2])})")
                can_transport.reexec_in_private_netns(
                    [sys.executable, "-m", "planer.cli", *sys.argv[1:]]
                )
            cross = True
        elif args.cross_process:
            raise FieldbusError(f"cannot run the simulator as a separate process: {why}")
        else:
            progress(
                f"planer hil: {why}; falling back to the in-process simulator "
                "(simulated time, virtual CAN)"
            )
    told: list[dict] = []

    def tell(summary: dict) -> None:
        """Write the figures and print the summary (before the servers hold the end)."""
        summary["figures"] = _write_figures(summary, progress)
        if args.json:
            # strict JSON: NaN/inf become null (listed in null_reasons); a regression fails
            print(json.dumps(hil.json_ready(summary), allow_nan=False), flush=True)
        else:
            print(_human(summary), flush=True)
        told.append(summary)

    try:
        summary = _run_scenario(hil, scenario, args, cross=cross, log_path=log_path,
                                progress=progress, pace=pace, tell=tell)
    except KeyboardInterrupt:
        if told:  # the run was over and told; Ctrl-C ended the serving of its final state
            progress("planer hil: stopped serving")
            return 0 if told[-1]["passed"] else 1
        if is_database_url(log_path) or log_path.exists():
            progress(f"planer hil: stopped early; the quality log so far is "
                     f"{log_target(log_path)}")  # a URL with its '//'
        raise
    if not told:
        tell(summary)
    return 0 if summary["passed"] else 1


def _write_figures(summary: dict, progress: Callable[[str], None]) -> dict[str, str]:
    """The report's figures of this run's records, next to the quality log: paths by name.

    A figure that cannot be written is reported on stderr; the summary still goes out.
    """
    import time

    from controller.quality.log import QualityLog, is_database_url
    from controller.quality.report import build_figures, save_figures

    qlog = summary["quality_log"]
    path = Path(qlog["path"])
    # next to an SQLite log; for a database, in runs/ named after the run
    out_dir, stem = (Path("runs"), time.strftime("hil-%Y%m%d-%H%M%S")) \
        if is_database_url(path) else (path.parent, path.stem)
    try:
        with QualityLog(path, create=False) as log:
            records = log.records(after_id=int(qlog.get("after_id", 0)))
            quality_class = log.quality_class()
        out_dir.mkdir(parents=True, exist_ok=True)
        if summary.get("machine") == "moulder":  # each head's figures, <stem>_<head>_<name>
            from controller.quality.head_report import build_head_figures, save_head_figures

            with QualityLog(path, create=False) as log:
                classes = {h["name"]: log.quality_class(head=h["name"])
                           for h in summary["heads"]}
            saved = save_head_figures(build_head_figures(records, classes), out_dir, stem=stem)
            return {f"{head}_{name}": where for head, mine in saved.items()
                    for name, where in mine.items()}
        figures = build_figures(records, quality_class=quality_class,
                                safe_periods_s=summary.get("safe_periods_s"))
        return save_figures(figures, out_dir, stem=stem)
    except (OSError, ValueError) as exc:
        progress(f"planer hil: figures not written: {exc}")
        return {}


async def _final_state_served(servers: Any, *, timeout_s: float = 10.0) -> None:
    """Wait (at most ``timeout_s``) until the servers' process has the ended run's last state.

    The service is looked at every period (:func:`controller.edge.feed.follow`); two looks taken
    by the sender after the run ended mean the first, which holds the last state, was sent; then
    the servers' process must report having received as many messages as were sent.
    """
    import asyncio
    import time

    deadline = time.monotonic() + timeout_s
    box = servers.mailbox
    for _ in range(2):
        n = box.put_count
        while box.put_count == n or len(box):
            if time.monotonic() > deadline:
                return
            await asyncio.sleep(0.02)
    sent = servers.sent
    left = max(0.0, deadline - time.monotonic())
    await asyncio.to_thread(servers.wait_stats, lambda s: s.get("received", 0) >= sent, left)


def _run_scenario(hil: Any, scenario: Any, args: argparse.Namespace, *, cross: bool,
                  log_path: Path, progress: Callable[[str], None], pace: float | None = None,
                  tell: Callable[[dict], None] | None = None) -> dict:
    """Run the scenario in the chosen mode; return the summary.

    With servers asked for (``--http``, ``--opcua``) the summary is told (``tell``) when the
    run ends and the servers go on serving its final state until Ctrl-C (``KeyboardInterrupt``).
    """
    import asyncio

    from controller.edge.compose import serving
    from controller.opcua.compose import server_for
    from planer.hil.interrupt import raise_if_cancel_lost

    cfg = hil.machine_config_for(scenario, log_path=log_path)
    server_for(cfg, getattr(args, "opcua", None))  # bad endpoint / security: one line, early
    from controller.web.compose import listen_for

    listen_for(cfg, getattr(args, "http", None))  # bad address / no web packages: one line
    opened: list = []

    async def with_opcua(run: Callable[[], Any], get_service: Callable[[], Any]) -> dict:
        # the run's coroutine is made only once the servers listen: a busy port leaves no
        # coroutine never awaited
        async with serving(cfg, get_service, opcua=getattr(args, "opcua", None),
                           http=getattr(args, "http", None), say=progress) as servers:
            summary = await run()
            raise_if_cancel_lost()  # a Ctrl-C during the run ends it here, never in serving
            if servers is None or tell is None:
                return summary
            tell(summary)
            await _final_state_served(servers)
            where = " and ".join(x for x in (servers.url, servers.endpoint) if x)
            progress(f"planer hil: the run is over; serving its final state at {where} "
                     "until Ctrl-C")
            await asyncio.Event().wait()  # until Ctrl-C or SIGTERM (KeyboardInterrupt)
            return summary

    if cross:
        # the simulator's config and frame spool (tens of MB) live in a temporary folder that
        # run_cross_process removes when the run ends
        summary = asyncio.run(with_opcua(
            lambda: hil.run_cross_process(scenario, log_path=log_path, progress=progress,
                                          on_service=opened.append),
            lambda: opened[-1] if opened else None))
    elif len(cfg.heads) > 1:  # a moulder: every head's service and the one feed
        from planer.hil.moulder import MoulderHil

        moulder = MoulderHil(scenario, log_path=log_path, progress=progress)
        summary = asyncio.run(with_opcua(moulder.run,
                                         lambda: getattr(moulder, "service", None)))
    else:
        runner = hil.InProcessHil(
            scenario, log_path=log_path, plc_transport=args.plc, progress=progress, pace=pace,
            realtime=not getattr(args, "no_realtime", False),  # as planer serve's bus thread
        )
        summary = asyncio.run(with_opcua(runner.run,
                                         lambda: getattr(runner, "service", None)))
    return summary
