"""Write-ahead sink, what a record costs: batches that wait for more records, encoded once.

The journal appends at most once per ``JOURNAL_WAIT_S`` and the database writes at most once
per ``DB_WAIT_S``: records that come meanwhile join the next append (one fsync) or
transaction, and a full batch goes at once. Judged by counts, never by time: the waits are
made an hour long, so a record that went alone would show as a batch of its own. ``close``
and ``wait_logged`` wait for no more records. A record's ``extra`` is encoded to JSON once for
both the journal and the log, and what either holds is what it held when each encoded the
record on its own.
"""

from __future__ import annotations

import json
import math
import sqlite3
import threading
from dataclasses import replace

import numpy as np
import pytest

from controller.quality import schema, write_ahead
from controller.quality.journal import JournalEntry, parse_line, read_journal
from controller.quality.log import (
    QualityLog,
    QualityRecord,
    check_storable,
    record_json,
    record_to_dict,
    storable,
    utc_iso,
)
from controller.quality.write_ahead import WriteAheadSink

BACKSTOP_S = 60.0
HOUR_S = 3600.0


def _rec(i: int, **kw) -> QualityRecord:
    kw.setdefault("extra", {"i": i, "timing_ms": {"vision_ms": 7.5 + i}})
    return QualityRecord(t_s=0.01 * i, wall_time=utc_iso(0.0), seq=i, board_id=1,
                         board_position_mm=0.0, ok=True, **kw)


class Durable:
    """Collects ``on_durable`` answers; ``wait(n)`` until n items were answered."""

    def __init__(self) -> None:
        self.items: list = []
        self._cond = threading.Condition()

    def __call__(self, items, durable) -> None:
        with self._cond:
            self.items += items
            self._cond.notify_all()

    def wait(self, n: int) -> None:
        with self._cond:
            assert self._cond.wait_for(lambda: len(self.items) >= n, BACKSTOP_S)


def _until(sink: WriteAheadSink, ok) -> None:
    with sink._cond:
        assert sink._cond.wait_for(lambda: ok(sink.state), BACKSTOP_S)


def test_records_that_come_while_the_journal_waits_join_one_append(tmp_path, monkeypatch):
    monkeypatch.setattr(write_ahead, "JOURNAL_WAIT_S", HOUR_S)
    monkeypatch.setattr(write_ahead, "COMPACT_IDLE_S", HOUR_S)  # the journal read below
    with QualityLog(tmp_path / "q.db") as log:
        durable = Durable()
        sink = WriteAheadSink(log, journal_path=tmp_path / "j.jsonl", on_durable=durable)
        sink.put(_rec(0))
        durable.wait(1)  # the first after a pause goes at once
        for i in range(1, 5):
            sink.put(_rec(i))
        assert sink.queued == 4 and len(durable.items) == 1  # waiting for the next append
        assert sink.wait_logged(BACKSTOP_S)  # a flush waits for no more records
        assert sink.state.counters["batches"] == 2  # [0], [1, 2, 3, 4]: two fsyncs
        assert [r.seq for r in durable.items] == list(range(5))
        assert [r.seq for r in read_journal(tmp_path / "j.jsonl")[0]] == list(range(5))
        assert sink.close() is None
        assert [r.seq for r in log.records()] == list(range(5))


def test_records_that_come_while_the_database_waits_join_one_transaction(tmp_path,
                                                                          monkeypatch):
    monkeypatch.setattr(write_ahead, "JOURNAL_WAIT_S", 0.0)
    monkeypatch.setattr(write_ahead, "DB_WAIT_S", HOUR_S)
    with QualityLog(tmp_path / "q.db") as log:
        durable = Durable()
        sink = WriteAheadSink(log, journal_path=tmp_path / "j.jsonl", on_durable=durable)
        sink.put(_rec(0))
        _until(sink, lambda st: st.counters["logged"] == 1)
        for i in range(1, 5):
            sink.put(_rec(i))
            durable.wait(i + 1)  # each durable in the journal on its own ...
        st = sink.state
        assert st.counters["batches"] == 5 and st.pending == 4  # ... none in the log yet
        assert st.problem is None and not st.failing  # waiting is no trouble
        assert sink.wait_logged(BACKSTOP_S)
        assert sink.state.counters["db_batches"] == 2  # [0], [1, 2, 3, 4]: two commits
        assert sink.close() is None
        assert [r.seq for r in log.records()] == list(range(5))


def test_a_full_batch_waits_for_no_more_records(tmp_path, monkeypatch):
    monkeypatch.setattr(write_ahead, "JOURNAL_WAIT_S", HOUR_S)
    monkeypatch.setattr(write_ahead, "DB_WAIT_S", HOUR_S)
    monkeypatch.setattr(write_ahead, "JOURNAL_BATCH_MAX", 3)
    monkeypatch.setattr(write_ahead, "DB_BATCH_MAX", 3)
    with QualityLog(tmp_path / "q.db") as log:
        durable = Durable()
        sink = WriteAheadSink(log, journal_path=tmp_path / "j.jsonl", on_durable=durable)
        sink.put(_rec(0))
        durable.wait(1)
        _until(sink, lambda st: st.counters["logged"] == 1)
        for i in range(1, 4):
            sink.put(_rec(i))
        durable.wait(4)  # three waiting make a full append: it goes without its time
        _until(sink, lambda st: st.counters["logged"] == 4)  # and a full transaction
        st = sink.state
        assert st.counters["batches"] == 2 and st.counters["db_batches"] == 2
        assert sink.close() is None
        assert [r.seq for r in log.records()] == list(range(4))


class WatchedLog:
    """A real log that notes, per transaction, whether the sink had already given up waiting."""

    def __init__(self, log: QualityLog) -> None:
        self.log = log
        self.sink: WriteAheadSink | None = None
        self.given_up: list[bool] = []

    def append(self, record, *, uid=None, extra_json=None):
        return self.append_many([record], uids=[uid], extra_json=[extra_json])[0]

    def append_many(self, records, *, uids=None, extra_json=None):
        self.given_up.append(self.sink._stop_db)
        return self.log.append_many(records, uids=uids, extra_json=extra_json)

    def __getattr__(self, name):
        return getattr(self.log, name)


def test_close_waits_for_no_more_records(tmp_path, monkeypatch):
    # were close to wait out the journal's or the database's wait, the records would still
    # be pending when close stops waiting for the log (its time limit)
    monkeypatch.setattr(write_ahead, "JOURNAL_WAIT_S", HOUR_S)
    monkeypatch.setattr(write_ahead, "DB_WAIT_S", HOUR_S)
    with QualityLog(tmp_path / "q.db") as real:
        log = WatchedLog(real)
        durable = Durable()
        log.sink = sink = WriteAheadSink(log, journal_path=tmp_path / "j.jsonl",
                                         on_durable=durable)
        sink.put(_rec(0))
        _until(sink, lambda st: st.counters["logged"] == 1)  # both windows open from here
        for i in range(1, 5):
            sink.put(_rec(i))
        assert sink.close(timeout_s=BACKSTOP_S) is None and sink.state.pending == 0
        assert log.given_up == [False, False]  # [0], [1, 2, 3, 4] while close still waited
        assert [r.seq for r in real.records()] == list(range(5))
        assert [r.seq for r in durable.items] == list(range(5))  # each answered once


def test_a_record_is_encoded_once_for_the_journal_and_the_log(tmp_path, monkeypatch):
    rec = _rec(1, extra={"profile": {"x_mm": [0.0, 0.1], "height_um": [1.5, 2.5]},
                         "vision": np.float32(0.5)})
    encoded = []
    dumps = json.dumps

    def counting(obj, *a, **kw):
        if obj is rec.extra:
            encoded.append(obj)
        return dumps(obj, *a, **kw)

    class CountingEncoder(json.JSONEncoder):
        def encode(self, obj):
            if obj is rec.extra:
                encoded.append(obj)
            return super().encode(obj)

    monkeypatch.setattr(schema.json, "dumps", counting)
    monkeypatch.setattr(schema, "_EXTRA_ENCODER", CountingEncoder(default=schema._json_default))
    monkeypatch.setattr(write_ahead, "COMPACT_IDLE_S", HOUR_S)  # the journal read below
    with QualityLog(tmp_path / "q.db", machine_id="m1") as log:
        sink = WriteAheadSink(log, journal_path=tmp_path / "j.jsonl")
        sink.put(rec)
        assert sink.wait_logged(BACKSTOP_S)
        held = read_journal(tmp_path / "j.jsonl")[0]
        assert sink.close() is None
        assert log.records() == [replace(rec, machine_id="m1")] and held == [rec]
    assert len(encoded) == 1  # not once for the journal and again for the log's row


def _raw_rows(path) -> list[tuple]:
    conn = sqlite3.connect(path)
    try:
        return conn.execute("SELECT * FROM records ORDER BY record_id").fetchall()
    finally:
        conn.close()


EXTRAS = [
    {"i": 1, "nested": {"a": [1.0, 2.5], "b": None}, "text": "caf\u00e9 \udc80"},
    {"nan": math.nan, "list": [1.0, math.inf], "deep": {"x": -math.inf}},  # not strict JSON
    {"says": "NaN and Infinity are words here", "n": np.int64(3),
     "arr": np.array([0.25, 0.5]), "tup": (1, 2)},
    {},
]


@pytest.mark.parametrize("extra", EXTRAS, ids=["plain", "non-finite", "numpy-and-words",
                                               "empty"])
def test_the_text_encoded_once_stores_what_each_encoded_on_its_own(tmp_path, extra):
    rec = _rec(2, extra=extra, mark_widths_mm=(1.0, math.nan), piezo_offsets_um=(0.5, -0.5))
    checked, text = storable(rec)
    assert checked is rec and text == check_storable(rec)
    with QualityLog(tmp_path / "a.db", machine_id="m1") as a, \
            QualityLog(tmp_path / "b.db", machine_id="m1") as b:
        a.append(rec)
        b.append(rec, extra_json=text)
        b.append_many([rec, _rec(3)], extra_json=[text, None])
        a.append(rec)
        a.append(_rec(3))
    assert _raw_rows(tmp_path / "a.db") == _raw_rows(tmp_path / "b.db")
    # the journal's line: strict JSON, the same object record_to_dict gives
    line = JournalEntry("u1", rec, text).line()
    strict = json.loads(line, parse_constant=lambda c: pytest.fail(f"{c} in a journal line"))
    assert strict["record"] == json.loads(json.dumps(record_to_dict(rec), allow_nan=False))
    assert strict == json.loads(JournalEntry("u1", rec).line())
    assert json.loads(record_json(rec, extra_json=text)) == strict["record"]
    back = parse_line(line.rstrip("\n").encode())  # a replayed line: encoded once again
    assert back.uid == "u1" and back.extra_json == check_storable(back.record)
