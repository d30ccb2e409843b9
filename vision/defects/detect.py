"""Planing defects (ASTM D1666) found on the 2-D surface map of one pair.

Each kind has its own detector, all working from one :class:`Residual` of the map
(:mod:`vision.defects.surface_map`):

- the cuttermarks run straight across the feed, so their slope -- and anything else that is a
  function of the position along the feed alone (illumination, the pair's imbalance) -- is the
  map's robust mean over its rows (the median of groups of rows, then the mean of the samples
  near it); the *residual* slope ``r = p - mean`` holds what is
  two-dimensional: the defects, the noise and the albedo the registration leaves;
- ``r`` is summed into cells (``cell_px`` map columns along the feed, one map row across:
  ~0.3 x 0.4 mm on the :class:`DefectFinder`'s map); a cell is *marked* when its mean square,
  smoothed over 3 x 3 cells, exceeds ``excess`` times the field's median (noise-adaptive) or,
  on an almost noise-free pair, ``excess`` times the floor ``floor_slope**2``;
- marked cells form blobs (8-connected).  Area and strength of every blob at once; only the
  blobs large and strong enough to be reported are analysed further: the depth of the slope
  integrated along each row across it (rim to rim), and its roughness (the share of ``r``'s
  power above ~1 cycle/mm).

Detectors: :func:`knife_nicks` (a band of rows marked along most of the field: a ridge running
along the feed), :func:`raised_grain` (many thin lines over the field: ridges on the rings),
:func:`pits` (compact blobs: a smooth dent is a *chip mark*, a rough or sharp-walled pit is
*torn grain*, a rough patch without a dent is *fuzzy grain*), :func:`chatter` (a waviness of
the marks' lowest points whose period is not the revolution's: needs the number of knives)
and :func:`snipe` (the field's height bent along the feed, concave: the cut deepening toward
one end).  A ridge running exactly along the feed has no along-feed slope: raised grain whose
rings run within ~10 deg of the feed is not observed (the lights lie along the feed).

Coordinates follow the measurement's contract: ``x_mm``, ``y_mm`` of a defect's centre in image
A's undistorted frame from its top-left corner (x = columns, along the feed); ``length_mm``
along the feed, ``width_mm`` across it; ``depth_um`` (positive = below the surface) where it
is measured, else ``None``.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import scipy.fft as sfft

from config.rig import Camera, Lights
from core.checks import check_positive
from vision import ffts
from vision.defects import kernels
from vision.defects.surface_map import SurfaceMap, SurfaceMapper

_NICK_SLACK = 1.0 / 3.0
"""Rows whose plain mean fold stands out this share of ``nick_ratio`` get the median fold."""


class DefectKind(enum.Enum):
    """The planing defects of ASTM D1666 the vision finds (values are the JSON contract)."""

    TORN_GRAIN = "torn_grain"
    RAISED_GRAIN = "raised_grain"
    FUZZY_GRAIN = "fuzzy_grain"
    CHIP_MARK = "chip_mark"
    KNIFE_NICK = "knife_nick"
    CHATTER = "chatter"
    SNIPE = "snipe"


@dataclass(frozen=True)
class Defect:
    """One defect of one pair.

    Attributes
    ----------
    kind : DefectKind
    x_mm, y_mm : float
        Centre in A's undistorted image frame, mm from its top-left corner (x along the feed).
    length_mm, width_mm : float
        Extent along and across the feed, mm.
    depth_um : float or None
        Depth below the surrounding surface (height of a ridge, amplitude of chatter, sag of
        snipe), um; ``None`` where not measurable.
    confidence : float
        In [0, 1].
    """

    kind: DefectKind
    x_mm: float
    y_mm: float
    length_mm: float
    width_mm: float
    depth_um: float | None
    confidence: float

    def to_json(self) -> dict[str, Any]:
        """The contract's JSON object.

        Keys ``kind``, ``x_mm``, ``y_mm``, ``length_mm``, ``width_mm``, ``depth_um`` (or null),
        ``confidence``.
        """
        return {
            "kind": self.kind.value,
            "x_mm": round(float(self.x_mm), 3),
            "y_mm": round(float(self.y_mm), 3),
            "length_mm": round(float(self.length_mm), 3),
            "width_mm": round(float(self.width_mm), 3),
            "depth_um": (None if self.depth_um is None or not math.isfinite(self.depth_um)
                         else round(float(self.depth_um), 2)),
            "confidence": round(float(min(1.0, max(0.0, self.confidence))), 3),
        }


@dataclass(frozen=True)
class DefectSettings:
    """Thresholds of the detectors (measured on the independent boards; docs/vision.md).

    Attributes
    ----------
    cell_mm : float
        Cell length along the feed, mm.
    col_mm, row_mm : float
        The map's column spacing along the feed and row spacing across it the
        :class:`DefectFinder` aims at, mm (whole image columns and row bins averaged).
    excess : float
        A cell is marked when its smoothed mean square exceeds this many times the median.
    floor_slope : float
        The median's floor: the rms residual slope of a cell on a surface without noise (a
        cell is marked only above ``excess * floor_slope**2``; what the map's registration
        and undistortion leave on an ideal pair stays below it).
    min_blob_mm2 : float
        Smallest compact defect, mm^2.
    min_fuzzy_mm2 : float
        Smallest patch of fuzzy grain, mm^2.
    min_confidence : float
        Less confident detections are not reported.
    nick_ratio : float
        A knife nick's rows: the mean square of their residual folded at one revolution stands
        out from the median row's by at least this factor (:func:`knife_nicks`).
    nick_max_mm : float
        Widest band across the feed that is still one nick, mm.
    raised_coherence, raised_strong : float
        Raised grain: the rows' correlation at a lag other than 0, or at any lag
        (:func:`raised_grain`).
    dent_um : float
        A blob whose integrated depth exceeds this is a dent (chip mark or torn grain), um.
    rough : float
        Texture (:func:`_texture`: share of the residual's power at periods below ~0.8 mm away
        from cast shadows, the noise's removed) above which a dent is torn grain.
    fuzzy_rough : float
        Roughness above which a patch without shadows is fuzzy grain.
    torn_shadow : float
        Share of a blob's samples near the shadow slope above which it is torn grain.
    torn_gap_mm : float
        Torn-grain blobs on common rows closer than this along the feed are one pit (its two
        ends), mm.
    chatter_um : float
        Smallest chatter amplitude reported, um.
    snipe_um : float
        Smallest snipe sag reported, um.
    slip_marked, slip_median, slip_cells : float
        A registration one marks' pitch off (:meth:`DefectFinder.registered`): looked for
        where at least ``slip_marked`` of the valid cells are marked; the map one pitch nearer
        the encoder's shift is kept where its cells' median mean square is below
        ``slip_median`` and its marked cells below ``slip_cells`` of the registered one's.
    """

    cell_mm: float = 0.4
    col_mm: float = 0.16
    row_mm: float = 0.4
    excess: float = 4.0
    floor_slope: float = 0.001
    min_blob_mm2: float = 1.0
    min_fuzzy_mm2: float = 10.0
    min_confidence: float = 0.3
    nick_ratio: float = 12.0
    nick_max_mm: float = 2.0
    raised_coherence: float = 0.4
    raised_strong: float = 0.8
    dent_um: float = 8.0
    rough: float = 0.15
    fuzzy_rough: float = 0.55
    torn_shadow: float = 0.05
    torn_gap_mm: float = 4.0
    chatter_um: float = 0.5
    snipe_um: float = 3.0
    slip_marked: float = 0.05
    slip_median: float = 0.3
    slip_cells: float = 0.5

    def __post_init__(self) -> None:
        for name in ("cell_mm", "col_mm", "row_mm", "excess", "floor_slope", "min_blob_mm2",
                     "min_fuzzy_mm2", "min_confidence",
                     "nick_ratio", "nick_max_mm", "raised_coherence", "raised_strong",
                     "dent_um", "rough", "fuzzy_rough", "torn_shadow", "torn_gap_mm",
                     "chatter_um", "snipe_um", "slip_marked", "slip_median",
                     "slip_cells"):
            check_positive(name, getattr(self, name))


@dataclass(frozen=True)
class Blob:
    """A connected group of marked cells (map coordinates: columns along the feed)."""

    cols: tuple[int, int]  # map columns [c0, c1)
    rows: tuple[int, int]  # map rows [r0, r1)
    area_mm2: float
    fill: float  # marked cells / bounding-box cells
    depth_um: float  # integrated depth below the rim (negative: a bump)
    rough: float  # share of the residual power at short periods
    shadow: float  # share of its samples at >= 0.7 of the shadow slope
    strength: float  # mean excess of its cells over the median
    texture: float = 0.0  # share of short-period power away from shadows, noise's removed


@dataclass(frozen=True)
class Residual:
    """The map's two-dimensional part and its cells (see the module's docstring).

    Attributes
    ----------
    smap : SurfaceMap
    r : ndarray of float32, shape (rows, cols)
        Residual slope (0 outside the valid map).
    profile : ndarray of float64, shape (cols,)
        The robust row mean of the slope (the marks' slope along the feed).
    excess : ndarray of float32, shape (rows, cells)
        Smoothed cell mean square over the field's median.
    marked : ndarray of bool, shape (rows, cells)
    cell_px : int
        Map columns per cell.
    base : float
        The mean square ``excess`` is relative to: the cells' median, or the floor
        ``floor_slope**2`` where that is larger.
    median : float
        The cells' median mean square.
    scale : float
        The residual's robust scale (1.4826 x the median absolute deviation of the samples
        from the profile's first estimate, shadows left out).
    """

    smap: SurfaceMap
    r: np.ndarray
    profile: np.ndarray
    excess: np.ndarray
    marked: np.ndarray
    valid_cells: np.ndarray
    cell_px: int
    base: float = 1.0
    median: float = 1.0
    scale: float = 0.0


def residual(smap: SurfaceMap, settings: DefectSettings) -> Residual:
    """Residual slope, cell excess and marked cells of a map (see the module's docstring).

    The marks' profile is each column's robust mean: the rows are averaged in groups
    (shadowed samples, ``|p| >= shadow_slope / 2``, left out); the column's location is the
    mean of the tightest run of ~35 % of its sorted group means (the *shorth*), so a defect
    covering even most of a column does not move it as long as its rows do not agree with
    each other as tightly as clean ones do (a pit's walls, rough bottom and cast shadows never
    do); then the mean of the column's samples near that location.  One compiled pass
    (:func:`vision.defects.kernels.residual_map`).
    """
    p, valid = smap.slope_along_feed, smap.valid
    rows, cols = p.shape
    group = max(1, rows // 16)
    n_g = rows // group
    cell = max(1, min(cols, int(round(settings.cell_mm * smap.cols_per_mm))))
    profile = np.empty(cols)
    r = np.empty((rows, cols), dtype=np.float32)
    e = np.empty((rows, cols // cell), dtype=np.float32)
    valid_cells = np.empty((rows, cols // cell), dtype=bool)
    cells = np.empty(e.size, dtype=np.float32)
    sat = 0.5 * smap.shadow_slope if math.isfinite(smap.shadow_slope) else 1e30
    mad, n_cells = kernels.residual_map(
        np.ascontiguousarray(p, dtype=np.float32), np.ascontiguousarray(valid), sat, group,
        max(2, min(n_g, int(math.ceil(0.35 * n_g)))), cell, profile, r, e, valid_cells, cells)
    median = 1.0
    if n_cells:  # the valid cells' (upper) median mean square (numpy's selection: the fastest)
        valid_e = cells[:n_cells]
        valid_e.partition(n_cells // 2)
        median = float(valid_e[n_cells // 2])
    median = max(median, 1e-12)
    base = max(median, settings.floor_slope ** 2)
    excess = np.empty_like(e)
    marked = np.empty_like(valid_cells)
    kernels.marked_cells(e, valid_cells, 1.0 / base, settings.excess, excess, marked)
    return Residual(smap, r, profile, excess, marked, valid_cells, cell, base, median,
                    1.4826 * mad)


def _row_depth_um(res: Residual, c0: int, c1: int, r0: int, r1: int, mask: np.ndarray
                  ) -> float:
    """Depth below the rim of the slope integrated along each row over columns [c0, c1).

    ``mask`` (shape ``(r1 - r0, c1 - c0)``) selects the blob's samples; each row's height
    less the line between its rims (its first and last tenth), the 90th percentile of the
    depths on ``mask`` (one compiled pass: :func:`vision.defects.kernels.row_depth`).
    """
    return float(kernels.row_depth(res.r, r0, r1, c0, c1, np.ascontiguousarray(mask),
                                   1000.0 / res.smap.cols_per_mm))


def blobs(res: Residual, settings: DefectSettings) -> list[Blob]:
    """The marked cells' connected groups, with their extent, depth and roughness.

    Area and strength of every group at once (``np.bincount`` over the labels); depth and
    shadows only for the groups large and strong enough to be reported, roughness and texture
    only for those that can be a D1666 defect (a dent, shadowed, or as large as a patch of
    fuzzy grain: the others are not returned).
    """
    smap = res.smap
    cell_mm = res.cell_px / smap.cols_per_mm
    row_mm = smap.row_step_px / smap.px_per_mm
    # no group can be reported when all the marked cells together are too few (a clean pair)
    if np.count_nonzero(res.marked) * cell_mm * row_mm < settings.min_blob_mm2:
        return []
    # Grana's block-based labelling (BBDT): the same groups and statistics, ~4x faster than
    # this OpenCV's default (Spaghetti) with statistics on a map's ~100 x 160 cells
    n, labels, stats, _ = cv2.connectedComponentsWithStatsWithAlgorithm(
        res.marked.view(np.uint8), 8, cv2.CV_32S, cv2.CCL_BBDT)
    if n <= 1:
        return []
    area = stats[:, cv2.CC_STAT_AREA].astype(np.float64)
    large = np.flatnonzero(area * cell_mm * row_mm >= settings.min_blob_mm2)
    large = large[large > 0]
    # the mean excess of the large groups only: each one's cells in its box, summed in order
    # (as np.bincount sums them; one compiled pass)
    strength = np.zeros(n)
    kernels.blob_strengths(labels, stats, res.excess, large, strength)
    # confidence >= min_confidence  <=>  strength >= excess (1 - ln(1 - c) / 1.5)
    need = settings.excess * (1.0 - math.log(1.0 - min(settings.min_confidence, 0.999)) / 1.5)
    keep = large[strength[large] >= need]
    out: list[Blob] = []
    if keep.size == 0:
        return out
    hp = hp5 = None
    for lab in keep:
        x, y, w, h, a = (int(v) for v in stats[lab])
        pad = max(2, w // 2) * res.cell_px
        c0 = max(0, x * res.cell_px - pad)
        c1 = min(res.r.shape[1], (x + w) * res.cell_px + pad)
        # the blob's samples, rows y..y+h, c0..c1, and the share of them at the shadow's slope
        mask = np.empty((h, c1 - c0), dtype=bool)
        shadow = kernels.blob_mask(labels, lab, x, y, w, res.cell_px, c0, smap.slope_along_feed,
                                   0.7 * smap.shadow_slope, mask)
        depth = _row_depth_um(res, c0, c1, y, y + h, mask)
        p_in = smap.slope_along_feed[y:y + h, c0:c1]
        if (depth < settings.dent_um and shadow < settings.torn_shadow
                and a * cell_mm * row_mm < settings.min_fuzzy_mm2):
            continue  # a weak dent or a bump without shadows, smaller than a fuzzy patch
        if hp is None or hp5 is None:
            # short periods: the residual minus its running mean over ~1 mm (and 5 columns)
            k = max(3, int(round(1.0 * smap.cols_per_mm)) | 1)
            hp = res.r - cv2.blur(res.r, (k, 1), borderType=cv2.BORDER_REFLECT)
            hp5 = res.r - cv2.blur(res.r, (5, 1), borderType=cv2.BORDER_REFLECT)
        r_in = res.r[y:y + h, c0:c1][mask]
        tot = float((r_in ** 2).sum())
        rough = float((hp[y:y + h, c0:c1][mask] ** 2).sum()) / max(tot, 1e-12)
        texture = _texture(res, hp5, p_in, (y, y + h, c0, c1), mask)
        out.append(Blob((x * res.cell_px, (x + w) * res.cell_px), (y, y + h),
                        a * cell_mm * row_mm, a / float(w * h), depth, rough, shadow,
                        float(strength[lab]), texture))
    return out


def _texture(res: Residual, hp: np.ndarray, p_in: np.ndarray,
             box: tuple[int, int, int, int], mask: np.ndarray) -> float:
    """Share of a blob's residual power at periods below ~0.8 mm, away from cast shadows.

    ``hp``: the residual less its running mean over 5 map columns.  Samples within one
    column of a shadow (``|p| >= shadow_slope / 2``: the saturated walls, whose steps would
    look rough) are left out, and the noise's share of the high-pass power (the cells' median
    mean square, ``1 - 1/5`` of it) is removed: a smooth dent (a chip mark) keeps almost none,
    the fibrous bottom of torn grain much.
    """
    y0, y1, c0, c1 = box
    sat = (np.abs(p_in) >= np.float32(0.5 * res.smap.shadow_slope)).astype(np.uint8)
    near = cv2.dilate(sat, np.ones((1, 3), np.uint8)).astype(bool)
    keep = mask & ~near & res.smap.valid[y0:y1, c0:c1]
    n = int(np.count_nonzero(keep))
    if n == 0:
        return 0.0
    tot = float(np.square(res.r[y0:y1, c0:c1][keep], dtype=np.float64).sum())
    high = float(np.square(hp[y0:y1, c0:c1][keep], dtype=np.float64).sum())
    return (high - n * res.median * (1.0 - 1.0 / 5.0)) / max(tot, 1e-12)


def _defect(res: Residual, kind: DefectKind, cols: tuple[float, float],
            rows: tuple[float, float], depth_um: float | None, confidence: float) -> Defect:
    smap = res.smap
    cc, rc = 0.5 * (cols[0] + cols[1] - 1), 0.5 * (rows[0] + rows[1] - 1)
    x, y = smap.image_xy_mm(cc, rc)
    length = (cols[1] - cols[0]) / smap.cols_per_mm
    width = (rows[1] - rows[0]) * smap.row_step_px / smap.px_per_mm
    return Defect(kind, float(x), float(y), float(length), float(width), depth_um,
                  float(min(1.0, max(0.0, confidence))))


def _confidence(strength: float, settings: DefectSettings) -> float:
    return 1.0 - math.exp(-max(0.0, strength / settings.excess - 1.0) * 1.5)


def knife_nicks(res: Residual, settings: DefectSettings, pitch_mm: float | None = None,
                knives: int | None = None) -> tuple[list[Defect], set[int]]:
    """Bands of rows whose residual repeats every revolution: knife nicks.

    A nick is one knife cutting short in a band across the feed: there that knife's marks
    differ from the others' by a ridge along the feed, the same on every revolution.  Each
    row's residual is folded at one revolution (``knives * pitch``; at one pitch when the
    knives are not known, where a nick on one of ``k`` knives stands out ``k`` times less) as
    the median over the revolutions per phase (a pit within one revolution does not move
    it); a nick's rows carry a folded profile whose mean square stands out ``nick_ratio``
    times from the median row's (of every eighth row).  The medians are taken only on the
    rows whose plain mean fold stands out a third as much, and on the reference rows
    (:func:`vision.defects.kernels.fold_rows`).  Returned with the map rows taken.
    """
    smap = res.smap
    if pitch_mm is None or not math.isfinite(pitch_mm) or pitch_mm <= 0:
        return [], set()
    period = (knives or 1) * pitch_mm * smap.cols_per_mm
    cols = smap.valid_cols
    if cols.size == 0 or (int(cols[-1]) + 1 - int(cols[0])) < 3 * period:
        return [], set()  # fewer than three revolutions: no median over them
    rows = res.r.shape[0]
    c0, c1 = int(cols[0]), int(cols[-1]) + 1
    nb = max(4, int(round(period)))
    folded = np.empty((rows, nb))
    energy = np.empty(rows)
    # the median fold on every 8th row (the reference) and on the rows that may stand out
    every = 8
    # ... then the reference rows' median, and whether any row stands out from it: one call
    n_ref, median, n_hot = kernels.fold_reference(
        res.r, np.ascontiguousarray(smap.valid), c0, float(period), nb,
        int((c1 - c0) // period), int(math.ceil(0.5 * cols.size)), every,
        _NICK_SLACK * settings.nick_ratio, settings.nick_ratio, folded, energy)
    if n_ref < 4 or n_hot == 0:
        return [], set()
    ratio = energy / max(median, 1e-18)  # NaN on rows without samples: never hot
    hot = ratio >= settings.nick_ratio  # n_hot of them
    edges = np.flatnonzero(np.diff(np.r_[0, hot.astype(np.int8), 0]))
    bands = list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))
    if len(bands) > 2:
        return [], set()  # many bands: ridges of raised grain, not a nick
    rows_mm = smap.row_step_px / smap.px_per_mm
    dx_um = 1000.0 / smap.cols_per_mm
    found, taken = [], set()
    for r0, r1 in bands:
        if (r1 - r0) * rows_mm > settings.nick_max_mm + 2 * rows_mm:
            continue
        # height of the ridge: the band's folded residual integrated along the feed
        f = np.nan_to_num(folded[r0:r1].mean(axis=0).astype(np.float64))
        h = np.cumsum(f - f.mean()) * dx_um
        depth = -float(h.max() - h.min())
        w = ratio[r0:r1]
        rc = float((np.arange(r0, r1) * w).sum() / w.sum())
        conf = 1.0 - math.exp(-max(0.0, float(w.max()) / settings.nick_ratio - 1.0) * 1.5)
        d = _defect(res, DefectKind.KNIFE_NICK, (float(cols[0]), float(cols[-1]) + 1),
                    (rc - 0.5 * (r1 - r0) + 0.5, rc + 0.5 * (r1 - r0) + 0.5), depth, conf)
        found.append(d)
        taken.update(range(r0, r1))
    return found, taken


def raised_grain(res: Residual, settings: DefectSettings) -> list[Defect]:
    """Ridges on the growth rings: rows that repeat each other shifted along the feed.

    :func:`oriented_coherence`: a peak at a lag other than 0 (ridges crossing the rows at an
    angle) of at least ``raised_coherence``, or any peak of at least ``raised_strong``
    (ridges almost across the feed).  Local defects correlate at lag 0 only.
    """
    coh, c0, lag = oriented_coherence(res)
    if not ((coh >= settings.raised_coherence and lag != 0 and coh - c0 >= 0.05)
            or coh >= settings.raised_strong):
        return []
    smap = res.smap
    rows = smap.valid_rows
    cols = smap.valid_cols
    # ridge height: the rms of the residual integrated along the rows, x sqrt(2)
    h = np.cumsum(res.r.astype(np.float64), axis=1) * 1000.0 / smap.cols_per_mm
    h -= h.mean(axis=1, keepdims=True)
    depth = -math.sqrt(2.0) * float(np.sqrt(np.mean(h[smap.valid] ** 2)))
    return [_defect(res, DefectKind.RAISED_GRAIN, (int(cols[0]), int(cols[-1]) + 1),
                    (int(rows[0]), int(rows[-1]) + 1), depth, min(1.0, coh))]


def pits(res: Residual, found: list[Blob], settings: DefectSettings) -> list[Defect]:
    """Compact blobs: chip marks, torn grain, fuzzy grain.

    A dent whose bottom is smooth is a chip mark (even a deep one that casts shadows), one
    with a fibrous bottom (:attr:`Blob.texture`) or a shadowed pit without a measurable
    depth torn grain, a rough patch without shadows fuzzy grain.
    """
    kept: list[tuple[DefectKind, Blob, float | None]] = []
    for b in found:
        depth: float | None = b.depth_um
        if b.rough >= settings.fuzzy_rough and b.shadow < settings.torn_shadow:
            if b.area_mm2 < settings.min_fuzzy_mm2:
                continue  # a few fibres: not a patch
            kind, depth = DefectKind.FUZZY_GRAIN, None
        elif b.depth_um >= settings.dent_um:  # a dent: a fibrous bottom is torn grain
            kind = DefectKind.TORN_GRAIN if b.texture >= settings.rough else (
                DefectKind.CHIP_MARK)
        elif b.shadow >= settings.torn_shadow:
            kind = DefectKind.TORN_GRAIN  # a pit whose depth its shadows hide
        else:
            continue  # a smooth bump or a weak dent: nothing D1666 names
        kept.append((kind, b, depth))
    return [_defect(res, kind, cols, rows, depth, _confidence(strength, settings))
            for kind, cols, rows, depth, strength in _joined_torn(res, kept, settings)]


def _joined_torn(res: Residual, kept: list[tuple[DefectKind, Blob, float | None]],
                 settings: DefectSettings) -> list[tuple[Any, ...]]:
    """Torn-grain blobs on common rows less than ``torn_gap_mm`` apart along the feed: one pit.

    A long pit's flat bottom between its walls leaves no residual, so its two ends can be two
    blobs.  Returns ``(kind, cols, rows, depth, strength)`` per defect.
    """
    gap = settings.torn_gap_mm * res.smap.cols_per_mm
    out: list[list[Any]] = []
    for kind, b, depth in sorted(kept, key=lambda k: k[1].cols[0]):
        last = next((o for o in reversed(out) if o[0] is DefectKind.TORN_GRAIN), None)
        if (kind is DefectKind.TORN_GRAIN and last is not None
                and b.cols[0] - last[1][1] <= gap
                and min(b.rows[1], last[2][1]) > max(b.rows[0], last[2][0])):
            last[1] = (last[1][0], max(last[1][1], b.cols[1]))
            last[2] = (min(last[2][0], b.rows[0]), max(last[2][1], b.rows[1]))
            last[3] = max(last[3] or 0.0, depth or 0.0)
            last[4] = max(last[4], b.strength)
            continue
        out.append([kind, b.cols, b.rows, depth, b.strength])
    return [tuple(o) for o in out]


def chatter(res: Residual, bottoms_mm: np.ndarray | None, knives: int | None,
            settings: DefectSettings) -> list[Defect]:
    """A waviness of the marks' lowest points whose period is not the revolution's.

    The marks' slope profile (the map's row mean) is integrated to the heights of the marks'
    lowest points; their *differences* from one mark to the next are fitted (the profile's
    noise integrates to a random walk, red in the heights and white in their differences),
    less each knife's mean (the runout repeats every revolution) and a linear trend (a slow
    bend: snipe, drift), with a sinusoid over periods of 2.2-16 passes away from the
    revolution's harmonics and at most 40 % of the marks seen (2.5 periods at least).  The
    amplitude of the heights is the differences' over ``2 sin(pi / period)``.
    """
    if bottoms_mm is None or knives is None or len(bottoms_mm) < 3 * knives + 3:
        return []
    smap = res.smap
    prof = res.profile
    bottoms = np.asarray(bottoms_mm, dtype=np.float64)
    basis = _chatter_basis(bottoms.size - 1, knives)
    if basis is None:
        return []
    trend, tt, waves, coef = basis
    xs = _feed_positions(prof.size, smap.col0_px, smap.col_step_px, smap.cx, smap.px_per_mm)
    # the heights at the marks' lowest points, their differences and the fit: one call
    fit = kernels.chatter_fit(prof, smap.cols_per_mm, xs,
                              np.ascontiguousarray(bottoms), knives, trend, tt, waves, coef)
    explained, amp_d, noise, amp = fit
    if amp < settings.chatter_um or explained < 0.5 or amp_d < 4.5 * noise:
        return []
    cols = smap.valid_cols
    rows = smap.valid_rows
    conf = min(1.0, explained) * min(1.0, amp / (2 * settings.chatter_um))
    return [_defect(res, DefectKind.CHATTER, (int(cols[0]), int(cols[-1]) + 1),
                    (int(rows[0]), int(rows[-1]) + 1), amp, conf)]


@functools.lru_cache(maxsize=8)
def _feed_positions(n: int, col0_px: float, col_step_px: float, cx: float,
                    px_per_mm: float) -> np.ndarray:
    """The map columns' positions along the feed as ``Measurement.x_mm`` (mm), once per grid.

    ``smap.feed_mm(np.arange(n)) + smap.cx / smap.px_per_mm`` of a map with this grid: the
    same numbers (read-only).
    """
    c = np.arange(n).astype(np.float64)
    xs = (col0_px + c * col_step_px - cx) / px_per_mm + cx / px_per_mm
    xs.flags.writeable = False
    return xs


@functools.lru_cache(maxsize=32)
def _chatter_basis(m: int, knives: int) -> tuple[Any, ...] | None:
    """The sinusoids :func:`chatter` fits to ``m`` differences (``knives`` knives), set up once.

    Each knife's mean and a linear trend removed from them as from the data; returns
    ``(trend, tt, waves, coef)`` (``tt`` the trend's square; ``waves``: the sines and cosines,
    shape (2, frequencies, m); ``coef``: rows ``f``, ``gss``, ``gsc``, ``gcc`` and ``det``,
    each frequency's normal equations' determinant floored at ``1e-18``: what
    :func:`vision.defects.kernels.chatter_fit` reads) or ``None`` without a frequency.
    """
    j = np.arange(m)
    knife = j % knives
    onehot = (knife[None, :] == np.arange(knives)[:, None]).astype(np.float64)
    per_knife = onehot / onehot.sum(axis=1, keepdims=True)  # (knives, m): each knife's mean
    trend = (j - 0.5 * (m - 1)) / m
    trend = trend - (per_knife @ trend)[knife]
    tt = float(trend @ trend)
    f = 1.0 / np.linspace(2.2, 16.0, 139)
    near = np.min(np.abs(f[:, None] - np.arange(knives + 1)[None, :] / knives), axis=1)
    # 2.5 periods at least over the marks: a longer wave is what the slow bends leave
    f = f[(near >= 0.6 / m) & (f >= 2.5 / m)]
    if f.size == 0:
        return None
    ph = 2 * np.pi * f[:, None] * (j[None, :] + 0.5)
    sn, cs = np.sin(ph), np.cos(ph)
    for b in (sn, cs):  # the same knife means and trend removed as from the data
        b -= (b @ per_knife.T)[:, knife]
        b -= np.outer(b @ trend, trend) / tt
    gss, gsc, gcc = (sn * sn).sum(1), (sn * cs).sum(1), (cs * cs).sum(1)
    det = np.maximum(gss * gcc - gsc * gsc, 1e-18)
    waves, coef = np.stack((sn, cs)), np.stack((f, gss, gsc, gcc, det))
    for a in (trend, waves, coef):
        a.flags.writeable = False
    return trend, float(trend @ trend), waves, coef


def snipe(res: Residual, pitch_mm: float | None, settings: DefectSettings) -> list[Defect]:
    """The field's height bent along the feed: concave, the cut deepening toward one end.

    The marks' slope profile is smoothed over one mark (which annihilates them) and fitted
    with ``b x + c x^2`` (its constant is the pair's imbalance, not observed); the integrated
    height's largest distance from its chord is the sag.  A concave sag (the ends lower) is
    snipe, at the end whose slope is steeper.
    """
    smap = res.smap
    prof = res.profile
    cols = smap.valid_cols
    if cols.size < 16:
        return []
    c0, c1 = int(cols[0]), int(cols[-1]) + 1
    k = 0  # no smoothing without the pitch
    if pitch_mm is not None and math.isfinite(pitch_mm) and pitch_mm > 0:
        k = max(1, int(round(pitch_mm * smap.cols_per_mm)))
    # smoothed over one mark (k < a third of the columns) and fitted: one compiled pass
    c2, c1_ = kernels.snipe_fit(prof, c0, c1, k, 1.0 / smap.cols_per_mm)
    half = 0.5 * (c1 - c0) / smap.cols_per_mm
    sag, dip = _sag_um(c1_, c2, half)  # concave: the middle above the chord
    if sag < settings.snipe_um or dip < -0.5 * sag:
        return []
    slope_ends = c1_ + 2 * c2 * np.array([-half, half])
    left = abs(slope_ends[0]) >= abs(slope_ends[1])
    rows = smap.valid_rows
    span = (c1 - c0) / 4
    cs = (c0, c0 + span) if left else (c1 - span, c1)
    conf = min(1.0, sag / (2 * settings.snipe_um))
    return [_defect(res, DefectKind.SNIPE, cs, (int(rows[0]), int(rows[-1]) + 1), sag, conf)]


def _sag_um(c1: float, c2: float, half: float) -> tuple[float, float]:
    """Largest and smallest distance above its chord of ``h = c1 x^2 / 2 + c2 x^3 / 3``, um.

    On ``[-half, half]`` (slope ``c1 x + c2 x^2``, x in mm).  ``h`` less its chord is
    ``(x^2 - half^2) (c1 / 2 + c2 x / 3)``: zero at the ends, its extremes where
    ``c2 x^2 + c1 x - c2 half^2 / 3 = 0``.
    """
    a, b = 0.5 * c1, c2 / 3.0
    points = [0.0] if b == 0 else []
    if b != 0:
        root = math.sqrt(a * a + 3.0 * b * b * half * half)
        points = [(-a + root) / (3.0 * b), (-a - root) / (3.0 * b)]
    dev = [1000.0 * (x * x - half * half) * (a + b * x) for x in points if abs(x) <= half]
    return max(dev + [0.0]), min(dev + [0.0])


def detect_defects(smap: SurfaceMap, *, bottoms_mm: np.ndarray | None = None,
                   knives: int | None = None, pitch_mm: float | None = None,
                   settings: DefectSettings | None = None) -> tuple[Defect, ...]:
    """Every detector on one pair's map.

    Parameters
    ----------
    smap : SurfaceMap
        The pair's map (:class:`vision.defects.surface_map.SurfaceMapper`).
    bottoms_mm : ndarray, optional
        The marks' lowest points (``Measurement.bottoms_mm``): chatter needs them.
    knives : int, optional
        Knives on the cutterhead: chatter needs them (the runout repeats per revolution).
    pitch_mm : float, optional
        The marks' pitch (``Measurement.pitch_mm``): snipe smooths over one mark.
    settings : DefectSettings, optional
        Thresholds.

    Returns
    -------
    tuple of Defect
        Sorted along the feed.
    """
    s = DefectSettings() if settings is None else settings
    return detect_in_residual(residual(smap, s), bottoms_mm, knives, pitch_mm, s)


def detect_in_residual(res: Residual, bottoms_mm: np.ndarray | None, knives: int | None,
                       pitch_mm: float | None, s: DefectSettings) -> tuple[Defect, ...]:
    """Every detector on one pair's residual: :func:`detect_defects` on a residual made.

    Parameters
    ----------
    res : Residual
        The pair's residual (:func:`residual` of its map with ``s``).
    bottoms_mm, knives, pitch_mm
        As :func:`detect_defects`.
    s : DefectSettings
        The settings ``res`` was made with.

    Returns
    -------
    tuple of Defect
        Sorted along the feed.
    """
    nicks, taken = knife_nicks(res, s, pitch_mm, knives)
    if taken:
        res = dataclasses.replace(res, marked=_unmark(res.marked, taken))
    raised = raised_grain(res, s)
    out = raised if raised else nicks + pits(res, blobs(res, s), s)
    if not any(d.kind in (DefectKind.RAISED_GRAIN, DefectKind.FUZZY_GRAIN) for d in out):
        out += chatter(res, bottoms_mm, knives, s)  # else the marks' profile carries them
    out += snipe(res, pitch_mm, s)
    out = [d for d in out if d.confidence >= s.min_confidence]
    return tuple(sorted(out, key=lambda d: (d.x_mm, d.y_mm)))


def _unmark(marked: np.ndarray, rows: set[int]) -> np.ndarray:
    m = marked.copy()
    for r in rows:
        lo, hi = max(0, r - 1), min(m.shape[0], r + 2)
        m[lo:hi] = False
    return m


class DefectFinder:
    """The map and the detectors of one rig and image shape (set up once).

    What :class:`vision.pipeline.Measurer` runs with ``defects=True``.

    Parameters
    ----------
    camera, lights : config.rig.Camera, config.rig.Lights
        The rig.
    shape : tuple of int
        ``(height, width)`` of the images, pixels.
    bin_rows, first_row_px, columns, source_rows
        The row bins the map is made from (:class:`vision.defects.surface_map.SurfaceMapper`).
    knives : int, optional
        Knives on the cutterhead (chatter is looked for only with them).
    settings : DefectSettings, optional
        Thresholds.
    """

    def __init__(self, camera: Camera, lights: Lights, shape: tuple[int, int], *,
                 bin_rows: int = 1, first_row_px: float | None = None,
                 columns: tuple[int, int] | None = None, source_rows: int | None = None,
                 knives: int | None = None, settings: DefectSettings | None = None) -> None:
        self.settings = DefectSettings() if settings is None else settings
        ppm = camera.px_per_mm
        merge = max(1, int(round(self.settings.row_mm * ppm / bin_rows)))
        n_src = source_rows if source_rows is not None else shape[0] // bin_rows
        merge = min(merge, max(1, n_src // 8))
        bin_cols = max(1, int(round(self.settings.col_mm * ppm)))
        # where the middle bin of an odd block alone still averages >= 3 x the pixels of a
        # 659 x 493 map's sample (2 columns x 5 rows), only it is read (1920 x 1200: 6 x 5
        # of 6 x 15 pixels, a third of the data)
        self.mapper = SurfaceMapper(camera, lights, shape, bin_rows=bin_rows,
                                    first_row_px=first_row_px, columns=columns,
                                    source_rows=source_rows, merge_rows=merge,
                                    bin_cols=bin_cols,
                                    middle_row=merge >= 3 and merge % 2 == 1
                                    and bin_rows * bin_cols >= 3 * 10)
        self.knives = knives
        kernels.warm_up()  # the detectors' loops compiled here, never on a frame

    def __call__(self, rows_a: np.ndarray, rows_b: np.ndarray, *, shift_px: float,
                 roll_deg: float, bottoms_mm: np.ndarray | None = None,
                 pitch_mm: float | None = None, encoder_shift_px: float | None = None,
                 coarse: tuple[np.ndarray | None, np.ndarray | None] | None = None
                 ) -> tuple[Defect, ...]:
        """The defects of one pair from its row bins.

        Registered at ``shift_px`` (px along the feed) with the feed at ``roll_deg``; or one
        marks' pitch off it, toward the encoder's shift (:meth:`registered`). ``coarse``: the
        map's coarse sources of A and B where already made
        (:meth:`vision.defects.surface_map.SurfaceMapper.coarse_source`).
        """
        res = self.registered(rows_a, rows_b, shift_px=shift_px, roll_deg=roll_deg,
                              pitch_mm=pitch_mm, encoder_shift_px=encoder_shift_px,
                              coarse=coarse)
        return detect_in_residual(res, bottoms_mm, self.knives, pitch_mm, self.settings)

    def residual_at(self, rows_a: np.ndarray, rows_b: np.ndarray, *, shift_px: float,
                    roll_deg: float,
                    coarse: tuple[np.ndarray | None, np.ndarray | None] | None = None
                    ) -> Residual:
        """The pair's residual registered at ``shift_px`` (its map without the albedo)."""
        return residual(self.mapper(rows_a, rows_b, shift_px=shift_px, roll_deg=roll_deg,
                                    albedo=False, coarse=coarse), self.settings)

    def registered(self, rows_a: np.ndarray, rows_b: np.ndarray, *, shift_px: float,
                   roll_deg: float, pitch_mm: float | None = None,
                   encoder_shift_px: float | None = None,
                   coarse: tuple[np.ndarray | None, np.ndarray | None] | None = None
                   ) -> Residual:
        """The pair's residual at ``shift_px``, or one marks' pitch off it toward the encoder.

        The marks repeat every pitch, so a registration can lock one pitch off the encoder's
        shift (the simulator's torn pits 0.4-1 mm deep made it: 15.0 px -> -3.7 px at a
        18.75 px pitch, within the measurer's 20 px of slip). The marks' profile is then
        right, but B's wood lies a pitch off A's: its grain does not cancel and bands of the
        field along the feed stand out (false chip marks in the columns around the pit).
        Where at least ``slip_marked`` of the cells are marked, the map is also made at
        ``shift_px +- pitch`` nearer ``encoder_shift_px`` than ``shift_px`` is, and kept where
        its cells' median mean square is below ``slip_median`` and its marked cells below
        ``slip_cells`` of the registered one's (the simulator's seven such pairs of two
        runs: medians 0.13-0.24, marked cells 0.06-0.43). Only toward the encoder, and both:
        a field of raised grain can have a lower median a pitch off (the independent
        renderer's 480 pairs of two splits mapped a pitch off their true shift: medians down
        to 0.21, five of them below 0.5 with half the cells marked; none below 0.3). A clean
        pair, or one
        without the encoder's shift or the pitch, pays nothing more.
        """
        s = self.settings
        res = self.residual_at(rows_a, rows_b, shift_px=shift_px, roll_deg=roll_deg,
                               coarse=coarse)
        if (pitch_mm is None or not math.isfinite(pitch_mm) or pitch_mm <= 0
                or encoder_shift_px is None or not math.isfinite(encoder_shift_px)):
            return res
        step = pitch_mm * res.smap.px_per_mm
        alts = [a for a in (shift_px - step, shift_px + step)
                if abs(a - encoder_shift_px) < abs(shift_px - encoder_shift_px)]
        if not alts:  # registered nearer the encoder than a pitch off either way
            return res
        n_valid = int(np.count_nonzero(res.valid_cells))
        n_marked = int(np.count_nonzero(res.marked))
        if n_valid == 0 or n_marked < s.slip_marked * n_valid:
            return res
        best = res
        ca, cb = (None, None) if coarse is None else coarse  # made once for the maps a pitch off
        coarse = (self.mapper.coarse_source(rows_a) if ca is None else ca,
                  self.mapper.coarse_source(rows_b) if cb is None else cb)
        for alt in alts:
            other = self.residual_at(rows_a, rows_b, shift_px=alt, roll_deg=roll_deg,
                                     coarse=coarse)
            if (other.median < s.slip_median * best.median
                    and np.count_nonzero(other.marked) < s.slip_cells * n_marked):
                best = other
        return best


def oriented_coherence(res: Residual, max_lag_mm: float = 2.0) -> tuple[float, float, int]:
    """How well each map row predicts the next one shifted along the feed.

    Ridges on the growth rings cross the rows at the rings' angle: row ``i + 1`` repeats row
    ``i`` shifted by ``row_step / tan(angle)``.  The residual is clipped at 4 of its robust
    scales (:attr:`Residual.scale`: a deep pit does not dominate) and the rows'
    cross-correlations summed (FFT) over the pairs of rows ``(4 i, 4 i + 1)`` (a quarter of
    the pairs: the ridges cover the field, so the peak stays far above the threshold).

    Returns
    -------
    tuple
        ``(peak correlation, correlation at lag 0, lag of the peak in map columns)``.
    """
    max_lag_px = max(2, int(round(max_lag_mm * res.smap.cols_per_mm)))
    scale = res.scale
    if not scale > 0:
        return 0.0, 0.0, 0
    # the pairs of rows (4 i, 4 i + 1): half the rows transformed, a quarter of the pairs
    pairs, size = _coherence_rows(res.r.shape[0], res.r.shape[1] + max_lag_px)
    # the rows clipped straight into the transform's zero padding, and their power
    r = np.empty((pairs.size, size), dtype=np.float32)
    r2 = np.empty(pairs.size)
    kernels.clipped_pairs(res.r, pairs, 4 * scale, r, r2)
    f = ffts.rfft(r, size, axis=1)  # scipy.fft's numbers without its dispatch
    spectrum = np.empty(f.shape[1], dtype=f.dtype)
    kernels.cross_spectrum(f, spectrum)
    x = ffts.irfft(spectrum, size)
    # the correlations over the rows' powers at lags 0 .. max_lag_px, then -max_lag_px .. -1,
    # and their peak: one compiled pass
    peak, at0, lag, ok = kernels.coherence_peak(x, r2, max_lag_px)
    if not ok:
        return 0.0, 0.0, 0
    return peak, at0, lag


@functools.lru_cache(maxsize=8)
def _coherence_rows(rows: int, length: int) -> tuple[np.ndarray, int]:
    """:func:`oriented_coherence`'s rows ``(4 i, 4 i + 1)`` of a map and its FFT length (once)."""
    first = np.arange(0, rows - 1, 4)
    pairs = np.stack([first, first + 1], axis=1).ravel()
    pairs.flags.writeable = False
    return pairs, sfft.next_fast_len(length, real=True)
