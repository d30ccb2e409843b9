"""numpy's sums of a few floats, bit for bit, without a numpy call (pure).

The laws handle a knife table (2-8 values) or a field's marks (a few dozen) per pair: one numpy
call costs more than the arithmetic, so where a result must stay numpy's bit for bit (a mean
that feeds a comparison, a pinned record) they sum in plain floats as numpy does.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["PAIRWISE_BLOCK", "numpy_mean", "numpy_sum"]

PAIRWISE_BLOCK = 128
"""numpy's pairwise summation block: up to this many values it sums in eight running sums."""


def numpy_sum(values: Sequence[float]) -> float:
    """``np.add.reduce`` of a 1-D float64 array of ``values``, bit for bit.

    numpy's pairwise summation onto its identity 0.0: under 8 values in order; up to
    :data:`PAIRWISE_BLOCK` in eight running sums (element ``i`` into sum ``i mod 8``) combined
    as ``((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))``, then the rest in order. More
    values than that (never a knife table, hardly a field's marks) are summed by numpy itself.

    Parameters
    ----------
    values : sequence of float
        Plain floats.

    Returns
    -------
    float
    """
    n = len(values)
    if n < 8:
        total = 0.0
        for v in values:
            total += v
        return total
    if n > PAIRWISE_BLOCK:
        return float(np.add.reduce(np.array(values, dtype=float)))
    r = list(values[:8])
    i, whole = 8, n - n % 8
    while i < whole:
        for j in range(8):
            r[j] += values[i + j]
        i += 8
    total = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    for v in values[whole:]:
        total += v
    return 0.0 + total


def numpy_mean(values: Sequence[float]) -> float:
    """``np.add.reduce(a) / a.size`` of a non-empty float64 array of ``values``, bit for bit."""
    return numpy_sum(values) / len(values)
