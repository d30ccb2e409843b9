"""One head's part of the operator page: its latest status and pair, its traces, its board strip.

A single machine is one head (the page's top-level ``status``, ``last``, ``trace``, ``board``);
a moulder has one :class:`HeadLive` per head (``heads`` in the page's snapshot). Not
thread-safe on its own: :class:`controller.web.live.LiveView` holds the lock.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

from controller.quality.schema import QualityClass
from controller.web.board_strip import BoardStrip

__all__ = ["TRACE_KEYS", "HeadLive", "quality_class_json"]

TRACE_KEYS = ("seq", "t_s", "board_m", "ok", "state", "pitch_mm", "uniformity_cv", "depth_um",
              "confidence", "feed_setpoint_mm_s")
"""The fields of a pair kept for the along-the-board traces."""


def _num(v: Any) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def quality_class_json(qc: QualityClass | None) -> dict[str, Any] | None:
    """The band the page draws (``name``, ``target_pitch_mm``, ``pitch_lo_mm``, ...)."""
    if qc is None:
        return None
    return {
        "name": qc.name,
        "target_pitch_mm": _num(qc.target_pitch_mm),
        "pitch_tolerance": _num(qc.pitch_tolerance),
        "pitch_lo_mm": _num(qc.target_pitch_mm * (1 - qc.pitch_tolerance)),
        "pitch_hi_mm": _num(qc.target_pitch_mm * (1 + qc.pitch_tolerance)),
        "uniformity_max_cv": _num(qc.uniformity_max_cv),
        "depth_max_um": _num(qc.depth_max_um),
    }


class HeadLive:
    """The latest of one head for the page.

    Parameters
    ----------
    history : int
        Pairs kept for the traces.
    quality_class : QualityClass, optional
        Its band.
    counts_per_mm : float, optional
        Encoder counts per mm of board (places the pairs along the board).
    config : dict, optional
        The head's configuration as the page shows it (``name``, ``face``, ``knives``,
        ``rpm``, ``rpm_min``, ``rpm_max``, ``target_pitch_mm``; a moulder's head).
    """

    def __init__(self, history: int, *, quality_class: QualityClass | None = None,
                 counts_per_mm: float | None = None,
                 config: dict[str, Any] | None = None) -> None:
        self.qc = quality_class
        self.counts_per_mm = counts_per_mm
        self.config = dict(config or {})
        self.status: dict[str, Any] | None = None
        self.last: dict[str, Any] | None = None
        self.trace: deque[dict[str, Any]] = deque(maxlen=history)
        self.counts0: int | None = None
        self.board = BoardStrip()
        self.plc: dict[str, Any] = {}

    def set_counts_per_mm(self, counts_per_mm: float | None) -> bool:
        """Take the encoder scale (ignored unless finite and > 0); whether it was taken."""
        if counts_per_mm is not None and math.isfinite(counts_per_mm) and counts_per_mm > 0:
            self.counts_per_mm = float(counts_per_mm)
            return True
        return False

    def take_status(self, d: dict[str, Any]) -> bool:
        """Take a status (:func:`controller.web.live.status_json`); whether it changed."""
        if d == self.status:
            return False
        self.status = d
        return True

    def take_result(self, d: dict[str, Any]) -> None:
        """Take one pair (:func:`controller.web.live.result_json`; ``board_m`` is added)."""
        d = dict(d)
        if self.counts0 is None:
            self.counts0 = d["counts_a"]
        cpm = self.counts_per_mm
        d["board_m"] = (None if cpm is None
                        else round((d["counts_a"] - self.counts0) / cpm / 1000.0, 5))
        self.last = d
        self.board.take(d)
        self.trace.append({k: d[k] for k in TRACE_KEYS})

    def json(self) -> dict[str, Any]:
        """``status``, ``last``, ``trace``, ``quality_class``, ``board`` (plain JSON).

        A moulder's head adds its configuration's keys and ``plc`` (the measured
        ``spindle_rpm``, ``knives``).
        """
        out = {**self.config} if self.config else {}
        out.update({
            "status": self.status,
            "last": self.last,
            "trace": list(self.trace),
            "quality_class": quality_class_json(self.qc),
            "board": self.board.json(),
        })
        if self.config:
            out["plc"] = dict(self.plc)
        return out
