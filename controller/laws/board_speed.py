"""The board's actual speed over the last minutes: the feed per knife pass a board was cut with.

The mark attribution counts knife passes with the feed per pass at the pair, ``V / (n Z)``; the
board it sees was cut ``L / V`` earlier, and during a fast feed change the two differ by up to a
factor 2 (``docs/control_design.md``, section 5). :class:`BoardSpeedHistory` keeps the actual
feed and the knife passing rate the PLC reported, so the feed per pass at the cut is known from
the board travel alone: walk back ``L`` millimetres of travel from the pair. Unlike the feed
loop's setpoint history it follows the drive's lag. Pure: times are passed in.
"""

from __future__ import annotations

import bisect
import math

from core.checks import check_finite, check_positive


class BoardSpeedHistory:
    """Actual feed and knife passing rate over time (piecewise constant between samples).

    Parameters
    ----------
    horizon_s : float
        How far back samples are kept, seconds (longest transport delay plus margin).
    """

    def __init__(self, *, horizon_s: float = 120.0) -> None:
        self.horizon_s = check_positive("horizon_s", horizon_s)
        self._t: list[float] = []
        self._v: list[float] = []
        self._rate: list[float] = []
        self._d: list[float] = []  # board travel at each sample, mm

    def __len__(self) -> int:
        return len(self._t)

    def record(self, t_s: float, feed_mm_s: float, passes_per_s: float) -> None:
        """A reading: the board's speed and the knife passing rate ``n Z`` from ``t_s`` on.

        Readings older than the last one are ignored (the history only moves forward);
        a reading at the same instant replaces it. Non-finite or negative values are ignored.
        """
        t = check_finite("t_s", t_s)
        v, rate = float(feed_mm_s), float(passes_per_s)
        if not (math.isfinite(v) and v >= 0.0 and math.isfinite(rate) and rate >= 0.0):
            return
        if self._t and t < self._t[-1]:
            return
        if self._t and t == self._t[-1]:
            self._v[-1], self._rate[-1] = v, rate
            return
        d = self._d[-1] + self._v[-1] * (t - self._t[-1]) if self._t else 0.0
        self._t.append(t)
        self._v.append(v)
        self._rate.append(rate)
        self._d.append(d)
        k = bisect.bisect_right(self._t, t - self.horizon_s) - 1
        if k > 0:
            del self._t[:k], self._v[:k], self._rate[:k], self._d[:k]

    def pass_travel_mm(self, t_s: float, *, back_mm: float) -> float | None:
        """Feed per knife pass when the board was ``back_mm`` short of where it is at ``t_s``.

        Parameters
        ----------
        t_s : float
            E.g. the trigger time of a pair, seconds.
        back_mm : float
            Board travel back from then, mm (the cutter-to-camera distance: the image centre's
            cut), >= 0.

        Returns
        -------
        float or None
            ``V / (n Z)`` then, mm; ``None`` when the history does not reach back that far, or
            the board or the spindle stood.
        """
        t = check_finite("t_s", t_s)
        back = check_positive("back_mm", back_mm, allow_zero=True)
        if not self._t or t < self._t[0]:
            return None
        i = bisect.bisect_right(self._t, t) - 1
        d_then = self._d[i] + self._v[i] * (t - self._t[i]) - back
        if d_then < self._d[0]:
            return None
        j = bisect.bisect_right(self._d, d_then) - 1  # the sample whose speed covered d_then
        v, rate = self._v[j], self._rate[j]
        if not (v > 0.0 and rate > 0.0):
            return None
        return v / rate
