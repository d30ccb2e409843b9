"""Write-ahead sink: no lost wake-up, nothing lost, each item answered in order, exactly once.

The writer threads sleep on their own conditions (one lock) and are woken only when there is
something for them. Every test here makes that sleep an hour (``COMPACT_IDLE_S``, the batch
waits) and never calls :meth:`WriteAheadSink.wait_logged` (which wakes both threads), so a
missed wake-up shows as a record that never arrives (the 60 s backstop), not as a slow test.
The interleavings are forced (a put made just as a writer thread goes to sleep, a hand-on
made while the other thread is inside a call), never hoped for by timing.
"""

from __future__ import annotations

import sqlite3
import threading
import time
from collections import defaultdict

import pytest

from controller.quality import write_ahead
from controller.quality.journal import read_journal
from controller.quality.log import QualityLog, QualityRecord, RecordRefusedError, utc_iso
from controller.quality.write_ahead import WriteAheadSink

BACKSTOP_S = 60.0
HOUR_S = 3600.0


def _rec(i: int) -> QualityRecord:
    return QualityRecord(t_s=0.01 * i, wall_time=utc_iso(0.0), seq=i, board_id=1,
                         board_position_mm=0.0, ok=True, extra={"i": i, "w": [0.5, 1.5]})


class Answers:
    """Collects ``on_durable`` answers per item (a record's seq) in the order given."""

    def __init__(self) -> None:
        self.flags: dict[int, list[bool]] = defaultdict(list)
        self.n = 0
        self._cond = threading.Condition()

    def __call__(self, items, durable) -> None:
        with self._cond:
            for item in items:
                self.flags[item.seq].append(durable)
            self.n += len(items)
            self._cond.notify_all()

    def wait(self, n: int) -> None:
        with self._cond:
            assert self._cond.wait_for(lambda: self.n >= n, BACKSTOP_S)


def _until(sink: WriteAheadSink, ok) -> None:
    with sink._cond:
        assert sink._cond.wait_for(lambda: ok(sink.state), BACKSTOP_S), sink.state


def _quiet(monkeypatch, *, journal_wait_s: float = 0.0, db_wait_s: float = 0.0) -> None:
    """No timed wake-up within a test: a writer thread sleeps until it is woken."""
    monkeypatch.setattr(write_ahead, "COMPACT_IDLE_S", HOUR_S)
    monkeypatch.setattr(write_ahead, "JOURNAL_WAIT_S", journal_wait_s)
    monkeypatch.setattr(write_ahead, "DB_WAIT_S", db_wait_s)


class HookedCondition(threading.Condition):
    """A condition that runs ``hook()`` (on a new thread) just as a waiter goes to sleep.

    ``when()`` (called with the lock held) picks the wait; the hook runs once. The hook's
    thread needs the lock, so it acts only once the waiter sleeps and has released it.
    """

    def __init__(self, lock, when, hook) -> None:
        super().__init__(lock)
        self._when, self._hook = when, hook
        self.fired = threading.Event()

    def wait(self, timeout=None):
        if not self.fired.is_set() and self._when():
            self.fired.set()
            threading.Thread(target=self._hook, daemon=True).start()
        return super().wait(timeout)


def test_the_first_record_goes_at_once_however_long_the_clock_has_run(tmp_path, monkeypatch):
    # waits longer than the monotonic clock has run (a host booted minutes ago): the first
    # record after the start still goes at once, to the journal and to the log
    longer = time.monotonic() + HOUR_S
    _quiet(monkeypatch, journal_wait_s=longer, db_wait_s=longer)
    with QualityLog(tmp_path / "q.db") as log:
        answers = Answers()
        sink = WriteAheadSink(log, journal_path=tmp_path / "j.jsonl", on_durable=answers)
        sink.put(_rec(0))
        answers.wait(1)
        _until(sink, lambda st: st.counters["logged"] == 1)
        assert sink.close() is None
        assert [r.seq for r in log.records()] == [0]


@pytest.fixture
def quiet_sink(tmp_path, monkeypatch):
    """``(log, sink, answers)``: a sink on a real log whose threads sleep until woken."""
    _quiet(monkeypatch)
    with QualityLog(tmp_path / "q.db") as log:
        answers = Answers()
        sink = WriteAheadSink(log, journal_path=tmp_path / "j.jsonl", on_durable=answers)
        yield log, sink, answers


def _put_one_as_it_sleeps(sink: WriteAheadSink, when) -> HookedCondition:
    """A condition for a writer thread that puts record [1] just as ``when()`` it sleeps."""
    return HookedCondition(sink._cond._lock, when=when, hook=lambda: sink.put(_rec(1)))


def _logged_two(log, sink: WriteAheadSink) -> None:
    """Both records in the log, in order; the sink closes with nothing left."""
    _until(sink, lambda st: st.counters["logged"] == 2)
    assert sink.close() is None
    assert [r.seq for r in log.records()] == [0, 1]


def test_a_put_just_as_the_journal_thread_goes_to_sleep_wakes_it(quiet_sink):
    log, sink, answers = quiet_sink
    sink._group.journal_cv = _put_one_as_it_sleeps(
        sink, lambda: not sink._inbox and sink._counts["journalled"] == 1)
    sink.put(_rec(0))
    answers.wait(2)  # [1] came as the journal thread fell asleep after [0]: woken
    assert sink._group.journal_cv.fired.is_set()
    _logged_two(log, sink)
    assert dict(answers.flags) == {0: [True], 1: [True]}


def test_a_put_while_the_journal_thread_appends_is_taken_without_another(quiet_sink,
                                                                        monkeypatch):
    log, sink, answers = quiet_sink
    inside, gate = threading.Event(), threading.Event()
    synced = write_ahead._append_synced

    def held(fd, body):
        if not gate.is_set():
            inside.set()
            assert gate.wait(BACKSTOP_S)
        return synced(fd, body)

    monkeypatch.setattr(write_ahead, "_append_synced", held)
    sink.put(_rec(0))
    assert inside.wait(BACKSTOP_S)  # the journal thread is inside its append of [0]
    sink.put(_rec(1))  # its wake-up finds nobody asleep
    gate.set()
    answers.wait(2)  # ... yet [1] is journalled: the thread looks before it sleeps
    _until(sink, lambda st: st.counters["logged"] == 2)
    assert sink.state.counters["batches"] == 2  # two appends, no third
    _logged_two(log, sink)


def test_records_handed_on_just_as_the_database_thread_goes_to_sleep_wake_it(quiet_sink):
    log, sink, _ = quiet_sink
    sink._group.db_cv = _put_one_as_it_sleeps(
        sink, lambda: not sink._todo and sink._counts["logged"] == 1)
    sink.put(_rec(0))
    _logged_two(log, sink)  # woken for [1], not an hour on
    assert sink._group.db_cv.fired.is_set()


class GatedLog:
    """A real quality log whose first write waits at ``gate`` (``inside`` set meanwhile)."""

    def __init__(self, path) -> None:
        self.log = QualityLog(path)
        self.gate, self.inside = threading.Event(), threading.Event()

    def append(self, record, *, uid=None, extra_json=None):
        return self.append_many([record], uids=[uid], extra_json=[extra_json])[0]

    def append_many(self, records, *, uids=None, extra_json=None):
        if not self.gate.is_set():
            self.inside.set()
            assert self.gate.wait(BACKSTOP_S)
        return self.log.append_many(records, uids=uids, extra_json=extra_json)

    def __getattr__(self, name):
        return getattr(self.log, name)


def test_records_handed_on_while_the_database_writes_follow_without_a_wake_up(tmp_path,
                                                                             monkeypatch):
    _quiet(monkeypatch)
    log = GatedLog(tmp_path / "q.db")
    answers = Answers()
    sink = WriteAheadSink(log, journal_path=tmp_path / "j.jsonl", on_durable=answers)
    sink.put(_rec(0))
    assert log.inside.wait(BACKSTOP_S)  # the database thread is inside its write of [0]
    for i in range(1, 4):
        sink.put(_rec(i))
    answers.wait(4)  # handed on while it writes: no wake-up for it ...
    log.gate.set()
    _until(sink, lambda st: st.counters["logged"] == 4)  # ... it looks before it sleeps
    assert sink.close() is None
    assert [r.seq for r in log.log.records()] == [0, 1, 2, 3]
    log.log.close()


def test_records_the_journal_refused_are_answered_false_before_true(tmp_path, monkeypatch):
    # the journal cannot be written (its folder is a file); the log takes the records and
    # answers them durable. The journal thread is held after its failed append until the
    # log could have taken them: the log's True must still come after the journal's False.
    _quiet(monkeypatch)
    (tmp_path / "file").write_text("not a folder")
    with QualityLog(tmp_path / "q.db") as log:
        answers = Answers()
        sink = WriteAheadSink(log, journal_path=tmp_path / "file" / "j.jsonl",
                              on_durable=answers)
        journal = sink._journal

        def slow_journal(retry, entries, items):
            ok, late = journal(retry, entries, items)
            if not ok and entries:  # a chance for the log to answer first, were they handed on
                with sink._cond:
                    sink._cond.wait_for(
                        lambda: not any(e.uid in sink._unsaved for e in entries), 0.5)
            return ok, late

        sink._journal = slow_journal
        for i in range(3):
            sink.put(_rec(i))
        answers.wait(6)
        assert dict(answers.flags) == {i: [False, True] for i in range(3)}
        assert sink.close() is None
        assert [r.seq for r in log.records()] == [0, 1, 2]


class RefusingLog:
    """A real log that refuses (schema-wise) every record whose ``extra["i"]`` is ``bad``."""

    def __init__(self, path, bad: int) -> None:
        self.log = QualityLog(path)
        self.bad = bad

    def _check(self, record) -> None:
        if record.extra.get("i") == self.bad:
            raise RecordRefusedError("extra", f"the database refuses i={self.bad}")

    def append(self, record, *, uid=None, extra_json=None):
        self._check(record)
        return self.log.append(record, uid=uid, extra_json=extra_json)

    def append_many(self, records, *, uids=None, extra_json=None):
        for r in records:
            self._check(r)
        return self.log.append_many(records, uids=uids, extra_json=extra_json)

    def __getattr__(self, name):
        return getattr(self.log, name)


def test_a_record_the_database_refuses_is_logged_failed_and_blocks_nothing(tmp_path,
                                                                          monkeypatch):
    _quiet(monkeypatch, journal_wait_s=HOUR_S, db_wait_s=HOUR_S)
    log = RefusingLog(tmp_path / "q.db", bad=2)
    answers = Answers()
    sink = WriteAheadSink(log, journal_path=tmp_path / "j.jsonl", on_durable=answers)
    for i in range(5):
        sink.put(_rec(i))
    assert sink.close() is None  # a window open: close waits for neither
    got = log.log.records()
    assert [r.seq for r in got] == [0, 1, 0, 3, 4]
    refused = got[2]
    assert not refused.ok and "refuses i=2" in refused.error
    assert set(refused.extra) == {"refused"}  # the failed record's own extra, not the text
    assert [r.extra for r in got[:2] + got[3:]] == [_rec(i).extra for i in (0, 1, 3, 4)]
    assert sink.state.counters["rewritten"] == 1
    assert dict(answers.flags) == {i: [True] for i in range(5)}
    log.log.close()


def _rows(path) -> list[tuple]:
    conn = sqlite3.connect(path)
    try:
        return conn.execute("SELECT * FROM records ORDER BY record_id").fetchall()
    finally:
        conn.close()


def test_a_journal_replayed_after_the_log_took_it_adds_nothing(tmp_path, monkeypatch):
    # a crash after the log's commit and before the journal's truncation: the next sink
    # replays the journal through the batches (uids and the encoded text) and adds no row
    _quiet(monkeypatch, journal_wait_s=HOUR_S, db_wait_s=HOUR_S)
    journal = tmp_path / "j.jsonl"
    with QualityLog(tmp_path / "q.db", machine_id="m1") as log:
        sink = WriteAheadSink(log, journal_path=journal)
        for i in range(6):
            sink.put(_rec(i))
        assert sink.wait_logged(BACKSTOP_S)
        left = journal.read_bytes()
        assert sink.close() is None and not journal.exists()
    rows = _rows(tmp_path / "q.db")
    assert [r.seq for r in read_journal(_write(journal, left))[0]] == list(range(6))
    with QualityLog(tmp_path / "q.db", machine_id="m1") as log:
        again = WriteAheadSink(log, journal_path=journal)
        assert again.state.pending == 6
        again.put(_rec(6))
        assert again.close() is None and not journal.exists()
        assert [r.seq for r in log.records()] == list(range(7))
    assert _rows(tmp_path / "q.db")[:6] == rows


def _write(path, data: bytes):
    path.write_bytes(data)
    return path
