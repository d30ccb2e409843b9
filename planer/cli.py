"""The ``planer`` command: one sub-command per module in :mod:`planer.commands`.

Each command module defines ``HELP`` (one line), ``configure(parser)`` and ``run(args) -> int``;
modules keep heavy imports inside ``run`` so that ``planer --help`` stays fast. Errors raised on
purpose (``PlanerError``, ``ValueError``, ``OSError``) become one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

COMMANDS = ("measure", "calibrate", "bench", "sim", "serve", "hil", "report")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every sub-command registered."""
    parser = argparse.ArgumentParser(
        prog="planer",
        description="Cuttermark measurement and closed-loop control of a planing machine.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        mod = importlib.import_module(f"planer.commands.{name}")
        p = sub.add_parser(name, help=mod.HELP, description=mod.HELP)
        mod.configure(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``planer`` command; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print("planer: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError) as exc:  # PlanerError subclasses are among these
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        print(f"planer {args.command}: error: {msg}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
