"""The uniformity loop's plain-float shortcuts are numpy's results bit for bit.

A knife table has 2-8 values: one numpy call costs more than the arithmetic, so the loop sums and
projects in plain floats where that gives the same bits (``plain_floats.numpy_sum``: numpy's
pairwise summation, also of a field's marks; ``_zero_mean_in_box``: the projection's common
case). These tests pin them to numpy (a numpy that sums otherwise fails here, not silently in
the loop).
"""

from __future__ import annotations

import random

import numpy as np

from controller.laws.limits import project_zero_mean_box
from controller.laws.plain_floats import PAIRWISE_BLOCK, numpy_mean, numpy_sum
from controller.laws.uniformity_loop import _zero_mean_in_box


def _value(rng: random.Random) -> float:
    return rng.choice([0.0, -0.0, rng.uniform(-10.0, 10.0) * 10.0 ** rng.randint(-4, 4)])


def test_numpy_sum_is_add_reduce_bit_for_bit():
    """Every length up to past the 128-value block, signed zeros and mixed magnitudes."""
    rng = random.Random(1)
    for n in [*range(0, 41), 63, 64, 65, 127, 128, 129, 200, 257, 300]:
        for _ in range(300):
            v = [_value(rng) for _ in range(n)]
            want = float(np.add.reduce(np.array(v, dtype=float)))
            got = numpy_sum(v)
            assert repr(got) == repr(want), (n, v)
            if n:
                assert repr(numpy_mean(v)) == repr(float(np.array(v).mean()))
    assert PAIRWISE_BLOCK == 128  # past it numpy sums the halves apart: numpy_sum calls numpy


def test_the_table_projection_is_project_zero_mean_box_bit_for_bit():
    """Tables inside the box after the shift (the shortcut) and beyond it (the projection)."""
    rng = random.Random(2)
    inside = 0
    for _ in range(20000):
        z = rng.randint(1, 8)
        bound = rng.uniform(0.1, 20.0)
        v = [rng.uniform(-1.6, 1.6) * bound for _ in range(z)]
        want = project_zero_mean_box(np.array(v), bound=bound)
        got = _zero_mean_in_box(v, bound)
        assert got.dtype == want.dtype and got.tobytes() == want.tobytes(), (v, bound)
        inside += bool(np.max(np.abs(np.array(v) - np.mean(v))) <= bound)
    assert 2000 < inside < 18000  # both branches taken often
