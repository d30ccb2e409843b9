"""``planer calibrate``: camera intrinsics from checkerboard photographs, into a rig file.

Reads the images, finds the board in each (:func:`vision.calibration.camera.find_corners`),
calibrates
(:func:`vision.calibration.camera.calibrate`) and writes the rig file with the new ``[camera]``
intrinsics. Images that cannot be read or show no complete board are skipped with a one-line
warning on stderr naming the file. The other values of the rig (``[lights]``, ``[encoder]``,
``px_per_mm``, ``exposure_ms``) come from ``--rig`` or, without it, from the shipped default
``config/rig.toml``; ``--px-per-mm`` overrides the scale. The file is written atomically; its
folder is created when missing (checked before the images are read).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

_DESCRIPTION = (
    "Find the checkerboard's inner corners (sub-pixel) in each image, calibrate the camera with "
    "OpenCV and write the rig file. Default model k1: radial k1 only (the seed's Eq. 7), "
    "dist = [k1, 0, 0, 0, 0]; 'full' frees k1, k2, p1, p2, k3. Unreadable images and images "
    "without a complete board are skipped with a warning."
)


def configure(parser: argparse.ArgumentParser) -> None:
    """Add this command's arguments."""
    parser.description = _DESCRIPTION
    parser.add_argument("images", nargs="+", metavar="IMAGE", help="checkerboard photographs")
    parser.add_argument(
        "--pattern",
        required=True,
        metavar="COLSxROWS",
        help="inner corners of the board, e.g. 7x7",
    )
    parser.add_argument(
        "--square-mm",
        type=float,
        default=1.0,
        metavar="S",
        help="side of one square in mm (default 1.0; the intrinsics do not depend on it)",
    )
    parser.add_argument(
        "--model",
        choices=("k1", "full"),
        default="k1",
        help="distortion model: k1 only (default, seed Eq. 7) or all five coefficients",
    )
    parser.add_argument("--out", required=True, metavar="RIG.toml", help="rig file to write")
    parser.add_argument(
        "--px-per-mm",
        type=float,
        default=None,
        metavar="V",
        help="px per mm of the undistorted image along the feed (default: from the base rig)",
    )
    parser.add_argument(
        "--rig",
        default=None,
        metavar="BASE.toml",
        help="rig file whose other values ([lights], [encoder], px_per_mm, exposure_ms) are kept",
    )


def _warn(message: str) -> None:
    print(f"planer calibrate: warning: {message}", file=sys.stderr)


def _read_gray(path: Path) -> Any:
    """The image as an 8-bit grayscale array, or a string saying why it cannot be read."""
    import cv2
    import numpy as np

    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return "file not found"
    except IsADirectoryError:
        return "is a directory"
    except OSError as exc:
        return f"cannot read file ({exc.strerror or exc})"
    if not data:
        return "empty file"
    try:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    except cv2.error:
        image = None
    if image is None:
        return "not a readable image"
    return image


def _unknown_keys(data: dict[str, Any]) -> list[str]:
    """Keys of a parsed rig file that :class:`config.rig.Rig` does not hold (not carried over)."""
    from dataclasses import fields

    from config.rig import Camera, Encoder, Lights

    known = {"camera": Camera, "lights": Lights, "encoder": Encoder}
    out = []
    for table, value in data.items():
        if table not in known:
            out.append(table)
            continue
        if isinstance(value, dict):
            names = {f.name for f in fields(known[table])}
            out += [f"{table}.{k}" for k in value if k not in names]
    return out


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    import dataclasses

    try:
        import tomllib
    except ModuleNotFoundError:  # pragma: no cover - Python 3.10
        import tomli as tomllib  # type: ignore[no-redef]

    from config.loading import default_path, load_toml
    from config.rig import rig_from_dict, rig_to_toml
    from core.checks import check_positive
    from core.errors import ConfigError
    from core.fileio import atomic_write_text
    from planer.cli import output_file
    from vision.calibration.camera import MIN_IMAGES, calibrate, find_corners, parse_pattern

    pattern = parse_pattern(args.pattern)
    square_mm = check_positive("--square-mm", args.square_mm)
    px_per_mm = None if args.px_per_mm is None else check_positive("--px-per-mm", args.px_per_mm)
    out = Path(output_file("--out", args.out))  # its folder is created if missing

    # The base rig first, so that a bad --rig fails before the slow corner search.
    base_path = Path(args.rig) if args.rig is not None else default_path("rig.toml")
    base_data = load_toml(base_path)
    try:
        base = rig_from_dict(base_data)
    except ConfigError as exc:
        raise ConfigError(f"{base_path}: {exc}") from None
    if args.rig is not None:
        dropped = _unknown_keys(base_data)
        if dropped:
            _warn(f"{base_path}: not carried over to {out}: {', '.join(dropped)}")

    corner_sets = []
    size: tuple[int, int] | None = None
    skipped = 0
    cols, rows = pattern
    for name in args.images:
        path = Path(name)
        image = _read_gray(path)
        if isinstance(image, str):
            _warn(f"skipping {name}: {image}")
            skipped += 1
            continue
        h, w = image.shape[:2]
        if size is not None and (w, h) != size:
            _warn(
                f"skipping {name}: size {w}x{h} differs from the first image's {size[0]}x{size[1]}"
            )
            skipped += 1
            continue
        corners = find_corners(image, pattern=pattern)
        if corners is None:
            _warn(f"skipping {name}: no {cols}x{rows} checkerboard found")
            skipped += 1
            continue
        size = (w, h)
        corner_sets.append(corners)

    if size is None or len(corner_sets) < MIN_IMAGES:
        raise ValueError(
            f"only {len(corner_sets)} of {len(args.images)} images usable "
            f"(unreadable or no {cols}x{rows} board); calibration needs at least {MIN_IMAGES}"
        )
    result = calibrate(corner_sets, size, pattern=pattern, square_mm=square_mm, model=args.model)

    camera = dataclasses.replace(
        base.camera,
        fx=result.fx,
        fy=result.fy,
        cx=result.cx,
        cy=result.cy,
        dist=result.dist,
        px_per_mm=base.camera.px_per_mm if px_per_mm is None else px_per_mm,
    )
    rig = dataclasses.replace(base, camera=camera)
    header = (
        f"# written by planer calibrate: {result.n_images} images {size[0]}x{size[1]}, "
        f"pattern {cols}x{rows}, model {args.model}, rms {result.rms_px:.3f} px\n"
    )
    text = header + rig_to_toml(rig)
    rig_from_dict(tomllib.loads(text))  # what we write must load back
    atomic_write_text(out, text)

    k = result.dist
    print(f"images: {result.n_images} used, {skipped} skipped; model {args.model}")
    print(
        f"rms reprojection: {result.rms_px:.3f} px "
        f"(worst image {max(result.per_image_error_px):.3f} px)"
    )
    print(f"fx {result.fx:.2f}  fy {result.fy:.2f}  cx {result.cx:.2f}  cy {result.cy:.2f} px")
    dist_text = f"k1 {k[0]:.5f}"
    if args.model == "full":
        dist_text += f"  k2 {k[1]:.5f}  p1 {k[2]:.5f}  p2 {k[3]:.5f}  k3 {k[4]:.5f}"
    print(dist_text)
    print(f"px_per_mm {camera.px_per_mm:g}; wrote {out}")
    return 0
