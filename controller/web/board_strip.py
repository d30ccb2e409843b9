"""The operator page's board strip: the planing defects of the board under the camera, its grade.

:func:`defect_fields_json` adds a pair's board and defects to its page JSON
(:func:`controller.web.live.result_json`); :class:`BoardStrip` collects them per board (the
frame's ``board_id``, as the quality log) and grades the board so far by the same rule as the
log (:class:`controller.quality.defect_fields.BoardGrades`). Pure, not thread-safe: the
:class:`~controller.web.live.LiveView` calls it under its lock.
"""

from __future__ import annotations

import math
from typing import Any

from controller.quality.defect_fields import (
    BoardGrades,
    along_board_mm,
    frame_centre_mm,
    pair_fields,
)
from controller.service.frame_result import FrameResult

__all__ = ["MAX_STRIP_DEFECTS", "BoardStrip", "defect_fields_json"]

MAX_STRIP_DEFECTS = 200
"""Most defects of one board kept for the strip (the first ones; the counts count all): at
about 200 bytes of JSON each, at most 40 kB more in every page message."""


def _num(v: Any, digits: int) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return round(f, digits) if math.isfinite(f) else None


def defect_fields_json(r: FrameResult) -> dict[str, Any]:
    """The page JSON's board and defect keys of one pair.

    Returns
    -------
    dict
        ``board_id`` (0: none), ``board_position_mm`` (image A's centre from the board's
        leading end, or ``None``), ``defects`` (the contract's objects, ``None`` when not
        looked for), ``grade`` and ``grade_reason`` (``None`` likewise) and
        ``frame_centre_x_mm`` (image A's along-feed centre in its frame, ``None`` without).
    """
    board = r.extra.get("board_id")
    out: dict[str, Any] = {
        "board_id": board if isinstance(board, int) and board > 0 else 0,
        "board_position_mm": _num(r.extra.get("board_position_mm"), 2),
        "defects": None, "grade": None, "grade_reason": None, "frame_centre_x_mm": None,
    }
    m = r.surface  # the measurement, or a refused pair's defects found all the same
    found = pair_fields(m) if m is not None else {}
    if found:
        centre = _num(r.extra.get("frame_centre_x_mm"), 3)
        out.update(defects=list(found["defects"]), grade=found["grade"],
                   grade_reason=found["grade_reason"],
                   frame_centre_x_mm=centre if centre is not None else frame_centre_mm(m))
    return out


class BoardStrip:
    """The current board's defects along it and its grade so far; the last board's grade."""

    def __init__(self) -> None:
        self._grades = BoardGrades()
        self._current: dict[str, Any] | None = None
        self._last: dict[str, Any] | None = None

    def take(self, d: dict[str, Any]) -> None:
        """Take one pair's page JSON (with :func:`defect_fields_json`'s keys)."""
        board, defects = d.get("board_id") or 0, d.get("defects")
        if defects is None or board <= 0:
            return
        if self._current is not None and self._current["board_id"] != board:
            self._last = self._current
            self._current = None
        graded = self._grades.add(board, defects, d.get("board_position_mm"))
        cur = self._current
        if cur is None:
            cur = self._current = {"board_id": board, "pairs": 0, "from_mm": None,
                                   "to_mm": None, "defects": []}
        cur.update(grade=graded["board_grade"], grade_reason=graded["board_grade_reason"],
                   defect_counts=graded["board_defect_counts"], pair_grade=d.get("grade"))
        cur["pairs"] += 1
        pos = d.get("board_position_mm")
        if pos is None:
            return
        cur["from_mm"] = pos if cur["from_mm"] is None else min(cur["from_mm"], pos)
        cur["to_mm"] = pos if cur["to_mm"] is None else max(cur["to_mm"], pos)
        centre = d.get("frame_centre_x_mm")
        for item in defects:
            if len(cur["defects"]) >= MAX_STRIP_DEFECTS:
                break
            along = along_board_mm(pos, item["x_mm"], centre)
            cur["defects"].append({**item, "board_x_mm": round(along, 2), "seq": d.get("seq")})

    def json(self) -> dict[str, Any]:
        """The strip as JSON: ``{"current": ..., "last": ...}``.

        Each ``None`` or ``board_id``, ``pairs``, ``from_mm`` / ``to_mm`` (the pairs' span
        along the board), ``grade``,
        ``grade_reason``, ``defect_counts`` (per kind), ``pair_grade`` (the newest pair's) and
        ``defects`` (each the contract's object with ``board_x_mm`` along the board and the
        pair's ``seq``).
        """
        return {"current": self._current, "last": self._last}
