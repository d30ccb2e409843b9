"""Column profiles that leave out the rows of a defect whose shading depends on the light.

A torn-out pit, a chip mark or a tuft of raised fibres covers a few rows of every column it
crosses.  The column mean (:mod:`vision.profile`) averages its shading -- strong, and mirrored
between the two lights -- into the cuttermarks' profile: pitch and widths survive, the profile
does not.  The cuttermarks run straight across the field, so in the registered pair the
log-ratio ``log B_j(u + d) - log A_j(u)`` of every row bin ``j`` holds the same marks' shading
(the albedo cancels: the same wood in both shots); what a bin has that the others have not is a
defect.  :func:`defect_mask` finds those samples (far from the column's median, against the
noise of all bins), and :func:`masked_profiles` averages the other bins, the *same* board
samples in A and in B, so the albedo still cancels in the ratio.  A pair without such samples
is left as it is (its profiles identical to the plain column means).

Raised grain follows the growth rings across the field at an angle, so each row bin sees its
ridges a little further along the feed: no bin is clean, and the plain mean over the field's
height keeps the part of the ridges its ends cut off (the profile's correlation with the
cuttermarks 0.91 on pine with 50 um ridges at 62 deg).  When the row bins disagree beyond
their noise by more than the marks' own shading varies (:func:`ridged_rows`), the bins are
weighted by a tapered window (:func:`row_window`, the same weights in A and in B, so the
albedo still cancels): the tapered ends cut off little (0.99).  The marks run straight across
and are weighted alike; a pair whose bins agree is averaged plainly (a window weights fewer
rows: more noise).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from core.checks import check_finite, check_positive
from vision import check_kernels
from vision.profile import overlap


@dataclass(frozen=True)
class RowMask:
    """Row-bin samples of the registered pair that carry a defect (A's frame).

    Attributes
    ----------
    mask : ndarray of bool, shape (n_bins, u1 - u0)
        True where bin ``j`` at A's column ``u0 + i`` is left out.
    u0, u1 : int
        A's columns the mask covers (the overlap at the shift).
    shift_px : float
        The registration the mask was found at, pixels.
    """

    mask: np.ndarray
    u0: int
    u1: int
    shift_px: float

    @property
    def fraction(self) -> float:
        """Fraction of the overlap's samples left out."""
        return float(np.count_nonzero(self.mask)) / max(self.mask.size, 1)


TAPER = 0.5
"""Fraction of the field's height over which :func:`row_window` tapers (half at either end)."""


def row_window(n: int) -> np.ndarray:
    """Weights of ``n`` row bins: a Tukey window tapering over :data:`TAPER` of the height.

    Flat in the middle, a raised cosine over a quarter of the bins at either end, reaching
    zero one bin beyond them (a Hann window over the whole height also cancels the ridges, but
    weights fewer rows: on noisy pairs the profile lost marks).

    Returns float64, shape (n,), summing to ``n`` (the plain mean's weights sum to ``n`` too).
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n!r}")
    x = (np.arange(n) + 1.0) / (n + 1.0)
    edge = np.minimum(x, 1.0 - x) / (0.5 * TAPER)
    w = np.where(edge < 1.0, np.sin(0.5 * np.pi * np.minimum(edge, 1.0)) ** 2, 1.0)
    return w * (n / w.sum())


def weighted_profile(rows: np.ndarray, factor: int, weights: np.ndarray) -> np.ndarray:
    """The column profile of row bins weighted by ``weights`` (units of one ``k0`` bin).

    Parameters
    ----------
    rows : ndarray, shape (n_bins, width)
        :meth:`vision.front_end.FrontEnd.profile_rows`.
    factor : int
        ``k0``-row bins summed per row bin.
    weights : ndarray, shape (n_bins,)
        Summing to ``n_bins`` (:func:`row_window`).

    Returns
    -------
    ndarray, shape (width,), float64
    """
    r = np.asarray(rows)
    w = np.asarray(weights, dtype=np.float64)
    if r.ndim != 2 or w.shape != (r.shape[0],):
        raise ValueError(f"rows must be 2-D with one weight per bin, got shapes {r.shape} and "
                         f"{w.shape}")
    return (w @ r.astype(np.float64, copy=False)) / (w.sum() * factor)


def rows_disagreement(rows_a: np.ndarray, rows_b: np.ndarray, shift_px: float, u0: int,
                      u1: int) -> float:
    """How much the row bins' log-ratios disagree, beyond their noise, for the marks' shading.

    The log-ratio of every bin at the nearest column of the shift, less its column mean, on
    ~200 pairs of neighbouring columns: its mean square less the noise's (half the mean square
    of its differences within the pairs: the noise is white, a ridge's shading is not),
    rooted, over the rms of the column mean (the marks' shading).  0.0-0.6 on boards without
    defects (up to 20 DN of noise), 1.0-1.5 with pits and chips, 2.1-2.5 with raised grain at
    60-70 deg; NaN when the overlap is too small.
    """
    s, lo, hi = _columns(shift_px, u0, u1, rows_a.shape[1])
    if hi - lo < 16 or rows_a.shape[0] < 2:
        return math.nan
    # pairs of neighbouring columns, ~200 pairs over the overlap: the same statistics, at a
    # fraction of the cost on wide images
    step = _pair_step(lo, hi)
    logs = np.empty((rows_a.shape[0], 2 * ((hi - 1 - lo) // step)), dtype=np.float32)
    check_kernels.ratios_pairs(_compiled_rows(rows_a), _compiled_rows(rows_b), s, lo, step,
                               logs)
    return _disagreement(cv2.log(logs, dst=logs))


def _columns(shift_px: float, u0: int, u1: int, width: int) -> tuple[int, int, int]:
    """B's whole-column offset and A's columns ``lo .. hi - 1`` the row checks compare."""
    s = int(round(shift_px))
    return s, max(u0, -s), min(u1, width - s)


def _pair_step(lo: int, hi: int) -> int:
    """Columns between the disagreement's pairs (~200 pairs over ``lo .. hi - 1``)."""
    return max(2, (hi - lo) // 200)


def _disagreement(logs: np.ndarray) -> float:
    """:func:`rows_disagreement` from the pairs' log-ratios (NaN without marks' variance)."""
    total, noise, marks = check_kernels.disagreement_sums(logs)
    if not marks > 0:
        return math.nan
    return math.sqrt(max(total - noise, 0.0) / marks)


def _compiled_rows(rows: np.ndarray) -> np.ndarray:
    """The rows as the compiled loops take them: C-ordered ``uint16`` or ``float32``.

    As they come (no copy) when they are; else copied (the loops are compiled for these
    layouts only, at set-up).
    """
    r = np.asarray(rows)
    if r.dtype not in (np.uint16, np.float32):
        r = r.astype(np.float32)
    return np.ascontiguousarray(r)


RIDGED = 1.0
"""Row bins disagreeing by more than this (:func:`rows_disagreement`) are weighted."""


def ridged_rows(width: int, rows_a: np.ndarray, rows_b: np.ndarray, shift_px: float,
                margin: int, *, threshold: float = RIDGED) -> np.ndarray | None:
    """The row bins' weights when they disagree (:func:`rows_disagreement` > ``threshold``).

    Returns :func:`row_window` of the bins, or ``None`` (the plain mean) when they agree.
    """
    u0, u1 = overlap(width, shift_px, columns=(margin, width - margin))
    if not rows_disagreement(rows_a, rows_b, shift_px, u0, u1) > threshold:
        return None
    return row_window(rows_a.shape[0])


def _log_rows(rows: np.ndarray) -> np.ndarray:
    r = np.asarray(rows, dtype=np.float32)
    return cv2.log(np.maximum(r, np.float32(0.5)))


def registered_rows(rows: np.ndarray, shift_px: float, u0: int, u1: int) -> np.ndarray:
    """Rows sampled at ``u0 + d .. u1 - 1 + d`` by Keys' cubic (as :func:`shift_profile`).

    Indices beyond the rows repeat the edge column.  Returns float64, shape (n, u1 - u0).
    """
    r = np.asarray(rows, dtype=np.float64)
    base = math.floor(shift_px)
    t = shift_px - base
    a = -0.5
    s = 1.0 - t
    weights = (a * t * (t - 1) ** 2, (a + 2) * t**3 - (a + 3) * t**2 + 1,
               (a + 2) * s**3 - (a + 3) * s**2 + 1, a * s * (s - 1) ** 2)
    cols = np.arange(u0, u1) + base
    w = r.shape[1]
    out = np.zeros((r.shape[0], u1 - u0))
    for k, wk in enumerate(weights):
        if wk != 0.0:
            out += wk * r[:, np.clip(cols + k - 1, 0, w - 1)]
    return out


def _screened(a: np.ndarray, b: np.ndarray, d: float, u0: int, u1: int, limit: float,
              min_run_px: int, min_samples: int) -> bool:
    """Whether any run of samples departs from its column's mean by ``limit`` mean deviations.

    B's rows are taken at the nearest column (the cusps' sharp steps half a pixel off are
    single columns, which the run length drops), every second column; ``float32``, the
    departures and their runs in one compiled pass (:func:`vision.check_kernels.screen_hits`).
    """
    s, lo, hi = _columns(d, u0, u1, a.shape[1])
    if hi - lo < 16:
        return True
    # every second column: a run of min_run_px columns still shows as half as many samples
    ratio = np.empty((a.shape[0], (hi - lo + 1) // 2), dtype=np.float32)
    check_kernels.ratios_every_second(_compiled_rows(a), _compiled_rows(b), s, lo, ratio)
    return _screen_hit(cv2.log(ratio, dst=ratio), limit, min_run_px, min_samples)


def _screen_hit(logs: np.ndarray, limit: float, min_run_px: int, min_samples: int) -> bool:
    """:func:`_screened` from the log-ratios at every second column."""
    # 0.8: mean |x| of a unit normal
    return bool(check_kernels.screen_hits(logs, limit * 0.8, max(1, (min_run_px + 1) // 2),
                                          (min_samples + 1) // 2))


THRESHOLD = 6.0
"""Default of :func:`defect_mask`'s ``threshold`` (robust standard deviations)."""
MIN_RUN_PX = 5
"""Default of :func:`defect_mask`'s ``min_run_px``."""
MIN_SAMPLES = 4
"""Default of :func:`defect_mask`'s ``min_samples``."""


def defect_mask(rows_a: np.ndarray, rows_b: np.ndarray, shift_px: float, *, u0: int, u1: int,
                threshold: float = THRESHOLD, floor: float = 0.02, grow_px: int = 3,
                weak_fraction: float = 0.4, min_run_px: int = MIN_RUN_PX,
                min_samples: int = MIN_SAMPLES, screen: float = 1.0) -> RowMask | None:
    """The row-bin samples whose log-ratio departs from their column's (a defect's shading).

    Parameters
    ----------
    rows_a, rows_b : ndarray, shape (n_bins, width)
        The profile's row bins of A and of B (:meth:`vision.front_end.FrontEnd.profile_rows`),
        both at the marks' direction.
    shift_px : float
        Registered shift, pixels: A's column ``u`` is B's ``u + shift_px``.
    u0, u1 : int
        A's columns to judge (B's ``u0 + shift_px .. u1 + shift_px + 1`` must exist).
    threshold : float, optional
        A sample is a defect's when its log-ratio is more than this many robust standard
        deviations (of all bins' departures) from its column's median.
    floor : float, optional
        ...and more than this (natural log units) from it.
    weak_fraction : float, optional
        Samples above this fraction of the limit that touch the samples found are the
        defect's too (its fainter rim).
    grow_px : int, optional
        The samples found are grown by this many columns either way (a defect's soft edges).
    min_run_px : int, optional
        Only runs of at least this many columns count (a defect spans columns; a cusp's sharp
        step seen through a slightly wrong shear is a column or two).
    min_samples : int, optional
        Fewer samples found are taken for noise (``None`` returned).
    screen : float, optional
        First a cheap screen (:func:`_screened`, the departures from the column's *mean* at
        ``screen * threshold`` times their mean absolute value, B at the nearest column): a
        pair it passes is left as it is without the median's cost (every clean pair).

    Returns
    -------
    RowMask or None
        ``None`` when there are fewer than 3 bins or no defect is found.
    """
    a = np.asarray(rows_a)
    b = np.asarray(rows_b)
    if a.ndim != 2 or a.shape != b.shape:
        raise ValueError(f"rows_a and rows_b must be 2-D of one shape, got {a.shape}, {b.shape}")
    d = check_finite("shift_px", shift_px)
    check_positive("threshold", threshold)
    n, w = a.shape
    if not 0 <= u0 < u1 <= w:
        raise ValueError(f"columns {u0}..{u1} must lie within the rows ({w} wide)")
    if n < 3 or not _screened(a, b, d, u0, u1, screen * threshold, min_run_px, min_samples):
        return None
    return _mask(a, b, d, u0, u1, threshold=threshold, floor=floor, grow_px=grow_px,
                 weak_fraction=weak_fraction, min_run_px=min_run_px, min_samples=min_samples)


def _mask(a: np.ndarray, b: np.ndarray, d: float, u0: int, u1: int, *, threshold: float,
          floor: float = 0.02, grow_px: int = 3, weak_fraction: float = 0.4,
          min_run_px: int = MIN_RUN_PX, min_samples: int = MIN_SAMPLES) -> RowMask | None:
    """:func:`defect_mask` of rows its screen did not pass (the medians' statistics)."""
    n = a.shape[0]
    ratio = _log_rows(registered_rows(b, d, u0, u1)) - _log_rows(a[:, u0:u1])
    dev = ratio - np.median(ratio, axis=0)[None, :]
    mag = np.abs(dev)
    sigma = 1.4826 * float(np.median(mag))
    limit = max(threshold * sigma, floor)
    hits = (mag > limit).astype(np.uint8)
    if min_run_px > 1:  # a defect spans columns; a sharp cusp off by a little shear does not
        hits = cv2.morphologyEx(hits, cv2.MORPH_OPEN, np.ones((1, min_run_px), np.uint8))
    if np.count_nonzero(hits) < min_samples:
        return None
    # the defect's fainter rim: samples above the weak limit connected to it (hysteresis)
    weak = (mag > weak_fraction * limit).astype(np.uint8)
    cross = np.ones((3, 3), np.uint8)
    for _ in range(2 * n):
        grown = cv2.dilate(hits, cross)
        np.bitwise_and(grown, weak, out=grown)
        np.bitwise_or(grown, hits, out=grown)
        if np.array_equal(grown, hits):
            break
        hits = grown
    if grow_px > 0:
        hits = cv2.dilate(hits, np.ones((1, 2 * grow_px + 1), np.uint8))
    return RowMask(hits.astype(bool), int(u0), int(u1), d)


def masked_pair(rows_a: np.ndarray, rows_b: np.ndarray, factor: int, mask: RowMask, *,
                min_kept: float = 0.3, weights: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Column profiles of A and of B registered onto A, from the row bins the mask keeps.

    The same board samples enter both (B's rows resampled at ``u + shift_px`` before they are
    averaged), so the albedo cancels in their ratio as in the plain column means.

    Parameters
    ----------
    rows_a, rows_b : ndarray, shape (n_bins, width)
        The profile's row bins of A and B.
    factor : int
        ``k0``-row bins per row bin (the profile is in units of one ``k0``-row bin).
    mask : RowMask
        From :func:`defect_mask` on these rows.
    min_kept : float, optional
        A column that keeps fewer than this fraction of its bins keeps those nearest its
        median instead (that fraction of them).
    weights : ndarray, shape (n_bins,), optional
        The bins' weights (:func:`ridged_rows`; default: alike).

    Returns
    -------
    profile_a, profile_b : ndarray, shape (width,), float64
        A's profile and B's at ``u + shift_px``, both in A's columns (outside the mask's
        columns every bin; B's edge columns repeated beyond its end).
    """
    a = np.asarray(rows_a, dtype=np.float64)
    n, w = a.shape
    b = registered_rows(rows_b, mask.shift_px, 0, w)
    keep = np.ones((n, w))
    keep[:, mask.u0:mask.u1] = ~mask.mask
    few = keep.sum(axis=0) < max(1.0, min_kept * n)
    if np.any(few):  # the bins whose log-ratio lies nearest the column's median
        ratio = _log_rows(b[:, few]) - _log_rows(a[:, few])
        dist = np.abs(ratio - np.median(ratio, axis=0)[None, :])
        rank = np.argsort(np.argsort(dist, axis=0), axis=0)
        keep[:, few] = rank < max(1, math.ceil(min_kept * n))
    if weights is not None:
        keep *= np.asarray(weights, dtype=np.float64)[:, None]
    total = keep.sum(axis=0) * factor
    return (keep * a).sum(axis=0) / total, (keep * b).sum(axis=0) / total


def clean_columns(mask: RowMask, *, min_kept: float = 0.5, min_width: int = 1
                  ) -> tuple[int, int] | None:
    """The longest run of A's columns in which every column keeps most of its row bins.

    A pit across the feed can cover most of the field's height: its columns have no clean
    rows to average, and whatever is kept there is the pit's.  The measurement then uses only
    the longest stretch of the overlap free of such columns, when it is still wide enough.

    Parameters
    ----------
    mask : RowMask
        From :func:`defect_mask`.
    min_kept : float, optional
        A column keeping fewer than this fraction of its bins is the defect's.
    min_width : int, optional
        Narrower stretches are not used (``None`` returned).

    Returns
    -------
    tuple of int or None
        ``(c0, c1)``: A's columns ``c0 .. c1 - 1``; ``None`` when every column keeps enough
        bins (the whole overlap is clean) or the longest stretch is narrower than ``min_width``.
    """
    n = mask.mask.shape[0]
    bad = np.count_nonzero(~mask.mask, axis=0) < min_kept * n
    if not bad.any():
        return None
    edges = np.flatnonzero(np.diff(np.concatenate([[1], bad.astype(np.int8), [1]])))
    starts, stops = edges[0::2], edges[1::2]  # runs of clean columns
    if starts.size == 0:
        return None
    k = int(np.argmax(stops - starts))
    if stops[k] - starts[k] < min_width:
        return None
    return mask.u0 + int(starts[k]), mask.u0 + int(stops[k])


def row_checks(width: int, rows_a: np.ndarray, rows_b: np.ndarray, shift_px: float,
               margin: int) -> tuple[RowMask | None, np.ndarray | None]:
    """:func:`defect_rows` and :func:`ridged_rows` of one pair at one shift, in one call.

    The overlap is found once, and the intensity ratios of the screen (every second column)
    and of the disagreement (pairs of neighbouring columns) come from one compiled pass over
    the rows (:func:`vision.check_kernels.check_ratios`: every column's ratio once, both
    samplings picked from it; the same values, logs and statistics as the two functions
    compute).

    Returns
    -------
    mask : RowMask or None
        :func:`defect_rows`.
    weights : ndarray or None
        :func:`ridged_rows` (at its default threshold).
    """
    u0, u1 = overlap(width, shift_px, columns=(margin, width - margin))
    a, b = np.asarray(rows_a), np.asarray(rows_b)
    if a.ndim != 2 or a.shape != b.shape:
        raise ValueError(f"rows_a and rows_b must be 2-D of one shape, got {a.shape}, {b.shape}")
    d = check_finite("shift_px", shift_px)
    n, w = a.shape
    s, lo, hi = _columns(d, u0, u1, w)
    if n < 3 or u1 - u0 < 16 or hi - lo < 16 or not 0 <= u0 < u1 <= w:
        # small or odd cases: the two functions as they are
        return (defect_rows(width, a, b, d, margin),
                ridged_rows(width, a, b, d, margin))
    step = _pair_step(lo, hi)
    screen = np.empty((n, (hi - lo + 1) // 2), dtype=np.float32)
    pairs = np.empty((n, 2 * ((hi - 1 - lo) // step)), dtype=np.float32)
    check_kernels.check_ratios(_compiled_rows(a), _compiled_rows(b), s, lo, step, screen,
                               pairs)
    mask = None
    if _screen_hit(cv2.log(screen, dst=screen), THRESHOLD, MIN_RUN_PX, MIN_SAMPLES):
        mask = _mask(a, b, d, u0, u1, threshold=THRESHOLD)
    ridged = _disagreement(cv2.log(pairs, dst=pairs)) > RIDGED
    return mask, (row_window(n) if ridged else None)


def defect_rows(width: int, rows_a: np.ndarray, rows_b: np.ndarray, shift_px: float,
                margin: int) -> RowMask | None:
    """:func:`defect_mask` over the overlap the measurement uses at ``shift_px`` (see there)."""
    u0, u1 = overlap(width, shift_px, columns=(margin, width - margin))
    if u1 - u0 < 16:
        return None
    return defect_mask(rows_a, rows_b, shift_px, u0=u0, u1=u1)
