"""Record journal: nothing lost when the quality log fails, exactly once after a crash."""

from __future__ import annotations

import json
import math
import os
import random
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from controller.quality.journal import RETRY_EVERY_APPENDS, RecordSink, default_journal_path
from controller.quality.log import (
    SQLITE_INT_MAX,
    QualityLog,
    QualityRecord,
    RecordRefusedError,
    record_from_dict,
    record_to_dict,
    storable,
    utc_iso,
)
from protocol.frames import Frame
from protocol.spool import SpoolWriter

REPO = Path(__file__).resolve().parents[3]


def _rec(i: int, **kw) -> QualityRecord:
    base = dict(t_s=0.1 * i, wall_time=utc_iso(1.7e9 + i), seq=i, board_id=1,
                board_position_mm=10.0 * i, ok=True, pitch_mm=1.5, mark_widths_mm=[1.4, 1.6],
                uniformity_cv=0.05, feed_setpoint_mm_s=600.0, piezo_offsets_um=[1.0, -1.0],
                extra={"i": i})
    base.update(kw)
    return QualityRecord(**base)


class FlakyLog:
    """A real quality log whose appends fail while ``failing`` is set (disk full, locked)."""

    def __init__(self, path: Path) -> None:
        self.inner = QualityLog(path)
        self.failing = False
        self.attempts = 0

    def append(self, record: QualityRecord, *, uid: str | None = None) -> int:
        self.attempts += 1
        if self.failing:
            raise OSError(28, "No space left on device")
        return self.inner.append(record, uid=uid)

    def has_uid(self, uid: str) -> bool:
        return self.inner.has_uid(uid)


def _seqs(log: QualityLog) -> list[int]:
    return [r.extra["i"] for r in log.records()]


# --------------------------------------------------------------------------------------------
# the log's side: refused values, identities


@pytest.mark.parametrize("name", ["seq", "board_id"])
@pytest.mark.parametrize("value", [SQLITE_INT_MAX + 1, 10**20])
def test_log_refuses_out_of_range_integers_naming_the_field(tmp_path, name, value):
    with QualityLog(tmp_path / "q.db") as log:
        with pytest.raises(RecordRefusedError, match=name) as info:
            log.append(_rec(0, **{name: value}))
        assert info.value.field == name and isinstance(info.value, ValueError)
        assert len(log) == 0
        log.append(_rec(1, **{name: SQLITE_INT_MAX}))  # the largest value goes in
        assert getattr(log.records()[0], name) == SQLITE_INT_MAX


def test_storable_names_every_refused_field():
    bad = _rec(3, seq=10**20, board_id=2**64, error=None, extra={"i": 3, "obj": object()})
    out = storable(bad)[0]
    assert not out.ok and out.seq == 0 and out.board_id == 0
    for name in ("seq", "board_id", "extra"):
        assert name in out.error and name in out.extra["refused"]
    assert out.extra["refused"]["seq"] == str(10**20)
    assert out.feed_setpoint_mm_s == bad.feed_setpoint_mm_s and out.t_s == bad.t_s
    failed = _rec(4, ok=False, error="registration failed: low", pitch_mm=None,
                  mark_widths_mm=(), uniformity_cv=None, seq=10**20)
    assert storable(failed)[0].error.startswith("registration failed: low (record refused")
    good = _rec(5)
    assert storable(good)[0] is good


def test_storable_escapes_lone_surrogates(tmp_path):
    bad = _rec(1, ok=False, error="bad \udcff byte", pitch_mm=None, mark_widths_mm=(),
               uniformity_cv=None)
    with QualityLog(tmp_path / "q.db") as log:
        with pytest.raises(RecordRefusedError, match="error"):
            log.append(bad)
        log.append(storable(bad)[0])
        assert "\\udcff" in log.records()[0].error


def test_uid_appends_once(tmp_path):
    with QualityLog(tmp_path / "q.db") as log:
        assert not log.has_uid("a")
        rid = log.append(_rec(0), uid="a")
        assert log.append(_rec(0), uid="a") == rid and len(log) == 1
        assert log.has_uid("a") and log.append(_rec(1), uid="b") > rid
        with pytest.raises(ValueError, match="uid"):
            log.append(_rec(2), uid="")


def test_record_dict_round_trip_with_nan_and_numpy():
    rec = _rec(2, mark_widths_mm=[1.0, math.nan], extra={"a": np.float32(1.5), "n": math.nan,
                                                         "arr": np.arange(3)})
    back = record_from_dict(json.loads(json.dumps(record_to_dict(rec), allow_nan=False)))
    assert back.mark_widths_mm[0] == 1.0 and math.isnan(back.mark_widths_mm[1])
    assert back.extra == {"a": 1.5, "n": None, "arr": [0, 1, 2]}
    with pytest.raises(ValueError, match="unknown record field"):
        record_from_dict({**record_to_dict(rec), "bogus": 1})


# --------------------------------------------------------------------------------------------
# the sink


def test_healthy_log_takes_records_directly(tmp_path):
    log = QualityLog(tmp_path / "q.db")
    journal = default_journal_path(log.path)
    sink = RecordSink(log, journal_path=journal)
    for i in range(5):
        sink.append(_rec(i))
    assert sink.pending == 0 and sink.problem is None and sink.retry() == 0
    assert sink.close() is None and not journal.exists()
    assert _seqs(log) == list(range(5))


def test_failing_log_journals_then_retry_writes_in_order(tmp_path):
    log = FlakyLog(tmp_path / "q.db")
    journal = tmp_path / "j.jsonl"
    sink = RecordSink(log, journal_path=journal)
    sink.append(_rec(0))
    log.failing = True
    n_fail = RETRY_EVERY_APPENDS - 2
    for i in range(1, 1 + n_fail):
        sink.append(_rec(i))
    assert sink.pending == n_fail
    assert "No space left" in sink.problem and str(journal) in sink.problem
    assert len(journal.read_text().splitlines()) == n_fail  # durable before append returned
    assert sink.retry() == 0 and sink.pending == n_fail
    log.failing = False
    sink.append(_rec(1 + n_fail))  # still behind the journal: order is kept
    assert sink.retry() == n_fail + 1
    assert sink.pending == 0 and sink.problem is None and not journal.exists()
    assert _seqs(log.inner) == list(range(n_fail + 2))


def test_append_retries_by_itself_every_few_appends(tmp_path):
    log = FlakyLog(tmp_path / "q.db")
    sink = RecordSink(log, journal_path=tmp_path / "j.jsonl")
    log.failing = True
    sink.append(_rec(0))
    log.failing = False
    attempts = log.attempts
    for i in range(1, RETRY_EVERY_APPENDS + 1):
        sink.append(_rec(i))
    assert sink.pending == 0 and log.attempts > attempts
    assert _seqs(log.inner) == list(range(RETRY_EVERY_APPENDS + 1))


def test_refused_record_becomes_failed_record(tmp_path):
    log = QualityLog(tmp_path / "q.db")
    sink = RecordSink(log, journal_path=tmp_path / "j.jsonl")
    sink.append(_rec(0, board_id=10**20))
    sink.append(_rec(1))
    assert sink.pending == 0 and sink.counters["rewritten"] == 1
    first, second = log.records()
    assert not first.ok and "board_id" in first.error
    assert first.extra["refused"] == {"board_id": str(10**20)} and second.ok


def test_a_record_the_log_refuses_anyway_does_not_block_the_others(tmp_path):
    class Picky(FlakyLog):
        def append(self, record, *, uid=None):
            if record.extra.get("i") == 1:
                raise RecordRefusedError("pitch_mm", "pitch_mm refused by a stricter log")
            return super().append(record, uid=uid)

    log = Picky(tmp_path / "q.db")
    sink = RecordSink(log, journal_path=tmp_path / "j.jsonl")
    for i in range(3):
        sink.append(_rec(i))
    recs = log.inner.records()
    assert sink.pending == 0 and len(recs) == 3 and sink.counters["rewritten"] == 1
    assert not recs[1].ok and "pitch_mm refused" in recs[1].error


def test_close_leaves_journal_and_next_sink_replays_exactly_once(tmp_path):
    log = FlakyLog(tmp_path / "q.db")
    journal = tmp_path / "j.jsonl"
    sink = RecordSink(log, journal_path=journal)
    log.failing = True
    for i in range(4):
        sink.append(_rec(i))
    assert sink.close() == journal and journal.exists()
    log.failing = False
    again = RecordSink(log, journal_path=journal)
    assert again.pending == 4
    assert again.retry() == 4 and again.close() is None
    assert _seqs(log.inner) == [0, 1, 2, 3]


def test_crash_between_log_commit_and_journal_rewrite_appends_nothing_twice(tmp_path):
    log = FlakyLog(tmp_path / "q.db")
    journal = tmp_path / "j.jsonl"
    sink = RecordSink(log, journal_path=journal)
    log.failing = True
    for i in range(3):
        sink.append(_rec(i))
    # the log committed the first two, then the process died before the journal was rewritten
    for line in journal.read_text().splitlines()[:2]:
        obj = json.loads(line)
        log.inner.append(record_from_dict(obj["record"]), uid=obj["uid"])
    log.failing = False
    again = RecordSink(log, journal_path=journal)
    assert again.pending == 1 and again.counters["replayed_known"] == 2
    assert again.retry() == 1 and again.close() is None
    assert _seqs(log.inner) == [0, 1, 2]


def test_torn_tail_is_cut_and_bad_lines_are_kept(tmp_path):
    log = FlakyLog(tmp_path / "q.db")
    journal = tmp_path / "j.jsonl"
    sink = RecordSink(log, journal_path=journal)
    log.failing = True
    for i in range(2):
        sink.append(_rec(i))
    lines = journal.read_text().splitlines()
    journal.write_text(lines[0] + "\n" + "not json\n" + lines[1] + "\n" + '{"v":1,"uid":"x"')
    log.failing = False
    again = RecordSink(log, journal_path=journal)
    assert again.pending == 2 and "not records" in again.problem
    assert again.retry() == 2
    assert again.close() == journal  # the unreadable line stays, named
    assert journal.read_text() == "not json\n"
    assert _seqs(log.inner) == [0, 1]


def test_unwritable_journal_and_log_hold_in_memory_then_recover(tmp_path, capsys):
    log = FlakyLog(tmp_path / "q.db")
    (tmp_path / "missing").write_text("a file, not a folder")  # the journal cannot be made
    sink = RecordSink(log, journal_path=tmp_path / "missing" / "j.jsonl")
    log.failing = True
    sink.append(_rec(0))
    assert sink.unsaved == 1 and "NOT durable" in sink.problem
    log.failing = False
    assert sink.retry() == 1 and sink.pending == 0 and sink.problem is None
    log.failing = True
    sink.append(_rec(1))
    assert sink.close() is None  # nowhere to go: printed on stderr, never silently dropped
    err = capsys.readouterr().err
    assert err.startswith("unsaved quality record: ")
    obj = json.loads(err.split(": ", 1)[1])
    assert record_from_dict(obj["record"]).extra["i"] == 1


def test_closed_log_is_log_trouble_not_an_exception(tmp_path):
    log = QualityLog(tmp_path / "q.db")
    sink = RecordSink(log, journal_path=tmp_path / "j.jsonl")
    log.close()
    sink.append(_rec(0))
    assert sink.pending == 1 and "closed" in sink.problem
    assert sink.close() == tmp_path / "j.jsonl"
    with QualityLog(tmp_path / "q.db") as log2:
        assert RecordSink(log2, journal_path=tmp_path / "j.jsonl").close() is None
        assert _seqs(log2) == [0]


def test_not_a_record_is_a_programming_error(tmp_path):
    sink = RecordSink(QualityLog(tmp_path / "q.db"), journal_path=tmp_path / "j.jsonl")
    with pytest.raises(ValueError, match="QualityRecord"):
        sink.append({"seq": 1})  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------------
# SIGKILL at random points: every acknowledged pair in the log exactly once
#
# The child is the service's records stage: it reads pairs from a spool the test fills (as a
# camera would), makes each pair's quality record and appends it to a RecordSink over a log
# that fails in bursts (disk full), so records go to the journal and back. A pair is
# ACKNOWLEDGED when sink.append returned for its record (then it is committed to the log or
# fsync'ed to the journal); the child prints "ack <seq>" only then. The test kills the child
# with SIGKILL at random moments (during log commits, journal appends, journal rewrites,
# replays), restarts it (start="new": the pairs written while it was down are a camera's
# loss, not the log's), and at the end checks every acknowledged pair is in the log once.

_CHILD = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from controller.quality.log import QualityLog, QualityRecord, utc_iso
    from controller.quality.journal import RecordSink
    from protocol.spool import SpoolReader

    db, journal, spool = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3])

    class Flaky:
        # fails in bursts (disk full for a while), so records go to the journal and back
        def __init__(self, log):
            self.log, self.calls = log, 0
        def append(self, record, *, uid=None):
            self.calls += 1
            if (self.calls // 7) % 3 == 1:
                raise OSError(28, "No space left on device")
            return self.log.append(record, uid=uid)
        def has_uid(self, uid):
            return self.log.has_uid(uid)

    sink = RecordSink(Flaky(QualityLog(db)), journal_path=journal)
    reader = SpoolReader(spool, start="new")
    print("ready", sink.pending, flush=True)
    n = 0
    while True:
        frame = reader.poll()
        if frame is None:
            time.sleep(0.001)  # the child's own idle wait, not a test's
            continue
        rec = QualityRecord(t_s=frame.t_s, wall_time=utc_iso(1.7e9 + frame.t_s),
                            seq=frame.seq, board_id=frame.board_id, board_position_mm=0.0,
                            ok=True, pitch_mm=1.5)
        sink.append(rec)
        print("ack", frame.seq, flush=True)  # acknowledged: durable in the log or journal
        n += 1
        if n % 5 == 0:
            sink.retry()
""")


def test_sigkill_at_random_points_loses_no_acknowledged_pair(tmp_path):
    db, journal, spool = tmp_path / "q.db", tmp_path / "q.db.journal.jsonl", tmp_path / "spool"
    writer = SpoolWriter(spool, keep=1000, fsync=False)
    seq = 0

    def camera(n: int) -> None:
        nonlocal seq
        for _ in range(n):
            seq += 1
            writer.write(Frame(seq=seq, t_s=0.01 * seq, image_a=None, image_b=None,
                               counts_a=seq, counts_b=seq, speed_mm_s=600.0, board_id=7))

    rng = random.Random(1414)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    acked: list[int] = []
    replayed = 0
    for _run in range(8):
        child = subprocess.Popen([sys.executable, "-c", _CHILD, str(db), str(journal),
                                  str(spool)], stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True, cwd=REPO, env=env)
        first = child.stdout.readline().split()
        assert first and first[0] == "ready", child.stderr.read()
        replayed += int(first[1])
        wanted = rng.randint(1, 40)
        camera(wanted + rng.randint(0, 20))  # more pairs than the kill lets it acknowledge
        for _ in range(wanted):  # wait for acknowledgements (poll the pipe, no sleep)
            line = child.stdout.readline()
            assert line.startswith("ack"), child.stderr.read()
            acked.append(int(line.split()[1]))
        child.send_signal(signal.SIGKILL)  # lands anywhere: log commit, journal write, rewrite
        rest, _ = child.communicate()
        # whole lines only: the kill may land inside the flush of one (an "ack" cut short,
        # "ack 1" of "ack 12", acknowledges nothing the parent may count on)
        whole = rest.split("\n")[:-1]
        acked += [int(ln.split()[1]) for ln in whole if ln.startswith("ack ")]
        assert child.returncode == -signal.SIGKILL
    with QualityLog(db) as log:
        assert RecordSink(log, journal_path=journal).close() is None  # the last replay
        logged = [r.seq for r in log.records()]
    assert len(logged) == len(set(logged)), "a pair was logged twice"
    lost = set(acked) - set(logged)
    assert not lost, f"acknowledged but not in the log: {sorted(lost)[:5]}"
    assert len(acked) >= 8 and replayed > 0  # the kills did leave journals to replay


# --------------------------------------------------------------------------------------------
# fuzz: any journal content opens; nothing in it is lost or raises


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(st.lists(st.one_of(st.binary(max_size=60), st.just(None)), max_size=6))
def test_any_journal_content_opens_and_keeps_what_it_cannot_replay(tmp_path_factory, parts):
    d = tmp_path_factory.mktemp("j")
    good = _record_line(d)
    lines = [good if p is None else p.replace(b"\n", b" ") for p in parts]
    journal = d / "j.jsonl"
    journal.write_bytes(b"\n".join(lines) + (b"\n" if lines else b""))
    with QualityLog(d / "q.db") as log:
        sink = RecordSink(log, journal_path=journal)
        n_good = parts.count(None)
        assert sink.pending == min(n_good, 1)  # the same uid appears once
        sink.retry()
        left = sink.close()
        assert len(log) == min(n_good, 1)
    bad = [p for p in parts if p is not None and p.strip()]
    if left is None:
        assert not journal.exists() and not any(_is_record_line(p) for p in bad)
    else:
        kept = [ln for ln in journal.read_bytes().split(b"\n") if ln.strip()]
        assert left == journal and len(kept) == len(bad)  # every unreadable line kept


def _record_line(d: Path) -> bytes:
    obj = {"v": 1, "uid": "u" * 32, "record": record_to_dict(_rec(1))}
    return json.dumps(obj).encode()


def _is_record_line(data: bytes) -> bool:
    try:
        obj = json.loads(data)
        record_from_dict(obj["record"])
        return isinstance(obj["uid"], str)
    except Exception:  # noqa: BLE001 - anything else is not a record line
        return False
