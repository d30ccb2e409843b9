"""``planer measure``: profile and cuttermark metrics of one image pair, as one JSON object.

Usage::

    planer measure A.png B.png --counts-a N --counts-b M --rig rig.toml [--speed-mm-s V]
                   [--plot out.png] [--flat-a FA.png --flat-b FB.png]
                   [--radius-mm R] [--knives Z] [--rpm N]

Prints one JSON object on stdout with the contract keys ``x_mm``, ``height_um``, ``pitch_mm``,
``mark_widths_mm``, ``uniformity_cv``, ``depth_um``, ``shift_px`` and extras (``mark_depths_um``,
``cusps_mm``, ``bottoms_mm``, ``marks``, ``encoder_shift_px``, ``confidence``, ``blur_px``,
``roll_deg``, ``roll_confidence``, ``kinematic_depth_um``, ``uncalibrated_depth_um``,
``calibration`` (``state``: off / applied / untrusted, gain, scattering, confidences),
``knife_widths_mm``, ``feed_per_pass_mm``).  Without ``--radius-mm`` the self-calibration is off
(``calibration.state == "off"``).
Bad input raises ``ValueError``/``OSError`` subclasses with one line, which :mod:`planer.cli`
prints as ``planer measure: error: ...`` with exit code 2.
"""

from __future__ import annotations

import argparse
import json
import math
import sys


def _finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite: {text!r}")
    return value


def _count(text: str) -> int:
    try:
        return int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer count: {text!r}") from None


MAX_SPEED_MM_S = 3000.0  # fastest plausible feed (planers run up to ~2 m/s)


def check_speed_mm_s(speed_mm_s: float | None) -> float | None:
    """Refuse an implausible feed speed (negative, or faster than ``MAX_SPEED_MM_S``)."""
    if speed_mm_s is None:
        return None
    if not 0.0 <= speed_mm_s <= MAX_SPEED_MM_S:
        raise ValueError(
            f"--speed-mm-s must be between 0 and {MAX_SPEED_MM_S:g} mm/s, got {speed_mm_s:g}"
        )
    return speed_mm_s


def positive_number(text: str) -> float:
    """Argument type: a finite number > 0 (``--radius-mm``, ``--rpm``, ...)."""
    value = _finite_float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0: {text!r}")
    return value


def knife_count(text: str) -> int:
    """Argument type: a number of knives, 1..64."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if not 1 <= value <= 64:
        raise argparse.ArgumentTypeError(f"must be 1-64: {text!r}")
    return value


def configure(parser: argparse.ArgumentParser) -> None:
    """Add this command's arguments."""
    parser.add_argument("image_a", metavar="A", help="image lit by light A (taken first)")
    parser.add_argument("image_b", metavar="B", help="image lit by light B (taken second)")
    parser.add_argument("--counts-a", type=_count, required=True,
                        help="encoder count latched at trigger A")
    parser.add_argument("--counts-b", type=_count, required=True,
                        help="encoder count latched at trigger B")
    parser.add_argument("--rig", required=True, help="rig file (TOML: [camera] [lights] [encoder])")
    parser.add_argument("--speed-mm-s", type=_finite_float, default=None,
                        help="feed speed at capture, mm/s (for motion deblurring)")
    parser.add_argument("--plot", metavar="OUT.png", default=None,
                        help="also draw the profile with its marks into this image file")
    parser.add_argument("--flat-a", metavar="FA", default=None,
                        help="flat-board reference image for light A (with --flat-b)")
    parser.add_argument("--flat-b", metavar="FB", default=None,
                        help="flat-board reference image for light B (with --flat-a)")
    parser.add_argument("--radius-mm", type=positive_number, default=None,
                        help="cutting radius of the knives, mm (turns the self-calibration on)")
    parser.add_argument("--knives", type=knife_count, default=None,
                        help="number of knives (per-knife mark widths)")
    parser.add_argument("--rpm", type=positive_number, default=None,
                        help="spindle speed, rev/min (with --knives and --speed-mm-s: the feed "
                             "per knife pass)")


def run(args: argparse.Namespace) -> int:
    """Run the command: read, measure, print JSON (and plot)."""
    from config.rig import load_rig
    from core.imageio import read_gray
    from vision.pipeline import Measurer

    speed = check_speed_mm_s(args.speed_mm_s)
    if (args.flat_a is None) != (args.flat_b is None):
        raise ValueError("--flat-a and --flat-b must be given together")
    if args.plot:  # before the work: a figure file, writable, none of the inputs
        from planer.cli import output_file
        from planer.outputs import figure_file, not_an_input

        figure_file("--plot", args.plot)
        not_an_input("--plot", args.plot, {"IMAGE_A": args.image_a, "IMAGE_B": args.image_b,
                                           "--rig": args.rig, "--flat-a": args.flat_a,
                                           "--flat-b": args.flat_b})
        output_file("--plot", args.plot)
    rig = load_rig(args.rig)
    image_a = read_gray(args.image_a)
    image_b = read_gray(args.image_b)
    if image_a.shape != image_b.shape:
        raise ValueError(
            f"images differ in size: {args.image_a} is {image_a.shape[1]}x{image_a.shape[0]}, "
            f"{args.image_b} is {image_b.shape[1]}x{image_b.shape[0]}"
        )
    flat = None
    if args.flat_a is not None:
        flat = (read_gray(args.flat_a), read_gray(args.flat_b))
        for path, img in zip((args.flat_a, args.flat_b), flat, strict=True):
            if img.shape != image_a.shape:
                raise ValueError(
                    f"flat-field image {path} is {img.shape[1]}x{img.shape[0]}, the pair is "
                    f"{image_a.shape[1]}x{image_a.shape[0]}"
                )
    measurer = Measurer(rig, image_a.shape, flat_field=flat,  # type: ignore[arg-type]
                        radius_mm=args.radius_mm, knives=args.knives, defects=True)
    result = measurer.measure(
        image_a, image_b, counts_a=args.counts_a, counts_b=args.counts_b, speed_mm_s=speed,
    )
    if args.plot:
        from planer.outputs import writing
        from vision.plot import profile_figure

        fig = profile_figure(result, title=f"{args.image_a} / {args.image_b}")
        with writing("--plot", args.plot):
            fig.savefig(args.plot, dpi=110)
    data = result.to_json()
    feed = None
    if args.knives is not None and args.rpm is not None and speed is not None:
        feed = speed * 60.0 / (args.rpm * args.knives)
    data["feed_per_pass_mm"] = None if feed is None else round(feed, 5)
    json.dump(data, sys.stdout, allow_nan=False, separators=(",", ":"))
    sys.stdout.write("\n")
    return 0
