"""The records stage of a moulder's head: its name on every record, its own journal.

Two heads' stages write into one log (as a moulder's services do); each record names the head
whose pair it is, and each head that is not ``"main"`` journals beside the log in its own file.
"""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from config.machine import load_machine
from controller.quality.journal import default_journal_path
from controller.quality.log import QualityLog
from controller.service.events import EventLog
from controller.service.frame_result import FrameResult
from controller.service.records import QualityRecords
from protocol.frames import Frame

IMG = np.zeros((4, 4))


def _failed(seq: int) -> tuple[FrameResult, Frame]:
    result = FrameResult(seq=seq, ok=False, error="registration failed: confidence 0.2",
                         measurement=None, knife_widths_mm=(), applied=False,
                         feed_setpoint_mm_s=600.0, offsets_um=(0.0, 0.0), state="run",
                         t_s=0.1 * seq, latency_s=0.0)
    frame = Frame(seq=seq, t_s=0.1 * seq, image_a=IMG, image_b=IMG, counts_a=100 * seq,
                  counts_b=100 * seq + 24, speed_mm_s=600.0, board_id=1)
    return result, frame


def _stage(log: QualityLog, **kw) -> QualityRecords:
    return QualityRecords(load_machine(), log, EventLog(), on_health=lambda ok: None,
                          threaded=False, **kw)


def test_each_heads_stage_names_its_head_on_every_record(tmp_path):
    path = tmp_path / "run.db"
    log = QualityLog(path)
    stages = {"main": _stage(log), "top": _stage(log, head="top")}
    assert stages["main"].head == "main"

    async def run() -> None:
        for seq in range(6):
            head = ("main", "top")[seq % 2]
            await stages[head].append(*_failed(seq), t=0.1 * seq)

    asyncio.run(run())
    back = QualityLog(path, create=False)
    assert [(r.seq, r.head) for r in back.records()] == [
        (0, "main"), (1, "top"), (2, "main"), (3, "top"), (4, "main"), (5, "top")]
    assert [r.seq for r in back.records(head="top")] == [1, 3, 5]
    back.close()
    assert stages["main"].sink.journal_path == default_journal_path(path)
    assert stages["top"].sink.journal_path == tmp_path / "run.db.top.journal.jsonl"
    for stage in stages.values():
        stage.sink.close()
    log.close()


def test_record_of_carries_the_head():
    stage = _stage(None, head="bottom")
    rec = stage.record_of(*_failed(3))
    assert rec.head == "bottom" and rec.seq == 3 and not rec.ok


def test_a_head_that_is_not_a_name_is_refused():
    with pytest.raises(ValueError, match="head must be a head name"):
        _stage(None, head="Bottom")
