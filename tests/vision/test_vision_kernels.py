"""The compiled loops of vision.kernels against the plain numpy they replace."""

from __future__ import annotations

import numpy as np
import pytest

from vision import kernels


@pytest.mark.parametrize("k, m, plain_dtype", [(5, 5, np.uint16), (3, 1, np.uint16),
                                               (4, 5, np.float32)])
def test_bin_rows_are_the_integer_sums(k, m, plain_dtype):
    rng = np.random.default_rng(k)
    h, w = 131, 37
    image = rng.integers(0, 256, (h, w), dtype=np.uint8)
    hb, r0 = h // k, (h - (h // k) * k) // 2
    start = 1
    n_plain = (hb - start) // m
    v0, v1, c0, c1 = 0, max(1, n_plain - 1), 3, w - 2
    bins = np.empty((hb, w), dtype=np.uint16)
    plain = np.empty((n_plain, w), dtype=plain_dtype)
    cols = np.empty(c1 - c0)
    scratch = np.empty(c1 - c0, dtype=np.uint32 if plain_dtype == np.uint16 else np.float64)
    kernels.bin_rows(image, r0, k, bins, start, m, plain, v0, v1, c0, c1, scratch, cols)
    want_bins = image[r0:r0 + hb * k].reshape(hb, k, w).sum(axis=1, dtype=np.int64)
    assert np.array_equal(bins, want_bins)
    want_plain = want_bins[start:start + n_plain * m].reshape(n_plain, m, w).sum(axis=1)
    assert np.array_equal(plain, want_plain)
    assert np.array_equal(cols, want_plain[v0:v1, c0:c1].sum(axis=0).astype(np.float64))


def _running_mean_reference(values: np.ndarray, length: float) -> np.ndarray:
    """The window mean of the piecewise-constant signal, by np.interp of its integral."""
    n = values.shape[0]
    half = 0.5 * length
    m0 = int(np.ceil(half - 0.5))
    centres = np.arange(m0, n - m0, dtype=np.float64)
    knots = np.arange(n + 1) - 0.5
    cum = np.concatenate([np.zeros((1,) + values.shape[1:]), np.cumsum(values, axis=0)])
    cols = cum.reshape(n + 1, -1)
    out = [(np.interp(centres + half, knots, c) - np.interp(centres - half, knots, c)) / length
           for c in cols.T]
    return np.stack(out, axis=-1).reshape((centres.size,) + values.shape[1:])


@pytest.mark.parametrize("n, length", [(50, 1.0), (50, 7.0), (64, 12.37), (9, 9.0),
                                       (200, 33.5)])
def test_running_means_match_the_interpolated_integral(n, length):
    rng = np.random.default_rng(n)
    v = rng.standard_normal(n)
    np.testing.assert_allclose(kernels.running_mean_1d(v, length),
                               _running_mean_reference(v, length), rtol=0, atol=1e-12)
    both = rng.standard_normal((n, 4))
    np.testing.assert_allclose(kernels.running_mean_2d(both, length),
                               _running_mean_reference(both, length), rtol=0, atol=1e-12)


def test_smooth5_is_the_same_mode_box_convolution():
    v = np.random.default_rng(1).standard_normal(40)
    np.testing.assert_allclose(kernels.smooth5(v), np.convolve(v, np.ones(5) / 5.0, "same"),
                               rtol=0, atol=1e-15)


def test_solve_small_solves_and_reports_singular_systems():
    rng = np.random.default_rng(2)
    a = rng.standard_normal((6, 4, 4)) + 4 * np.eye(4)
    b = rng.standard_normal((6, 4))
    want = np.linalg.solve(a, b[:, :, None])[:, :, 0]
    aa, bb = a.copy(), b.copy()
    assert kernels.solve_small(aa, bb)
    np.testing.assert_allclose(bb, want, rtol=1e-12, atol=1e-12)
    singular = np.ones((1, 3, 3))
    assert not kernels.solve_small(singular, np.ones((1, 3)))


def test_arc_slopes_are_the_kinematic_sawtooth():
    cusps = np.array([0.0, 1.5, 3.1, 4.5])
    bottoms = np.array([0.7, 2.2, 3.9])
    x = np.linspace(-1.0, 6.0, 141)
    got = kernels.arc_slopes(x, cusps, bottoms, 60.0)
    k = np.searchsorted(cusps, x, side="right") - 1
    inside = (k >= 0) & (k < bottoms.size)
    assert np.array_equal(np.isnan(got), ~inside)
    np.testing.assert_allclose(got[inside], (x[inside] - bottoms[k[inside]]) / 60.0,
                               rtol=0, atol=1e-15)


def test_warm_up_is_idempotent():
    kernels.warm_up()
    kernels.warm_up()
    assert kernels._WARM[0]


@pytest.mark.parametrize("top", [2, 256, 1276, 4081])
def test_rows_over_means_are_numpys_float32_quotients(top):
    # the rotated texture's rows over their means: bit for bit the numpy expression it replaced
    from vision.front_end import FrontEnd

    rng = np.random.default_rng(top)
    for n, w in ((98, 659), (7, 40), (1, 3)):
        bins = rng.integers(0, top, (n, w)).astype(np.uint16)
        bins[n // 2] = 0  # a dark row: divided by 1
        c0, c1 = (2, w - 1) if w > 4 else (0, w)
        front = FrontEnd.__new__(FrontEnd)
        front.columns = (c0, c1)
        want = bins.astype(np.float32)
        mean = want[:, c0:c1].mean(axis=1, keepdims=True)
        want /= np.where(mean > 0, mean, np.float32(1.0))
        got = front._over_row_means(bins)
        assert got.dtype == np.float32
        assert np.array_equal(got, want)


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_scaled_less_one_is_numpys_product_less_one(dtype):
    rng = np.random.default_rng(7)
    rows = (rng.random((16, 659)) * 1300).astype(dtype)
    scale = (1.0 / (rng.random(659) * 900 + 1)).astype(np.float32)
    want = np.multiply(rows, scale[None, :], dtype=np.float32)
    want -= np.float32(1.0)
    got = np.empty(rows.shape, dtype=np.float32)
    kernels.scaled_less_one(rows, scale, got)
    assert np.array_equal(got, want)


def test_inverse_column_means_are_cv2s_average_inverted():
    import cv2

    from vision.front_end import _inverse

    rng = np.random.default_rng(11)
    for n, w, spread in ((16, 659, 0.3), (1, 9, 1.0), (5, 40, 1000.0)):
        rows = (1.0 + spread * rng.standard_normal((n, w))).astype(np.float32)
        rows[:, 3] = -1.0  # a column whose mean is not positive: 0
        want = _inverse(cv2.reduce(rows, 0, cv2.REDUCE_AVG, dtype=cv2.CV_64F).ravel())
        got = np.empty(w, dtype=np.float32)
        kernels.inverse_column_means(rows, np.empty(w), got)
        assert got[3] == 0.0
        assert np.array_equal(got, want)


@pytest.mark.parametrize("m, top", [(1, 6000), (5, 1276), (7, 9000)])
def test_group_sums_into_uint16_are_numpys_uint16_sums(m, top):
    # the sheared profile's bins: the reshape-and-sum they replaced, integer for integer
    rng = np.random.default_rng(m)
    bins = rng.integers(0, top, (m * 9 + 3, 37)).astype(np.uint16)
    for start in (0, 2):
        g = (bins.shape[0] - start) // m
        want = bins[start:start + g * m].reshape(g, m, 37).sum(axis=1, dtype=np.uint16)
        got = np.empty((g, 37), dtype=np.uint16)
        kernels.group_sums(bins, start, m, got)  # the same kernel as float32 groups
        assert np.array_equal(got, want)

