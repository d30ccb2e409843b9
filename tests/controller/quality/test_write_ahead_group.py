"""Write-ahead sinks sharing one writer group: a moulder's heads, one connection, two threads.

Every head's sink keeps its own journal, answers and state; one journal thread and one
database thread serve them all, and a transaction holds the records of every head that had
some waiting. Judged by counts and order (the waits made an hour long), never by time.
"""

from __future__ import annotations

import threading

import pytest

from controller.quality import write_ahead
from controller.quality.journal import default_journal_path, read_journal
from controller.quality.log import QualityLog, QualityRecord, utc_iso
from controller.quality.write_ahead import SharedLog, WriteAheadSink, WriterGroup
from tests.controller.quality.test_write_ahead import GatedLog

BACKSTOP_S = 60.0
HOUR_S = 3600.0
HEADS = ("bottom", "right", "left")


def _rec(i: int, head: str) -> QualityRecord:
    return QualityRecord(t_s=0.01 * i, wall_time=utc_iso(0.0), seq=i, board_id=1,
                         board_position_mm=0.0, ok=True, head=head, extra={"i": i})


class Durable:
    """Collects ``on_durable`` answers of one head: ``(seq, durable)`` in the order given."""

    def __init__(self, cond: threading.Condition) -> None:
        self.answers: list[tuple[int, bool]] = []
        self._cond = cond

    def __call__(self, items, durable) -> None:
        with self._cond:
            self.answers += [(item.seq, durable) for item in items]
            self._cond.notify_all()


def _group(tmp_path) -> tuple[WriterGroup, dict[str, WriteAheadSink], dict[str, Durable]]:
    path = tmp_path / "q.db"
    group = WriterGroup(QualityLog(path))
    cond = threading.Condition()
    answers = {h: Durable(cond) for h in HEADS}
    sinks = {h: WriteAheadSink(group.head_log(), journal_path=default_journal_path(path, head=h),
                               on_durable=answers[h]) for h in HEADS}
    return group, sinks, answers


def _writer_threads() -> list[str]:
    return sorted(t.name for t in threading.enumerate()
                  if t.name in ("quality-journal", "quality-database"))


def test_every_heads_records_go_through_one_journal_thread_and_one_transaction(tmp_path,
                                                                              monkeypatch):
    monkeypatch.setattr(write_ahead, "JOURNAL_WAIT_S", 0.0)
    monkeypatch.setattr(write_ahead, "DB_WAIT_S", HOUR_S)
    monkeypatch.setattr(write_ahead, "COMPACT_IDLE_S", HOUR_S)  # the journals read below
    before = _writer_threads()
    group, sinks, answers = _group(tmp_path)
    cond = answers["bottom"]._cond
    sinks["bottom"].put(_rec(0, "bottom"))  # the first goes at once: a transaction alone
    with sinks["bottom"]._cond:
        assert sinks["bottom"]._cond.wait_for(
            lambda: sinks["bottom"].state.counters["logged"] == 1, BACKSTOP_S)
    assert _writer_threads() == sorted(before + ["quality-database", "quality-journal"])
    for i in range(1, 13):  # the heads in turn, while the database's wait is open
        sinks[HEADS[i % 3]].put(_rec(i, HEADS[i % 3]))
    with cond:  # every record journalled (durable), none logged since the first
        assert cond.wait_for(lambda: sum(len(a.answers) for a in answers.values()) == 13,
                             BACKSTOP_S)
    assert sum(s.state.pending for s in sinks.values()) == 12
    assert all(s.wait_logged(BACKSTOP_S) for s in sinks.values())
    assert group.transactions == 2  # [0], then every head's in one
    assert {h: s.state.counters["db_batches"] for h, s in sinks.items()} == {
        "bottom": 2, "right": 1, "left": 1}
    for h in HEADS:  # each head's own journal, its records in its order, answered once
        mine = [i for i in range(13) if HEADS[i % 3] == h]
        held, bad = read_journal(default_journal_path(tmp_path / "q.db", head=h))
        assert [r.seq for r in held] == mine and bad == 0
        assert answers[h].answers == [(i, True) for i in mine]
    for s in sinks.values():
        assert s.close() is None
    assert _writer_threads() == before  # the threads end with the last head
    log = group.log
    got = log.records()
    for h in HEADS:
        assert [r.seq for r in got if r.head == h] == [i for i in range(13) if HEADS[i % 3] == h]
    group.close()
    assert log._store.closed  # the group closes the one connection after every head


def test_a_head_that_closes_leaves_the_others_writing(tmp_path):
    group, sinks, answers = _group(tmp_path)
    sinks["right"].put(_rec(1, "right"))
    assert sinks["right"].close() is None  # its records logged, its journal removed
    assert not default_journal_path(tmp_path / "q.db", head="right").exists()
    assert not group.log._store.closed  # its view closed, not the log
    for i in range(2, 6):
        sinks["bottom"].put(_rec(i, "bottom"))
    assert sinks["bottom"].wait_logged(BACKSTOP_S)
    group.close()  # the heads never closed are closed with it
    assert all(s.state.pending == 0 for s in sinks.values())
    with QualityLog(tmp_path / "q.db", create=False) as log:
        assert [(r.head, r.seq) for r in log.records()] == [("right", 1)] + [
            ("bottom", i) for i in range(2, 6)]


def test_a_write_that_never_returns_keeps_the_log_open_and_the_records_journalled(tmp_path):
    hung = GatedLog(tmp_path / "q.db", threading.Event(), fail_on_release=True)
    group = WriterGroup(hung)
    view = group.head_log()
    assert isinstance(view, SharedLog) and view.path == tmp_path / "q.db"
    sinks = [WriteAheadSink(group.head_log(), journal_path=tmp_path / f"{h}.jsonl")
             for h in ("bottom", "top")]
    sinks[0].put(_rec(0, "bottom"))
    sinks[1].put(_rec(1, "top"))
    assert hung.inside.wait(BACKSTOP_S)
    left = [s.close(timeout_s=0.1) for s in sinks]
    assert left[0] == tmp_path / "bottom.jsonl"  # kept for the next service
    group.close()
    assert not hung.log._store.closed  # the hung call holds it: left to the exit
    hung.gate.set()
    hung.log.close()
    held = [r.seq for p in (tmp_path / "bottom.jsonl", tmp_path / "top.jsonl") if p.exists()
            for r in read_journal(p)[0]]
    assert sorted(held) == [0, 1]  # every record durable on disk


def test_a_group_takes_no_sink_once_closed(tmp_path):
    group = WriterGroup(QualityLog(tmp_path / "q.db"))
    group.close()
    with pytest.raises(ValueError, match="closed"):
        WriteAheadSink(group.head_log(), journal_path=tmp_path / "j.jsonl")
