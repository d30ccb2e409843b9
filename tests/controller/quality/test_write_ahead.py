"""Write-ahead sink: journal first, database after, and nothing waits for the database.

Judged by order and content, never by time: a database held at a gate shows that every record
reaches the journal (fsync'ed) while no database call can finish, that the sink's state is read
meanwhile, and that the records then reach the log in order, once each.
"""

from __future__ import annotations

import json
import sqlite3
import threading
from dataclasses import replace

import pytest

from controller.quality import write_ahead
from controller.quality.journal import JournalEntry, read_journal
from controller.quality.log import QualityLog, QualityRecord, utc_iso
from controller.quality.write_ahead import WriteAheadSink

BACKSTOP_S = 60.0


def _rec(i: int, **kw) -> QualityRecord:
    return QualityRecord(t_s=0.01 * i, wall_time=utc_iso(0.0), seq=i, board_id=1,
                         board_position_mm=0.0, ok=True, extra={"i": i}, **kw)


class GatedLog:
    """A real quality log whose writes wait for ``gate`` (``inside`` set while one waits)."""

    def __init__(self, path, gate: threading.Event, *, fail_on_release: bool = False) -> None:
        self.log = QualityLog(path)
        self.gate = gate
        self.inside = threading.Event()
        self.fail_on_release = fail_on_release

    def append(self, record, *, uid=None):
        return self.append_many([record], uids=[uid])[0]

    def append_many(self, records, *, uids=None):
        self.inside.set()
        assert self.gate.wait(BACKSTOP_S), "the test never opened the gate"
        if self.fail_on_release:
            raise ConnectionError("database gone")
        return self.log.append_many(records, uids=uids)

    def __getattr__(self, name):
        return getattr(self.log, name)


class Durable:
    """Collects ``on_durable`` answers; ``wait(n)`` until n items were answered."""

    def __init__(self) -> None:
        self.items: list = []
        self.flags: list[bool] = []
        self._cond = threading.Condition()

    def __call__(self, items, durable) -> None:
        with self._cond:
            self.items += items
            self.flags += [durable] * len(items)
            self._cond.notify_all()

    def wait(self, n: int) -> None:
        with self._cond:
            assert self._cond.wait_for(lambda: len(self.items) >= n, BACKSTOP_S)


def _seqs(path) -> list[int]:
    with QualityLog(path, create=False) as log:
        return [r.seq for r in log.records()]


def test_records_are_journalled_while_the_database_is_held_then_logged_in_order_once(tmp_path):
    gate = threading.Event()
    log = GatedLog(tmp_path / "q.db", gate)
    durable = Durable()
    sink = WriteAheadSink(log, journal_path=tmp_path / "j.jsonl", on_durable=durable)
    for i in range(50):
        sink.put(_rec(i))
    durable.wait(50)  # every record fsync'ed to the journal ...
    assert log.inside.wait(BACKSTOP_S)  # ... while a database call cannot finish
    held, bad = read_journal(tmp_path / "j.jsonl")
    assert [r.seq for r in held] == list(range(50)) and bad == 0 and all(durable.flags)
    st = sink.state  # read while the database thread is stuck in its call
    assert st.pending == 50 and st.unsaved == 0 and not st.failing
    sink.put(_rec(50))  # and a put does not wait either
    gate.set()
    assert sink.wait_logged(BACKSTOP_S)
    assert sink.close() is None and not (tmp_path / "j.jsonl").exists()
    assert _seqs(tmp_path / "q.db") == list(range(51))
    assert sink.state.problem is None and sink.state.pending == 0
    log.log.close()


def test_a_locked_sqlite_log_is_a_problem_but_not_a_failure_and_recovers(tmp_path):
    db = tmp_path / "q.db"
    log = QualityLog(db)
    holder = sqlite3.connect(db, isolation_level=None)
    holder.execute("BEGIN EXCLUSIVE")  # another connection holds the log
    durable = Durable()
    sink = WriteAheadSink(log, journal_path=tmp_path / "j.jsonl", on_durable=durable,
                          db_timeout_s=0.05)
    for i in range(10):
        sink.put(_rec(i))
    durable.wait(10)
    assert all(durable.flags)  # durable on disk although the log is locked

    def locked_problem():
        st = sink.state
        return st.problem is not None and "locked" in st.problem

    with sink._cond:
        assert sink._cond.wait_for(locked_problem, BACKSTOP_S)
    st = sink.state
    assert not st.failing and st.pending == 10 and "kept in journal" in st.problem
    holder.execute("COMMIT")
    holder.close()
    assert sink.wait_logged(BACKSTOP_S)
    assert sink.close() is None and sink.state.problem is None
    log.close()
    assert _seqs(db) == list(range(10))


def test_the_journal_is_not_truncated_per_batch(tmp_path, monkeypatch):
    monkeypatch.setattr(write_ahead, "COMPACT_IDLE_S", 3600.0)
    monkeypatch.setattr(write_ahead, "COMPACT_BYTES", 1 << 30)
    with QualityLog(tmp_path / "q.db") as log:
        durable = Durable()
        sink = WriteAheadSink(log, journal_path=tmp_path / "j.jsonl", on_durable=durable)
        for i in range(20):
            sink.put(_rec(i))
            durable.wait(i + 1)  # one batch each
        assert sink.wait_logged(BACKSTOP_S)
        counts = sink.state.counters
        assert counts["batches"] == 20 and counts["compactions"] == 0
        held, _ = read_journal(tmp_path / "j.jsonl")
        assert len(held) == 20  # logged, still in the journal: no truncation per batch
        assert sink.close() is None and not (tmp_path / "j.jsonl").exists()
        assert [r.seq for r in log.records()] == list(range(20))


def test_the_journal_is_truncated_once_everything_in_it_is_logged(tmp_path, monkeypatch):
    monkeypatch.setattr(write_ahead, "COMPACT_IDLE_S", 3600.0)
    monkeypatch.setattr(write_ahead, "COMPACT_BYTES", 1)
    with QualityLog(tmp_path / "q.db") as log:
        durable = Durable()
        sink = WriteAheadSink(log, journal_path=tmp_path / "j.jsonl", on_durable=durable)
        sink.put(_rec(0))
        durable.wait(1)
        with sink._cond:
            assert sink._cond.wait_for(lambda: sink.state.counters["compactions"] >= 1,
                                       BACKSTOP_S)
        assert (tmp_path / "j.jsonl").stat().st_size == 0
        sink.put(_rec(1))  # appended after the truncation
        assert sink.wait_logged(BACKSTOP_S) and sink.close() is None
        assert [r.seq for r in log.records()] == [0, 1]


def test_a_backlog_beyond_memory_waits_on_disk_and_comes_back_in_order(tmp_path, monkeypatch):
    monkeypatch.setattr(write_ahead, "MAX_IN_MEMORY", 5)
    gate = threading.Event()
    log = GatedLog(tmp_path / "q.db", gate)
    durable = Durable()
    sink = WriteAheadSink(log, journal_path=tmp_path / "j.jsonl", on_durable=durable)
    for i in range(40):
        sink.put(_rec(i))
    durable.wait(40)
    assert len(sink._todo) <= 5 and sink._spill is not None  # the rest only on disk
    assert sink.state.pending == 40
    gate.set()
    assert sink.wait_logged(BACKSTOP_S) and sink.close() is None
    log.log.close()
    assert _seqs(tmp_path / "q.db") == list(range(40))


def test_a_journal_left_behind_is_written_first_torn_line_cut_known_records_once(tmp_path):
    journal = tmp_path / "j.jsonl"
    entries = [JournalEntry(f"{i:032x}", _rec(i)) for i in range(3)]
    with QualityLog(tmp_path / "q.db") as log:
        log.append(entries[0].record, uid=entries[0].uid)  # logged before the crash
        journal.write_text("".join(e.line() for e in entries) + '{"v": 1, "uid": "to')
        sink = WriteAheadSink(log, journal_path=journal)
        assert sink.state.pending == 3  # the whole lines left
        sink.put(_rec(3))
        assert sink.wait_logged(BACKSTOP_S) and sink.close() is None
        assert [r.seq for r in log.records()] == [0, 1, 2, 3]


def test_a_value_the_log_refuses_becomes_a_failed_record(tmp_path):
    with QualityLog(tmp_path / "q.db") as log:
        sink = WriteAheadSink(log, journal_path=tmp_path / "j.jsonl")
        sink.put(_rec(0))
        sink.put(replace(_rec(1), seq=10**20))
        sink.put(_rec(2))
        assert sink.wait_logged(BACKSTOP_S) and sink.close() is None
        got = log.records()
        assert [r.seq for r in got] == [0, 0, 2] and not got[1].ok and "seq" in got[1].error
        assert sink.state.counters["rewritten"] == 1


def test_close_waits_a_bounded_time_for_a_database_that_never_answers(tmp_path):
    gate = threading.Event()
    log = GatedLog(tmp_path / "q.db", gate, fail_on_release=True)
    durable = Durable()
    sink = WriteAheadSink(log, journal_path=tmp_path / "j.jsonl", on_durable=durable)
    for i in range(5):
        sink.put(_rec(i))
    durable.wait(5)
    assert log.inside.wait(BACKSTOP_S)
    left = sink.close(timeout_s=0.2)  # the database thread is still inside its call
    assert left == tmp_path / "j.jsonl" and sink.database_busy and sink.state.pending == 5
    gate.set()  # the hung call comes back (failing); nothing was written
    with QualityLog(tmp_path / "q.db") as again:  # the next service replays the journal
        sink2 = WriteAheadSink(again, journal_path=left)
        assert sink2.close() is None
        assert [r.seq for r in again.records()] == list(range(5))
    log.log.close()


def test_a_journal_that_cannot_be_written_keeps_records_in_memory_and_fails(tmp_path, capsys):
    (tmp_path / "file").write_text("not a folder")
    gate = threading.Event()
    log = GatedLog(tmp_path / "q.db", gate)
    durable = Durable()
    sink = WriteAheadSink(log, journal_path=tmp_path / "file" / "j.jsonl", on_durable=durable)
    for i in range(3):
        sink.put(_rec(i))
    durable.wait(3)
    st = sink.state
    assert durable.flags == [False] * 3
    assert st.failing and st.unsaved == 3 and "NOT durable" in st.problem
    gate.set()  # the log still takes them
    assert sink.wait_logged(BACKSTOP_S)
    assert not sink.state.failing and sink.state.unsaved == 0
    durable.wait(6)  # in the log: durable at last, each answered so once
    assert durable.flags == [False] * 3 + [True] * 3
    assert sorted(r.seq for r in durable.items[3:]) == [0, 1, 2]
    assert sink.close() is None and capsys.readouterr().err == ""
    log.log.close()
    assert _seqs(tmp_path / "q.db") == [0, 1, 2]


def test_records_only_in_memory_are_answered_durable_once_the_journal_takes_them(tmp_path,
                                                                                  monkeypatch):
    gate = threading.Event()
    log = GatedLog(tmp_path / "q.db", gate)  # the log takes nothing meanwhile
    append = write_ahead.WriteAheadSink._append
    failing = threading.Event()
    failing.set()

    def flaky_append(self, body):  # the local disk refuses the journal's writes, then takes them
        if failing.is_set():
            raise OSError(28, "No space left on device")
        return append(self, body)

    monkeypatch.setattr(write_ahead.WriteAheadSink, "_append", flaky_append)
    durable = Durable()
    sink = WriteAheadSink(log, journal_path=tmp_path / "j.jsonl", on_durable=durable)
    for i in range(3):
        sink.put(_rec(i))
    durable.wait(3)
    assert durable.flags == [False] * 3 and sink.state.unsaved == 3
    failing.clear()  # the journal's retry (every second while records are only in memory)
    durable.wait(6)
    assert durable.flags == [False] * 3 + [True] * 3  # each answered durable exactly once
    assert sorted(r.seq for r in durable.items[3:]) == [0, 1, 2]
    held, bad = read_journal(tmp_path / "j.jsonl")
    assert sorted(r.seq for r in held) == [0, 1, 2] and bad == 0
    assert sink.state.unsaved == 0 and not sink.state.failing
    gate.set()
    assert sink.wait_logged(BACKSTOP_S)
    assert sink.close() is None
    assert len(durable.items) == 6  # the log taking them later answers nothing again
    log.log.close()
    assert _seqs(tmp_path / "q.db") == [0, 1, 2]


def test_records_nowhere_durable_at_close_are_printed(tmp_path, capsys):
    (tmp_path / "file").write_text("not a folder")
    gate = threading.Event()
    log = GatedLog(tmp_path / "q.db", gate, fail_on_release=True)
    sink = WriteAheadSink(log, journal_path=tmp_path / "file" / "j.jsonl")
    sink.put(_rec(7))
    assert log.inside.wait(BACKSTOP_S)
    sink.close(timeout_s=0.1)
    gate.set()
    err = capsys.readouterr().err
    assert err.startswith("unsaved quality record: ")
    assert json.loads(err.split(": ", 1)[1])["record"]["seq"] == 7
    log.log.close()


def test_put_after_close_is_refused(tmp_path):
    with QualityLog(tmp_path / "q.db") as log:
        sink = WriteAheadSink(log, journal_path=tmp_path / "j.jsonl")
        assert sink.close() is None
        with pytest.raises(ValueError, match="closed"):
            sink.put(_rec(0))
