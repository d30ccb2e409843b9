"""OPC UA: the board's D1666 grade and the last board's defect counts, read by a client.

A real asyncua server (127.0.0.1, ephemeral port) fed pair results whose measurements carry
planing defects, read by a real asyncua client: before any graded board the grades read 0; on
board 5 ``BoardGrade`` follows the board so far; when board 6 begins ``LastBoard*`` hold board
5's grade, its reason and its defects per kind (the quality log's rule, the same numbers).
"""

from __future__ import annotations

from types import SimpleNamespace

import pytest

asyncua = pytest.importorskip("asyncua", reason="asyncua is not installed")


from controller.opcua.view import DEFECT_COUNT_NAMES, MANUFACTURER_NAMES  # noqa: E402
from controller.service.frame_result import FrameResult  # noqa: E402
from tests.controller.opcua.test_opcua_server import (  # noqa: E402, F401
    feed_and_wait,
    read_manufacturer,
    served,
)
from vision.defects.detect import Defect, DefectKind  # noqa: E402
from vision.defects.grading import grade_board, grade_pair  # noqa: E402

NICK = Defect(DefectKind.KNIFE_NICK, 22.0, 30.0, 44.0, 0.4, 9.0, 0.8)  # moderate
CHIP = Defect(DefectKind.CHIP_MARK, 10.0, 5.0, 3.0, 3.0, 30.0, 0.5)  # slight
NAMES = ("BoardGrade", "LastBoardId", "LastBoardGrade", "LastBoardGradeReason",
         "LastBoardDefects", *DEFECT_COUNT_NAMES.values())


def _result(seq: int, board: int, found: list[Defect]) -> FrameResult:
    g = grade_pair(found)
    m = SimpleNamespace(pitch_mm=1.5, uniformity_cv=0.02, depth_um=5.0, confidence=0.9,
                        defects=tuple(found), grade=g.grade, grade_reason=g.reason)
    return FrameResult(seq=seq, ok=True, error=None, measurement=m,
                       knife_widths_mm=(1.5,) * 4, applied=True, feed_setpoint_mm_s=400.0,
                       offsets_um=(0.0,) * 4, state="run", t_s=300.0 + 0.1 * seq,
                       latency_s=0.01, extra={"board_id": board, "board_position_mm": 50.0})


def _read_all(srv) -> dict:
    return read_manufacturer(srv, NAMES)


def test_the_names_are_served_with_their_types():
    assert set(NAMES) <= set(MANUFACTURER_NAMES)
    assert DEFECT_COUNT_NAMES == {
        "torn_grain": "LastBoardTornGrain", "raised_grain": "LastBoardRaisedGrain",
        "fuzzy_grain": "LastBoardFuzzyGrain", "chip_mark": "LastBoardChipMark",
        "knife_nick": "LastBoardKnifeNick", "chatter": "LastBoardChatter",
        "snipe": "LastBoardSnipe"}
    assert MANUFACTURER_NAMES["LastBoardGrade"] == "Int64"
    assert MANUFACTURER_NAMES["LastBoardGradeReason"] == "String"


def test_a_client_reads_the_boards_grade_and_the_last_boards_counts(served):  # noqa: F811
    srv = served.srv
    v = _read_all(srv)
    assert v["BoardGrade"] == 0 and v["LastBoardGrade"] == 0 and v["LastBoardId"] == 0
    assert v["LastBoardGradeReason"] == "" and v["LastBoardDefects"] == 0

    board5 = [[], [NICK, CHIP], [NICK], []]
    for i, found in enumerate(board5):
        feed_and_wait(served, lambda i=i, found=found: srv.result(_result(i, 5, found)))
    v = _read_all(srv)
    want = grade_board(board5, positions_mm=[50.0] * 4)  # every pair at 50 mm (_result)
    assert v["BoardGrade"] == want.grade == 4  # nicks on half the pairs: widespread
    assert v["LastBoardGrade"] == 0  # board 5 is still under the camera

    feed_and_wait(served, lambda: srv.result(_result(10, 6, [])))
    v = _read_all(srv)
    assert v["LastBoardId"] == 5 and v["LastBoardGrade"] == want.grade
    assert v["LastBoardGradeReason"] == want.reason
    assert v["LastBoardKnifeNick"] == 2 and v["LastBoardChipMark"] == 1
    assert v["LastBoardTornGrain"] == 0 and v["LastBoardDefects"] == 3
    assert v["BoardGrade"] == 1  # board 6 so far: defect-free
