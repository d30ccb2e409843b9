"""The knife condition in the quality log of a closed-loop run, and in ``planer report``.

The ``knife_wear`` plant (knife 0 wears back 6 um/min against a 6 um stroke) for 12 m of board,
the pairs measured by the simulator's truth: every record from the first applied offset table
on carries the knife condition in force (schema version 6), fitting for the first 3 m, then a
forecast; the last record's condition is the service's own; the report summarises it.
"""

from __future__ import annotations

import asyncio
import math
from dataclasses import replace

from controller.quality.log import QualityLog
from controller.quality.report import build_figures, summarise
from planer.hil.in_process import InProcessPlant
from planer.hil.scenario import load_scenario, machine_config_for, sim_config_for
from planer.hil.soak import TruthMeasurer

DISTANCE_M = 12.0


def test_records_carry_the_knife_condition_in_force_and_the_report_reads_it(tmp_path):
    sc = replace(load_scenario("knife_wear"), faults=())
    log_path = tmp_path / "log.sqlite"
    cfg = machine_config_for(sc, log_path=log_path)
    truth = TruthMeasurer()
    plant = InProcessPlant(cfg, sim_config_for(sc), seed=sc.seed, render_images=False,
                           plc_transport="direct", measurer_factory=lambda shape: truth)
    advance = plant.machine.advance

    def filing(dt_s):
        frames = advance(dt_s)
        truth.file(frames)
        return frames

    plant.machine.advance = filing

    made = []  # every forecast the service made, in order

    async def run():
        await plant.start()
        svc = plant.service
        watch = svc.loops.condition
        real = watch._forecast
        watch._forecast = lambda t: made.append(real(t)) or made[-1]
        try:
            while svc.loops.board_travel_m < DISTANCE_M:
                await plant.step()
            await svc.pipeline.drain()
            return svc.status().knife_condition
        finally:
            await plant.close()

    kc = asyncio.run(run())
    with QualityLog(log_path, create=False) as log:
        recs = log.records()
    carried = [r for r in recs if r.jointing_state is not None]
    assert carried and len(carried) >= 0.8 * len(recs)  # all but the first pairs
    first = recs.index(carried[0])
    assert all(r.jointing_state is not None for r in recs[first:])  # once there, always
    travel = [r.board_travel_m for r in carried]
    assert travel == sorted(travel) and travel[-1] > DISTANCE_M - 2.0
    fitting = [r for r in carried if r.jointing_state == "fitting"]
    assert fitting and max(r.board_travel_m for r in fitting) < 3.0 + 0.1  # the fit's span
    fitted = [r for r in carried if r.board_travel_m > 4.0]
    assert all(r.jointing_state in ("due", "not_due") for r in fitted)
    assert all(len(r.knife_reserve_um) == 4 and not math.isnan(r.knife_drift_um_per_m[0])
               for r in fitted)
    assert fitted[-1].knife_drift_um_per_m[0] < 0  # knife 0 wears back
    # each record carries the newest forecast made before its pair (between the pairs before)
    for r in carried:
        f = max((f for f in made if f["t_s"] < r.t_s), key=lambda f: f["t_s"])
        assert (r.board_travel_m, r.jointing_state) == (f["board_travel_m"], f["state"])
        assert list(r.knife_reserve_um) == [k["reserve_um"] for k in f["knives"]]
        if r.jointing_state == "due":
            assert (r.jointing_due_m, r.jointing_knife) == (f["due_in_m"], f["knife"])
    assert kc == made[-1]  # the status shows the newest
    last = carried[-1]
    ks = summarise(recs)["knife_condition"]
    assert ks["last"]["state"] == last.jointing_state
    assert ks["knives"][0]["reserve_um"] == last.knife_reserve_um[0]
    assert "knife_condition" in build_figures(recs)
