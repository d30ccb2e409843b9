"""Mark-to-knife attribution stage: which knife pass cut each mark of a valid measurement.

The phase and the travel per pass come from the mark bottoms that lie inside their marks
(:func:`controller.knife_phase.attribute_marks`, guided by ``V / (n Z)``); a narrow mark whose
bottom sits on its cusp and a knife that left no mark do not spoil them. The result
(:class:`Attributed`) is what the loops get: widths per knife and the pitch per knife pass.
Pure: no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from controller import knife_phase
from controller.events import exc_name
from controller.measurement import expected_pitch_mm
from controller.plc_client import PlcSnapshot
from protocol.frames import Frame

MAX_PHASE_SPREAD = 0.15
"""Marks whose pass numbers spread more than this (in passes) are not attributed to knives."""
MIN_BOTTOM_INSET_SAMPLES = 1.0
"""A mark bottom closer than this (in profile samples, ``1 / px_per_mm``) to a cusp of its mark
was clipped there by the vision (narrow mark, BDC outside it) and does not set the phase."""


@dataclass(frozen=True)
class Attributed:
    """The marks of one valid pair attributed to knife passes (what the loops get).

    Attributes
    ----------
    knife_widths_mm : ndarray, shape (Z,)
        Width per knife and pass, a pass without a mark counting 0; NaN for a knife that
        left no mark in the field, mm.
    pass_pitch_mm : float
        Board travel per knife pass: the marks' width sum over the knife passes they span
        (the measured mean mark width when no knife is missing), mm. The feed loop holds this
        at the target; the uniformity loop scales its steps by it.
    missing_passes : int
        Knife passes in that span that left no mark.
    spread : float
        Phase spread of the reliable bottoms, passes.
    reliable_marks : int
        Marks whose bottoms lie inside them (these set the phase).
    """

    knife_widths_mm: np.ndarray
    pass_pitch_mm: float
    missing_passes: int
    spread: float
    reliable_marks: int

    def to_json(self) -> dict[str, Any]:
        """Plain-JSON summary for the quality record's ``extra["passes"]``."""
        return {
            "pass_pitch_mm": self.pass_pitch_mm,
            "missing_passes": self.missing_passes,
            "phase_spread": self.spread,
            "reliable_marks": self.reliable_marks,
        }


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
    pa = knife_phase.attribute_marks(
        bottoms,
        cusps,
        counts_a=int(frame.counts_a),
        index_latch_counts=int(frame.index_latch_counts),
        cutter_to_camera_mm=snap.cutter_to_camera_mm,
        counts_per_mm=snap.counts_per_mm,
        px_per_mm=cam.px_per_mm,
        cx_px=cam.cx,
        pass_guide_mm=expected_pitch_mm(frame, snap),
        knives=snap.knives,
        min_inset_mm=MIN_BOTTOM_INSET_SAMPLES / cam.px_per_mm,
        counter_bits=rig.encoder.counter_bits,
    )
    if not pa.spread <= MAX_PHASE_SPREAD:
        raise ValueError(f"marks off the knife passes (phase spread {pa.spread:.2f})")
    if pa.missing == 0:
        pitch = float(meas.pitch_mm)  # the mean mark width, as measured
    else:
        pitch = float(widths.sum()) / pa.n_passes
    return Attributed(
        knife_widths_mm=pa.knife_widths(widths),
        pass_pitch_mm=pitch,
        missing_passes=pa.missing,
        spread=float(pa.spread),
        reliable_marks=int(pa.reliable.sum()),
    )


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
