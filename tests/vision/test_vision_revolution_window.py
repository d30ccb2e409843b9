"""The slow-height removal spans one cutterhead revolution, not one pitch.

With a weak runout the repeat period of the marks is one pitch; a running mean over one pitch
follows the knife-to-knife heights and took half of a small CV away (true 0.0104 measured
0.0032 at 4 knives, 1.5 mm). With the knives known the window is a revolution.
"""

from __future__ import annotations

import numpy as np
import pytest

from plant_sim.rendering.scenarios import board_pair
from vision.pipeline import Measurer, revolution_px


def _sawtooth(pitch_px: float, n: int = 600) -> np.ndarray:
    x = np.arange(n, dtype=float)
    return (x % pitch_px) / pitch_px - 0.5


@pytest.mark.parametrize(
    "period, knives, expect",
    [
        (15.0, 4, 60.0),   # weak runout: the repeat period is one pitch -> four
        (30.0, 4, 60.0),   # two pitches (opposite knives alike) -> four
        (60.0, 4, 60.0),   # already the revolution
        (15.0, 3, 45.0),
        (30.0, 3, 30.0),   # two pitches do not divide three knives: as it is
        (15.0, None, 15.0),  # knives unknown: as it is
        (15.0, 8, 120.0),
        (15.0, 40, 15.0),  # a revolution longer than half the profile: as it is
    ],
)
def test_revolution_window_from_the_repeat_period(period, knives, expect):
    assert revolution_px(_sawtooth(15.0), period, knives) == pytest.approx(expect, rel=0.02)


def test_revolution_window_keeps_a_nan_period():
    assert np.isnan(revolution_px(_sawtooth(15.0), float("nan"), 4))


@pytest.mark.parametrize("knives, pitch_mm", [(4, 1.5), (8, 1.2), (2, 3.0)])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_small_cv_follows_the_true_one(knives, pitch_mm, seed):
    """A weak runout's CV (0.002-0.02) within 0.005 or 20 % of the true one."""
    r = 0.2 * np.random.default_rng(seed).normal(size=knives)
    rig, pair = board_pair(seed=seed, pitch_mm=pitch_mm, knives=knives, runout_um=list(r),
                           species="spruce")
    m = Measurer(rig, pair.image_a.shape, radius_mm=60.0, knives=knives).measure(
        pair.image_a, pair.image_b, counts_a=pair.counts_a, counts_b=pair.counts_b)
    true_cv = pair.truth.metrics(m.cusps_mm[0] - 0.01, m.cusps_mm[-1] + 0.01)["uniformity_cv"]
    assert abs(m.uniformity_cv - true_cv) <= max(0.005, 0.2 * true_cv)
