"""The constrained optimum of the per-knife offsets: a small exact QP on the width model.

With relative depths ``z = A o - s`` (``A`` the actuator's effective gain matrix, ``s`` the
runout as the loop estimates it, both in um) the width errors are ``G D z`` (``D`` the circulant
second difference, ``controller.laws.uniformity_loop``), so the best offsets the stroke allows are::

    minimise  || D (A o - s) ||^2    subject to  sum(o) = 0,  |o_k| <= bound

— the zero-mean set within the stroke with the smallest width CV, not the clipped unconstrained
solution (which minimises ``||o - A^-1 s||``, a different norm: it leaves ``D``'s largest mode
uncorrected first). The problem is a convex QP in ``Z <= 8`` variables with one equality and a
box; :func:`box_qp` solves it exactly with a primal active-set method (finite, a few iterations,
each one solve of at most ``Z + 1`` equations) started from a feasible point. When the
unconstrained zero-sum minimiser lies inside the box (checked exactly) it is the answer and no
iteration runs. A part of the table may be held (a knife pattern the actuator cannot move:
``hold``, a projector onto those modes, with a stiff penalty keeping it at a given table).
:class:`OffsetPlanner` sets the problem up once for one width operator and actuator (the
uniformity loop's, rebuilt when the identified actuator changes), so a pair costs one ``Z x Z``
product in plain floats when no bound is active. Pure: arrays in, arrays out.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Sequence

import numpy as np

from controller.laws.limits import project_zero_mean_box
from core.checks import check_positive

MAX_ITERATIONS = 200
"""Active-set iterations before giving up (the problem needs at most a few times ``Z``)."""
HOLD_WEIGHT = 1e4
"""Weight of a held part of the table (:class:`OffsetPlanner` ``hold``) against the scaled width
cost (whose largest diagonal entry is 1): a held knife pattern moves by about 1e-4 of what the
width cost asks of it."""


def _solve(kkt: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.solve(kkt, rhs)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(kkt, rhs, rcond=None)[0]


def _equality_multiplier(grad: np.ndarray, free: np.ndarray, lower: np.ndarray,
                         upper: np.ndarray) -> float:
    """The multiplier ``nu`` of ``sum(o) = 0`` at a stationary point of the working set."""
    if np.any(free):
        return float(-grad[free].mean())
    # every variable on a bound: nu is any value in [max over lower of -g, min over upper of -g]
    lo = float(np.max(-grad[lower])) if np.any(lower) else -np.inf
    hi = float(np.min(-grad[upper])) if np.any(upper) else np.inf
    if np.isfinite(lo) and np.isfinite(hi):
        return 0.5 * (lo + hi)
    return lo if np.isfinite(lo) else hi


def _kkt(h: np.ndarray) -> np.ndarray:
    """``[[H, 1], [1', 0]]``: the equality-constrained system of the free variables."""
    n = h.shape[0]
    kkt = np.zeros((n + 1, n + 1))
    kkt[:n, :n] = h
    kkt[:n, n] = 1.0
    kkt[n, :n] = 1.0
    return kkt


def _inside(o: np.ndarray, b: float) -> np.ndarray | None:
    """``o`` with its sum carried back to zero if then every entry is within ``+-b``, else None."""
    o = o - o.sum() / o.size
    return o if bool(np.all(np.abs(o) <= b)) else None


def box_qp(
    hessian: np.ndarray, linear: np.ndarray, *, bound: float, start: np.ndarray | None = None
) -> np.ndarray:
    """Minimise ``0.5 o' H o - c' o`` subject to ``sum(o) = 0`` and ``|o_k| <= bound``.

    The unconstrained zero-sum minimiser (one solve of the ``n + 1`` KKT equations), its sum
    carried back to zero, is returned at once when every entry lies within the box (checked
    exactly: it then satisfies the KKT conditions with no active bound); otherwise the active
    set iterates from ``start``.

    Parameters
    ----------
    hessian : ndarray, shape (n, n)
        ``H``, symmetric and positive definite on the zero-sum subspace.
    linear : ndarray, shape (n,)
        ``c``.
    bound : float
        Half-width of the box (> 0).
    start : ndarray, shape (n,), optional
        A starting point (projected into the feasible set); default the projection of the
        unconstrained zero-sum minimiser.

    Returns
    -------
    ndarray, shape (n,)
        The minimiser: zero sum, every entry within ``[-bound, bound]``.
    """
    h = np.asarray(hessian, dtype=float)
    c = np.asarray(linear, dtype=float)
    n = c.size
    if c.ndim != 1 or h.shape != (n, n):
        raise ValueError(f"hessian must be ({n}, {n}) for a linear term of {n}, got {h.shape}")
    if not (np.all(np.isfinite(h)) and np.all(np.isfinite(c))):
        raise ValueError("hessian and linear must be finite")
    b = check_positive("bound", bound)
    unconstrained = _solve(_kkt(h), np.append(c, 0.0))[:n]
    fast = _inside(unconstrained, b)
    if fast is not None:
        return fast
    return _active_set(h, c, b, unconstrained if start is None else start)


def _active_set(h: np.ndarray, c: np.ndarray, b: float, start: np.ndarray) -> np.ndarray:
    """:func:`box_qp`'s iteration from ``start`` (projected into the feasible set)."""
    n = c.size
    o = project_zero_mean_box(np.asarray(start, dtype=float), bound=b)
    tol = 1e-12 * max(1.0, b)
    upper = o >= b - tol
    lower = o <= -b + tol
    o[upper], o[lower] = b, -b
    for _ in range(MAX_ITERATIONS):
        free = ~(upper | lower)
        grad = h @ o - c
        nf = int(free.sum())
        p = np.zeros(n)
        if nf > 1:
            hf = h[np.ix_(free, free)]
            p[free] = _solve(_kkt(hf), np.append(-grad[free], 0.0))[:nf]
        if np.max(np.abs(p)) <= 1e-12 * max(1.0, float(np.max(np.abs(o)))):
            nu = _equality_multiplier(grad, free, lower, upper)
            mu = np.where(upper, -(grad + nu), np.where(lower, grad + nu, 0.0))
            worst = int(np.argmin(mu))
            if mu[worst] >= -1e-10 * max(1.0, float(np.max(np.abs(grad)))):
                break  # KKT: optimal
            upper[worst] = lower[worst] = False
            continue
        # longest step along p inside the box; a blocking bound joins the working set
        step, block = 1.0, -1
        for i in np.flatnonzero(free & (p != 0.0)):
            room = (b - o[i]) / p[i] if p[i] > 0 else (-b - o[i]) / p[i]
            if room < step:
                step, block = max(room, 0.0), int(i)
        o = o + step * p
        if block >= 0:
            if p[block] > 0:
                o[block], upper[block] = b, True
            else:
                o[block], lower[block] = -b, True
    free = ~(upper | lower)
    if np.any(free):  # rounding: the free entries carry the sum back to zero
        o[free] -= o.sum() / int(free.sum())
    return np.clip(o, -b, b)


def best_offsets_um(
    disturbance_um: np.ndarray,
    *,
    width_operator: np.ndarray,
    actuator: np.ndarray,
    bound_um: float,
    start_um: np.ndarray | None = None,
) -> np.ndarray:
    """The zero-mean offsets within ``bound_um`` that minimise ``|| W (A o - s) ||``.

    Parameters
    ----------
    disturbance_um : ndarray, shape (Z,)
        ``s``: the runout as the loop sees it, um (its mean does not matter).
    width_operator : ndarray, shape (Z, Z)
        ``W``: width errors per um of relative depth (the second difference ``D``; its scale
        does not change the minimiser).
    actuator : ndarray, shape (Z, Z)
        ``A``: effective relative depth per um of commanded offset (identity for an ideal
        actuator).
    bound_um : float
        Largest magnitude of an offset, um.
    start_um : ndarray, shape (Z,), optional
        Warm start of the iteration (e.g. the offsets in force) when a bound is active.

    Returns
    -------
    ndarray, shape (Z,)
        The constrained optimum, um.
    """
    planner = OffsetPlanner(width_operator=width_operator, actuator=actuator)
    return planner.best_offsets_um(disturbance_um, bound_um=bound_um, start_um=start_um)


class OffsetPlanner:
    """:func:`best_offsets_um` set up once for one width operator and one actuator.

    The Hessian ``H = (W A)' (W A)``, the map ``s -> c = (W A)' W s`` (both scaled so that the
    tolerances are scale-free) and the map from ``s`` to the unconstrained zero-sum minimiser
    are computed here; :meth:`best_offsets_um` then costs one ``Z x Z`` product in plain floats
    when that minimiser lies inside the box (checked exactly), else the active set of
    :func:`box_qp`.

    Parameters
    ----------
    width_operator : ndarray, shape (Z, Z)
        ``W`` (the second difference ``D``).
    actuator : ndarray, shape (Z, Z)
        ``A`` (identity for an ideal actuator).
    """

    def __init__(
        self,
        *,
        width_operator: np.ndarray,
        actuator: np.ndarray,
        hold: np.ndarray | None = None,
    ) -> None:
        w = np.asarray(width_operator, dtype=float)
        a = np.asarray(actuator, dtype=float)
        n = w.shape[0]
        if w.shape != (n, n) or a.shape != (n, n):
            raise ValueError(f"width_operator and actuator must be square and alike, got "
                             f"{w.shape} and {a.shape}")
        if not (np.all(np.isfinite(w)) and np.all(np.isfinite(a))):
            raise ValueError("width_operator and actuator must be finite")
        wa = w @ a
        h = wa.T @ wa
        self._w = w
        self._wa = wa
        self._scale = float(np.max(np.abs(np.diag(h)))) or 1.0  # scale-free tolerances
        self._hold: np.ndarray | None = None
        if hold is not None:
            p = np.asarray(hold, dtype=float)
            if p.shape != (n, n) or not np.all(np.isfinite(p)):
                raise ValueError(f"hold must be a finite ({n}, {n}) projector, got {p.shape}")
            self._hold = HOLD_WEIGHT * p
            h = h / self._scale + self._hold
        else:
            h = h / self._scale
        self.hessian = h
        """``H`` over its largest diagonal entry (plus the hold's penalty), shape (Z, Z)."""
        # unconstrained zero-sum minimiser: o = K c (K the top-left block of the KKT inverse)
        kinv = np.linalg.pinv(_kkt(self.hessian))[:n, :n]
        gain = kinv @ ((wa.T @ w) / self._scale)
        self._rows = tuple(tuple(float(v) for v in row) for row in gain)
        self._hold_rows = (None if self._hold is None else
                           tuple(tuple(float(v) for v in row) for row in kinv @ self._hold))

    @property
    def knives(self) -> int:
        """``Z``."""
        return len(self._rows)

    def linear(self, disturbance_um: np.ndarray, hold_um: np.ndarray | None = None) -> np.ndarray:
        """``c = (W A)' W s`` over the scale (plus the hold's ``w P h``), shape (Z,)."""
        s = np.asarray(disturbance_um, dtype=float)
        c = self._wa.T @ (self._w @ s) / self._scale
        if self._hold is not None and hold_um is not None:
            c = c + self._hold @ np.asarray(hold_um, dtype=float)
        return c

    def best_offsets_um(
        self,
        disturbance_um: Sequence[float] | np.ndarray,
        *,
        bound_um: float,
        start_um: np.ndarray | None = None,
        hold_um: np.ndarray | None = None,
    ) -> np.ndarray:
        """The zero-mean offsets within ``bound_um`` that minimise ``|| W (A o - s) ||``.

        Parameters
        ----------
        disturbance_um : sequence of float, shape (Z,)
            ``s``, um (finite).
        bound_um : float
            Largest magnitude of an offset, um (> 0).
        start_um : ndarray, shape (Z,), optional
            Warm start of the iteration when a bound is active.
        hold_um : ndarray, shape (Z,), optional
            With a ``hold`` projector ``P``: the table whose ``P`` part the result keeps (the
            penalty ``HOLD_WEIGHT ||P (o - h)||^2`` on the scaled cost); default zeros.

        Returns
        -------
        ndarray, shape (Z,)
            The constrained optimum, um (the unconstrained one when it fits the box).
        """
        b = check_positive("bound_um", bound_um)
        s_arr = np.asarray(disturbance_um, dtype=float)
        n = len(self._rows)
        s = s_arr.tolist()
        if s_arr.shape != (n,) or not all(map(math.isfinite, s)):
            raise ValueError(f"disturbance_um must be {n} finite values, got {disturbance_um!r}")
        o = [sum(map(operator.mul, row, s)) for row in self._rows]
        hold = None
        if self._hold_rows is not None and hold_um is not None:
            hold = np.asarray(hold_um, dtype=float)
            if hold.shape != (n,) or not np.all(np.isfinite(hold)):
                raise ValueError(f"hold_um must be {n} finite values, got {hold_um!r}")
            hl = hold.tolist()
            o = [v + sum(map(operator.mul, row, hl)) for v, row in zip(o, self._hold_rows,
                                                                        strict=True)]
        mean = sum(o) / n
        o = [v - mean for v in o]
        if max(map(abs, o)) <= b:
            return np.array(o)
        return _active_set(self.hessian, self.linear(s, hold), b,
                           np.array(o) if start_um is None else start_um)
