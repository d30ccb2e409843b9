"""Planing defects and D1666 grades in a quality log: the summary, its text and two figures.

Records since schema version 7 carry each pair's defects and grade and their board's grade and
defect counts over its pairs so far (:mod:`controller.quality.defect_fields`): a board's last
record that looked for defects holds the whole board's. :func:`defect_summary` gives the
boards' grades and counts and the grade histograms, :func:`format_defect_summary` its lines
for ``planer report``, :func:`defect_map_figure` the defects of each board drawn where they
were (x along the board, y across it, by kind) and :func:`grade_histogram_figure` the pairs'
and boards' grades. Pure: records in, dict / text / matplotlib figure out. What they show:
``docs/quality_log.md``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from controller.quality.defect_fields import DEFECT_KINDS, along_board_mm
from controller.quality.schema import QualityRecord

__all__ = ["board_grades", "defect_map_figure", "defect_summary", "format_defect_summary",
           "grade_histogram_figure"]

#: Most boards drawn in the defect map (the last ones; a figure stays readable).
MAP_BOARDS = 12
#: Colour and marker of each kind in the defect map.
KIND_STYLE: dict[str, tuple[str, str]] = {
    "torn_grain": ("tab:red", "o"),
    "raised_grain": ("tab:orange", "^"),
    "fuzzy_grain": ("tab:olive", "s"),
    "chip_mark": ("tab:purple", "v"),
    "knife_nick": ("tab:blue", "D"),
    "chatter": ("tab:cyan", "|"),
    "snipe": ("tab:brown", "_"),
}
#: The extra key of a record holding image A's optical axis along the feed, mm (the defects'
#: ``x_mm`` minus it is their distance from the pair's ``board_position_mm`` toward the board's
#: leading end: :func:`controller.quality.defect_fields.along_board_mm`).
FRAME_CENTRE_KEY = "frame_centre_x_mm"


def _graded(records: Sequence[QualityRecord]) -> list[QualityRecord]:
    return [r for r in records if r.defects is not None]


def board_grades(records: Sequence[QualityRecord]) -> list[dict[str, Any]]:
    """Each board's grade and defect counts, from its last record that looked for defects.

    Returns
    -------
    list of dict
        In order of first appearance: ``board_id``, ``n_pairs`` (pairs looked at),
        ``grade``, ``grade_reason``, ``defect_counts`` (per kind), ``n_defects``.
    """
    last: dict[int, QualityRecord] = {}
    pairs: dict[int, int] = {}
    for r in _graded(records):
        if r.board_grade is None:
            continue
        last[r.board_id] = r
        pairs[r.board_id] = pairs.get(r.board_id, 0) + 1
    return [{"board_id": bid, "n_pairs": pairs[bid], "grade": r.board_grade,
             "grade_reason": r.board_grade_reason,
             "defect_counts": dict(r.board_defect_counts or {}),
             "n_defects": sum((r.board_defect_counts or {}).values())}
            for bid, r in last.items()]


def defect_summary(records: Sequence[QualityRecord]) -> dict[str, Any] | None:
    """The defects and grades over a log (``None`` when no record looked for defects).

    Returns
    -------
    dict or None
        ``n_pairs`` (records that looked for defects), ``n_defects``, ``defect_counts``
        (per kind over those pairs), ``pair_grades`` and ``board_grades`` (histograms:
        ``"1"`` .. ``"5"`` -> count), ``boards`` (:func:`board_grades`).
    """
    graded = _graded(records)
    if not graded:
        return None
    counts = dict.fromkeys(DEFECT_KINDS, 0)
    for r in graded:
        for d in r.defects or ():
            counts[d["kind"]] += 1
    boards = board_grades(graded)
    pair_hist = {str(g): 0 for g in range(1, 6)}
    for r in graded:
        pair_hist[str(r.grade)] += 1
    board_hist = {str(g): 0 for g in range(1, 6)}
    for b in boards:
        board_hist[str(b["grade"])] += 1
    return {"n_pairs": len(graded), "n_defects": sum(counts.values()), "defect_counts": counts,
            "pair_grades": pair_hist, "board_grades": board_hist, "boards": boards}


def _counts_text(counts: dict[str, int]) -> str:
    return ", ".join(f"{k} x{n}" for k, n in counts.items() if n) or "none"


def format_defect_summary(summary: dict[str, Any] | None) -> list[str]:
    """The lines of ``planer report``'s defects section (empty without defects looked for)."""
    if not summary:
        return []
    s = summary
    hist = "  ".join(f"{g}: {n}" for g, n in s["pair_grades"].items())
    lines = [f"Planing defects (ASTM D1666 grade 1 defect-free .. 5 very poor): "
             f"{s['n_defects']} on {s['n_pairs']} pairs looked at: "
             f"{_counts_text(s['defect_counts'])}",
             f"  pair grades  {hist}"]
    if s["boards"]:
        lines.append("  board grades " + "  ".join(f"{g}: {n}"
                                                     for g, n in s["board_grades"].items()))
        lines.append(f"  {'board':>6} {'pairs':>5} {'grade':>5}  defects")
        for b in s["boards"]:
            lines.append(f"  {b['board_id']:>6} {b['n_pairs']:>5} {b['grade']:>5}  "
                         f"{_counts_text(b['defect_counts'])}")
            lines.append(f"  {'':>6} {'':>5} {'':>5}  {b['grade_reason']}")
    return lines


def _along_board(rec: QualityRecord, x_mm: float) -> float:
    centre = rec.extra.get(FRAME_CENTRE_KEY)
    return along_board_mm(rec.board_position_mm, x_mm,
                          None if centre is None else float(centre))


def defect_map_figure(records: Sequence[QualityRecord]) -> Figure | None:
    """The defects of each board where they were (``None`` when no record looked for defects).

    One panel per board (the last :data:`MAP_BOARDS`), x along the board from its leading end
    (:func:`controller.quality.defect_fields.along_board_mm`), y across it (the
    defect's ``y_mm`` in image A), one marker and colour per kind, its extent as a box; the
    pairs looked at as grey ticks along the bottom; the board's grade in the title.
    """
    graded = [r for r in _graded(records) if r.board_id > 0]
    if not graded:
        return None
    by_board: dict[int, list[QualityRecord]] = {}
    for r in graded:
        by_board.setdefault(r.board_id, []).append(r)
    grades = {b["board_id"]: b for b in board_grades(graded)}
    shown = list(by_board)[-MAP_BOARDS:]
    fig = Figure(figsize=(10.0, 1.0 + 1.6 * len(shown)))
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(shown), 1, squeeze=False)[:, 0]
    seen: set[str] = set()
    for ax, bid in zip(axes, shown, strict=True):
        recs = by_board[bid]
        ax.plot([r.board_position_mm for r in recs], [0.0] * len(recs), "|", color="0.6",
                markersize=6)
        for r in recs:
            for d in r.defects or ():
                colour, marker = KIND_STYLE[d["kind"]]
                x = _along_board(r, d["x_mm"])
                ax.add_patch(_box(x, d, colour))
                ax.plot([x], [d["y_mm"]], marker, color=colour, markersize=5,
                        label=None if d["kind"] in seen else d["kind"].replace("_", " "))
                seen.add(d["kind"])
        g = grades.get(bid)
        ax.set_title(f"board {bid}: grade {g['grade'] if g else '-'}"
                     + (f" ({_counts_text(g['defect_counts'])})" if g else ""), fontsize=9,
                     loc="left")
        ax.set_ylabel("across, mm")
        ax.invert_yaxis()  # y from the image's top, as the camera sees it
    axes[-1].set_xlabel("along the board (from its leading end), mm")
    if seen:
        fig.legend(loc="upper right", fontsize=8, ncols=min(4, len(seen)))
    fig.suptitle("Planing defects per board", x=0.01, ha="left")
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    return fig


def _box(x: float, d: dict[str, Any], colour: str) -> Any:
    from matplotlib.patches import Rectangle

    w, h = max(d["length_mm"], 1.0), max(d["width_mm"], 0.5)
    return Rectangle((x - w / 2, d["y_mm"] - h / 2), w, h, facecolor=colour, alpha=0.2,
                     edgecolor=colour, linewidth=0.6)


def grade_histogram_figure(records: Sequence[QualityRecord]) -> Figure | None:
    """Bars of the pairs' and the boards' D1666 grades (``None`` without defects looked for)."""
    s = defect_summary(records)
    if s is None:
        return None
    fig = Figure(figsize=(7.0, 3.2))
    FigureCanvasAgg(fig)
    ax_p, ax_b = fig.subplots(1, 2)
    grades = [int(g) for g in s["pair_grades"]]
    for ax, hist, what in ((ax_p, s["pair_grades"], "pairs"), (ax_b, s["board_grades"],
                                                                 "boards")):
        counts = [hist[str(g)] for g in grades]
        ax.bar(grades, counts, color=["tab:green", "yellowgreen", "gold", "tab:orange",
                                      "tab:red"])
        for g, n in zip(grades, counts, strict=True):
            if n:
                ax.annotate(str(n), (g, n), ha="center", va="bottom", fontsize=8)
        ax.set_xticks(grades)
        ax.set_xlabel("D1666 grade (1 defect-free .. 5 very poor)")
        ax.set_ylabel(what)
        ax.set_title(f"{sum(counts)} {what}", fontsize=9)
    fig.suptitle("Grades of the pairs and the boards")
    fig.tight_layout()
    return fig
