"""The feed per knife pass when a pair's marks were cut, and the attribution's fit against it.

The marks a pair's camera sees were cut ``L`` (``cutter_to_camera_mm``) of board travel
earlier, at the feed and spindle speed of then: during a ramp ``V / (n Z)`` at the pair (the
attribution's guide) differs from it by up to 25 % (eight knives, the feed rising 5000
mm/s^2: 0.756-0.987 of the guide over the first 9 pairs). :class:`PairFeedHistory` keeps, per
pair, the board position (the feed encoder's counts at trigger A, unwrapped), the time and
the feed per pass ``V / (n Z)`` from the encoder's speed and the PLC's spindle speed and
knives; :func:`cut_feed` finds the pairs whose positions bracket the cut of the field's marks
(``L + x - cx / px_per_mm`` behind the pair for a mark at ``x`` in image A) and gives the
range of their feeds per pass (:class:`CutFeed`). A knife-phase fit whose travel per pass
lies outside that range widened by ``[plausibility] pass_tolerance`` has counted the passes
per revolution wrong (Z / (Z + 1) or (Z + 1) / Z of the true travel: the marks given to the
wrong knives) and is refused (:func:`pass_disagreement`).

Where no pair history brackets the cut (the first ``L`` of travel after the service
started, or a change of the knives), the PLC's feed and spindle readings over the time the
cut may lie back (:meth:`controller.service.pitch_check.FeedHistory.pitch_range`) give the
range; where even those do not reach back so far, the range of the feeds per pass the PLC
reported since its history began (the feed at the cut taken to be one the service saw: true
when the service ran before the board was cut; a service started mid-board at another feed
may refuse the first pairs). With no reading at all nothing is checked. Pure: no I/O.
"""

from __future__ import annotations

import bisect
import itertools
import math
from collections import deque
from dataclasses import dataclass
from enum import Enum

from controller.service.pitch_check import FeedHistory
from core.checks import check_finite, check_int, check_positive
from core.units import counter_difference

MAX_PAIRS = 1024
"""Most pairs kept (the history is bounded whatever the travel per pair)."""
KEEP_BEYOND_MM = 200.0
"""Travel kept behind the newest pair beyond ``L``, mm (the camera's field, ~52 mm, and a
pair's spacing at the fastest feed, ~100 mm at 1000 mm/s and 10 pairs/s)."""


class CutFeedSource(Enum):
    """Where the range of the feed per pass at the cut came from."""

    PAIRS = "pairs"
    """The pairs whose board positions bracket the cut."""
    PLC = "plc"
    """The PLC's readings over the time the cut may lie back."""


@dataclass(frozen=True)
class CutFeed:
    """The feed per knife pass over the cut of a pair's marks: a range, mm.

    Attributes
    ----------
    lo_mm, hi_mm : float
        Lowest and highest feed per pass ``V / (n Z)`` over the cut, mm.
    source : CutFeedSource
        Where they came from.
    """

    lo_mm: float
    hi_mm: float
    source: CutFeedSource

    def __post_init__(self) -> None:
        lo = check_positive("lo_mm", self.lo_mm)
        hi = check_positive("hi_mm", self.hi_mm)
        if hi < lo:
            raise ValueError(f"hi_mm must be >= lo_mm, got {hi!r} < {lo!r}")


class PairFeedHistory:
    """The feed per knife pass of the recent pairs, keyed by board position (bounded).

    Parameters
    ----------
    max_pairs : int
        Most pairs kept.
    keep_beyond_mm : float
        Travel kept behind the newest pair beyond the ``L`` given at :meth:`note`, mm.
    """

    def __init__(self, max_pairs: int = MAX_PAIRS,
                 keep_beyond_mm: float = KEEP_BEYOND_MM) -> None:
        self.max_pairs = check_int("max_pairs", max_pairs, lo=2)
        self.keep_beyond_mm = check_positive("keep_beyond_mm", keep_beyond_mm)
        self._counts: int | None = None  # the newest pair's wrapped counts
        self._pos: deque[int] = deque()  # unwrapped counts, ascending
        self._pitch: deque[float] = deque()
        self._knives: deque[int] = deque()
        self._t: deque[float] = deque()

    def __len__(self) -> int:
        return len(self._pos)

    def position(self, counts: int, *, counter_bits: int) -> int | None:
        """Unwrapped position (counts) of a counter reading near the newest pair's."""
        if self._counts is None:
            return None
        return self._pos[-1] + counter_difference(int(counts), self._counts, bits=counter_bits)

    def note(self, counts: int, t_s: float, pass_mm: float, knives: int, *,
             counter_bits: int, counts_per_mm: float, keep_mm: float) -> None:
        """Keep one pair (ignored: a feed per pass not finite and > 0, or not ahead).

        Parameters
        ----------
        counts : int
            Feed encoder counts at trigger A (wrapped).
        t_s : float
            Its time, s.
        pass_mm : float
            ``V / (n Z)`` at the pair, mm.
        knives : int
            Knives Z in force.
        counter_bits : int
            Width of the encoder's counter.
        counts_per_mm : float
            Encoder counts per mm.
        keep_mm : float
            Travel to keep behind this pair (``L``), mm; :attr:`keep_beyond_mm` more is kept.
        """
        if not (math.isfinite(pass_mm) and pass_mm > 0 and knives >= 1):
            return
        pos = self.position(counts, counter_bits=counter_bits)
        if pos is None:
            pos = 0
        elif pos <= self._pos[-1]:
            return  # the same pair again, or the encoder ran back
        self._counts = int(counts)
        for q, v in ((self._pos, pos), (self._pitch, float(pass_mm)),
                     (self._knives, int(knives)), (self._t, float(t_s))):
            q.append(v)
        limit = pos - (keep_mm + self.keep_beyond_mm) * counts_per_mm
        # keep one pair at or behind the limit: it brackets a cut there
        while len(self._pos) > self.max_pairs or (len(self._pos) > 1 and self._pos[1] <= limit):
            for q in (self._pos, self._pitch, self._knives, self._t):
                q.popleft()

    def bracket(self, lo_pos: float, hi_pos: float, knives: int) -> tuple[float, float] | None:
        """Lowest and highest feed per pass of the pairs bracketing ``[lo_pos, hi_pos]``.

        From the last pair at or behind ``lo_pos`` to the first at or ahead of ``hi_pos``
        (positions in counts); ``None`` when no pair lies on one side or the knives changed
        in between.
        """
        pos = self._pos
        if not pos or pos[0] > lo_pos or pos[-1] < hi_pos:
            return None
        # the positions ascend strictly (note): the last at or behind, the first at or ahead
        first = bisect.bisect_right(pos, lo_pos) - 1
        last = bisect.bisect_left(pos, hi_pos)
        kept = list(itertools.islice(self._knives, first, last + 1))
        if kept.count(knives) != len(kept):
            return None
        values = list(itertools.islice(self._pitch, first, last + 1))
        return min(values), max(values)


def cut_feed(pairs: PairFeedHistory | None, plc: FeedHistory | None, *, counts: int,
             t_s: float | None, knives: int, back_mm: tuple[float, float],
             counts_per_mm: float, counter_bits: int) -> CutFeed | None:
    """The feed per pass over the cut of a pair's marks (see the module docstring).

    Parameters
    ----------
    pairs : PairFeedHistory or None
        The pairs so far (this one included or not).
    plc : FeedHistory or None
        The PLC's readings (the start-up's fallback).
    counts : int
        The pair's encoder counts at trigger A.
    t_s : float or None
        The time of the pair's register read (``None``: the PLC's readings are not used).
    knives : int
        Knives Z in force.
    back_mm : (float, float)
        Nearest and furthest board travel back to the cut of the field's marks, mm.
    counts_per_mm : float
        Encoder counts per mm.
    counter_bits : int
        Width of the encoder's counter.

    Returns
    -------
    CutFeed or None
        ``None`` when nothing is known of the feed at the cut.
    """
    near, far = (check_finite("back_mm", float(b)) for b in back_mm)
    cpm = check_positive("counts_per_mm", counts_per_mm)
    if pairs is not None:
        now = pairs.position(counts, counter_bits=counter_bits)
        if now is not None:
            got = pairs.bracket(now - far * cpm, now - near * cpm, knives)
            if got is not None:
                return CutFeed(got[0], got[1], CutFeedSource.PAIRS)
    if plc is None or t_s is None or not math.isfinite(t_s):
        return None
    got = plc.pitch_range(t_s, travel_mm=max(far, 1e-9), knives=knives)
    if got is None:
        return None
    lo, hi, reaches = got
    return CutFeed(lo, hi, CutFeedSource.PLC) if reaches else None


def pass_disagreement(pass_mm: float, cut: CutFeed | None, *, tolerance: float) -> str | None:
    """Why a fit's travel per pass disagrees with the feed per pass at the cut, or ``None``.

    Parameters
    ----------
    pass_mm : float
        The knife-phase fit's board travel per pass, mm.
    cut : CutFeed or None
        The feed per pass over the cut (``None``: not known, not checked).
    tolerance : float
        Relative margin beyond the range (``[plausibility] pass_tolerance``).

    Returns
    -------
    str or None
        ``None`` when ``lo (1 - tolerance) <= pass_mm <= hi (1 + tolerance)``; else the
        reason, naming the travel per pass and the range.
    """
    tol = check_positive("tolerance", tolerance)
    p = check_finite("pass_mm", pass_mm)
    if cut is None:
        return None
    if cut.lo_mm * (1.0 - tol) <= p <= cut.hi_mm * (1.0 + tol):
        return None
    ref = cut.lo_mm if p < cut.lo_mm else cut.hi_mm
    feed = (f"{cut.lo_mm:.4f} mm" if cut.hi_mm - cut.lo_mm < 5e-5
            else f"{cut.lo_mm:.4f}-{cut.hi_mm:.4f} mm")
    return (f"travel per pass {p:.4f} mm is {100 * (p / ref - 1.0):+.1f} % off the feed per "
            f"pass {feed} when the marks were cut ({cut.source.value}; tolerance "
            f"{100 * tol:.2g} %)")
