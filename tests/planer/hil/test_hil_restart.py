"""A restart of the service on a running machine (in-process HIL, real vision on rendered images).

The service is stopped at 2.5 m of board -- cleanly, or as a ``kill -9`` leaves it -- and a new
one starts on the same plant and quality log. With the learnt state kept beside the log it
resumes the offsets and the feed model, holds the PLC's feed while it starts and costs less
than 0.2 m of board outside the bands; with a knife set that changed it learns afresh.
"""

from __future__ import annotations

import asyncio
import json

import pytest

from controller.quality.learned_state import learned_state_path
from controller.service.events import EventKind
from planer.hil.in_process import InProcessPlant
from planer.hil.scenario import Scenario, machine_config_for, sim_config_for

SCENARIO = Scenario(runout_um=(0.0, 4.0, -2.0, 2.0), initial_feed_mm_s=800.0,
                    target_pitch_mm=1.5)


async def _restart_run(tmp_path, *, kill: bool, edit=None, at_mm=2500.0, end_mm=4500.0):
    """Pairs ``(travel_mm, true pitch, true cv, setpoint)`` and the second service's events."""
    cfg = machine_config_for(SCENARIO, log_path=tmp_path / "hil.sqlite")
    plant = InProcessPlant(cfg, sim_config_for(SCENARIO), seed=0)
    await plant.start()
    rows, restarted_at, events = [], None, []
    try:
        while plant.travelled_mm < end_mm:
            if restarted_at is None and plant.travelled_mm >= at_mm:
                await plant.stop_service(kill=kill)
                if edit is not None:
                    edit(learned_state_path(cfg.log.path))
                restarted_at = plant.travelled_mm
                await plant.start_service()
            for r in await plant.step():
                if r.truth:
                    rows.append((plant.travelled_mm, float(r.truth["pitch_mm"]),
                                 float(r.truth["uniformity_cv"]), r.feed_setpoint_mm_s))
    finally:
        events = list(plant.service.events) if plant.service is not None else []
        await plant.close()
    return rows, restarted_at, events


def _outside_mm(rows, since_mm):
    """Board (pair spacing) after ``since_mm`` whose pitch or CV is outside the bands, mm."""
    out, prev = 0.0, None
    for d, p, cv, _ in rows:
        if prev is not None and d >= since_mm and (abs(p / 1.5 - 1) > 0.02 or cv > 0.05):
            out += d - prev
        prev = d
    return out


@pytest.mark.parametrize("kill", [True, False], ids=["kill-9", "clean"])
def test_a_restart_resumes_the_learnt_state_and_costs_under_0_2_m(tmp_path, kill):
    rows, at, events = asyncio.run(_restart_run(tmp_path, kill=kill))
    before = [r for r in rows if r[0] < at]
    assert _outside_mm(before, at - 500.0) == 0.0  # converged before the restart
    assert _outside_mm(rows, at) < 200.0
    resumed = [e for e in events if e.kind is EventKind.LEARNED_STATE_RESUMED]
    assert len(resumed) == 1 and resumed[0].data["warm"]
    # no ramp of the feed: the setpoint stays at the target feed through the restart
    after = [f for d, *_, f in rows if d >= at]
    assert min(after) >= 0.99 * 600.0
    assert not [e for e in events if e.kind is EventKind.LEARNED_STATE_DISCARDED]


def test_a_changed_knife_set_is_relearnt_from_a_cold_start(tmp_path):
    def other_head(path):  # the knives were changed for a head of another radius
        doc = json.loads(path.read_text())
        doc["knife_set"]["radius_mm"] = 55.0
        path.write_text(json.dumps(doc))

    rows, at, events = asyncio.run(_restart_run(tmp_path, kill=True, edit=other_head,
                                                end_mm=3500.0))
    dropped = [e for e in events if e.kind is EventKind.LEARNED_STATE_DISCARDED]
    assert len(dropped) == 1 and "cutting radius 55 mm then, 60 mm now" in dropped[0].reason
    assert not [e for e in events if e.kind is EventKind.LEARNED_STATE_RESUMED]
    # a cold start: the safe ramp while starting up, and the offsets learnt again
    after = [f for d, *_, f in rows if d >= at]
    assert min(after) < 0.95 * 600.0
    assert _outside_mm(rows, at) > 200.0
