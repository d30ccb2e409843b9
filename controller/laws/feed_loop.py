"""The feed loop: hold the target pitch under a depth ceiling while feeding as fast as it allows.

Pure and clock-injected: :meth:`FeedLoop.update` takes the measurement, the spindle speed and
the time, and returns the feed setpoint; nothing here sleeps or reads a clock.

Law (the design and its margins are in ``docs/control_design.md`` and `controller.laws.design`)::

    p*      = min(target_pitch, sqrt(8 R depth_max))          # depth = p^2 / (8 R)
    V_des   = clamp(exp(x) * p* * n * Z, feed_min, feed_max)   # feed-forward times correction
    V       = rate_limit(V_des, V_prev, rate_max, now - t_prev)
    x      += g * (log(p* / p_meas) + log(p_cmd(t_cut) / (p* exp(x))))   # on a trusted measurement

``x`` is the log of the correction factor; ``log(p*/p_meas)`` is the normalised pitch error,
the same loop gain at every feed because the pitch scales with ``V / n``. The second term uses
the pitch that was *commanded* when the measured board was cut (``p_cmd = V / (n Z)`` from the
loop's own setpoint history, the cut time found by integrating the setpoints back over the
cutter-to-camera distance): it makes the update equal to ``g * (log(1 / k_hat) - x)`` with
``k_hat = p_meas / p_cmd(t_cut)`` the measured model error (belt or encoder scale, spindle
slip). So the correction learns the model error, not the delay, and the clamp and the rate limit
cannot wind it up (back-calculation with the tracking gain equal to ``g``). In steady state
without clamping the term vanishes and the law is plain integral action on the pitch error.

A measurement is trusted only when the board it shows was cut after the last setpoint change had
taken effect: the commanded pitch must have been steady (within ``steady_tol``) from
``settle_s`` before the first to the last cut instant of the measured window. Otherwise (and
for ``None``) the correction is held and only the feed-forward follows the spindle speed.

The history holds only setpoints that reached the machine: the caller takes back one it did not
write, or that the PLC refused, with :meth:`FeedLoop.reject`, or one it held back because the
change was too small to write with :meth:`FeedLoop.defer` (the rate limit then counts from the
setpoint in force, so steps smaller than a write deadband add up instead of freezing the feed).

What the drive really did rules the learning when the caller reports it
(:meth:`FeedLoop.observe_drive`: the PLC's actual feed and the spindle speed, every cycle): the
measured board's cut interval is found by integrating the actual feed, and the model error is
``p_meas`` over the pitch the drive actually cut with (``V_act / (n Z)``, travel over passes in
the window). A drive that lags its setpoint (a slow ramp of the PLC, a low bandwidth) then
teaches the loop nothing false: no wind-up while the drive is rate-limited. Without drive
readings the setpoint history stands in for them (the drive follows within ``settle_s``).

In a moulder another law sets the one feed (`controller.laws.moulder_feed`): each head's loop
still learns its correction in :meth:`FeedLoop.update` (its proposal is not written), and
:meth:`FeedLoop.follow_setpoint` records the setpoint really written in its place, so the history,
the trust rule and the cut interval see the feed the board had.

The per-measurement gain is scheduled on the loop delay so that the crossover sits at a fixed
fraction of the delay at every feed: ``g = ki * Ts / (T_delay + Ts)``.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from controller.laws.limits import check_time_forward, clamp, rate_limit
from core.checks import check_finite, check_int, check_positive, check_range
from core.errors import ConfigError

#: Values of :attr:`FeedLoop.status` after an update.
STATUSES = ("accepted", "no_measurement", "no_history", "transient", "implausible", "idle")


class DriveHistory:
    """The drive's actual feed and knife passing rate over time (piecewise constant, pure).

    Parameters
    ----------
    horizon_s : float
        How far back readings are kept, s.
    """

    def __init__(self, horizon_s: float) -> None:
        self.horizon_s = check_positive("horizon_s", horizon_s)
        self._t: list[float] = []
        self._v: list[float] = []  # actual feed, mm/s
        self._r: list[float] = []  # knife passes per second, n Z
        self._d: list[float] = []  # board travel at each reading, mm
        self._n: list[float] = []  # knife passes at each reading

    def __len__(self) -> int:
        return len(self._t)

    def record(self, t: float, feed_mm_s: float, passes_per_s: float) -> None:
        """A reading from ``t`` on; older than the last one: ignored, same instant: replaces."""
        v, r = float(feed_mm_s), float(passes_per_s)
        if not (math.isfinite(t) and math.isfinite(v) and v >= 0.0 and math.isfinite(r)
                and r >= 0.0):
            return
        if self._t and t <= self._t[-1]:
            if t == self._t[-1]:
                self._v[-1], self._r[-1] = v, r
            return
        if self._t:
            dt = t - self._t[-1]
            d, n = self._d[-1] + self._v[-1] * dt, self._n[-1] + self._r[-1] * dt
        else:
            d = n = 0.0
        for lst, x in ((self._t, t), (self._v, v), (self._r, r), (self._d, d), (self._n, n)):
            lst.append(x)
        k = bisect.bisect_right(self._t, t - self.horizon_s) - 1
        if k > 0:
            del self._t[:k], self._v[:k], self._r[:k], self._d[:k], self._n[:k]

    def distance_at(self, t: float) -> float | None:
        """Board travel at ``t`` (history coordinates), mm; ``None`` before the first reading."""
        if not self._t or t < self._t[0]:
            return None
        i = bisect.bisect_right(self._t, t) - 1
        return self._d[i] + self._v[i] * (t - self._t[i])

    def time_at(self, d: float) -> float | None:
        """When the board had travelled ``d``; ``None`` before the history or while it stood."""
        if not self._d or d < self._d[0]:
            return None
        i = bisect.bisect_right(self._d, d) - 1
        while i > 0 and self._v[i] <= 0.0 and d == self._d[i]:
            i -= 1
        if self._v[i] <= 0.0:
            return None if d > self._d[i] else self._t[i]
        return self._t[i] + (d - self._d[i]) / self._v[i]

    def _passes_at(self, t: float) -> float:
        i = bisect.bisect_right(self._t, t) - 1
        return self._n[i] + self._r[i] * (t - self._t[i])

    def pitch_stats(self, t0: float, t1: float) -> tuple[float, float, float] | None:
        """Min, max and mean (travel over passes) of the cut pitch ``V / (n Z)`` in ``[t0, t1]``.

        ``None`` before the history, or when the spindle or the board stood meanwhile.
        """
        if not self._t or t0 < self._t[0] or t1 < t0:
            return None
        i0 = bisect.bisect_right(self._t, t0) - 1
        i1 = bisect.bisect_right(self._t, t1) - 1
        vals = []
        for i in range(i0, i1 + 1):
            if not (self._v[i] > 0.0 and self._r[i] > 0.0):
                return None
            vals.append(self._v[i] / self._r[i])
        passes = self._passes_at(t1) - self._passes_at(t0)
        if passes <= 0.0:
            return vals[0], vals[0], vals[0]
        d0, d1 = self.distance_at(t0), self.distance_at(t1)
        assert d0 is not None and d1 is not None
        return min(vals), max(vals), (d1 - d0) / passes


def integral_gain(ki: float, sample_time_s: float, delay_s: float) -> float:
    """Per-measurement integral gain scheduled on the loop delay.

    Parameters
    ----------
    ki : float
        Integral gain per loop delay (dimensionless, the design parameter).
    sample_time_s : float
        Nominal interval between measurements, seconds.
    delay_s : float
        Loop delay: age of the measured board when the new setpoint takes effect, seconds.

    Returns
    -------
    float
        ``ki * Ts / (delay_s + Ts)``: the crossover sits near ``ki / delay`` rad/s at every feed.
    """
    return ki * sample_time_s / (max(delay_s, 0.0) + sample_time_s)


def pitch_ceiling_mm(depth_max_um: float, radius_mm: float) -> float:
    """Largest pitch whose cusp depth ``p^2 / (8 R)`` stays within ``depth_max_um``."""
    return math.sqrt(8.0 * radius_mm * depth_max_um * 1e-3)


def config_from_mapping(
    cls: type, mapping: Mapping[str, Any] | None, prefix: str, **overrides: Any
) -> Any:
    """Build the frozen config ``cls`` from a TOML table plus keyword overrides.

    Keys are the dataclass's field names; missing keys take the defaults, unknown keys and
    invalid values raise :class:`core.errors.ConfigError` naming ``prefix.key``.
    """
    names = {f.name for f in fields(cls)}
    data = dict(mapping or {})
    for key in data:
        if key not in names:
            raise ConfigError(f"unknown key {prefix}.{key}")
    data.update(overrides)
    try:
        return cls(**data)
    except ValueError as exc:
        raise ConfigError(f"{prefix}.{exc}") from None


@dataclass(frozen=True)
class FeedLoopConfig:
    """Parameters of the feed loop (validated on construction; errors name the field).

    Attributes
    ----------
    sample_time_s : float
        Nominal interval between measurements (image pairs), seconds.
    target_pitch_mm : float
        Pitch of the quality class, mm.
    depth_max_um : float
        Ceiling on the cusp depth ``p^2 / (8 R)``, um; lowers the target pitch if needed.
    knives : int
        Knives on the cutterhead, ``Z``.
    radius_mm : float
        Cutting radius ``R``, mm.
    feed_min_mm_s, feed_max_mm_s : float
        Limits of the feed setpoint the machine accepts, mm/s.
    rate_max_mm_s2 : float
        Largest change of the setpoint per second, mm/s^2.
    ki : float
        Integral gain per loop delay (see :func:`integral_gain`); 0.5 gives about 13.7 dB and
        74 deg at every feed (``controller.laws.design``).
    cutter_to_camera_mm : float
        Distance ``L`` from the cutter to the image centre along the board, mm.
    window_mm : float
        Length of board one measurement averages over (the image's field of view), mm.
    settle_s : float
        Time the feed drive needs after a setpoint change before the cut board is trusted, s.
    steady_tol : float
        Largest relative spread of the commanded pitch over a trusted measurement's cut window.
    correction_min, correction_max : float
        Bounds of the learnt correction factor ``exp(x)``; a measured model error outside
        ``[1/correction_max, 1/correction_min]`` is rejected as implausible.
    initial_feed_mm_s : float or None
        Setpoint before the first update; ``None`` = ``feed_min_mm_s``.
    """

    sample_time_s: float = 0.1
    target_pitch_mm: float = 1.5
    depth_max_um: float = 20.0
    knives: int = 4
    radius_mm: float = 60.0
    feed_min_mm_s: float = 50.0
    feed_max_mm_s: float = 1000.0
    rate_max_mm_s2: float = 500.0
    ki: float = 0.5
    cutter_to_camera_mm: float = 300.0
    window_mm: float = 40.0
    settle_s: float = 0.2
    steady_tol: float = 0.01
    correction_min: float = 0.67
    correction_max: float = 1.5
    initial_feed_mm_s: float | None = None

    def __post_init__(self) -> None:
        for name in (
            "sample_time_s",
            "target_pitch_mm",
            "depth_max_um",
            "radius_mm",
            "feed_min_mm_s",
            "feed_max_mm_s",
            "rate_max_mm_s2",
            "cutter_to_camera_mm",
            "window_mm",
            "steady_tol",
        ):
            check_positive(name, getattr(self, name))
        check_int("knives", self.knives, lo=1)
        check_range("ki", self.ki, 1e-6, 1.5)
        check_positive("settle_s", self.settle_s, allow_zero=True)
        if self.feed_max_mm_s <= self.feed_min_mm_s:
            raise ValueError(
                f"feed_max_mm_s must be > feed_min_mm_s, got {self.feed_max_mm_s!r} "
                f"<= {self.feed_min_mm_s!r}"
            )
        check_range("correction_min", self.correction_min, 1e-3, 1.0)
        check_range("correction_max", self.correction_max, 1.0, 1e3)
        if self.initial_feed_mm_s is not None:
            check_range(
                "initial_feed_mm_s", self.initial_feed_mm_s, self.feed_min_mm_s, self.feed_max_mm_s
            )

    @classmethod
    def from_mapping(
        cls, mapping: Mapping[str, Any] | None, *, prefix: str = "feed_loop", **overrides: Any
    ) -> FeedLoopConfig:
        """Build from a ``[feed_loop]`` TOML table; ``overrides`` win (e.g. limits from the PLC)."""
        return config_from_mapping(cls, mapping, prefix, **overrides)

    @property
    def pitch_setpoint_mm(self) -> float:
        """The pitch the loop holds: the target, lowered to the depth ceiling if needed, mm."""
        return min(self.target_pitch_mm, pitch_ceiling_mm(self.depth_max_um, self.radius_mm))

    @property
    def history_s(self) -> float:
        """How far back the setpoint history must reach (slowest feed, whole window), s."""
        span = (self.cutter_to_camera_mm + self.window_mm) / self.feed_min_mm_s
        return span + self.settle_s + 10.0 * self.sample_time_s


class FeedLoop:
    """Feed-forward plus delay-aware integral feedback on the measured pitch.

    Parameters
    ----------
    cfg : FeedLoopConfig
        Limits, gains and geometry.

    Notes
    -----
    The setpoint stays inside ``[feed_min_mm_s, feed_max_mm_s]`` and never changes faster than
    ``rate_max_mm_s2`` between two updates. ``status`` tells what the last update did with its
    measurement (one of :data:`STATUSES`).
    """

    def __init__(self, cfg: FeedLoopConfig) -> None:
        if not isinstance(cfg, FeedLoopConfig):
            raise ValueError(f"cfg must be a FeedLoopConfig, got {type(cfg).__name__}")
        self.cfg = cfg
        self._p_star = cfg.pitch_setpoint_mm
        self._x_lo = math.log(cfg.correction_min)
        self._x_hi = math.log(cfg.correction_max)
        self.drive = DriveHistory(cfg.history_s)
        """The drive's actual feed and passing rate (:meth:`observe_drive`); kept by
        :meth:`reset` (what the drive did stays true)."""
        self.reset()

    # -- state ------------------------------------------------------------------------------
    def reset(
        self,
        *,
        feed_mm_s: float | None = None,
        now_s: float | None = None,
        correction: float = 1.0,
    ) -> None:
        """Forget the history; start from ``feed_mm_s`` (default: the config's initial feed).

        Parameters
        ----------
        feed_mm_s : float, optional
            The setpoint in force now (e.g. the PLC's actual feed), mm/s, within the limits.
        now_s : float, optional
            Time of that setpoint; the first update's rate limit counts from it. Without it the
            first update keeps ``feed_mm_s``.
        correction : float
            Initial correction factor ``exp(x)`` (e.g. the value learnt on the previous board).
        """
        c = self.cfg
        feed = c.initial_feed_mm_s if feed_mm_s is None else feed_mm_s
        feed = c.feed_min_mm_s if feed is None else feed
        self._feed = check_range("feed_mm_s", feed, c.feed_min_mm_s, c.feed_max_mm_s)
        self._t_last = None if now_s is None else check_finite("now_s", now_s)
        self._t_rate = self._t_last  # the rate limit counts from the setpoint in force then
        corr = check_range("correction", correction, c.correction_min, c.correction_max)
        self._x = math.log(corr)
        self._hist_t: list[float] = []  # update times; setpoint i holds on [t_i, t_{i+1})
        self._hist_v: list[float] = []  # feed setpoints, mm/s
        self._hist_p: list[float] = []  # commanded pitch V / (n Z), mm (nan: spindle stopped)
        self._hist_d: list[float] = []  # board travelled at t_i since the first entry, mm
        self._undo: tuple[float, float | None, tuple[float, float, float, float] | None] | None
        self._undo = None
        self.status = "idle"
        self.last_gain = 0.0
        self.last_model_error = math.nan

    @property
    def feed_mm_s(self) -> float:
        """The last setpoint returned, mm/s."""
        return self._feed

    @property
    def correction(self) -> float:
        """The learnt correction factor ``exp(x)`` applied to the feed-forward."""
        return math.exp(self._x)

    @property
    def pitch_setpoint_mm(self) -> float:
        """The pitch the loop holds (target under the depth ceiling), mm."""
        return self._p_star

    # -- the law ----------------------------------------------------------------------------
    def update(
        self,
        *,
        measured_pitch_mm: float | None,
        spindle_rpm: float,
        now_s: float,
        measured_at_s: float | None = None,
    ) -> float:
        """One control step; returns the feed setpoint (mm/s).

        Parameters
        ----------
        measured_pitch_mm : float or None
            Mean mark width of the last valid measurement, mm; ``None`` when there is none (the
            correction is held, the feed-forward still follows the spindle).
        spindle_rpm : float
            Measured spindle speed, rev/min (>= 0).
        now_s : float
            Current time, seconds (never decreasing between calls).
        measured_at_s : float, optional
            When the measured image pair was taken (trigger A), seconds, ``<= now_s``;
            default ``now_s``.

        Returns
        -------
        float
            Feed setpoint within ``[feed_min_mm_s, feed_max_mm_s]``, mm/s.
        """
        c = self.cfg
        t = check_time_forward(now_s, self._t_last)
        rpm = check_positive("spindle_rpm", spindle_rpm, allow_zero=True)
        if measured_pitch_mm is None:
            self.status = "no_measurement"
            self.last_gain = 0.0
        else:
            p_meas = check_positive("measured_pitch_mm", measured_pitch_mm)
            t_meas = t if measured_at_s is None else check_finite("measured_at_s", measured_at_s)
            if t_meas > t:
                raise ValueError(f"measured_at_s must be <= now_s, got {t_meas!r} > {t!r}")
            self._learn(p_meas, t_meas, t)

        n_rev_s = rpm / 60.0
        desired = clamp(
            math.exp(self._x) * self._p_star * n_rev_s * c.knives, c.feed_min_mm_s, c.feed_max_mm_s
        )
        dt = 0.0 if self._t_rate is None else max(t - self._t_rate, 0.0)
        feed = rate_limit(desired, self._feed, rate_max=c.rate_max_mm_s2, dt_s=dt)
        prev_feed, prev_t_rate = self._feed, self._t_rate
        self._feed = clamp(feed, c.feed_min_mm_s, c.feed_max_mm_s)
        self._t_last = self._t_rate = t
        p_cmd = self._feed / (n_rev_s * c.knives) if n_rev_s > 0 else math.nan
        replaced = self._record(t, self._feed, p_cmd)
        self._undo = (prev_feed, prev_t_rate, replaced)
        return self._feed

    def observe_drive(self, *, now_s: float, feed_actual_mm_s: float, spindle_rpm: float) -> None:
        """What the drive does at ``now_s``: the PLC's actual feed and the spindle speed.

        From then on the learning judges each measurement against the pitch the drive really
        cut with (see the module's docstring). Readings that go back in time are ignored.
        """
        t = check_finite("now_s", now_s)
        rate = check_positive("spindle_rpm", spindle_rpm, allow_zero=True) / 60.0 * self.cfg.knives
        self.drive.record(t, check_finite("feed_actual_mm_s", feed_actual_mm_s), rate)

    def follow_setpoint(self, *, now_s: float, feed_mm_s: float, spindle_rpm: float) -> float:
        """The feed in force from ``now_s`` on was set by another law (a moulder's one feed).

        In a moulder one feed serves every head (`controller.laws.moulder_feed`): each head's
        loop still learns its own correction in :meth:`update` (the coordinator reads
        :attr:`correction`; the update's own proposal is not written), and this records the
        setpoint really written in place of that proposal. The setpoint history, its trust rule
        and :meth:`cut_interval_s` then see the feed the board really had (also without
        :meth:`observe_drive`), :attr:`feed_mm_s` is the setpoint in force and the next update's
        rate limit counts from it. A proposal of an update at the same instant is replaced;
        :meth:`reject` takes the followed setpoint back to the one in force before that update.

        Parameters
        ----------
        now_s : float
            When the setpoint was written, seconds (never before the last update).
        feed_mm_s : float
            The feed setpoint written, mm/s (> 0; not limited to this loop's own feed range).
        spindle_rpm : float
            The head's spindle speed with it, rev/min (a variable head: the setpoint in force);
            0 = stopped (no commanded pitch: the trust rule holds the correction meanwhile).

        Returns
        -------
        float
            ``feed_mm_s``.
        """
        t = check_time_forward(now_s, self._t_last)
        feed = check_positive("feed_mm_s", feed_mm_s)
        n_rev_s = check_positive("spindle_rpm", spindle_rpm, allow_zero=True) / 60.0
        p_cmd = feed / (n_rev_s * self.cfg.knives) if n_rev_s > 0 else math.nan
        same_update = self._undo is not None and self._t_last == t
        prev_feed, prev_t_rate = self._feed, self._t_rate
        replaced = self._record(t, feed, p_cmd)
        if not same_update:  # else keep the update's undo: back to before that update
            self._undo = (prev_feed, prev_t_rate, replaced)
        self._feed = feed
        self._t_last = self._t_rate = t
        return feed

    def defer(self) -> float:
        """The last update's setpoint was held back as too small a change to write.

        Taken back as :meth:`reject` does, except that the rate limit of the next update still
        counts from the setpoint in force: the steps held back add up until one is worth
        writing (a slow ramp of a few tenths of mm/s per cycle still moves).

        Returns
        -------
        float
            The setpoint in force, mm/s.
        """
        undo = self._undo
        feed = self.reject()
        if undo is not None:
            self._t_rate = undo[1]
        return feed

    def reject(self) -> float:
        """The setpoint the last :meth:`update` returned never reached the machine.

        The caller did not write it (deadband) or the PLC refused it or the write failed: it
        leaves the setpoint history (the board moved at the feed really in force, and the loop
        learns its model error against that), and :attr:`feed_mm_s` goes back to the setpoint
        in force before. What the update learnt from its measurement stays. The next update's
        rate limit counts from the setpoint in force. Rejecting again, or before any update,
        changes nothing.

        Returns
        -------
        float
            The setpoint in force, mm/s.
        """
        if self._undo is None:
            return self._feed
        prev_feed, _, replaced = self._undo
        self._undo = None
        if self._hist_t:
            self._hist_t.pop()
            self._hist_v.pop()
            self._hist_p.pop()
            self._hist_d.pop()
        if replaced is not None:
            t, v, p, d = replaced
            self._hist_t.append(t)
            self._hist_v.append(v)
            self._hist_p.append(p)
            self._hist_d.append(d)
        self._feed = prev_feed
        return self._feed

    def cut_interval_s(self, measured_at_s: float) -> tuple[float, float] | None:
        """When the board seen by a measurement taken at ``measured_at_s`` was cut.

        The board moved ``cutter_to_camera_mm -+ window_mm / 2`` between the cut and the
        measurement; the distance is integrated over the drive's actual feed when it was
        reported (:meth:`observe_drive`) back that far, else over the setpoint history (the
        drive follows its setpoint within ``settle_s``).

        Parameters
        ----------
        measured_at_s : float
            Time of the measurement, seconds.

        Returns
        -------
        (float, float) or None
            Earliest and latest cut time of the measured window, seconds; ``None`` when the
            history does not reach back far enough.
        """
        t_m = check_finite("measured_at_s", measured_at_s)
        by_drive = self._drive_interval(t_m)
        if by_drive is not None:
            return by_drive
        d_m = self._distance_at(t_m)
        if d_m is None:
            return None
        half = 0.5 * self.cfg.window_mm
        t_lo = self._time_at(d_m - self.cfg.cutter_to_camera_mm - half)
        t_hi = self._time_at(d_m - self.cfg.cutter_to_camera_mm + half)
        if t_lo is None or t_hi is None:
            return None
        return t_lo, t_hi

    # -- internals --------------------------------------------------------------------------
    def _drive_interval(self, t_m: float) -> tuple[float, float] | None:
        """The cut interval from the drive's actual feed (``None``: not reported back so far)."""
        drive = self.drive
        d_m = drive.distance_at(t_m)
        if d_m is None:
            return None
        half = 0.5 * self.cfg.window_mm
        t_lo = drive.time_at(d_m - self.cfg.cutter_to_camera_mm - half)
        t_hi = drive.time_at(d_m - self.cfg.cutter_to_camera_mm + half)
        if t_lo is None or t_hi is None:
            return None
        return t_lo, t_hi

    def _cut_pitch(self, t_meas: float) -> tuple[float, float, float, float, float] | str:
        """``(t_lo, t_hi, min, max, mean)`` of the pitch the measured board was cut with.

        From the drive's readings when they reach back (no settling allowance: they show the
        drive's lag), else from the setpoint history (``settle_s`` before the window too). A
        status string when there is none.
        """
        c = self.cfg
        if len(self.drive) and self.drive.distance_at(t_meas) is not None:
            interval = self._drive_interval(t_meas)
            stats = None if interval is None else self.drive.pitch_stats(*interval)
            if interval is None or stats is None:
                return "no_history"
            return (*interval, *stats)
        interval = self.cut_interval_s(t_meas)
        if interval is None or interval[0] - c.settle_s < self._hist_t[0]:
            return "no_history"
        t_lo, t_hi = interval
        stats = self._pitch_stats(t_lo - c.settle_s, t_hi)
        if stats is None:
            return "transient"
        mean = self._pitch_stats(t_lo, t_hi)
        assert mean is not None
        return t_lo, t_hi, stats[0], stats[1], mean[2]

    def _learn(self, p_meas: float, t_meas: float, now: float) -> None:
        c = self.cfg
        self.last_gain = 0.0
        cut = self._cut_pitch(t_meas)
        if isinstance(cut, str):
            self.status = cut
            return
        t_lo, t_hi, p_min, p_max, p_mean = cut
        if p_max - p_min > c.steady_tol * p_mean:
            self.status = "transient"
            return
        k_hat = p_meas / p_mean
        if not 1.0 / c.correction_max <= k_hat <= 1.0 / c.correction_min:
            self.status = "implausible"
            return
        delay_s = now - 0.5 * (t_lo + t_hi) + c.sample_time_s
        g = integral_gain(c.ki, c.sample_time_s, delay_s)
        self._x = min(max(self._x + g * (-math.log(k_hat) - self._x), self._x_lo), self._x_hi)
        self.status = "accepted"
        self.last_gain = g
        self.last_model_error = k_hat

    def _record(
        self, t: float, feed: float, p_cmd: float
    ) -> tuple[float, float, float, float] | None:
        """Append a setpoint to the history; return the entry it replaced (same instant)."""
        replaced = None
        if self._hist_t:
            d = self._hist_d[-1] + self._hist_v[-1] * (t - self._hist_t[-1])
            if t == self._hist_t[-1]:  # same instant: the newer setpoint replaces the older
                replaced = (
                    self._hist_t.pop(),
                    self._hist_v.pop(),
                    self._hist_p.pop(),
                    self._hist_d.pop(),
                )
                d = replaced[3]
        else:
            d = 0.0
        self._hist_t.append(t)
        self._hist_v.append(feed)
        self._hist_p.append(p_cmd)
        self._hist_d.append(d)
        # drop entries that ended before the horizon (keep the one in force at the horizon)
        horizon = t - self.cfg.history_s
        k = bisect.bisect_right(self._hist_t, horizon) - 1
        if k > 0:
            del self._hist_t[:k], self._hist_v[:k], self._hist_p[:k], self._hist_d[:k]
        return replaced

    def _distance_at(self, t: float) -> float | None:
        """Board travelled at time ``t`` (history coordinates), mm; None before the history."""
        if not self._hist_t or t < self._hist_t[0]:
            return None
        i = bisect.bisect_right(self._hist_t, t) - 1
        return self._hist_d[i] + self._hist_v[i] * (t - self._hist_t[i])

    def _time_at(self, d: float) -> float | None:
        """Time at which the board had travelled ``d`` (inverse of `_distance_at`)."""
        if not self._hist_d or d < self._hist_d[0]:
            return None
        i = bisect.bisect_right(self._hist_d, d) - 1
        return self._hist_t[i] + (d - self._hist_d[i]) / self._hist_v[i]

    def _pitch_stats(self, t0: float, t1: float) -> tuple[float, float, float] | None:
        """Min, max and time-weighted mean of the commanded pitch over ``[t0, t1]``."""
        i0 = bisect.bisect_right(self._hist_t, t0) - 1
        i1 = bisect.bisect_right(self._hist_t, t1) - 1
        if i0 < 0:
            return None
        vals = self._hist_p[i0 : i1 + 1]
        if any(map(math.isnan, vals)):
            return None
        if t1 <= t0 or i0 == i1:
            return vals[0], vals[0], vals[0]
        # entry i holds on [t_i, t_{i+1}): clipped to [t0, t1] only at both ends (t_{i0} <= t0
        # < t_{i0+1}, t_{i1} <= t1), so the pieces are the gaps between the times in between
        ts = self._hist_t
        total = vals[0] * max(ts[i0 + 1] - t0, 0.0)
        for i in range(i0 + 1, i1):
            total += vals[i - i0] * (ts[i + 1] - ts[i])
        total += vals[-1] * max(t1 - ts[i1], 0.0)
        return min(vals), max(vals), total / (t1 - t0)
