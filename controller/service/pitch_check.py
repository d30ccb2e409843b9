"""The measured pitch against the machine: feed per knife pass ``V / (n Z)`` from the PLC.

A pair's marks were cut ``L / V`` before the camera saw them (``L`` = ``cutter_to_camera_mm``).
Where the PLC's feed (``feed_actual_mm_s``) and spindle speed (``spindle_rpm``) held steady from
that cut until the pair's register read, the pitch per knife pass is known from the machine to
within the spindle's ripple and droop and the encoder's slip: a measured pitch further from it
than ``tolerance`` (``[plausibility] pitch_tolerance``) is a measurement gone wrong (a defect
the vision took for marks, a wrong registration), and the pair is flagged. Where the feed
changed over that time (the feed loop's own steps, a ramp) the cutting feed is not known from
the PLC and nothing is checked: the wide ratio check and the feed loop's own steadiness test
remain.

:class:`Flagged` is the error of a flagged pair (the vision's flag or this check's).
:class:`FeedHistory` keeps the PLC's readings (every PLC cycle, :meth:`FeedHistory.note`);
:func:`pitch_disagreement` is the check itself. Pure: no I/O, times passed in.
"""

from __future__ import annotations

import bisect
import itertools
import math
from collections import deque
from dataclasses import dataclass

from controller.fieldbus.plc_protocol import PlcSnapshot
from core.checks import check_finite, check_positive

FIELD_HALF_MM = 30.0
"""Half the camera's field along the feed and then some, mm: the marks of one pair were cut
over ``L -+ FIELD_HALF_MM`` of board travel before the pair."""
LATENCY_S = 0.2
"""Longest time from trigger A to the pair's register read, s (the spool's hand-off included)."""
HISTORY_S = 10.0
"""Readings kept, s (``L / V`` is 0.3-6.6 s between 1000 and 50 mm/s at L = 330 mm)."""


@dataclass(frozen=True)
class CuttingFeed:
    """The feed and spindle speed the PLC reported, steady over a pair's cut-to-read time.

    Attributes
    ----------
    feed_mm_s : float
        Mean ``feed_actual_mm_s`` over the time, mm/s.
    spindle_rpm : float
        Mean ``spindle_rpm`` over the time, rpm.
    knives : int
        Knives Z.
    spread : float
        ``(max - min) / mean`` of the feed per pass over the time.
    """

    feed_mm_s: float
    spindle_rpm: float
    knives: int
    spread: float

    @property
    def pitch_mm(self) -> float:
        """Feed per knife pass ``V / (n Z)``, mm."""
        return self.feed_mm_s / (self.spindle_rpm / 60.0 * self.knives)


class FeedHistory:
    """The PLC's feed and spindle readings of the last :data:`HISTORY_S` seconds.

    Parameters
    ----------
    history_s : float
        Readings older than this (before the newest) are dropped, s.
    """

    def __init__(self, history_s: float = HISTORY_S) -> None:
        self.history_s = check_positive("history_s", history_s)
        self._t: deque[float] = deque()
        self._pitch: deque[float] = deque()  # feed per pass, mm
        self._feed: deque[float] = deque()
        self._rpm: deque[float] = deque()
        self._knives: deque[int] = deque()
        # the slowest feed of the readings kept, kept as they come and go: ``(t, feed)`` of
        # each reading no later one is slower than (ascending feeds; the first the slowest)
        self._slow: deque[tuple[float, float]] = deque()

    def __len__(self) -> int:
        return len(self._t)

    def note(self, snap: PlcSnapshot | None) -> None:
        """Keep one register read (ignored: ``None``, unsound, stopped, or not newer)."""
        if snap is None:
            return
        try:
            t = float(snap.t_s)
            feed, rpm, knives = snap.feed_actual_mm_s, snap.spindle_rpm, snap.knives
        except (AttributeError, KeyError, TypeError, ValueError, OverflowError):
            return  # not a register read of the PLC (a stand-in without times)
        if not (math.isfinite(t) and math.isfinite(feed) and math.isfinite(rpm)
                and feed > 0 and rpm > 0 and knives >= 1):
            return
        if self._t and t <= self._t[-1]:
            return  # the same read again (the pair's snapshot is the cycle's)
        self._t.append(t)
        self._feed.append(feed)
        self._rpm.append(rpm)
        self._knives.append(knives)
        self._pitch.append(feed / (rpm / 60.0 * knives))
        slow = self._slow
        while slow and slow[-1][1] > feed:
            slow.pop()
        slow.append((t, feed))
        while self._t and self._t[0] < t - self.history_s:
            if slow[0][0] == self._t[0]:
                slow.popleft()
            for q in (self._t, self._feed, self._rpm, self._knives, self._pitch):
                q.popleft()

    def _slowest(self, upto: int) -> float:
        """The slowest feed of the first ``upto`` readings (``upto`` > 0)."""
        if upto == len(self._t):  # all of them (a pair's own read is the newest): kept
            return self._slow[0][1]
        return min(itertools.islice(self._feed, upto))

    def cutting_feed(self, t_s: float, *, travel_mm: float) -> CuttingFeed | None:
        """The readings from ``travel_mm`` of board travel before ``t_s`` up to ``t_s``.

        The time back is ``travel_mm`` over the slowest feed kept (the longest the travel may
        have taken) plus :data:`LATENCY_S`. ``None`` when the history does not
        reach that far back, a reading in it changed the knives, or it holds no reading.
        """
        t = check_finite("t_s", t_s)
        travel = check_positive("travel_mm", travel_mm)
        # the times ascend strictly (note): the readings up to t are the first `upto`
        upto = bisect.bisect_right(self._t, t)
        if not upto:
            return None
        last = upto - 1
        slowest = self._slowest(upto)  # the longest the travel may take
        t0 = t - travel / slowest - LATENCY_S
        if self._t[0] > t0:
            return None  # the history does not reach back to the cut
        first = bisect.bisect_right(self._t, t0, 0, upto) - 1
        knives = list(itertools.islice(self._knives, first, upto))
        if knives.count(knives[-1]) != len(knives):
            return None
        pitches = list(itertools.islice(self._pitch, first, upto))
        mean = sum(pitches) / len(pitches)
        n = len(pitches)
        return CuttingFeed(
            feed_mm_s=sum(itertools.islice(self._feed, first, upto)) / n,
            spindle_rpm=sum(itertools.islice(self._rpm, first, upto)) / n,
            knives=self._knives[last],
            spread=(max(pitches) - min(pitches)) / mean,
        )

    def pitch_range(self, t_s: float, *, travel_mm: float,
                    knives: int) -> tuple[float, float, bool] | None:
        """Lowest and highest feed per pass of ``knives`` from ``travel_mm`` before ``t_s``.

        The time back as in :meth:`cutting_feed`. Returns ``(lo, hi, reaches_back)``: where
        the history does not reach back that far, the range of all readings up to ``t_s``
        (``reaches_back`` false); ``None`` when no reading of ``knives`` is kept up to ``t_s``.
        """
        t = check_finite("t_s", t_s)
        travel = check_positive("travel_mm", travel_mm)
        # the times ascend strictly (note): the readings up to t are the first `upto`
        upto = bisect.bisect_right(self._t, t)
        kept = self._knives if upto == len(self._t) else list(itertools.islice(self._knives, upto))
        if upto and kept.count(knives) == upto:  # one knife set throughout: slices
            t0 = t - travel / self._slowest(upto) - LATENCY_S
            behind = bisect.bisect_right(self._t, t0, 0, upto)  # readings at or before t0
            pitches = list(itertools.islice(self._pitch, max(behind - 1, 0), upto))
            return min(pitches), max(pitches), behind > 0 and self._t[0] <= t0
        idx = [i for i, k in enumerate(itertools.islice(kept, upto)) if k == knives]
        if not idx:
            return None
        feed = list(itertools.islice(self._feed, upto))
        times = list(itertools.islice(self._t, upto))
        t0 = t - travel / min(feed[i] for i in idx) - LATENCY_S
        back = [i for i in idx if times[i] <= t0]
        first = back[-1] if back else idx[0]
        pitch = list(itertools.islice(self._pitch, upto))
        pitches = [pitch[i] for i in idx if i >= first]
        return min(pitches), max(pitches), bool(back) and self._t[0] <= t0


class Flagged(str):
    """The error of a flagged pair, ``"flagged: <reason>"``; :attr:`flag_reason` the reason.

    A string like every other error of a pair (``FrameResult.error``), which the quality
    record's ``flag_reason`` is taken from.
    """

    flag_reason: str

    def __new__(cls, reason: str) -> Flagged:  # noqa: D102 (the class says it)
        text = str(reason) or "flagged"
        obj = super().__new__(cls, f"flagged: {text}")
        obj.flag_reason = text
        return obj


def flag_reason_of(error: object) -> str | None:
    """The flag reason of a pair's error (``None``: not a flagged pair)."""
    return error.flag_reason if isinstance(error, Flagged) else None


def pitch_disagreement(pitch_mm: float, cutting: CuttingFeed | None, *,
                       tolerance: float) -> str | None:
    """Why ``pitch_mm`` disagrees with the cutting feed per pass, or ``None``.

    Parameters
    ----------
    pitch_mm : float
        Measured pitch per knife pass, mm.
    cutting : CuttingFeed or None
        The PLC's feed and spindle over the pair's cut-to-read time (``None``: not known, not
        checked).
    tolerance : float
        Largest relative difference allowed (``[plausibility] pitch_tolerance``).

    Returns
    -------
    str or None
        ``None`` when the feed changed by more than ``tolerance`` over the time (the cutting
        feed is not known) or the pitch lies within ``tolerance`` of ``V / (n Z)``; else the
        reason, naming both pitches.
    """
    tol = check_positive("tolerance", tolerance)
    p = check_finite("pitch_mm", pitch_mm)
    if cutting is None or cutting.spread > tol:
        return None
    expected = cutting.pitch_mm
    off = p / expected - 1.0
    if abs(off) <= tol:
        return None
    return (f"pitch {p:.3f} mm is {100 * off:+.1f} % off the feed per pass {expected:.3f} mm "
            f"(V {cutting.feed_mm_s:.1f} mm/s, {cutting.spindle_rpm:.0f} rpm, "
            f"{cutting.knives} knives; tolerance {100 * tol:.2g} %)")
