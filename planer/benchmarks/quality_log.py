"""The quality log's write path: records per CPU-second through the write-ahead sinks.

``python -m planer.benchmarks.quality_log [--quick] [--json] [--heads N] [--separate]`` hands
records to a :class:`~controller.quality.write_ahead.WriteAheadSink` per head at ``rate_hz``
each, the heads' records interleaved, and waits until all are in the log. The heads are the
moulder's (``config/machine_moulder.toml``, four; ``--heads 1``: one, the single-head service's
``"main"``); as a moulder's service opens them, every head's sink joins ONE
:class:`~controller.quality.write_ahead.WriterGroup` (one connection to the SQLite file, one
journal thread, one database thread; each head its own journal). ``--separate`` gives each
head a group of its own instead (its own connection and two threads), for comparison. The
records are made beforehand, like a service's (a decimated profile on every tenth, the
timings, the passes and the marks in ``extra``), so what is measured is the sinks' own work:
each record checked, encoded, journalled (fsync) and inserted; ``--made`` hands in each record's
fields instead and the journal thread makes the record (``QualityRecord(**fields)``, its
checks), as the service's ``make`` does. ``cpu_ms_per_record`` is this
process's CPU less the feeding thread's (the writer threads, user and system),
``records_per_cpu_s`` its inverse; ``records_per_append`` and ``records_per_transaction`` show
the batching.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

RATE_HZ = 100.0
"""Records per second of each head (a camera's pairs)."""
RECORDS = 4000
"""Records in a full run (10 s at four heads x 100/s); ``quick``: :data:`QUICK_RECORDS`."""
QUICK_RECORDS = 1200
"""Records in a quick run."""
PROFILE_EVERY = 10
"""Every this many records carries an 800-point profile (as the service's records do)."""


def moulder_heads() -> tuple[str, ...]:
    """The moulder's heads, in order (``config/machine_moulder.toml``'s names)."""
    from config.machine import default_path, load_machine

    return tuple(h.name for h in load_machine(default_path("machine_moulder.toml")).heads)


def sample_records(n: int, *, heads: tuple[str, ...] | None = None,
                   seed: int = 1) -> list[Any]:
    """``n`` records like a moulder service's, the heads in turn (numbers from ``seed``).

    ``heads``: default :func:`moulder_heads`.
    """
    from controller.quality.log import QualityRecord, utc_iso

    heads = moulder_heads() if heads is None else heads

    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        widths = tuple(float(w) for w in 1.5 + 0.3 * rng.standard_normal(4))
        marks = [float(w) for w in 1.5 + 0.3 * rng.standard_normal(33)]
        extra: dict[str, Any] = {
            "state": "run", "safe_reason": None, "applied": True,
            "latency_ms": float(8 + rng.random()),
            "timing_ms": {k: float(rng.random()) for k in
                          ("plc_read_ms", "measure_ms", "vision_ms", "checks_ms", "control_ms")},
            "knife_widths_mm": list(widths),
            "passes": {"pass_pitch_mm": 1.49, "missing_passes": 0, "reliable_marks": 33,
                       "knife": [k % 4 for k in range(33)], "marks_cv": float(rng.random())},
            "piezo": {"limit_um": 20.0, "source": "machine.toml", "tables_refused": 0},
            "marks_mm": marks,
        }
        if i % PROFILE_EVERY == 0:
            x = np.linspace(0.0, 40.0, 800)
            extra["profile"] = {"x_mm": [round(float(v), 3) for v in x],
                                "height_um": [round(float(v), 1) for v in
                                              5 * np.sin(x * 4.2) + rng.standard_normal(800)]}
        out.append(QualityRecord(
            t_s=0.01 * i, wall_time=utc_iso(1.7e9 + 0.01 * i), seq=i // len(heads) + 1,
            board_id=1 + i // 400, board_position_mm=float(i % 400), ok=True,
            pitch_mm=1.49, mark_widths_mm=widths, uniformity_cv=float(rng.random() / 4),
            depth_um=5.0, shift_px=15.0, confidence=0.9, feed_setpoint_mm_s=598.5,
            piezo_offsets_um=(-0.6, 3.1, -3.6, 1.1), target_pitch_mm=1.5, passed=True,
            true_pitch_mm=1.5, true_uniformity_cv=0.22, extra=extra, roll_deg=0.41,
            roll_confidence=0.99, board_travel_m=0.36,
            knife_drift_um_per_m=(math.nan,) * 4, knife_reserve_um=(19.4, 16.9, 16.4, 18.9),
            jointing_state="fitting", head=heads[i % len(heads)]))
    return out


def run(quick: bool = False, *, heads: tuple[str, ...] | None = None,
        rate_hz: float = RATE_HZ, records: int | None = None, folder: Path | None = None,
        shared: bool = True, made: bool = False) -> dict[str, Any]:
    """Hand ``records`` records to a sink per head at ``rate_hz`` each; the figures.

    Parameters
    ----------
    quick : bool
        :data:`QUICK_RECORDS` records instead of :data:`RECORDS` (unless ``records`` is given).
    heads : tuple of str, optional
        The heads (default :func:`moulder_heads`).
    rate_hz : float
        Records per second of each head.
    records : int, optional
        Records in all.
    folder : Path, optional
        Where the log and journals go (default a new temporary folder, removed after).
    shared : bool
        Every head's sink in one :class:`~controller.quality.write_ahead.WriterGroup` (as a
        moulder's service); ``False``: each head a group (connection, threads) of its own.
    made : bool
        Hand in each record's fields; the journal thread makes the record
        (``QualityRecord(**fields)``, as the service's ``make``). Result key ``made``.
    """
    from core.checks import check_int, check_positive

    heads = moulder_heads() if heads is None else tuple(heads)
    if not heads:
        raise ValueError("heads must name at least one head, got none")
    n = check_int("records", QUICK_RECORDS if quick and records is None else
                  RECORDS if records is None else records, lo=1)
    rate = check_positive("rate_hz", rate_hz) * len(heads)
    recs: list[Any] = sample_records(n, heads=heads)
    if made:
        from dataclasses import fields

        names = [f.name for f in fields(recs[0])]
        recs = [{k: getattr(r, k) for k in names} for r in recs]
    if folder is not None:
        out = _run_in(Path(folder), heads, recs, rate, shared, made)
    else:
        with tempfile.TemporaryDirectory(prefix="planer-qlog-") as tmp:
            out = _run_in(Path(tmp), heads, recs, rate, shared, made)
    return {"rate_hz_per_head": rate_hz, **out}


def _run_in(folder: Path, heads: tuple[str, ...], recs: list[Any], rate: float,
            shared: bool, made: bool) -> dict[str, Any]:
    """:func:`run` in ``folder``: the sinks opened, fed at ``rate`` in all, closed."""
    from controller.quality.journal import default_journal_path
    from controller.quality.log import QualityLog, QualityRecord
    from controller.quality.write_ahead import (
        DB_WAIT_S,
        JOURNAL_WAIT_S,
        WriteAheadSink,
        WriterGroup,
    )

    n = len(recs)
    path = folder / "quality.sqlite"
    if shared:
        groups = [WriterGroup(QualityLog(path, machine_id="bench"))]
        logs: list[Any] = [groups[0].head_log() for _ in heads]
    else:
        groups = [WriterGroup(QualityLog(path, machine_id="bench")) for _ in heads]
        logs = [g.head_log() for g in groups]
    try:
        make = (lambda kw: QualityRecord(**kw)) if made else None
        sinks = [WriteAheadSink(log, journal_path=default_journal_path(path, head=h), make=make)
                 for log, h in zip(logs, heads, strict=True)]
        t0, c0, f0 = time.monotonic(), os.times(), time.thread_time()
        for i, rec in enumerate(recs):
            ahead = t0 + i / rate - time.monotonic()
            if ahead > 0:
                time.sleep(ahead)
            sinks[i % len(heads)].put(rec)
        done = all(s.wait_logged(60.0) for s in sinks)
        c1, f1, wall = os.times(), time.thread_time(), time.monotonic() - t0
        counts = [dict(s.state.counters) for s in sinks]
        commits = sum(g.transactions for g in groups)
        for s in sinks:
            s.close()
        stored = len(groups[0].log)
    finally:
        for g in groups:
            g.close()
    user = c1.user - c0.user
    system = c1.system - c0.system
    cpu = max(1e-9, user + system - (f1 - f0))
    appends = sum(c["batches"] for c in counts)
    return {
        "records": n, "logged": stored, "all_logged": done and stored == n,
        "heads": len(heads), "shared_writer": shared, "made": made, "wall_s": wall,
        "cpu_ms_per_record": cpu * 1e3 / n, "records_per_cpu_s": n / cpu,
        "user_ms_per_record": user * 1e3 / n, "system_ms_per_record": system * 1e3 / n,
        "journal_appends": appends, "db_transactions": commits,
        "records_per_append": n / appends if appends else None,
        "records_per_transaction": n / commits if commits else None,
        "journal_wait_s": JOURNAL_WAIT_S, "db_wait_s": DB_WAIT_S,
    }


def text(result: dict[str, Any]) -> str:
    """The readable lines of :func:`run`'s result."""
    r = result
    writers = ("one writer group" if r["shared_writer"] or r["heads"] == 1
               else "a writer group per head")
    if r.get("made"):
        writers += ", records made by the journal thread"
    return (f"quality log ({r['heads']} heads x {r['rate_hz_per_head']:g} records/s, "
            f"{writers}, {r['records']} records, all logged: {r['all_logged']}):\n"
            f"  writer CPU {r['cpu_ms_per_record']:.3f} ms a record "
            f"({r['records_per_cpu_s']:.0f} records per CPU-second; user "
            f"{r['user_ms_per_record']:.3f}, system {r['system_ms_per_record']:.3f} of the "
            f"process)\n  {r['records_per_append'] or 0:.1f} records an fsync'ed journal "
            f"append, {r['records_per_transaction'] or 0:.1f} a transaction")


def main(argv: list[str] | None = None) -> int:
    """``python -m planer.benchmarks.quality_log``: run and print (text or JSON)."""
    parser = argparse.ArgumentParser(prog="python -m planer.benchmarks.quality_log",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a shorter run")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--heads", type=int, default=None,
                        help="the first this many of the moulder's heads (1: the single head)")
    parser.add_argument("--separate", action="store_true",
                        help="each head its own writer group (connection, two threads)")
    parser.add_argument("--made", action="store_true",
                        help="hand in fields: the journal thread makes each record (as the "
                             "service's make)")
    args = parser.parse_args(argv)
    heads = None
    if args.heads is not None:
        every = moulder_heads()
        if not 1 <= args.heads <= len(every):
            parser.error(f"--heads must be 1..{len(every)}, got {args.heads}")
        heads = ("main",) if args.heads == 1 else every[:args.heads]
    result = run(args.quick, heads=heads, shared=not args.separate, made=args.made)
    print(json.dumps(result) if args.json else text(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
