"""The ASTM D1666 grade of a pair and of a board from the defects found (the rule, once).

ASTM D1666 grades a planed surface 1 (defect-free) to 5 (very poor).  The rule here, written in
``docs/quality_log.md`` ("Planing defects and the D1666 grade"):

1. every defect gets a *severity* from its kind and size (:func:`severity`):

   ============== ================================== ==================================
   kind           severity 1 (slight) / 2 (moderate)  3 (severe) / 4 (very severe)
   ============== ================================== ==================================
   chatter        1; 2 at >= 1.5 um amplitude         --
   chip_mark      1 below 50 um deep; 2 below 100 um  3 at >= 100 um
   knife_nick     2                                   3 at >= 25 um
   raised_grain   2                                   3 at >= 30 um
   fuzzy_grain    2                                   3 over >= 100 mm^2
   snipe          2                                   3 at >= 20 um of sag
   torn_grain     --                                  3; 4 at >= 10 mm long or >= 300 um
   ============== ================================== ==================================

2. a pair's grade is 1 without defects, else 1 + the worst severity, one step worse when three
   or more defects of severity >= 2 are on it; at most 5;
3. a board's grade is its worst pair's, one step worse when defects of severity >= 2 are on more
   than a quarter of its pairs (widespread); at most 5.

Defects reported with a confidence below ``min_confidence`` (0.3) do not count.

*Snipe on a board* (:func:`judge_snipe`). Snipe is the first or last 50-150 mm of a board cut
deeper. One pair's detector sees only a bow of its field along the feed, and the rig's own
optics bend every field alike (a light's fall-off cannot be told from a bow without a flat
field), so a pair reports a *raw* bend. Where the pairs' places along their board are known
(``positions_mm``: image A's optical axis from the board's leading end), the board decides: the
*reference* is the median raw sag of the board's middle pairs (the pairs more than
:data:`SNIPE_END_MM` from either end; a pair without a snipe counts 0); a pair within
:data:`SNIPE_END_MM` of an end is sniped when its raw sag exceeds the reference by the
*margin* (:func:`snipe_margin_um`), the excess its depth; a middle pair's bend is the rig's and
does not count; with fewer than :data:`SNIPE_MIN_MIDDLE` middle pairs snipe is not judged. A
pair whose place is unknown (``None``) keeps its raw snipe in the board's grade. A pair's
own grade (:func:`pair_grade`: what a measurement carries) leaves snipe to its board: it
cannot tell snipe from the rig's bow.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from core.checks import check_range
from vision.defects.detect import Defect, DefectKind

MIN_CONFIDENCE = 0.3
"""Defects less confident than this do not count toward the grade."""
SNIPE_END_MM = 200.0
"""A pair whose optical axis is within this of a board's end can show snipe (the first or last
50-150 mm of the board cut deeper, seen in a field of ~50 mm), mm."""
SNIPE_MIN_MIDDLE = 3
"""Middle pairs a board needs before its ends' snipe is judged (the reference bow)."""
SNIPE_MARGIN_UM = 3.0
"""Least excess of an end pair's sag over the reference that is snipe, um (the detector's own
``DefectSettings.snipe_um``)."""
SNIPE_MARGIN_FRAC = 0.1
"""... or this share of the reference, whichever is larger: the rig's bow varies a little with
the machine's state (on the simulator's 86 um bow, 85.2-88.7 um on the first board of a run)."""


@dataclass(frozen=True)
class Grade:
    """A D1666 grade (1 defect-free ... 5 very poor) and why."""

    grade: int
    reason: str


def severity(kind: DefectKind, *, length_mm: float, width_mm: float,
             depth_um: float | None) -> int:
    """Severity 1 (slight) ... 4 (very severe) of one defect (the table in the module doc).

    Parameters
    ----------
    kind : DefectKind
    length_mm, width_mm : float
        Extent along and across the feed, mm.
    depth_um : float or None
        Depth (ridge height, chatter amplitude, snipe sag: their magnitude), um; ``None``
        when not measured (the size alone decides).
    """
    d = 0.0 if depth_um is None else abs(float(depth_um))
    if kind is DefectKind.CHATTER:
        return 2 if d >= 1.5 else 1
    if kind is DefectKind.CHIP_MARK:
        return 3 if d >= 100.0 else (2 if d >= 50.0 else 1)
    if kind is DefectKind.KNIFE_NICK:
        return 3 if d >= 25.0 else 2
    if kind is DefectKind.RAISED_GRAIN:
        return 3 if d >= 30.0 else 2
    if kind is DefectKind.FUZZY_GRAIN:
        return 3 if length_mm * width_mm >= 100.0 else 2
    if kind is DefectKind.SNIPE:
        return 3 if d >= 20.0 else 2
    if kind is DefectKind.TORN_GRAIN:
        return 4 if max(length_mm, width_mm) >= 10.0 or d >= 300.0 else 3
    raise ValueError(f"kind must be a DefectKind, got {kind!r}")


def _counted(defects: Iterable[Defect], min_confidence: float) -> list[tuple[int, Defect]]:
    return [(severity(d.kind, length_mm=d.length_mm, width_mm=d.width_mm, depth_um=d.depth_um),
             d) for d in defects if d.confidence >= min_confidence]


def _describe(sev: int, d: Defect) -> str:
    words = {1: "slight", 2: "moderate", 3: "severe", 4: "very severe"}[sev]
    size = f"{d.length_mm:.1f} x {d.width_mm:.1f} mm"
    if d.depth_um is not None:
        size += f", {abs(d.depth_um):.1f} µm"
    return f"{d.kind.value} {size} at x={d.x_mm:.1f} mm, y={d.y_mm:.1f} mm ({words})"


def grade_pair(defects: Sequence[Defect], *, min_confidence: float = MIN_CONFIDENCE) -> Grade:
    """The D1666 grade of one pair from its defects (rule 2 of the module doc).

    Parameters
    ----------
    defects : sequence of Defect
        The pair's defects (:func:`vision.defects.detect.detect_defects`).
    min_confidence : float, optional
        Less confident defects do not count.

    Returns
    -------
    Grade
    """
    check_range("min_confidence", min_confidence, 0.0, 1.0)
    counted = _counted(defects, min_confidence)
    if not counted:
        return Grade(1, "defect-free: no defect found")
    worst_sev, worst = max(counted, key=lambda t: (t[0], t[1].confidence))
    g = 1 + worst_sev
    reason = f"worst: {_describe(worst_sev, worst)}"
    many = sum(1 for s, _ in counted if s >= 2)
    if many >= 3 and g < 5:
        g += 1
        reason += f"; {many} defects of severity >= 2: one step worse"
    return Grade(min(g, 5), f"grade {min(g, 5)}: {reason}")


def pair_grade(defects: Sequence[Defect], *, min_confidence: float = MIN_CONFIDENCE) -> Grade:
    """A pair's own D1666 grade: :func:`grade_pair` of its defects but snipe.

    One pair cannot tell snipe from the rig's bow (its detector reports a *raw* bend: the
    module doc), so the pair's own grade leaves snipe to its board (:func:`judge_snipe`,
    :func:`grade_board`); the reason names the raw bend it left. This is the grade a
    measurement carries (``Measurement.grade``, ``grade_reason``; ``planer measure``'s JSON and
    each quality record); the pair's ``defects`` keep the raw bend for the board to judge.

    Parameters
    ----------
    defects : sequence of Defect
        The pair's defects as its detector reported them.
    min_confidence : float, optional
        Less confident defects do not count.

    Returns
    -------
    Grade
    """
    check_range("min_confidence", min_confidence, 0.0, 1.0)
    g = grade_pair([d for d in defects if d.kind is not DefectKind.SNIPE],
                   min_confidence=min_confidence)
    sag = raw_sag_um(defects, min_confidence)
    if sag <= 0.0:
        return g
    return Grade(g.grade, f"{g.reason}; a bend of {sag:.1f} µm along the feed, judged on the "
                          f"board (one pair cannot tell it from the rig's bow)")


def raw_sag_um(defects: Iterable[Defect], min_confidence: float = MIN_CONFIDENCE) -> float:
    """The deepest counted snipe's sag of one pair, um (0 without one): its raw bend."""
    return max((abs(d.depth_um) for d in defects if d.kind is DefectKind.SNIPE
                and d.depth_um is not None and d.confidence >= min_confidence), default=0.0)


def snipe_margin_um(reference_um: float) -> float:
    """Least excess over the board's reference sag that an end pair's snipe needs, um."""
    return max(SNIPE_MARGIN_UM, SNIPE_MARGIN_FRAC * abs(reference_um))


def median(values: Sequence[float]) -> float:
    """The median of sorted ``values`` (the mean of the middle two of an even count)."""
    n = len(values)
    return float(values[n // 2]) if n % 2 else 0.5 * (values[n // 2 - 1] + values[n // 2])


def end_of_board(position_mm: float, last_mm: float) -> bool:
    """Whether a pair at ``position_mm`` is near an end of its board.

    ``last_mm`` is the board's last pair's place (both image A's optical axis from the leading
    end, mm).
    """
    return position_mm <= SNIPE_END_MM or position_mm >= last_mm - SNIPE_END_MM


def judged_pair(defects: Sequence[Defect], *, end: bool, reference_um: float | None,
                min_confidence: float = MIN_CONFIDENCE) -> list[Defect]:
    """One placed pair's defects with its snipe judged on its board.

    Parameters
    ----------
    defects : sequence of Defect
        The pair's defects as its detector reported them (a raw bend as ``snipe``).
    end : bool
        The pair is within :data:`SNIPE_END_MM` of an end of its board.
    reference_um : float or None
        The board's reference sag (``None``: too few middle pairs, snipe not judged).

    Returns
    -------
    list of Defect
        The other defects as reported; a snipe only on an end pair whose sag exceeds the
        reference by the margin, its depth the excess.
    """
    out = [d for d in defects if d.kind is not DefectKind.SNIPE]
    if not end or reference_um is None:
        return out
    excess = raw_sag_um(defects, min_confidence) - reference_um
    if excess < snipe_margin_um(reference_um):
        return out
    raw = max((d for d in defects if d.kind is DefectKind.SNIPE and d.depth_um is not None
               and d.confidence >= min_confidence), key=lambda d: abs(d.depth_um or 0.0))
    conf = min(1.0, excess / (2 * SNIPE_MARGIN_UM))
    return [*out, dataclasses.replace(raw, depth_um=excess, confidence=conf)]


def snipe_note(reference_um: float | None, n_middle: int) -> str:
    """The board grade's note on how its snipe was judged."""
    if reference_um is None:
        return (f"snipe not judged: {n_middle} middle pairs, {SNIPE_MIN_MIDDLE} needed for "
                f"the rig's bow")
    return (f"snipe over the middle's bow of {reference_um:.1f} µm ({n_middle} pairs) + "
            f"{snipe_margin_um(reference_um):.1f} µm")


def judge_snipe(pairs: Sequence[Sequence[Defect]], positions_mm: Sequence[float | None], *,
                min_confidence: float = MIN_CONFIDENCE) -> tuple[list[list[Defect]], str]:
    """A board's pairs with their snipe judged on the board (the module doc's rule).

    Parameters
    ----------
    pairs : sequence of sequence of Defect
        Each pair's defects as reported, in the order measured.
    positions_mm : sequence of float or None
        Each pair's image A optical axis from the board's leading end, mm (``None`` or not
        finite: not placed, its raw snipe kept).

    Returns
    -------
    tuple
        ``(pairs, note)``: the judged pairs (:func:`judged_pair`) and how (:func:`snipe_note`;
        empty when no pair is placed).
    """
    if len(positions_mm) != len(pairs):
        raise ValueError(f"positions_mm must give one place per pair ({len(pairs)}), "
                         f"got {len(positions_mm)}")
    pos = [float(p) if p is not None and math.isfinite(p) else None for p in positions_mm]
    if all(p is None for p in pos):
        return [list(p) for p in pairs], ""
    last = max(p for p in pos if p is not None)
    placed = [p is not None for p in pos]
    ends = [p is not None and end_of_board(p, last) for p in pos]
    middle = sorted(raw_sag_um(d, min_confidence) for d, ok, e
                    in zip(pairs, placed, ends, strict=True) if ok and not e)
    ref = median(middle) if len(middle) >= SNIPE_MIN_MIDDLE else None
    out = [judged_pair(d, end=e, reference_um=ref, min_confidence=min_confidence) if ok
           else list(d) for d, ok, e in zip(pairs, placed, ends, strict=True)]
    return out, snipe_note(ref, len(middle))


def grade_board(pairs: Sequence[Sequence[Defect]], *,
                positions_mm: Sequence[float | None] | None = None,
                min_confidence: float = MIN_CONFIDENCE) -> Grade:
    """The D1666 grade of one board from its pairs' defects (rule 3 of the module doc).

    Parameters
    ----------
    pairs : sequence of sequence of Defect
        Each pair's defects, in the order measured.
    positions_mm : sequence of float or None, optional
        Each pair's place along the board (image A's optical axis from its leading end, mm):
        snipe is judged on the board (:func:`judge_snipe`). Without it every pair's raw snipe
        counts as reported.
    min_confidence : float, optional
        Less confident defects do not count.

    Returns
    -------
    Grade
    """
    if len(pairs) == 0:
        raise ValueError("pairs must hold at least one pair's defects, got none")
    note = ""
    if positions_mm is not None:
        pairs, note = judge_snipe(pairs, positions_mm, min_confidence=min_confidence)
    grades = [grade_pair(p, min_confidence=min_confidence) for p in pairs]
    worst_i = max(range(len(grades)), key=lambda i: grades[i].grade)
    hit = sum(1 for p in pairs if any(s >= 2 for s, _ in _counted(p, min_confidence)))
    return board_rule(worst_i, grades[worst_i], hit, len(pairs), note)


def board_rule(worst_i: int, worst: Grade, hit: int, n: int, note: str = "") -> Grade:
    """Rule 3 on a board's figures: its first worst pair, the pairs hit, the pairs, a note."""
    tail = f"; {note}" if note else ""
    g = worst.grade
    if g == 1:
        return Grade(1, f"defect-free: no defect found on {n} pairs{tail}")
    reason = f"worst pair {worst_i}: {worst.reason}"
    if hit > n / 4 and g < 5:
        g += 1
        reason += f"; defects on {hit} of {n} pairs: one step worse"
    return Grade(g, f"grade {g}: {reason}{tail}")
