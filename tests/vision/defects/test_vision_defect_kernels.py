"""The defects' compiled loops against plain numpy computations of the same steps."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from vision.defects import kernels, map_kernels


@pytest.mark.parametrize("n", [1, 2, 3, 8, 35, 1000])
def test_median_and_selection_as_numpy(n):
    rng = np.random.default_rng(n)
    for ties in (False, True):
        v = rng.standard_normal(n)
        if ties:
            v = np.round(v, 1)
        assert kernels._median(v.copy(), n) == np.median(v)
        assert kernels._select(v.copy(), n, n // 2) == np.partition(v, n // 2)[n // 2]


def _reference_map(a, b, valid, d, ka, kb):
    """The map's registration and ratio as numpy/OpenCV steps."""
    rows, width = a.shape
    b_reg = cv2.warpAffine(b, np.array([[1.0, 0.0, d], [0.0, 1.0, 0.0]]), (width, rows),
                           flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    k = int(math.floor(d))
    both = np.zeros_like(valid)
    lo, hi = max(0, -k), min(width, width - k - 1)
    both[:, lo:hi] = (valid[:, lo:hi] & valid[:, lo + k:hi + k]
                      & valid[:, lo + k + 1:hi + k + 1])
    both &= (a > 0) & (b_reg > 0)
    n = int(both.sum())
    sa, sb = float(a[both].sum()), float(b_reg[both].sum())
    r = b_reg * (sa / sb)
    slope = np.where(both, (r - a) / (r * ka - a * kb), 0.0)
    albedo = np.where(both, (a + r) * n / (2 * sa), 0.0)
    return slope, albedo, both


@pytest.mark.parametrize("d", [0.0, 7.3, -4.6])
def test_register_ratio_as_numpy(d):
    rng = np.random.default_rng(3)
    a = (100 + 20 * rng.random((40, 90))).astype(np.float32)
    b = (110 + 20 * rng.random((40, 90))).astype(np.float32)
    valid = np.ones(a.shape, bool)
    valid[:, :3] = False
    valid[5, 40:44] = False
    ka = math.tan(math.radians(82))
    slope, albedo = np.empty_like(a), np.empty_like(a)
    both = np.empty(a.shape, bool)
    n = map_kernels.register_ratio(a, b, valid, d, ka, -ka, slope, albedo, both)
    ref = _reference_map(a, b, valid, d, ka, -ka)
    assert n == int(ref[2].sum())
    assert np.array_equal(both, ref[2])
    np.testing.assert_allclose(slope, ref[0], atol=2e-6)
    np.testing.assert_allclose(albedo, ref[1], rtol=2e-5, atol=1e-6)


def _reference_profile(p, valid, sat, group, k):
    """The shorth of the row groups, then the mean of the samples near it (numpy)."""
    rows, cols = p.shape
    n_g = rows // group
    ok = valid & (np.abs(p) < sat)
    w = ok.astype(np.float64)
    pw = np.where(ok, p, 0.0).astype(np.float64)
    ps = pw[:n_g * group].reshape(n_g, group, cols).sum(axis=1)
    ws = w[:n_g * group].reshape(n_g, group, cols).sum(axis=1)
    far = (1e3 + 10.0 * np.arange(n_g))[:, None]
    gm = np.sort(np.where(ws >= 0.5 * group, ps / np.maximum(ws, 1.0), far), axis=0)
    j = np.argmin(gm[k - 1:] - gm[:n_g - k + 1], axis=0)
    loc = np.array([gm[j[c]:j[c] + k, c].mean() for c in range(cols)])
    count = w.sum(axis=0)
    loc = np.where(np.abs(loc) < 10.0, loc, pw.sum(axis=0) / np.maximum(count, 1.0))
    dev = np.abs(p - loc[None, :])
    scale = float(np.median(dev[::3, ::3][ok[::3, ::3]]))
    keep = ok & (dev <= 5.0 * 1.4826 * scale + 1e-4)
    kc = keep.sum(axis=0)
    prof = np.where(kc > 0, np.where(keep, p, 0.0).sum(axis=0) / np.maximum(kc, 1), loc)
    return np.where(count > 0, prof, 0.0), scale


def test_residual_map_as_numpy():
    rng = np.random.default_rng(4)
    rows, cols, cell = 50, 120, 3
    x = np.arange(cols)
    p = (0.01 * np.sin(x / 5.0)[None, :] + 0.003 * rng.standard_normal((rows, cols)))
    p[10:40, 50:60] += 0.05 * rng.standard_normal((30, 10))  # a rough pit over most rows
    p[12:30, 52] = 0.2  # its shadow
    p = p.astype(np.float32)
    valid = np.ones((rows, cols), bool)
    valid[:, :4] = False
    valid[45:, 100:] = False
    profile = np.empty(cols)
    r = np.empty_like(p)
    e = np.empty((rows, cols // cell), np.float32)
    vc = np.empty((rows, cols // cell), bool)
    cells = np.empty(e.size, np.float32)
    mad, n_cells = kernels.residual_map(p, valid, 0.07, 3, 6, cell, profile, r, e, vc, cells)
    ref_profile, ref_mad = _reference_profile(p, valid, 0.07, 3, 6)
    assert mad == pytest.approx(ref_mad, rel=1e-5)
    np.testing.assert_allclose(profile, ref_profile, atol=1e-6)
    assert np.abs(profile[50:60] - 0.01 * np.sin(x[50:60] / 5.0)).max() < 0.004
    ref_r = np.where(valid, p - profile.astype(np.float32)[None, :], 0.0)
    np.testing.assert_allclose(r, ref_r, atol=1e-7)
    w = valid[:, :cols // cell * cell].reshape(rows, -1, cell).sum(axis=2)
    ref_e = (ref_r[:, :cols // cell * cell] ** 2).reshape(rows, -1, cell).sum(axis=2)
    ref_vc = w >= 0.5 * cell
    assert np.array_equal(vc, ref_vc) and n_cells == int(ref_vc.sum())
    assert np.array_equal(cells[:n_cells], e[vc])  # the valid cells in order
    np.testing.assert_allclose(e, np.where(ref_vc, ref_e / np.maximum(w, 1), 0.0),
                               rtol=1e-5, atol=1e-9)


def test_clipped_pairs_and_cross_spectrum_as_numpy():
    rng = np.random.default_rng(6)
    r = rng.standard_normal((20, 37)).astype(np.float32)
    rows = np.array([0, 1, 4, 5, 8, 9], dtype=np.int64)
    out = np.full((rows.size, 48), np.nan, np.float32)  # the padding written too
    r2 = np.empty(rows.size)
    kernels.clipped_pairs(r, rows, 1.5, out, r2)
    ref = np.clip(r[rows], np.float32(-1.5), np.float32(1.5))
    assert np.array_equal(out[:, :37], ref) and not out[:, 37:].any()
    np.testing.assert_allclose(r2, (ref * ref).sum(axis=1, dtype=np.float64), rtol=1e-12)
    f = np.fft.rfft(out, axis=1).astype(np.complex64)
    got = np.empty(f.shape[1], np.complex64)
    kernels.cross_spectrum(f, got)
    ref = (np.conj(f[0::2].astype(np.complex128)) * f[1::2]).sum(axis=0)
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5 * np.abs(ref).max())


@pytest.mark.parametrize("n", [30, 33, 40])
def test_reference_median_as_numpy(n):
    rng = np.random.default_rng(n)
    energy = rng.random(n)
    energy[[3, 16]] = np.nan  # rows not taken; 16 is a reference row
    energy[5] = 50.0  # stands out
    out = np.empty(3)
    kernels.reference_median(energy, 8, 12.0, out)
    ref = energy[::8]
    ref = ref[np.isfinite(ref)]
    median = np.median(ref)
    with np.errstate(invalid="ignore"):
        hot = int(np.count_nonzero(energy / max(median, 1e-18) >= 12.0))
    assert (out[0], out[1], out[2]) == (ref.size, median, hot) and hot >= 1


def test_marked_cells_as_opencv():
    rng = np.random.default_rng(7)
    e = (rng.random((30, 41)) ** 4).astype(np.float32)
    valid = rng.random((30, 41)) > 0.1
    excess = np.empty_like(e)
    marked = np.empty_like(valid)
    kernels.marked_cells(e, valid, 1.0 / 0.07, 4.0, excess, marked)
    ref = cv2.blur(e, (3, 3), borderType=cv2.BORDER_REFLECT) * np.float32(1.0 / 0.07)
    np.testing.assert_allclose(excess, ref, rtol=2e-6)
    tie = np.abs(ref - 4.0) < 1e-5  # a hair from the limit: either side
    assert np.array_equal(marked[~tie], ((ref > 4.0) & valid)[~tie]) and marked.any()
    one = e[:, :1].copy()  # one column: both edges at once
    x1, m1 = np.empty_like(one), np.empty((30, 1), dtype=bool)
    kernels.marked_cells(one, valid[:, :1].copy(), 1.0, 0.0, x1, m1)
    np.testing.assert_allclose(x1, cv2.blur(one, (3, 3), borderType=cv2.BORDER_REFLECT),
                               rtol=2e-6)
    kernels.marked_cells(e[:, :0].copy(), valid[:, :0].copy(), 1.0, 4.0,
                         np.empty((30, 0), np.float32), np.empty((30, 0), bool))  # no cells


def test_fold_rows_as_numpy():
    rng = np.random.default_rng(5)
    rows, cols, period = 24, 200, 18.5
    r = rng.standard_normal((rows, cols)).astype(np.float32)
    r[7] += np.where((np.arange(cols) % period) < 4, 3.0, 0.0)  # stands out every period
    valid = np.ones((rows, cols), bool)
    valid[3, 20:60] = False
    nb, n_per, c0 = 18, 10, 5
    folded, energy = np.empty((rows, nb)), np.empty(rows)
    kernels.fold_rows(r, valid, c0, period, nb, n_per, 100, 4, 4.0, folded, energy)
    cols_used = np.arange(c0, c0 + int(n_per * period))
    ph = (cols_used - c0) / period
    per, b = np.floor(ph).astype(int), np.minimum(np.floor((ph % 1) * nb).astype(int), nb - 1)
    taken = [i for i in range(rows) if np.isfinite(energy[i])]
    assert set(range(0, rows, 4)) | {7} == set(taken)  # the reference rows and the one out
    for i in taken:
        cells = np.full((n_per, nb), np.nan)
        for q in range(n_per):
            for j in range(nb):
                sel = (per == q) & (b == j) & valid[i, cols_used]
                if sel.any():
                    cells[q, j] = r[i, cols_used[sel]].mean()
        ref = np.nanmedian(cells, axis=0)
        np.testing.assert_allclose(folded[i], ref, atol=1e-6)
        assert energy[i] == pytest.approx(np.mean(ref ** 2), rel=1e-6)


@pytest.mark.parametrize("k", [1, 2, 3, 4, 6, 7, 8])
def test_column_means_are_opencvs_area_resize(k):
    """The map's coarse source: INTER_AREA's integers, whether OpenCV or the kernel makes them."""
    rng = np.random.default_rng(k)
    for top in (65535, 1300, 40):
        src = (rng.random((31, 100 * k + k - 1)) * top).astype(np.uint16)
        rows = src[1:31:3, :100 * k]  # the middle row of blocks of three, whole blocks
        ref = cv2.resize(rows, (100, 10), interpolation=cv2.INTER_AREA).astype(np.float32)
        out = np.empty((10, 100), np.float32)
        map_kernels.column_means_u16(src, 1, 3, k, out)
        assert np.array_equal(out, ref)
        if k == 2:  # a linear resize to exactly half the width: the same integers
            lin = cv2.resize(rows, (100, 10), interpolation=cv2.INTER_LINEAR)
            assert np.array_equal(lin.astype(np.float32), ref)


def _reference_depth(rmap, c0, c1, r0, r1, mask, dx_um):
    """A blob's depth below its rim as numpy steps (what ``row_depth`` replaces)."""
    seg = rmap[r0:r1, c0:c1].astype(np.float64)
    h = np.cumsum(seg, axis=1) * dx_um
    h = np.concatenate([np.zeros((h.shape[0], 1)), h], axis=1)[:, :-1]
    n = h.shape[1]
    edge = max(1, n // 10)
    left = h[:, :edge].mean(axis=1, keepdims=True)
    right = h[:, -edge:].mean(axis=1, keepdims=True)
    h = h - (left + (right - left) * np.linspace(0.0, 1.0, n)[None, :])
    v = -h[mask]
    return float(np.percentile(v, 90)) if v.size else 0.0


def test_row_depth_as_numpy():
    """Bit for bit numpy's steps (its sums of the rims, np.percentile's interpolation)."""
    rng = np.random.default_rng(8)
    rmap = (0.01 * rng.standard_normal((60, 330))).astype(np.float32)
    for _ in range(300):
        n, h = int(rng.integers(1, 300)), int(rng.integers(1, 25))
        c0, r0 = int(rng.integers(0, 330 - n)), int(rng.integers(0, 60 - h))
        mask = rng.random((h, n)) < rng.random()
        dx = float(rng.uniform(50.0, 300.0))
        assert kernels.row_depth(rmap, r0, r0 + h, c0, c0 + n, mask, dx) == _reference_depth(
            rmap, c0, c0 + n, r0, r0 + h, mask, dx)
