"""SQLite's batch insert (one ``executemany``) pinned to the row-by-row insert it replaced.

Random batches (uids new, repeated within a batch, known from an earlier batch, or none) go
into two fresh logs, one through ``insert_many``, one through the earlier row-by-row loop:
the returned ids and both tables, row for row, must be the same.
"""

from __future__ import annotations

import sqlite3
import uuid

import numpy as np
import pytest

from controller.quality.log import QualityLog, QualityRecord, utc_iso
from controller.quality.schema import column_names
from controller.quality.store_sqlite import _UIDS_TABLE


def _old_insert_many(store, rows, uids) -> list[int]:
    """The row-by-row insert as it was (one transaction)."""
    conn = store._connection()
    cols = column_names(store.schema_version)[1]
    sql = f"INSERT INTO records ({', '.join(cols)}) VALUES ({', '.join('?' * len(cols))})"
    ids: list[int] = []
    conn.execute("BEGIN IMMEDIATE")
    if any(u is not None for u in uids):
        conn.execute(_UIDS_TABLE)
    for row, uid in zip(rows, uids, strict=True):
        known = None if uid is None else conn.execute(
            "SELECT record_id FROM record_uids WHERE uid = ?", (uid,)).fetchone()
        if known is not None:
            ids.append(int(known[0]))
            continue
        rid = int(conn.execute(sql, tuple(row)[:len(cols)]).lastrowid)
        if uid is not None:
            conn.execute("INSERT INTO record_uids (uid, record_id) VALUES (?, ?)", (uid, rid))
        ids.append(rid)
    conn.execute("COMMIT")
    return ids


def _tables(path) -> tuple[list, list]:
    conn = sqlite3.connect(path)
    try:
        recs = conn.execute("SELECT * FROM records ORDER BY record_id").fetchall()
        has = conn.execute("SELECT 1 FROM sqlite_master WHERE name = 'record_uids'").fetchone()
        uids = conn.execute("SELECT rowid, uid, record_id FROM record_uids ORDER BY rowid"
                            ).fetchall() if has else []
        return recs, uids
    finally:
        conn.close()


@pytest.mark.parametrize("seed", range(3))
def test_a_batch_stores_what_row_by_row_stored(tmp_path, seed):
    rng = np.random.default_rng(seed)
    new, old = QualityLog(tmp_path / "new.db", machine_id="m"), QualityLog(
        tmp_path / "old.db", machine_id="m")
    seen: list[str] = []
    n = 0
    try:
        for _ in range(12):
            rows, uids = [], []
            for _ in range(int(rng.integers(1, 30))):
                rec = QualityRecord(t_s=0.01 * n, wall_time=utc_iso(1.7e9 + n), seq=n,
                                    board_id=1, board_position_mm=float(n), ok=True,
                                    extra={"n": n})
                n += 1
                pick = rng.random()
                if pick < 0.15:
                    uid = None
                elif pick < 0.3 and seen:
                    uid = seen[int(rng.integers(0, len(seen)))]  # known, or earlier in batch
                else:
                    uid = uuid.UUID(int=int(rng.integers(0, 2**62))).hex
                    seen.append(uid)
                rows.append(new._row(rec, uid, None))
                uids.append(uid)
            assert new._call("insert_many", rows, uids) == _old_insert_many(
                old._store, rows, uids)
    finally:
        new.close()
        old.close()
    assert _tables(tmp_path / "new.db") == _tables(tmp_path / "old.db")


def test_ids_that_would_not_be_consecutive_go_row_by_row(tmp_path):
    # a deleted newest record: AUTOINCREMENT gives the next row an id past the largest held
    log = QualityLog(tmp_path / "q.db", machine_id="m")
    try:
        recs = [QualityRecord(t_s=0.0, wall_time=utc_iso(0.0), seq=i, board_id=1,
                              board_position_mm=0.0, ok=True) for i in range(5)]
        assert log.append_many(recs[:2], uids=["a", "b"]) == [1, 2]
        log._store._connection().execute("DELETE FROM records WHERE record_id = 2")
        assert log.append_many(recs[2:], uids=["c", "a", "d"]) == [3, 1, 4]
        assert [r.seq for r in log.records()] == [0, 2, 4]
    finally:
        log.close()
