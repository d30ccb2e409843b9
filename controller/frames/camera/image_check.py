"""Whether a camera image can be measured at all: dark, flat or saturated (pure).

A camera set up with the wrong exposure delivers images that pair and spool perfectly and
measure nothing: black (exposure far too short: Aravis' fake camera at a real camera's 0.1 ms),
one flat grey (no light, lens cap, out of focus), or clipped white (too long, too much gain).
:func:`image_problems` names those from the grey-level histogram of one Mono8 image;
``planer acquire`` warns with them.

Thresholds (8-bit grey levels): *dark* when 99 % of the pixels are below
:data:`DARK_LEVEL`; *saturated* when more than :data:`SATURATED_FRACTION` of them are at
full scale (255); *flat* when neither but the middle 98 % of the pixels span fewer than
:data:`FLAT_SPAN` grey levels (one grey: no texture to find cuttermarks in).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

__all__ = ["DARK_LEVEL", "FLAT_SPAN", "SATURATED_FRACTION", "ImageLevels", "ImageProblem",
           "image_problems"]

DARK_LEVEL = 16
"""Grey level below which 99 % of a dark image's pixels lie."""
SATURATED_FRACTION = 0.05
"""Fraction of pixels at 255 above which an image is saturated."""
FLAT_SPAN = 8
"""Grey levels the 1st..99th percentiles of a flat image span at most (exclusive)."""


class ImageProblem(enum.Enum):
    """What makes an image useless for the measurement."""

    DARK = "dark"
    FLAT = "flat"
    SATURATED = "saturated"


@dataclass(frozen=True)
class ImageLevels:
    """The grey levels of one image.

    ``p1``, ``p99``: the 1st and 99th percentiles; ``mean``; ``saturated``: the fraction at 255.
    """

    p1: int
    p99: int
    mean: float
    saturated: float

    def describe(self) -> str:
        """The levels in one phrase.

        E.g. ``grey levels 0..0 (1st..99th percentile), mean 0.0, 0.0 % at 255``.
        """
        return (f"grey levels {self.p1}..{self.p99} (1st..99th percentile), mean "
                f"{self.mean:.1f}, {100 * self.saturated:.1f} % at 255")


def image_levels(image: np.ndarray) -> ImageLevels:
    """The grey levels of a Mono8 image (``uint8``, any shape, at least one pixel)."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f"image must be Mono8 (uint8), got {img.dtype}")
    if img.size == 0:
        raise ValueError("image must have at least one pixel")
    hist = np.bincount(img.ravel(), minlength=256)
    cdf = np.cumsum(hist) / img.size
    p1 = int(np.searchsorted(cdf, 0.01))
    p99 = int(np.searchsorted(cdf, 0.99))
    mean = float(np.dot(hist, np.arange(256)) / img.size)
    return ImageLevels(p1=p1, p99=p99, mean=mean, saturated=float(hist[255] / img.size))


def image_problems(image: np.ndarray) -> tuple[tuple[ImageProblem, ...], ImageLevels]:
    """What is wrong with a Mono8 image for the measurement, and its grey levels.

    Returns
    -------
    problems : tuple of ImageProblem
        Empty for a usable image, else one of dark, saturated, flat (dark and saturated
        exclude each other: a saturated image's 99th percentile is 255).
    levels : ImageLevels
        The figures the verdict rests on (for the warning).
    """
    lv = image_levels(image)
    out = []
    if lv.p99 < DARK_LEVEL:
        out.append(ImageProblem.DARK)
    if lv.saturated > SATURATED_FRACTION:
        out.append(ImageProblem.SATURATED)
    if not out and lv.p99 - lv.p1 < FLAT_SPAN:
        out.append(ImageProblem.FLAT)
    return tuple(out), lv
