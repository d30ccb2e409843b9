"""The front end's compiled sums (orientation groups, profile column sums) against numpy."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vision import kernels
from vision.front_end import mean_profile

kernels.warm_up()


@pytest.mark.parametrize("size", [1, 3, 7, 256])
def test_group_sums_are_numpys_float32_sums(size):
    rng = np.random.default_rng(size)
    g, w, first = 5, 37, 3
    bins = rng.integers(0, 65536, (first + g * size + 2, w)).astype(np.uint16)
    out = np.empty((g, w), dtype=np.float32)
    kernels.group_sums(bins, first, size, out)
    want = bins[first: first + g * size].reshape(g, size, w).sum(axis=1, dtype=np.float32)
    np.testing.assert_array_equal(out, want)
    # and exact: the integer sums themselves (below 2**24 for up to 256 bins per group)
    exact = bins[first: first + g * size].reshape(g, size, w).sum(axis=1, dtype=np.int64)
    np.testing.assert_array_equal(out.astype(np.int64), exact)


@pytest.mark.parametrize("shape", [(1, 9), (19, 659), (40, 1920)])
def test_mean_profile_of_uint16_rows_is_cv2_reduce_exactly(shape):
    rng = np.random.default_rng(shape[1])
    rows = rng.integers(0, 65536, shape).astype(np.uint16)
    want = cv2.reduce(rows, 0, cv2.REDUCE_SUM, dtype=cv2.CV_64F).ravel() / (shape[0] * 3)
    np.testing.assert_array_equal(mean_profile(rows, 3), want)
    # float32 rows and strided views take OpenCV's sums (the same definition)
    f = rows.astype(np.float32)
    np.testing.assert_array_equal(
        mean_profile(f, 3), cv2.reduce(f, 0, cv2.REDUCE_SUM, dtype=cv2.CV_64F).ravel()
        / (shape[0] * 3))
    view = rows[:, ::2]
    np.testing.assert_array_equal(
        mean_profile(view, 1), view.sum(axis=0, dtype=np.float64) / shape[0])
