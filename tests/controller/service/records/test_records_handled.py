"""A pair is handled only once its quality record is durable; its setpoints never wait for that.

In real time (``threaded``) the record goes to the journal on the journal thread after the
pair's setpoints went out. The pair counts as *handled* (counted ``ok`` / ``failed``, shown as
the status's last measurement, told to ``on_result``, kept in ``results``) only when the journal
says its record is fsync'ed. Judged by order and content with the journal's writes held at a
gate, never by time: while the gate is shut the pairs' setpoints go out and nothing is handled;
when it opens each pair is handled once, in order, after its record is durable.
"""

from __future__ import annotations

import asyncio
import threading
from dataclasses import replace

from config.machine import load_machine
from controller.quality import write_ahead
from controller.quality.log import QualityLog
from controller.service.supervisor import SafetyState
from planer.hil import Scenario, sim_config_for
from tests.support.plant_support import record_frames, run_for, truth_measurer

SCENARIO = Scenario(runout_um=(0.0, 4.0, -2.0, 2.0), initial_feed_mm_s=800.0)
BACKSTOP_S = 60.0


def _real_time_plant(tmp_path):
    """The in-process plant with the service's records as ``planer serve`` writes them."""
    from controller.service.service import Service
    from planer.hil import InProcessPlant

    cfg = load_machine()
    cfg = cfg.with_changes(log=replace(cfg.log, path=tmp_path / "q.sqlite"))
    frames: dict = {}
    plant = InProcessPlant(cfg, sim_config_for(SCENARIO), render_images=False,
                           measurer_factory=lambda shape: truth_measurer(frames), log=None)
    record_frames(plant, frames)
    plant.service = Service(cfg, plc=plant.plc, piezo=plant.piezo, rig=plant.rig,
                            log=QualityLog(tmp_path / "q.sqlite"), clock=plant.clock,
                            threaded=True, measurer_factory=lambda shape: truth_measurer(frames),
                            pairs_per_s=plant.sim_cfg.camera.pairs_per_s)
    return plant


async def _until(changed: asyncio.Event, predicate, what: str) -> None:
    """Wait on the event loop (the journal's answers arrive on it) until ``predicate()``.

    ``changed`` is set by every ``on_result``; checked and cleared with no await between.
    """
    while not predicate():
        changed.clear()
        try:
            await asyncio.wait_for(changed.wait(), BACKSTOP_S)
        except asyncio.TimeoutError:
            raise AssertionError(f"timed out waiting for {what}") from None


def test_a_pair_is_handled_only_after_its_record_is_durable(tmp_path, monkeypatch):
    gate = threading.Event()
    gate.set()  # open while the service comes up
    durable_seqs: list[int] = []
    append = write_ahead.WriteAheadSink._append

    def gated_append(self, body):  # the journal's write and fsync wait for the gate
        assert gate.wait(BACKSTOP_S), "the test never opened the gate"
        start = append(self, body)
        durable_seqs.extend(e.record.seq for e in _entries_of(body))
        return start

    monkeypatch.setattr(write_ahead.WriteAheadSink, "_append", gated_append)

    async def main():
        plant = _real_time_plant(tmp_path)
        svc = plant.service
        svc.keep_results = True
        order: list[tuple[str, int]] = []
        svc.records.on_stored = lambda seq, at: order.append(("stored", int(seq)))
        changed = asyncio.Event()

        def on_result(r):
            order.append(("handled", int(r.seq)))
            changed.set()

        svc.on_result = on_result
        feeds: list[float] = []
        write_feed = plant.plc.write_feed

        async def noting_write_feed(feed_mm_s):
            await write_feed(feed_mm_s)
            feeds.append(feed_mm_s)

        plant.plc.write_feed = noting_write_feed
        started = await run_for(plant, 2.0)
        assert svc.state is SafetyState.RUN
        await _until(changed, lambda: len(svc.results) == len(started),
                     "the start-up pairs handled")
        counted = svc.status().counters
        last = svc.status().last_measurement
        gate.clear()  # from now on no record can become durable
        feeds.clear()
        held = await run_for(plant, 1.0)
        for _ in range(50):  # whatever else the loop has to do, done
            await asyncio.sleep(0)
        during = (len(svc.results), dict(svc.status().counters), svc.status().last_measurement)
        gate.set()
        await _until(changed, lambda: len(svc.results) == len(started) + len(held),
                     "the held pairs handled")
        await plant.close()
        return started, held, counted, last, during, feeds, order, svc

    started, held, counted, last, during, feeds, order, svc = asyncio.run(main())
    assert held and all(r.applied for r in held) and feeds  # control went on meanwhile ...
    n_during, counters_during, last_during = during
    assert n_during == len(started)  # ... but none of those pairs was handled
    assert counters_during.get("ok", 0) == counted.get("ok", 0)
    assert counters_during.get("failed", 0) == counted.get("failed", 0)
    assert last_during == last
    seqs = [r.seq for r in held]
    assert [r.seq for r in svc.results] == [r.seq for r in started] + seqs  # once, in order
    handled = [s for kind, s in order if kind == "handled"]
    assert handled == [r.seq for r in svc.results]
    for s in handled:  # each was durable before it was handled
        assert order.index(("stored", s)) < order.index(("handled", s))
        assert s in durable_seqs
    ok = sum(1 for r in svc.results if r.ok)
    assert svc.counters["ok"] == ok and svc.counters["failed"] == len(svc.results) - ok
    assert svc.status().last_measurement.seq == seqs[-1]
    with QualityLog(tmp_path / "q.sqlite", create=False) as check:
        assert [r.seq for r in check.records()] == [r.seq for r in svc.results]


def _entries_of(body: bytes):
    from controller.quality.journal import parse_line

    return [parse_line(raw) for raw in body.split(b"\n") if raw.strip()]


def test_without_a_log_a_pair_is_handled_at_once(tmp_path):
    from controller.service.service import Service
    from planer.hil import InProcessPlant

    cfg = load_machine()
    frames: dict = {}
    plant = InProcessPlant(cfg, sim_config_for(SCENARIO), render_images=False,
                           measurer_factory=lambda shape: truth_measurer(frames), log=None)
    record_frames(plant, frames)
    plant.service = Service(cfg, plc=plant.plc, piezo=plant.piezo, rig=plant.rig, log=None,
                            clock=plant.clock, threaded=True,
                            measurer_factory=lambda shape: truth_measurer(frames),
                            pairs_per_s=plant.sim_cfg.camera.pairs_per_s)
    plant.service.keep_results = True

    async def main():
        out = await run_for(plant, 1.0)
        seen = list(plant.service.results)
        await plant.close()
        return out, seen

    out, seen = asyncio.run(main())
    assert out and [r.seq for r in seen] == [r.seq for r in out]

