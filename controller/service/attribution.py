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
only the guide, since the marks were cut ``L / V`` earlier, at the feed of then. Pure: no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from controller.fieldbus.plc_protocol import PlcSnapshot
from controller.laws import knife_phase
from controller.service.events import exc_name
from controller.service.measurement import expected_pitch_mm
from protocol.frames import Frame

MAX_PHASE_SPREAD = 0.15
"""Marks whose pass numbers spread more than this (in passes) are not attributed to knives."""
MIN_BOTTOM_INSET_SAMPLES = 1.0
"""A mark bottom closer than this (in profile samples, ``1 / px_per_mm``) to a cusp of its mark
was clipped there by the vision (narrow mark, BDC outside it) and does not set the phase."""


def vanished_knives(passes_per_knife: Sequence[int], mark_knife: Sequence[int]) -> tuple[int, ...]:
    """Knives that had passes over the marks' span but left no mark there.

    Parameters
    ----------
    passes_per_knife : sequence of int, shape (Z,)
        Passes of each knife from the first mark's pass to the last mark's
        (:attr:`controller.laws.knife_phase.PassAttribution.passes_per_knife`).
    mark_knife : sequence of int, shape (n,)
        Knife of each mark, in ``[0, Z)``.

    Returns
    -------
    tuple of int
        The vanished knives, ascending (empty when every knife with a pass left a mark).
    """
    per = np.asarray(passes_per_knife)
    counts = per.tolist() if per.ndim == 1 else []
    if not counts or min(counts) < 0:
        raise ValueError(f"passes_per_knife must be counts >= 0, one per knife, got {per!r}")
    knife = np.asarray(mark_knife)
    marks = knife.tolist() if knife.ndim == 1 else None
    if marks is None or (marks and (min(marks) < 0 or max(marks) >= len(counts))):
        raise ValueError(f"mark_knife must hold knives in [0, {per.size}), got {knife!r}")
    marked = {int(k) for k in marks}
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
        Knives with passes in the span and no mark (:func:`vanished_knives`).
    kinematic_cv : float
        :func:`kinematic_cv` of ``knife_widths_mm``.
    feed_per_pass_mm : float
        ``V / (n Z)``: the encoder's board speed over the PLC's spindle speed times knives, at
        the pair (the guide of the attribution; the marks were cut ``L / V`` earlier), mm.
    marks_pitch_mm, marks_cv : float
        The measurement's own pitch (mean mark width) and CV over the marks found.
    bdc_pitch_mm : float
        Board travel per knife pass fitted to the reliable mark bottoms (the knives' BDCs),
        mm.
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

        The CV of the marks found, or the :attr:`kinematic_cv` if passes left no mark (a
        vanished knife counted as width 0).
        """
        return self.marks_cv if self.complete else self.kinematic_cv

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
            "knife": list(self.mark_knife),
        }


def _json_float(value: float) -> float | None:
    v = float(value)
    return v if math.isfinite(v) else None


def attribute(meas: Any, frame: Frame, snap: PlcSnapshot, rig: Any) -> Attributed:
    """Attribute the marks to knife passes: widths per knife, pitch per knife pass.

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

    Returns
    -------
    Attributed

    Raises
    ------
    ValueError
        The marks do not line up with the knife passes (phase spread too large, two marks
        on one pass, too few bottoms inside their marks) or do not fit each other.
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
    marks_pitch = float(meas.pitch_mm)
    if pa.missing == 0:
        pitch = marks_pitch  # the mean mark width, as measured
    else:  # the feed per pass from the knives' BDCs: the widths' sum over the passes
        pitch = float(pa.pass_mm)  # spanned is off by the widened end marks' overhang
    per_knife = pa.knife_widths(widths)
    gone = vanished_knives(pa.passes_per_knife, pa.knife)
    if gone:
        per_knife[list(gone)] = 0.0  # no mark in any of its passes: width 0, not "unknown"
    return Attributed(
        knife_widths_mm=per_knife,
        pass_pitch_mm=pitch,
        missing_passes=pa.missing,
        spread=float(pa.spread),
        reliable_marks=int(np.count_nonzero(pa.reliable)),
        mark_knife=tuple(pa.knife.tolist()),
        vanished_knives=gone,
        kinematic_cv=kinematic_cv(per_knife),
        feed_per_pass_mm=guide,
        marks_pitch_mm=marks_pitch,
        marks_cv=_marks_cv(meas, widths),
        bdc_pitch_mm=float(pa.pass_mm),
    )


def _marks_cv(meas: Any, widths: np.ndarray) -> float:
    """The measurement's CV over the marks found (from the widths if it reports none)."""
    cv = getattr(meas, "uniformity_cv", None)
    if cv is not None:
        return float(cv)
    mean = float(widths.mean()) if widths.size else math.nan
    return float(widths.std() / mean) if mean > 0 else math.nan


def attribute_or_reason(
    meas: Any, frame: Frame, snap: PlcSnapshot, rig: Any
) -> tuple[Attributed | None, str | None]:
    """:func:`attribute`, with a failure as its reason: ``(attributed, None)`` or ``(None, why)``.

    The reason reads ``"knife phase failed: ..."``; marks without the expected fields (a
    measurement of another shape) fail the same way.
    """
    try:
        return attribute(meas, frame, snap, rig), None
    except ValueError as exc:
        return None, f"knife phase failed: {exc}"
    except (AttributeError, TypeError, LookupError, ArithmeticError) as exc:
        return None, f"knife phase failed: {exc_name(exc)}: {exc}"
