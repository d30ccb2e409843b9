"""The quality log on a real PostgreSQL server: same records, same report, same CSV as SQLite.

The server is started by the test session (``tests/support/pg_support.py``); these tests skip with
the
reason where PostgreSQL or psycopg is missing.
"""

from __future__ import annotations

import json
import math
import random
import threading
from pathlib import Path

import pytest

from controller.quality.journal import RecordSink, default_journal_path
from controller.quality.log import (
    CSV_COLUMNS,
    QualityClass,
    QualityLog,
    QualityLogError,
    QualityRecord,
    database_url,
    is_database_url,
    open_quality_log,
    utc_iso,
)
from controller.quality.report import summarise
from tests.support import pg_support
from tests.support.old_logs import downgrade
from tests.support.pg_support import wait_until

pg_server = pg_support.pg_server  # the fixtures
fresh_db = pg_support.fresh_db

QC = QualityClass("fine-1.5", 1.5, 0.02, 0.08, 8.0)


def _record(i: int, *, rng: random.Random, machine_id: str | None = None) -> QualityRecord:
    ok = rng.random() > 0.15
    kw = dict(
        t_s=0.05 * i, wall_time=utc_iso(1.7e9 + 86400 * (i % 3) + i), seq=i,
        board_id=1 + i // 7, board_position_mm=rng.uniform(0, 4000), ok=ok,
        shift_px=rng.uniform(30, 60), confidence=rng.random(),
        feed_setpoint_mm_s=rng.uniform(100, 900) * 0.1 * 7,
        piezo_offsets_um=[rng.uniform(-20, 20), math.nan, 0.1 * 3, -0.0],
        target_pitch_mm=1.5, true_pitch_mm=rng.choice([None, 1.5 + rng.gauss(0, 0.01)]),
        extra={"state": rng.choice(["run", "safe"]), "safe_reason": None, "i": i,
               "nested": {"x": [1, 2.5, None], "s": "\u00fc\u00df \\ \"q\""},
               "profile": {"x_mm": [0.1 * k for k in range(5)], "height_um": [1e-300, 3.0]}},
        machine_id=machine_id,
    )
    if ok:
        kw.update(pitch_mm=1.5 + rng.gauss(0, 0.02), uniformity_cv=rng.random() * 0.1,
                  mark_widths_mm=[rng.uniform(1, 2), math.nan, 1.2, 0.7],
                  depth_um=rng.uniform(0, 10), passed=rng.random() < 0.7)
    else:
        kw["error"] = rng.choice(["registration failed: confidence 0.2",
                                  "unreadable pair: b.png missing", "marks: none found"])
    return QualityRecord(**kw)


def _key(rec: QualityRecord) -> tuple:
    return tuple((k, tuple("nan" if math.isnan(x) else x for x in v) if isinstance(v, tuple)
                  else v) for k, v in vars(rec).items())


def test_url_forms():
    url = "postgresql://u@127.0.0.1:5432/fleet"
    assert is_database_url(url) and is_database_url(Path(url))  # Path folds "//" to "/"
    assert database_url(Path(url)) == url and database_url("postgres:/u@h/db") == "postgres://u@h/db"
    assert not is_database_url("runs/q.sqlite") and not is_database_url(Path("postgresql.db"))


def test_same_records_same_report_and_csv_as_sqlite(fresh_db, tmp_path):
    rng = random.Random(13)
    recs = [_record(i, rng=rng) for i in range(40)]
    csvs = {}
    back = {}
    for name, target in (("sqlite", tmp_path / "q.sqlite"), ("pg", fresh_db)):
        with open_quality_log(target, machine_id="planer-7") as log:
            ids = [log.append(r) for r in recs]
            log.set_quality_class(QC)
        with open_quality_log(target, create=False) as log:  # a reader: nothing to create
            assert ids == sorted(ids) and log.last_id == ids[-1] and len(log) == len(recs)
            back[name] = log.records()
            assert log.quality_class() == QC
            assert [r.seq for r in log.records(board_id=2)] == [r.seq for r in recs
                                                                 if r.board_id == 2]
            assert [r.seq for r in log.records(since_seq=35)] == list(range(35, 40))
            assert [r.seq for r in log.records(after_id=ids[9])] == list(range(10, 40))
            assert log.records(machine_id="other") == []
            csvs[name] = tmp_path / f"{name}.csv"
            assert log.export_csv(csvs[name]) == len(recs)
    stamped = [_key(QualityRecord(**{**vars(r), "machine_id": "planer-7"})) for r in recs]
    assert [_key(r) for r in back["sqlite"]] == stamped
    assert [_key(r) for r in back["pg"]] == stamped
    assert csvs["pg"].read_bytes() == csvs["sqlite"].read_bytes()
    assert csvs["pg"].read_text().splitlines()[0] == ",".join(CSV_COLUMNS)
    assert (json.dumps(summarise(back["pg"], quality_class=QC), sort_keys=True)
            == json.dumps(summarise(back["sqlite"], quality_class=QC), sort_keys=True))


def test_nul_in_error_is_refused_naming_the_field_and_sink_keeps_it(fresh_db, tmp_path):
    bad = QualityRecord(t_s=0.0, wall_time=utc_iso(1.7e9), seq=0, board_id=0,
                        board_position_mm=0.0, ok=False, error="bad\x00text")
    with QualityLog(fresh_db) as log:
        with pytest.raises(ValueError, match="error"):
            log.append(bad)
        assert len(log) == 0
        sink = RecordSink(log, journal_path=tmp_path / "j.jsonl")
        sink.append(bad)
        assert sink.close() is None and len(log) == 1
        (kept,) = log.records()
        assert not kept.ok and "record refused" in kept.error


def test_several_machines_share_one_database(fresh_db):
    rng = random.Random(5)
    n = 60
    machines = ("planer-1", "planer-2", "planer-3")

    def writer(mid: str) -> None:
        with QualityLog(fresh_db, machine_id=mid) as log:  # one connection per writer
            for i in range(n):
                log.append(_record(i, rng=random.Random(hash((mid, i)))), uid=f"{mid}-{i}")

    with QualityLog(fresh_db) as first:  # creates the tables before the writers race
        first.append(_record(0, rng=rng, machine_id="setup"))
    threads = [threading.Thread(target=writer, args=(m,)) for m in machines]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    with QualityLog(fresh_db, create=False) as log:
        assert len(log) == 1 + n * len(machines)
        for m in machines:
            assert [r.seq for r in log.records(machine_id=m)] == list(range(n))
        # a replayed uid is stored once, whichever writer sends it again
        before = len(log)
        rid = log.append(_record(0, rng=rng), uid="planer-2-0")
        assert len(log) == before and log.has_uid("planer-2-0") and rid > 0


def test_racing_first_writers_create_the_tables_once(fresh_db):
    errors: list[BaseException] = []

    def open_and_write(k: int) -> None:
        try:
            with QualityLog(fresh_db, machine_id=f"m{k}") as log:
                log.append(_record(k, rng=random.Random(k)))
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=open_and_write, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    with QualityLog(fresh_db, create=False) as log:
        assert sorted(r.machine_id for r in log.records()) == ["m0", "m1", "m2", "m3"]


def test_reader_of_an_empty_database_and_foreign_tables(fresh_db):
    import psycopg

    with pytest.raises(QualityLogError, match="holds no quality log"):
        QualityLog(fresh_db, create=False)
    with psycopg.connect(fresh_db, autocommit=True) as conn:
        conn.execute("CREATE TABLE meta (x int)")
    with pytest.raises(QualityLogError, match="not a planer quality log"):
        QualityLog(fresh_db)


def test_unreachable_database_is_one_line_naming_it(pg_server):
    from tests.support.pg_support import _free_port

    port = _free_port()  # nothing listens there
    url = f"postgresql://postgres:secret@127.0.0.1:{port}/fleet"
    with pytest.raises(OSError) as info:
        QualityLog(url, timeout_s=2.0)
    msg = str(info.value)
    assert f"127.0.0.1:{port}/fleet" in msg and "\n" not in msg and "secret" not in msg


def test_journal_of_a_database_log_lies_on_local_disk(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path))
    a = default_journal_path("postgresql://u:pw@db.plant:5433/fleet")
    assert a == default_journal_path(Path("postgresql://u:pw@db.plant:5433/fleet"))
    assert a.parent == tmp_path / "planer" and "pw" not in a.name
    assert "db.plant" in a.name and "5433" in a.name and "fleet" in a.name
    assert a != default_journal_path("postgresql://u@db.plant:5433/other")


def test_server_restart_mid_run_loses_nothing_and_stores_nothing_twice(pg_server, tmp_path):
    """Appends through the RecordSink while the server is killed and started again."""
    import psycopg

    url = pg_server.create_db()
    n_before, n_after = 40, 40
    journal = tmp_path / "fleet.journal.jsonl"
    log = QualityLog(url, machine_id="planer-9", timeout_s=2.0)
    log._store._retry_after_s = 0.0  # noqa: SLF001 - reconnect at every retry in this test
    sink = RecordSink(log, journal_path=journal)
    rng = random.Random(9)
    seq = 0

    def put(k: int) -> None:
        nonlocal seq
        for _ in range(k):
            sink.append(_record(seq, rng=rng))
            seq += 1

    restarted = threading.Event()

    def crash_and_restart() -> None:
        pg_server.stop("immediate")  # like a power cut of the database host
        restarted.set()

    try:
        put(n_before)
        assert sink.pending == 0 and len(log) == n_before
        killer = threading.Thread(target=crash_and_restart)
        killer.start()
        while not restarted.is_set():  # the loop runs on while the server goes away
            put(1)
        killer.join()
        put(n_after)  # the server is down: these wait in the journal
        assert sink.pending >= n_after and journal.exists()
        assert "kept in journal" in (sink.problem or "")
        pg_server.start()
        wait_until(lambda: sink.retry() >= 0 and sink.pending == 0, what="journal written")
        assert sink.close() is None and not journal.exists()
        with psycopg.connect(url) as conn:
            (n, distinct, lo, hi), = conn.execute(
                "SELECT COUNT(*), COUNT(DISTINCT seq), MIN(seq), MAX(seq) FROM records "
                "WHERE machine_id = 'planer-9'").fetchall()
            (uids,), = conn.execute("SELECT COUNT(DISTINCT uid) FROM record_uids").fetchall()
        assert (n, distinct, lo, hi) == (seq, seq, 0, seq - 1)  # 0 lost, 0 twice
        assert uids == seq
        assert sink.counters["journalled"] >= n_after
        assert [r.seq for r in log.records()] == list(range(seq))  # the order is kept
    finally:
        log.close()
        if not pg_server.port_open():
            pg_server.start()


def _report(argv, capsys) -> tuple[int, str, str]:
    from planer.cli import main

    code = main(["report", *argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_planer_report_on_a_database_matches_the_sqlite_file(fresh_db, tmp_path, capsys,
                                                           monkeypatch):
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    rng = random.Random(21)
    recs = [_record(i, rng=rng, machine_id=("planer-1", "planer-2")[i % 2]) for i in range(30)]
    db_file = tmp_path / "q.sqlite"
    for target in (db_file, fresh_db):
        with open_quality_log(target) as log:
            for r in recs:
                log.append(r)
            log.set_quality_class(QC)
    results = {}
    for name, target in (("sqlite", str(db_file)), ("pg", fresh_db)):
        for machine in (None, "planer-2")[:1 if name == "sqlite" else 2]:
            out_dir = tmp_path / f"fig-{name}-{machine}"
            out_dir.mkdir()
            csv_path = tmp_path / f"{name}-{machine}.csv"
            argv = [target, "--json", "--out", str(out_dir), "--csv", str(csv_path)]
            code, out, err = _report(argv + (["--machine", machine] if machine else []), capsys)
            assert code == 0, err
            summary = json.loads(out)
            assert summary["journal"] is None and summary["csv"] == str(csv_path)
            for k in ("log", "figures", "csv", "journal"):
                summary.pop(k)
            stem = "q" if name == "sqlite" else fresh_db.rsplit("/", 1)[-1]
            figures = sorted(p.name for p in out_dir.iterdir())
            assert figures and all(f.startswith(stem + "_") for f in figures)
            results[name, machine] = (summary, csv_path.read_bytes(),
                                      [f[len(stem):] for f in figures])
    assert results["pg", None] == results["sqlite", None]
    with open_quality_log(db_file, create=False) as log:  # one machine: as the file's export
        log.export_csv(tmp_path / "sqlite-2.csv", machine_id="planer-2")
    assert results["pg", "planer-2"][1] == (tmp_path / "sqlite-2.csv").read_bytes()
    assert results["pg", "planer-2"][0]["machine"] == "planer-2"
    assert results["pg", "planer-2"][1].count(b"\n") == 1 + 15
    assert results["pg", None][1].count(b"\n") == 1 + 30


def test_planer_report_unreachable_database_is_one_line_exit_2(pg_server, capsys):
    from tests.support.pg_support import _free_port

    port = _free_port()
    code, out, err = _report([f"postgresql://postgres@127.0.0.1:{port}/fleet"], capsys)
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and f"127.0.0.1:{port}/fleet" in err, err
    assert err.startswith("planer report: error:")


def test_documented_pass_rate_query_counts_as_python_does(fresh_db):
    import re
    from collections import defaultdict

    import psycopg

    doc = (Path(__file__).parents[3] / "docs" / "quality_log.md").read_text()
    query = re.findall(r"```sql\n(.*?)```", doc[doc.index("### Fleet queries"):], re.S)[0]
    rng = random.Random(3)
    recs = [_record(i, rng=rng, machine_id=f"planer-{i % 3}") for i in range(90)]
    with QualityLog(fresh_db) as log:
        for r in recs:
            log.append(r)
    want: dict = defaultdict(list)
    for r in recs:
        want[r.machine_id, r.wall_time[:10]].append(r)
    with psycopg.connect(fresh_db) as conn:
        rows = conn.execute(query).fetchall()
    assert len(rows) == len(want)
    for machine, day, n, failed, rate in rows:
        group = want[machine, day.date().isoformat()]
        judged = [r.passed for r in group if r.passed is not None]
        assert n == len(group) and failed == sum(not r.ok for r in group)
        assert float(rate) == pytest.approx(round(100 * sum(judged) / len(judged), 1))


def test_version_3_database_is_read_as_is_and_migrated_by_a_writer(fresh_db):
    import psycopg

    from controller.quality.log import SCHEMA_VERSION

    rng = random.Random(3)
    old = [_record(i, rng=rng, machine_id="planer-1") for i in range(5)]
    with QualityLog(fresh_db) as log:
        for r in old:
            log.append(r)
    with psycopg.connect(fresh_db, autocommit=True) as conn:  # the layout of version 3
        downgrade(conn.execute, 3)
    with QualityLog(fresh_db, create=False) as reader:
        assert reader.schema_version == 3
        assert [_key(r) for r in reader.records()] == [_key(r) for r in old]
    new = QualityRecord(t_s=1.0, wall_time=utc_iso(1.7e9), seq=99, board_id=3,
                        board_position_mm=10.0, ok=True, pitch_mm=1.5, depth_um=4.0,
                        roll_deg=0.4, roll_confidence=0.9, calibration_state="applied",
                        calibration_gain=0.8, calibration_gain_confidence=0.95,
                        kinematic_depth_um=4.6, uncalibrated_depth_um=3.2, machine_id="planer-1")
    with QualityLog(fresh_db) as writer:
        assert writer.schema_version == SCHEMA_VERSION
        writer.append(new)
        back = writer.records()
    assert [_key(r) for r in back] == [_key(r) for r in old + [new]]
    assert back[0].calibration_state is None and back[-1].calibration_state == "applied"


def test_append_many_is_one_transaction_on_postgres_too(fresh_db):
    # Batched commits (the service's record writer) reach PostgreSQL as one transaction: known
    # uids give their stored ids, and one refused record stores none of the batch.
    rng = random.Random(11)
    recs = [_record(i, rng=rng) for i in range(5)]
    with QualityLog(fresh_db) as log:
        ids = log.append_many(recs[:3], uids=["a", "b", "c"])
        assert ids == sorted(ids) and len(set(ids)) == 3
        again = log.append_many([recs[1], recs[3]], uids=["b", "d"])
        assert again[0] == ids[1] and again[1] > ids[2]
        assert [r.seq for r in log.records()] == [r.seq for r in recs[:4]]
        bad = QualityRecord(t_s=0.0, wall_time=utc_iso(1.7e9), seq=9, board_id=0,
                            board_position_mm=0.0, ok=False, error="bad\x00text")
        with pytest.raises(ValueError, match="error"):
            log.append_many([recs[4], bad], uids=["e", "f"])
        assert len(log) == 4 and log.append_many([]) == []
