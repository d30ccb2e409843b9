"""Compiled loops (numba) for the per-pair steps that are many small numpy calls otherwise.

A pair's measurement at 659 x 493 is about a millisecond, and most of it was Python and numpy
call overhead on short 1-D arrays, not arithmetic.  The loops here fuse such chains into one
call each, with the arithmetic of the numpy code they replace (same order of the sums where
the result must not move, e.g. integer sums and sequential cumulative sums):

* :func:`bin_rows` -- an 8-bit image summed into ``k``-row bins, those summed ``m`` at a time
  over a band, and that band's column sums, in one pass over the image;
* :func:`group_sums` -- groups of adjacent ``uint16`` bins summed in the output's dtype: the
  orientation's groups (``float32``) and the unsheared profile's bins (``uint16``), one kernel;
* :func:`column_sums` -- the column sums of ``uint16`` rows (the profile's), exact;
* :func:`rows_over` -- ``uint16`` rows divided by their means (the rotated texture's);
* :func:`scaled_less_one` -- rows times a column scale, less one (the shading-free texture);
* :func:`inverse_column_means` -- the inverse of rows' column means (the rotated texture's);
* :func:`running_mean_1d`, :func:`running_mean_2d` -- running means of fractional length
  (cumulative sums and linear interpolation, as
  :func:`vision.calibration.illumination.running_mean`);
* :func:`cusp_candidates` -- the candidate cusps of :func:`vision.marks.find_marks` and the
  slope's noise;
* :func:`smooth_trend` -- the illumination polynomial fitted to running means;
* :func:`arc_model` -- the arc model of :mod:`vision.marks` (cusps and bottoms refined);
* :func:`spectrum_peak`, :func:`smooth5`, :func:`repeat_lag` -- the steps of
  :func:`vision.marks.repeat_period_px` between its FFTs;
* :func:`arc_slopes` -- the kinematic slope of a chain of arcs;
* :func:`delay_scores` -- the fine registration's scores of its grid of delays;
* :func:`solve_small` -- a batch of small dense linear systems (partial pivoting);
* :func:`blur_fits` -- the self-calibration's normal equations and their fits;
* :func:`model_span` -- the span of the kinematic slope the self-calibration fits over;
* :func:`wiener_terms` -- the scattering deblur's transfer function and Wiener denominator;
* :func:`ratio_slope` -- the slope from the intensity ratio (seed Eq. 4) and its finiteness;
* :func:`power_spectrum` -- ``|X|^2`` of a complex spectrum (real and imaginary squared);
* :func:`any_nonpositive` -- whether two profiles hold a sample ``<= 0``;
* :func:`knife_sums` -- a per-mark quantity summed per knife, in the marks' order;
* :func:`arc_depths` -- the marks' kinematic depths from their cusps and lowest points;
* :func:`cubic_shift` -- a profile resampled by Keys' cubic at a fractional offset;
* :func:`feed_positions` -- the registered profile's positions along the feed, mm;
* :func:`all_finite` -- whether two arrays hold only finite numbers;
* :func:`less_running` -- a height less its running mean, held constant beyond its ends.

All are compiled with ``cache=True`` (the machine code is kept in ``__pycache__`` beside this
file, reused by later processes) and on first use; :func:`warm_up` compiles every one with the
argument types the measurement passes, so a :class:`vision.pipeline.Measurer` does that at
set-up, never on a frame.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_JIT = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}


@njit(**_JIT)
def bin_rows(image: np.ndarray, r0: int, k: int, bins: np.ndarray, start: int, m: int,
             plain: np.ndarray, v0: int, v1: int, c0: int, c1: int, acc: np.ndarray,
             columns: np.ndarray) -> None:  # pragma: no cover - compiled
    """Row bins, coarse bins and column sums of an 8-bit image in one pass.

    Parameters
    ----------
    image : ndarray, shape (height, width), uint8
        Distorted image.
    r0, k : int
        First image row and rows per bin.
    bins : ndarray, shape (n_bins, width), uint16
        Out: ``bins[j] = sum(image[r0 + j k : r0 + (j + 1) k])``.
    start, m : int
        First bin and bins per coarse bin of ``plain``.
    plain : ndarray, shape (n_plain, width), uint16 or float32
        Out: ``plain[i] = sum(bins[start + i m : start + (i + 1) m])``.
    v0, v1, c0, c1 : int
        Rows of ``plain`` and columns summed into ``columns``.
    acc : ndarray, shape (c1 - c0,), uint32 (``plain`` uint16) or float64
        Scratch: the column sums as they are added up (integers: exact, and vectorised).
    columns : ndarray, shape (c1 - c0,), float64
        Out: column sums of ``plain[v0:v1, c0:c1]``.
    """
    n_bins, w = bins.shape
    n_plain = plain.shape[0]
    for c in range(c1 - c0):
        acc[c] = 0
    # Integer sums (exact in any order): each bin row is added to its coarse bin, and each
    # finished coarse bin to the column sums, while it is still in the cache.
    for j in range(n_bins):
        out = bins[j]
        row = image[r0 + j * k]
        for c in range(w):
            out[c] = row[c]
        for i in range(1, k):
            row = image[r0 + j * k + i]
            for c in range(w):
                out[c] += row[c]
        q = j - start
        if q < 0 or q >= n_plain * m:
            continue
        dest = plain[q // m]
        if q % m == 0:
            for c in range(w):
                dest[c] = out[c]
        else:
            for c in range(w):
                dest[c] += out[c]
        if q % m == m - 1 and v0 <= q // m < v1:
            part = dest[c0:c1]
            for c in range(c1 - c0):
                acc[c] += part[c]
    for c in range(c1 - c0):
        columns[c] = acc[c]


@njit(**_JIT)
def group_sums(bins: np.ndarray, first: int, size: int,
               out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``out[q] = sum(bins[first + q size : first + (q + 1) size])`` in ``out``'s dtype.

    The row-group sums of integer bins, one pass, each bin converted to ``out``'s dtype and
    added there: as ``bins[first:first + g size].reshape(g, size, w).sum(axis=1,
    dtype=out.dtype)`` for ``out`` of shape ``(g, w)``. The front end's two uses: the
    orientation's groups in ``float32`` (``uint16`` bins, ``size <= 256``: the sums stay below
    ``2**24``, exact in ``float32`` in any order) and the unsheared profile's bins in
    ``uint16`` (sums that fit it: integers, any order). The same sums, no temporaries.
    """
    g, w = out.shape
    cast = out.dtype.type  # the accumulator: out's dtype (float32 or uint16)
    for q in range(g):
        o = out[q]
        r0 = first + q * size
        row = bins[r0]
        for c in range(w):
            o[c] = cast(row[c])
        for s in range(1, size):
            row = bins[r0 + s]
            for c in range(w):
                o[c] += cast(row[c])


@njit(**_JIT)
def rows_over(bins: np.ndarray, means: np.ndarray,
              out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``out[r] = float32(bins[r]) / means[r]``, each a correctly rounded ``float32`` quotient.

    As ``np.divide(bins, means[:, None], dtype=np.float32)`` (the same quotients), without its
    broadcast's slow path: 4x faster on the rotated texture's ``uint16`` bins.
    """
    n, w = bins.shape
    for r in range(n):
        row = bins[r]
        o = out[r]
        mean = means[r]
        for c in range(w):
            o[c] = np.float32(row[c]) / mean


@njit(**_JIT)
def scaled_less_one(rows: np.ndarray, scale: np.ndarray,
                    out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``out = float32(rows * scale[None, :]) - 1`` in ``float32`` (the texture rows).

    As ``np.multiply(rows, scale[None, :], dtype=np.float32) - np.float32(1)``: each product
    rounded to ``float32``, then the subtraction (no fused multiply-add without fastmath), so
    the same numbers in one pass instead of numpy's broadcast and a second pass.
    """
    n, w = rows.shape
    one = np.float32(1.0)
    for r in range(n):
        row = rows[r]
        o = out[r]
        for c in range(w):
            o[c] = np.float32(np.float32(row[c]) * scale[c]) - one


@njit(**_JIT)
def inverse_column_means(rows: np.ndarray, acc: np.ndarray,
                         out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``out = 1 / float32(mean of rows down each column)`` (0 where the mean is not > 0).

    As ``_inverse(cv2.reduce(rows, 0, cv2.REDUCE_AVG, dtype=cv2.CV_64F).ravel())`` of the
    texture rows: each column summed in ``float64`` row after row (``acc``, scratch of shape
    ``(width,)``), times ``1 / rows`` (OpenCV's average), rounded to ``float32`` and inverted in
    ``float32``: the same numbers without the reduction's and the masked division's calls.
    """
    n, w = rows.shape
    for c in range(w):
        acc[c] = np.float64(rows[0, c])
    for r in range(1, n):
        row = rows[r]
        for c in range(w):
            acc[c] += np.float64(row[c])
    scale = 1.0 / n
    one = np.float32(1.0)
    for c in range(w):
        mean = np.float32(acc[c] * scale)
        out[c] = one / mean if mean > np.float32(0.0) else np.float32(0.0)


@njit(**_JIT)
def column_sums(rows: np.ndarray, acc: np.ndarray,
                out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``out[c] = sum(rows[:, c])`` of ``uint16`` rows, added up as integers (exact).

    ``acc`` (``uint32``, shape ``(width,)``) is scratch: fewer than 65,537 rows cannot
    overflow it, and integer sums are the same in any order (``cv2.reduce``'s float64 sums
    of the same integers are exact too), vectorised.
    """
    n, w = rows.shape
    for c in range(w):
        acc[c] = 0
    for j in range(n):
        row = rows[j]
        for c in range(w):
            acc[c] += row[c]
    for c in range(w):
        out[c] = acc[c]


@njit(**_JIT)
def _interp_at(x: float, cum: np.ndarray, col: int) -> float:  # pragma: no cover - compiled
    """``np.interp(x, knots, cum[:, col])`` with knots ``-0.5, 0.5, ..., n + 0.5``."""
    last = cum.shape[0] - 1
    j = int(math.floor(x + 0.5))  # knots[j] = j - 0.5 <= x
    if j >= last:
        return cum[last, col]
    j = max(j, 0)
    t = x - (j - 0.5)
    return (cum[j + 1, col] - cum[j, col]) * t + cum[j, col]


@njit(**_JIT)
def running_mean_2d(values: np.ndarray, length: float) -> np.ndarray:  # pragma: no cover
    """:func:`vision.calibration.illumination.running_mean` of an ``(n, k)`` array along axis 0.

    Returns
    -------
    ndarray, shape (n - 2 m0, k)
        ``m0 = ceil(length / 2 - 1/2)``.
    """
    n, kk = values.shape
    cum = np.zeros((n + 1, kk))
    for c in range(kk):
        acc = 0.0
        for i in range(n):
            acc += values[i, c]
            cum[i + 1, c] = acc
    half = 0.5 * length
    m0 = int(math.ceil(half - 0.5))
    out = np.empty((n - 2 * m0, kk))
    for i in range(n - 2 * m0):
        x = float(m0 + i)
        for c in range(kk):
            hi = _interp_at(x + half, cum, c)
            hi -= _interp_at(x - half, cum, c)
            out[i, c] = hi / length
    return out


@njit(**_JIT)
def running_mean_1d(values: np.ndarray, length: float) -> np.ndarray:  # pragma: no cover
    """:func:`vision.calibration.illumination.running_mean` of a 1-D array."""
    return running_mean_2d(values.reshape(values.size, 1), length)[:, 0]


@njit(**_JIT)
def smooth_trend(values: np.ndarray, basis: np.ndarray,
                 length: float) -> tuple[bool, np.ndarray]:  # pragma: no cover - compiled
    """The polynomial fitted to the running means of ``values`` and of its ``basis``.

    As :meth:`vision.calibration.illumination.Detrender.trend` with a period: the running mean over
    ``length`` samples of the values and of each basis column, the normal equations of those,
    and the fitted polynomial ``basis @ coef`` over all samples.

    Returns
    -------
    ok : bool
        False when the normal equations are singular.
    trend : ndarray, shape (n,)
    """
    n, d = basis.shape
    both = np.empty((n, d + 1))
    for i in range(n):
        both[i, 0] = values[i]
        for j in range(d):
            both[i, j + 1] = basis[i, j]
    smooth = running_mean_2d(both, length)
    m = smooth.shape[0]
    gram = np.zeros((1, d, d))
    rhs = np.zeros((1, d))
    for i in range(m):
        for a in range(d):
            ba = smooth[i, a + 1]
            rhs[0, a] += smooth[i, 0] * ba
            for b in range(a, d):
                gram[0, a, b] += ba * smooth[i, b + 1]
    for a in range(d):
        for b in range(a):
            gram[0, a, b] = gram[0, b, a]
    out = np.zeros(n)
    if not solve_small(gram, rhs):
        return False, out
    for i in range(n):
        acc = 0.0
        for j in range(d):
            acc += basis[i, j] * rhs[0, j]
        out[i] = acc
    return True, out


@njit(**_JIT)
def arc_model(h: np.ndarray, p: np.ndarray, gaps: np.ndarray, dx: float, guard: int,
              cum_p: np.ndarray) -> tuple[bool, np.ndarray, np.ndarray, np.ndarray,
                                          np.ndarray]:  # pragma: no cover - compiled
    """The arc model of :func:`vision.marks.find_marks` (the loops of its numpy version).

    Parameters
    ----------
    h, p : ndarray, shape (n,)
        Height (um) and slope.
    gaps : ndarray, shape (g,)
        Cusps to a sample (between samples ``i`` and ``i + 1``: ``i + 0.5``).
    dx : float
        Sample spacing, mm.
    guard : int
        Samples left out either side of a cusp.
    cum_p : ndarray, shape (n + 1,)
        ``[0, cumsum(p)]``.

    Returns
    -------
    ok : bool
        False: the model does not apply (the caller takes the samples instead).
    cusps, cusp_heights, bottoms, bottom_heights : ndarray
        In samples and um, as :func:`vision.marks._arc_model`.
    """
    n = h.size
    g = gaps.size
    segs = g + 1
    empty = np.empty(0)
    b = np.full(segs, np.nan)
    e = np.full(segs, np.nan)
    sx_a = np.zeros(segs)
    sxx_a = np.zeros(segs)
    sp_a = np.zeros(segs)
    sh_a = np.zeros(segs)
    cnt_a = np.zeros(segs)
    ok = np.zeros(segs, dtype=np.bool_)
    cum_xp = np.empty(n + 1)
    cum_h = np.empty(n + 1)
    cum_xp[0] = cum_h[0] = 0.0
    acc_xp = acc_h = 0.0
    for i in range(n):
        acc_xp += float(i) * p[i]
        acc_h += h[i]
        cum_xp[i + 1] = acc_xp
        cum_h[i + 1] = acc_h
    den = 0.0
    num = 0.0
    any_ok = False
    for k in range(segs):
        lo = 1 if k == 0 else max(int(math.ceil(gaps[k - 1] + guard - 0.5)), 1)
        hi = (n - 2 if k == g else min(int(math.floor(gaps[k] - guard + 0.5)), n - 2)) + 1
        if hi - lo < 2:
            continue
        any_ok = True
        ok[k] = True
        lo_f, hi_f = float(lo), float(hi)
        sx = (hi_f * (hi_f - 1) - lo_f * (lo_f - 1)) / 2
        sxx = ((hi_f - 1) * hi_f * (2 * hi_f - 1) - (lo_f - 1) * lo_f * (2 * lo_f - 1)) / 6
        sp = cum_p[hi] - cum_p[lo]
        sxp = cum_xp[hi] - cum_xp[lo]
        cnt = float(hi - lo)
        sx_a[k], sxx_a[k], sp_a[k], cnt_a[k] = sx, sxx, sp, cnt
        sh_a[k] = cum_h[hi] - cum_h[lo]
        den += sxx - sx * sx / cnt
        num += sxp - sx * sp / cnt
    if not any_ok:
        return False, empty, empty, empty, empty
    kappa = num / den if den > 0 else 0.0  # slope per sample
    if not kappa > 0:
        return False, empty, empty, empty, empty
    scale = 1000.0 * dx  # um per (slope x sample)
    for k in range(segs):
        if ok[k]:
            cnt = cnt_a[k]
            bk = (sx_a[k] - sp_a[k] / kappa) / cnt  # p = kappa (s - b)
            b[k] = bk
            quad = sxx_a[k] - 2 * bk * sx_a[k] + bk * bk * cnt
            e[k] = (sh_a[k] - 0.5 * scale * kappa * quad) / cnt
    half = 0.5 * scale * kappa
    # Cusps where neighbouring arcs meet.
    xc = np.empty(g)
    good = np.zeros(g, dtype=np.bool_)
    j0 = -1
    j1 = -1
    found = 0
    for k in range(g):
        bl, br = b[k], b[k + 1]
        xc[k] = 0.5 * (bl + br) + (e[k + 1] - e[k]) / (2.0 * half * (br - bl))
        good[k] = np.isfinite(xc[k]) and br > bl and abs(xc[k] - gaps[k]) <= 1.5
        if good[k]:
            found += 1
            if j0 < 0:
                j0 = k
            j1 = k + 1
    if found < 2:
        return False, empty, empty, empty, empty
    # Drop unrefined cusps at the ends; inner ones keep the sample position.
    nc = j1 - j0
    cusp = np.empty(nc)
    cusp_h = np.empty(nc)
    for q in range(nc):
        k = j0 + q
        c = xc[k] if good[k] else gaps[k]
        cusp[q] = c
        dl = c - b[k]
        dr = c - b[k + 1]
        hl = e[k] + half * (dl * dl)
        hr = e[k + 1] + half * (dr * dr)
        fl, fr = np.isfinite(hl), np.isfinite(hr)
        if fl and fr:
            cusp_h[q] = 0.5 * (hl + hr)
        elif fl:
            cusp_h[q] = hl
        elif fr:
            cusp_h[q] = hr
        else:
            cusp_h[q] = np.interp(c, np.arange(n, dtype=np.float64), h)
    bottoms, bottom_h = _arc_bottoms(h, b, e, half, cusp, j0)
    return True, cusp, cusp_h, bottoms, bottom_h


@njit(**_JIT)
def _arc_bottoms(h: np.ndarray, b: np.ndarray, e: np.ndarray, half: float, cusp: np.ndarray,
                 j0: int) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Bottoms of :func:`arc_model`: each complete mark's arc vertex, kept inside the mark."""
    nc = cusp.size
    bottoms = np.empty(nc - 1)
    bottom_h = np.empty(nc - 1)
    for q in range(nc - 1):
        bq = b[j0 + 1 + q]
        vertex = bq if np.isfinite(bq) else 0.5 * (cusp[q] + cusp[q + 1])
        bot = min(max(vertex, cusp[q]), cusp[q + 1])
        d = bot - bq
        bh = e[j0 + 1 + q] + half * (d * d)
        if not np.isfinite(bh):
            a_, z_ = int(math.ceil(cusp[q])), int(math.floor(cusp[q + 1]))
            if z_ >= a_:
                i = a_ + int(np.argmin(h[a_ : z_ + 1]))
            else:
                i = int(round(cusp[q]))
            bot, bh = float(i), h[i]
        bottoms[q] = bot
        bottom_h[q] = bh
    return bottoms, bottom_h


@njit(**_JIT)
def spectrum_peak(spec: np.ndarray, k_lo: int, k_hi: int) -> float:  # pragma: no cover
    """Bin of the largest power ``|spec|^2`` in ``k_lo..k_hi``, refined by a parabola.

    The first of equal maxima (as ``np.argmax``); no refinement where the power is not
    curved downwards.
    """
    best = -1.0
    k = k_lo
    for i in range(k_lo, k_hi + 1):
        v = spec[i].real ** 2 + spec[i].imag ** 2
        if v > best:
            best, k = v, i
    y0 = spec[k - 1].real ** 2 + spec[k - 1].imag ** 2
    y2 = spec[k + 1].real ** 2 + spec[k + 1].imag ** 2
    curv = y0 - 2 * best + y2
    frac = 0.5 * (y0 - y2) / curv if curv < 0 else 0.0
    return k + frac


@njit(**_JIT)
def smooth5(values: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """``np.convolve(values, np.ones(5) / 5, mode="same")`` (zeros beyond the ends)."""
    n = values.size
    out = np.empty(n)
    w = 1.0 / 5.0
    for i in range(n):
        acc = 0.0
        for j in range(i - 2, i + 3):
            if 0 <= j < n:
                acc += values[j] * w
        out[i] = acc
    return out


@njit(**_JIT)
def repeat_lag(s: np.ndarray, dots: np.ndarray, period: float, ks: np.ndarray,
               tolerance: float) -> float:  # pragma: no cover - compiled
    """The repeat period from the self-correlation at multiples of ``period``.

    ``dots[lag] = sum s[u] s[u + lag]``; the self-correlation at a lag is that over the
    energies of both stretches.  For each multiple ``k period`` the parabola through the three
    integer lags around it gives the peak's lag and value; the smallest multiple whose value is
    within ``tolerance`` of the best is returned (as :func:`vision.marks.repeat_period_px`).
    """
    n = s.size
    cum = np.empty(n + 1)
    cum[0] = 0.0
    acc = 0.0
    for i in range(n):
        acc += s[i] * s[i]
        cum[i + 1] = acc
    total = cum[n]
    m = ks.size
    lag = np.empty(m)
    value = np.empty(m)
    for q in range(m):
        target = period * ks[q]
        edge = False
        c = int(np.rint(target))
        if c < 2 or c + 1 >= n - 8:
            edge = True
        y = np.zeros(3)
        if edge:
            cc = max(1, min(c, n - 9))
            den = math.sqrt(cum[n - cc] * (total - cum[cc]))
            lag[q] = target
            value[q] = dots[cc] / den if den > 0 else 0.0
            continue
        for r in range(3):
            ll = c - 1 + r
            den = math.sqrt(cum[n - ll] * (total - cum[ll]))
            y[r] = dots[ll] / den if den > 0 else 0.0
        curv = y[0] - 2 * y[1] + y[2]
        if curv < 0:
            frac = min(0.5, max(-0.5, 0.5 * (y[0] - y[2]) / curv))
            lag[q] = c + frac
            value[q] = y[1] - 0.25 * (y[0] - y[2]) * frac
        else:
            lag[q] = float(c)
            value[q] = y[1]
    best = value.max()
    for q in range(m):
        if value[q] >= best - tolerance:
            return lag[q]
    return lag[0]


@njit(**_JIT)
def cusp_candidates(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float,
                                            bool]:  # pragma: no cover - compiled
    """The first step of :func:`vision.marks.find_marks`: candidate cusps and their scale.

    Returns
    -------
    cum_p : ndarray, shape (n + 1,)
        ``[0, cumsum(p)]``.
    cand, size : ndarray
        Strict local maxima ``i`` of ``-steps`` (the slope's fall across the gap after
        sample ``i``, two samples either side) that are ``>= 0``, and their heights.
    noise : float
        Robust standard deviation of one slope sample (from the differences).
    typical : float
        90th percentile of ``size`` (NaN without candidates).
    simple : bool
        False when a plateau or two maxima closer than 3 samples need scipy's rules (the
        caller then finds the peaks itself).
    """
    n = p.size
    cum = np.empty(n + 1)
    cum[0] = 0.0
    acc = 0.0
    for i in range(n):
        acc += p[i]
        cum[i + 1] = acc
    k = 2
    neg = np.zeros(n)  # -steps
    if n >= 2 * k + 1:
        for i in range(k - 1, n - k):
            mid = cum[i + 1]
            neg[i] = -(((cum[i + 1 + k] - mid) - (mid - cum[i + 1 - k])) / k)
    cand = np.empty(n, dtype=np.intp)
    size = np.empty(n)
    count = 0
    simple = True
    for i in range(1, n - 1):
        v = neg[i]
        if neg[i - 1] < v:
            if v == neg[i + 1] and i < n - 2:
                simple = False  # a plateau inside the signal
            elif v > neg[i + 1] and v >= 0.0:
                if count and i - cand[count - 1] < 3:
                    simple = False
                cand[count] = i
                size[count] = v
                count += 1
    cand = cand[:count]
    size = size[:count]
    noise = math.nan
    typical = math.nan
    if count:
        d = np.empty(n - 1)
        for i in range(n - 1):
            d[i] = p[i + 1] - p[i]
        med = _median(d)
        for i in range(n - 1):
            d[i] = abs(d[i] - med)
        noise = 1.4826 * _median(d) / math.sqrt(2.0)
        srt = np.sort(size)
        pos = (count - 1) * 0.9
        lo = int(math.floor(pos))
        hi = min(lo + 1, count - 1)
        a, b = srt[lo], srt[hi]
        t = pos - lo
        typical = b - (b - a) * (1.0 - t) if t >= 0.5 else a + (b - a) * t
    return cum, cand, size, noise, typical, simple


@njit(**_JIT)
def _median(values: np.ndarray) -> float:  # pragma: no cover - compiled
    """Median of a non-empty 1-D array (the mean of the two middle values; quickselect)."""
    return np.median(values)


@njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def delay_scores(spec_a: np.ndarray, spec_b: np.ndarray, phasors: np.ndarray,
                 score: np.ndarray) -> float:  # pragma: no cover - compiled
    """The fine registration's scores of a grid of delays from two spectra.

    The cross-spectrum ``X = conj(A) B``, its phase doubled (``X^2 / |X|``, so a frequency
    whose shading is mirrored votes as the albedo does), in ``float32`` as the phasors; then
    ``score[j] = Re sum_k P[j, k] X2[k]`` with ``phasors = [Re P, -Im P]`` (shape
    ``(delays, 2 k)``).  Sums in ``float32``, vectorised (reordered as a BLAS product would).

    Returns
    -------
    float
        ``sum |X|`` (0: no signal; the scores are then not computed).
    """
    k = spec_a.size
    parts = np.empty(2 * k, dtype=np.float32)
    total = 0.0
    for i in range(k):
        x = spec_a[i].conjugate() * spec_b[i]
        mag = abs(x)
        total += mag
        d = x * x / (mag if mag > 0 else 1.0)
        parts[i] = np.float32(d.real)
        parts[k + i] = np.float32(d.imag)
    if not total > 0:
        return total
    for j in range(phasors.shape[0]):
        row = phasors[j]
        acc = np.float32(0.0)
        for i in range(2 * k):
            acc += row[i] * parts[i]
        score[j] = acc
    return total


@njit(**_JIT)
def arc_slopes(x: np.ndarray, cusps: np.ndarray, bottoms: np.ndarray,
               radius: float) -> np.ndarray:  # pragma: no cover - compiled
    """``(x - b_k) / R`` inside mark ``k`` (between cusps ``k`` and ``k + 1``), NaN outside.

    As :func:`vision.calibration.selfcal.kinematic_slope` (a position on a cusp belongs to the
    mark after
    it).
    """
    k = np.searchsorted(cusps, x, side="right") - 1
    out = np.empty(x.size)
    for i in range(x.size):
        j = k[i]
        out[i] = (x[i] - bottoms[j]) / radius if 0 <= j < bottoms.size else np.nan
    return out


@njit(**_JIT)
def solve_small(a: np.ndarray, b: np.ndarray) -> bool:  # pragma: no cover - compiled
    """Solve ``a[i] x = b[i]`` in place for every ``i`` (Gaussian elimination, partial pivots).

    Parameters
    ----------
    a : ndarray, shape (batch, n, n), float64
        Matrices; overwritten.
    b : ndarray, shape (batch, n), float64
        Right-hand sides; overwritten by the solutions.

    Returns
    -------
    bool
        False when a matrix is singular (``b`` then undefined).
    """
    batch, n, _ = a.shape
    for q in range(batch):
        m = a[q]
        r = b[q]
        for col in range(n):
            piv = col
            best = abs(m[col, col])
            for row in range(col + 1, n):
                v = abs(m[row, col])
                if v > best:
                    best, piv = v, row
            if best == 0.0:
                return False
            if piv != col:
                for j in range(n):
                    m[col, j], m[piv, j] = m[piv, j], m[col, j]
                r[col], r[piv] = r[piv], r[col]
            d = m[col, col]
            for row in range(col + 1, n):
                f = m[row, col] / d
                if f != 0.0:
                    for j in range(col, n):
                        m[row, j] -= f * m[col, j]
                    r[row] -= f * r[col]
        for col in range(n - 1, -1, -1):
            acc = r[col]
            for j in range(col + 1, n):
                acc -= m[col, j] * r[j]
            r[col] = acc / m[col, col]
    return True


@njit(**_JIT)
def blur_fits(gram: np.ndarray, rhs: np.ndarray, yy: float, plain: bool, rss: np.ndarray,
              coef_a: np.ndarray, coef_b: np.ndarray, count: int,
              var: float) -> tuple[int, float]:  # pragma: no cover - compiled
    """The self-calibration's least-squares fits from its normal equations.

    ``gram = D D'`` and ``rhs = D y`` of a design ``D`` whose rows are the model (row 0),
    ``L`` blurred models (rows ``1..L``), ones and x (the last two rows); ``yy = y'y``.  Fit 0
    (``plain``) uses rows ``0, L+1, L+2``; fit ``1 + l`` rows ``0, 1 + l, L+1, L+2``.  Out: the
    residual sums of squares ``rss`` (left as they are for a singular fit), the model's
    coefficient ``coef_a`` and the blurred model's ``coef_b`` of each fit.

    Returns the best admissible fit -- a positive gain ``coef_a + coef_b``, not mostly a
    negative unblurred part -- and its residual variance over ``var`` (``count`` samples):
    ``(-1, nan)`` when none is admissible.
    """
    n_l = gram.shape[0] - 3
    for q in range(n_l + 1):
        if q == 0:
            if not plain:
                continue
            idx = np.array([0, n_l + 1, n_l + 2])
        else:
            idx = np.array([0, q, n_l + 1, n_l + 2])
        k = idx.size
        a = np.empty((1, k, k))
        b = np.empty((1, k))
        for i in range(k):
            b[0, i] = rhs[idx[i]]
            for j in range(k):
                a[0, i, j] = gram[idx[i], idx[j]]
        if not solve_small(a, b):
            continue
        fit = 0.0
        for i in range(k):
            fit += b[0, i] * rhs[idx[i]]
        rss[q] = yy - fit
        coef_a[q] = b[0, 0]
        coef_b[q] = b[0, 1] if q > 0 else 0.0
    best = -1
    best_resid = np.inf
    for q in range(n_l + 1):
        g = coef_a[q] + coef_b[q]
        if not (np.isfinite(rss[q]) and g > 0 and not coef_a[q] < -0.05 * g):
            continue
        resid = max(rss[q], 0.0) / count / var
        if best < 0 or resid < best_resid:
            best, best_resid = q, resid
    if best < 0:
        return -1, np.nan
    return best, best_resid


@njit(**_JIT)
def model_span(model: np.ndarray, slope: np.ndarray,
               out: np.ndarray) -> tuple[int, int, int, bool]:  # pragma: no cover - compiled
    """The samples of a kinematic slope the self-calibration fits over, in one pass.

    As :func:`vision.calibration.selfcal.fit_calibration`'s ``inside = isfinite(model)``,
    ``lo, hi`` (the first finite sample and one past the last), ``model[lo:hi]`` with its
    non-finite samples set to 0 (written to ``out[:hi - lo]``), and ``slope[lo:hi].max() >
    slope[lo:hi].min()`` (``False`` when that span holds a NaN, as numpy's ``max``/``min``
    propagate it).  Returns ``(lo, hi, finite count, varies)``; ``(0, 0, 0, False)`` when no
    sample is finite.
    """
    n = model.size
    lo = -1
    hi = 0
    count = 0
    for i in range(n):
        if np.isfinite(model[i]):
            if lo < 0:
                lo = i
            hi = i + 1
            count += 1
    if lo < 0:
        return 0, 0, 0, False
    top = -np.inf
    bottom = np.inf
    nan = False
    for i in range(lo, hi):
        v = model[i]
        out[i - lo] = v if np.isfinite(v) else 0.0
        s = slope[i]
        if s != s:
            nan = True
        if s > top:
            top = s
        if s < bottom:
            bottom = s
    return lo, hi, count, (not nan) and top > bottom


@njit(**_JIT)
def wiener_terms(nu: np.ndarray, scale: float, fraction: float, regularisation: float,
                 h: np.ndarray, den: np.ndarray) -> None:  # pragma: no cover - compiled
    """The scattering deblur's ``h = (1 - f) + f / (1 + (scale nu)^2)`` and ``h h + c``.

    The arithmetic of :func:`vision.calibration.selfcal.scatter_transfer` (``scale = 2 pi
    l``, as its ``2.0 * math.pi * scatter_mm``) and of the Wiener denominator
    ``h * h + regularisation``, each sample's operations in numpy's order, into ``h`` and
    ``den``.
    """
    keep = 1.0 - fraction
    for i in range(nu.size):
        t = scale * nu[i]
        k = 1.0 / (1.0 + t * t)
        v = keep + fraction * k
        h[i] = v
        den[i] = v * v + regularisation


@njit(**_JIT)
def ratio_slope(ratio: np.ndarray, ca: float, tan_a: float, b: float,
                out: np.ndarray) -> bool:  # pragma: no cover - compiled
    """:class:`vision.slope.RatioSlope` of a 1-D ratio into ``out``; whether all is finite.

    ``den = ratio * ca * tan_a - b``; ``(ratio - 1) / den``, NaN where ``den == 0`` (numpy's
    operations in its order: ``(ratio * ca) * tan_a``).
    """
    finite = True
    for i in range(ratio.size):
        r = ratio[i]
        den = r * ca * tan_a - b
        if den != 0:
            p = (r - 1.0) / den
        else:
            p = np.nan
        out[i] = p
        if not np.isfinite(p):
            finite = False
    return finite


@njit(**_JIT)
def power_spectrum(spec: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """``spec.real ** 2 + spec.imag ** 2`` of a 1-D complex spectrum."""
    out = np.empty(spec.size)
    for i in range(spec.size):
        re = spec[i].real
        im = spec[i].imag
        out[i] = re * re + im * im
    return out


@njit(**_JIT)
def any_nonpositive(a: np.ndarray, b: np.ndarray) -> bool:  # pragma: no cover - compiled
    """``np.any(a <= 0) or np.any(b <= 0)`` of two 1-D float arrays (NaN is not ``<= 0``)."""
    for i in range(a.size):
        if a[i] <= 0:
            return True
    for i in range(b.size):
        if b[i] <= 0:
            return True
    return False


@njit(**_JIT)
def knife_sums(values: np.ndarray, knives: int, phase: int, sums: np.ndarray,
               counts: np.ndarray) -> None:  # pragma: no cover - compiled
    """Mark ``i``'s value added to knife ``(phase + i) mod knives`` (``sums``, ``counts``).

    The sums run in the marks' order from 0.0 (what :func:`vision.marks.knife_means` divides);
    ``phase`` may be negative (Python's modulo).
    """
    for i in range(values.size):
        k = (phase + i) % knives
        if k < 0:
            k += knives
        sums[k] += values[i]
        counts[k] += 1


@njit(**_JIT)
def arc_depths(cusps: np.ndarray, bottoms: np.ndarray,
               radius: float) -> np.ndarray:  # pragma: no cover - compiled
    """``1000 ((c_k - b_k)^2 + (c_(k+1) - b_k)^2) / (4 R)`` per mark, numpy's order."""
    m = bottoms.size
    out = np.empty(m)
    four_r = 4.0 * radius
    for k in range(m):
        left = cusps[k] - bottoms[k]
        right = cusps[k + 1] - bottoms[k]
        out[k] = 1000.0 * (left * left + right * right) / four_r
    return out


@njit(**_JIT)
def cubic_shift(p: np.ndarray, i0: int, count: int, w_m1: float, w_0: float, w_p1: float,
                w_p2: float) -> np.ndarray:  # pragma: no cover - compiled
    """``w_m1 p[i0 - 1 + i] + w_0 p[i0 + i] + w_p1 p[i0 + 1 + i] + w_p2 p[i0 + 2 + i]``.

    :func:`vision.profile.shift_profile`'s sum of four weighted slices, summed left to right
    as numpy does; the caller checks that the slices lie inside ``p``.
    """
    out = np.empty(count)
    for i in range(count):
        j = i0 + i
        out[i] = w_m1 * p[j - 1] + w_0 * p[j] + w_p1 * p[j + 1] + w_p2 * p[j + 2]
    return out


@njit(**_JIT)
def feed_positions(first_col: int, cx: float, cos_roll: float, px_per_mm: float,
                   out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``(cx + (cols - cx) * cos_roll) / px_per_mm`` for ``cols = first_col + arange(n)``.

    Written into ``out`` (``n`` samples): an array numpy made, so that the measurement's
    ``x_mm`` keeps numpy's own ``float64`` dtype object (and pickles as before).
    """
    for i in range(out.size):
        out[i] = (cx + (float(first_col + i) - cx) * cos_roll) / px_per_mm


@njit(**_JIT)
def all_finite(a: np.ndarray, b: np.ndarray) -> bool:  # pragma: no cover - compiled
    """``np.all(np.isfinite(a)) and np.all(np.isfinite(b))`` of two 1-D float arrays."""
    for i in range(a.size):
        if not np.isfinite(a[i]):
            return False
    for i in range(b.size):
        if not np.isfinite(b[i]):
            return False
    return True


@njit(**_JIT)
def less_running(h: np.ndarray, slow: np.ndarray, m0: int,
                 out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``h`` less ``slow`` at ``m0 ..``, less its first value before and its last after.

    :func:`vision.pipeline.remove_slow`'s three slice subtractions in one pass (``out``).
    """
    n = h.size
    m1 = m0 + slow.size
    first = slow[0]
    last = slow[slow.size - 1]
    for i in range(n):
        if i < m0:
            out[i] = h[i] - first
        elif i < m1:
            out[i] = h[i] - slow[i - m0]
        else:
            out[i] = h[i] - last


_WARM = [False]


def warm_up() -> None:
    """Compile (or load from the cache) every kernel for the types the measurement uses.

    Called by set-up code (:class:`vision.pipeline.Measurer`); idempotent and cheap after the
    first call in a process.
    """
    if _WARM[0]:
        return
    img = np.zeros((4, 8), dtype=np.uint8)
    bins = np.empty((2, 8), dtype=np.uint16)
    cols = np.empty(8)
    bin_rows(img, 0, 2, bins, 0, 1, np.empty((2, 8), dtype=np.uint16), 0, 2, 0, 8,
             np.empty(8, dtype=np.uint32), cols)
    bin_rows(img, 0, 2, bins, 0, 1, np.empty((2, 8), dtype=np.float32), 0, 2, 0, 8, cols,
             cols)
    group_sums(bins, 0, 1, np.empty((2, 8), dtype=np.float32))
    column_sums(bins, np.empty(8, dtype=np.uint32), cols)
    rows_over(bins, np.ones(2, dtype=np.float32), np.empty((2, 8), dtype=np.float32))
    group_sums(bins, 0, 1, np.empty((2, 8), dtype=np.uint16))
    scale, tex = np.ones(8, dtype=np.float32), np.empty((2, 8), dtype=np.float32)
    scaled_less_one(tex, scale, tex)
    scaled_less_one(bins, scale, tex)
    inverse_column_means(tex, np.empty(8), scale)
    v = np.arange(8.0)
    running_mean_1d(v, 2.5)
    running_mean_2d(np.ones((8, 3)), 2.5)
    smooth_trend(v, np.vander(v, 3), 2.5)
    cum = np.zeros(9)
    np.cumsum(v, out=cum[1:])
    arc_model(v, v, np.array([2.5, 5.5]), 0.1, 1, cum)
    solve_small(np.eye(3)[None].copy(), np.ones((1, 3)))
    cusp_candidates(np.sin(v))
    arc_slopes(v, np.array([1.0, 3.0, 5.0]), np.array([2.0, 4.0]), 60.0)
    spec = np.ones(4, dtype=np.complex128)
    delay_scores(spec, spec, np.ones((3, 8), dtype=np.float32), np.empty(3))
    spectrum_peak(np.ones(8, dtype=np.complex128), 1, 5)
    smooth5(v)
    repeat_lag(v, v, 2.5, np.array([1.0, 2.0]), 0.02)
    blur_fits(np.eye(5), np.ones(5), 1.0, True, np.empty(3), np.empty(3), np.empty(3), 8,
              1.0)
    model_span(v, v, np.empty(8))
    frozen = v.copy()
    frozen.flags.writeable = False  # the cached frequency axes are read-only: their own type
    wiener_terms(frozen, 1.0, 0.5, 0.03, np.empty(8), np.empty(8))
    ratio_slope(v, 1.0, 0.5, -0.5, np.empty(8))
    power_spectrum(spec)
    any_nonpositive(v, v)
    knife_sums(v, 3, 0, np.zeros(3), np.zeros(3, dtype=np.int64))
    arc_depths(v, v[:7], 60.0)
    cubic_shift(v, 1, 4, 0.1, 0.2, 0.3, 0.4)
    feed_positions(3, 1.5, 0.5, 2.0, np.empty(4))
    all_finite(v, v)
    less_running(v, v[2:6], 2, np.empty(8))
    from vision import marks_kernels  # the cusps' choice (find_marks), compiled beside these

    marks_kernels.warm_up()
    _WARM[0] = True
