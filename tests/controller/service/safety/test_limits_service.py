"""The service with an amplifier whose stroke differs from machine.toml's, on simulated time.

The amplifier (10 um) reports its limits over CAN; machine.toml says 20 um; the runout (up to
15 um) asks for more than either. The service must use 10 um and say so, never send more, never
cycle through the safe state; a table the amplifier refuses anyway is re-planned, never resent;
after a reconnect the limits are read again.
"""

from __future__ import annotations

import asyncio
from dataclasses import replace

import numpy as np

from config.machine import load_machine
from controller.quality.log import QualityLog
from controller.service.events import EventKind
from controller.service.supervisor import SafetyState
from planer.hil import Scenario, sim_config_for
from planer.hil.summary import limits_report
from tests.controller.service.test_service_loop import TruthMeasurer
from tests.support.plant_support import record_frames, run_for

AMP_UM, CONFIG_UM = 10.0, 20.0
SCENARIO = Scenario(runout_um=(0.0, 15.0, -8.0, 5.0), initial_feed_mm_s=800.0,
                    amp_stroke_um=AMP_UM, stroke_um=CONFIG_UM)


def _plant(tmp_path):
    from planer.hil import InProcessPlant

    cfg = load_machine()
    cfg = cfg.with_changes(stroke_um=CONFIG_UM, log=replace(cfg.log, path=tmp_path / "q.sqlite"))
    frames: dict = {}
    plant = InProcessPlant(cfg, sim_config_for(SCENARIO), measurer_factory=lambda s: TruthMeasurer(
        frames), render_images=False)
    record_frames(plant, frames)
    return plant


def _watch_tables(plant):
    """Record every table the amplifier got (accepted or refused), with its verdict."""
    machine = plant.machine
    accept = machine.set_piezo_offsets
    got: list[tuple[tuple[float, ...], bool]] = []

    def recording(offsets_um):
        table = tuple(round(float(v), 3) for v in offsets_um)
        try:
            accept(offsets_um)
        except ValueError:
            got.append((table, False))
            raise
        got.append((table, True))

    machine.set_piezo_offsets = recording
    return got


def _events(svc, kind):
    return [e for e in svc.events if e.kind is kind]


def test_the_amplifiers_smaller_stroke_is_used_and_said(tmp_path):
    async def main():
        plant = _plant(tmp_path)
        tables = _watch_tables(plant)
        await plant.start()
        res = await run_for(plant, 5.0)
        svc = plant.service
        assert svc.state is SafetyState.RUN and svc.counters["safe_entries"] == 0
        assert svc.counters["recoveries"] == 1  # only the start
        (ev,) = _events(svc, EventKind.PIEZO_LIMITS)
        assert ev.data["limit_um"] == AMP_UM and ev.data["source"] == "amplifier"
        assert ev.data["config_stroke_um"] == CONFIG_UM and "amplifier" in ev.text
        st = svc.status()
        assert st.piezo_limits["limit_um"] == AMP_UM and st.to_dict()["piezo_limits"]["source"]
        # the runout asks for more: the offsets sit at the amplifier's stroke, never beyond
        assert tables and all(ok for _, ok in tables)
        assert max(abs(v) for t, _ in tables for v in t) <= AMP_UM
        assert AMP_UM / 2 <= max(abs(v) for r in res for v in r.offsets_um) <= AMP_UM
        uni = svc.uniformity_loop  # told the amplifier's stroke (it keeps its own margin)
        if hasattr(uni, "stroke_um"):
            assert uni.stroke_um == AMP_UM
        assert all(abs(sum(r.offsets_um)) < 0.01 for r in res)  # zero mean kept
        assert svc.counters["tables_refused"] == 0
        lim = limits_report(res, 50.0, 1000.0, CONFIG_UM, events=svc.events,
                            safe_entries={"count": 0, "unexplained": 0},
                            piezo_limits=svc.out.limits())
        assert lim["ok"] and lim["stroke_um"] == AMP_UM and lim["stroke_source"] == "amplifier"
        await plant.close()
        with QualityLog(tmp_path / "q.sqlite", create=False) as log:
            recs = [r for _, r in log.entries()]
        assert recs and all(r.extra["piezo"]["limit_um"] == AMP_UM for r in recs)
        assert all(r.extra["piezo"]["safe_entries"] == 0 for r in recs)

    asyncio.run(main())


def test_a_refused_table_is_replanned_and_never_sent_again(tmp_path):
    """The amplifier says 10 um but takes only 6 um: refusals narrow the bound, no safe state."""

    async def main():
        plant = _plant(tmp_path)
        machine = plant.machine
        accept = machine.set_piezo_offsets

        def lying(offsets_um):
            if max(abs(float(v)) for v in offsets_um) > 6.0:
                raise ValueError("offsets_um beyond +-6 um")
            accept(offsets_um)

        machine.set_piezo_offsets = lying
        tables = _watch_tables(plant)
        await plant.start()
        await run_for(plant, 5.0)
        svc = plant.service
        refused = {t for t, ok in tables if not ok}
        assert refused and svc.counters["tables_refused"] >= 1
        # after its refusal, a table never reaches the amplifier again
        for i, (table, ok) in enumerate(tables):
            if not ok:
                assert all(t != table for t, _ in tables[i + 1:])
        events = _events(svc, EventKind.OFFSETS_REFUSED)
        assert len(events) == svc.counters["tables_refused"]
        assert all(e.data["replanned_um"] is not None for e in events)
        assert all(max(map(abs, e.data["replanned_um"])) <= e.data["limit_um"] for e in events)
        # re-planned in time: no safe state, the loop runs on inside what the amplifier takes
        assert svc.counters["safe_entries"] == 0 and svc.state is SafetyState.RUN
        assert max(abs(v) for v in svc.offsets_um) <= 6.0
        assert svc.status().piezo_limits["source"] == "refused table"
        await plant.close()

    asyncio.run(main())


def test_limits_are_read_again_after_a_reconnect(tmp_path):
    async def main():
        plant = _plant(tmp_path)
        await plant.start()
        await run_for(plant, 3.0)
        svc = plant.service
        t0 = plant.clock()
        plant.can_fault("can_silence", 0.6)
        await run_for(plant, 3.5)
        assert svc.piezo.reconnects == 1
        evs = [e for e in _events(svc, EventKind.PIEZO_LIMITS) if e.t_s >= t0]
        assert [e.data["source"] for e in evs] == ["unknown", "amplifier"]
        assert evs[0].t_s < evs[1].t_s <= evs[0].t_s + 0.15  # with the next heartbeat
        assert svc.state is SafetyState.RUN and svc.counters["safe_entries"] == 1
        assert np.abs(svc.offsets_um).max() <= AMP_UM
        await plant.close()

    asyncio.run(main())
