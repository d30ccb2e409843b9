"""Column averaging, sub-pixel resampling and the overlap of a registered pair."""

from __future__ import annotations

import numpy as np
import pytest

from vision.profile import column_profile, overlap, shift_profile


def test_column_profile_is_the_column_mean():
    rng = np.random.default_rng(0)
    for dtype in (np.uint8, np.uint16, np.float32, np.float64, np.int32):
        rows = (rng.uniform(0, 200, (37, 51))).astype(dtype)
        np.testing.assert_allclose(column_profile(rows), rows.astype(float).mean(axis=0),
                                   rtol=1e-6)
    with pytest.raises(ValueError):
        column_profile(np.zeros(5))


def test_shift_profile_integer_and_fractional_shifts():
    x = np.arange(100, dtype=float)
    quad = 0.3 * x**2 - 2 * x + 1
    np.testing.assert_array_equal(shift_profile(quad, shift_px=3.0, start=2, count=10), quad[5:15])
    # Keys' cubic reproduces quadratics exactly
    got = shift_profile(quad, shift_px=4.37, start=5, count=50)
    xs = 5 + 4.37 + np.arange(50)
    np.testing.assert_allclose(got, 0.3 * xs**2 - 2 * xs + 1, rtol=1e-12)
    got = shift_profile(quad, shift_px=-2.6, start=10, count=20)
    xs = 10 - 2.6 + np.arange(20)
    np.testing.assert_allclose(got, 0.3 * xs**2 - 2 * xs + 1, rtol=1e-12)
    with pytest.raises(ValueError, match="outside"):
        shift_profile(quad, shift_px=0.5, start=0, count=10)  # needs sample -1


@pytest.mark.parametrize("width, d", [(659, 15.0), (659, 15.4), (659, -12.3), (100, 0.0)])
def test_overlap_keeps_every_partner_inside(width, d):
    u0, u1 = overlap(width, d)
    assert u1 - u0 > width - abs(d) - 5
    prof = np.arange(width, dtype=float)
    out = shift_profile(prof, shift_px=d, start=u0, count=u1 - u0)  # must not raise
    np.testing.assert_allclose(out, u0 + d + np.arange(u1 - u0), atol=1e-9)
    assert overlap(width, width + 5.0)[1] <= overlap(width, width + 5.0)[0]
