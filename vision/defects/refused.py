"""The planing defects of a pair whose cuttermark measurement was refused.

The measurement refuses a pair when its own checks cannot trust the shift for the cuttermarks
(a defect's mirrored shading outvoting the albedo, too few marks on a board of raised grain):
a pitch or a CV from it would be wrong, and it is not reported.  The 2-D map needs less: the
defects are found on the residual left once every column's robust mean is taken out, so the
marks' own registration does not enter, only B's wood lying on A's.  This module finds the
defects of such a pair anyway, from the encoder's shift refined on the map itself:

- every candidate shift within ``encoder +- slip_px`` is mapped
  (:class:`vision.defects.surface_map.SurfaceMapper` on the coarse map) and scored by the
  median cell mean square of its residual (:func:`vision.defects.detect.residual`): where B's
  wood lies off A's, the albedo does not cancel in the ratio and every cell's residual grows,
  while a defect, however strong, covers fewer than half the cells and does not move the
  median.  A grid of ``COARSE_STEP`` map columns, then ``FINE_STEP`` around the best;
- the marks' pitch (which the knife-nick fold and the snipe's smoothing need) is the map's own
  marks' profile's dominant period (:func:`map_pitch_mm`); the marks' lowest points are not
  known, so chatter is not looked for.

The refusal stands (the caller re-raises the measurement's error); the defects ride on it
(:func:`attach`, :func:`surface_of`; an attribute of the exception, so it survives pickling to
another process).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from core.checks import check_finite, check_positive
from vision.defects.detect import Defect, Residual, detect_in_residual
from vision.defects.grading import pair_grade
from vision.marks import dominant_period_px
from vision.registration.registrar import encoder_shift_px

if TYPE_CHECKING:
    from vision.defects.detect import DefectFinder



class MapMeasurer(Protocol):
    """What a refused pair's map needs of the measurer (:class:`vision.pipeline.Measurer`)."""

    defect_finder: DefectFinder | None
    rig: Any
    width: int
    min_overlap_px: int
    min_roll_confidence: float
    px_per_mm: float
    max_slip_px: float

    def _binned(self, image: np.ndarray, name: str) -> Any: ...

    def orientation(self, binned_a: Any, binned_b: Any) -> Any:  # noqa: D102
        ...


COARSE_STEP = 1.0
"""Step of the shift search's first grid, map columns."""

FINE_STEP = 0.25
"""Step of its second grid around the first's best, map columns."""

SLIP_MM = 0.5
"""Farthest the search looks from the encoder's shift, mm along the feed (at most the measurer's
``max_slip_px``).  Over the measurer's default 20 px (1.6 mm at 12.5 px/mm) the score's minimum
wanders on boards of raised grain (whose ridges change the median cell with the shift): 3 of
21 such pairs lost their raised grain and 3 pairs gained a false snipe, against 1 and 0 at
0.5 mm (the renderer's belt slips up to 4 px, 0.32 mm)."""

MIN_PITCH_MM = 0.5
"""Shortest pitch looked for in the map's marks' profile, mm."""


@dataclass(frozen=True)
class RefusedSurface:
    """The defects of a refused pair and the shift they were found at.

    Attributes
    ----------
    defects : tuple of vision.defects.detect.Defect
        As ``Measurement.defects``.
    grade, grade_reason : int, str
        As ``Measurement.grade``, ``grade_reason``.
    shift_px : float
        The shift the map was registered at, px along the feed.
    encoder_shift_px : float
        The encoder's shift it was searched around, px.
    pitch_mm : float
        The marks' pitch read from the map (NaN: none found); for the detectors only, not a
        measurement of the marks.
    """

    defects: tuple[Defect, ...]
    grade: int
    grade_reason: str
    shift_px: float
    encoder_shift_px: float
    pitch_mm: float

    def to_json(self) -> dict[str, Any]:
        """Plain-JSON dict of the refused pair's defects.

        Keys ``defects``, ``grade``, ``grade_reason``, ``shift_px``, ``encoder_shift_px``,
        ``pitch_mm`` (``None`` when not found).
        """
        return {
            "defects": [d.to_json() for d in self.defects],
            "grade": self.grade,
            "grade_reason": self.grade_reason,
            "shift_px": round(float(self.shift_px), 3),
            "encoder_shift_px": round(float(self.encoder_shift_px), 3),
            "pitch_mm": (round(float(self.pitch_mm), 5) if math.isfinite(self.pitch_mm)
                         else None),
        }


def map_pitch_mm(res: Residual) -> float:
    """The marks' pitch from the map's robust row mean (its dominant period), mm.

    Parameters
    ----------
    res : vision.defects.detect.Residual
        The map's residual (``profile``: the marks' slope along the feed).

    Returns
    -------
    float
        Pitch, mm; NaN when the profile holds fewer than two periods of anything.
    """
    smap = res.smap
    cols = smap.valid_cols
    if cols.size < 16:
        return math.nan
    prof = res.profile[int(cols[0]):int(cols[-1]) + 1]
    period = dominant_period_px(prof, min_period_px=max(4.0, MIN_PITCH_MM * smap.cols_per_mm))
    return period / smap.cols_per_mm if math.isfinite(period) else math.nan


def _grid(centre: float, half: float, step: float) -> np.ndarray:
    k = int(math.floor(half / step + 1e-9))
    return centre + step * np.arange(-k, k + 1)


def refused_surface(finder: DefectFinder, rows_a: np.ndarray, rows_b: np.ndarray, *,
                    encoder_shift_px: float, roll_deg: float, slip_px: float,
                    coarse: tuple[np.ndarray | None, np.ndarray | None] | None = None
                    ) -> RefusedSurface:
    """The defects of a refused pair (see the module's docstring).

    Parameters
    ----------
    finder : vision.defects.detect.DefectFinder
        The measurer's finder (its map's set-up, settings and knives).
    rows_a, rows_b : ndarray
        The pair's row bins (as :meth:`DefectFinder.__call__`).
    encoder_shift_px : float
        The encoder's shift, px along the feed (``Measurement.encoder_shift_px``).
    roll_deg : float
        Direction of the feed in the image, degrees.
    slip_px : float
        How far from the encoder's shift the board may have moved (the belt's slip), px;
        0: the encoder's shift as it is.
    coarse : tuple of ndarray or None, optional
        The map's coarse sources of A and B where already made (as
        :meth:`DefectFinder.__call__`); made here once otherwise, not for every shift tried.

    Returns
    -------
    RefusedSurface
    """
    enc = check_finite("encoder_shift_px", encoder_shift_px)
    slip = check_positive("slip_px", slip_px, allow_zero=True)
    settings = finder.settings
    col_px = float(finder.mapper.bin_cols)  # image px per map column
    # the coarse sources made once for every shift tried
    ca, cb = (None, None) if coarse is None else coarse
    coarse = (finder.mapper.coarse_source(rows_a) if ca is None else ca,
              finder.mapper.coarse_source(rows_b) if cb is None else cb)

    def scored(shift: float) -> tuple[float, Residual]:
        res = finder.residual_at(rows_a, rows_b, shift_px=shift, roll_deg=roll_deg,
                                 coarse=coarse)
        return res.median, res

    best_shift = enc
    best_score, best_res = scored(enc)
    seen = {round(enc, 6)}
    for step, half, centre in ((COARSE_STEP * col_px, slip, enc),
                               (FINE_STEP * col_px, COARSE_STEP * col_px, None)):
        if slip <= 0:
            break
        for shift in _grid(best_shift if centre is None else centre, half, step):
            shift = float(shift)
            if abs(shift - enc) > slip + 1e-9 or round(shift, 6) in seen:
                continue
            seen.add(round(shift, 6))
            value, res = scored(shift)
            if value < best_score:
                best_shift, best_score, best_res = shift, value, res
    pitch = map_pitch_mm(best_res)
    # the detectors on the residual already made (not a second one from its map)
    found = detect_in_residual(best_res, None, finder.knives,
                               pitch if math.isfinite(pitch) else None, settings)
    g = pair_grade(found)
    return RefusedSurface(found, g.grade, g.reason, best_shift, enc, pitch)


_ATTRIBUTE = "refused_surface"


def attach(exc: BaseException, surface: RefusedSurface) -> None:
    """Let a refusal carry the pair's defects (:func:`surface_of` reads them)."""
    setattr(exc, _ATTRIBUTE, surface)


def surface_of(exc: BaseException) -> RefusedSurface | None:
    """The defects a refusal carries (``None``: not looked for, or not a refusal of a pair)."""
    found = getattr(exc, _ATTRIBUTE, None)
    return found if isinstance(found, RefusedSurface) else None


def refused_pair(measurer: MapMeasurer, image_a: np.ndarray, image_b: np.ndarray, *,
                 counts_a: int, counts_b: int) -> RefusedSurface | None:
    """The defects of a pair the measurer refused (``None``: not looked for, or no map).

    The pair is binned again and its roll estimated from its own rows (a refusal is rare; the
    board's known roll, if any, is not consumed), and :func:`refused_surface` searches
    ``min(SLIP_MM, measurer.max_slip_px)`` around the encoder's shift.

    Parameters
    ----------
    measurer : MapMeasurer
        A :class:`vision.pipeline.Measurer`.
        The measurer that refused the pair (``defects=True``, else ``None`` is returned).
    image_a, image_b : ndarray
        The pair.
    counts_a, counts_b : int
        The encoder's counts at the two triggers.

    Returns
    -------
    RefusedSurface or None
        ``None`` also when the encoder's shift leaves too little overlap or the images are
        too dark or clipped to map.
    """
    finder = measurer.defect_finder
    if finder is None:
        return None
    enc = measurer.rig.encoder
    try:  # a pair that cannot be mapped either: the refusal goes out as it is
        d_enc = encoder_shift_px(counts_a, counts_b, px_per_count=enc.px_per_count,
                                 counter_bits=enc.counter_bits)
        if abs(d_enc) > measurer.width - measurer.min_overlap_px:
            return None
        ba = measurer._binned(np.asarray(image_a), "image_a")
        bb = measurer._binned(np.asarray(image_b), "image_b")
    except ValueError:  # MeasurementError included: too dark, clipped, bad counts
        return None
    orient = measurer.orientation(ba, bb)
    roll = (orient.roll_deg if orient.confidence >= measurer.min_roll_confidence
            else measurer.rig.camera.roll_deg)
    slip = min(SLIP_MM * measurer.px_per_mm, measurer.max_slip_px)
    return refused_surface(finder, ba.bins, bb.bins, encoder_shift_px=d_enc, roll_deg=roll,
                           slip_px=slip)
