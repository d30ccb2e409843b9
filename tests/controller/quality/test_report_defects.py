"""``planer report`` on planing defects: each board's D1666 grade, the defect map, the histogram.

A log whose records carry defects (schema version 7) gets the per-board grades and defect counts
in its text and ``--json``, the pairs' and boards' grade histograms, a defect-map figure (each
board's defects where they were, by kind) and a grade-histogram figure; a log without defects
gets neither.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from controller.quality.defect_fields import DEFECT_KINDS, BoardGrades
from controller.quality.defect_report import board_grades, defect_map_figure, defect_summary
from controller.quality.log import QualityLog, QualityRecord, utc_iso
from controller.quality.report import build_figures, format_summary, summarise
from planer.cli import main
from vision.defects.detect import Defect, DefectKind
from vision.defects.grading import grade_board, grade_pair

TORN = Defect(DefectKind.TORN_GRAIN, 30.0, 12.0, 12.0, 4.0, 250.0, 0.9)  # severity 4
RAISED = Defect(DefectKind.RAISED_GRAIN, 20.0, 25.0, 18.0, 0.5, 20.0, 0.6)  # severity 2
CHIP = Defect(DefectKind.CHIP_MARK, 10.0, 5.0, 3.0, 3.0, 30.0, 0.5)  # severity 1
#: Board 1 clean, board 2 a torn pit and raised grain, board 3 a chip mark; 8 pairs each.
PLAN = {1: {}, 2: {2: [TORN], 5: [RAISED, CHIP]}, 3: {6: [CHIP]}}


def _records() -> tuple[list[QualityRecord], dict[int, list[list[Defect]]]]:
    grades = BoardGrades()
    recs, truth = [], {}
    i = 0
    for board, hits in PLAN.items():
        for k in range(8):
            found = hits.get(k, [])
            truth.setdefault(board, []).append(found)
            g = grade_pair(found)
            objs = tuple(d.to_json() for d in found)
            recs.append(QualityRecord(
                t_s=0.5 * i, wall_time=utc_iso(1.7e9 + 0.5 * i), seq=i, board_id=board,
                board_position_mm=500.0 * k + 40.0, ok=True, pitch_mm=1.5, uniformity_cv=0.01,
                mark_widths_mm=(1.5,) * 4, depth_um=4.0, defects=objs, grade=g.grade,
                grade_reason=g.reason, extra={"frame_centre_x_mm": 22.0},
                **grades.add(board, objs)))
            i += 1
    return recs, truth


def test_each_boards_grade_is_the_rule_over_its_pairs():
    recs, truth = _records()
    boards = board_grades(recs)
    assert [b["board_id"] for b in boards] == [1, 2, 3]
    for b in boards:
        want = grade_board(truth[b["board_id"]])
        assert (b["grade"], b["grade_reason"]) == (want.grade, want.reason)
        assert b["n_pairs"] == 8
    assert [b["grade"] for b in boards] == [1, 5, 2]
    assert boards[1]["defect_counts"] == {**dict.fromkeys(DEFECT_KINDS, 0), "torn_grain": 1,
                                          "raised_grain": 1, "chip_mark": 1}
    s = defect_summary(recs)
    assert s["n_pairs"] == 24 and s["n_defects"] == 4
    assert s["board_grades"] == {"1": 1, "2": 1, "3": 0, "4": 0, "5": 1}
    assert s["pair_grades"] == {"1": 21, "2": 1, "3": 1, "4": 0, "5": 1}


def test_the_text_names_each_boards_grade_and_why():
    recs, _ = _records()
    text = format_summary(summarise(recs))
    section = text[text.index("Planing defects"):]
    assert "4 on 24 pairs looked at: torn_grain x1, raised_grain x1, chip_mark x2" in section
    rows = [line.split() for line in section.splitlines()
            if line.strip() and line.split()[0] in ("1", "2", "3")]
    assert [r[:3] for r in rows] == [["1", "8", "1"], ["2", "8", "5"], ["3", "8", "2"]]
    assert "grade 5: worst pair 2: grade 5: worst: torn_grain" in section


def test_the_map_draws_each_defect_where_it_was_on_its_board():
    recs, _ = _records()
    fig = defect_map_figure(recs)
    axes = fig.axes
    assert len(axes) == 3 and axes[1].get_title(loc="left").startswith("board 2: grade 5")
    # board 2: the torn pit of pair 2, 8 mm past the optical axis (22 mm) in image A: 8 mm
    # nearer the leading end than the pair's 1040 mm; 12 mm across
    points = [(line.get_xdata()[0], line.get_ydata()[0]) for line in axes[1].get_lines()
              if line.get_label() == "torn grain"]
    assert points == [(pytest.approx(1032.0), pytest.approx(12.0))]
    assert defect_map_figure([QualityRecord(t_s=0, wall_time=utc_iso(1.7e9), seq=0,
                                            board_id=1, board_position_mm=0, ok=True)]) is None


def test_planer_report_json_and_figures(tmp_path, capsys):
    recs, _ = _records()
    log_path = tmp_path / "q.sqlite"
    with QualityLog(log_path) as log:
        for r in recs:
            log.append(r)
    assert main(["report", str(log_path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    d = out["defects"]
    assert [(b["board_id"], b["grade"]) for b in d["boards"]] == [(1, 1), (2, 5), (3, 2)]
    assert d["defect_counts"]["chip_mark"] == 2
    assert set(out["figures"]) >= {"defect_map", "grades"}
    figs = build_figures(recs)
    hist = figs["grades"].axes[1]  # the boards' grades: one each of 1, 2, 5
    assert [p.get_height() for p in hist.patches] == [1, 1, 0, 0, 1]


def test_a_log_without_defects_has_no_defect_section():
    rec = QualityRecord(t_s=0, wall_time=utc_iso(1.7e9), seq=0, board_id=1,
                        board_position_mm=0, ok=True, pitch_mm=1.5, depth_um=np.float64(4.0))
    s = summarise([rec])
    assert s["defects"] is None and "Planing defects" not in format_summary(s)
    assert "defect_map" not in build_figures([rec]) and "grades" not in build_figures([rec])
