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
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from core.checks import check_range
from vision.defects.detect import Defect, DefectKind

MIN_CONFIDENCE = 0.3
"""Defects less confident than this do not count toward the grade."""


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


def grade_board(pairs: Sequence[Sequence[Defect]], *,
                min_confidence: float = MIN_CONFIDENCE) -> Grade:
    """The D1666 grade of one board from its pairs' defects (rule 3 of the module doc).

    Parameters
    ----------
    pairs : sequence of sequence of Defect
        Each pair's defects, in the order measured.
    min_confidence : float, optional
        Less confident defects do not count.

    Returns
    -------
    Grade
    """
    if len(pairs) == 0:
        raise ValueError("pairs must hold at least one pair's defects, got none")
    grades = [grade_pair(p, min_confidence=min_confidence) for p in pairs]
    worst_i = max(range(len(grades)), key=lambda i: grades[i].grade)
    g = grades[worst_i].grade
    if g == 1:
        return Grade(1, f"defect-free: no defect found on {len(pairs)} pairs")
    hit = sum(1 for p in pairs if any(s >= 2 for s, _ in _counted(p, min_confidence)))
    reason = f"worst pair {worst_i}: {grades[worst_i].reason}"
    if hit > len(pairs) / 4 and g < 5:
        g += 1
        reason += f"; defects on {hit} of {len(pairs)} pairs: one step worse"
    return Grade(g, f"grade {g}: {reason}")
