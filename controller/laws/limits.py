"""Limits of the setpoints: clamp, rate limit, box projections, and the piezo offsets' bound.

The functions are stateless; the loops in `controller.laws.feed_loop` and
`controller.laws.uniformity_loop` keep their own state and call them.

The piezo offsets' bound (:class:`OffsetLimit`, pure, no I/O) is the smaller of the stroke in
``machine.toml`` and what the amplifier reports over CAN (``PIEZO_LIMITS``: :class:`AmpLimits`),
narrowed after a table the amplifier refused; until the amplifier has reported its limits
(at start and after every reconnect) the bound is zero. :func:`replan_offsets` brings a table
inside a bound keeping its mean (zero-mean tables stay zero-mean).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from core.checks import check_finite, check_positive, check_range


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


def project_zero_mean_box(values: np.ndarray, *, bound: float, mean: float = 0.0) -> np.ndarray:
    """Euclidean projection onto ``{v : mean(v) = mean, |v_k| <= bound}`` (default mean 0).

    The projection of ``values`` onto the intersection of the hyperplane and the box is
    ``clip(values - c, -bound, bound)`` with the scalar ``c`` that gives the mean (the KKT
    conditions of the problem); the sum is piecewise linear and monotone in ``c``, so ``c`` is
    found exactly from its values at the breakpoints ``values -+ bound``. When ``values``
    shifted to the mean lies inside the box, that shift is the projection (no breakpoints).

    Parameters
    ----------
    values : ndarray, shape (n,)
        The point to project (finite).
    bound : float
        Half-width of the box (> 0).
    mean : float
        The mean of the result, within ``[-bound, bound]``.

    Returns
    -------
    ndarray, shape (n,)
        The nearest point with that mean and every entry within ``[-bound, bound]``.
    """
    v = np.asarray(values, dtype=float)
    if v.ndim != 1 or v.size == 0:
        raise ValueError(f"values must be a non-empty 1-D array, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("values contains NaN or infinite values")
    check_positive("bound", bound)
    target = v.size * check_range("mean", mean, -bound, bound)
    shifted = v - (float(v.mean()) - float(mean))  # the projection when no entry meets the box
    if float(np.max(np.abs(shifted))) <= bound:
        return shifted
    # s(c) = sum(clip(v - c, -bound, bound)) is continuous, non-increasing and piecewise linear
    # in c with breakpoints at v_k -+ bound: evaluate it there and interpolate the target.
    knots = np.sort(np.concatenate([v - bound, v + bound]))
    sums = np.clip(v[None, :] - knots[:, None], -bound, bound).sum(axis=1)
    # first knot with s <= target (s(knots[0]) = n*bound >= target >= s(knots[-1]) = -n*bound)
    i = min(int(np.searchsorted(-sums, -target)), len(knots) - 1)
    if sums[i] == target or i == 0 or sums[i - 1] == sums[i]:
        c = float(knots[i])
    else:
        c0, c1, s0, s1 = knots[i - 1], knots[i], sums[i - 1], sums[i]
        c = float(c0 + (c1 - c0) * (s0 - target) / (s0 - s1))
    return np.clip(v - c, -bound, bound)


def replan_offsets(offsets_um: Sequence[float] | np.ndarray, *, limit_um: float) -> np.ndarray:
    """An offset table inside ``+-limit_um``: unchanged if it is, else re-planned.

    The re-planned table is the nearest one (Euclidean) with every entry within the limit and
    the same mean (clipped to the limit): a zero-mean table (the uniformity loop's) stays
    zero-mean, so the board's thickness does not change; the knives' relative depths are kept
    as far as the limit allows. A limit of 0 gives zeros.

    Parameters
    ----------
    offsets_um : sequence of float, shape (Z,)
        The table, um (finite).
    limit_um : float
        The bound, um (>= 0).

    Returns
    -------
    ndarray, shape (Z,)
        The table to send; every ``|entry| <= limit_um``.
    """
    v = np.asarray(offsets_um, dtype=float)
    if v.ndim != 1 or v.size == 0:
        raise ValueError(f"offsets_um must be a non-empty 1-D sequence, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("offsets_um contains NaN or infinite values")
    lim = check_positive("limit_um", limit_um, allow_zero=True)
    if float(np.max(np.abs(v))) <= lim:
        return v.copy()
    if lim == 0.0:
        return np.zeros_like(v)
    mean = min(max(float(v.mean()), -lim), lim)
    return np.clip(project_zero_mean_box(v, bound=lim, mean=mean), -lim, lim)


def check_time_forward(now_s: float, last_s: float | None) -> float:
    """Return ``now_s`` as float; ``ValueError`` if it is not finite or earlier than ``last_s``."""
    t = check_finite("now_s", now_s)
    if last_s is not None and t < last_s:
        raise ValueError(f"now_s must not decrease: got {t!r} after {last_s!r}")
    return t


# ---------------------------------------------------------------------------------- piezo bound
REFUSAL_SHRINK = 0.8
"""After a refused table the bound becomes this fraction of the table's largest offset."""
MIN_LIMIT_UM = 0.05
"""A bound below this is zero: the table is all zeros (the safe table), um."""


@dataclass(frozen=True)
class AmpLimits:
    """What the amplifier reports of its limits (CAN ``PIEZO_LIMITS``).

    Attributes
    ----------
    stroke_um : float
        The actuator's stroke, um (> 0).
    offset_min_um, offset_max_um : float
        The offsets it accepts in a table, um (``offset_min_um <= 0 <= offset_max_um``: the
        zero table is always accepted).
    slew_max_um_ms : float
        Largest output slew rate, um/ms (0: not limited).
    setpoint_timeout_s : float
        Its setpoint timeout, s (>= 0).
    """

    stroke_um: float
    offset_min_um: float
    offset_max_um: float
    slew_max_um_ms: float = 0.0
    setpoint_timeout_s: float = 0.1

    def __post_init__(self) -> None:
        check_positive("stroke_um", self.stroke_um)
        lo = check_finite("offset_min_um", self.offset_min_um)
        hi = check_finite("offset_max_um", self.offset_max_um)
        if not lo <= 0.0 <= hi:
            raise ValueError(
                f"offset_min_um <= 0 <= offset_max_um must hold, got [{lo!r}, {hi!r}] µm"
            )
        check_positive("slew_max_um_ms", self.slew_max_um_ms, allow_zero=True)
        check_positive("setpoint_timeout_s", self.setpoint_timeout_s, allow_zero=True)

    @classmethod
    def from_signals(cls, signals: Mapping[str, float | int]) -> AmpLimits:
        """From a decoded ``PIEZO_LIMITS``; ``ValueError`` naming the signal that makes no sense."""
        try:
            return cls(
                stroke_um=float(signals["stroke_um"]),
                offset_min_um=float(signals["offset_min_um"]),
                offset_max_um=float(signals["offset_max_um"]),
                slew_max_um_ms=float(signals["slew_max_um_ms"]),
                setpoint_timeout_s=float(signals["setpoint_timeout_ms"]) * 1e-3,
            )
        except KeyError as exc:
            raise ValueError(f"PIEZO_LIMITS lacks signal {exc.args[0]}") from None

    @property
    def bound_um(self) -> float:
        """The largest offset magnitude it accepts both ways, um."""
        return min(self.stroke_um, -self.offset_min_um, self.offset_max_um)


class OffsetLimit:
    """The bound on the piezo offsets in force (pure; no clock, no I/O).

    ``limit_um`` is ``min(config stroke, amplifier's bound)``, narrowed after a refused table
    (to ``REFUSAL_SHRINK`` times its largest offset, zero below ``MIN_LIMIT_UM``), and zero
    while the amplifier has not reported its limits (at start, after a reconnect): a stroke in
    ``machine.toml`` larger than the amplifier's is never used. The narrowing holds until the
    amplifier reports other limits or is lost and found again.

    Parameters
    ----------
    config_stroke_um : float
        ``machine.toml``'s ``[piezo] stroke_um``, um (> 0).
    wire_bound_um : float, optional
        The largest offset the CAN signals carry, um (the smaller bound wins).
    """

    def __init__(self, config_stroke_um: float, *, wire_bound_um: float | None = None) -> None:
        cfg = check_positive("config_stroke_um", config_stroke_um)
        if wire_bound_um is not None:
            cfg = min(cfg, check_positive("wire_bound_um", wire_bound_um))
        self.config_stroke_um = cfg
        """The configured stroke (within what the wire carries), um."""
        self.amp: AmpLimits | None = None
        """The amplifier's last report since it was (re)connected."""
        self.refused_bound_um: float | None = None
        """The bound after the last refused table (``None``: none refused)."""

    # ------------------------------------------------------------------ state
    @property
    def stroke_um(self) -> float | None:
        """``min(config, amplifier)``, um; ``None`` while the amplifier has not reported."""
        if self.amp is None:
            return None
        return min(self.config_stroke_um, self.amp.bound_um)

    @property
    def limit_um(self) -> float:
        """The bound on every offset now, um (0 while the amplifier's limits are unknown)."""
        stroke = self.stroke_um
        if stroke is None:
            return 0.0
        if self.refused_bound_um is not None:
            return min(stroke, self.refused_bound_um)
        return stroke

    @property
    def source(self) -> str:
        """Where the bound comes from.

        ``amplifier``, ``machine.toml``, ``refused table`` or ``unknown`` (the amplifier has
        not reported its limits).
        """
        if self.amp is None:
            return "unknown"
        if self.refused_bound_um is not None and self.refused_bound_um < self.stroke_um:
            return "refused table"
        return "amplifier" if self.amp.bound_um < self.config_stroke_um else "machine.toml"

    # ------------------------------------------------------------------ inputs
    def amp_reported(self, limits: AmpLimits) -> bool:
        """The amplifier's report; whether it changed the amplifier's limits known."""
        if not isinstance(limits, AmpLimits):
            raise ValueError(f"limits must be AmpLimits, got {type(limits).__name__}")
        if limits == self.amp:
            return False
        self.amp = limits
        self.refused_bound_um = None  # new limits: a refusal under the old ones says nothing
        return True

    def amp_lost(self) -> bool:
        """The amplifier went silent (a reconnect follows): forget its limits; whether known."""
        known = self.amp is not None
        self.amp = None
        self.refused_bound_um = None
        return known

    def table_refused(self, table_um: Sequence[float]) -> float | None:
        """The amplifier refused ``table_um``: narrow the bound below it.

        Returns
        -------
        float or None
            The new bound (every later table differs from the refused one), or ``None`` when
            the refused table was all zeros (nothing smaller exists: the amplifier is faulty).
        """
        t = np.asarray(table_um, dtype=float)
        if t.ndim != 1 or t.size == 0 or not np.all(np.isfinite(t)):
            raise ValueError("table_um must be a non-empty 1-D sequence of finite values")
        largest = float(np.max(np.abs(t)))
        if largest == 0.0:
            return None
        new = REFUSAL_SHRINK * largest
        if new < MIN_LIMIT_UM:
            new = 0.0
        old = self.refused_bound_um
        self.refused_bound_um = new if old is None else min(old, new)
        return self.limit_um

    # ------------------------------------------------------------------ outputs
    def plan(self, offsets_um: Sequence[float] | np.ndarray) -> np.ndarray:
        """The table within the bound now (:func:`replan_offsets`)."""
        return replan_offsets(offsets_um, limit_um=self.limit_um)

    def describe(self) -> str:
        """One line: the bound in force and where it comes from."""
        cfg = self.config_stroke_um
        amp = self.amp
        if amp is None:
            return (f"piezo offsets held at zero: the amplifier has not reported its limits "
                    f"(machine.toml: stroke {cfg:.3f} µm)")
        src = self.source
        lim = self.limit_um
        if src == "refused table":
            return (f"piezo offsets within +-{lim:.3f} µm after a refused table (stroke "
                    f"{self.stroke_um:.3f} µm: amplifier {amp.bound_um:.3f}, machine.toml "
                    f"{cfg:.3f})")
        if src == "amplifier":
            return (f"piezo offsets within +-{lim:.3f} µm: the amplifier's stroke, smaller than "
                    f"machine.toml's {cfg:.3f} µm")
        return (f"piezo offsets within +-{lim:.3f} µm: machine.toml's stroke (the amplifier "
                f"allows {amp.bound_um:.3f} µm)")

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON of the bound and what it comes from.

        Keys ``limit_um``, ``stroke_um``, ``source``, ``config_stroke_um``, ``amp_stroke_um``,
        ``amp_offset_range_um``, ``amp_slew_max_um_ms``, ``amp_setpoint_timeout_s``,
        ``refused_bound_um``.
        """
        amp = self.amp
        return {
            "limit_um": self.limit_um,
            "stroke_um": self.stroke_um,
            "source": self.source,
            "config_stroke_um": self.config_stroke_um,
            "amp_stroke_um": None if amp is None else amp.stroke_um,
            "amp_offset_range_um": None if amp is None else [amp.offset_min_um,
                                                            amp.offset_max_um],
            "amp_slew_max_um_ms": None if amp is None else amp.slew_max_um_ms,
            "amp_setpoint_timeout_s": None if amp is None else amp.setpoint_timeout_s,
            "refused_bound_um": self.refused_bound_um,
        }
