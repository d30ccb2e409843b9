"""Compiled loops (numba) of the defect detectors' per-pair steps on a surface map.

The map of a pair is ~330 x 100 samples; as numpy chains, its steps were dozens of calls over
it each (masks, sums, a sort per column), which cost more than their arithmetic.  The loops
here do each step in one call, with the arithmetic of the numpy code they replace (the
map's own loops are :mod:`vision.defects.map_kernels`):

* :func:`residual_map` -- the marks' robust column profile (the densest row groups, then the
  samples near it), the residual slope, its cells' mean squares and the valid ones in order
  for their median (:func:`vision.defects.detect.residual`);
* :func:`marked_cells` -- the cells' smoothed excess over the field's median and the marked
  cells (:func:`vision.defects.detect.residual`);
* :func:`blob_strengths`, :func:`blob_mask`, :func:`row_depth` -- the blobs' mean excess,
  a blob's samples and their shadowed share, its depth below its rim
  (:func:`vision.defects.detect.blobs`);
* :func:`fold_rows` -- each row's residual folded at one revolution, the median over the
  revolutions per phase, and its mean square (:func:`vision.defects.detect.knife_nicks`);
* :func:`clipped_pairs`, :func:`cross_spectrum`, :func:`coherence_peak` -- raised grain's
  row pairs clipped into the FFT's padding, their cross-spectrum summed, and the correlations'
  peak (:func:`vision.defects.detect.oriented_coherence`);
* :func:`reference_median` -- the knife-nick folds' reference median and the rows standing
  out from it (:func:`vision.defects.detect.knife_nicks`); :func:`fold_reference`: the fold
  and it in one call;
* :func:`snipe_fit` -- the marks' profile smoothed over one mark and its quadratic
  (:func:`vision.defects.detect.snipe`);
* :func:`chatter_fit` -- the marks' heights at their lowest points, their differences and
  the best sinusoid on them (:func:`vision.defects.detect.chatter`).

Where a loop runs over a row it reads the row as a 1-D view, and where it can it is
branch-free, so that it vectorises (the shorth's column sort); a loop whose
branches the data predicts well (the folds' scatter, ~all samples valid) stays branchy: its
branch-free form measured slower in the finder's sequence.

Compiled with ``cache=True`` on first use; :func:`warm_up` compiles every one with the types
the detectors pass, so a :class:`vision.defects.detect.DefectFinder` does that at set-up, never
on a frame.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_JIT = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}


@njit(**_JIT)
def _select(v: np.ndarray, n: int, k: int) -> float:  # pragma: no cover - compiled
    """The k-th smallest of ``v[:n]`` (reorders it; Hoare's selection)."""
    lo, hi = 0, n - 1
    while lo < hi:
        pivot = v[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while v[i] < pivot:
                i += 1
            while v[j] > pivot:
                j -= 1
            if i <= j:
                v[i], v[j] = v[j], v[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return v[k]


@njit(**_JIT)
def _median(v: np.ndarray, n: int) -> float:  # pragma: no cover - compiled
    """The median of ``v[:n]`` (the mean of the two middle values for even ``n``)."""
    hi = _select(v, n, n // 2)
    if n % 2:
        return hi
    lo = v[0]
    for i in range(1, n // 2):  # the largest of the lower half, after the selection
        if v[i] > lo:
            lo = v[i]
    return 0.5 * (lo + hi)


@njit(**_JIT)
def _sort_columns(v: np.ndarray) -> None:  # pragma: no cover - compiled
    """Sort every column of ``v`` (shape (n, cols)) in place, all columns at once.

    Odd-even transposition: ``n`` rounds of compare-and-swap of neighbouring rows, each a
    loop over the columns that vectorises (for the ~16 group means of ~330 columns, several
    times faster than one insertion sort per column; the same sorted values).
    """
    n, cols = v.shape
    for rnd in range(n):
        for g in range(rnd % 2, n - 1, 2):
            lo, hi = v[g], v[g + 1]
            for c in range(cols):
                x, y = lo[c], hi[c]
                lo[c] = min(x, y)
                hi[c] = max(x, y)


@njit(**_JIT)
def _cell_means(sq: np.ndarray, vv: np.ndarray, cell: int, n_cells: int, half_cell: float,
                vc: np.ndarray, er: np.ndarray) -> None:  # pragma: no cover - compiled
    """A row's cells: each cell's mean of ``sq`` over its valid samples ``vv``.

    The sum over the cell's ``cell`` columns in order over its valid samples (``vc``: at
    least ``half_cell`` of them; ``er`` 0 where not).  Cells of 2 and 3 columns (the maps'
    ~0.4 mm) have loops of their own that vectorise: the same additions in the same order.
    """
    if cell == 3:
        for j in range(n_cells):
            acc = ((0.0 + sq[3 * j]) + sq[3 * j + 1]) + sq[3 * j + 2]
            w = (vv[3 * j] + vv[3 * j + 1]) + vv[3 * j + 2]
            ok = w >= half_cell
            vc[j] = ok
            er[j] = acc / max(w, 1) if ok else 0.0
    elif cell == 2:
        for j in range(n_cells):
            acc = (0.0 + sq[2 * j]) + sq[2 * j + 1]
            w = vv[2 * j] + vv[2 * j + 1]
            ok = w >= half_cell
            vc[j] = ok
            er[j] = acc / max(w, 1) if ok else 0.0
    else:
        for j in range(n_cells):
            b = j * cell
            acc = 0.0 + sq[b]
            w = vv[b]
            for q in range(1, cell):
                acc += sq[b + q]
                w += vv[b + q]
            ok = w >= half_cell
            vc[j] = ok
            er[j] = acc / max(w, 1) if ok else 0.0


@njit(**_JIT)
def residual_map(p: np.ndarray, valid: np.ndarray, sat_limit: float, group: int, k: int,
                 cell: int, profile: np.ndarray, r: np.ndarray, e: np.ndarray,
                 valid_cells: np.ndarray,
                 cells: np.ndarray) -> tuple[float, int]:  # pragma: no cover
    """The marks' robust column profile, the residual and its cells (see ``residual``).

    Parameters
    ----------
    p : ndarray of float32, shape (rows, cols)
        Slope along the feed.
    valid : ndarray of bool, shape (rows, cols)
    sat_limit : float
        Samples with ``|p| >= sat_limit`` (cast shadows) do not enter the profile.
    group, k : int
        Rows per group, and groups in the shorth's run.
    cell : int
        Map columns per cell.
    profile : ndarray of float64, shape (cols,)
        Out: the marks' slope profile.
    r : ndarray of float32, shape (rows, cols)
        Out: ``p - profile`` (0 outside ``valid``).
    e : ndarray of float32, shape (rows, cols // cell)
        Out: each cell's mean square of ``r`` (0 where not ``valid_cells``).
    valid_cells : ndarray of bool, shape (rows, cols // cell)
        Out: at least half the cell's samples valid.
    cells : ndarray of float32, shape (rows * (cols // cell),)
        Out: the valid cells' mean squares in row-major order (``e[valid_cells]``), first
        ``n`` of them.

    Returns
    -------
    tuple
        The median absolute deviation of the samples from the profile's first estimate
        (every third row and column), and the number of valid cells.
    """
    rows, cols = p.shape
    n_g = rows // group
    lim = np.float32(sat_limit)
    # group sums, row-major (the rows are contiguous)
    gs = np.zeros((n_g, cols))
    gw = np.zeros((n_g, cols), dtype=np.int32)
    total = np.zeros(cols)
    count = np.zeros(cols, dtype=np.int32)
    zero = np.float32(0.0)
    for i in range(rows):  # branch-free over row views (vectorises; adding 0 changes no bit)
        g = i // group
        pr, vr = p[i], valid[i]
        if g < n_g:
            gsr, gwr = gs[g], gw[g]
            for c in range(cols):
                v = pr[c]
                ok = vr[c] & (abs(v) < lim)
                x = v if ok else zero
                total[c] += x
                count[c] += ok
                gsr[c] += x
                gwr[c] += ok
        else:
            for c in range(cols):
                v = pr[c]
                ok = vr[c] & (abs(v) < lim)
                total[c] += v if ok else zero
                count[c] += ok
    loc = np.empty(cols, dtype=np.float64)
    # every column's group means sorted at once: rows of g over the columns (vectorises)
    gm = np.empty((n_g, cols))
    half = 0.5 * group
    for g in range(n_g):
        far = 1e3 + 10.0 * g
        gsr, gwr, gmr = gs[g], gw[g], gm[g]
        for c in range(cols):
            w = gwr[c]
            # groups mostly outside or shadowed: spread far apart, no run of them is tight
            gmr[c] = gsr[c] / w if (w >= half) & (w > 0) else far
    _sort_columns(gm)
    # the tightest run of k sorted group means (the first of equals), and its mean
    best = np.zeros(cols, dtype=np.int64)
    span = np.full(cols, np.inf)
    for j in range(n_g - k + 1):
        top, low = gm[j + k - 1], gm[j]
        for c in range(cols):
            sp = top[c] - low[c]
            better = sp < span[c]
            span[c] = sp if better else span[c]
            best[c] = j if better else best[c]
    run = np.zeros(cols)
    for j in range(n_g):  # the run's values in order, zeros elsewhere: the same sums
        gmr = gm[j]
        for c in range(cols):
            b = best[c]
            run[c] += gmr[c] if (j >= b) & (j < b + k) else 0.0
    for c in range(cols):
        m = run[c] / k
        if not abs(m) < 10.0:  # a column mostly outside: its plain mean
            m = total[c] / count[c] if count[c] > 0 else 0.0
        loc[c] = m
    # the deviations' robust scale (every third row and column)
    buf = np.empty(((rows + 2) // 3) * ((cols + 2) // 3), dtype=np.float64)
    nb = 0
    for i in range(0, rows, 3):
        for c in range(0, cols, 3):
            v = p[i, c]
            if valid[i, c] and abs(v) < lim:
                buf[nb] = abs(v - loc[c])
                nb += 1
    scale = _median(buf, nb) if nb > 0 else 0.0
    limit = 5.0 * 1.4826 * scale + 1e-4
    near = np.zeros(cols)
    n_near = np.zeros(cols, dtype=np.int32)
    for i in range(rows):
        pr, vr = p[i], valid[i]
        for c in range(cols):
            v = pr[c]
            ok = vr[c] & (abs(v) < lim) & (abs(v - loc[c]) <= limit)
            near[c] += v if ok else zero
            n_near[c] += ok
    for c in range(cols):
        if count[c] == 0:
            profile[c] = 0.0  # no sample of the column enters the profile
        else:
            profile[c] = near[c] / n_near[c] if n_near[c] > 0 else loc[c]
    n_cells = cols // cell
    nc = 0
    prof32 = profile.astype(np.float32)
    half_cell = 0.5 * cell
    sq = np.empty(cols)  # a row's squares (float32 products, as float64) and valid samples
    vv = np.empty(cols, dtype=np.int32)
    for i in range(rows):
        pr, vr, rr, vc, er = p[i], valid[i], r[i], valid_cells[i], e[i]
        for c in range(cols):
            x = pr[c] - prof32[c] if vr[c] else zero
            rr[c] = x
            sq[c] = x * x
            vv[c] = vr[c]
        # each cell's sum over its columns in order (r is 0 outside valid: adds nothing)
        _cell_means(sq, vv, cell, n_cells, half_cell, vc, er)
        for j in range(n_cells):  # the valid cells' values in order, for their median
            cells[nc] = er[j]
            nc += vc[j]
    return scale, nc


@njit(**_JIT)
def marked_cells(e: np.ndarray, valid_cells: np.ndarray, inv_base: float, limit: float,
                 excess: np.ndarray, marked: np.ndarray) -> None:  # pragma: no cover
    """Each cell's mean square smoothed over 3 x 3 cells, over the base, and the marked cells.

    ``excess`` is the 3 x 3 mean of ``e`` (the edges mirrored, the edge cell repeated:
    OpenCV's ``BORDER_REFLECT``) times ``inv_base``; ``marked`` where it exceeds ``limit`` on
    a valid cell (:func:`vision.defects.detect.residual`).
    """
    rows, cols = e.shape
    if cols == 0:  # no cells (the edge columns' writes would leave the arrays)
        return
    ninth = np.float32(1.0 / 9.0)
    f = np.float32(inv_base)
    lim = np.float32(limit)
    for i in range(rows):
        up, mid, low = e[max(i - 1, 0)], e[i], e[min(i + 1, rows - 1)]
        xr, mr, vr = excess[i], marked[i], valid_cells[i]
        for j in (0, cols - 1):  # the edge columns: the edge cell repeated
            jl = max(j - 1, 0)
            jr = min(j + 1, cols - 1)
            xr[j] = ((up[jl] + up[j] + up[jr]) + (mid[jl] + mid[j] + mid[jr])
                     + (low[jl] + low[j] + low[jr])) * ninth * f
        for j in range(1, cols - 1):  # the inner columns (vectorises)
            xr[j] = ((up[j - 1] + up[j] + up[j + 1]) + (mid[j - 1] + mid[j] + mid[j + 1])
                     + (low[j - 1] + low[j] + low[j + 1])) * ninth * f
        for j in range(cols):
            mr[j] = (xr[j] > lim) & vr[j]


@njit(**_JIT)
def _pairwise_mean(v: np.ndarray, lo: int, hi: int) -> float:  # pragma: no cover - compiled
    """The mean of ``v[lo:hi]`` as numpy's ``mean`` sums it (:func:`_pairwise_split`)."""
    return _pairwise_split(v, lo, 1, 0, hi - lo) / (hi - lo)


@njit(**_JIT)
def row_depth(r: np.ndarray, r0: int, r1: int, c0: int, c1: int, mask: np.ndarray,
              dx_um: float) -> float:  # pragma: no cover - compiled
    """Depth below the rim of the residual integrated along rows ``r0..r1``, columns ``c0..c1``.

    Each row's running sum (the height before each sample, ``dx_um`` per column) less the
    straight line between its rims (the means of its first and last tenth); the 90th
    percentile (linear, as ``np.percentile``) of the heights' negatives on ``mask`` (shape
    ``(r1 - r0, c1 - c0)``), 0 without one (:func:`vision.defects.detect.blobs`).  At most
    ~1270 columns (numpy's sums of a rim beyond 128 values split further).
    """
    rows = r1 - r0
    n = c1 - c0
    edge = max(1, n // 10)
    h = np.empty(n)
    vals = np.empty(rows * n)
    nv = 0
    step = 1.0 / (n - 1) if n > 1 else 0.0  # np.linspace(0, 1, n)
    for i in range(rows):
        h[0] = 0.0
        s = 0.0
        for j in range(1, n):
            s += np.float64(r[r0 + i, c0 + j - 1])
            h[j] = s * dx_um
        left = _pairwise_mean(h, 0, edge)
        right = _pairwise_mean(h, n - edge, n)
        for j in range(n):
            if mask[i, j]:
                t = j * step if j < n - 1 else 1.0
                vals[nv] = -(h[j] - (left + (right - left) * t))
                nv += 1
    if nv == 0:
        return 0.0
    q = 0.9 * (nv - 1)
    lo = int(math.floor(q))
    hi = int(math.ceil(q))
    a = _select(vals, nv, lo)
    b = _select(vals, nv, hi)
    return a + (b - a) * (q - lo)


@njit(**_JIT)
def blob_strengths(labels: np.ndarray, stats: np.ndarray, excess: np.ndarray,
                   large: np.ndarray, strength: np.ndarray) -> None:  # pragma: no cover
    """The mean excess of the groups ``large``: each one's cells in its box, summed in order.

    ``strength[lab]`` is the sum (float64, row by row through the group's bounding box, as
    ``np.cumsum`` sums them) of ``excess`` over the cells labelled ``lab``, over the group's
    area (``stats``: OpenCV's connected components' left, top, width, height, area)
    (:func:`vision.defects.detect.blobs`).
    """
    for q in range(large.size):
        lab = large[q]
        x, y, w, h = stats[lab, 0], stats[lab, 1], stats[lab, 2], stats[lab, 3]
        acc = 0.0
        for i in range(y, y + h):
            lr, er = labels[i], excess[i]
            for j in range(x, x + w):
                if lr[j] == lab:
                    acc += np.float64(er[j])
        strength[lab] = acc / np.float64(stats[lab, 4])


@njit(**_JIT)
def blob_mask(labels: np.ndarray, lab: int, x: int, y: int, w: int, cell: int, c0: int,
              p: np.ndarray, limit: float, mask: np.ndarray) -> float:  # pragma: no cover
    """A group's samples on the map and the share of them at the shadow's slope.

    ``mask`` (shape ``(h, c1 - c0)``, rows ``y..y + h``, map columns ``c0..c1``) is True on
    the samples of the cells labelled ``lab`` in the box ``x..x + w`` (each cell ``cell``
    map columns from column ``x * cell``); returns the share of them whose ``|p|`` is at
    least ``limit`` (:func:`vision.defects.detect.blobs`).
    """
    h, n = mask.shape
    m0 = x * cell - c0
    lim = np.float32(limit)  # as numpy compares float32 samples with a Python float
    hits = 0
    total = 0
    for i in range(h):
        mr, lr, pr = mask[i], labels[y + i], p[y + i]
        for j in range(n):
            mr[j] = False
        for j in range(w * cell):
            if lr[x + j // cell] == lab:
                mr[m0 + j] = True
                total += 1
                hits += abs(pr[c0 + m0 + j]) >= lim
    return hits / total if total > 0 else np.nan


@njit(**_JIT)
def _fold_columns(c0: int, x1: int, period: float, nb: int,
                  n_per: int) -> tuple:  # pragma: no cover - compiled
    """:func:`fold_rows`' table of its columns ``c0..x1`` (set up once per call).

    Each column's (period, bin) cell and its bin alone, and the columns per cell and per bin.
    Columns past the last period go to a spare cell / bin (``n_per * nb``, ``nb``) that is
    never read.
    """
    n_cells = n_per * nb
    span = max(x1 - c0, 0)
    where = np.empty(span, dtype=np.int64)
    phase = np.empty(span, dtype=np.int64)
    full_cell = np.zeros(n_cells + 1, dtype=np.int64)
    full_bin = np.zeros(nb + 1, dtype=np.int64)
    for c in range(c0, x1):
        ph = (c - c0) / period
        per = int(math.floor(ph))
        b = min(int(math.floor((ph - per) * nb)), nb - 1)
        where[c - c0] = per * nb + b if per < n_per else n_cells
        phase[c - c0] = b if per < n_per else nb
        full_cell[where[c - c0]] += 1
        full_bin[phase[c - c0]] += 1
    return where, phase, full_cell, full_bin


@njit(**_JIT)
def _taken_rows(plain: np.ndarray, every: int, slack: float, folded: np.ndarray,
                energy: np.ndarray) -> tuple:  # pragma: no cover - compiled
    """:func:`fold_rows`' rows that take the median fold, ``(rows, how many)``.

    Every ``every``-th row with a plain mean fold and those whose plain fold's mean square
    ``plain`` is at least ``slack`` times the median row's; ``folded`` and ``energy`` are
    set to NaN on every row (the taken ones' are written later).
    """
    rows, nb = folded.shape
    buf = np.empty(rows)
    n_ok = 0
    for i in range(rows):
        if not np.isnan(plain[i]):
            buf[n_ok] = plain[i]
            n_ok += 1
    limit = slack * _median(buf, n_ok) if n_ok > 0 else np.inf
    taken = np.empty(rows, dtype=np.int64)
    n_taken = 0
    for i in range(rows):
        energy[i] = np.nan
        for b in range(nb):
            folded[i, b] = np.nan
        if not (np.isnan(plain[i]) or (i % every != 0 and plain[i] < limit)):
            taken[n_taken] = i
            n_taken += 1
    return taken, n_taken


@njit(**_JIT)
def _fold_medians(cm: np.ndarray, seen: np.ndarray, taken: np.ndarray, n_taken: int,
                  folded: np.ndarray, energy: np.ndarray) -> None:  # pragma: no cover
    """:func:`fold_rows`' medians of the taken rows from their sorted columns ``cm``.

    Column ``t * nb + b`` holds row ``taken[t]``'s bin ``b`` over the periods, its ``seen``
    valid ones first: the median is the middle of those; ``energy`` the mean square of the
    row's medians.
    """
    nb = folded.shape[1]
    for t in range(n_taken):
        i = taken[t]
        s2 = 0.0
        nbins = 0
        for b in range(nb):
            m = seen[t * nb + b]
            if m == 0:
                continue
            hi = cm[m // 2, t * nb + b]
            med = hi if m % 2 else 0.5 * (cm[m // 2 - 1, t * nb + b] + hi)
            folded[i, b] = med
            s2 += med * med
            nbins += 1
        if nbins > 0:
            energy[i] = s2 / nbins


@njit(**_JIT)
def fold_rows(r: np.ndarray, valid: np.ndarray, c0: int, period: float, nb: int, n_per: int,
              min_valid: int, every: int, slack: float, folded: np.ndarray,
              energy: np.ndarray) -> None:  # pragma: no cover - compiled
    """Rows of the residual folded at ``period`` columns from column ``c0``.

    Per row, the mean of its valid samples in each (period, phase bin) cell, then per phase
    bin the median over the periods that saw it.  The medians are taken on every
    ``every``-th row (the reference) and on the rows whose residual folded as the plain mean
    over all periods (cheap) has a mean square above ``slack`` times the median row's: a
    row whose median fold stands out has a mean fold that does too.  A row valid over all
    its folded columns (nearly every row) takes the columns' counts per bin and cell, set up
    once, and sums without a test per sample; the taken rows' medians come from one sort of
    all their (row, bin) columns of period means at once (:func:`_sort_columns`; the same
    values as a selection per bin).

    Parameters
    ----------
    r : ndarray of float32, shape (rows, cols)
    valid : ndarray of bool, shape (rows, cols)
    c0 : int
        First column of the first period.
    period : float
        Columns per period.
    nb, n_per : int
        Phase bins per period, and periods.
    min_valid : int
        Rows with fewer valid samples are left out (``energy`` NaN).
    every : int
        The median fold is taken on every ``every``-th row.
    slack : float
        ... and on the rows whose mean fold's mean square is above ``slack`` times the
        median row's.
    folded : ndarray of float64, shape (rows, nb)
        Out: the median fold (NaN where not taken or no period saw the bin).
    energy : ndarray of float64, shape (rows,)
        Out: the mean square of ``folded`` over its bins (NaN where not taken).
    """
    rows, cols = r.shape
    x1 = min(cols, c0 + int(n_per * period))
    span = max(x1 - c0, 0)
    n_cells = n_per * nb
    where, phase, full_cell, full_bin = _fold_columns(c0, x1, period, nb, n_per)
    # the plain mean fold of every row; a row valid over all its folded columns (nearly
    # every row) takes the columns' counts, set up once, and sums without a test per sample
    plain = np.full(rows, np.nan)
    bsum = np.zeros(nb + 1)
    bcount = np.zeros(nb + 1, dtype=np.int64)
    whole = np.zeros(rows, dtype=np.bool_)
    for i in range(rows):
        vr, rr = valid[i], r[i]
        nv = 0
        for c in range(cols):
            nv += vr[c]
        if nv < min_valid:
            continue
        inside = 0
        for c in range(c0, x1):
            inside += vr[c]
        whole[i] = inside == span
        bsum[:] = 0.0
        if whole[i]:
            bcount[:] = full_bin
            for c in range(c0, x1):
                bsum[phase[c - c0]] += rr[c]
        else:
            bcount[:] = 0
            for c in range(c0, x1):
                if vr[c]:
                    bsum[phase[c - c0]] += rr[c]
                    bcount[phase[c - c0]] += 1
        s2 = 0.0
        n = 0
        for b in range(nb):
            if bcount[b] > 0:
                m = bsum[b] / bcount[b]
                s2 += m * m
                n += 1
        if n > 0:
            plain[i] = s2 / n
    taken, n_taken = _taken_rows(plain, every, slack, folded, energy)
    # the taken rows' cell means, one column per (row, bin), the periods down the rows;
    # +inf where no sample of the cell is valid (sorted last: the finite ones first, so the
    # median of a bin's m valid periods is the middle of its first m sorted values)
    lanes = n_taken * nb
    cm = np.empty((n_per, lanes))
    seen = np.zeros(lanes, dtype=np.int64)
    sums = np.zeros(n_cells + 1)
    counts = np.zeros(n_cells + 1, dtype=np.int64)
    for t in range(n_taken):
        i = taken[t]
        vr, rr = valid[i], r[i]
        sums[:] = 0.0
        if whole[i]:
            counts[:] = full_cell
            for c in range(c0, x1):
                sums[where[c - c0]] += rr[c]
        else:
            counts[:] = 0
            for c in range(c0, x1):
                if vr[c]:
                    sums[where[c - c0]] += rr[c]
                    counts[where[c - c0]] += 1
        for per in range(n_per):
            row = cm[per]
            for b in range(nb):
                q = per * nb + b
                if counts[q] > 0:
                    row[t * nb + b] = sums[q] / counts[q]
                    seen[t * nb + b] += 1
                else:
                    row[t * nb + b] = np.inf
    _sort_columns(cm)  # every (row, bin) at once: the same values as one selection each
    _fold_medians(cm, seen, taken, n_taken, folded, energy)


@njit(**_JIT)
def clipped_pairs(r: np.ndarray, rows: np.ndarray, limit: float, out: np.ndarray,
                  r2: np.ndarray) -> None:  # pragma: no cover - compiled
    """The rows ``rows`` of the residual clipped to ``+-limit``, zero-padded, and their power.

    ``out[k, :cols]`` is ``r[rows[k]]`` clipped, zero beyond (the FFT's padding: ``out``
    may come uninitialised); ``r2[k]`` the sum of its squares (float64, in order)
    (:func:`vision.defects.detect.oriented_coherence`).  The rows are clipped in one loop that
    vectorises, and four rows' sums run side by side (each still in order: the same sums,
    without waiting on one chain of additions).
    """
    cols = r.shape[1]
    width = out.shape[1]
    hi = np.float32(limit)
    lo = -hi
    zero = np.float32(0.0)
    n = rows.size
    for k in range(n):
        src, dst = r[rows[k]], out[k]
        for c in range(cols):
            dst[c] = min(max(src[c], lo), hi)
        for c in range(cols, width):
            dst[c] = zero
    k = 0
    while k + 4 <= n:
        a, b, c_, d = out[k], out[k + 1], out[k + 2], out[k + 3]
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        s3 = 0.0
        for c in range(cols):
            s0 += a[c] * a[c]
            s1 += b[c] * b[c]
            s2 += c_[c] * c_[c]
            s3 += d[c] * d[c]
        r2[k] = s0
        r2[k + 1] = s1
        r2[k + 2] = s2
        r2[k + 3] = s3
        k += 4
    while k < n:
        a = out[k]
        s0 = 0.0
        for c in range(cols):
            s0 += a[c] * a[c]
        r2[k] = s0
        k += 1


@njit(**_JIT)
def cross_spectrum(f: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``out = sum_k conj(f[2 k]) f[2 k + 1]`` over the row pairs, in order (complex64).

    numpy's ``(np.conj(f[0::2]) * f[1::2]).sum(axis=0)`` without its two temporaries (its
    numbers to float32 rounding).
    """
    n = f.shape[1]
    for j in range(n):
        out[j] = 0
    for k in range(f.shape[0] // 2):
        a, b = f[2 * k], f[2 * k + 1]
        for j in range(n):
            out[j] += np.conj(a[j]) * b[j]


@njit(**_JIT)
def _pairwise_block(v: np.ndarray, start: int, step: int, i0: int,
                    n: int) -> float:  # pragma: no cover - compiled
    """The pairwise sum numpy takes of ``n <= 128`` strided values from ``i0`` (its leaf).

    Fewer than 8 values in order; more in eight interleaved partial sums, then the rest in
    order (:func:`_pairwise_mean`'s order).
    """
    if n < 8:
        s = 0.0
        for i in range(n):
            s += v[start + (i0 + i) * step]
        return s
    r = np.empty(8)
    for q in range(8):
        r[q] = v[start + (i0 + q) * step]
    i = 8
    while i < n - n % 8:
        for q in range(8):
            r[q] += v[start + (i0 + i + q) * step]
        i += 8
    s = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    while i < n:
        s += v[start + (i0 + i) * step]
        i += 1
    return s


@njit(**_JIT)
def _pairwise_sum(v: np.ndarray, start: int, step: int) -> float:  # pragma: no cover
    """``v[start::step].sum()`` as numpy sums it (float64): the same bits at any length.

    numpy's pairwise summation: blocks of at most 128 values (:func:`_pairwise_block`); a
    longer run split at half its length rounded down to a multiple of 8, each part summed
    alike and the two added (:func:`_pairwise_split`).
    """
    n = (v.size - start + step - 1) // step if v.size > start else 0
    return _pairwise_split(v, start, step, 0, n)


@njit(**_JIT)
def _pairwise_split(v: np.ndarray, start: int, step: int, i0: int,
                    n: int) -> float:  # pragma: no cover - compiled
    """The pairwise sum numpy takes of ``n`` strided values from value ``i0`` (any ``n``).

    numpy's recursion, walked with explicit stacks (a cached compiled recursive function
    crashed when loaded from numba's cache): a run of ``n > 128`` values splits at
    ``n2 = n // 2 - (n // 2) % 8``, each part summed alike, left plus right.
    """
    if n <= 128:  # one block: numpy's leaf
        return _pairwise_block(v, start, step, i0, n)
    run_i = np.empty(64, dtype=np.int64)  # depth log2(n / 128): 64 covers any length
    run_n = np.empty(64, dtype=np.int64)
    state = np.zeros(64, dtype=np.int64)  # 0: split it, 1: its left part summed, 2: both
    sums = np.empty(65)
    run_i[0], run_n[0], state[0] = i0, n, 0
    top, k = 0, 0
    while top >= 0:
        i, m = run_i[top], run_n[top]
        if m <= 128:
            sums[k] = _pairwise_block(v, start, step, i, m)
            k += 1
            top -= 1
            continue
        n2 = m // 2
        n2 -= n2 % 8
        if state[top] == 0:  # its left part next
            state[top] = 1
            top += 1
            run_i[top], run_n[top], state[top] = i, n2, 0
        elif state[top] == 1:  # then its right part
            state[top] = 2
            top += 1
            run_i[top], run_n[top], state[top] = i + n2, m - n2, 0
        else:  # both summed: left plus right
            sums[k - 2] = sums[k - 2] + sums[k - 1]
            k -= 1
            top -= 1
    return sums[0]


@njit(**_JIT)
def coherence_peak(x: np.ndarray, r2: np.ndarray,
                   max_lag: int) -> tuple:  # pragma: no cover - compiled
    """The rows' correlation peak over lags ``-max_lag..max_lag`` (raised grain's last step).

    ``x``: the summed cross-correlation (float32, the inverse FFT's, lags 0.. then negative
    lags from the end); ``r2``: the row pairs' powers.  As numpy: ``norm = (r2[0::2].sum() *
    r2[1::2].sum()) ** 0.5``, the float32 correlations at lags 0..max_lag then -max_lag..-1
    over it, the first largest (``np.argmax``: the first NaN).  Returns ``(peak, at lag 0,
    lag, ok)``; ``ok`` False where ``norm <= 0`` (no correlation).
    """
    norm = (_pairwise_sum(r2, 0, 2) * _pairwise_sum(r2, 1, 2)) ** 0.5
    if norm <= 0:
        return 0.0, 0.0, 0, False
    f = np.float32(norm)
    n = x.size
    best = np.float32(0.0)
    k = -1
    at0 = x[0] / f
    for q in range(2 * max_lag + 1):
        v = x[q] / f if q <= max_lag else x[n - (2 * max_lag + 1) + q] / f
        if k < 0 or v > best or (np.isnan(v) and not np.isnan(best)):
            best, k = v, q
        if np.isnan(best):
            break  # np.argmax stops at the first NaN
    lag = k if k <= max_lag else k - (2 * max_lag + 1)
    return float(best), float(at0), lag, True


@njit(**_JIT)
def snipe_fit(profile: np.ndarray, c0: int, c1: int, k: int,
              dx: float) -> tuple[float, float]:  # pragma: no cover - compiled
    """``(c2, c1)`` of ``c2 x^2 + c1 x + c0`` fitted to the profile smoothed over ``k`` columns.

    ``profile[c0:c1]`` averaged over ``k`` columns (``np.convolve(y, np.ones(k) / k,
    "valid")``; not when ``k < 1`` or ``k >= (c1 - c0) // 3``), then the least-squares
    quadratic in ``x`` spaced ``dx`` apart and centred on the middle sample
    (:func:`vision.defects.detect.snipe`).
    """
    n = c1 - c0
    w = 1.0 / k if k >= 1 else 1.0
    smooth = 1 <= k < n // 3
    if smooth:
        n = n - k + 1
    m = 0.5 * (n - 1)
    sy = 0.0
    sxy = 0.0
    sx2y = 0.0
    for j in range(n):
        if smooth:
            v = 0.0
            for q in range(k):
                v += profile[c0 + j + q] * w
        else:
            v = profile[c0 + j]
        i = j - m
        sy += v
        sxy += i * v
        sx2y += i * i * v
    s2 = n * (n * n - 1.0) / 12.0 * dx ** 2  # sum x^2
    s4 = n * (n * n - 1.0) * (3.0 * n * n - 7.0) / 240.0 * dx ** 4  # sum x^4
    det = s4 * n - s2 * s2
    return (n * sx2y * dx ** 2 - s2 * sy) / det, sxy * dx / s2


@njit(**_JIT)
def reference_median(energy: np.ndarray, every: int, ratio: float,
                     out: np.ndarray) -> None:  # pragma: no cover - compiled
    """The median of the finite ``energy[::every]`` and how many rows stand out from it.

    ``out = (n, median, hot)``: ``n`` finite reference energies, their median (the mean of
    the two middle ones for even ``n``; 0 without any) and the rows whose
    ``energy / max(median, 1e-18) >= ratio`` (:func:`vision.defects.detect.knife_nicks`).
    """
    buf = np.empty((energy.size + every - 1) // every)
    n = 0
    for i in range(0, energy.size, every):
        v = energy[i]
        if np.isfinite(v):
            buf[n] = v
            n += 1
    median = _median(buf, n) if n > 0 else 0.0
    m = max(median, 1e-18)
    hot = 0
    for i in range(energy.size):
        hot += energy[i] / m >= ratio  # NaN: never
    out[0] = n
    out[1] = median
    out[2] = hot


@njit(**_JIT)
def fold_reference(r: np.ndarray, valid: np.ndarray, c0: int, period: float, nb: int,
                   n_per: int, min_valid: int, every: int, slack: float, ratio: float,
                   folded: np.ndarray, energy: np.ndarray) -> tuple:  # pragma: no cover
    """:func:`fold_rows`, then :func:`reference_median` on its energies, in one call.

    Returns ``(n, median, hot)``: the finite reference energies, their median and the rows
    standing out ``ratio`` times from it (:func:`vision.defects.detect.knife_nicks`).
    """
    fold_rows(r, valid, c0, period, nb, n_per, min_valid, every, slack, folded, energy)
    stats = np.empty(3)
    reference_median(energy, every, ratio, stats)
    return int(stats[0]), stats[1], int(stats[2])

@njit(**_JIT)
def _mark_differences(profile: np.ndarray, cols_per_mm: float, xs: np.ndarray,
                      bottoms: np.ndarray, d: np.ndarray) -> None:  # pragma: no cover
    """The differences of the marks' lowest points' heights from one mark to the next, um.

    ``np.diff(np.interp(bottoms, xs, np.cumsum(profile) * 1000.0 / cols_per_mm))`` into ``d``
    (shape ``bottoms.size - 1``): the same sums in the same order, numpy's interpolation (numba's
    facsimile of it).
    """
    n = profile.size
    h = np.empty(n)
    acc = 0.0
    for c in range(n):
        acc += profile[c]
        h[c] = acc * 1000.0 / cols_per_mm
    at = np.interp(bottoms, xs, h)
    for i in range(d.size):
        d[i] = at[i + 1] - at[i]


@njit(**_JIT)
def sinusoid_fit(d: np.ndarray, knives: int, trend: np.ndarray, tt: float,
                  waves: np.ndarray, coef: np.ndarray) -> tuple:  # pragma: no cover - compiled
    """Chatter's best sinusoid on the differences ``d`` (``detect._chatter_basis``'s basis).

    Each knife's mean and the trend removed from ``d``, the least-squares sine and cosine of
    every frequency (``waves[0]``, ``waves[1]``: shape (frequencies, m); ``coef``: rows
    ``f, gss, gsc, gcc, det``), the one explaining most.  Returns ``(explained, amp_d, noise,
    amp)`` as :func:`vision.defects.detect.chatter` reads them.  The sums run in order (numpy's
    matrix products sum in BLAS's order: the same numbers to ~1e-15 relative).
    """
    m = d.size
    e = np.empty(m)
    for k in range(knives):  # each knife's mean (its samples times 1 / their count, in order)
        w = 1.0 / len(range(k, m, knives))
        s = 0.0
        for j in range(k, m, knives):
            s += d[j] * w
        for j in range(k, m, knives):
            e[j] = d[j] - s
    te = 0.0
    for j in range(m):
        te += trend[j] * e[j]
    ee = 0.0
    for j in range(m):
        e[j] = e[j] - trend[j] * te / tt
        ee += e[j] * e[j]
    ee = max(ee, 1e-18)
    sn, cs = waves[0], waves[1]
    best = -np.inf
    k = -1
    best_s = 0.0
    best_c = 0.0
    for q in range(sn.shape[0]):
        rs, rc = sn[q], cs[q]
        bs = 0.0
        bc = 0.0
        for j in range(m):
            bs += rs[j] * e[j]
            bc += rc[j] * e[j]
        gss, gsc, gcc, det = coef[1, q], coef[2, q], coef[3, q], coef[4, q]
        a_s = (gcc * bs - gsc * bc) / det
        a_c = (gss * bc - gsc * bs) / det
        fitted = a_s * bs + a_c * bc
        if k < 0 or fitted > best or (np.isnan(fitted) and not np.isnan(best)):
            best, k, best_s, best_c = fitted, q, a_s, a_c  # np.argmax: the first NaN or max
    explained = best / ee
    amp_d = math.hypot(best_s, best_c)
    noise = math.sqrt(max(ee - best, 0.0) / m) * math.sqrt(2.0 / m)
    amp = amp_d / (2.0 * math.sin(math.pi * coef[0, k]))
    return explained, amp_d, noise, amp


@njit(**_JIT)
def chatter_fit(profile: np.ndarray, cols_per_mm: float, xs: np.ndarray, bottoms: np.ndarray,
                knives: int, trend: np.ndarray, tt: float, waves: np.ndarray,
                coef: np.ndarray) -> tuple:  # pragma: no cover - compiled
    """Chatter's fit of one pair in one call (:func:`vision.defects.detect.chatter`).

    The marks' heights at their lowest points, their differences
    (:func:`_mark_differences`) and the best sinusoid on them (:func:`sinusoid_fit`).
    """
    d = np.empty(bottoms.size - 1)
    _mark_differences(profile, cols_per_mm, xs, bottoms, d)
    return sinusoid_fit(d, knives, trend, tt, waves, coef)


_WARM = [False]


def warm_up() -> None:
    """Compile (or load from the cache) the kernels the detectors call, for the map's types.

    Called by :class:`vision.defects.detect.DefectFinder` at set-up; idempotent and cheap
    after the first call in a process.
    """
    if _WARM[0]:
        return
    a = np.ones((8, 12), dtype=np.float32)
    valid = np.ones((8, 12), dtype=np.bool_)
    out = np.empty_like(a)
    cells = np.empty((8, 4), dtype=np.float32)
    residual_map(a, valid, 0.07, 2, 2, 3, np.empty(12), out, cells,
                 np.empty((8, 4), dtype=np.bool_), np.empty(32, dtype=np.float32))
    row_depth(a, 0, 4, 0, 10, np.ones((4, 10), dtype=np.bool_), 160.0)
    labels = np.zeros((8, 4), dtype=np.int32)
    stats = np.ones((2, 5), dtype=np.int32)
    blob_strengths(labels, stats, cells, np.array([1], dtype=np.int64), np.zeros(2))
    blob_mask(labels, 1, 0, 0, 1, 3, 0, a, 0.5, np.empty((1, 6), dtype=np.bool_))
    pad = np.zeros((2, 16), dtype=np.float32)
    clipped_pairs(a, np.array([0, 1], dtype=np.int64), 0.5, pad, np.empty(2))
    cross_spectrum(np.ones((2, 9), dtype=np.complex64), np.empty(9, dtype=np.complex64))
    snipe_fit(np.ones(40), 2, 38, 3, 0.16)
    coherence_peak(np.ones(16, dtype=np.float32), np.ones(6), 3)
    fold_reference(a, valid, 0, 4.0, 4, 3, 6, 4, 0.3, 12.0, np.empty((8, 4)), np.empty(8))
    fixed = [np.arange(40.0), np.ones(14), np.ones((2, 3, 14)), np.ones((5, 3))]
    for v in fixed:  # read-only, as the caches hand them over
        v.flags.writeable = False
    chatter_fit(np.ones(40), 6.25, fixed[0], np.linspace(2.0, 30.0, 15), 2, fixed[1], 14.0,
                fixed[2], fixed[3])
    marked_cells(cells, np.ones((8, 4), dtype=np.bool_), 2.0, 4.0, np.empty_like(cells),
                 np.empty((8, 4), dtype=np.bool_))
    _WARM[0] = True
