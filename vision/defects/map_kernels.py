"""Compiled loops (numba) of the planing defects' surface map: a pair's along-feed slope on a grid.

What :class:`vision.defects.surface_map.SurfaceMapper` runs per pair, each step one call with
the arithmetic of the numpy and OpenCV code it replaces (the detectors' loops on the map are
:mod:`vision.defects.kernels`):

* :func:`remap_pair` -- both coarse images sampled on the map's grid at once, OpenCV's
  remap's numbers;
* :func:`column_means_u16` -- the map's coarse source: whole blocks of columns of
  ``uint16`` row bins averaged, as ``float32``;
* :func:`valid_any`, :func:`valid_extent` -- the map's valid rows and columns in one pass;
* :func:`register_ratio` -- B registered onto A along the rows (linear), the samples both
  shots see, the pair's constant imbalance removed, the slope by seed Eq. 4 and (when
  wanted) the albedo;
* :func:`map_pair` -- :func:`remap_pair` and :func:`register_ratio` in one call, with the
  map's valid rows and columns found in the ratio's pass (what the mapper calls).

Where a loop runs over a row it reads the row as a 1-D view and is branch-free, so that it
vectorises (the ratio's pass). Compiled with ``cache=True`` on first use; :func:`warm_up`
compiles every one with the types the mapper passes, so a
:class:`~vision.defects.surface_map.SurfaceMapper` does that at set-up, never on a frame.
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

_JIT = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}


@intrinsic
def _fma32(typingctx, a, b, c):  # type: ignore[no-untyped-def]  # pragma: no cover
    """``a * b + c`` rounded once (float32): LLVM's ``fma``, as OpenCV's remap computes it."""
    sig = types.float32(types.float32, types.float32, types.float32)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        f = ir.FloatType()
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(f, [f, f, f]),
                                            "llvm.fma.f32")
        return builder.call(fn, args)

    return sig, codegen


@njit(**_JIT)
def remap_pair(a: np.ndarray, b: np.ndarray, off: np.ndarray, ax: np.ndarray, ay: np.ndarray,
               x0: np.ndarray, y0: np.ndarray, inside: np.ndarray, out_a: np.ndarray,
               out_b: np.ndarray) -> None:  # pragma: no cover - compiled
    """Both images of a pair sampled bilinearly at the same grid points, as ``cv2.remap`` does.

    ``out[i, j]`` is ``a`` at ``(x0 + ax, y0 + ay)`` (column, row) by OpenCV's arithmetic for
    ``float32`` images and maps (``INTER_LINEAR``, ``BORDER_REPLICATE``): the fraction
    ``ax = x - floor(x)``, then ``v0 = fma(p01 - p00, ax, p00)``, ``v1 = fma(p11 - p10, ax,
    p10)``, ``fma(v1 - v0, ay, v0)`` -- the same bits as OpenCV 5's remap.  The two images
    share the taps (:class:`vision.defects.surface_map.SurfaceMapper`'s table per roll).

    Parameters
    ----------
    a, b : ndarray of float32, shape (h, w), C-contiguous
        The coarse sources.
    off : ndarray of uint32, shape (rows, cols)
        ``y0 * w + x0`` (read on the rows ``inside``).
    ax, ay : ndarray of float32, shape (rows, cols)
        The fractions.
    x0, y0 : ndarray of int32, shape (rows, cols)
        ``floor`` of the coordinates (read on the other rows, where taps are clamped to the
        image: OpenCV's ``BORDER_REPLICATE``).
    inside : ndarray of bool, shape (rows,)
        Rows all of whose taps lie inside the image.
    out_a, out_b : ndarray of float32, shape (rows, cols)
        Out.
    """
    h, w = a.shape
    af = a.reshape(a.size)
    bf = b.reshape(b.size)
    rows, cols = out_a.shape
    one = np.uint64(1)
    step = np.uint64(w)
    for i in range(rows):
        txr, tyr, ra, rb = ax[i], ay[i], out_a[i], out_b[i]
        if inside[i]:  # no tap to clamp: unsigned offsets (the loop has no index checks)
            orow = off[i]
            for j in range(cols):
                o = np.uint64(orow[j])
                tx = txr[j]
                ty = tyr[j]
                p00, p01, p10, p11 = af[o], af[o + one], af[o + step], af[o + step + one]
                v0 = _fma32(p01 - p00, tx, p00)
                ra[j] = _fma32(_fma32(p11 - p10, tx, p10) - v0, ty, v0)
                p00, p01, p10, p11 = bf[o], bf[o + one], bf[o + step], bf[o + step + one]
                v0 = _fma32(p01 - p00, tx, p00)
                rb[j] = _fma32(_fma32(p11 - p10, tx, p10) - v0, ty, v0)
        else:
            xr, yr = x0[i], y0[i]
            for j in range(cols):
                xa = min(max(xr[j], 0), w - 1)
                xb = min(max(xr[j] + 1, 0), w - 1)
                ya = min(max(yr[j], 0), h - 1)
                yb = min(max(yr[j] + 1, 0), h - 1)
                tx = txr[j]
                ty = tyr[j]
                p00, p01, p10, p11 = a[ya, xa], a[ya, xb], a[yb, xa], a[yb, xb]
                v0 = _fma32(p01 - p00, tx, p00)
                ra[j] = _fma32(_fma32(p11 - p10, tx, p10) - v0, ty, v0)
                p00, p01, p10, p11 = b[ya, xa], b[ya, xb], b[yb, xa], b[yb, xb]
                v0 = _fma32(p01 - p00, tx, p00)
                rb[j] = _fma32(_fma32(p11 - p10, tx, p10) - v0, ty, v0)


@njit(**_JIT)
def _register_ratio(a: np.ndarray, b: np.ndarray, valid: np.ndarray, d: float, ka: float,
                    kb: float, slope: np.ndarray, albedo: np.ndarray, both: np.ndarray,
                    any_rows: np.ndarray,
                    any_cols: np.ndarray) -> int:  # pragma: no cover - compiled
    """:func:`register_ratio`, and which rows and columns of ``both`` hold a sample.

    ``any_rows``, ``any_cols`` (out): ``both.any(axis=1)``, ``both.any(axis=0)``, found in the
    pass that writes ``both``.

    Slope and albedo of a pair on the map grid (B shifted by ``d`` columns onto A).

    Parameters
    ----------
    a, b : ndarray of float32, shape (rows, cols)
        A and B on the map grid (B where the board was when B was taken).
    valid : ndarray of bool, shape (rows, cols)
        Grid samples inside the image.
    d : float
        Board motion from A to B, map columns: ``b_reg[:, j] = b[:, j + d]`` (linear).
    ka, kb : float
        ``cos(azimuth) tan(slant)`` of light A and B (seed Eq. 4).
    slope : ndarray of float32, shape (rows, cols)
        Out: ``dz/dx`` with the pair's constant imbalance removed; 0 where not ``both``.
    albedo : ndarray of float32, shape (rows, cols) or (0, 0)
        Out (unless empty: not wanted): the albedo relative to the map's mean; 0 where not
        ``both``.
    both : ndarray of bool, shape (rows, cols)
        Out: both shots see the sample.

    Returns
    -------
    int
        Samples both shots see.
    """
    rows, cols = a.shape
    k = int(math.floor(d))
    t = np.float32(d - k)
    u = np.float32(1.0) - t
    zero = np.float32(0.0)
    # columns whose B samples j + k, j + k + 1 lie on the map; the others are not seen
    lo = min(max(0, -k), cols)
    hi = max(min(cols, cols - k - 1), lo)
    m = hi - lo
    # branch-free rows over slices (the loop vectorises), sums per column: the same sums
    sum_a = np.zeros(m)
    sum_b = np.zeros(m)
    count = np.zeros(m, dtype=np.int64)
    for i in range(rows):
        for j in range(lo):
            both[i, j] = False
        for j in range(hi, cols):
            both[i, j] = False
        ar, vr, sr, br_ = a[i, lo:hi], valid[i, lo:hi], slope[i, lo:hi], both[i, lo:hi]
        vb, bb = valid[i, lo + k:hi + k + 1], b[i, lo + k:hi + k + 1]
        for q in range(m):
            bv = bb[q] * u + bb[q + 1] * t
            av = ar[q]
            ok = vr[q] & vb[q] & vb[q + 1] & (av > zero) & (bv > zero)
            br_[q] = ok
            sr[q] = bv  # B registered, kept here for the second pass
            sum_a[q] += av if ok else zero
            sum_b[q] += bv if ok else zero
            count[q] += ok
        hit = False
        for q in range(m):  # a row with a sample: found at its first one (mostly the first)
            if br_[q]:
                hit = True
                break
        any_rows[i] = hit
    for j in range(cols):  # a column with a sample: its count (none outside lo..hi)
        any_cols[j] = lo <= j < hi and count[j - lo] > 0
    sa, sb, n = sum_a.sum(), sum_b.sum(), int(count.sum())
    if not (sa > 0 and sb > 0):
        sa = 1.0
        sb = 1.0
    gain = np.float32(sa / sb)
    fka, fkb = np.float32(ka), np.float32(kb)
    if albedo.size > 0:  # before the slope replaces B
        scale = np.float32(max(n, 1) / (2.0 * sa))
        for i in range(rows):
            for j in range(cols):
                w = (a[i, j] + slope[i, j] * gain) * scale
                albedo[i, j] = w if both[i, j] else zero
    for i in range(rows):
        for j in range(cols):
            av = a[i, j]
            r = slope[i, j] * gain
            v = (r - av) / (r * fka - av * fkb)
            slope[i, j] = v if both[i, j] else zero
    return n


@njit(**_JIT)
def register_ratio(a: np.ndarray, b: np.ndarray, valid: np.ndarray, d: float, ka: float,
                   kb: float, slope: np.ndarray, albedo: np.ndarray,
                   both: np.ndarray) -> int:  # pragma: no cover - compiled
    """Slope and albedo of a pair on the map grid (B shifted by ``d`` columns onto A).

    :func:`_register_ratio` (see there) without the valid rows and columns.
    """
    return _register_ratio(a, b, valid, d, ka, kb, slope, albedo, both,
                           np.empty(a.shape[0], dtype=np.bool_),
                           np.empty(a.shape[1], dtype=np.bool_))


@njit(**_JIT)
def map_pair(a: np.ndarray, b: np.ndarray, off: np.ndarray, ax: np.ndarray, ay: np.ndarray,
             x0: np.ndarray, y0: np.ndarray, inside: np.ndarray, valid: np.ndarray, d: float,
             ka: float, kb: float, slope: np.ndarray, albedo: np.ndarray,
             both: np.ndarray) -> tuple:  # pragma: no cover - compiled
    """A pair's map in one call: :func:`remap_pair`, then :func:`_register_ratio`.

    ``a``, ``b``: the coarse sources; the taps as :func:`remap_pair`'s; ``valid`` and the
    rest as :func:`register_ratio`'s (``slope``, ``albedo``, ``both`` out).  Returns the map's
    valid rows and columns, ``(np.flatnonzero(both.any(axis=1)),
    np.flatnonzero(both.any(axis=0)))`` (:func:`valid_extent`'s).
    """
    rows, cols = both.shape
    out_a = np.empty((rows, cols), dtype=np.float32)
    out_b = np.empty((rows, cols), dtype=np.float32)
    remap_pair(a, b, off, ax, ay, x0, y0, inside, out_a, out_b)
    any_rows = np.empty(rows, dtype=np.bool_)
    any_cols = np.empty(cols, dtype=np.bool_)
    _register_ratio(out_a, out_b, valid, d, ka, kb, slope, albedo, both, any_rows, any_cols)
    return np.flatnonzero(any_rows), np.flatnonzero(any_cols)


@njit(**_JIT)
def valid_any(valid: np.ndarray, rows: np.ndarray,
              cols: np.ndarray) -> None:  # pragma: no cover - compiled
    """Which rows and which columns of ``valid`` hold a valid sample, in one pass.

    As ``valid.any(axis=1)`` into ``rows`` and ``valid.any(axis=0)`` into ``cols`` (the map's
    valid rows and columns, :attr:`vision.defects.surface_map.SurfaceMap.valid_rows`), ~2x
    faster than numpy's two reductions on a map of ~100 x 330 samples.
    """
    n, w = valid.shape
    for c in range(w):
        cols[c] = False
    for r in range(n):
        row = valid[r]
        hit = False
        for c in range(w):
            v = row[c]
            cols[c] |= v
            hit |= v
        rows[r] = hit


@njit(**_JIT)
def valid_extent(valid: np.ndarray) -> tuple:  # pragma: no cover - compiled
    """The indices of the rows and of the columns of ``valid`` holding a valid sample.

    ``(np.flatnonzero(valid.any(axis=1)), np.flatnonzero(valid.any(axis=0)))`` (int64) in one
    call (:func:`valid_any`, then the indices):
    :attr:`vision.defects.surface_map.SurfaceMap.valid_rows` and ``valid_cols``.
    """
    any_rows = np.empty(valid.shape[0], dtype=np.bool_)
    any_cols = np.empty(valid.shape[1], dtype=np.bool_)
    valid_any(valid, any_rows, any_cols)
    return np.flatnonzero(any_rows), np.flatnonzero(any_cols)

@njit(**_JIT)
def column_means_u16(src: np.ndarray, row0: int, row_step: int, k: int,
                     out: np.ndarray) -> None:  # pragma: no cover - compiled
    """Means of ``k`` adjacent columns of every ``row_step``-th row from ``row0``, rounded.

    ``out[i, x]`` is the mean of ``src[row0 + i * row_step, x * k:(x + 1) * k]`` rounded to
    the nearest integer (half to even) -- the integers OpenCV's ``INTER_AREA`` resize by a
    whole factor ``k`` along the rows gives a ``uint16`` image (the integer sum times the
    ``float32`` ``1 / k``, rounded), as ``float32``.  An even ``k`` sums the columns in pairs
    first (a loop that vectorises), then ``k / 2`` pair sums; the integer sums are exact in
    any order, so the means are the same.

    Parameters
    ----------
    src : ndarray of uint16, shape (rows, cols)
    row0, row_step : int
        The rows read.
    k : int
        Columns per mean, at most 32768 (the sums fit an int32).
    out : ndarray of float32, shape (n_out, w_out)
        Out; ``w_out * k <= cols``.
    """
    scale = np.float32(1.0) / np.float32(k)
    n_out, w_out = out.shape
    half = k // 2
    pairs = np.empty(w_out * half if k % 2 == 0 else 0, dtype=np.int32)
    for i in range(n_out):
        s = src[row0 + i * row_step]
        o = out[i]
        if k % 2 == 0:
            for c in range(w_out * half):
                pairs[c] = np.int32(s[2 * c]) + np.int32(s[2 * c + 1])
            if half == 1:
                for x in range(w_out):
                    o[x] = np.rint(np.float32(pairs[x]) * scale)
            elif half == 2:
                for x in range(w_out):
                    o[x] = np.rint(np.float32(pairs[2 * x] + pairs[2 * x + 1]) * scale)
            elif half == 3:
                for x in range(w_out):
                    o[x] = np.rint(np.float32(pairs[3 * x] + pairs[3 * x + 1]
                                              + pairs[3 * x + 2]) * scale)
            else:
                for x in range(w_out):
                    a = np.int32(0)
                    for q in range(half):
                        a += pairs[x * half + q]
                    o[x] = np.rint(np.float32(a) * scale)
        else:
            for x in range(w_out):
                a = np.int32(0)
                for q in range(k):
                    a += np.int32(s[x * k + q])
                o[x] = np.rint(np.float32(a) * scale)


_WARM = [False]


def warm_up() -> None:
    """Compile (or load from the cache) the map kernels the mapper calls, for its types.

    Called by :class:`vision.defects.surface_map.SurfaceMapper` at set-up; idempotent and
    cheap after the first call in a process.
    """
    if _WARM[0]:
        return
    a = np.ones((8, 12), dtype=np.float32)
    valid = np.ones((8, 12), dtype=np.bool_)
    out = np.empty_like(a)
    # what the mapper calls (remap_pair, the ratio's pass and valid_any are compiled inside
    # map_pair and valid_extent; register_ratio and the others alone only where called)
    for alb in (np.empty_like(a), np.empty((0, 0), np.float32)):
        map_pair(a, a, np.zeros((8, 12), dtype=np.uint32), np.zeros((8, 12), np.float32),
                 np.zeros((8, 12), np.float32), np.zeros((8, 12), np.int32),
                 np.zeros((8, 12), np.int32), np.zeros(8, dtype=np.bool_), valid, 1.5, 7.1,
                 -7.1, out, alb, np.empty_like(valid))
    column_means_u16(np.ones((8, 12), dtype=np.uint16), 1, 3, 6, np.empty((2, 2), np.float32))
    valid_extent(np.ones((2, 3), dtype=bool))
    _WARM[0] = True
