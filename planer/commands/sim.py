"""``planer sim``: the simulated planer alone, as a stand-in machine.

Runs the machine model behind its PLC Modbus TCP server, its piezo amplifier CAN node and its
frame spool until stopped (Ctrl-C, SIGTERM) or for ``--duration`` seconds of machine time.
The first lines say where it listens, one each, then ``ready``, then progress::

    modbus: 127.0.0.1:5020 unit 1
    can: virtual:planer-piezo
    frames: spool runs/spool keep 50
    ready
    t=1.00 s  rtf=1.00  feed=800.0 mm/s  spindle=6000 rpm  frames=10  modbus=...  can ...

A ``--config`` with ``[[heads]]`` (``config/sim_moulder.toml``) runs the moulder
(:class:`plant_sim.run.moulder_runner.MoulderRunner`): the same Modbus server with every head's
register block, every head's amplifier node (its node id) on the one CAN bus, head ``<name>``'s
pairs in ``<spool>/<name>``; the banner adds ``heads: ...`` and a ``head <name>: ...`` line each,
the progress lines give each head's spindle speed and pairs.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


def configure(parser: argparse.ArgumentParser) -> None:
    """Add this command's arguments."""
    parser.add_argument(
        "--config", default=None, help="simulator config (default: the shipped config/sim.toml)"
    )
    parser.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="S",
        help="stop after S seconds of machine time (default: run until stopped)",
    )
    parser.add_argument(
        "--time-scale",
        type=float,
        default=None,
        metavar="X",
        help="simulated seconds per wall second (default [run] time_scale; 0: as fast as possible)",
    )
    parser.add_argument("--seed", type=int, default=0, help="machine model seed (default 0)")
    parser.add_argument(
        "--port",
        type=int,
        default=None,
        help="Modbus TCP port (default [modbus] port; 0: a free one)",
        metavar="P",
    )
    parser.add_argument("--spool", default=None, metavar="DIR", help="frame spool directory")
    parser.add_argument(
        "--no-images", action="store_true", help="do not render images (machine model only)"
    )
    parser.add_argument(
        "--no-realtime",
        action="store_true",
        help="do not ask for real-time priority for the Modbus server and the CAN node "
        "(nor lower the render workers' priority)",
    )
    parser.add_argument(
        "--progress",
        type=float,
        default=1.0,
        metavar="S",
        help="machine seconds between progress lines (default 1)",
    )


def _check_port_free(host: str, port: int, *, option: str) -> None:
    """Raise ``ValueError`` naming ``option`` when ``host:port`` is taken (before any set-up)."""
    import errno
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise ValueError(
                    f"{option} {port}: {host}:{port} is already in use (another planer sim?); "
                    "choose another port, or --port 0 for a free one"
                ) from None
            raise ValueError(
                f"{option} {port}: cannot listen on {host}:{port}: {exc.strerror or exc}"
            ) from None


INTERFACE_SWITCH_INTERVAL_S = 0.0005
"""The interpreter's thread switch interval in ``planer sim`` (default 5 ms), s."""


class _QuietPipe:
    """Prints a line to stdout; when the reader has gone (``planer sim | head``), stops quietly.

    The first ``BrokenPipeError`` points stdout at ``/dev/null`` (so nothing fails at exit) and
    calls ``on_closed`` (the runner's ``request_stop``): the run ends with exit code 0.
    """

    def __init__(self) -> None:
        self.on_closed: Callable[[], None] | None = None
        self.closed = False

    def __call__(self, line: str) -> None:
        import os
        import sys

        if self.closed:
            return
        try:
            print(line, flush=True)
        except BrokenPipeError:
            self.closed = True
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
            if self.on_closed is not None:
                self.on_closed()


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    import asyncio
    import logging
    import signal
    import sys

    from config.sim import load_sim
    from core.checks import check_int
    from planer.cli import output_folder
    from plant_sim.interfaces.thread import RENDER_NICE
    from plant_sim.run.moulder_runner import runner_for

    if args.duration is not None and not (math.isfinite(args.duration) and args.duration >= 0):
        raise ValueError(f"--duration must be a finite number >= 0, got {args.duration}")
    scale = args.time_scale
    if scale is not None:
        if not scale >= 0:
            raise ValueError(f"--time-scale must be >= 0, got {scale}")
        scale = math.inf if scale == 0 else scale
    if args.port is not None:
        check_int("--port", args.port, lo=0, hi=65535)
    if not args.progress > 0:
        raise ValueError(f"--progress must be > 0, got {args.progress}")
    cfg = load_sim(args.config)
    if args.spool is not None:
        output_folder("--spool", args.spool)
    else:
        output_folder(f"{args.config or 'config/sim.toml'}: frames.spool_dir", cfg.frames.spool_dir)
    port = cfg.modbus.port if args.port is None else args.port
    if port:
        _check_port_free(cfg.modbus.host, port, option="--port" if args.port else "modbus.port")
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)

    # the interface thread gets the GIL within 0.5 ms of a request (Modbus answers in ms)
    sys.setswitchinterval(INTERFACE_SWITCH_INTERVAL_S)

    async def main() -> int:
        out = _QuietPipe()
        runner = runner_for(
            cfg,
            seed=args.seed,
            render_images=not args.no_images,
            time_scale=scale,
            modbus_port=args.port,
            spool_dir=args.spool,
            realtime_interfaces=not args.no_realtime,
            render_nice=None if args.no_realtime else RENDER_NICE,
            out=out,
            progress_every_s=args.progress,
        )
        out.on_closed = runner.request_stop
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, runner.request_stop)
        summary = await runner.run(duration_s=args.duration)
        per_head = ""
        if summary.frames_by_head is not None:
            per_head = " (" + ", ".join(
                f"{name} {n}" for name, n in summary.frames_by_head.items()) + ")"
        out(
            f"stopped at t={summary.sim_time_s:.3f} s: {summary.steps} steps, "
            f"{summary.frames} frames{per_head}, real-time factor "
            f"{summary.real_time_factor:.2f}"
        )
        return 0

    return asyncio.run(main())
