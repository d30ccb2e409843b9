"""The row-bin checks of one pair in one call (row_checks) give what the two checks give."""

from __future__ import annotations

import numpy as np
import pytest

from vision.registration.defect_rows import (
    RIDGED,
    defect_rows,
    ridged_rows,
    row_checks,
    rows_disagreement,
)


def _pair(rng: np.random.Generator, n: int, w: int, dtype: type, *, pit: bool, ridges: bool
          ) -> tuple[np.ndarray, np.ndarray]:
    u = np.arange(w + 30.0)
    marks = np.exp(0.1 * ((u % 25) / 25 - 0.5))
    albedo = 1.0 + 0.1 * rng.random((n, w + 30))
    a = 1000 * albedo[:, :w] * marks[:w]
    b = 1000 * albedo[:, :w] / marks[:w]  # B at u + 9 sees A's point u
    b = np.concatenate([np.full((n, 9), 1000.0), b], axis=1)[:, :w]
    a = a * (1 + 0.01 * rng.standard_normal((n, w)))
    b = b * (1 + 0.01 * rng.standard_normal((n, w)))
    if ridges:
        ridge = np.exp(0.4 * np.sin(2 * np.pi * (np.arange(w)[None, :]
                                                 + 15 * np.arange(n)[:, None]) / 60))
        a, b = a * ridge, b / ridge
    if pit:
        a[n // 3: n // 3 + 2, w // 3: w // 3 + 40] *= 0.3
    return a.astype(dtype), b.astype(dtype)


@pytest.mark.parametrize("dtype", [np.uint16, np.float32, np.float64])
def test_row_checks_are_defect_rows_and_ridged_rows(dtype):
    rng = np.random.default_rng(5)
    seen_mask, seen_weights = set(), set()
    for trial in range(16):
        n, w = int(rng.integers(1, 30)), int(rng.integers(200, 900))
        if trial >= 12:  # the small cases: too few bins, or too little overlap
            n, w = (2, 300) if trial % 2 else (8, int(rng.integers(40, 60)))
        a, b = _pair(rng, n, w, dtype, pit=trial % 2 == 1, ridges=trial % 3 == 0)
        d, margin = 9.0 + rng.uniform(-0.3, 0.3), int(rng.integers(0, 12))
        if trial >= 12 and w < 100:
            margin = 12
        mask, weights = row_checks(w, a, b, d, margin)
        want_mask = defect_rows(w, a, b, d, margin)
        want_weights = ridged_rows(w, a, b, d, margin)
        assert (mask is None) == (want_mask is None), trial
        if mask is not None:
            np.testing.assert_array_equal(mask.mask, want_mask.mask)
            assert (mask.u0, mask.u1, mask.shift_px) == (want_mask.u0, want_mask.u1, d)
        assert (weights is None) == (want_weights is None), trial
        if weights is not None:
            np.testing.assert_array_equal(weights, want_weights)
        seen_mask.add(mask is None)
        seen_weights.add(weights is None)
    assert seen_mask == {True, False} and seen_weights == {True, False}


def test_row_checks_threshold_is_the_ridged_rows_default():
    rng = np.random.default_rng(9)
    a, b = _pair(rng, 12, 400, np.float32, pit=False, ridges=True)
    level = rows_disagreement(a, b, 9.0, 0, 391)
    assert level > RIDGED
    assert ridged_rows(400, a, b, 9.0, 0, threshold=level + 0.01) is None
    assert row_checks(400, a, b, 9.0, 0)[1] is not None
