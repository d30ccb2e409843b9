"""Frame intake: the first stage a pair goes through in the service.

It notes the pair's place in the camera's sequence (gaps are pairs that never reached the
service: reported, counted), maps the camera's clock (trigger A's machine time) onto the service
clock, and makes the frame's metadata fit for a quality record (odd values are noted, never
fatal). Pure bookkeeping: no I/O, time passed in.
"""

from __future__ import annotations

import math
from typing import Any

from controller.service.events import EventKind, EventLog
from protocol.frames import Frame


def finite_or_none(v: Any) -> float | None:
    """``float(v)`` if that is a finite number, else ``None``."""
    if v is None:
        return None
    try:
        f = float(v)
    except (TypeError, ValueError, OverflowError):
        return None
    return f if math.isfinite(f) else None


def int_or(v: Any, default: int) -> int:
    """``int(v)``, or ``default`` when ``v`` is not a number."""
    try:
        return int(v)
    except (TypeError, ValueError, OverflowError):
        return default


def frame_metadata(frame: Frame) -> tuple[dict[str, Any], dict[str, Any]]:
    """The record's frame fields, made valid (``t_s``, ``seq``, ``board_*``), and the odd ones.

    Returns
    -------
    fields : dict
        ``t_s`` (s), ``seq``, ``board_id``, ``board_position_mm`` (mm); an unusable value is
        replaced by 0.
    odd : dict
        ``repr`` of each replaced value, by field name.
    """
    out: dict[str, Any] = {}
    odd: dict[str, Any] = {}
    for name, kind, default in (
        ("t_s", float, 0.0),
        ("seq", int, 0),
        ("board_id", int, 0),
        ("board_position_mm", float, 0.0),
    ):
        raw = getattr(frame, name, None)
        try:
            v = kind(raw)
            good = math.isfinite(v) if kind is float else v >= 0
        except (TypeError, ValueError, OverflowError):
            good = False
        if good:
            out[name] = v
        else:
            out[name] = default
            odd[name] = repr(raw)
    return out, odd


class FrameIntake:
    """Sequence gaps and the camera clock of the pairs, in the order they arrive.

    Parameters
    ----------
    report : EventLog
        Where gaps (``PAIRS_MISSED``, counter ``missed``) and a camera clock that went back
        (``CAMERA_CLOCK_WENT_BACK``) are reported.
    """

    def __init__(self, report: EventLog) -> None:
        self._report = report
        self._machine_offset_s: float | None = None  # service clock minus machine time
        self._last_frame_t: float | None = None
        self._last_seq: int | None = None

    def arrive(self, frame: Frame, t_arr: float) -> float:
        """Take one pair arriving at service time ``t_arr``; service time of its trigger A.

        The offset is the lowest arrival delay seen (exact in simulated time). When the
        camera's clock goes backwards (a restarted camera or simulator) the mapping starts
        afresh; otherwise every later pair would look ages old and the feed loop would never
        learn again.

        Returns
        -------
        float
            Service time at which the pair was taken (never after ``t_arr``), s.
        """
        self._note_seq(frame, t_arr)
        ft = finite_or_none(frame.t_s)
        if ft is None:
            return t_arr
        if self._last_frame_t is not None and ft < self._last_frame_t:
            self._machine_offset_s = None
            self._report.emit(t_arr, EventKind.CAMERA_CLOCK_WENT_BACK,
                              f"camera clock went back by {self._last_frame_t - ft:.3f} s")
        self._last_frame_t = ft
        off = t_arr - ft
        if self._machine_offset_s is None or off < self._machine_offset_s:
            self._machine_offset_s = off
        return min(ft + self._machine_offset_s, t_arr)

    def _note_seq(self, frame: Frame, t: float) -> None:
        """Report a gap in the camera's sequence with its numbers (files it skipped: the spool)."""
        try:
            seq = int(frame.seq)
        except (TypeError, ValueError, OverflowError):
            return
        last, self._last_seq = self._last_seq, seq
        if last is not None and seq > last + 1:
            n = seq - last - 1
            self._report.count("missed", n)
            self._report.emit(t, EventKind.PAIRS_MISSED,
                              f"{n} sequence number(s) without a pair: the camera's seq jumped "
                              f"from {last} to {seq}")
