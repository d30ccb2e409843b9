"""The constrained optimum of the per-knife offsets: a small exact QP on the width model.

With relative depths ``z = A o - s`` (``A`` the actuator's effective gain matrix, ``s`` the
runout as the loop estimates it, both in um) the width errors are ``G D z`` (``D`` the circulant
second difference, ``controller.uniformity_loop``), so the best offsets the stroke allows are::

    minimise  || D (A o - s) ||^2    subject to  sum(o) = 0,  |o_k| <= bound

— the zero-mean set within the stroke with the smallest width CV, not the clipped unconstrained
solution (which minimises ``||o - A^-1 s||``, a different norm: it leaves ``D``'s largest mode
uncorrected first). The problem is a convex QP in ``Z <= 8`` variables with one equality and a
box; :func:`box_qp` solves it exactly with a primal active-set method (finite, a few iterations,
each one solve of at most ``Z + 1`` equations) started from a feasible point. Pure: arrays in,
arrays out.
"""

from __future__ import annotations

import numpy as np

from controller.limits import project_zero_mean_box
from core.checks import check_positive

MAX_ITERATIONS = 200
"""Active-set iterations before giving up (the problem needs at most a few times ``Z``)."""


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


def box_qp(
    hessian: np.ndarray, linear: np.ndarray, *, bound: float, start: np.ndarray | None = None
) -> np.ndarray:
    """Minimise ``0.5 o' H o - c' o`` subject to ``sum(o) = 0`` and ``|o_k| <= bound``.

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
    ones = np.ones(n)
    if start is None:
        kkt = np.block([[h, ones[:, None]], [ones[None, :], np.zeros((1, 1))]])
        start = _solve(kkt, np.concatenate([c, [0.0]]))[:n]
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
            kkt = np.block([[hf, np.ones((nf, 1))], [np.ones((1, nf)), np.zeros((1, 1))]])
            p[free] = _solve(kkt, np.concatenate([-grad[free], [0.0]]))[:nf]
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
        Warm start (e.g. the offsets in force).

    Returns
    -------
    ndarray, shape (Z,)
        The constrained optimum, um.
    """
    s = np.asarray(disturbance_um, dtype=float)
    wa = np.asarray(width_operator, dtype=float) @ np.asarray(actuator, dtype=float)
    h = wa.T @ wa
    c = wa.T @ (np.asarray(width_operator, dtype=float) @ s)
    scale = float(np.max(np.abs(np.diag(h)))) or 1.0  # keep the tolerances scale-free
    return box_qp(h / scale, c / scale, bound=bound_um, start=start_um)
