"""Planing defects and the ASTM D1666 grade in the quality record (schema version 7).

Pure: the checks of the record's defect fields, the fields of one pair's measurement and the
running grade of the board under the camera (:class:`BoardGrades`). The grade rule itself is
:mod:`vision.defects.grading` (written in ``docs/quality_log.md``); this module only applies
it to what the log holds.

A pair's defects are the contract's JSON objects (``planer measure``'s ``defects``): ``kind``
(one of :data:`DEFECT_KINDS`), ``x_mm``, ``y_mm`` (centre in image A's undistorted frame from
its top-left corner, x along the feed), ``length_mm``, ``width_mm``, ``depth_um`` (or
``None``), ``confidence`` (0..1).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from vision.defects.detect import Defect, DefectKind
from vision.defects.grading import (
    MIN_CONFIDENCE,
    SNIPE_MIN_MIDDLE,
    Grade,
    board_rule,
    end_of_board,
    grade_pair,
    judged_pair,
    median,
    raw_sag_um,
    severity,
    snipe_note,
)

#: The defect kinds, in the order the counts, the report and the servers list them.
DEFECT_KINDS: tuple[str, ...] = tuple(k.value for k in DefectKind)
#: The keys of one defect object (the contract).
DEFECT_KEYS = ("kind", "x_mm", "y_mm", "length_mm", "width_mm", "depth_um", "confidence")


def check_defect(name: str, value: Any) -> dict[str, Any]:
    """One defect object checked and normalised (floats; ``depth_um`` ``None`` when unmeasured).

    Raises
    ------
    ValueError
        Not a mapping with exactly :data:`DEFECT_KEYS`, an unknown ``kind``, a non-finite
        position or size, a negative size or a confidence outside [0, 1]; ``name`` and the
        key are named.
    """
    if not isinstance(value, Mapping):
        raise ValueError(f"{name} must be a defect object, got {value!r:.80}")
    keys = set(value)
    if keys != set(DEFECT_KEYS):
        odd = sorted(keys ^ set(DEFECT_KEYS))
        raise ValueError(f"{name} must have the keys {', '.join(DEFECT_KEYS)}; "
                         f"{odd[0]!r} {'is unknown' if odd[0] in keys else 'is missing'}")
    kind = value["kind"]
    if kind not in DEFECT_KINDS:
        raise ValueError(f"{name}.kind must be one of {', '.join(DEFECT_KINDS)}, got {kind!r:.80}")
    out: dict[str, Any] = {"kind": kind}
    for key in ("x_mm", "y_mm", "length_mm", "width_mm", "depth_um", "confidence"):
        v = value[key]
        if v is None and key == "depth_um":
            out[key] = None
            continue
        try:
            f = float(v)
        except (TypeError, ValueError):
            raise ValueError(f"{name}.{key} must be a number, got {v!r:.80}") from None
        if not math.isfinite(f):
            if key == "depth_um":  # not measurable
                out[key] = None
                continue
            raise ValueError(f"{name}.{key} must be finite, got {v!r}")
        if key in ("length_mm", "width_mm") and f < 0:
            raise ValueError(f"{name}.{key} must be >= 0, got {v!r}")
        if key == "confidence" and not 0.0 <= f <= 1.0:
            raise ValueError(f"{name}.confidence must be in [0, 1], got {v!r}")
        out[key] = f
    return out


def check_defects(value: Any) -> tuple[dict[str, Any], ...] | None:
    """The record's ``defects``: ``None`` (not looked for) or a tuple of checked objects."""
    if value is None:
        return None
    if isinstance(value, (str, bytes, Mapping)) or not hasattr(value, "__iter__"):
        raise ValueError(f"defects must be a list of defect objects or None, got {value!r:.80}")
    return tuple(check_defect(f"defects[{i}]", d) for i, d in enumerate(value))


def check_counts(value: Any) -> dict[str, int] | None:
    """The record's ``board_defect_counts``: ``None`` or a count (>= 0) for every kind."""
    if value is None:
        return None
    if not isinstance(value, Mapping) or set(value) != set(DEFECT_KINDS):
        raise ValueError(f"board_defect_counts must give a count for each of "
                         f"{', '.join(DEFECT_KINDS)}, got {value!r:.120}")
    out: dict[str, int] = {}
    for kind in DEFECT_KINDS:
        n = value[kind]
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            if not (isinstance(n, float) and n.is_integer() and n >= 0):
                raise ValueError(f"board_defect_counts[{kind!r}] must be a count >= 0, "
                                 f"got {n!r}")
        out[kind] = int(n)
    return out


def check_grade(name: str, value: Any) -> int | None:
    """A D1666 grade 1..5 or ``None``."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != int(value) \
            or not 1 <= int(value) <= 5:
        raise ValueError(f"{name} must be a D1666 grade 1..5 or None, got {value!r:.80}")
    return int(value)


def check_defect_fields(rec: Any) -> dict[str, Any]:
    """The record's defect fields checked together (values to put; raises ``ValueError``).

    ``grade`` and ``grade_reason`` go with ``defects`` (all or none); ``board_grade``,
    ``board_grade_reason`` and ``board_defect_counts`` likewise, and only on a board
    (``board_id`` > 0).
    """
    out = {
        "defects": check_defects(rec.defects),
        "grade": check_grade("grade", rec.grade),
        "board_grade": check_grade("board_grade", rec.board_grade),
        "board_defect_counts": check_counts(rec.board_defect_counts),
    }
    for name in ("grade_reason", "board_grade_reason"):
        v = getattr(rec, name)
        if v is not None and (not isinstance(v, str) or not v):
            raise ValueError(f"{name} must be a non-empty string or None, got {v!r:.80}")
    pair = (out["defects"], out["grade"], rec.grade_reason)
    if any(v is None for v in pair) and any(v is not None for v in pair):
        raise ValueError("defects, grade and grade_reason go together: all or none, got "
                         f"defects {'set' if pair[0] is not None else None}, grade {pair[1]!r},"
                         f" grade_reason {'set' if pair[2] is not None else None}")
    board = (out["board_grade"], rec.board_grade_reason, out["board_defect_counts"])
    if any(v is None for v in board) and any(v is not None for v in board):
        raise ValueError("board_grade, board_grade_reason and board_defect_counts go together:"
                         " all or none")
    if out["board_grade"] is not None and rec.board_id == 0:
        raise ValueError("board_grade needs a board: board_id must be > 0, got 0")
    return out


def _defect(d: Mapping[str, Any]) -> Defect:
    return Defect(kind=DefectKind(d["kind"]), x_mm=d["x_mm"], y_mm=d["y_mm"],
                  length_mm=d["length_mm"], width_mm=d["width_mm"], depth_um=d["depth_um"],
                  confidence=d["confidence"])


def defects_of(record_defects: Sequence[Mapping[str, Any]]) -> list[Defect]:
    """The vision's :class:`~vision.defects.detect.Defect` objects of a record's defects."""
    return [_defect(d) for d in record_defects]


def count_kinds(pairs: Sequence[Sequence[Mapping[str, Any]]]) -> dict[str, int]:
    """Defects per kind over some pairs' defect objects (every kind, 0 when none)."""
    counts = dict.fromkeys(DEFECT_KINDS, 0)
    for pair in pairs:
        for d in pair:
            counts[d["kind"]] += 1
    return counts


def pair_fields(measurement: Any) -> dict[str, Any]:
    """The record's ``defects``, ``grade`` and ``grade_reason`` of a vision measurement.

    Parameters
    ----------
    measurement : object
        A ``vision.pipeline.Measurement`` (``defects``: tuple of Defect or ``None`` when the
        measurer did not look; ``grade``, ``grade_reason``).

    Returns
    -------
    dict
        Empty when the defects were not looked for.
    """
    found = getattr(measurement, "defects", None)
    if found is None or getattr(measurement, "grade", None) is None:
        return {}
    return {"defects": tuple(d.to_json() for d in found),
            "grade": int(measurement.grade), "grade_reason": str(measurement.grade_reason)}


def frame_centre_mm(measurement: Any) -> float | None:
    """Along-feed centre of image A in its frame, mm: the middle of the measured profile.

    The fallback of the optical axis (the rig's ``cx / px_per_mm``, which the service puts in
    ``FrameResult.extra["frame_centre_x_mm"]``); ``None`` without a profile.
    """
    try:
        x = np.asarray(measurement.x_mm, dtype=float).ravel()
        return round(float(0.5 * (x[0] + x[-1])), 2) if x.size else None
    except (AttributeError, TypeError, ValueError, IndexError):
        return None


def along_board_mm(board_position_mm: float, x_mm: float, centre_mm: float | None) -> float:
    """Where a defect was along its board, mm from the board's leading end.

    ``board_position_mm`` is image A's optical axis from the leading end; image x runs along
    the feed, toward the leading end (the rig's convention), so a defect ``x_mm - centre_mm``
    further along the image is that much nearer the leading end.
    """
    return board_position_mm - (x_mm - (0.0 if centre_mm is None else centre_mm))


class BoardGrades:
    """The running D1666 grade of the board under the camera, pair by pair.

    Records are made in pair order (one thread); each pair whose defects were looked for
    adds to its board (a board = the PLC's / simulator's ``board_id`` of the frame; 0 = no
    board, not graded). The board's grade after a pair is
    :func:`vision.defects.grading.grade_board` over the board's pairs so far with their places
    along it (as if the board ended there: its newest pairs are its trailing end), so the
    board's last record carries the whole board's grade and counts. Snipe is judged on the
    board (:func:`vision.defects.grading.judge_snipe`): only a pair near an end whose bend
    exceeds the board's middle pairs' counts; ``board_defect_counts`` counts those snipes (the
    pairs' own ``defects`` keep the raw bend each reported). Kept up pair by pair: a pair is
    graded once when it is known to be in the board's middle (or has no place), only the
    pairs near the ends (a few) again as the reference moves, so the cost does not grow with
    the board (the whole list re-graded cost 0.35 ms at the 67th pair of a board, 1.1 ms at
    the 200th). The tests hold it equal to ``grade_board`` of the whole list, reason included.
    """

    def __init__(self) -> None:
        self.board_id = 0
        self._reset()

    def _reset(self) -> None:
        self._n = 0
        self._placed = 0
        self._last: float | None = None  # the board's furthest pair's place, mm
        self._fixed: tuple[int, Grade] | None = None  # (index, grade): first worst settled pair
        self._fixed_hit = 0  # settled pairs with a counted defect of severity >= 2
        self._fixed_snipes = 0  # snipes of the unplaced pairs (raw, counted as reported)
        self._middle: list[float] = []  # the middle pairs' raw sags, sorted
        self._ends: list[tuple[int, float, list[Defect]]] = []  # (index, place, defects)
        self._counts = dict.fromkeys(DEFECT_KINDS, 0)  # every kind but snipe, as reported

    def add(self, board_id: int, defects: Sequence[Mapping[str, Any]] | None,
            position_mm: float | None = None) -> dict[str, Any]:
        """Add one pair; the record's board fields (empty without defects or board).

        Parameters
        ----------
        board_id : int
            The pair's board (0: none).
        defects : sequence of mapping or None
            The pair's checked defect objects (:func:`pair_fields`), ``None`` when not looked
            for (the pair adds nothing).
        position_mm : float, optional
            Image A's optical axis from the board's leading end, mm (the record's
            ``board_position_mm``); without it the pair's snipe counts as reported.

        Returns
        -------
        dict
            ``board_grade``, ``board_grade_reason``, ``board_defect_counts``, or empty.
        """
        if defects is None or board_id <= 0:
            return {}
        if board_id != self.board_id:
            self.board_id = board_id
            self._reset()
        found = defects_of(defects)
        for d in defects:
            if d["kind"] != DefectKind.SNIPE.value:
                self._counts[d["kind"]] += 1
        pos = None if position_mm is None or not math.isfinite(position_mm) else float(
            position_mm)
        i, self._n = self._n, self._n + 1
        if pos is None:
            self._settle(i, found)
            self._fixed_snipes += sum(1 for d in found if d.kind is DefectKind.SNIPE)
        else:
            self._placed += 1
            self._last = pos if self._last is None else max(self._last, pos)
            self._ends.append((i, pos, found))
            keep = []
            for e in self._ends:  # those no longer near an end are the board's middle
                if end_of_board(e[1], self._last):
                    keep.append(e)
                else:
                    self._settle(e[0], [d for d in e[2] if d.kind is not DefectKind.SNIPE])
                    bisect.insort(self._middle, raw_sag_um(e[2]))
            self._ends = keep
        board, snipes = self._board_grade()
        return {"board_grade": board.grade, "board_grade_reason": board.reason,
                "board_defect_counts": {**self._counts,
                                        DefectKind.SNIPE.value: self._fixed_snipes + snipes}}

    def _settle(self, i: int, found: Sequence[Defect]) -> None:
        """A pair whose judged defects no longer change: into the board's running figures."""
        g = grade_pair(found)
        if self._fixed is None or (g.grade, -i) > (self._fixed[1].grade, -self._fixed[0]):
            self._fixed = (i, g)  # the first worst (pairs settle out of order)
        if any(d.confidence >= MIN_CONFIDENCE and severity(
                d.kind, length_mm=d.length_mm, width_mm=d.width_mm, depth_um=d.depth_um) >= 2
               for d in found):
            self._fixed_hit += 1

    def _board_grade(self) -> tuple[Grade, int]:
        """``grade_board`` of the board so far on the running figures; the snipes at its ends."""
        ref = median(self._middle) if len(self._middle) >= SNIPE_MIN_MIDDLE else None
        worst, hit, snipes = self._fixed, self._fixed_hit, 0
        for i, _, found in self._ends:
            judged = judged_pair(found, end=True, reference_um=ref)
            g = grade_pair(judged)
            if worst is None or (g.grade, -i) > (worst[1].grade, -worst[0]):
                worst = (i, g)
            hit += any(d.confidence >= MIN_CONFIDENCE and severity(
                d.kind, length_mm=d.length_mm, width_mm=d.width_mm, depth_um=d.depth_um) >= 2
                for d in judged)
            snipes += sum(1 for d in judged if d.kind is DefectKind.SNIPE)
        note = snipe_note(ref, len(self._middle)) if self._placed else ""
        worst_i, g = worst  # type: ignore[misc]
        return board_rule(worst_i, g, hit, self._n, note), snipes
