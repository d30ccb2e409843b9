"""The operator page's board strip: the board's planing defects as they pass and its grade.

The :class:`LiveView` collects each pair's defects per board (the frame's ``board_id``) and
grades the board so far by the quality log's rule; the page draws the current board with each
defect where it was along the board, its grade and why, and the last board's grade. In a real
browser (headless Chromium; skips with the reason when it or the packages are missing).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("starlette", reason="the web extra (starlette) is not installed")

from controller.service.frame_result import FrameResult  # noqa: E402
from controller.web.live import LiveView, result_json  # noqa: E402
from vision.defects.detect import Defect, DefectKind  # noqa: E402
from vision.defects.grading import grade_board, grade_pair  # noqa: E402

TORN = Defect(DefectKind.TORN_GRAIN, 30.0, 12.0, 12.0, 4.0, 250.0, 0.9)
NICK = Defect(DefectKind.KNIFE_NICK, 22.0, 30.0, 44.0, 0.4, 9.0, 0.8)
CENTRE = 22.0  # the middle of the profile (0..44 mm): the fallback of the optical axis
AXIS = 26.0  # the optical axis in image A (the rig's cx / px_per_mm, as the pipeline gives it)


def _result(seq: int, board: int, pos: float, found: list[Defect] | None, *,
            axis: float | None = AXIS) -> FrameResult:
    g = grade_pair(found) if found is not None else None
    m = SimpleNamespace(x_mm=np.linspace(0.0, 2 * CENTRE, 50), height_um=np.zeros(50),
                        defects=None if found is None else tuple(found),
                        grade=None if g is None else g.grade,
                        grade_reason=None if g is None else g.reason, confidence=0.9)
    return FrameResult(seq=seq, ok=True, error=None, measurement=m, knife_widths_mm=(),
                       applied=True, feed_setpoint_mm_s=600.0, offsets_um=(0.0,) * 4,
                       state="run", t_s=0.1 * seq, latency_s=0.01, counts_a=100 * seq,
                       extra={"board_id": board, "board_position_mm": pos,
                              "frame_centre_x_mm": axis})


#: board 3: four pairs, a torn pit on the second, a nick on the fourth; then board 4 begins
PAIRS = [(0, 3, 100.0, []), (1, 3, 400.0, [TORN]), (2, 3, 700.0, None), (3, 3, 1000.0, [NICK]),
         (4, 4, 100.0, [])]


def test_the_page_json_carries_the_pairs_board_and_defects():
    d = result_json(_result(1, 3, 400.0, [TORN]))
    assert d["board_id"] == 3 and d["board_position_mm"] == 400.0
    assert d["defects"] == [TORN.to_json()] and d["grade"] == 5
    assert d["frame_centre_x_mm"] == AXIS
    assert result_json(_result(1, 3, 400.0, [TORN], axis=None))["frame_centre_x_mm"] == CENTRE
    none = result_json(_result(2, 3, 700.0, None))  # not looked for
    assert none["defects"] is None and none["grade"] is None


def test_the_live_view_grades_the_board_so_far_and_keeps_the_last():
    live = LiveView()
    for seq, board, pos, found in PAIRS[:4]:
        live.take_result(result_json(_result(seq, board, pos, found)))
    cur = live.snapshot()["board"]["current"]
    # the pair not looked at does not count; snipe judged with the pairs' places
    want = grade_board([[], [TORN], [NICK]], positions_mm=[100.0, 400.0, 1000.0])
    assert (cur["grade"], cur["grade_reason"]) == (want.grade, want.reason)
    assert cur["pairs"] == 3 and (cur["from_mm"], cur["to_mm"]) == (100.0, 1000.0)
    assert [(d["kind"], d["board_x_mm"], d["seq"]) for d in cur["defects"]] == [
        # image x runs toward the board's leading end: 4 mm past the axis is 4 mm nearer it
        ("torn_grain", 400.0 - (30.0 - AXIS), 1), ("knife_nick", 1000.0 - (22.0 - AXIS), 3)]
    assert cur["defect_counts"]["torn_grain"] == 1 and cur["defect_counts"]["knife_nick"] == 1
    live.take_result(result_json(_result(*PAIRS[4])))
    board = live.snapshot()["board"]
    assert board["last"]["board_id"] == 3 and board["last"]["grade"] == want.grade
    assert board["current"]["board_id"] == 4 and board["current"]["grade"] == 1


def test_the_strip_keeps_the_first_defects_and_counts_them_all():
    from controller.web.board_strip import MAX_STRIP_DEFECTS

    live = LiveView()
    for seq in range(MAX_STRIP_DEFECTS // 2 + 25):  # two nicks a pair
        live.take_result(result_json(_result(seq, 9, 60.0 * seq, [NICK, NICK])))
    cur = live.snapshot()["board"]["current"]
    assert len(cur["defects"]) == MAX_STRIP_DEFECTS
    assert cur["defect_counts"]["knife_nick"] == MAX_STRIP_DEFECTS + 50
    assert cur["defects"][-1]["seq"] == MAX_STRIP_DEFECTS // 2 - 1


def _strip(driver) -> dict:
    return driver.execute_script("""
        const rects = Array.from(document.querySelectorAll('#board-strip rect.defect'));
        return {
          grade: document.getElementById('bs-grade').textContent,
          grade_class: document.getElementById('bs-grade').className,
          reason: document.getElementById('bs-reason').textContent,
          board: document.getElementById('bs-board').textContent,
          counts: document.getElementById('bs-counts').textContent,
          last: document.getElementById('bs-last').textContent,
          kinds: rects.map((r) => r.dataset.kind),
          xs: rects.map((r) => parseFloat(r.getAttribute('x'))),
          titles: rects.map((r) => r.textContent),
        };""")


def test_the_strip_shows_the_defects_as_they_pass_and_the_grade(chrome):  # noqa: F811
    from selenium.webdriver.support.ui import WebDriverWait

    from controller.web.app import make_app
    from controller.web.server import WebServer
    from tests.controller.web.test_web_browser import TIMEOUT_S

    live = LiveView()
    live.take_result(result_json(_result(*PAIRS[0])))
    server = WebServer(make_app(live, None), "127.0.0.1:0")
    server.start()
    try:
        chrome.get(server.url)
        wait = WebDriverWait(chrome, TIMEOUT_S)
        wait.until(lambda d: _strip(d)["grade"] == "grade 1 defect-free")
        assert _strip(chrome)["kinds"] == [] and _strip(chrome)["counts"] == "no defects"
        for pair in PAIRS[1:4]:  # the pit, then a pair not looked at, then the nick
            live.take_result(result_json(_result(*pair)))
        wait.until(lambda d: len(_strip(d)["kinds"]) == 2)
        s = _strip(chrome)
        assert s["kinds"] == ["torn_grain", "knife_nick"] and s["xs"][0] < s["xs"][1]
        assert s["grade"] == "grade 5 very poor" and "g5" in s["grade_class"].split()
        assert s["reason"].startswith("grade 5: worst pair 1: grade 5: worst: torn_grain")
        assert s["board"] == "(board 3, 3 pairs so far)"
        assert s["counts"] == "torn grain 1, knife nick 1"
        assert s["titles"][0] == "torn grain at 396 mm: 12.0 x 4.0 mm, 250 µm (pair 1)"
        live.take_result(result_json(_result(*PAIRS[4])))  # board 4 begins, clean
        wait.until(lambda d: _strip(d)["last"] != "")
        s = _strip(chrome)
        assert s["last"] == "; last board 3: grade 5 (torn grain 1, knife nick 1)"
        assert s["grade"] == "grade 1 defect-free" and s["kinds"] == []
    finally:
        server.stop()


from tests.controller.web.test_web_browser import chrome  # noqa: E402, F401


def _graded_log(tmp_path):
    from controller.quality.log import QualityLog
    from tests.controller.quality.test_report_defects import _records

    recs, _ = _records()  # boards 1 (clean), 2 (a torn pit: 5), 3 (a chip mark: 2)
    path = tmp_path / "q.sqlite"
    with QualityLog(path) as log:
        for r in recs:
            log.append(r)
    return path


def test_the_quality_page_data_has_each_boards_grade_and_defect_map(tmp_path):
    from controller.web.quality import QualityBrowser

    qb = QualityBrowser(_graded_log(tmp_path))
    try:
        boards = {b["board_id"]: b for b in qb.boards()}
        assert [(b, boards[b]["grade"], boards[b]["defects"]) for b in (1, 2, 3)] == [
            (1, 1, 0), (2, 5, 3), (3, 2, 1)]
        assert boards[2]["defect_counts"]["torn_grain"] == 1
        board = qb.board(2)
        assert "defect_map" in board["figures"]
        assert [r["grade"] for r in board["records"]][2] == 5
        assert board["records"][5]["defects"] == ["raised_grain", "chip_mark"]
        assert qb.figure_png(2, "defect_map").startswith(b"\x89PNG")
    finally:
        qb.close()


def test_the_quality_page_shows_the_grades_in_the_browser(chrome, tmp_path):  # noqa: F811
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    from controller.web.app import make_app
    from controller.web.quality import QualityBrowser
    from controller.web.server import WebServer
    from tests.controller.web.test_web_browser import TIMEOUT_S

    qb = QualityBrowser(_graded_log(tmp_path))
    server = WebServer(make_app(None, qb), "127.0.0.1:0")
    server.start()
    try:
        chrome.get(server.url + "quality?board=2")
        wait = WebDriverWait(chrome, TIMEOUT_S)
        wait.until(lambda d: len(d.find_elements(By.CSS_SELECTOR, "#records tbody tr")) == 8)
        table = chrome.execute_script("""
            const col = (id, name) => Array.from(document.querySelectorAll(`#${id} thead th`))
              .findIndex((th) => th.textContent === name);
            const rows = (id) => Array.from(document.querySelectorAll(`#${id} tbody tr`))
              .map((r) => Array.from(r.cells).map((c) => c.textContent));
            return {boards: rows('boards'), records: rows('records'),
                    bg: col('boards', 'grade'), rg: col('records', 'grade'),
                    rd: col('records', 'defects')};""")
        assert [r[table["bg"]] for r in table["boards"]] == ["1", "5", "2"]
        assert table["records"][2][table["rg"]] == "5"
        assert table["records"][2][table["rd"]] == "torn_grain"
        assert table["records"][0][table["rd"]] == "none"
        wait.until(lambda d: d.execute_script(
            "return Array.from(document.querySelectorAll('#figures img'))"
            ".some((i) => i.alt.startsWith('defect_map') && i.complete && i.naturalWidth > 0);"))
    finally:
        server.stop()
        qb.close()
