"""Mark-to-knife attribution stage: which knife pass cut each mark of a valid measurement.

The phase and the travel per pass come from the mark bottoms that lie inside their marks
(:func:`controller.laws.knife_phase.attribute_marks`, guided by the feed per pass ``V / (n Z)``
from the encoder speed and the PLC's spindle speed and knives); a narrow mark whose bottom sits
on its cusp and a knife that left no mark do not spoil them. The result (:class:`Attributed`)
is what the loops get: widths per knife and the pitch per knife pass.

Vanished marks: every mark gets a knife pass of its own, so the passes
between the first and the last mark that got none are the passes that left no mark, and a
knife with passes there but no mark at all has *vanished* (another knife's cut removed its
mark). Then the marks found say little: the mean mark width is a multiple of the feed per pass
and their CV leaves the vanished knife out. The pair reports instead (:attr:`Attributed.pitch_mm`,
:attr:`Attributed.uniformity_cv`) the kinematics: the board travel per knife pass, and the CV of
the widths per knife and pass (:func:`kinematic_cv`) in which a vanished knife counts 0 and its
neighbours the wider marks they cut; the uniformity loop gets the same widths (0 pushes the
vanished knife's offset down until its mark is back). The board travel per pass is then
fitted to the knives' BDCs (the mark bottoms inside their marks): ``V / (n Z)`` at the pair is
only the guide, since the marks were cut ``L / V`` earlier, at the feed of then.

Complete marks: the pair reports the CV of the widths as the knives cut them
(:func:`_knife_model_cv`): each mark's width is its knife's plus a trend along the field (a feed
change), fitted over the field's marks. The CV of the widths as found
(:attr:`Attributed.marks_cv`) holds the read noise once per mark (at 30 DN ~0.013 where the
knives cut evenly, ~0.004 in the fit). Pure: no I/O.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from controller.fieldbus.plc_protocol import PlcSnapshot
from controller.laws import knife_phase
from controller.service.cut_feed import (
    CutFeed,
    PairFeedHistory,
    cut_feed,
    pass_disagreement,
)
from controller.service.events import exc_name
from controller.service.measurement import expected_pitch_mm
from controller.service.pitch_check import FeedHistory
from protocol.frames import Frame

MAX_PHASE_SPREAD = 0.15
"""Marks whose pass numbers spread more than this (in passes) are not attributed to knives."""
PASS_TOLERANCE = 0.03
"""Default margin of the fit's travel per pass around the feed per pass at the cut
(``[plausibility] pass_tolerance``)."""
MIN_BOTTOM_INSET_SAMPLES = 1.0
"""A mark bottom closer than this (in profile samples, ``1 / px_per_mm``) to a cusp of its mark
was clipped there by the vision (narrow mark, BDC outside it) and does not set the phase."""


def _vanished(counts: list[int], marks: list[int]) -> tuple[int, ...]:
    """Knives that had passes over the marks' span but left no mark there, ascending.

    ``counts``: passes of each knife from the first mark's pass to the last mark's
    (:attr:`controller.laws.knife_phase.PassAttribution.passes_per_knife`); ``marks``: the
    knife of each mark, in ``[0, Z)`` (both as :func:`attribute` has them from
    :func:`controller.laws.knife_phase.attribute_marks`).
    """
    marked = set(marks)
    return tuple(k for k, n in enumerate(counts) if n > 0 and k not in marked)


def kinematic_cv(knife_widths_mm: Sequence[float]) -> float:
    """CV (population std / mean) of the widths per knife and pass, a vanished knife at 0.

    Parameters
    ----------
    knife_widths_mm : sequence of float, shape (Z,)
        Width of each knife's mark per pass, mm: 0 for a knife that left no mark, NaN for a
        knife with no pass in the field (left out).

    Returns
    -------
    float
        ``std(w) / mean(w)`` over the knives with passes; NaN when none has or the mean is 0.
        With one of Z knives vanished and the others equal: ``1 / sqrt(Z - 1)``.
    """
    w = np.asarray(knife_widths_mm, dtype=float)
    if w.ndim != 1:
        raise ValueError("knife_widths_mm must be a 1-D sequence of widths >= 0 (or NaN)")
    values = w.tolist()
    if any(math.isinf(v) or v < 0 for v in values):  # (NaN < 0 is false)
        raise ValueError("knife_widths_mm must be a 1-D sequence of widths >= 0 (or NaN)")
    mean, std = mean_std([v for v in values if not math.isnan(v)])
    return std / mean if mean > 0 else math.nan


def mean_std(values: list[float]) -> tuple[float, float]:
    """Mean and population standard deviation of a few finite floats; ``(nan, nan)`` for none.

    Plain floats (a knife table has at most 8 values: numpy's calls cost more than the sums);
    equal to ``np.mean`` / ``np.std`` to rounding.

    Parameters
    ----------
    values : list of float, shape (n,)
        The values (finite).

    Returns
    -------
    (float, float)
        Mean and population standard deviation.
    """
    n = len(values)
    if n == 0:
        return math.nan, math.nan
    mean = sum(values) / n
    return mean, math.sqrt(sum((v - mean) * (v - mean) for v in values) / n)


KNIFE_MODEL_MIN_DOF = 3
"""Fewer marks than knives with marks + 1 + this: the CV of the widths as found is reported."""


def _knife_model_cv(ws: list[float], labels: list[Any], xs: list[float]) -> float:
    """CV of the mark widths as the knives cut them: each knife's width, not each mark's.

    Each mark's width is modelled as its knife's width plus a trend along the field (the feed
    changing while the field was cut), ``w_i = a_(k(i)) + c (x_i - mean x)``, fitted by least
    squares; the CV is the population std / mean of the fitted widths. Widths that repeat per
    knife (the runout's pattern) along a steady or steadily changing feed are fitted exactly,
    so without noise this is the CV of the widths; the read noise of each width (a cusp
    placed ~0.2 px off at 30 DN) enters through ``K + 1`` fitted values instead of ``n``
    single widths: its share of the variance falls by about ``(K + 1) / n``.

    Parameters
    ----------
    ws : list of float, shape (n,)
        Width of each mark, mm (finite, > 0 on average).
    labels : list, shape (n,)
        Knife of each mark (any hashable values: marks of one knife share a value).
    xs : list of float, shape (n,)
        Position of each mark along the field (its lowest point), mm (finite).

    Returns
    -------
    float
        The CV; the population std / mean of the widths themselves when the marks are too few
        for the model (fewer than ``K + 1 + KNIFE_MODEL_MIN_DOF``, ``K`` the knives with
        marks); NaN for no marks or a mean <= 0.
    """
    n = len(ws)
    mean = sum(ws) / n if n else math.nan
    if not mean > 0:
        return math.nan
    groups: dict[Any, list[float]] = {}  # knife: [marks, sum of widths, sum of positions]
    for v, wi, xi in zip(labels, ws, xs, strict=True):
        g = groups.get(v)
        if g is None:
            groups[v] = [1.0, wi, xi]
        else:
            g[0] += 1.0
            g[1] += wi
            g[2] += xi
    if n - len(groups) - 1 < KNIFE_MODEL_MIN_DOF:
        return mean_std(ws)[1] / mean
    return _knife_model_std(ws, xs, labels, groups, mean) / mean


def _knife_model_std(ws: list[float], xs: list[float], labels: list[Any],
                     groups: dict[Any, list[float]], mean: float) -> float:
    """The population std of the least-squares fit ``w_i = a_(k(i)) + c (x_i - mean x)``.

    In closed form (one width per knife and a common trend: the within-knife regression): the
    fitted width of a mark is its knife's mean width plus ``c`` times its position from its
    knife's mean position, ``c = Sxw / Sxx`` over the deviations from the knives' means, so the
    fitted widths' sum of squares about their mean (the widths' mean) is
    ``sum_k n_k (mean_k w - mean w)^2 + Sxw^2 / Sxx``: the least-squares projection
    (``np.linalg.lstsq`` of the design with one column per knife and the centred positions) to
    rounding, without its set-up (:func:`_knife_model_cv`, a knife table of at most ~50 marks).
    Positions that do not spread within any knife's marks (``Sxx`` nil against the field's)
    leave no trend to fit: ``c = 0``, as the least-squares minimum norm solution.
    """
    means = {v: (g[1] / g[0], g[2] / g[0]) for v, g in groups.items()}
    sxx = sxw = 0.0
    for v, wi, xi in zip(labels, ws, xs, strict=True):
        mw, mx = means[v]
        dx = xi - mx
        sxx += dx * dx
        sxw += dx * (wi - mw)
    between = 0.0
    for v, g in groups.items():
        d = means[v][0] - mean
        between += g[0] * d * d
    n = len(ws)
    xm = sum(xs) / n
    spread = sum((xi - xm) * (xi - xm) for xi in xs)
    if sxx > (n * sys.float_info.epsilon) ** 2 * max(spread, 1.0):  # else: no trend to fit
        between += sxw * sxw / sxx
    return math.sqrt(max(between, 0.0) / n)


@dataclass(frozen=True)
class Attributed:
    """The marks of one valid pair attributed to knife passes (what the loops get).

    Attributes
    ----------
    knife_widths_mm : ndarray, shape (Z,)
        Width per knife and pass, a pass without a mark counting 0 (so a vanished knife has
        width 0 and its neighbours the wider marks they cut); NaN for a knife without a pass
        in the field (a field shorter than a revolution), mm.
    pass_pitch_mm : float
        Board travel per knife pass, the feed per pass: the measured mean mark width when no
        pass is missing; else the travel per pass fitted to the knives' BDCs (the reliable
        bottoms, :attr:`bdc_pitch_mm`), which neither the marks a vanished knife's neighbours
        widened nor a feed change since the cut (``feed_per_pass_mm``) bias, mm. The feed
        loop holds this at the target; the uniformity loop scales its steps by it.
    missing_passes : int
        Knife passes in that span that left no mark.
    spread : float
        Phase spread of the reliable bottoms, passes.
    reliable_marks : int
        Marks whose bottoms lie inside them (these set the phase).
    mark_knife : tuple of int, shape (n,)
        Knife of each mark, in the order of the measurement's marks.
    vanished_knives : tuple of int
        Knives with passes in the span and no mark (:func:`_vanished`).
    kinematic_cv : float
        :func:`kinematic_cv` of ``knife_widths_mm``.
    feed_per_pass_mm : float
        ``V / (n Z)``: the encoder's board speed over the PLC's spindle speed times knives, at
        the pair (the guide of the attribution; the marks were cut ``L / V`` earlier), mm.
    marks_pitch_mm, marks_cv : float
        The measurement's own pitch (mean mark width) and CV over the marks found.
    knife_cv : float
        :func:`_knife_model_cv` of the marks found: their CV as the knives cut them (each
        knife's width and a trend along the field; NaN when passes left no mark: not
        computed).
    bdc_pitch_mm : float
        Board travel per knife pass fitted to the reliable mark bottoms (the knives' BDCs),
        mm.
    cut_feed : CutFeed or None
        The feed per pass when the marks were cut, the fit was checked against
        (:mod:`controller.service.cut_feed`; ``None``: not known, not checked).
    """

    knife_widths_mm: np.ndarray
    pass_pitch_mm: float
    missing_passes: int
    spread: float
    reliable_marks: int
    mark_knife: tuple[int, ...] = ()
    vanished_knives: tuple[int, ...] = ()
    kinematic_cv: float = math.nan
    feed_per_pass_mm: float = math.nan
    marks_pitch_mm: float = math.nan
    marks_cv: float = math.nan
    bdc_pitch_mm: float = math.nan
    knife_cv: float = math.nan
    cut_feed: CutFeed | None = None

    @property
    def complete(self) -> bool:
        """Whether every knife pass over the marks' span left a mark."""
        return self.missing_passes == 0

    @property
    def pitch_mm(self) -> float:
        """The pitch the pair reports, mm.

        The measured one, or the travel per pass if passes left no mark (the mean of the
        marks found is then a multiple of it).
        """
        return self.marks_pitch_mm if self.complete else self.pass_pitch_mm

    @property
    def uniformity_cv(self) -> float:
        """The uniformity the pair reports.

        The CV of the marks found as the knives cut them (:attr:`knife_cv`; the CV of the
        widths as found, :attr:`marks_cv`, when that is not known), or the
        :attr:`kinematic_cv` if passes left no mark (a vanished knife counted as width 0).
        """
        if not self.complete:
            return self.kinematic_cv
        return self.knife_cv if math.isfinite(self.knife_cv) else self.marks_cv

    def to_json(self) -> dict[str, Any]:
        """Plain-JSON summary for the quality record's ``extra["passes"]`` (NaN as ``None``)."""
        return {
            "pass_pitch_mm": _json_float(self.pass_pitch_mm),
            "missing_passes": self.missing_passes,
            "phase_spread": _json_float(self.spread),
            "reliable_marks": self.reliable_marks,
            "vanished_knives": list(self.vanished_knives),
            "kinematic_cv": _json_float(self.kinematic_cv),
            "feed_per_pass_mm": _json_float(self.feed_per_pass_mm),
            "bdc_pitch_mm": _json_float(self.bdc_pitch_mm),
            "pitch_mm": _json_float(self.pitch_mm),
            "uniformity_cv": _json_float(self.uniformity_cv),
            "marks_cv": _json_float(self.marks_cv),
            "knife": list(self.mark_knife),
            "cut_pass_mm": (None if self.cut_feed is None
                            else [self.cut_feed.lo_mm, self.cut_feed.hi_mm]),
            "cut_feed_source": None if self.cut_feed is None else self.cut_feed.source.value,
        }


def _json_float(value: float) -> float | None:
    v = float(value)
    return v if math.isfinite(v) else None


def attribute(meas: Any, frame: Frame, snap: PlcSnapshot, rig: Any, *,
              pairs: PairFeedHistory | None = None, plc: FeedHistory | None = None,
              pass_tolerance: float = PASS_TOLERANCE) -> Attributed:
    """Attribute the marks to knife passes: widths per knife, pitch per knife pass.

    The fit's travel per pass is checked against the feed per pass when the field's marks
    were cut (:func:`controller.service.cut_feed.cut_feed` from ``pairs`` and ``plc``):
    outside that range widened by ``pass_tolerance`` the fit counted the passes per
    revolution wrong and the pair is refused. Without either history nothing is checked.

    Parameters
    ----------
    meas : Measurement
        ``bottoms_mm``, ``mark_widths_mm`` (shape (n,)), ``pitch_mm``, optional ``cusps_mm``
        (shape (n + 1,)), mm.
    frame : Frame
        The pair (``counts_a``, ``index_latch_counts``, ``speed_mm_s``).
    snap : PlcSnapshot
        The registers in force (``knives``, ``cutter_to_camera_mm``, ``counts_per_mm``, ...).
    rig : Rig
        ``camera.px_per_mm``, ``camera.cx``, ``encoder.counter_bits``.
    pairs : PairFeedHistory, optional
        The pairs so far, keyed by board position.
    plc : FeedHistory, optional
        The PLC's readings (where no pair brackets the cut).
    pass_tolerance : float
        ``[plausibility] pass_tolerance``.

    Returns
    -------
    Attributed

    Raises
    ------
    ValueError
        The marks do not line up with the knife passes (phase spread too large, two marks
        on one pass, too few bottoms inside their marks), do not fit each other, or the
        fit's travel per pass disagrees with the feed per pass at the cut.
    """
    cam = rig.camera
    bottoms = np.asarray(meas.bottoms_mm, dtype=float)
    widths = np.asarray(meas.mark_widths_mm, dtype=float)
    if bottoms.shape != widths.shape:
        raise ValueError(f"{bottoms.size} mark bottoms for {widths.size} widths")
    cusps = getattr(meas, "cusps_mm", None)
    if cusps is not None:
        cusps = np.asarray(cusps, dtype=float)
        if cusps.shape != (widths.size + 1,):
            cusps = None  # not the cusps of these marks: every bottom counts
    guide = expected_pitch_mm(frame, snap)
    pa = knife_phase.attribute_marks(
        bottoms,
        cusps,
        counts_a=int(frame.counts_a),
        index_latch_counts=int(frame.index_latch_counts),
        cutter_to_camera_mm=snap.cutter_to_camera_mm,
        counts_per_mm=snap.counts_per_mm,
        px_per_mm=cam.px_per_mm,
        cx_px=cam.cx,
        pass_guide_mm=guide,
        knives=snap.knives,
        min_inset_mm=MIN_BOTTOM_INSET_SAMPLES / cam.px_per_mm,
        counter_bits=rig.encoder.counter_bits,
    )
    if not pa.spread <= MAX_PHASE_SPREAD:
        raise ValueError(f"marks off the knife passes (phase spread {pa.spread:.2f})")
    cut = _cut_feed_of(bottoms, frame, snap, rig, pairs, plc)
    why = pass_disagreement(float(pa.pass_mm), cut, tolerance=pass_tolerance)
    if why is not None:
        raise ValueError(why)
    marks_pitch = float(meas.pitch_mm)
    missing = pa.missing
    if missing == 0:
        pitch = marks_pitch  # the mean mark width, as measured
    else:  # the feed per pass from the knives' BDCs: the widths' sum over the passes
        pitch = float(pa.pass_mm)  # spanned is off by the widened end marks' overhang
    per_knife = pa.knife_widths(widths)  # (checks the widths: finite, one per mark)
    knife = pa.knife.tolist()
    gone = _vanished(pa.passes_per_knife.tolist(), knife)  # (attribute_marks' own counts)
    if gone:
        per_knife[list(gone)] = 0.0  # no mark in any of its passes: width 0, not "unknown"
    return Attributed(
        knife_widths_mm=per_knife,
        pass_pitch_mm=pitch,
        missing_passes=missing,
        spread=float(pa.spread),
        reliable_marks=int(np.count_nonzero(pa.reliable)),
        mark_knife=tuple(knife),
        vanished_knives=gone,
        kinematic_cv=kinematic_cv(per_knife),
        feed_per_pass_mm=guide,
        marks_pitch_mm=marks_pitch,
        marks_cv=_marks_cv(meas, widths),
        bdc_pitch_mm=float(pa.pass_mm),
        knife_cv=(_knife_model_cv(widths.tolist(), knife, bottoms.tolist()) if missing == 0
                  else math.nan),  # (the bottoms checked finite by attribute_marks)
        cut_feed=cut,
    )


def _cut_feed_of(bottoms: np.ndarray, frame: Frame, snap: PlcSnapshot, rig: Any,
                 pairs: PairFeedHistory | None, plc: FeedHistory | None) -> CutFeed | None:
    """The feed per pass over the cut of the marks at ``bottoms`` (image A, mm).

    A mark at ``x`` was cut ``L + x - cx / px_per_mm`` of board travel before trigger A.
    """
    if (pairs is None and plc is None) or bottoms.size == 0:
        return None
    cam = rig.camera
    # the bottoms do not decrease (attribute_marks refuses them otherwise): first and last
    ends = [snap.cutter_to_camera_mm + float(x) - cam.cx / cam.px_per_mm
            for x in (bottoms[0], bottoms[-1])]
    return cut_feed(pairs, plc, counts=int(frame.counts_a), t_s=getattr(snap, "t_s", None),
                    knives=snap.knives, back_mm=(min(ends), max(ends)),
                    counts_per_mm=snap.counts_per_mm, counter_bits=rig.encoder.counter_bits)


def _marks_cv(meas: Any, widths: np.ndarray) -> float:
    """The measurement's CV over the marks found (from the widths if it reports none)."""
    cv = getattr(meas, "uniformity_cv", None)
    if cv is not None:
        return float(cv)
    mean = float(widths.mean()) if widths.size else math.nan
    return float(widths.std() / mean) if mean > 0 else math.nan


def attribute_or_reason(
    meas: Any, frame: Frame, snap: PlcSnapshot, rig: Any, *,
    pairs: PairFeedHistory | None = None, plc: FeedHistory | None = None,
    pass_tolerance: float = PASS_TOLERANCE,
) -> tuple[Attributed | None, str | None]:
    """:func:`attribute`, with a failure as its reason: ``(attributed, None)`` or ``(None, why)``.

    The reason reads ``"knife phase failed: ..."``; marks without the expected fields (a
    measurement of another shape) fail the same way. ``pairs``, ``plc``, ``pass_tolerance``:
    as :func:`attribute`'s.
    """
    try:
        return attribute(meas, frame, snap, rig, pairs=pairs, plc=plc,
                         pass_tolerance=pass_tolerance), None
    except ValueError as exc:
        return None, f"knife phase failed: {exc}"
    except (AttributeError, TypeError, LookupError, ArithmeticError) as exc:
        return None, f"knife phase failed: {exc_name(exc)}: {exc}"
