"""The defects' compiled loops pinned to their earlier forms: random inputs, the same bits.

Each loop restructured for speed keeps the arithmetic of the form it replaced (the same
additions in the same order, the same selections); the earlier forms are kept here.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from numba import njit

from config.rig import Camera, Lights
from vision.defects import kernels, map_kernels
from vision.defects.surface_map import SurfaceMap, SurfaceMapper, _Taps


@njit(cache=False)
def old_fold_rows(r: np.ndarray, valid: np.ndarray, c0: int, period: float, nb: int, n_per: int,
              min_valid: int, every: int, slack: float, folded: np.ndarray,
              energy: np.ndarray) -> None:
    """``kernels.fold_rows`` as it was: a pass per row, one selection per phase bin."""
    rows, cols = r.shape
    x1 = min(cols, c0 + int(n_per * period))
    where = np.empty(max(x1 - c0, 0), dtype=np.int64)  # (period, bin) cell of each column
    phase = np.empty(max(x1 - c0, 0), dtype=np.int64)  # and its bin alone
    for c in range(c0, x1):
        ph = (c - c0) / period
        per = int(math.floor(ph))
        b = min(int(math.floor((ph - per) * nb)), nb - 1)
        where[c - c0] = per * nb + b if per < n_per else -1
        phase[c - c0] = b if per < n_per else -1
    sums = np.zeros(n_per * nb)
    counts = np.zeros(n_per * nb, dtype=np.int64)
    vals = np.empty(n_per)
    # the plain mean fold of every row
    plain = np.full(rows, np.nan)
    bsum = np.zeros(nb)
    bcount = np.zeros(nb, dtype=np.int64)
    for i in range(rows):
        nv = 0
        for c in range(cols):
            if valid[i, c]:
                nv += 1
        if nv < min_valid:
            continue
        bsum[:] = 0.0
        bcount[:] = 0
        for c in range(c0, x1):
            b = phase[c - c0]
            if valid[i, c] and b >= 0:
                bsum[b] += r[i, c]
                bcount[b] += 1
        s2 = 0.0
        n = 0
        for b in range(nb):
            if bcount[b] > 0:
                m = bsum[b] / bcount[b]
                s2 += m * m
                n += 1
        if n > 0:
            plain[i] = s2 / n
    buf = np.empty(rows)
    n_ok = 0
    for i in range(rows):
        if not np.isnan(plain[i]):
            buf[n_ok] = plain[i]
            n_ok += 1
    limit = slack * kernels._median(buf, n_ok) if n_ok > 0 else np.inf
    for i in range(rows):
        energy[i] = np.nan
        for b in range(nb):
            folded[i, b] = np.nan
        if np.isnan(plain[i]) or (i % every != 0 and plain[i] < limit):
            continue
        sums[:] = 0.0
        counts[:] = 0
        for c in range(c0, x1):
            q = where[c - c0]
            if valid[i, c] and q >= 0:
                sums[q] += r[i, c]
                counts[q] += 1
        s2 = 0.0
        nbins = 0
        for b in range(nb):
            m = 0
            for per in range(n_per):
                q = per * nb + b
                if counts[q] > 0:
                    vals[m] = sums[q] / counts[q]
                    m += 1
            if m == 0:
                continue
            med = kernels._median(vals, m)
            folded[i, b] = med
            s2 += med * med
            nbins += 1
        if nbins > 0:
            energy[i] = s2 / nbins


@njit(cache=False)
def old_cell_means(sq, vv, cell, n_cells, half_cell, vc, er):
    """The residual's cells as ``kernels.residual_map`` summed them: one loop for any cell."""
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


def _fold_case(rng):
    rows, cols = int(rng.integers(8, 60)), int(rng.integers(40, 300))
    period = float(rng.uniform(4.0, 30.0))
    c0 = int(rng.integers(0, 10))
    n_per = max(1, int((cols - c0) // period))
    r = rng.standard_normal((rows, cols)).astype(np.float32)
    if rng.random() < 0.5:
        r = np.round(r, 1)  # ties among the periods' means
    for i in rng.integers(0, rows, 3):  # rows that stand out
        r[i] += np.where(np.arange(cols) % period < period / 4, 3.0, 0.0).astype(np.float32)
    valid = rng.random((rows, cols)) > rng.choice([0.0, 0.01, 0.3])
    if rng.random() < 0.3:
        valid[:, :c0] = False
    valid[int(rng.integers(0, rows)), :] = False
    r = np.where(valid, r, 0.0).astype(np.float32)
    return (r, valid, c0, period, max(4, int(round(period))), n_per,
            int(rng.integers(1, cols)), int(rng.integers(1, 9)), float(rng.uniform(0.5, 5.0)))


@pytest.mark.parametrize("seed", range(6))
def test_fold_rows_is_its_earlier_form(seed):
    """Whole rows summed without a test per sample and every bin's median from one sort of
    all the taken rows' periods: the same folds and energies, bit for bit."""
    rng = np.random.default_rng(seed)
    for _ in range(40):
        r, valid, c0, period, nb, n_per, min_valid, every, slack = _fold_case(rng)
        rows = r.shape[0]
        got = np.empty((rows, nb)), np.empty(rows)
        ref = np.empty((rows, nb)), np.empty(rows)
        kernels.fold_rows(r, valid, c0, period, nb, n_per, min_valid, every, slack, *got)
        old_fold_rows(r, valid, c0, period, nb, n_per, min_valid, every, slack, *ref)
        assert np.array_equal(got[0], ref[0], equal_nan=True)
        assert np.array_equal(got[1], ref[1], equal_nan=True)


@pytest.mark.parametrize("seed", range(4))
def test_fold_reference_is_the_fold_then_its_reference_median(seed):
    """The knife nicks' two calls in one: the same folds, energies and reference statistics."""
    rng = np.random.default_rng(100 + seed)
    hot = 0
    for _ in range(40):
        r, valid, c0, period, nb, n_per, min_valid, every, slack = _fold_case(rng)
        ratio = float(rng.uniform(1.5, 12.0))
        rows = r.shape[0]
        got = np.empty((rows, nb)), np.empty(rows)
        ref = np.empty((rows, nb)), np.empty(rows)
        stats = kernels.fold_reference(r, valid, c0, period, nb, n_per, min_valid, every,
                                       slack, ratio, *got)
        kernels.fold_rows(r, valid, c0, period, nb, n_per, min_valid, every, slack, *ref)
        want = np.empty(3)
        kernels.reference_median(ref[1], every, ratio, want)
        assert np.array_equal(got[0], ref[0], equal_nan=True)
        assert np.array_equal(got[1], ref[1], equal_nan=True)
        assert stats == (int(want[0]), float(want[1]), int(want[2]))
        assert isinstance(stats[0], int) and isinstance(stats[2], int)
        hot += stats[2] > 0
    assert hot > 0


@pytest.mark.parametrize("cell", [1, 2, 3, 4, 5])
def test_cell_means_are_their_earlier_form(cell):
    rng = np.random.default_rng(cell)
    for _ in range(30):
        n_cells = int(rng.integers(0, 120))
        x = rng.standard_normal(n_cells * cell + int(rng.integers(0, cell))).astype(np.float32)
        sq = (x * x).astype(np.float64)
        vv = (rng.random(x.size) > rng.choice([0.0, 0.4])).astype(np.int32)
        half = 0.5 * cell
        got = np.empty(n_cells, bool), np.empty(n_cells, np.float32)
        ref = np.empty(n_cells, bool), np.empty(n_cells, np.float32)
        kernels._cell_means(sq, vv, cell, n_cells, half, *got)
        old_cell_means(sq, vv, cell, n_cells, half, *ref)
        assert np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1])


def _labelled(rng, rows=40, cols=60):
    """A map's marked cells and their groups, as ``vision.defects.detect.blobs`` labels them."""
    marked = (rng.random((rows, cols)) < rng.uniform(0.05, 0.5)).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStatsWithAlgorithm(
        marked, 8, cv2.CV_32S, cv2.CCL_BBDT)
    return n, labels, stats


@pytest.mark.parametrize("seed", range(4))
def test_blob_strengths_are_their_earlier_form(seed):
    rng = np.random.default_rng(seed)
    for _ in range(20):
        n, labels, stats = _labelled(rng)
        excess = (10.0 * rng.random(labels.shape)).astype(np.float32)
        large = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] >= rng.integers(1, 6))
        large = large[large > 0]
        got = np.zeros(n)
        kernels.blob_strengths(labels, stats, excess, large, got)
        ref = np.zeros(n)
        area = stats[:, cv2.CC_STAT_AREA].astype(np.float64)
        for lab in large.tolist():  # the earlier form: numpy over each group's box
            x, y, w, h = (int(v) for v in stats[lab, :4])
            box = excess[y:y + h, x:x + w][labels[y:y + h, x:x + w] == lab]
            ref[lab] = float(np.cumsum(box, dtype=np.float64)[-1]) / area[lab]
        assert np.array_equal(got, ref)


@pytest.mark.parametrize("cell", [1, 2, 3])
def test_blob_mask_is_its_earlier_form(cell):
    """The blob's samples and their shadowed share as numpy made them (its float32
    comparison with the Python float limit included)."""
    rng = np.random.default_rng(cell)
    for _ in range(10):
        n, labels, stats = _labelled(rng)
        p = (0.2 * rng.standard_normal((labels.shape[0], labels.shape[1] * cell))
             ).astype(np.float32)
        limit = 0.7 * float(rng.uniform(0.05, 0.3))
        p[0, :4] = np.float32(limit)  # samples on the limit, either side of its float32
        for lab in range(1, n):
            x, y, w, h = (int(v) for v in stats[lab, :4])
            pad = max(2, w // 2) * cell
            c0, c1 = max(0, x * cell - pad), min(p.shape[1], (x + w) * cell + pad)
            got = np.empty((h, c1 - c0), bool)
            share = kernels.blob_mask(labels, lab, x, y, w, cell, c0, p, limit, got)
            ref = np.zeros((h, c1 - c0), dtype=bool)  # the earlier form
            m0 = x * cell - c0
            ref[:, m0:m0 + w * cell] = np.repeat(labels[y:y + h, x:x + w] == lab, cell, axis=1)
            assert np.array_equal(got, ref)
            assert share == float(np.mean(np.abs(p[y:y + h, c0:c1][ref]) >= limit))


@pytest.mark.parametrize("n_rows", [1, 3, 4, 6, 9])
def test_clipped_pairs_power_is_its_earlier_form(n_rows):
    """Four rows' sums side by side: each row's squares still added in order, the same bits."""
    rng = np.random.default_rng(n_rows)
    r = rng.standard_normal((12, 101)).astype(np.float32)
    rows = rng.integers(0, 12, n_rows).astype(np.int64)
    out = np.full((n_rows, 120), np.nan, np.float32)
    r2 = np.empty(n_rows)
    kernels.clipped_pairs(r, rows, 1.2, out, r2)
    for k in range(n_rows):  # the earlier form: one chain per row
        s = 0.0
        for x in np.clip(r[rows[k]], np.float32(-1.2), np.float32(1.2)):
            s += float(x * x)
        assert r2[k] == s
    assert not out[:, 101:].any()


@pytest.mark.parametrize("where", ["inside", "edges", "anywhere"])
def test_remap_pair_is_opencvs_remap(where):
    """Both images sampled at once with the table's taps: cv2.remap's numbers (the map's
    earlier form), bit for bit, on the source's edges and beyond (BORDER_REPLICATE) too."""
    rng = np.random.default_rng(len(where))
    for _ in range(60):
        h, w = int(rng.integers(2, 40)), int(rng.integers(2, 60))
        shape = (int(rng.integers(1, 30)), int(rng.integers(1, 50)))
        a, b = ((1000 * rng.random((h, w))).astype(np.float32) for _ in range(2))
        if where == "inside":
            mx, my = rng.uniform(0, w - 1, shape), rng.uniform(0, h - 1, shape)
        elif where == "edges":
            mx = rng.choice([0.0, w - 1.0, -0.5, w - 0.5, w + 3.0, -4.2, 1.25], shape)
            my = rng.choice([0.0, h - 1.0, -0.5, h - 0.5, 0.75], shape)
        else:
            mx, my = rng.uniform(-3, w + 2, shape), rng.uniform(-3, h + 2, shape)
        mx, my = mx.astype(np.float32), my.astype(np.float32)
        t = _Taps.of(mx, my, w, h)
        got_a, got_b = np.empty(shape, np.float32), np.empty(shape, np.float32)
        map_kernels.remap_pair(a, b, t.off, t.ax, t.ay, t.x0, t.y0, t.inside, got_a, got_b)
        for img, got in ((a, got_a), (b, got_b)):
            ref = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            assert np.array_equal(got, ref)


def test_the_mapper_is_its_earlier_form():
    """A distorted, rolled camera's map: the slope and validity as with cv2.remap of the
    coarse images through the float tables (the taps' x0 + ax is the table's float32)."""
    cam = Camera(fx=1400.0, fy=1400.0, cx=329.0, cy=120.0, dist=(-0.12, 0.0, 0.0, 0.0, 0.0),
                 px_per_mm=12.5, exposure_ms=0.05)
    rng = np.random.default_rng(11)
    rows_a = (1000 + 200 * rng.random((48, 659))).astype(np.uint16)
    rows_b = (1000 + 200 * rng.random((48, 659))).astype(np.uint16)
    mapper = SurfaceMapper(cam, Lights(slant_deg=82.0), (240, 659), bin_rows=5, bin_cols=2)
    for roll in (0.0, 0.7, -2.3):
        got = mapper(rows_a, rows_b, shift_px=14.6, roll_deg=roll, albedo=False)
        taps, valid = mapper._table(roll)
        mx = (taps.x0 + taps.ax).astype(np.float32)
        my = (taps.y0 + taps.ay).astype(np.float32)
        assert not taps.inside.all() or roll == 0.0  # the rolled grids leave the source
        a, b = (cv2.remap(mapper._coarse(r), mx, my, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE) for r in (rows_a, rows_b))
        slope, both = np.empty_like(a), np.empty(a.shape, bool)
        map_kernels.register_ratio(a, b, valid, 14.6 / 2, mapper._ka, mapper._kb, slope,
                               np.empty((0, 0), np.float32), both)
        assert np.array_equal(got.valid, both) and np.array_equal(got.slope_along_feed, slope)


def test_the_maps_valid_rows_and_columns_come_with_it():
    """The mapper's maps carry their valid rows and columns (found in the ratio's pass):
    numpy's of their ``valid``, also with rows and columns without a sample."""
    cam = Camera(fx=1400.0, fy=1400.0, cx=329.0, cy=120.0, dist=(-0.12, 0.0, 0.0, 0.0, 0.0),
                 px_per_mm=12.5, exposure_ms=0.05)
    rng = np.random.default_rng(12)
    rows_a = (1000 + 200 * rng.random((48, 659))).astype(np.uint16)
    rows_b = (1000 + 200 * rng.random((48, 659))).astype(np.uint16)
    rows_a[20:31] = 0  # dark rows: no sample
    rows_b[:, 300:340] = 0
    mapper = SurfaceMapper(cam, Lights(slant_deg=82.0), (240, 659), bin_rows=5, bin_cols=2)
    for roll, shift in ((0.0, 14.6), (0.7, -40.3), (-2.3, 300.0), (0.0, 2000.0)):
        got = mapper(rows_a, rows_b, shift_px=shift, roll_deg=roll, albedo=True)
        carried = got.__dict__["_valid_extent"]
        want = (np.flatnonzero(got.valid.any(axis=1)), np.flatnonzero(got.valid.any(axis=0)))
        for g, w in zip(carried, want, strict=True):
            assert g.dtype == w.dtype and np.array_equal(g, w) and not g.flags.writeable
        assert got.valid_rows is carried[0] and got.valid_cols is carried[1]
        if shift < 1000:
            assert 0 < want[0].size < got.valid.shape[0]  # some rows without a sample


@pytest.mark.parametrize("shape", [(1, 1), (7, 13), (98, 329), (80, 320)])
def test_valid_any_is_numpys_any_along_both_axes(shape):
    """The map's valid rows and columns in one pass: ``valid.any(axis=1)``, ``any(axis=0)``."""
    rng = np.random.default_rng(shape[1])
    for p in (0.0, 0.002, 0.5, 1.0):
        valid = rng.random(shape) < p
        rows, cols = np.empty(shape[0], bool), np.empty(shape[1], bool)
        map_kernels.valid_any(valid, rows, cols)
        assert np.array_equal(rows, valid.any(axis=1))
        assert np.array_equal(cols, valid.any(axis=0))
        got = map_kernels.valid_extent(valid)  # and their indices, as the map takes them
        want = (np.flatnonzero(valid.any(axis=1)), np.flatnonzero(valid.any(axis=0)))
        for g, w in zip(got, want, strict=True):
            assert g.dtype == w.dtype and np.array_equal(g, w)


def test_the_maps_valid_rows_and_columns_are_numpys():
    valid = np.zeros((9, 21), bool)
    valid[2:7, 3:18] = True
    valid[8, 20] = True
    smap = SurfaceMap(slope_along_feed=np.zeros(valid.shape, np.float32), albedo=None,
                      valid=valid, col0_px=0.0, row0_px=0.0, row_step_px=1.0, roll_deg=0.0,
                      cx=0.0, cy=0.0, px_per_mm=1.0)
    assert np.array_equal(smap.valid_cols, np.flatnonzero(valid.any(axis=0)))
    assert np.array_equal(smap.valid_rows, np.flatnonzero(valid.any(axis=1)))
    assert smap.valid_cols is smap.valid_cols and not smap.valid_rows.flags.writeable


def _old_peak(x: np.ndarray, r2: np.ndarray, max_lag_px: int) -> tuple[float, float, int]:
    """:func:`vision.defects.detect.oriented_coherence`'s last step as numpy calls."""
    norm = float(r2[0::2].sum() * r2[1::2].sum()) ** 0.5
    if norm <= 0:
        return 0.0, 0.0, 0
    vals = np.concatenate((x[:max_lag_px + 1], x[-max_lag_px:])) / norm
    k = int(np.argmax(vals))
    lag = k if k <= max_lag_px else k - (2 * max_lag_px + 1)
    return float(vals[k]), float(vals[0]), int(lag)


@pytest.mark.parametrize("n", [0, 1, 7, 8, 9, 127, 128, 129, 255, 256, 257, 300, 513, 1031, 4099])
def test_strided_pairwise_sums_are_numpys_at_any_length(n):
    """numpy's pairwise summation, its blocks of 128 and its splits above: the same bits."""
    rng = np.random.default_rng(n)
    for _ in range(5):
        v = rng.standard_normal(n) * rng.uniform(1e-3, 1e3, n)
        for start, step in ((0, 1), (0, 2), (1, 2), (2, 3)):
            assert kernels._pairwise_sum(v, start, step) == v[start::step].sum(), (start, step)


@pytest.mark.parametrize("pairs", [1, 3, 4, 7, 8, 9, 25, 40, 64, 129, 200, 600])
def test_coherence_peak_is_its_numpy_form(pairs):
    """Norm (numpy's pairwise sums), float32 correlations, the first peak: the same bits."""
    rng = np.random.default_rng(pairs)
    for trial in range(60):
        size = int(rng.integers(12, 400))
        max_lag = int(rng.integers(2, (size - 1) // 2))
        x = (rng.standard_normal(size) * rng.uniform(0.01, 100.0)).astype(np.float32)
        r2 = rng.uniform(0.0, 50.0, 2 * pairs) * rng.uniform(1e-3, 1e3)
        if trial % 10 == 1:
            r2[::2] = 0.0  # no power: no correlation
        if trial % 10 == 2:
            x[rng.integers(0, size, 3)] = np.nan
        if trial % 10 == 3:
            x[int(rng.integers(0, max_lag))] = x[-int(rng.integers(1, max_lag))] = 1e3  # a tie
        peak, at0, lag, ok = kernels.coherence_peak(x, r2, max_lag)
        want = _old_peak(x, r2, max_lag)
        got = (peak, at0, lag) if ok else (0.0, 0.0, 0)
        assert np.array_equal(np.array(got), np.array(want), equal_nan=True), (got, want)
        assert isinstance(got[2], int)
