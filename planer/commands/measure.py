"""``planer measure``: profile and cuttermark metrics of one image pair, as one JSON object.

Usage::

    planer measure A.png B.png --counts-a N --counts-b M --rig rig.toml [--speed-mm-s V]
                   [--plot out.png] [--flat-a FA.png --flat-b FB.png]

Prints one JSON object on stdout with the contract keys ``x_mm``, ``height_um``, ``pitch_mm``,
``mark_widths_mm``, ``uniformity_cv``, ``depth_um``, ``shift_px`` and extras (``mark_depths_um``,
``cusps_mm``, ``bottoms_mm``, ``marks``, ``encoder_shift_px``, ``confidence``, ``blur_px``).
Bad input raises ``ValueError``/``OSError`` subclasses with one line, which :mod:`planer.cli`
prints as ``planer measure: error: ...`` with exit code 2.
"""

from __future__ import annotations

import argparse
import json
import math
import sys

HELP = "measure the profile and cuttermarks of an image pair (prints one JSON object)"


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


def run(args: argparse.Namespace) -> int:
    """Run the command: read, measure, print JSON (and plot)."""
    from config.rig import load_rig
    from core.imageio import read_gray
    from vision.pipeline import Measurer

    if (args.flat_a is None) != (args.flat_b is None):
        raise ValueError("--flat-a and --flat-b must be given together")
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
    measurer = Measurer(rig, image_a.shape, flat_field=flat)  # type: ignore[arg-type]
    result = measurer.measure(
        image_a, image_b, counts_a=args.counts_a, counts_b=args.counts_b,
        speed_mm_s=args.speed_mm_s,
    )
    if args.plot:
        from vision.plot import profile_figure

        fig = profile_figure(result, title=f"{args.image_a} / {args.image_b}")
        fig.savefig(args.plot, dpi=110)
    json.dump(result.to_json(), sys.stdout, allow_nan=False, separators=(",", ":"))
    sys.stdout.write("\n")
    return 0
