"""The control path waits for no database commit; the record comes after the setpoint.

Judged by the order of events, never by time: a quality log whose commits are held back by a
gate shows that the service writes its setpoints for pair after pair while no record is
committed, that each pair's feed setpoint went out before its record was committed, and that
the records then arrive, in order, once each, in fewer commits than records (batched).
"""

from __future__ import annotations

import asyncio
import gc
import sys
import threading
import time
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from config.machine import load_machine
from controller.quality.journal import RecordSink
from controller.quality.log import QualityLog, QualityRecord, RecordRefusedError, utc_iso
from controller.service import latency
from controller.service import records as quality_records
from controller.service.events import EventLog
from controller.service.frame_result import FrameResult
from controller.service.latency import GcPauses, tune_for_latency
from controller.service.supervisor import SafetyState
from planer.hil import Scenario, sim_config_for
from protocol.frames import Frame
from tests.support.plant_support import record_frames, run_for, truth_measurer

SCENARIO = Scenario(runout_um=(0.0, 4.0, -2.0, 2.0), initial_feed_mm_s=800.0)
BACKSTOP_S = 60.0


class GatedLog:
    """A real quality log whose commits wait for ``gate`` and are noted in ``events``."""

    def __init__(self, path, events: list, gate: threading.Event) -> None:
        self.log = QualityLog(path)
        self.events = events
        self.gate = gate
        self.commits = 0

    def append(self, record, *, uid=None):
        return self.append_many([record], uids=[uid])[0]

    def append_many(self, records, *, uids=None):
        assert self.gate.wait(BACKSTOP_S), "the test never opened the gate"
        ids = self.log.append_many(records, uids=uids)
        self.commits += 1
        self.events.append(("commit", tuple(r.seq for r in records)))
        return ids

    def __getattr__(self, name):
        return getattr(self.log, name)


def _real_time_plant(tmp_path, log):
    """The in-process plant with the service as ``planer serve`` runs it (threaded)."""
    from controller.service.service import Service
    from planer.hil import InProcessPlant

    cfg = load_machine()
    cfg = cfg.with_changes(log=replace(cfg.log, path=tmp_path / "q.sqlite"))
    frames: dict = {}
    plant = InProcessPlant(cfg, sim_config_for(SCENARIO), render_images=False,
                           measurer_factory=lambda shape: truth_measurer(frames), log=None)
    record_frames(plant, frames)
    plant.service = Service(cfg, plc=plant.plc, piezo=plant.piezo, rig=plant.rig, log=log,
                            clock=plant.clock, threaded=True,
                            measurer_factory=lambda shape: truth_measurer(frames),
                            pairs_per_s=plant.sim_cfg.camera.pairs_per_s)
    plant.service.keep_results = True
    return plant


def test_setpoints_go_out_while_no_record_is_committed_and_records_follow_in_order(tmp_path):
    events: list = []
    gate = threading.Event()
    gate.set()  # open while the service comes up
    log = GatedLog(tmp_path / "q.sqlite", events, gate)

    async def main():
        plant = _real_time_plant(tmp_path, log)
        svc = plant.service
        write_feed = plant.plc.write_feed

        async def noting_write_feed(feed_mm_s):
            await write_feed(feed_mm_s)
            events.append(("feed", svc.pipeline_seq))

        plant.plc.write_feed = noting_write_feed
        svc.pipeline_seq = None
        handle = svc.pipeline.handle

        async def noting_handle(frame, now_s=None):
            svc.pipeline_seq = frame.seq
            return await handle(frame, now_s)

        svc.pipeline.handle = noting_handle
        await run_for(plant, 2.0)
        assert svc.state is SafetyState.RUN
        svc.records.flush()  # the records of the start-up pairs are in
        gate.clear()  # from now on no commit can finish
        commits_before = log.commits
        events.clear()
        held = await run_for(plant, 1.0)
        assert held and log.commits == commits_before  # the pairs went through, no commit
        assert all(r.applied for r in held)
        # none of them reached the log: they wait in the journal. The status is a snapshot the
        # journal thread publishes as it takes the records: wait (bounded) until it has them all
        deadline = time.monotonic() + BACKSTOP_S
        while svc.records.pending < len(held) and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        queued = svc.records.pending
        gate.set()
        svc.records.flush()  # writes what is queued
        await plant.close()
        return held, queued, commits_before

    held, queued, commits_before = asyncio.run(main())
    seqs = [r.seq for r in held]
    assert queued >= len(held)  # the held pairs' records waited for the log (journal)
    fed = [s for kind, s in events if kind == "feed"]
    assert set(seqs) <= set(fed)  # every applied pair's feed setpoint went out ...
    first_commit = next(i for i, e in enumerate(events) if e[0] == "commit")
    assert all(e[0] == "feed" for e in events[:first_commit])  # ... before any record of them
    committed = [s for kind, batch in events if kind == "commit" for s in batch]
    assert committed == seqs  # then the records, in order, once each
    commits = sum(1 for kind, _ in events if kind == "commit")
    assert commits < len(seqs)  # batched: what queued up went in one commit
    with QualityLog(tmp_path / "q.sqlite", create=False) as check:
        logged = [r.seq for r in check.records()]
    assert logged[-len(seqs):] == seqs and len(logged) == len(set(logged))


def _result(seq: int) -> tuple[FrameResult, Frame]:
    r = FrameResult(seq=seq, ok=False, error="measurement failed: test", measurement=None,
                    knife_widths_mm=(), applied=False, feed_setpoint_mm_s=600.0,
                    offsets_um=(0.0,) * 4, state="run", t_s=0.01 * seq, latency_s=0.001)
    f = Frame(seq=seq, t_s=0.01 * seq, image_a=None, image_b=None, counts_a=seq, counts_b=seq,
              speed_mm_s=600.0, board_id=1)
    return r, f


def test_a_stuck_database_never_makes_a_pair_wait(tmp_path, monkeypatch):
    # write-ahead: the records wait in the journal, not in the pipeline (was: the next pair
    # waited for the database beyond MAX_QUEUED records)
    monkeypatch.setattr(quality_records, "MAX_QUEUED", 3)
    gate = threading.Event()
    log = GatedLog(tmp_path / "q.sqlite", [], gate)
    records = quality_records.QualityRecords(load_machine(), log, EventLog(),
                                             on_health=lambda ok: None, threaded=True)

    async def main():
        for seq in range(20):  # far beyond MAX_QUEUED, the database held at the gate
            await asyncio.wait_for(records.append(*_result(seq), 0.01 * seq), BACKSTOP_S)
        gate.set()

    asyncio.run(main())
    records.close(0.0)
    with QualityLog(tmp_path / "q.sqlite", create=False) as check:
        assert [r.seq for r in check.records()] == list(range(20))


def test_the_next_pair_waits_only_when_too_many_records_wait_for_the_journal(tmp_path,
                                                                              monkeypatch):
    from controller.quality import write_ahead

    monkeypatch.setattr(quality_records, "MAX_QUEUED", 3)
    gate = threading.Event()
    append = write_ahead.WriteAheadSink._append

    def gated_append(self, body):  # the local disk does not take the journal's writes
        assert gate.wait(BACKSTOP_S), "the test never opened the gate"
        return append(self, body)

    monkeypatch.setattr(write_ahead.WriteAheadSink, "_append", gated_append)
    log = QualityLog(tmp_path / "q.sqlite")
    records = quality_records.QualityRecords(load_machine(), log, EventLog(),
                                             on_health=lambda ok: None, threaded=True)

    async def main():
        for seq in range(3):  # held at the gate or waiting behind it: at the limit
            await records.append(*_result(seq), 0.01 * seq)
        over = asyncio.ensure_future(records.append(*_result(3), 0.03))
        for _ in range(50):  # everything else the loop has to do, done
            await asyncio.sleep(0)
        blocked = not over.done()
        gate.set()
        await asyncio.wait_for(over, BACKSTOP_S)
        return blocked

    assert asyncio.run(main())  # only the journal could let it go, and the gate held it
    records.close(0.0)
    with QualityLog(tmp_path / "q.sqlite", create=False) as check:
        assert [r.seq for r in check.records()] == [0, 1, 2, 3]


def test_inline_records_are_written_before_the_pair_returns(tmp_path):
    # simulated time (threaded=False): deterministic, the record is in the log at once
    log = QualityLog(tmp_path / "q.sqlite")
    records = quality_records.QualityRecords(load_machine(), log, EventLog(),
                                             on_health=lambda ok: None, threaded=False)
    rid = asyncio.run(records.append(*_result(7), 0.07))
    assert rid == log.last_id and records.pending == 0 and records.batches == 0
    records.close(0.0)


# ---------------------------------------------------------------------------------------------
# batched commits: one transaction, all or nothing, exactly once


def _rec(i: int, **kw) -> QualityRecord:
    return QualityRecord(t_s=0.01 * i, wall_time=utc_iso(0.0), seq=i, board_id=1,
                         board_position_mm=0.0, ok=True, extra={"i": i}, **kw)


def test_append_many_is_one_transaction_and_skips_known_uids(tmp_path):
    with QualityLog(tmp_path / "q.db") as log:
        ids = log.append_many([_rec(0), _rec(1), _rec(2)], uids=["a", "b", "c"])
        assert ids == sorted(ids) and len(set(ids)) == 3
        again = log.append_many([_rec(1), _rec(3)], uids=["b", "d"])
        assert again[0] == ids[1] and again[1] > ids[2]  # a known uid: its stored id
        assert [r.seq for r in log.records()] == [0, 1, 2, 3]
        assert log.append_many([]) == []
        with pytest.raises(ValueError, match="one per record"):
            log.append_many([_rec(4)], uids=["e", "f"])


def test_append_many_writes_nothing_when_one_record_is_refused(tmp_path):
    with QualityLog(tmp_path / "q.db") as log:
        with pytest.raises(RecordRefusedError, match="seq"):
            log.append_many([_rec(0), replace(_rec(1), seq=10**20)])
        assert len(log) == 0


def test_sink_batches_go_to_the_journal_together_and_back_once(tmp_path):
    class Failing:
        def __init__(self):
            self.log = QualityLog(tmp_path / "q.db")
            self.failing = True

        def append(self, record, *, uid=None):
            if self.failing:
                raise OSError(28, "No space left on device")
            return self.log.append(record, uid=uid)

        def append_many(self, records, *, uids=None):
            if self.failing:
                raise OSError(28, "No space left on device")
            return self.log.append_many(records, uids=uids)

        def has_uid(self, uid):
            return self.log.has_uid(uid)

    log = Failing()
    sink = RecordSink(log, journal_path=tmp_path / "j.jsonl")
    assert sink.append_many([_rec(0), _rec(1)]) == [None, None]
    assert sink.pending == 2 and "No space left" in sink.problem
    assert len((tmp_path / "j.jsonl").read_text().splitlines()) == 2
    log.failing = False
    ids = sink.append_many([_rec(2), _rec(3)])  # the held ones first, in order
    assert sink.pending == 0 and sink.problem is None and ids == [3, 4]
    assert sink.append_many([_rec(4), _rec(5)]) == [5, 6]  # nothing held: one transaction
    assert sink.close() is None
    assert [r.seq for r in log.log.records()] == [0, 1, 2, 3, 4, 5]
    log.log.close()


def test_sink_batch_with_a_refused_record_keeps_every_record(tmp_path):
    with QualityLog(tmp_path / "q.db") as log:
        sink = RecordSink(log, journal_path=tmp_path / "j.jsonl")
        bad = replace(_rec(1), extra={"i": 1, "x": object()})  # not JSON: refused
        sink.append_many([_rec(0), bad, _rec(2)])
        assert sink.pending == 0 and sink.counters["rewritten"] == 1
        got = log.records()
        assert len(got) == 3 and got[0].seq == 0 and got[2].seq == 2  # none lost, in order
        assert not got[1].ok and "extra" in got[1].error  # the refused one says why
        assert sink.close() is None


# ---------------------------------------------------------------------------------------------
# the process tuning and the collector's pauses


def test_tune_for_latency_freezes_the_heap_and_shortens_the_switch_interval():
    before = sys.getswitchinterval()
    try:
        out = tune_for_latency(switch_interval_s=0.001)
        assert sys.getswitchinterval() == pytest.approx(0.001)
        assert out["previous_switch_interval_s"] == before
        assert out["frozen"] > 0 and gc.get_freeze_count() > 0
        with pytest.raises(ValueError, match="switch_interval_s"):
            tune_for_latency(switch_interval_s=0.0)
    finally:
        if (idle := latency.idle_collector()) is not None:
            idle.uninstall()
        gc.unfreeze()
        sys.setswitchinterval(before)


def test_gc_pauses_are_recorded_by_generation():
    with GcPauses() as pauses:
        gc.collect()
        gc.collect(0)
    s = pauses.summary()
    assert s["collections"] >= 2 and s["full"] >= 1
    assert s["max_pause_ms"] >= 0 and s["total_ms"] >= s["max_pause_ms"]
    with GcPauses() as none:
        pass
    assert none.summary() == {"collections": 0, "full": 0, "max_pause_ms": 0.0, "total_ms": 0.0}


def test_bench_figures_break_the_latency_down_from_the_results():
    from planer.benchmarks import service as bench

    frames = [SimpleNamespace(image_a=np.zeros((4, 6), np.uint8), seq=i) for i in range(3)]
    res = []
    for i, (vision, measure, checks) in enumerate([(2.0, 2.5, 0.0), (3.0, 4.0, 0.25),
                                                    (2.5, 3.0, 0.0)]):
        res.append(SimpleNamespace(
            seq=i, ok=True, applied=True, t_s=10.0 + i, latency_s=0.004,
            extra={"timing_ms": {"plc_read_ms": 0.1, "measure_ms": measure,
                                 "vision_ms": vision, "checks_ms": checks,
                                 "control_ms": 1.0}}))
    service = SimpleNamespace(results=res, records=SimpleNamespace(batches=2))
    put = {i: 10.0 + i - 0.001 for i in range(3)}  # 1 ms in the source
    stored = {i: 10.0 + i + 0.004 + 0.002 for i in range(3)}  # durable 2 ms after
    out = bench._latency_figures(service, put, stored, GcPauses(), frames=frames,
                                 rate_hz=100.0, workers=0)
    assert out["median_ms"] == pytest.approx(5.0) and out["max_ms"] == pytest.approx(5.0)
    assert out["breakdown_ms"]["queue"]["median"] == pytest.approx(1.0)
    assert out["breakdown_ms"]["handoff"]["max"] == pytest.approx(0.75)  # checks apart
    assert out["breakdown_ms"]["checks"]["max"] == pytest.approx(0.25)
    assert out["breakdown_ms"]["vision"]["median"] == pytest.approx(2.5)
    assert out["record_after_setpoint_ms"]["median"] == pytest.approx(2.0)
    assert out["pairs_per_commit"] == pytest.approx(1.5)
    assert out["meets"] == {"p99": True, "max": True, "p99_over_median": True}
    text = bench.text({**out, "modes": [out], "machine": {"cores": 2, "load_avg": [1.0]}})
    assert "median 5.00 ms" in text and "vision" in text


def test_bench_leaves_the_first_pairs_out_of_the_p99_but_not_out_of_the_max(monkeypatch):
    from planer.benchmarks import service as bench

    monkeypatch.setattr(bench, "WARMUP_PAIRS", 2)
    n = 12
    frames = [SimpleNamespace(image_a=np.zeros((4, 6), np.uint8), seq=i) for i in range(n)]
    lat_ms = [15.0, 9.0] + [3.0] * (n - 2)  # two cold first pairs, then the steady state
    res = [SimpleNamespace(seq=i, ok=True, applied=True, t_s=10.0 + i,
                           latency_s=lat_ms[i] * 1e-3, extra={}) for i in range(n)]
    service = SimpleNamespace(results=res, records=SimpleNamespace(batches=1))
    out = bench._latency_figures(service, {i: 10.0 + i for i in range(n)}, {}, GcPauses(),
                                 frames=frames, rate_hz=100.0, workers=0)
    assert out["p99_ms"] == pytest.approx(3.0) and out["median_ms"] == pytest.approx(3.0)
    assert out["max_ms"] == pytest.approx(15.0) and out["warmup_max_ms"] == pytest.approx(15.0)
    assert out["warmup_pairs"] == 2 and out["p99_all_ms"] > 9.0
    assert out["meets"]["p99"] and out["meets"]["max"]
    monkeypatch.setattr(bench, "WARMUP_PAIRS", 0)  # none apart: the first pairs count
    out = bench._latency_figures(service, {i: 10.0 + i for i in range(n)}, {}, GcPauses(),
                                 frames=frames, rate_hz=100.0, workers=0)
    assert out["p99_ms"] > 9.0 and not out["meets"]["p99"]


def test_a_pair_in_the_spool_wakes_the_service_without_a_poll_interval(tmp_path):
    # the asyncio side waits for the reader thread's word, not for its poll interval: with an
    # interval of an hour, next() returns the pair the reader thread delivers while it waits
    from controller.frames.source import SpoolFrameSource
    from protocol.spool import SpoolReader

    image = np.full((8, 12), 100, np.uint8)
    go = threading.Event()

    class OnePair(SpoolReader):
        delivered = False

        def poll(self):
            if self.delivered or not go.wait(BACKSTOP_S):
                return None
            self.delivered = True
            return Frame(seq=5, t_s=0.0, image_a=image, image_b=image, counts_a=1,
                         counts_b=2, speed_mm_s=600.0)

    (tmp_path / "spool").mkdir()
    source = SpoolFrameSource(OnePair(tmp_path / "spool"), poll_s=3600.0)

    async def main():
        waiting = asyncio.ensure_future(source.next())
        for _ in range(20):
            await asyncio.sleep(0)
        assert not waiting.done()
        go.set()  # the reader thread delivers the pair now
        return await asyncio.wait_for(waiting, BACKSTOP_S)

    try:
        frame = asyncio.run(main())
    finally:
        source.close()
    assert frame.seq == 5 and frame.image_a.shape == (8, 12)


class _Snap:
    def __init__(self, radius_mm=60.0, knives=4, problem=None):
        self.values = {"cutterhead_radius_mm": radius_mm, "knives": knives,
                       "spindle_rpm": 6000.0}
        self.knives, self.spindle_rpm, self._problem = knives, 6000.0, problem

    def __getitem__(self, name):
        return self.values[name]

    def problem(self):
        return self._problem


def test_the_measurer_is_set_up_for_the_plcs_facts_before_the_first_pair():
    from controller.service.measurement import MachineFacts, MeasurementStage

    built = []

    class Factory:
        takes_facts = True

        def __call__(self, shape, facts=None):
            built.append((shape, facts))
            return SimpleNamespace(measure=lambda a, b, **kw: SimpleNamespace(facts=facts))

    stage = MeasurementStage(None, Factory(), threaded=False)
    stage.measurer((6, 8))  # the configured image size, at start-up: no facts yet
    stage.prepare(_Snap())  # the PLC cycle's registers: set up for R and Z now
    assert built[-1] == ((6, 8), MachineFacts(60.0, 4, 6000.0))
    n = len(built)
    for snap in (_Snap(), _Snap(radius_mm=60.0 + 4e-4), None,
                 _Snap(radius_mm=float("nan"), problem="cutterhead_radius_mm is nan"),
                 _Snap(knives=6, problem="knives 6 refused")):
        stage.prepare(snap)  # the same facts, none, or registers that make no sense: nothing
    assert len(built) == n
    frame = SimpleNamespace(image_a=np.zeros((6, 8)), image_b=np.zeros((6, 8)), counts_a=1,
                            counts_b=2, speed_mm_s=600.0, board_id=1)
    error, meas = asyncio.run(stage.measure(frame, _Snap()))
    assert error is None and meas.facts.key == (60.0, 4) and len(built) == n  # no set-up now
    stage.prepare(_Snap(knives=6))
    assert built[-1][1].knives == 6 and len(stage._measurers) == 1  # the old facts' went
