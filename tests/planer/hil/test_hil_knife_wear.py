"""Knife wear in the closed loop: the jointing forecast made at 20 m against when it happens.

The ``knife_wear`` scenario (config/hil.toml): knife 1 wears back 6 um/min against a 6 um
stroke. The uniformity loop follows the wear with its table until the table reaches the stroke;
then the finish leaves its class (true CV above ``[quality] uniformity_max_cv``). The service's
knife condition (:mod:`controller.laws.knife_condition`, in its status snapshot) forecasts when,
from the tables in force. The pairs are measured by the simulator's truth (no images), so the
run is the loop's and the forecast's, not the vision's.
"""

from __future__ import annotations

import asyncio
from dataclasses import replace

import pytest

from controller.service.events import EventKind
from planer.hil.in_process import InProcessPlant
from planer.hil.scenario import load_scenario, machine_config_for, sim_config_for
from planer.hil.soak import TruthMeasurer

FORECAST_AT_M = 20.0


@pytest.mark.slow
def test_the_jointing_forecast_at_20_m_is_within_20_percent_of_when_the_finish_leaves_its_class(
        tmp_path):
    sc = replace(load_scenario("knife_wear"), faults=())
    cfg = machine_config_for(sc, log_path=tmp_path / "log.sqlite")
    truth = TruthMeasurer()
    plant = InProcessPlant(cfg, sim_config_for(sc), seed=sc.seed, render_images=False,
                           plc_transport="direct", measurer_factory=lambda shape: truth)
    advance = plant.machine.advance

    def filing(dt_s):
        frames = advance(dt_s)
        truth.file(frames)
        return frames

    plant.machine.advance = filing
    cv_max = cfg.quality.uniformity_max_cv

    async def run():
        await plant.start()
        svc = plant.service
        forecast = None
        out_at = None
        try:
            while svc.loops.board_travel_m < sc.distance_m:
                for r in await plant.step():
                    tr = (r.measurement is not None and getattr(r, "ok", False))
                    if not tr:
                        continue
                    cv = r.measurement.uniformity_cv  # the truth (the truth measurer)
                    x = svc.loops.board_travel_m
                    if out_at is None and x > 5.0 and cv > cv_max:
                        out_at = x
                if forecast is None and svc.loops.board_travel_m >= FORECAST_AT_M:
                    kc = svc.status().knife_condition
                    forecast = (svc.loops.board_travel_m, kc)
                if out_at is not None:
                    break
            events = [e for e in svc.events if e.kind is EventKind.JOINTING_DUE]
        finally:
            await plant.close()
        return forecast, out_at, events

    (at_m, kc), out_at, events = asyncio.run(run())
    assert out_at is not None, "the finish never left its class within the run"
    assert kc is not None and kc["due_in_m"] is not None, kc
    assert at_m - kc["board_travel_m"] < 1.5 + 0.1  # made within 2 s (and a pair) of 20 m
    predicted = kc["board_travel_m"] + kc["due_in_m"]  # from where the forecast was made
    assert kc["knife"] == 0 and "jointing due in" in kc["text"]
    assert abs(predicted - out_at) <= 0.2 * (out_at - at_m), (predicted, out_at)
    worn = kc["knives"][0]
    assert worn["drift_um_per_m"] < 0 and worn["reserve_um"] < 6.0  # it wears, the stroke goes
    assert events and events[0].data["knife"] == 0  # the operator was told
