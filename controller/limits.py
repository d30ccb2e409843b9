"""Small, pure helpers for the control laws: clamp, rate limit, zero-mean box projection.

Every function here is stateless; the loops in `controller.feed_loop` and
`controller.uniformity_loop` keep their own state and call these.
"""

from __future__ import annotations

import numpy as np

from core.checks import check_finite, check_positive


def clamp(value: float, lo: float, hi: float) -> float:
    """Return ``value`` limited to ``[lo, hi]``.

    Parameters
    ----------
    value : float
        The value to limit.
    lo, hi : float
        The bounds, ``lo <= hi``.

    Returns
    -------
    float
        ``min(max(value, lo), hi)``.
    """
    if lo > hi:
        raise ValueError(f"lo must be <= hi, got lo={lo!r}, hi={hi!r}")
    return min(max(float(value), lo), hi)


def rate_limit(target: float, previous: float, *, rate_max: float, dt_s: float) -> float:
    """Move from ``previous`` toward ``target`` by at most ``rate_max * dt_s``.

    Parameters
    ----------
    target : float
        Where the signal wants to go.
    previous : float
        The last output of the limiter.
    rate_max : float
        The largest allowed change per second (> 0), in the signal's unit per second.
    dt_s : float
        Time since ``previous`` was output (>= 0), seconds.

    Returns
    -------
    float
        The limited value; equal to ``target`` when the step is small enough.
    """
    check_positive("rate_max", rate_max)
    check_positive("dt_s", dt_s, allow_zero=True)
    step = rate_max * dt_s
    return previous + min(max(target - previous, -step), step)


def project_zero_mean_box(values: np.ndarray, *, bound: float) -> np.ndarray:
    """Euclidean projection onto ``{v : sum(v) = 0, |v_k| <= bound}``.

    The projection of ``values`` onto the intersection of the zero-sum hyperplane and the box
    is ``clip(values - c, -bound, bound)`` with the scalar ``c`` that makes the sum zero (the
    KKT conditions of the problem); the sum is piecewise linear and monotone in ``c``, so ``c``
    is found exactly from its values at the breakpoints ``values -+ bound``.

    Parameters
    ----------
    values : ndarray, shape (n,)
        The point to project (finite).
    bound : float
        Half-width of the box (> 0).

    Returns
    -------
    ndarray, shape (n,)
        The nearest point with zero mean and every entry within ``[-bound, bound]``.
    """
    v = np.asarray(values, dtype=float)
    if v.ndim != 1 or v.size == 0:
        raise ValueError(f"values must be a non-empty 1-D array, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("values contains NaN or infinite values")
    check_positive("bound", bound)
    # s(c) = sum(clip(v - c, -bound, bound)) is continuous, non-increasing and piecewise linear
    # in c with breakpoints at v_k -+ bound: evaluate it there and interpolate the zero.
    knots = np.sort(np.concatenate([v - bound, v + bound]))
    sums = np.clip(v[None, :] - knots[:, None], -bound, bound).sum(axis=1)
    i = int(np.searchsorted(-sums, 0.0))  # first knot with s <= 0 (s(knots[0]) = n*bound > 0)
    if sums[i] == 0.0 or i == 0:
        c = float(knots[i])
    else:
        c0, c1, s0, s1 = knots[i - 1], knots[i], sums[i - 1], sums[i]
        c = float(c0 + (c1 - c0) * s0 / (s0 - s1))
    return np.clip(v - c, -bound, bound)


def check_time_forward(now_s: float, last_s: float | None) -> float:
    """Return ``now_s`` as float; ``ValueError`` if it is not finite or earlier than ``last_s``."""
    t = check_finite("now_s", now_s)
    if last_s is not None and t < last_s:
        raise ValueError(f"now_s must not decrease: got {t!r} after {last_s!r}")
    return t
