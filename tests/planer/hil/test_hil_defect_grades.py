"""HIL with wood defects and the defect detector on: the log's per-board grades against the truth.

The ``defects`` scenario (torn and raised grain on every other board, config/sim_defects.toml;
``defects = true``: the service looks for planing defects on every pair), 10 m of board in
process on simulated time. The run's summary counts the defects per kind (found and true) and
the grades; the quality log's board grades are the grading rule over the log's own pairs (their
places along the board: snipe is judged on the board), the simulator's defects
(``Frame.truth["defects"]``) are found on their boards and only there, and its clean boards
grade 1 although its lights bend every pair's field.
"""

from __future__ import annotations

import asyncio

import pytest

from controller.quality.defect_fields import along_board_mm, defects_of
from controller.quality.defect_report import board_grades
from controller.quality.log import QualityLog
from planer.hil import InProcessHil, load_scenario
from vision.defects.detect import Defect, DefectKind
from vision.defects.grading import grade_board

pytestmark = pytest.mark.slow

TRUE_KINDS = ("torn_grain", "raised_grain")
"""The kinds config/sim_defects.toml places."""


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    sc = load_scenario("defects")
    assert sc.defects is True  # config/hil.toml: the service looks for defects on every pair
    path = tmp_path_factory.mktemp("hil") / "hil.sqlite"
    hil = InProcessHil(sc, log_path=path)
    summary = asyncio.run(hil.run())
    with QualityLog(path, create=False) as log:
        records = log.records()
    return summary, hil.service.results, records


def _truth_boards(results, records) -> dict[int, list[list[Defect]]]:
    """Each board's pairs' true defects (the pairs the service looked at)."""
    looked = {r.seq: r.board_id for r in records if r.defects is not None and r.board_id > 0}
    out: dict[int, list[list[Defect]]] = {}
    for r in results:
        if r.seq not in looked:
            continue
        out.setdefault(looked[r.seq], []).append([
            Defect(DefectKind(d["kind"]), d["x_mm"], d["y_mm"], d["length_mm"], d["width_mm"],
                   d["depth_um"], 1.0) for d in (r.truth or {}).get("defects") or ()])
    return out


def test_the_summary_counts_the_defects_and_grades_per_kind(run):
    summary, results, records = run
    d = summary["defects"]
    looked = [r for r in records if r.defects is not None]
    assert d["n_pairs"] == len(looked) >= 100
    for kind in d["defect_counts"]:
        assert d["defect_counts"][kind] == sum(x["kind"] == kind for r in looked
                                               for x in r.defects)
    assert d["truth_counts"]["torn_grain"] > 0 and d["truth_counts"]["raised_grain"] > 0
    assert sum(d["pair_grades"].values()) == len(looked)
    assert sum(d["board_grades"].values()) == len(d["boards"]) >= 3


def test_the_logs_board_grades_are_the_rule_over_its_pairs(run):
    _, _, records = run
    boards = board_grades(records)
    for b in boards:
        mine = [r for r in records if r.board_id == b["board_id"] and r.defects is not None]
        want = grade_board([defects_of(r.defects) for r in mine],
                           positions_mm=[r.board_position_mm for r in mine])
        assert (b["grade"], b["grade_reason"]) == (want.grade, want.reason), b["board_id"]


def test_the_true_defects_are_found_on_their_boards_and_only_there(run):
    _, results, records = run
    truth = _truth_boards(results, records)
    found = {b["board_id"]: b for b in board_grades(records)}
    defect_boards = [bid for bid, pairs in truth.items() if any(pairs)]
    clean_boards = [bid for bid, pairs in truth.items() if not any(pairs)]
    assert defect_boards and clean_boards
    for bid in defect_boards:  # a torn pit is very severe: the board's grade is the truth's
        assert found[bid]["grade"] == grade_board(truth[bid]).grade == 5, bid
        assert found[bid]["defect_counts"]["torn_grain"] > 0, bid
    for bid in clean_boards:  # none of the simulator's kinds where it placed none
        assert all(found[bid]["defect_counts"][k] == 0 for k in TRUE_KINDS), found[bid]


def test_the_log_places_each_torn_pit_where_it_was_on_its_board(run):
    """A torn pit's place along its board from the log is the truth's within 2 mm."""
    _, results, records = run
    truth = {r.seq: r.truth or {} for r in results}
    errors = []
    for r in records:
        t = truth[r.seq]
        for d in r.defects or ():
            pits = [x for x in t.get("defects") or () if x["kind"] == d["kind"] == "torn_grain"]
            if not pits:
                continue
            pit = min(pits, key=lambda x: abs(x["x_mm"] - d["x_mm"]) + abs(x["y_mm"] - d["y_mm"]))
            mine = along_board_mm(r.board_position_mm, d["x_mm"], r.extra["frame_centre_x_mm"])
            # the truth's board coordinates: the pit's and the optical axis's
            true = r.board_position_mm - (pit["board_x_mm"] - t["board_x_mm"])
            errors.append(abs(mine - true))
    assert len(errors) >= 5 and max(errors) <= 2.0, errors


def test_clean_boards_grade_as_the_truth(run):
    """The simulator's lights bend every field alike (~86 um of sag): each pair reports it as a
    raw snipe, its board judges it the optics (its middle pairs bend as much) and counts none."""
    _, results, records = run
    truth = _truth_boards(results, records)
    found = {b["board_id"]: b for b in board_grades(records)}
    clean = [bid for bid, pairs in truth.items() if not any(pairs)]
    assert clean
    for bid in clean:
        assert found[bid]["grade"] == grade_board(truth[bid]).grade == 1, found[bid]
        assert found[bid]["n_defects"] == 0, found[bid]
        assert "snipe over the middle's bow" in found[bid]["grade_reason"], found[bid]
        bends = [d["depth_um"] for r in records if r.board_id == bid and r.defects
                 for d in r.defects if d["kind"] == "snipe"]
        assert bends and min(bends) > 50.0  # the raw bends are there: the board discounts them
        # each pair's own grade leaves the bend to the board (vision.defects.grading.pair_grade)
        for r in records:
            if r.board_id == bid and r.defects is not None:
                assert r.grade == 1 and "snipe" not in r.grade_reason, (r.seq, r.grade_reason)
