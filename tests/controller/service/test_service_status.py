"""``Service.status()``: a frozen snapshot that agrees with the service, in RUN and in SAFE.

Also the typed events' ``reason`` (safe-state entries name why without text parsing) and the
feed setpoint in force on failed records (docs/quality_log.md). Simulated time, the in-process
plant of ``tests/controller/service/test_service_loop.py``.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json

import pytest

from controller.quality.log import QualityLog
from controller.service.events import EventKind
from controller.service.status import ServiceStatus
from controller.service.supervisor import SOURCES, SafetyState
from core.errors import MeasurementError
from tests.controller.service.test_service_loop import make_plant
from tests.support.plant_support import run_for


def _check_agrees(svc, st: ServiceStatus) -> None:
    assert st.state == svc.state.value
    assert st.feed_setpoint_mm_s == svc.feed_setpoint_mm_s
    assert st.offsets_um == tuple(svc.offsets_um)
    assert dict(st.counters) == svc.counters
    assert set(st.missing) <= set(SOURCES)
    assert (st.safe_reason is None) == (st.state == "run")
    last = svc.results[-1] if svc.results else None
    if last is not None:
        m = st.last_measurement
        assert m is not None and m.seq == last.seq and m.ok == last.ok
        assert m.applied == last.applied and m.error == last.error
    doc = st.to_dict()
    assert json.loads(json.dumps(doc, allow_nan=False)) == doc  # plain JSON, no NaN


def test_status_is_a_frozen_snapshot_that_agrees_with_the_service(tmp_path):
    async def main():
        plant, _ = make_plant(tmp_path)
        await plant.start()
        svc = plant.service
        first = svc.status()
        assert first.state == "safe" and first.last_measurement is None  # starts in SAFE
        await run_for(plant, 3.0)
        st = svc.status()
        assert svc.state is SafetyState.RUN
        _check_agrees(svc, st)
        assert st.feed_actual_mm_s == pytest.approx(plant.plc.last.feed_actual_mm_s)
        assert st.amplifier_enabled and st.log_problem is None and st.records_pending == 0
        assert st.last_measurement.pitch_mm > 0
        with pytest.raises(dataclasses.FrozenInstanceError):
            st.state = "safe"  # type: ignore[misc]
        with pytest.raises(TypeError):
            st.counters["frames"] = 0  # type: ignore[index]
        frames = st.counters["frames"]
        await run_for(plant, 0.5)
        assert st.counters["frames"] == frames < svc.counters["frames"]  # a snapshot
        await plant.close()

    asyncio.run(main())


def test_safe_state_in_status_and_in_the_event_reason(tmp_path):
    async def main():
        plant, _ = make_plant(tmp_path)
        await plant.start()
        await run_for(plant, 3.0)
        svc = plant.service
        plant.can_fault("can_silence", 1.0)
        await run_for(plant, 0.6)
        st = svc.status()
        assert st.state == "safe" and "can" in st.missing
        _check_agrees(svc, st)
        safe = [e for e in svc.events if e.kind is EventKind.SAFE_STATE]
        ev = safe[-1]
        assert ev.reason and ev.text == f"safe state: {ev.reason}"
        assert "can gone" in ev.reason and ev.to_dict()["reason"] == ev.reason
        assert st.safe_reason == ev.reason
        assert all(e.reason is None for e in svc.events if e.kind is not EventKind.SAFE_STATE)
        assert st.offsets_um == (0.0,) * len(st.offsets_um) and not st.amplifier_enabled
        await plant.close()

    asyncio.run(main())


def test_failed_records_carry_the_feed_setpoint_in_force(tmp_path):
    async def main():
        plant, measurer = make_plant(tmp_path)
        await plant.start()
        await run_for(plant, 2.0)
        measurer.fail_with = MeasurementError("saturated pair")
        failed = await run_for(plant, 0.5)
        measurer.fail_with = None
        assert failed and all(not r.ok for r in failed)
        await plant.close()
        with QualityLog(tmp_path / "q.sqlite", create=False) as log:
            recs = {r.seq: r for r in log.records()}
        for r in failed:
            rec = recs[r.seq]
            assert not rec.ok and rec.feed_setpoint_mm_s is not None
            assert rec.feed_setpoint_mm_s == pytest.approx(r.feed_setpoint_mm_s)
        # every record names the feed in force (before the first write: the PLC's setpoint)
        assert all(recs[s].feed_setpoint_mm_s is not None for s in recs)
        # and each result names its record's id in the log
        with QualityLog(tmp_path / "q.sqlite", create=False) as log:
            ids = {r.seq: rid for rid, r in log.entries()}
        assert all(r.record_id == ids[r.seq] for r in failed)

    asyncio.run(main())


def test_a_pair_before_any_setpoint_was_written_records_the_plcs_setpoint(tmp_path):
    async def main():
        plant, _ = make_plant(tmp_path)
        await plant.start()
        svc = plant.service
        frames = []
        while not frames:
            frames = plant.machine.advance(plant.cfg.safety.cycle_s)
        # no cycle ran yet: the service wrote no feed; the pair reads the registers itself
        r = await svc.handle_frame(frames[0], now_s=plant.clock())
        assert svc.feed_setpoint_mm_s is None and r.feed_setpoint_mm_s is None
        plc_feed = plant.machine.register_values()["feed_setpoint_mm_s"]
        await plant.close()
        with QualityLog(tmp_path / "q.sqlite", create=False) as log:
            (rec,) = log.records()
        assert rec.seq == r.seq and rec.feed_setpoint_mm_s == pytest.approx(plc_feed)

    asyncio.run(main())
