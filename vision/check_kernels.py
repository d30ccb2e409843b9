"""Compiled loops (numba) for the measurement's own checks (each a chain of small numpy calls).

The checks that keep defect boards honest (:mod:`vision.registration.consistency`,
:mod:`vision.registration.defect_rows`,
the roll estimate's clip in :mod:`vision.orientation`) run on every pair; as numpy chains they
cost about a third of a clean pair's measurement, most of it call overhead and temporaries.
The loops here compute the same statistics in one or two calls each:

* :func:`ratios_every_second`, :func:`ratios_pairs` -- the row bins' intensity ratio
  ``B_j(c + s) / A_j(c)`` at every second column or at pairs of neighbouring columns (the log
  then by one ``cv2.log`` of the whole block, vectorised, which numba's scalar ``log`` is not);
  :func:`check_ratios` both from one pass (every column's ratio once);
* :func:`screen_hits` -- the defect screen's departures from the column means and their runs
  along the rows;
* :func:`disagreement_sums` -- the row bins' disagreement from pairs of neighbouring columns;
* :func:`marks_agreement` -- the marks' kinematic slope against both log-profiles, a cubic
  removed (its normal equations, as
  :func:`vision.registration.consistency.marks_shading_agreement`);
  :func:`marks_agreement_slow_removed` the same after :func:`without_slow` (the log-profiles'
  running mean over 8 marks removed), in one call;
* :func:`clip_robust` -- the clip of high-passed rows at a multiple of their robust deviation.

Compiled with ``cache=True`` and warmed up beside :func:`vision.kernels.warm_up` (a measurer's
set-up), never on a frame.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from vision.kernels import running_mean_2d, solve_small

_JIT = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}


# reassociation lets the sums vectorise (statistics against thresholds: their last bits do not
# matter); no finite-math assumptions (a NaN stays a NaN)
_SUMS = {**_JIT, "fastmath": {"reassoc", "nsz", "arcp", "contract"}}


@njit(**_SUMS)
def ratios_every_second(rows_a: np.ndarray, rows_b: np.ndarray, shift: int, lo: int,
                        out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``out[j, k] = max(B[j, c + shift], 0.5) / max(A[j, c], 0.5)``, ``c = lo + 2 k`` (float32).

    ``out`` has shape ``(n_bins, m)``; ``A``'s columns ``lo .. lo + 2 (m - 1)`` and ``B``'s
    ``shift`` further must exist.
    """
    half = np.float32(0.5)
    m = out.shape[1]
    for j in range(rows_a.shape[0]):
        ra = rows_a[j, lo:]
        rb = rows_b[j, lo + shift:]
        o = out[j]
        for k in range(m):  # the literal stride vectorises (a stride argument does not)
            o[k] = max(np.float32(rb[2 * k]), half) / max(np.float32(ra[2 * k]), half)


@njit(**_SUMS)
def ratios_pairs(rows_a: np.ndarray, rows_b: np.ndarray, shift: int, lo: int, step: int,
                 out: np.ndarray) -> None:  # pragma: no cover - compiled
    """The ratios (as :func:`ratios_every_second`) at pairs of neighbouring columns.

    ``out`` has shape ``(n_bins, 2 m)``: columns ``c_k = lo + k step`` in ``0 .. m - 1``,
    ``c_k + 1`` in ``m .. 2 m - 1``.
    """
    half = np.float32(0.5)
    m = out.shape[1] // 2
    for j in range(rows_a.shape[0]):
        ra = rows_a[j]
        rb = rows_b[j]
        o = out[j]
        for k in range(m):
            c = lo + k * step
            o[k] = max(np.float32(rb[c + shift]), half) / max(np.float32(ra[c]), half)
            o[m + k] = (max(np.float32(rb[c + 1 + shift]), half)
                        / max(np.float32(ra[c + 1]), half))


@njit(**_SUMS)
def check_ratios(rows_a: np.ndarray, rows_b: np.ndarray, shift: int, lo: int, step: int,
                 screen: np.ndarray, pairs: np.ndarray) -> None:  # pragma: no cover - compiled
    """:func:`ratios_every_second` into ``screen`` and :func:`ratios_pairs` into ``pairs``.

    Every column's ratio ``max(B[j, c + shift], 0.5) / max(A[j, c], 0.5)`` over the span
    both need is computed once per row (a contiguous, vectorised loop) and both samplings
    are picked from it: the same float32 values as the two loops give.
    """
    half = np.float32(0.5)
    m2 = screen.shape[1]
    m = pairs.shape[1] // 2
    span = 2 * m2 - 1
    if m > 0:
        span = max(span, (m - 1) * step + 2)
    full = np.empty(max(span, 0), dtype=np.float32)
    for j in range(rows_a.shape[0]):
        ra = rows_a[j, lo:lo + span]
        rb = rows_b[j, lo + shift:lo + shift + span]
        for c in range(span):
            full[c] = max(np.float32(rb[c]), half) / max(np.float32(ra[c]), half)
        o = screen[j]
        for k in range(m2):
            o[k] = full[2 * k]
        p = pairs[j]
        for k in range(m):
            p[k] = full[k * step]
            p[m + k] = full[k * step + 1]


@njit(**_SUMS)
def screen_hits(ratio: np.ndarray, limit: float, run: int, needed: int
                ) -> bool:  # pragma: no cover - compiled
    """Whether ``needed`` samples lie in runs of ``run`` departing from their column's mean.

    A sample departs when ``|r - mean(column)| > limit * mean |r - mean(column)|`` (the mean
    over every sample); runs are along the rows (an opening by a ``1 x run`` line, counted).
    """
    n, m = ratio.shape
    mean = np.zeros(m, dtype=np.float32)
    for j in range(n):
        row = ratio[j]
        for k in range(m):
            mean[k] += row[k]
    inv = np.float32(1.0 / n)
    for k in range(m):
        mean[k] *= inv
    total = 0.0
    for j in range(n):
        row = ratio[j]
        part = np.float32(0.0)
        for k in range(m):
            part += abs(row[k] - mean[k])
        total += part
    level = np.float32(limit * total / (n * m))
    flags = np.empty((n, m), dtype=np.uint8)
    row_hits = np.zeros(n, dtype=np.int64)
    for j in range(n):
        row = ratio[j]
        f = flags[j]
        for k in range(m):
            f[k] = abs(row[k] - mean[k]) > level
        h = 0
        for k in range(m):
            h += f[k]
        row_hits[j] = h
    if row_hits.sum() < needed:  # the runs hold fewer
        return False
    # the opening by a 1 x run line, row by row, as byte operations (vectorised): an erosion
    # (every sample of a window departs), then a dilation (the samples of such windows)
    span = m - run + 1
    ero = np.empty(max(span, 0), dtype=np.uint8)
    dil = np.empty(m, dtype=np.uint8)
    count = 0
    for j in range(n):
        if row_hits[j] < run or span <= 0:  # no run in this row
            continue
        f = flags[j]
        for k in range(span):
            ero[k] = f[k]
        for r in range(1, run):
            for k in range(span):
                ero[k] &= f[k + r]
        dil[:] = 0
        for r in range(run):
            for k in range(span):
                dil[k + r] |= ero[k]
        for k in range(m):
            count += dil[k]
        if count >= needed:
            return True
    return False


@njit(**_SUMS)
def disagreement_sums(logs: np.ndarray) -> tuple[float, float, float]:  # pragma: no cover
    """Mean square of the bins' departures, the noise's share of it and the marks' variance.

    ``logs`` (shape ``(n_bins, 2 m)``) holds the log-ratios of the pairs' first columns
    (``0 .. m - 1``) and of their second columns (``m .. 2 m - 1``).  Returns
    ``(total, noise, marks)``: the mean of the squared departures from each column's mean,
    half the mean square of the departures' differences within the pairs, the variance of
    the column means.
    """
    n, w = logs.shape
    pairs = w // 2
    mean = np.zeros(w)
    for j in range(n):
        row = logs[j]
        for k in range(w):
            mean[k] += row[k]
    for k in range(w):
        mean[k] /= n
    total = 0.0
    noise = 0.0
    for j in range(n):
        row = logs[j]
        for k in range(pairs):
            d0 = row[k] - mean[k]
            d1 = row[pairs + k] - mean[pairs + k]
            total += d0 * d0 + d1 * d1
            noise += (d1 - d0) * (d1 - d0)
    mu = 0.0
    for k in range(w):
        mu += mean[k]
    mu /= w
    marks = 0.0
    for k in range(w):
        marks += (mean[k] - mu) * (mean[k] - mu)
    return total / (n * w), 0.5 * noise / (n * pairs), marks / w


@njit(**_JIT)
def marks_agreement(la: np.ndarray, lb: np.ndarray, x: np.ndarray, cusps: np.ndarray,
                    bottoms: np.ndarray, max_samples: int
                    ) -> tuple[float, float]:  # pragma: no cover - compiled
    """``(-corr(la, p), corr(lb, p))`` inside the marks, a cubic in ``x`` removed from each.

    As :func:`vision.registration.consistency.marks_shading_agreement` (its validated arguments):
    ``p`` is
    ``x - b_k`` in mark ``k`` (a position on a cusp belongs to the mark after it), the samples
    inside ``cusps[0] .. cusps[-1]`` with a mark, every ``k``-th of them (at most
    ``max_samples``); NaN for fewer than 16 samples or a residual without variance.
    """
    nan = (np.nan, np.nan)
    c_lo, c_hi = cusps[0], cusps[-1]
    m = bottoms.size
    idx = np.empty(x.size, dtype=np.int64)
    pv = np.empty(x.size)
    inside = 0
    ok = 0
    k = -1  # the mark of the last sample: cusps[k] <= x < cusps[k + 1]
    last = -np.inf
    for i in range(x.size):
        xi = x[i]
        if not (xi >= c_lo and xi <= c_hi):
            continue
        inside += 1
        if xi >= last:  # increasing positions: walk on (else search afresh)
            while k + 1 < cusps.size and cusps[k + 1] <= xi:
                k += 1
        else:
            k = np.searchsorted(cusps, xi, side="right") - 1
        last = xi
        if 0 <= k < m:
            p = xi - bottoms[k]
            if np.isfinite(p):
                idx[ok] = i
                pv[ok] = p
                ok += 1
    if inside < 16 or ok < 16:
        return nan
    step = max(1, -(-ok // max_samples))
    first, last = x[idx[0]], x[idx[((ok - 1) // step) * step]]
    mid = 0.5 * (first + last)
    half = max(0.5 * (last - first), 1e-9)
    # the normal equations from power sums: sum t^e (e = 0..6) and sum t^e y (e = 0..3)
    pw = np.zeros(7)
    ty = np.zeros((3, 4))
    for s in range(0, ok, step):
        t = (x[idx[s]] - mid) / half
        t2 = t * t
        t3 = t2 * t
        pw[1] += t
        pw[2] += t2
        pw[3] += t3
        pw[4] += t2 * t2
        pw[5] += t3 * t2
        pw[6] += t3 * t3
        pw[0] += 1.0
        y0, y1, y2 = pv[s], la[idx[s]], lb[idx[s]]
        ty[0, 0] += t3 * y0
        ty[0, 1] += t2 * y0
        ty[0, 2] += t * y0
        ty[0, 3] += y0
        ty[1, 0] += t3 * y1
        ty[1, 1] += t2 * y1
        ty[1, 2] += t * y1
        ty[1, 3] += y1
        ty[2, 0] += t3 * y2
        ty[2, 1] += t2 * y2
        ty[2, 2] += t * y2
        ty[2, 3] += y2
    gram = np.empty((3, 4, 4))
    for r in range(4):
        for c in range(4):
            gram[0, r, c] = pw[6 - r - c]  # basis (t^3, t^2, t, 1)
    gram[1] = gram[0]
    gram[2] = gram[0]
    rhs = ty
    if not solve_small(gram, rhs):
        return nan
    sxx = np.zeros(3)
    sxy = np.zeros(2)
    for s in range(0, ok, step):
        t = (x[idx[s]] - mid) / half
        r0 = pv[s] - (((rhs[0, 0] * t + rhs[0, 1]) * t + rhs[0, 2]) * t + rhs[0, 3])
        r1 = la[idx[s]] - (((rhs[1, 0] * t + rhs[1, 1]) * t + rhs[1, 2]) * t + rhs[1, 3])
        r2 = lb[idx[s]] - (((rhs[2, 0] * t + rhs[2, 1]) * t + rhs[2, 2]) * t + rhs[2, 3])
        sxx[0] += r0 * r0
        sxx[1] += r1 * r1
        sxx[2] += r2 * r2
        sxy[0] += r1 * r0
        sxy[1] += r2 * r0
    norms = np.sqrt(sxx)
    if not (norms[0] > 0 and norms[1] > 0 and norms[2] > 0):
        return nan
    return -sxy[0] / (norms[0] * norms[1]), sxy[1] / (norms[0] * norms[2])


@njit(**_JIT)
def without_slow(la: np.ndarray, lb: np.ndarray, x: np.ndarray, cusps: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Both log-profiles less their running mean over 8 marks (held at its ends' values).

    :func:`vision.registration.consistency._without_slow` compiled: the same running mean
    (:func:`vision.kernels.running_mean_2d` of the two as columns) and the same arithmetic, so
    the same values; the profiles themselves (new arrays) when there is no such mean.
    """
    n = la.size
    if cusps.size < 2 or n < 2 or not x[-1] > x[0]:
        return la.copy(), lb.copy()
    length = 8.0 * (cusps[-1] - cusps[0]) / (cusps.size - 1) / ((x[-1] - x[0]) / (n - 1))
    if not (length >= 1.0 and length <= n):
        return la.copy(), lb.copy()
    both = np.empty((n, 2))
    for i in range(n):
        both[i, 0] = la[i]
        both[i, 1] = lb[i]
    mean = running_mean_2d(both, length)
    m = mean.shape[0]
    if m < 1:
        return la.copy(), lb.copy()
    lead = (n - m) // 2
    out_a = np.empty(n)
    out_b = np.empty(n)
    for i in range(n):
        j = min(max(i - lead, 0), m - 1)  # the mean held at its ends' values
        out_a[i] = both[i, 0] - mean[j, 0]
        out_b[i] = both[i, 1] - mean[j, 1]
    return out_a, out_b


@njit(**_JIT)
def marks_agreement_slow_removed(la: np.ndarray, lb: np.ndarray, x: np.ndarray,
                                 cusps: np.ndarray, bottoms: np.ndarray, max_samples: int
                                 ) -> tuple[float, float]:  # pragma: no cover - compiled
    """:func:`marks_agreement` of the log-profiles after :func:`without_slow`, in one call."""
    sa, sb = without_slow(la, lb, x, cusps)
    return marks_agreement(sa, sb, x, cusps, bottoms, max_samples)


@njit(**_JIT)
def clip_robust(values: np.ndarray, step: int, sigmas: float) -> float:  # pragma: no cover
    """Clip ``values`` (float32, 2-D, C order) in place at ``sigmas`` robust standard deviations.

    The deviation is ``1.4826`` times the median of ``|v|`` over every ``step``-th value of the
    flattened array; nothing is clipped when it is 0.  Returns the clip level.
    """
    flat = values.reshape(-1)
    n = (flat.size + step - 1) // step
    sample = np.empty(n, dtype=flat.dtype)
    for i in range(n):
        sample[i] = abs(flat[i * step])
    limit = sigmas * 1.4826 * float(np.median(sample))
    if limit > 0:
        hi = np.float32(limit)  # as np.clip with a Python float: the bound in float32
        lo = -hi
        for i in range(flat.size):
            v = flat[i]
            if v > hi:
                flat[i] = hi
            elif v < lo:
                flat[i] = lo
    return limit


def warm_up() -> None:
    """Compile (or load from the cache) the kernels for the types the checks pass."""
    ratio = np.ones((3, 4), dtype=np.float32)
    for dtype in (np.uint16, np.float32):
        rows = np.ones((3, 12), dtype=dtype)
        ratios_every_second(rows, rows, 1, 0, ratio)
        ratios_pairs(rows, rows, 1, 0, 3, ratio)
        check_ratios(rows, rows, 1, 0, 3, ratio, ratio)
    screen_hits(ratio, 4.8, 2, 2)
    disagreement_sums(ratio)
    x = np.arange(40.0)
    marks_agreement(x, x, x, np.array([0.0, 20.0, 39.0]), np.array([10.0, 30.0]), 700)
    marks_agreement_slow_removed(x, x, x, np.array([0.0, 20.0, 39.0]), np.array([10.0, 30.0]),
                                 700)
    clip_robust(np.ones((2, 4), dtype=np.float32), 1, 3.0)
