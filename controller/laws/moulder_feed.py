"""The moulder's feed law: one feed for N heads, the fastest at which every head meets its target.

Pure and clock-injected: :meth:`MoulderFeedLaw.update` takes each head's state and the time and
returns the feed setpoint and the variable heads' spindle setpoints; nothing here sleeps, reads
a clock or touches a bus.

Law (the argument is in ``docs/control_design.md``, "Moulder: one feed, many heads")::

    V_h   = c_h * p*_h * n_h * Z_h / 60        fixed head: n_h the measured spindle speed
    V_h   = c_h * p*_h * rpm_max_h * Z_h / 60  variable head: its fastest spindle
    V_des = clamp(min_h V_h, feed_min, feed_max)      over the heads that take part
    V     = rate_limit(V_des, V_prev, rate_max, now - t_prev)
    n_h   = clip(60 V / (c_h * p*_h * Z_h), rpm_min_h, rpm_max_h)   each variable head

``c_h`` is the head's learnt correction (its :class:`controller.laws.feed_loop.FeedLoop`'s
``correction``: the inverse of its model error, learnt from its own measured pitch against the
pitch the drive really cut with), ``p*_h`` its held pitch (target under the depth ceiling). The
pitch a head cuts is ``V / (n Z)`` times its model error, so ``V <= V_h`` is "head h meets its
target": the minimum is the fastest feed meeting all of them, and the head(s) at the minimum
are the limiting ones. A variable head then turns just fast enough to cut its own target at the
common feed (its pitch is its target whenever its speed range allows; below ``rpm_min`` it cuts
finer). A variable head's spindle setpoint is written only when it moved by more than
``spindle_deadband_rpm`` from the one written before.

A head takes part when the caller says so (a head whose service is in its own safe state for a
head-local reason still does, with its held correction) and its spindle turns; with no head
taking part the feed goes to ``feed_min``.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from config.heads import HEAD_NAME
from controller.laws.limits import check_time_forward, clamp, rate_limit
from core.checks import check_finite, check_int, check_positive, check_range


class FeedBound(enum.Enum):
    """What set the feed of a step (before the rate limit)."""

    HEADS = "heads"
    """The slowest head's ``V_h``, inside the feed limits."""
    FEED_MAX = "feed_max"
    """Every head allows more than the machine's largest feed."""
    FEED_MIN = "feed_min"
    """The slowest head asks for less than the machine's smallest feed (it cuts coarser)."""
    NO_HEAD = "no_head"
    """No head takes part: the smallest feed."""


def _check_name(name: Any) -> str:
    if not isinstance(name, str) or HEAD_NAME.fullmatch(name) is None:
        raise ValueError(f"name must match [a-z][a-z0-9_]*, got {name!r}")
    return name


@dataclass(frozen=True)
class HeadFeed:
    """One head as the feed law sees it in one step (validated on construction).

    Attributes
    ----------
    name : str
        The head's name (``[a-z][a-z0-9_]*``).
    knives : int
        Knives on its cutterhead, ``Z``.
    target_pitch_mm : float
        The pitch it holds, ``p*``: its target under its depth ceiling (``FeedLoop``'s
        ``pitch_setpoint_mm``), mm.
    rpm_min, rpm_max : float
        Its spindle's speed range, rev/min; equal for a fixed-speed head.
    spindle_rpm : float
        Its measured spindle speed, rev/min (0: stopped; the head then takes no part).
    correction : float
        Its learnt correction factor (``FeedLoop.correction``), > 0.
    takes_part : bool
        Whether it takes part in setting the feed (the caller's word; see the module).
    """

    name: str
    knives: int
    target_pitch_mm: float
    rpm_min: float
    rpm_max: float
    spindle_rpm: float
    correction: float = 1.0
    takes_part: bool = True

    def __post_init__(self) -> None:
        name = _check_name(self.name)
        check_int(f"{name}.knives", self.knives, lo=1)
        check_positive(f"{name}.target_pitch_mm", self.target_pitch_mm)
        check_positive(f"{name}.rpm_min", self.rpm_min)
        check_positive(f"{name}.rpm_max", self.rpm_max)
        if self.rpm_max < self.rpm_min:
            raise ValueError(
                f"{name}.rpm_max must be >= {name}.rpm_min, got {self.rpm_max!r} < "
                f"{self.rpm_min!r}"
            )
        check_positive(f"{name}.spindle_rpm", self.spindle_rpm, allow_zero=True)
        check_range(f"{name}.correction", self.correction, 1e-3, 1e3)
        if not isinstance(self.takes_part, bool):
            raise ValueError(f"{name}.takes_part must be a bool, got {self.takes_part!r}")

    @property
    def variable(self) -> bool:
        """Whether the law sets its spindle speed (``rpm_max > rpm_min``)."""
        return self.rpm_max > self.rpm_min

    @property
    def participates(self) -> bool:
        """Whether it sets the feed this step: it takes part and its spindle turns."""
        return self.takes_part and self.spindle_rpm > 0.0

    @property
    def feed_limit_mm_s(self) -> float:
        """``V_h``: the fastest feed at which it meets its target, mm/s."""
        rpm = self.rpm_max if self.variable else self.spindle_rpm
        return self.correction * self.target_pitch_mm * rpm / 60.0 * self.knives

    def spindle_for(self, feed_mm_s: float) -> float:
        """The speed at which it cuts its target at ``feed_mm_s``, within its range, rev/min."""
        rpm = 60.0 * feed_mm_s / (self.correction * self.target_pitch_mm * self.knives)
        return clamp(rpm, self.rpm_min, self.rpm_max)


@dataclass(frozen=True)
class MoulderFeedCommand:
    """What one step of :class:`MoulderFeedLaw` commands.

    Attributes
    ----------
    feed_mm_s : float
        The feed setpoint (clamped, rate-limited), mm/s.
    spindle_setpoints_rpm : dict[str, float]
        The variable heads' spindle setpoints to write now (those that moved by more than the
        deadband since the last written), rev/min.
    limiting : tuple[str, ...]
        The heads that set the feed (``V_h`` within ``limiting_rel_tol`` of the minimum), in the
        heads' order; empty when the feed limits or no head set it.
    desired_mm_s : float
        The feed before the rate limit, ``clamp(min V_h, feed_min, feed_max)``, mm/s.
    bound : FeedBound
        What set ``desired_mm_s``.
    head_feeds_mm_s : dict[str, float]
        ``V_h`` of every head that took part, mm/s.
    """

    feed_mm_s: float
    spindle_setpoints_rpm: dict[str, float]
    limiting: tuple[str, ...]
    desired_mm_s: float
    bound: FeedBound
    head_feeds_mm_s: dict[str, float]


@dataclass(frozen=True)
class MoulderFeedConfig:
    """Parameters of the moulder's feed law (validated on construction; errors name the field).

    Attributes
    ----------
    rate_max_mm_s2 : float
        Largest change of the feed setpoint per second, mm/s^2.
    spindle_deadband_rpm : float
        A variable head's setpoint is written when it moved by more than this, rev/min.
    limiting_rel_tol : float
        Heads whose ``V_h`` is within this fraction of the minimum are named limiting.
    initial_feed_mm_s : float or None
        The feed in force before the first update (``None``: the smallest feed then).
    """

    rate_max_mm_s2: float = 500.0
    spindle_deadband_rpm: float = 5.0
    limiting_rel_tol: float = 1e-3
    initial_feed_mm_s: float | None = None

    def __post_init__(self) -> None:
        check_positive("rate_max_mm_s2", self.rate_max_mm_s2)
        check_positive("spindle_deadband_rpm", self.spindle_deadband_rpm, allow_zero=True)
        check_range("limiting_rel_tol", self.limiting_rel_tol, 0.0, 0.5)
        if self.initial_feed_mm_s is not None:
            check_positive("initial_feed_mm_s", self.initial_feed_mm_s)


def _check_limits(feed_min_mm_s: float, feed_max_mm_s: float) -> tuple[float, float]:
    lo = check_positive("feed_min_mm_s", feed_min_mm_s)
    hi = check_positive("feed_max_mm_s", feed_max_mm_s)
    if hi <= lo:
        raise ValueError(f"feed_max_mm_s must be > feed_min_mm_s, got {hi!r} <= {lo!r}")
    return lo, hi


def _check_heads(heads: Sequence[HeadFeed]) -> tuple[HeadFeed, ...]:
    if isinstance(heads, (str, bytes)) or not isinstance(heads, Sequence):
        raise ValueError(f"heads must be a sequence of HeadFeed, got {type(heads).__name__}")
    if not heads:
        raise ValueError("heads must not be empty")
    seen: set[str] = set()
    for i, h in enumerate(heads):
        if not isinstance(h, HeadFeed):
            raise ValueError(f"heads[{i}] must be a HeadFeed, got {type(h).__name__}")
        if h.name in seen:
            raise ValueError(f"heads[{i}].name repeats {h.name!r}")
        seen.add(h.name)
    return tuple(heads)


class MoulderFeedLaw:
    """The one feed of a moulder and its variable heads' spindle speeds (see the module).

    Parameters
    ----------
    cfg : MoulderFeedConfig
        Rate limit, deadband, initial feed.
    """

    def __init__(self, cfg: MoulderFeedConfig) -> None:
        if not isinstance(cfg, MoulderFeedConfig):
            raise ValueError(f"cfg must be a MoulderFeedConfig, got {type(cfg).__name__}")
        self.cfg = cfg
        self.reset()

    def reset(self, feed_mm_s: float | None = None, now_s: float | None = None) -> None:
        """Start again from the feed in force (e.g. the PLC's actual feed) at ``now_s``.

        Without ``now_s`` the first update keeps that feed (limited to its feed range); the
        spindle setpoints written are forgotten (the next update writes every variable head's).
        """
        feed = self.cfg.initial_feed_mm_s if feed_mm_s is None else feed_mm_s
        self._feed = None if feed is None else check_positive("feed_mm_s", feed)
        self._t = None if now_s is None else check_finite("now_s", now_s)
        self._written: dict[str, float] = {}

    @property
    def feed_mm_s(self) -> float | None:
        """The feed last commanded (or given to :meth:`reset`), mm/s; ``None`` before."""
        return self._feed

    def forget_setpoint(self, name: str) -> None:
        """The speed last commanded to head ``name`` did not reach its drive.

        The next :meth:`update` commands it again (its deadband counts from nothing), so a
        refused or lost write is retried instead of being taken as written.
        """
        self._written.pop(name, None)

    @property
    def spindle_setpoints_rpm(self) -> dict[str, float]:
        """The variable heads' spindle setpoints written so far (the last of each), rev/min."""
        return dict(self._written)

    def update(
        self,
        heads: Sequence[HeadFeed],
        *,
        now_s: float,
        feed_min_mm_s: float,
        feed_max_mm_s: float,
    ) -> MoulderFeedCommand:
        """One step: the feed and the variable heads' spindle setpoints.

        Parameters
        ----------
        heads : sequence of HeadFeed
            Every head (unique names; those that do not take part included), in config order.
        now_s : float
            Current time, seconds (never decreasing between calls).
        feed_min_mm_s, feed_max_mm_s : float
            The feed range the machine accepts now (the PLC's), mm/s, ``0 < min < max``.

        Returns
        -------
        MoulderFeedCommand
            The feed setpoint, the spindle setpoints to write, the limiting heads.
        """
        hs = _check_heads(heads)
        t = check_time_forward(now_s, self._t)
        lo, hi = _check_limits(feed_min_mm_s, feed_max_mm_s)
        taking = [h for h in hs if h.participates]
        v_h = {h.name: h.feed_limit_mm_s for h in taking}
        limiting: tuple[str, ...] = ()
        if not taking:
            desired, bound = lo, FeedBound.NO_HEAD
        else:
            v_min = min(v_h.values())
            desired = clamp(v_min, lo, hi)
            if v_min > hi:
                bound = FeedBound.FEED_MAX
            else:
                bound = FeedBound.HEADS if v_min >= lo else FeedBound.FEED_MIN
                tol = v_min * (1.0 + self.cfg.limiting_rel_tol)
                limiting = tuple(n for n, v in v_h.items() if v <= tol)
        prev = lo if self._feed is None else self._feed
        dt = 0.0 if self._t is None else t - self._t
        feed = clamp(rate_limit(desired, prev, rate_max=self.cfg.rate_max_mm_s2, dt_s=dt), lo, hi)
        self._feed, self._t = feed, t
        writes: dict[str, float] = {}
        for h in taking:
            if not h.variable:
                continue
            rpm = h.spindle_for(feed)
            last = self._written.get(h.name)
            if last is None or abs(rpm - last) > self.cfg.spindle_deadband_rpm:
                writes[h.name] = self._written[h.name] = rpm
        return MoulderFeedCommand(
            feed_mm_s=feed,
            spindle_setpoints_rpm=writes,
            limiting=limiting,
            desired_mm_s=desired,
            bound=bound,
            head_feeds_mm_s=v_h,
        )


def pitch_mm(feed_mm_s: float, spindle_rpm: float, knives: int) -> float:
    """The nominal pitch ``V / (n Z)`` a head cuts, mm (``inf`` with the spindle stopped)."""
    n = spindle_rpm / 60.0 * knives
    return math.inf if n <= 0.0 else feed_mm_s / n
