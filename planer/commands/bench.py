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
PARTS = ("vision", "sim", "service", "camera")


def configure(parser: argparse.ArgumentParser) -> None:
    """Add this command's arguments."""
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    parser.add_argument(
        "--only", choices=PARTS, action="append", help="run only this part (repeatable)"
    )
    parser.add_argument("--quick", action="store_true", help="shorter runs (less precise)")


def _rtf_line(label: str, part: Any, target: Any) -> str:
    return (
        f"  {label}: real-time factor {part['real_time_factor']:.1f} (target >= {target:g}), "
        f"{part['sim_s']:g} s simulated in {part['wall_s']:.2f} s, {part['pairs']} pairs, "
        f"set-up {part['setup_s']:.2f} s"
    )


def _format(name: str, result: Any) -> str:
    """The readable text of one part; unknown shapes fall back to indented JSON."""
    try:
        if name == "vision":
            rows = [
                f"  {r['width']}x{r['height']}: {r['pairs_per_s']:.0f} pairs/s "
                f"(plain copy of the pair: {r['copy_pairs_per_s']:.0f}/s)"
                for r in result
            ]
            return "vision (one core):\n" + "\n".join(rows)
        if name == "sim":
            t = result["targets"]
            verdict = "meets the targets" if result["meets_targets"] else "MISSES a target"
            return "\n".join([
                f"sim (camera at {result['pairs_per_s']:g} pairs/s): {verdict}",
                _rtf_line("model alone ", result["model_only"], t["model_only"]),
                _rtf_line("with images ", result["with_images"], t["with_images"]),
            ])
        if name == "service":
            head = (
                f"service ({result['width']}x{result['height']}, {result['rate_hz']:g} pairs/s, "
                f"{result['transport']}): {result['applied']} of {result['pairs']} pairs applied, "
                f"{result['failed']} failed"
            )
            if "p99_ms" not in result:
                return head + "; no latency (no pair was applied)"
            ok = "meets" if result["p99_ms"] <= result["target_p99_ms"] else "MISSES"
            return head + (
                f"\n  latency frame -> setpoints: median {result['median_ms']:.1f} ms, "
                f"p99 {result['p99_ms']:.1f} ms, max {result['max_ms']:.1f} ms "
                f"({ok} the target p99 <= {result['target_p99_ms']:g} ms)"
            )
        if name == "camera":
            return _camera_text(result)
    except (KeyError, TypeError, ValueError):
        pass
    return f"{name}: {json.dumps(result, indent=2)}"


def _camera_text(result: Any) -> str:
    """The camera part (``planer/benchmarks/camera.py``)."""
    if not result["available"]:
        return f"camera: not measured ({result['reason']})"
    t, f = result["at_target"], result["fastest"]
    ok = "meets" if result["meets_target"] else "MISSES"
    return (f"camera (fake Fake_1, {result['width']}x{result['height']} Mono8): "
            f"{t['pairs_per_s']:.0f} pairs/s at {t['asked_pairs_per_s']:g} asked (camera made "
            f"{t['camera_pairs_per_s']:.0f}), {t['drops']} drops; fastest "
            f"{f['pairs_per_s']:.0f} pairs/s, {f['drops']} drops ({ok} the target "
            f"{result['target_pairs_per_s']:g} pairs/s with no drop)")


def run(args: argparse.Namespace) -> int:
    """Run the benchmarks."""
    out: dict[str, Any] = {}
    for name in args.only or PARTS:
        what = "short run" if args.quick else "full run, several seconds; --quick is faster"
        print(f"planer bench: measuring {name} ({what}) ...", file=sys.stderr, flush=True)
        mod = importlib.import_module(f"planer.benchmarks.{name}")
        out[name] = mod.run(quick=args.quick)
        if not args.json:
            print(_format(name, out[name]), flush=True)
    if args.json:
        print(json.dumps(out))
    return 0
