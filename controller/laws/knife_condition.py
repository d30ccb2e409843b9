"""The knives' condition ahead of time: wear, the offset table's reserve, and when jointing is due.

A knife whose edge wears back stands out less and less; the uniformity loop follows by moving
the head up while the other knives cut (its offset table holds, knife by knife, minus the
knives' stand-out differences). So the table in force, read against the board travelled, is a
measurement of each knife's wear, and the table's distance to the stroke is the reserve left to
correct it. When a knife's needed offset leaves the stroke, the loop can no longer make the
marks equal and the finish drifts out of its class.

:class:`KnifeConditionTracker` keeps the tables in force against the board travel (mm of
board), fits each knife's drift rate over a window (least squares), and forecasts with the
loop's own width model (:func:`controller.laws.uniformity_loop.linear_widths_mm`): the needed
table goes on at the fitted rates, the table that can be applied is its projection into the
stroke (:func:`controller.laws.limits.project_zero_mean_box`, as the loop applies it), and the
marks' CV of what is left over is the finish predicted; the forecast is the first board travel
at which it exceeds the quality class's ``uniformity_max_cv``.

A forecast is made only from a trend the tables show: each knife's fitted rate is tested
against its standard error (:class:`DriftFit`). The tables are autocorrelated (the loop
integrates its measurements, and converges from its first table over a few metres), so the
standard error from the fit's residuals is widened by the residuals' lag-1 autocorrelation
``rho`` (the AR(1) variance inflation ``(1 + rho) / (1 - rho)``; the effective number of points
``n (1 - rho) / (1 + rho)`` sets the Student t's degrees of freedom). A trend is significant
when some knife's ``|t|`` exceeds the two-sided critical value at ``confidence`` shared by the
knives (Bonferroni); without one the forecast says so (:attr:`Trend.NONE`, not due) and gives
no figure: noise and the loop's settling extrapolated to the class's limit would give one.

Pure: numbers in, numbers out; no clock, no I/O.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.special import stdtrit

from controller.laws.limits import project_zero_mean_box
from controller.laws.uniformity_loop import linear_widths_mm, width_cv
from core.checks import check_finite, check_int, check_positive, check_range

__all__ = ["DriftFit", "JointingForecast", "JointingState", "KnifeCondition",
           "KnifeConditionTracker", "Trend"]

RHO_MAX = 0.99
"""The residuals' lag-1 autocorrelation is taken at most this (a wave, not a trend)."""
SD_FLOOR_UM = 1e-6
"""The residuals' standard deviation at least this, um: below it the tables lie on a line to
rounding (no autocorrelation is estimated from them)."""


class JointingState(enum.Enum):
    """What the jointing forecast says (the value is a stable name for logs and JSON)."""

    FITTING = "fitting"
    """Not enough board travelled yet to fit the knives' drift: no forecast."""
    NOT_DUE = "not_due"
    """The finish stays in its class within the forecast's horizon at the present wear."""
    DUE = "due"
    """The finish leaves its class after ``due_in_m`` of board (0: now, a knife's offset at
    the end of its stroke)."""


class Trend(enum.Enum):
    """Whether the tables show a trend (the value is a stable name for logs and JSON)."""

    UNKNOWN = "unknown"
    """Not enough board travelled, or too few tables, to test one."""
    NONE = "none"
    """No knife's drift differs from noise at the stated confidence: no forecast (not due)."""
    SIGNIFICANT = "significant"
    """Some knife's drift is significant: the forecast extrapolates the fitted rates."""


@dataclass(frozen=True)
class DriftFit:
    """The knives' drift fitted over the window, and whether it is a trend.

    Attributes
    ----------
    rates_um_per_m : numpy.ndarray
        Each knife's least-squares drift of its offset, um/m.
    t : numpy.ndarray
        Each knife's rate over its standard error (widened for the residuals' autocorrelation).
    t_crit : numpy.ndarray
        Each knife's two-sided critical value at the tracker's confidence shared by the knives
        (``inf`` when its effective number of points leaves under one degree of freedom).
    points : int
        Tables in the window.
    significant : bool
        Whether some knife's ``|t|`` exceeds its ``t_crit``.
    """

    rates_um_per_m: np.ndarray
    t: np.ndarray
    t_crit: np.ndarray
    points: int
    significant: bool

    @property
    def trend(self) -> Trend:
        """:attr:`Trend.SIGNIFICANT` or :attr:`Trend.NONE`."""
        return Trend.SIGNIFICANT if self.significant else Trend.NONE

    @property
    def t_ratio(self) -> float:
        """The largest ``|t| / t_crit`` over the knives (above 1: significant)."""
        return float(np.max(np.abs(self.t) / self.t_crit))


@dataclass(frozen=True)
class KnifeCondition:
    """One knife's condition.

    Attributes
    ----------
    knife : int
        Knife index (0-based, as the offset table).
    offset_um : float
        Its offset in force, um (minus its stand-out relative to the others').
    drift_um_per_m : float
        Fitted change of its needed offset per metre of board, um/m (positive: the knife
        wears back, the head must come down less while it cuts); nan before enough travel.
    reserve_um : float
        Stroke left in the direction it drifts, um (the stroke minus ``|offset_um|`` when it
        drifts outwards, the whole span to the other end when it drifts back).
    """

    knife: int
    offset_um: float
    drift_um_per_m: float
    reserve_um: float


@dataclass(frozen=True)
class JointingForecast:
    """When the finish leaves its class at the fitted drift.

    Attributes
    ----------
    due_in_m : float or None
        Board travel until the predicted CV exceeds the class's limit, m (0: already;
        ``None``: not within the horizon, or not enough travel fitted yet).
    due_in_boards, due_in_h : float or None
        The same in boards of ``board_length_mm`` and hours at ``feed_mm_s``.
    knife : int or None
        The knife whose reserve runs out first (the one to joint or replace).
    cv_at_due : float or None
        The predicted CV there.
    text : str
        One line for the operator ("jointing due in 37 boards / 0.41 h at this feed").
    state : JointingState
        Fitting, not due (no trend, or none within the horizon), or due (the figures above
        set).
    trend : Trend
        Whether the tables show a trend (:attr:`Trend.NONE`: not due for want of one; a
        knife at the end of its stroke is due now whatever the trend).
    """

    due_in_m: float | None
    due_in_boards: float | None
    due_in_h: float | None
    knife: int | None
    cv_at_due: float | None
    text: str
    state: JointingState
    trend: Trend = Trend.UNKNOWN


class KnifeConditionTracker:
    """Wear and reserve of each knife from the tables in force, and the jointing forecast.

    Parameters
    ----------
    knives : int, keyword-only
        Knives of the head (1..8).
    stroke_um : float, keyword-only
        The offsets' bound, um (the loop's: the smaller of the amplifier's and the config's).
    window_m : float, keyword-only
        Board travel the drift rate is fitted over, m.
    min_span_m : float, keyword-only
        Least travel fitted before a rate (and a forecast) is given, m.
    horizon_m : float, keyword-only
        Longest travel forecast, m.
    confidence : float, keyword-only
        Confidence of the trend test, shared by the knives (0.5..0.999999): a series of noise
        alone is taken for a trend in at most ``1 - confidence`` of the windows.
    min_points : int, keyword-only
        Least tables in the window before a rate is given (>= 4).
    """

    def __init__(self, *, knives: int, stroke_um: float, window_m: float = 10.0,
                 min_span_m: float = 3.0, horizon_m: float = 5000.0,
                 confidence: float = 0.999, min_points: int = 10) -> None:
        self.knives = check_int("knives", knives, lo=1, hi=8)
        self.stroke_um = check_positive("stroke_um", stroke_um)
        self.window_m = check_positive("window_m", window_m)
        self.min_span_m = check_positive("min_span_m", min_span_m)
        if self.min_span_m > self.window_m:
            raise ValueError(f"min_span_m {min_span_m} must not exceed window_m {window_m}")
        self.horizon_m = check_positive("horizon_m", horizon_m)
        self.confidence = check_range("confidence", confidence, 0.5, 0.999999)
        self.min_points = check_int("min_points", min_points, lo=4)
        self._points: deque[tuple[float, tuple[float, ...]]] = deque()

    def update(self, *, board_m: float, offsets_um: Sequence[float]) -> None:
        """The table in force at ``board_m`` metres of board travelled (non-decreasing)."""
        x = check_finite("board_m", board_m)
        table = tuple(check_finite(f"offsets_um[{k}]", v) for k, v in enumerate(offsets_um))
        if len(table) != self.knives:
            raise ValueError(f"offsets_um must have {self.knives} values, got {len(table)}")
        if self._points and x < self._points[-1][0]:
            raise ValueError(f"board_m went back: {x} after {self._points[-1][0]}")
        self._points.append((x, table))
        while self._points and self._points[0][0] < x - self.window_m:
            self._points.popleft()

    def reset(self) -> None:
        """Forget the history (new knives, a jointing, a new cutterhead)."""
        self._points.clear()

    @property
    def span_m(self) -> float:
        """Board travel the current fit covers, m."""
        return self._points[-1][0] - self._points[0][0] if self._points else 0.0

    def fit(self) -> DriftFit | None:
        """The knives' drift over the window and its test.

        ``None`` before ``min_span_m`` of board and ``min_points`` tables.
        """
        n = len(self._points)
        if self.span_m < self.min_span_m or n < self.min_points:
            return None
        x = np.array([p[0] for p in self._points])
        y = np.array([p[1] for p in self._points])
        dx = x - x.mean()
        sxx = float(dx @ dx)
        rates = (dx @ (y - y.mean(axis=0))) / sxx
        resid = y - y.mean(axis=0) - np.outer(dx, rates)
        ss = np.einsum("ij,ij->j", resid, resid)
        lag1 = np.einsum("ij,ij->j", resid[1:], resid[:-1])
        sd = np.sqrt(ss / (n - 2))
        exact = sd < SD_FLOOR_UM  # a line to rounding: its residuals' correlation is numerics
        rho = np.clip(np.divide(lag1, ss, out=np.zeros_like(ss), where=~exact), 0.0, RHO_MAX)
        sd = np.maximum(sd, SD_FLOOR_UM)
        se = sd / math.sqrt(sxx) * np.sqrt((1.0 + rho) / (1.0 - rho))
        t = rates / se
        dof = n * (1.0 - rho) / (1.0 + rho) - 2.0
        alpha = (1.0 - self.confidence) / self.knives  # shared by the knives (Bonferroni)
        t_crit = np.where(dof >= 1.0, stdtrit(np.maximum(dof, 1.0), 1.0 - alpha / 2.0), np.inf)
        return DriftFit(rates_um_per_m=rates, t=t, t_crit=t_crit, points=n,
                        significant=bool(np.any(np.abs(t) > t_crit)))

    def rates_um_per_m(self) -> np.ndarray | None:
        """Each knife's least-squares drift of its offset, um/m (``None`` before the span)."""
        fit = self.fit()
        return None if fit is None else fit.rates_um_per_m

    def conditions(self) -> list[KnifeCondition]:
        """Every knife's offset, drift and reserve now (empty before the first table)."""
        if not self._points:
            return []
        table = self._points[-1][1]
        rates = self.rates_um_per_m()
        out = []
        for k, o in enumerate(table):
            r = math.nan if rates is None else float(rates[k])
            toward = 1.0 if (r >= 0 if not math.isnan(r) else o >= 0) else -1.0
            out.append(KnifeCondition(knife=k, offset_um=o, drift_um_per_m=r,
                                      reserve_um=max(0.0, self.stroke_um - toward * o)))
        return out

    def forecast(self, *, pitch_mm: float, radius_mm: float, cv_max: float,
                 feed_mm_s: float, board_length_mm: float, step_m: float = 0.1
                 ) -> JointingForecast:
        """When the finish leaves its class at the fitted drift (see the module's docstring).

        Parameters
        ----------
        pitch_mm, radius_mm : float
            The pitch cut and the cutting radius, mm (the width model).
        cv_max : float
            The quality class's ``uniformity_max_cv``.
        feed_mm_s, board_length_mm : float
            For the forecast in hours and in boards.
        step_m : float
            Resolution of the forecast, m.
        """
        check_positive("cv_max", cv_max)
        feed = check_positive("feed_mm_s", feed_mm_s)
        board = check_positive("board_length_mm", board_length_mm)
        step = check_positive("step_m", step_m)
        fit = self.fit()
        if fit is None:
            return JointingForecast(None, None, None, None, None,
                                    f"knife condition: fitting ({self.span_m:.1f} of "
                                    f"{self.min_span_m:.1f} m of board, "
                                    f"{len(self._points)} of {self.min_points} tables)",
                                    JointingState.FITTING)
        rates = fit.rates_um_per_m
        now = np.array(self._points[-1][1])

        def cv_at(d_m: float) -> float:
            needed = now + rates * d_m
            applied = project_zero_mean_box(needed - needed.mean(), bound=self.stroke_um)
            left = applied - (needed - needed.mean())  # relative depth the loop cannot remove
            return width_cv(linear_widths_mm(left, pitch_mm=pitch_mm, radius_mm=radius_mm))

        at_bound = np.abs(now) >= self.stroke_um - 1e-9
        if np.any(at_bound):  # the reserve is gone: the loop cannot follow the wear any more
            knife = int(np.argmax(np.abs(now)))
            return JointingForecast(0.0, 0.0, 0.0, knife, None,
                                    f"jointing due now: knife {knife} at the end of its "
                                    "stroke", JointingState.DUE, fit.trend)
        if not fit.significant:
            return JointingForecast(None, None, None, None, None,
                                    f"knife condition: no wear trend (|t|/t_crit "
                                    f"{fit.t_ratio:.2f} at {100 * self.confidence:g} %): "
                                    "jointing not due", JointingState.NOT_DUE, Trend.NONE)
        due = _first_crossing(lambda d_m: cv_at(d_m) > cv_max, step, self.horizon_m)
        if due is None:
            return JointingForecast(None, None, None, None, None,
                                    f"knife condition: no jointing due within "
                                    f"{self.horizon_m:.0f} m at this wear",
                                    JointingState.NOT_DUE, Trend.SIGNIFICANT)
        needed = now + rates * due
        knife = int(np.argmax(np.abs(needed - needed.mean())))
        boards = due * 1000.0 / board
        hours = due * 1000.0 / feed / 3600.0
        return JointingForecast(due, boards, hours, knife, cv_at(due),
                                f"jointing due in {boards:.0f} boards / {hours:.2f} h at this "
                                f"feed (knife {knife})", JointingState.DUE, Trend.SIGNIFICANT)


def _first_crossing(crossed, step_m: float, horizon_m: float) -> float | None:
    """The least travel (to ``step_m``) at which ``crossed(d)`` holds, ``None`` within none.

    The predicted CV is 0 while the table stays inside the stroke and grows with the travel
    after, so a geometric scan brackets the crossing and a bisection narrows it.
    """
    if crossed(0.0):
        return 0.0
    lo, hi = 0.0, step_m
    while not crossed(hi):
        if hi >= horizon_m:
            return None
        lo, hi = hi, min(hi * 1.5, horizon_m)
    while hi - lo > step_m:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if crossed(mid) else (mid, hi)
    return hi
