"""``planer bench``: throughput of the vision, real-time factor of the simulator, service latency.

Each part is measured by its own module in :mod:`planer.benchmarks` (``vision``, ``sim``,
``service``, ``camera``, ``quality_log``, ``moulder``), each exposing ``run(quick: bool)``.
``--json`` prints one JSON object whose keys are the parts; without it, a readable table.
Without ``--only`` the parts of :data:`DEFAULT_PARTS` run (``moulder``, four heads through the
service, only when named).
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from typing import Any

DEFAULT_PARTS = ("vision", "sim", "service", "camera", "quality_log")
"""The parts a bare ``planer bench`` runs."""
PARTS = (*DEFAULT_PARTS, "moulder")
"""Every part ``--only`` takes."""


def configure(parser: argparse.ArgumentParser) -> None:
    """Add this command's arguments."""
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    parser.add_argument(
        "--only", choices=PARTS, action="append",
        help="run only this part (repeatable; moulder runs only when named)"
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
            return vision_text(result)
        if name == "sim":
            t = result["targets"]
            verdict = "meets the targets" if result["meets_targets"] else "MISSES a target"
            return "\n".join([
                f"sim (camera at {result['pairs_per_s']:g} pairs/s): {verdict}",
                _rtf_line("model alone ", result["model_only"], t["model_only"]),
                _rtf_line("with images ", result["with_images"], t["with_images"]),
            ])
        if name == "service":
            from planer.benchmarks.service import text as service_text

            return service_text(result)
        if name == "camera":
            return _camera_text(result)
        if name == "quality_log":
            from planer.benchmarks.quality_log import text as quality_log_text

            return quality_log_text(result)
        if name == "moulder":
            from planer.benchmarks.moulder import text as moulder_text

            return moulder_text(result)
    except (KeyError, TypeError, ValueError):
        pass
    return f"{name}: {json.dumps(result, indent=2)}"


def _times(floor: Any, rate: Any) -> str:
    """How many times faster ``floor`` runs than ``rate`` (``"?x"`` when not a positive rate)."""
    try:
        if float(rate) > 0 and float(floor) >= 0:
            times = float(floor) / float(rate)
            return f"{times:.0f}x" if times >= 10 else f"{times:.1f}x"
    except (TypeError, ValueError):
        pass
    return "?x"


def vision_row_text(row: dict[str, Any]) -> str:
    """The readable lines of one image size of the vision part.

    Parameters
    ----------
    row : dict
        One entry of ``planer.benchmarks.vision.run``: ``width``, ``height``, ``pairs_per_s``,
        ``copy_pairs_per_s`` and, when measured, ``no_roll_pairs_per_s``,
        ``selfcal_pairs_per_s``, ``remap_pairs_per_s``, ``cpu_ms``, ``selfcal_cpu_ms``,
        ``remap_cpu_ms``, ``orientation_ms``, ``selfcal_ms``, ``rolled_cpu_ms``,
        ``remap_ratio``, ``selfcal_remap_ratio``, ``rolled_remap_ratio``,
        ``target_remap_ratio``, ``meets_target``, ``defects_ms``, ``defects_overhead``,
        ``service_defects_ms``, ``service_defects_overhead``.

    Returns
    -------
    str
        The measurement rate and CPU time with its speed as a multiple of one remap's (plain
        and as the service runs it, against the budget), its floors measured in the
        same run (a copy of the pair, one remap of the pair) as "N x faster" ratios, and the
        CPU cost of the orientation and self-calibration steps and of a rolled camera, and
        what the planing defects add (plain and as the service measures); rows without the
        step keys give one line.
    """
    rate = row["pairs_per_s"]
    head = f"  {row['width']}x{row['height']}: {rate:.0f} pairs/s"
    if "cpu_ms" in row:
        head += f", {row['cpu_ms']:.2f} ms CPU per pair"
    if "remap_ratio" in row:
        head += f" = {_ratio(row['remap_ratio'])} one remap's speed"
    if "selfcal_remap_ratio" in row:
        verdict = "meets" if row.get("meets_target") else "MISSES"
        head += (f"; as the service {_ratio(row['selfcal_remap_ratio'])} ({verdict} the "
                 f"target {row.get('target_remap_ratio', 1.0):g}x)")
    floors = [f"copy {row['copy_pairs_per_s']:.0f} pairs/s ({_times(row['copy_pairs_per_s'], rate)}"
              " faster)"]
    if "remap_pairs_per_s" in row:
        remap = f"one remap {row['remap_pairs_per_s']:.0f} pairs/s"
        if "remap_cpu_ms" in row:
            remap += f", {row['remap_cpu_ms']:.2f} ms CPU"
        floors.append(f"{remap} ({_times(row['remap_pairs_per_s'], rate)} faster)")
    lines = [head, "    floors, same run: " + "; ".join(floors)]
    steps = []
    if "orientation_ms" in row:
        step = f"orientation {row['orientation_ms']:+.2f} ms"
        if "no_roll_pairs_per_s" in row:
            step += f" (without it {row['no_roll_pairs_per_s']:.0f} pairs/s)"
        steps.append(step)
    if "selfcal_ms" in row:
        step = f"self-calibration {row['selfcal_ms']:+.2f} ms"
        service = []
        if "selfcal_pairs_per_s" in row:
            service.append(f"{row['selfcal_pairs_per_s']:.0f} pairs/s")
        if "selfcal_cpu_ms" in row:
            service.append(f"{row['selfcal_cpu_ms']:.2f} ms CPU")
        if service:
            step += f" (as the service runs it: {', '.join(service)})"
        steps.append(step)
    if "rolled_cpu_ms" in row:
        rolled = f"rolled camera {row['rolled_cpu_ms']:.2f} ms"
        if "rolled_remap_ratio" in row:
            rolled += f" ({_ratio(row['rolled_remap_ratio'])} one remap's speed)"
        steps.append(rolled)
    if steps:
        lines.append("    steps, CPU per pair: " + "; ".join(steps))
    if "defects_ms" in row:
        lines.append("    " + _defects_text(row))
    return "\n".join(lines)


def _defects_text(row: dict[str, Any]) -> str:
    """The line of the 2-D map and the planing defects, against their CPU budget."""
    from planer.benchmarks.vision import DEFECTS_BUDGET

    budget = f"the {100 * DEFECTS_BUDGET:+.0f} % budget"

    def part(ms_key: str, share_key: str) -> str:
        text = f"{float(row[ms_key]):+.2f} ms"
        share = row.get(share_key)
        if share is not None:
            verdict = "within" if float(share) <= DEFECTS_BUDGET else "OVER"
            text += f" = {100 * float(share):+.0f} % ({verdict} {budget})"
        return text

    text = "defects and 2-D map, CPU per pair: " + part("defects_ms", "defects_overhead")
    if "service_defects_ms" in row:
        text += "; on the service's measurement " + part("service_defects_ms",
                                                          "service_defects_overhead")
    return text


def _ratio(value: Any) -> str:
    """A speed ratio as ``"1.23x"`` (``"?x"`` when not a number)."""
    try:
        return f"{float(value):.2f}x" if float(value) == float(value) else "?x"
    except (TypeError, ValueError):
        return "?x"


def vision_text(result: Any) -> str:
    """The readable text of the vision part: :func:`vision_row_text` per image size."""
    return "vision (one core):\n" + "\n".join(vision_row_text(r) for r in result)


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
    for name in args.only or DEFAULT_PARTS:
        what = "short run" if args.quick else "full run, several seconds; --quick is faster"
        print(f"planer bench: measuring {name} ({what}) ...", file=sys.stderr, flush=True)
        mod = importlib.import_module(f"planer.benchmarks.{name}")
        out[name] = mod.run(quick=args.quick)
        if not args.json:
            print(_format(name, out[name]), flush=True)
    if args.json:
        print(json.dumps(out))
    return 0
