"""Compiled loops (numba) of :func:`vision.marks.find_marks`'s choice of cusps.

The candidate cusps (:func:`vision.kernels.cusp_candidates`) are tested against the arc model
of the slope, ``p = kappa (s - b_k)`` in the piece of profile between two cusps: one common
gradient ``kappa``, one lowest point ``b_k`` per piece, fitted from running sums.

* :func:`false_cusps` -- which cusps the noise put inside a mark (the pieces either side have
  the same ``b``; :func:`vision.marks.without_false_cusps`);
* :func:`narrow_cusps` -- the weaker candidates that bound a narrow mark of their own
  (:func:`vision.marks.with_narrow_marks`);
* :func:`cusp_gaps` -- the whole choice from the candidates in one call (the strong steps,
  :func:`false_cusps`, :func:`narrow_cusps`, :func:`false_cusps` again), as
  ``vision.marks._cusp_gaps`` composes the two functions above.

Compiled with ``cache=True`` on first use; :func:`warm_up` compiles both with the argument
types :mod:`vision.marks` passes (called from :func:`vision.kernels.warm_up`, so at a
measurer's set-up, never on a frame).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_JIT = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}


@njit(**_JIT)
def _cum_xp(p: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """``[0, cumsum(i p_i)]``."""
    out = np.empty(p.size + 1)
    out[0] = 0.0
    acc = 0.0
    for i in range(p.size):
        acc += float(i) * p[i]
        out[i + 1] = acc
    return out


@njit(**_JIT)
def _piece(gaps: np.ndarray, k: int, n: int,
           ex: int) -> tuple[int, int, bool]:  # pragma: no cover - compiled
    """Samples ``[lo, hi)`` of piece ``k`` (between ``gaps[k - 1]`` and ``gaps[k]``).

    And whether it is regular (``ex`` samples left out next to each cusp, one at the
    profile's ends, at least 2 left); a shorter piece keeps all its samples.
    """
    g = gaps.size
    start = 0 if k == 0 else int(gaps[k - 1] + 0.5)
    end = n if k == g else int(gaps[k] + 0.5)
    lo = 1 if k == 0 else start + ex
    hi = n - 1 if k == g else end - ex
    if hi - lo >= 2:
        return lo, hi, True
    return start, end, False


@njit(**_JIT)
def _kappa(cum_p: np.ndarray, cum_xp: np.ndarray, gaps: np.ndarray, n: int,
           ex: int) -> float:  # pragma: no cover - compiled
    """The common gradient pooled over the regular pieces (0 when none)."""
    num = 0.0
    den = 0.0
    for k in range(gaps.size + 1):
        lo, hi, regular = _piece(gaps, k, n, ex)
        if not regular:
            continue
        lo_f, hi_f = float(lo), float(hi)
        cnt = hi_f - lo_f
        sx = (hi_f * (hi_f - 1) - lo_f * (lo_f - 1)) / 2
        sxx = ((hi_f - 1) * hi_f * (2 * hi_f - 1) - (lo_f - 1) * lo_f * (2 * lo_f - 1)) / 6
        sp = cum_p[hi] - cum_p[lo]
        sxp = cum_xp[hi] - cum_xp[lo]
        den += sxx - sx * sx / cnt
        num += sxp - sx * sp / cnt
    return num / den if den > 0 else 0.0


@njit(**_JIT)
def false_cusps(p: np.ndarray, cum_p: np.ndarray, gaps: np.ndarray, guard: int,
                min_step: float) -> np.ndarray:  # pragma: no cover - compiled
    """Which cusps lie between pieces whose lowest points lie too close together.

    Closer than ``min_step`` of the median distance; all False when fewer than 4 pieces fit,
    3 distances are measured, or ``kappa <= 0``.
    """
    n = p.size
    g = gaps.size
    ex = max(guard - 1, 0)
    out = np.zeros(g, dtype=np.bool_)
    cum_xp = _cum_xp(p)
    kappa = _kappa(cum_p, cum_xp, gaps, n, ex)
    if not kappa > 0:
        return out
    b = np.full(g + 1, np.nan)
    fits = 0
    for k in range(g + 1):
        lo, hi, _ = _piece(gaps, k, n, ex)
        if hi - lo < 2:
            continue
        fits += 1
        b[k] = 0.5 * (lo + hi - 1) - (cum_p[hi] - cum_p[lo]) / (kappa * (hi - lo))
    if fits < 4:
        return out
    apart = b[1:] - b[:-1]
    measured = np.isfinite(apart)
    if np.count_nonzero(measured) < 3:
        return out
    typical = np.median(apart[measured])
    if not typical > 0:
        return out
    for k in range(g):
        out[k] = measured[k] and apart[k] < min_step * typical
    return out


@njit(**_JIT)
def _bottom(cum_p: np.ndarray, start: int, end: int, kappa: float, ex: int, before: bool,
            after: bool) -> tuple[float, int]:  # pragma: no cover - compiled
    """Lowest point of the line ``kappa (s - b)`` over ``[start, end)``, and the samples used.

    ``ex`` samples are left out next to a cusp, one at a profile end, when 2 stay; 0 samples
    (and NaN): a piece shorter than 2.
    """
    lo = start + (ex if before else 1)
    hi = end - (ex if after else 1)
    if hi - lo < 2:
        lo, hi = start, end
    if hi - lo < 2:
        return np.nan, 0
    cnt = hi - lo
    return 0.5 * (lo + hi - 1) - (cum_p[hi] - cum_p[lo]) / (kappa * cnt), cnt


@njit(**_JIT)
def narrow_cusps(p: np.ndarray, cum_p: np.ndarray, gaps: np.ndarray, weak: np.ndarray,
                 all_gaps: np.ndarray, guard: int, typical_step: float, noise: float,
                 min_fall: float, z: float) -> np.ndarray:  # pragma: no cover - compiled
    """``gaps`` with those ``weak`` candidates (tried in their order) that bound a mark.

    A candidate is added when the lowest points of its two pieces advance by
    ``min_fall * typical_step / kappa`` and by ``z`` standard errors, both pieces holding at
    least ``2 guard`` samples (``kappa`` pooled over the pieces of ``all_gaps``).
    """
    n = p.size
    ex = max(guard - 1, 0)
    cum_xp = _cum_xp(p)
    kappa = _kappa(cum_p, cum_xp, all_gaps, n, ex)
    out = np.empty(gaps.size + weak.size)
    m = gaps.size
    out[:m] = gaps
    if not (kappa > 0 and typical_step > 0):
        return out[:m].copy()
    need = min_fall * typical_step / kappa
    sigma = max(noise, 0.0) / kappa
    for w in range(weak.size):
        gw = weak[w]
        j = np.searchsorted(out[:m], gw)
        if j < m and out[j] == gw:
            continue
        cut = int(gw + 0.5)
        start = int(out[j - 1] + 0.5) if j > 0 else 0
        end = int(out[j] + 0.5) if j < m else n
        if min(cut - start, end - cut) < 2 * guard:
            continue
        bl, nl = _bottom(cum_p, start, cut, kappa, ex, j > 0, True)
        br, nr = _bottom(cum_p, cut, end, kappa, ex, True, j < m)
        if nl == 0 or nr == 0:
            continue
        apart = br - bl
        if apart >= need and apart >= z * sigma * math.sqrt(1.0 / nl + 1.0 / nr):
            for q in range(m, j, -1):
                out[q] = out[q - 1]
            out[j] = gw
            m += 1
    return out[:m].copy()


@njit(**_JIT)
def _without_false(p: np.ndarray, cum_p: np.ndarray, gaps: np.ndarray, guard: int,
                   min_step: float) -> np.ndarray:  # pragma: no cover - compiled
    """``gaps`` less :func:`false_cusps` (:func:`vision.marks.without_false_cusps`)."""
    false = false_cusps(p, cum_p, gaps, guard, min_step)
    if not false.any():
        return gaps
    return gaps[~false]


@njit(**_JIT)
def cusp_gaps(p: np.ndarray, cum_p: np.ndarray, cand: np.ndarray, size: np.ndarray,
              typical: float, noise: float, min_step: float, guard: int, weak_step: float,
              z: float) -> np.ndarray:  # pragma: no cover - compiled
    """The refined cusps to a sample from the candidates ``cand`` and their steps ``size``.

    The candidates whose step is at least ``min_step * typical``, less the false ones; then,
    with at least 3 left, the weaker candidates (at least ``weak_step * typical``, largest
    first, ties in their order) that bound a narrow mark, and the false ones of those dropped.
    The same operations in the same order as ``vision.marks._cusp_gaps`` (refined).
    """
    strong_lim = min_step * typical
    weak_lim = weak_step * typical
    n_strong = 0
    n_weak = 0
    n_all = 0
    for i in range(size.size):
        if size[i] >= strong_lim:
            n_strong += 1
        elif size[i] >= weak_lim:
            n_weak += 1
        if size[i] >= weak_lim:
            n_all += 1
    gaps = np.empty(n_strong)
    weak_size = np.empty(n_weak)
    weak_at = np.empty(n_weak)
    all_gaps = np.empty(n_all)
    a = 0
    b = 0
    c = 0
    for i in range(size.size):
        if size[i] >= strong_lim:
            gaps[a] = float(cand[i]) + 0.5
            a += 1
        elif size[i] >= weak_lim:
            weak_size[b] = -size[i]
            weak_at[b] = float(cand[i]) + 0.5
            b += 1
        if size[i] >= weak_lim:
            all_gaps[c] = float(cand[i]) + 0.5
            c += 1
    if gaps.size < 3:
        return gaps
    gaps = _without_false(p, cum_p, gaps, guard, min_step)
    if n_weak == 0 or gaps.size < 3:
        return gaps
    order = np.argsort(weak_size, kind="mergesort")  # stable, as numpy's "stable"
    more = narrow_cusps(p, cum_p, gaps, weak_at[order], all_gaps, guard, typical, noise,
                        weak_step, z)
    if more.size == gaps.size:
        return gaps
    return _without_false(p, cum_p, more, guard, min_step)


_WARM = [False]


def warm_up() -> None:
    """Compile (or load from the cache) the kernels for the types :mod:`vision.marks` uses."""
    if _WARM[0]:
        return
    p = np.tile(np.linspace(-1.0, 1.0, 10), 6)
    cum = np.concatenate((np.zeros(1), np.cumsum(p)))
    gaps = np.arange(9.5, 50.0, 10.0)
    false_cusps(p, cum, gaps, 2, 0.35)
    narrow_cusps(p, cum, gaps, np.array([4.5]), gaps, 2, 0.2, 0.01, 0.2, 5.0)
    cand = np.arange(9, 50, 5, dtype=np.int64)
    cusp_gaps(p, cum, cand, np.linspace(0.1, 1.0, cand.size), 0.8, 0.01, 0.35, 2, 0.12, 5.0)
    _WARM[0] = True
