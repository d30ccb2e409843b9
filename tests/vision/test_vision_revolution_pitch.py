"""The revolution window's pitch at the periodogram's own resolution (no zero-padding).

:func:`vision.pipeline.revolution_px` needs only the whole number of pitches in the repeat
period; the unpadded peak is within a fraction of a bin of the padded one, so the window is the
same as with :func:`vision.marks.dominant_period_px`.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from vision.marks import dominant_period_px
from vision.pipeline import _pitch_px, revolution_px


def _revolution_by_padded_pitch(slope, period, knives):
    pitch = dominant_period_px(slope)
    if not math.isfinite(pitch) or pitch <= 0:
        return period
    k = max(1, round(period / pitch))
    window = period * (knives // k)
    return window if knives % k == 0 and window <= slope.size / 2 else period


def _marks(rng, n, pitch, knives, runout, noise):
    x = np.arange(n, dtype=float)
    knife = (x // pitch).astype(int) % knives
    tooth = (x % pitch) / pitch - 0.5
    return tooth * (1 + runout * np.cos(2 * np.pi * knife / knives)) + noise * rng.normal(size=n)


@pytest.mark.parametrize("n", [300, 640, 1900])
def test_pitch_and_window_as_with_the_padded_periodogram(n):
    rng = np.random.default_rng(n)
    for _ in range(40):
        pitch = float(rng.uniform(8, n / 12))
        knives = int(rng.integers(1, 9))
        slope = _marks(rng, n, pitch, knives, float(rng.uniform(0, 0.5)),
                       float(rng.uniform(0, 0.3)))
        padded = dominant_period_px(slope)
        assert _pitch_px(slope) == pytest.approx(padded, rel=0.02)
        for k in range(1, knives + 1):
            period = k * padded
            for z in (2, 3, 4, 6, 8):
                assert revolution_px(slope, period, z) == _revolution_by_padded_pitch(
                    slope, period, z)


def test_pitch_of_too_short_or_flat_profiles():
    assert math.isnan(_pitch_px(np.zeros(5)))
    assert math.isnan(_pitch_px(np.ones(7)))
