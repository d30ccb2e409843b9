"""What the operator must be told that no safe state says: the service's alerts.

Three monitors, each one event kind (``controller.service.events``) when its condition is
confirmed and one when it clears, and a plain summary for the status snapshot
(:meth:`OperatorAlerts.describe`: the page and OPC UA show it):

* :class:`TargetReach` -- the target pitch cannot be reached: the feed stands at the machine's
  maximum and the measured pitch is still short of the target (or at the minimum and still too
  long), or the depth ceiling lowers the pitch the loop holds below the target's band. The
  loop runs at the limit correctly; the operator learns that the quality class needs a faster
  spindle, another knife set or another class (``TARGET_UNREACHABLE`` / ``TARGET_REACHABLE``).
* :class:`KnifeChipMonitor` -- a knife chipped or moved: the runout each pair shows
  (``s = o_cut - D^+ (w - mean w) / G``: the table in force when the board was cut less the
  width errors in um of offset, as the uniformity loop estimates it) steps on one knife by more
  than :data:`CHIP_STEP_UM` beyond what the table's own moves explain, on two pairs in a row:
  within two pairs (about 0.12 m of board at 600 mm/s) of the camera seeing it
  (``KNIFE_CHIPPED``).
* :class:`FailureMonitor` -- the measurement keeps failing: at least
  :data:`FAILING_SHARE` of the last :data:`FAILING_WINDOW` pairs failed (the supervisor's
  measurement timeout only trips when none succeeds) (``MEASUREMENTS_FAILING`` /
  ``MEASUREMENTS_RECOVERED``).
* :class:`KnifeNickMonitor` -- a knife nicked (a notch in one edge: a stone, a nail): the
  defect detector (:func:`vision.defects.detect.knife_nicks`, with ``Measurer(defects=True)``)
  finds the ridge the notch leaves along the feed, at the same place across it on every pair;
  the mark widths hardly move (the band is 0.3-2 mm of a field tens of mm wide), so
  :class:`KnifeChipMonitor` does not see it. A nick at one place (within
  :data:`NICK_Y_TOL_MM`) on :data:`NICK_CONFIRM` of the last :data:`NICK_WINDOW` pairs looked at
  is told as ``KNIFE_CHIPPED`` with ``data["cause"] = "nick"``, once per nick: within 2-3 pairs
  (0.12-0.18 m of board at 600 mm/s) of the first pair that shows it.

Pure apart from the event log they report to; times are passed in.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from controller.laws.plain_floats import numpy_mean
from controller.laws.uniformity_loop import second_difference, width_sensitivity_mm_per_um
from controller.service.events import EventKind, EventLog
from vision.defects.grading import median

CONFIRM_PAIRS = 5
"""Measurements in a row that confirm (or clear) an unreachable target."""
FEED_AT_LIMIT_MM_S = 0.5
"""A setpoint this close to a feed limit stands at it, mm/s."""
CHIP_STEP_UM = 1.5
"""Smallest runout step of one knife reported as a chip, um (the widths' noise shows as about
0.2 um; a chip of 1.5 um changes its mark's width by about 8 % at 1.5 mm and R 60 mm)."""
CHIP_REF_PAIRS = 5
"""Pairs whose median runout is the reference a step is measured from."""
FAILING_WINDOW = 20
"""Pairs over which the share of failures is judged (2 s at 10 pairs per second)."""
FAILING_SHARE = 0.5
"""A share of failed pairs at least this large is reported ..."""
RECOVERED_SHARE = 0.2
"""... and cleared once it fell below this one."""


class TargetReach:
    """Whether the target pitch is reachable within the machine's feed limits and depth ceiling.

    Parameters
    ----------
    report : EventLog
        Where the events go.
    target_pitch_mm : float
        The quality class's target, mm.
    tolerance : float
        The relative pitch tolerance of the class.
    """

    def __init__(self, report: EventLog, *, target_pitch_mm: float, tolerance: float) -> None:
        self._report = report
        self.target_mm = float(target_pitch_mm)
        self.tol = float(tolerance)
        self._run = 0  # measurements in a row that disagree with the state
        self.active: dict[str, Any] | None = None
        """The unreachable target's data while it lasts (``None``: reachable)."""

    def _why(self, pitch_mm: float, feed_mm_s: float, lo: float, hi: float,
             held_mm: float) -> tuple[str, float] | None:
        """Why the target is not reachable now, and the pitch the limit allows (mm)."""
        short = pitch_mm < self.target_mm * (1.0 - self.tol)
        long_ = pitch_mm > self.target_mm * (1.0 + self.tol)
        if held_mm < self.target_mm * (1.0 - self.tol) and short:
            return "depth ceiling", held_mm
        if short and feed_mm_s >= hi - FEED_AT_LIMIT_MM_S:
            return "feed at its maximum", pitch_mm * hi / max(feed_mm_s, 1e-9)
        if long_ and feed_mm_s <= lo + FEED_AT_LIMIT_MM_S:
            return "feed at its minimum", pitch_mm * lo / max(feed_mm_s, 1e-9)
        return None

    def update(self, t: float, *, pitch_mm: float, feed_mm_s: float, feed_limits_mm_s:
               tuple[float, float], held_pitch_mm: float) -> None:
        """One measurement: its pitch, the feed setpoint in force, the limits, the pitch held."""
        lo, hi = feed_limits_mm_s
        why = self._why(pitch_mm, feed_mm_s, lo, hi, held_pitch_mm)
        if (why is None) == (self.active is None):
            self._run = 0
            return
        self._run += 1
        if self._run < CONFIRM_PAIRS:
            return
        self._run = 0
        if why is not None:
            reason, reach = why
            self.active = {"reason": reason, "target_pitch_mm": self.target_mm,
                           "reachable_pitch_mm": round(reach, 4),
                           "measured_pitch_mm": round(pitch_mm, 4),
                           "feed_mm_s": round(feed_mm_s, 2), "since_s": t}
            self._report.count("targets_unreachable")
            self._report.emit(
                t, EventKind.TARGET_UNREACHABLE,
                f"target pitch {self.target_mm:g} mm not reachable ({reason}): the machine "
                f"holds {reach:.3f} mm", reason=reason, data=self.active)
        else:
            self.active = None
            self._report.emit(t, EventKind.TARGET_REACHABLE,
                              f"target pitch {self.target_mm:g} mm reached again")


class OffsetTimeline:
    """The offset table in force over time (piecewise constant), as the service sent it."""

    def __init__(self, horizon_s: float = 30.0) -> None:
        self.horizon_s = float(horizon_s)
        self._t: list[float] = []
        self._o: list[tuple[float, ...]] = []

    def note(self, t: float, offsets_um: Sequence[float]) -> None:
        """The table ``offsets_um`` is in force from ``t`` on."""
        o = tuple(float(v) for v in offsets_um)
        if self._o and (o == self._o[-1] or t < self._t[-1]):
            return
        self._t.append(float(t))
        self._o.append(o)
        k = bisect.bisect_right(self._t, t - self.horizon_s) - 1
        if k > 0:
            del self._t[:k], self._o[:k]

    def at(self, t: float) -> tuple[float, ...] | None:
        """The table in force at ``t`` (``None`` before the first one)."""
        i = bisect.bisect_right(self._t, t) - 1
        return None if i < 0 else self._o[i]


class KnifeChipMonitor:
    """A sudden runout step on one knife, from the mark widths per knife.

    Parameters
    ----------
    report : EventLog
        Where the events go.
    knives : int
        Knives ``Z``.
    radius_mm : float
        Cutting radius, mm.
    """

    def __init__(self, report: EventLog, *, knives: int, radius_mm: float) -> None:
        self._report = report
        self.knives = int(knives)
        self.radius_mm = float(radius_mm)
        self._d_pinv = np.linalg.pinv(second_difference(self.knives))
        self.timeline = OffsetTimeline()
        self._ref: deque[tuple[list[float], list[float]]] = deque(maxlen=CHIP_REF_PAIRS)
        self._pending: tuple[int, float] | None = None
        self.last: dict[str, Any] | None = None
        """The last chip reported (``None``: none)."""
        self.chips = 0

    def reset(self) -> None:
        """Forget the reference (after a safe state: the board cut meanwhile is not compared)."""
        self._ref.clear()
        self._pending = None

    def _runout(self, widths: Sequence[float], pitch_mm: float,
                o_cut: list[float]) -> list[float]:
        """``s - mean(s)``, ``s = o_cut - D^+ (w - mean(w)) / G``: the runout the pair shows, um.

        Plain floats but for the product with ``D^+`` (numpy's summation): the means are
        numpy's (:func:`~controller.laws.plain_floats.numpy_mean`), so the values are the
        arrays' bit for bit.
        """
        w = [0.0 if not math.isfinite(v) else float(v) for v in widths]
        w_mean = numpy_mean(w)
        y = (self._d_pinv @ np.array([v - w_mean for v in w])).tolist()
        g = width_sensitivity_mm_per_um(pitch_mm, self.radius_mm)
        s = [o - v / g for o, v in zip(o_cut, y, strict=True)]
        s_mean = numpy_mean(s)
        return [v - s_mean for v in s]

    def pair(self, t: float, *, widths_mm: Sequence[float], pitch_mm: float,
             cut_at_s: float | None, seq: int | None = None) -> bool:
        """One measured board's widths per knife; whether a chip was confirmed on it."""
        if self.knives < 3 or len(widths_mm) != self.knives or not pitch_mm > 0:
            return False
        o = self.timeline.at(t if cut_at_s is None else cut_at_s)
        if (o is None or len(o) != self.knives
                or all(math.isnan(float(v)) for v in widths_mm)):
            return False  # no table of these knives known yet, or no mark at all
        o_cut = [float(v) for v in o]
        s = self._runout(widths_mm, pitch_mm, o_cut)
        if len(self._ref) < self._ref.maxlen:  # type: ignore[operator]
            self._ref.append((s, o_cut))
            return False
        # plain floats (a few knives): np.median's and np.argmax's results, without their cost
        ref_s = _column_medians([r[0] for r in self._ref])
        ref_o = _column_medians([r[1] for r in self._ref])
        ds = [a - b for a, b in zip(s, ref_s, strict=True)]
        size = [abs(v) for v in ds]
        k = size.index(max(size))  # the first largest, as np.argmax
        moved = max(abs(a - b) for a, b in zip(o_cut, ref_o, strict=True))
        step = size[k]  # a step of one knife shows (Z - 1) / Z of it here
        if (step * self.knives / (self.knives - 1) < CHIP_STEP_UM + moved
                or max(size[:k] + size[k + 1:]) > 0.5 * step):
            self._pending = None
            self._ref.append((s, o_cut))
            return False
        sign = math.copysign(1.0, float(ds[k]))
        if self._pending is None or self._pending[0] != k or self._pending[1] != sign:
            self._pending = (k, sign)  # one pair may be an odd one: confirm on the next
            return False
        self._pending = None
        self._ref.clear()
        self._ref.append((s, o_cut))
        runout_step = float(ds[k]) * self.knives / (self.knives - 1)
        g = width_sensitivity_mm_per_um(pitch_mm, self.radius_mm)
        self.chips += 1
        self.last = {"knife": k, "cause": "runout_step",
                     "runout_step_um": round(runout_step, 3),
                     "width_change_mm": round(2.0 * g * runout_step, 4), "seq": seq,
                     "t_s": t}
        self._report.count("knife_chips")
        self._report.emit(
            t, EventKind.KNIFE_CHIPPED,
            f"knife {k} chipped or moved: its runout stepped by {runout_step:+.1f} µm "
            f"(its marks {2.0 * g * runout_step:+.3f} mm wider)", data=self.last)
        return True


def _column_medians(rows: Sequence[Sequence[float]]) -> list[float]:
    """``np.median(rows, axis=0)`` of a few rows of finite values, as plain floats.

    The middle value of each column sorted (:func:`vision.defects.grading.median`: the mean of
    the middle two for an even count, as numpy's); NaN where a column holds one (numpy's too).
    """
    return [math.nan if any(map(math.isnan, col)) else median(sorted(col))
            for col in zip(*rows, strict=True)]


class FailureMonitor:
    """A measurement that keeps failing, over the last pairs."""

    def __init__(self, report: EventLog) -> None:
        self._report = report
        self._window: deque[bool] = deque(maxlen=FAILING_WINDOW)
        self._last_error: str | None = None
        self.active: dict[str, Any] | None = None
        """The failing measurement's data while it lasts (``None``: measuring)."""

    def pair(self, t: float, ok: bool, error: str | None = None) -> None:
        """One pair's outcome."""
        self._window.append(not ok)
        if not ok:
            self._last_error = error
        n = len(self._window)
        failed = sum(self._window)
        if self.active is None and n == FAILING_WINDOW and failed >= FAILING_SHARE * n:
            self.active = {"failed": failed, "of": n, "last_error": self._last_error,
                           "since_s": t}
            self._report.count("measurements_failing")
            self._report.emit(t, EventKind.MEASUREMENTS_FAILING,
                              f"measurements failing: {failed} of the last {n} pairs "
                              f"({self._last_error})", data=self.active)
        elif self.active is not None and failed < RECOVERED_SHARE * n:
            self.active = None
            self._report.emit(t, EventKind.MEASUREMENTS_RECOVERED,
                              f"measurements recovered: {failed} of the last {n} pairs failed")


class OperatorAlerts:
    """The three monitors of one service (built with the loops; see the module's docstring)."""

    def __init__(self, report: EventLog, *, target_pitch_mm: float, tolerance: float) -> None:
        self.report = report
        self.target = TargetReach(report, target_pitch_mm=target_pitch_mm, tolerance=tolerance)
        self.failures = FailureMonitor(report)
        self.chips: KnifeChipMonitor | None = None

    def machine(self, knives: int, radius_mm: float) -> None:
        """A machine with these knives: a new chip monitor."""
        self.chips = KnifeChipMonitor(self.report, knives=knives, radius_mm=radius_mm)

    def describe(self) -> dict[str, Any]:
        """Plain JSON for the status: each alert's data while it lasts, the last chip."""
        return {
            "target_unreachable": None if self.target.active is None else dict(self.target.active),
            "measurements_failing": (None if self.failures.active is None
                                     else dict(self.failures.active)),
            "knife_chipped": (None if self.chips is None or self.chips.last is None
                              else dict(self.chips.last)),
        }


NICK_CONFIRM = 2
"""Pairs (of the last :data:`NICK_WINDOW` looked at) that must show a nick at one place."""
NICK_WINDOW = 3
"""Pairs over which a nick is confirmed (one pair may miss it: the detector's recall)."""
NICK_Y_TOL_MM = 2.0
"""Nicks this close across the feed are one, mm (the detector's position scatters ~0.5 mm)."""
NICK_FORGET_PAIRS = 50
"""A nick told is forgotten after this many pairs looked at without it (3 m of board at
0.06 m per pair): one seen again later (a new board, a new knife set) is told again."""
NICK_MIN_CONFIDENCE = 0.3
"""Detections below this confidence do not count (as in the D1666 grade)."""


def nick_positions(defects: Iterable[Any] | None) -> list[tuple[float, float | None]] | None:
    """``(y_mm, height_um)`` of the knife nicks among a pair's defects.

    ``None``: the pair was not looked at (no defect list: the measurer does not look for
    defects, or the pair failed before).
    """
    if defects is None:
        return None
    out = []
    for d in defects:
        kind = getattr(getattr(d, "kind", None), "value", getattr(d, "kind", None))
        if kind != "knife_nick" or float(getattr(d, "confidence", 1.0)) < NICK_MIN_CONFIDENCE:
            continue
        depth = getattr(d, "depth_um", None)
        out.append((float(d.y_mm), None if depth is None else abs(float(depth))))
    return out


class KnifeNickMonitor:
    """Knife nicks confirmed on consecutive pairs, told once each (see the module docstring).

    Parameters
    ----------
    report : EventLog
        Where ``KNIFE_CHIPPED`` goes (and the ``knife_chips`` counter).
    """

    def __init__(self, report: EventLog) -> None:
        self._report = report
        self._recent: deque[list[tuple[float, float | None]]] = deque(maxlen=NICK_WINDOW)
        self._known: list[list[float]] = []  # [y_mm, pairs since last seen] of nicks told
        self.last: dict[str, Any] | None = None
        """The last nick told (``None``: none)."""
        self.nicks = 0

    def reset(self) -> None:
        """Forget the pairs seen (the knives were changed): a nick seen again is told again."""
        self._recent.clear()
        self._known.clear()

    def pair(self, t: float, defects: Iterable[Any] | None, *, seq: int | None = None) -> bool:
        """One pair's defects (``Measurement.defects``); whether a nick was told on it."""
        found = nick_positions(defects)
        if found is None:
            return False
        for known in self._known:
            known[1] = 0 if any(abs(y - known[0]) <= NICK_Y_TOL_MM for y, _ in found) \
                else known[1] + 1
        self._known = [k for k in self._known if k[1] < NICK_FORGET_PAIRS]
        self._recent.append(found)
        told = False
        for y, height in found:
            if any(abs(y - k[0]) <= NICK_Y_TOL_MM for k in self._known):
                continue  # told already
            seen = sum(any(abs(y - y2) <= NICK_Y_TOL_MM for y2, _ in pair)
                       for pair in self._recent)
            if seen < NICK_CONFIRM:
                continue
            self._known.append([y, 0])
            self._tell(t, y, height, seq)
            told = True
        return told

    def _tell(self, t: float, y_mm: float, height_um: float | None, seq: int | None) -> None:
        self.nicks += 1
        self.last = {"knife": None, "cause": "nick", "y_mm": round(y_mm, 2),
                     "ridge_um": None if height_um is None else round(height_um, 1),
                     "runout_step_um": None, "width_change_mm": None, "seq": seq, "t_s": t}
        self._report.count("knife_chips")
        ridge = "" if height_um is None else f", a ridge {height_um:.0f} µm high"
        self._report.emit(
            t, EventKind.KNIFE_CHIPPED,
            f"a knife is nicked: its marks leave a ridge along the board at {y_mm:.1f} mm "
            f"across the camera's field{ridge}", data=self.last)
