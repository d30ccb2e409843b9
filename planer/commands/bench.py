"""``planer bench``: throughput of the vision, real-time factor of the simulator, service latency.

Each part is measured by its own module in :mod:`planer.benchmarks` (``vision``, ``sim``,
``service``), each exposing ``run(quick: bool)``. ``--json`` prints one JSON object whose keys are
the parts; without it, a readable table.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from typing import Any

HELP = "benchmarks: vision pairs/s, simulator real-time factor, service latency"
PARTS = ("vision", "sim", "service")


def configure(parser: argparse.ArgumentParser) -> None:
    """Add this command's arguments."""
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    parser.add_argument(
        "--only", choices=PARTS, action="append", help="run only this part (repeatable)"
    )
    parser.add_argument("--quick", action="store_true", help="shorter runs (less precise)")


def _format(name: str, result: Any) -> str:
    if name == "vision" and isinstance(result, list):
        rows = [
            f"  {r['width']}x{r['height']}: {r['pairs_per_s']:.0f} pairs/s "
            f"(plain copy of the pair: {r['copy_pairs_per_s']:.0f}/s)"
            for r in result
        ]
        return "vision (one core):\n" + "\n".join(rows)
    return f"{name}: {json.dumps(result, indent=2)}"


def run(args: argparse.Namespace) -> int:
    """Run the benchmarks."""
    out: dict[str, Any] = {}
    for name in args.only or PARTS:
        print(f"planer bench: measuring {name} ...", file=sys.stderr, flush=True)
        mod = importlib.import_module(f"planer.benchmarks.{name}")
        out[name] = mod.run(quick=args.quick)
        if not args.json:
            print(_format(name, out[name]), flush=True)
    if args.json:
        print(json.dumps(out))
    return 0
