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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from core.checks import check_finite, check_positive
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
    single columns, which the run length drops), every second column; ``float32`` and OpenCV
    throughout.
    """
    w = a.shape[1]
    s = int(round(d))
    lo, hi = max(u0, -s), min(u1, w - s)
    if hi - lo < 16:
        return True
    # every second column: a run of min_run_px columns still shows as half as many samples
    la = cv2.log(np.maximum(a[:, lo:hi:2].astype(np.float32), np.float32(0.5)))
    lb = cv2.log(np.maximum(b[:, lo + s: hi + s: 2].astype(np.float32), np.float32(0.5)))
    ratio = cv2.subtract(lb, la)
    mean = cv2.reduce(ratio, 0, cv2.REDUCE_AVG)
    mag = cv2.absdiff(ratio, np.repeat(mean, ratio.shape[0], axis=0))
    scale = float(cv2.mean(mag)[0])
    hits = (mag > limit * 0.8 * scale).astype(np.uint8)  # 0.8: mean |x| of a unit normal
    run = (min_run_px + 1) // 2
    if run > 1:
        hits = cv2.morphologyEx(hits, cv2.MORPH_OPEN, np.ones((1, run), np.uint8))
    return cv2.countNonZero(hits) >= (min_samples + 1) // 2


def defect_mask(rows_a: np.ndarray, rows_b: np.ndarray, shift_px: float, *, u0: int, u1: int,
                threshold: float = 6.0, floor: float = 0.02, grow_px: int = 3,
                weak_fraction: float = 0.4, min_run_px: int = 5, min_samples: int = 4,
                screen: float = 1.0) -> RowMask | None:
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
                min_kept: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
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

    Returns
    -------
    profile_a, profile_b : ndarray, shape (width,), float64
        A's profile and B's at ``u + shift_px``, both in A's columns (outside the mask's
        columns the plain means; B's edge columns repeated beyond its end).
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
    total = keep.sum(axis=0) * factor
    return (keep * a).sum(axis=0) / total, (keep * b).sum(axis=0) / total


def defect_rows(width: int, rows_a: np.ndarray, rows_b: np.ndarray, shift_px: float,
                margin: int) -> RowMask | None:
    """:func:`defect_mask` over the overlap the measurement uses at ``shift_px`` (see there)."""
    u0, u1 = overlap(width, shift_px, columns=(margin, width - margin))
    if u1 - u0 < 16:
        return None
    return defect_mask(rows_a, rows_b, shift_px, u0=u0, u1=u1)
