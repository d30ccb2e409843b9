"""``planer calibrate-rig``: camera roll and light slants from a reference run, into rig.toml.

Usage::

    planer calibrate-rig A1.png B1.png [A2.png B2.png ...] --counts CA1,CB1 [--counts CA2,CB2 ...]
                         --radius-mm R [--feed-mm-s V --rpm N --knives Z]
                         --rig rig.toml --out rig.toml
    planer calibrate-rig --spool DIR --radius-mm R [...] --rig rig.toml --out rig.toml

A reference run: a few pairs (5-20) of one planed board of known cutting radius R (a hardwood with
little subsurface scattering), at a steady feed.  The command measures every pair with the rig
file as it stands, estimates the camera roll and each light's slant
(:mod:`vision.calibration.rigcal`),
writes them (``[camera] roll_deg``, ``width``, ``height``; ``[lights] slant_deg``,
``slant_a_deg``, ``slant_b_deg``) into ``--out`` atomically, and prints one JSON object with the
estimate.  With ``--feed-mm-s``, ``--rpm`` and ``--knives`` it also reports the measured pitch
against the kinematic one (feed per knife pass), a check of ``px_per_mm``.  Step by step:
``docs/calibration.md``.
"""

from __future__ import annotations

import argparse
import json
import sys

from planer.commands.measure import knife_count, positive_number


def _counts(text: str) -> tuple[int, int]:
    try:
        a, b = text.split(",")
        return int(a, 0), int(b, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected CA,CB (two integer counts): {text!r}") from None


def configure(parser: argparse.ArgumentParser) -> None:
    """Add this command's arguments."""
    parser.add_argument("images", nargs="*", metavar="IMAGE",
                        help="image files A1 B1 A2 B2 ... (pairs, A lit first)")
    parser.add_argument("--counts", type=_counts, action="append", default=[],
                        metavar="CA,CB", help="encoder counts of one pair (once per pair)")
    parser.add_argument("--spool", metavar="DIR", default=None,
                        help="read the pairs (and their counts and speed) from a spool folder")
    parser.add_argument("--radius-mm", type=positive_number, required=True,
                        help="cutting radius of the knives, mm")
    parser.add_argument("--feed-mm-s", type=positive_number, default=None,
                        help="feed speed of the reference run, mm/s")
    parser.add_argument("--rpm", type=positive_number, default=None, help="spindle speed, rev/min")
    parser.add_argument("--knives", type=knife_count, default=None, help="number of knives")
    parser.add_argument("--rig", required=True, help="rig file to start from")
    parser.add_argument("--out", required=True, help="rig file to write (may be --rig)")


def _pairs_from_files(args: argparse.Namespace) -> list[tuple]:
    from core.imageio import read_gray

    if len(args.images) % 2:
        raise ValueError(f"images must come in pairs A B, got {len(args.images)} files")
    n = len(args.images) // 2
    if len(args.counts) != n:
        raise ValueError(f"--counts must be given once per pair: {n} pairs, "
                         f"{len(args.counts)} --counts")
    pairs = []
    for k in range(n):
        a = read_gray(args.images[2 * k])
        b = read_gray(args.images[2 * k + 1])
        if a.shape != b.shape:
            raise ValueError(f"pair {k + 1}: images differ in size")
        pairs.append((a, b, *args.counts[k]))
    return pairs


def _pairs_from_spool(directory: str) -> tuple[list[tuple], float | None]:
    """The good pairs of a spool folder and their median speed; a folder with none is an error.

    Raises
    ------
    ValueError
        Naming ``--spool`` and the folder: missing, not a folder, or without a good pair (with
        the count of failed pairs and files skipped).
    """
    import os

    from protocol.spool import SpoolReader

    if not os.path.exists(directory):
        raise ValueError(f"--spool {directory}: no such folder")
    if not os.path.isdir(directory):
        raise ValueError(f"--spool {directory}: is a file, expected a spool folder")
    reader = SpoolReader(directory, start="all")
    pairs = []
    speeds = []
    failed = 0
    while (frame := reader.poll()) is not None:
        if frame.error is not None or frame.image_a is None:
            failed += 1
            continue
        pairs.append((frame.image_a, frame.image_b, frame.counts_a, frame.counts_b))
        speeds.append(float(frame.speed_mm_s))
    if not pairs:
        skipped = len(reader.take_skips())
        raise ValueError(f"--spool {directory}: no good image pairs in the folder ({failed} "
                         f"failed pairs, {skipped} files skipped; docs/frames.md has the format)")
    speed = sorted(speeds)[len(speeds) // 2] if speeds else None
    return pairs, speed


def run(args: argparse.Namespace) -> int:
    """Run the command: measure the reference run, estimate, write the rig file."""
    from config.rig import load_rig, rig_to_toml
    from core.fileio import atomic_write_text
    from vision.calibration.rigcal import estimate_rig

    rig = load_rig(args.rig)
    speed = args.feed_mm_s
    if args.spool is not None:
        if args.images or args.counts:
            raise ValueError("give either image files with --counts or --spool, not both")
        pairs, spool_speed = _pairs_from_spool(args.spool)
        speed = speed if speed is not None else spool_speed
    else:
        pairs = _pairs_from_files(args)
    if not pairs:
        raise ValueError("no image pairs given (image files with --counts, or --spool DIR)")
    shapes = {p[0].shape for p in pairs}
    if len(shapes) != 1:
        raise ValueError(f"the pairs differ in size: {sorted(shapes)}")
    estimate = estimate_rig(pairs, rig, radius_mm=args.radius_mm, speed_mm_s=speed)
    h, w = pairs[0][0].shape
    new_rig = estimate.apply(rig, width=w, height=h)
    atomic_write_text(args.out, rig_to_toml(new_rig))
    report = {
        "pairs": len(pairs),
        "pairs_used": estimate.pairs_used,
        "roll_deg": round(estimate.roll_deg, 4),
        "roll_spread_deg": round(estimate.roll_spread_deg, 4)
        if estimate.roll_spread_deg == estimate.roll_spread_deg else None,
        "slant_a_deg": round(estimate.slant_a_deg, 3),
        "slant_b_deg": round(estimate.slant_b_deg, 3),
        "slant_deg": round(estimate.slant_sum_deg, 3),
        "residual": round(estimate.residual, 4),
        "out": str(args.out),
    }
    if speed is not None and args.rpm is not None and args.knives is not None:
        from vision.pipeline import Measurer

        feed = speed * 60.0 / (args.rpm * args.knives)
        measurer = Measurer(new_rig, (h, w))
        pitches = []
        for a, b, ca, cb in pairs:
            try:
                pitches.append(measurer.measure(a, b, counts_a=ca, counts_b=cb,
                                                speed_mm_s=speed).pitch_mm)
            except ValueError:
                continue
        if pitches:
            measured = sorted(pitches)[len(pitches) // 2]
            report["feed_per_pass_mm"] = round(feed, 5)
            report["measured_pitch_mm"] = round(measured, 5)
            report["px_per_mm_factor"] = round(measured / feed, 5)
    json.dump(report, sys.stdout, separators=(",", ":"))
    sys.stdout.write("\n")
    return 0
