"""Feed drive (lead-screw table with a velocity loop), the feed encoder and the stream of boards.

Feed position ``s`` (mm) is the distance the table has fed since time 0. The velocity loop is a
first-order loop of bandwidth ``bandwidth_hz`` whose acceleration is limited to
``accel_max_mm_s2``; the acceleration is held constant over each PLC cycle, so the position is
exactly quadratic in time within a cycle.

Boards: board ``n`` (id ``n + 1``) has its leading end at the cutter axis when
``s = first_at_mm + n * (length_mm + gap_mm)``, and at a station ``D`` mm downstream of the
cutter (the camera: ``D = L``) when ``s`` is ``D`` larger. A board's own coordinate ``x_mm``
(:mod:`plant_sim.model.surface`) runs from its trailing end (0) to its leading end (``length_mm``),
increasing in the direction of feed; the PLC's ``board_position_mm`` is measured from the leading
end, ``length_mm - x_mm``.

A moulder's heads stand one after another along the feed: :class:`BoardView` is the one stream
of boards seen from a head ``offset_mm`` downstream of the first (its cutter is that head's
station 0), so a board reaches a later head later by the distance between them.
"""

from __future__ import annotations

import math

from core.checks import check_finite, check_int

__all__ = ["BoardStream", "BoardView", "Encoder", "FeedDrive"]


class FeedDrive:
    """The table's velocity loop.

    Parameters
    ----------
    cfg : config.sim.FeedConfig
        Limits, acceleration limit, bandwidth and initial setpoint.

    Attributes
    ----------
    setpoint_mm_s : float
        Current setpoint (the PLC register).
    s_mm, v_mm_s, a_mm_s2 : float
        Position and speed at the start of the current cycle, acceleration over it.
    enabled : bool
        Whether the drive follows the setpoint (otherwise it decelerates to standstill).
    """

    def __init__(self, cfg) -> None:
        self.cfg = cfg
        self.setpoint_mm_s = cfg.initial_mm_s
        self.s_mm = 0.0
        self.v_mm_s = cfg.initial_mm_s
        self.a_mm_s2 = 0.0
        self.t_c = 0.0
        self.enabled = True
        self._k = 2.0 * math.pi * cfg.bandwidth_hz
        self._amax = cfg.accel_max_mm_s2

    def set_setpoint(self, feed_mm_s: float) -> None:
        """New setpoint; ``ValueError`` outside ``[min_mm_s, max_mm_s]`` (never clamped)."""
        v = check_finite("feed_mm_s", feed_mm_s)
        lo, hi = self.cfg.min_mm_s, self.cfg.max_mm_s
        if not lo <= v <= hi:
            raise ValueError(f"feed_mm_s must be in [{lo}, {hi}], got {feed_mm_s!r}")
        self.setpoint_mm_s = v

    def start_cycle(self, t_s: float, dt_s: float) -> None:
        """Choose the acceleration for the cycle ``[t_s, t_s + dt_s)``."""
        self.t_c = t_s
        err = (self.setpoint_mm_s if self.enabled else 0.0) - self.v_mm_s
        if err == 0.0:  # at the goal (the steady state): what the lines below give
            self.a_mm_s2 = 0.0
            return
        amax = self._amax
        a = max(-amax, min(amax, self._k * err))
        if abs(a) * dt_s >= abs(err):  # reach the goal within the cycle, never overshoot
            a = err / dt_s
        self.a_mm_s2 = a

    def end_cycle(self, dt_s: float) -> None:
        """Advance position and speed over the whole cycle."""
        self.s_mm += self.v_mm_s * dt_s + 0.5 * self.a_mm_s2 * dt_s * dt_s
        self.v_mm_s += self.a_mm_s2 * dt_s
        if abs(self.v_mm_s) < 1e-9:
            self.v_mm_s = 0.0
        self.t_c += dt_s
        self.a_mm_s2 = 0.0  # until the next cycle's start_cycle

    def position_at(self, t_s: float) -> float:
        """Feed position at time ``t_s`` within the current cycle, mm."""
        tau = t_s - self.t_c
        return self.s_mm + self.v_mm_s * tau + 0.5 * self.a_mm_s2 * tau * tau

    def speed_at(self, t_s: float) -> float:
        """Feed speed at time ``t_s`` within the current cycle, mm/s."""
        return self.v_mm_s + self.a_mm_s2 * (t_s - self.t_c)


class Encoder:
    """The feed encoder's counter: counts, wrap, slip and signal loss.

    ``raw(s)`` is the unwrapped count the counter has accumulated (``floor(s * counts_per_mm)``
    plus any counts lost or gained by belt slip); ``wrap(raw)`` what the PLC reads:
    ``(raw + start) mod 2**bits``.

    Parameters
    ----------
    cfg : config.sim.EncoderConfig
        Resolution, counter width, start value.
    """

    def __init__(self, cfg) -> None:
        self.counts_per_mm = cfg.counts_per_mm
        self.bits = cfg.counter_bits
        self.modulus = 1 << cfg.counter_bits
        self.start = cfg.start_counts
        self.slip = 0
        self.frozen: int | None = None

    def raw(self, s_mm: float) -> int:
        """Unwrapped count at feed position ``s_mm``."""
        if self.frozen is not None:
            return self.frozen
        return math.floor(s_mm * self.counts_per_mm + 1e-9) + self.slip

    def wrap(self, raw: int) -> int:
        """Counter value the PLC reads for an unwrapped count."""
        return (raw + self.start) % self.modulus

    def read(self, s_mm: float) -> int:
        """Counter value at feed position ``s_mm``."""
        return self.wrap(self.raw(s_mm))

    def add_slip(self, counts: int) -> None:
        """The belt slipped: from now on the counter is off by ``counts`` more."""
        self.slip += check_int("counts", counts)

    def preset_before_wrap(self, s_mm: float, counts_before_wrap: int) -> None:
        """Move the counter's origin so that it wraps ``counts_before_wrap`` counts from now."""
        n = check_int("counts_before_wrap", counts_before_wrap, lo=1, hi=self.modulus - 1)
        self.start = (self.modulus - n - self.raw(s_mm)) % self.modulus

    def freeze(self, s_mm: float) -> None:
        """Signal loss: the counter stops."""
        if self.frozen is None:
            self.frozen = self.raw(s_mm)

    def unfreeze(self, s_mm: float) -> None:
        """Signal back: the counter counts on from where it stopped."""
        if self.frozen is not None:
            frozen = self.frozen
            self.frozen = None
            self.slip += frozen - self.raw(s_mm)


class BoardStream:
    """Where the boards are: which board is at a station and at which board coordinate.

    Parameters
    ----------
    cfg : config.sim.BoardConfig
        Board length, gap, position of the first board, number of boards.
    """

    def __init__(self, cfg) -> None:
        self.length_mm = cfg.length_mm
        self.period_mm = cfg.length_mm + cfg.gap_mm
        self.first_at_mm = cfg.first_at_mm
        self.count = cfg.count

    def at(self, s_mm: float, station_mm: float, *, margin_mm: float = 0.0) -> tuple[int, float]:
        """Board at a station ``station_mm`` downstream of the cutter, at feed position ``s_mm``.

        Returns
        -------
        board_id : int
            ``n + 1`` for board ``n``; 0 when no board lies there (within ``margin_mm`` of its
            ends).
        x_mm : float
            Board coordinate (from the trailing end) at the station; NaN without a board.
        """
        rel = s_mm - self.first_at_mm - station_mm + margin_mm
        n = math.floor(rel / self.period_mm)
        if n < 0 or (self.count and n >= self.count):
            return 0, math.nan
        from_lead = s_mm - self.first_at_mm - station_mm - n * self.period_mm
        if from_lead > self.length_mm + margin_mm:
            return 0, math.nan
        return n + 1, self.length_mm - from_lead

    def lead_at_station_s(self, board_id: int, station_mm: float) -> float:
        """Feed position at which board ``board_id``'s leading end reaches the station, mm."""
        return self.first_at_mm + (board_id - 1) * self.period_mm + station_mm


class BoardView(BoardStream):
    """The boards of a :class:`BoardStream` seen from a cutter ``offset_mm`` further downstream.

    Its stations are measured from that cutter: ``view.at(s, d)`` is ``base.at(s, offset_mm +
    d)``, and a board's leading end reaches the view's cutter when the feed has moved
    ``offset_mm`` further than when it reached the base's. Nothing is copied that could change:
    the stream is the base's.

    Parameters
    ----------
    base : BoardStream
        The stream (the first head's).
    offset_mm : float
        How far this cutter stands downstream of the base's, mm (>= 0).
    """

    def __init__(self, base: BoardStream, offset_mm: float) -> None:
        off = check_finite("offset_mm", offset_mm)
        if off < 0:
            raise ValueError(f"offset_mm must be >= 0, got {offset_mm!r}")
        self.base = base
        self.offset_mm = off
        self.length_mm = base.length_mm
        self.period_mm = base.period_mm
        self.first_at_mm = base.first_at_mm + off
        self.count = base.count
