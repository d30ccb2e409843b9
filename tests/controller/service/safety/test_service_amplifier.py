"""The service and the piezo amplifier's own word: faults, refusals, a ramp it was not asked for.

The amplifier reports in its status (TPDO1) whether it plays the offsets (state 1, no fault bits).
An amplifier that faults, refuses the table (stroke-limit bit) or ramps to zero (setpoint
timeout) while the service commands enable is, after a short confirmation time, a CAN-side
failure: safe state (offsets 0, disable), reported once, RUN again once it reports healthy. And
board cut while it was not tracking must not teach the uniformity loop anything. Simulated time,
the in-process plant of ``tests/controller/service/test_service_loop.py``.
"""

from __future__ import annotations

import asyncio

import numpy as np

from controller.service.events import EventKind
from controller.service.supervisor import AMP_CONFIRM_S, SafetyState
from tests.controller.service.test_service_loop import make_plant
from tests.support.plant_support import run_for


def _amp_safe(plant) -> bool:
    core = plant.amp.core
    return all(v == 0.0 for v in core.offsets_um) and core.last_command["enable"] == 0


def _events(svc, since, kind):
    """(t, text) of the service's events of ``kind`` (None: every kind) since ``since``."""
    return [(e.t_s, e.text) for e in svc.events
            if e.t_s >= since and (kind is None or e.kind is kind)]


async def _running(tmp_path, seconds=3.0):
    plant, measurer = make_plant(tmp_path)
    await plant.start()
    await run_for(plant, seconds)
    svc = plant.service
    assert svc.state is SafetyState.RUN and np.abs(svc.offsets_um).max() > 0.5
    return plant, svc


async def _until(plant, cond, limit_s):
    """Step until ``cond()``; the machine time it took (a bound on simulated time, not wall)."""
    t0 = plant.clock()
    while not cond():
        await plant.step()
        assert plant.clock() - t0 < limit_s, "condition not reached in simulated time"
    return plant.clock() - t0


def test_amplifier_fault_goes_safe_once_and_recovers_when_healthy(tmp_path):
    async def main():
        plant, svc = await _running(tmp_path)
        cfg = plant.cfg.safety
        learnt = np.asarray(svc.offsets_um)
        t0 = plant.clock()
        plant.machine.inject("piezo_fault")  # overcurrent: state 3, output to zero
        took = await _until(plant, lambda: svc.state is SafetyState.SAFE, 1.0)
        assert took <= AMP_CONFIRM_S + 3 * cfg.cycle_s + 1e-9
        assert "amplifier" in svc.status().missing and "can" not in svc.status().missing
        (ev,) = _events(svc, t0, EventKind.AMPLIFIER_PROBLEM)
        assert "overcurrent" in ev[1]
        await run_for(plant, 0.04)
        assert svc.offsets_um == (0.0,) * len(learnt) and _amp_safe(plant)
        # the disable clears the amplifier's fault: healthy again, RUN after the confirmation
        t_rec = await _until(plant, lambda: svc.state is SafetyState.RUN, 2.0)
        assert t_rec <= AMP_CONFIRM_S + cfg.recovery_s + 0.2
        assert len(_events(svc, t0, EventKind.AMPLIFIER_PROBLEM)) == 1  # reported once
        assert _events(svc, t0, EventKind.AMPLIFIER_HEALTHY)
        await run_for(plant, 0.1)
        assert plant.machine.amp.state == 1
        assert np.allclose(plant.amp.core.offsets_um[: len(learnt)], learnt, atol=1e-3)
        await plant.close()

    asyncio.run(main())


def test_refused_offsets_are_not_believed(tmp_path):
    """The amplifier refuses the table (stroke-limit bit) and plays the old one: safe state."""

    async def main():
        plant, svc = await _running(tmp_path)
        t0 = plant.clock()
        machine = plant.machine
        accept = machine.set_piezo_offsets

        def refuse(offsets_um):
            raise ValueError("offsets_um[1] must be within +-1 um")

        machine.set_piezo_offsets = refuse
        await _until(plant, lambda: svc.state is SafetyState.SAFE, 1.0)
        assert "amplifier" in svc.status().missing
        (ev,) = _events(svc, t0, EventKind.AMPLIFIER_PROBLEM)
        assert "stroke limit" in ev[1]
        # while the amplifier refuses, the service stays safe and applies nothing
        res = await run_for(plant, 1.0)
        assert svc.state is SafetyState.SAFE
        assert res and not any(r.applied for r in res)
        assert all(r.state == "safe" for r in res)
        machine.set_piezo_offsets = accept  # the next table is taken: healthy, RUN again
        await _until(plant, lambda: svc.state is SafetyState.RUN, 2.0)
        await run_for(plant, 0.3)
        assert np.allclose(plant.amp.core.offsets_um[: len(svc.offsets_um)], svc.offsets_um,
                           atol=1e-3)
        await plant.close()

    asyncio.run(main())


def test_long_setpoint_timeout_with_status_flowing_is_a_can_failure(tmp_path):
    """Our frames do not reach the amplifier, its status still does: it ramps, we go safe."""

    async def main():
        plant, svc = await _running(tmp_path)
        cfg = plant.cfg.safety
        t0 = plant.clock()
        plant.can_fault("can_drop", 0.6)
        await _until(plant, lambda: svc.state is SafetyState.SAFE, 0.6)
        assert "amplifier" in svc.status().missing and "can" not in svc.status().missing
        (ev,) = _events(svc, t0, EventKind.AMPLIFIER_PROBLEM)
        assert "setpoint timeout" in ev[1]
        t_rec = await _until(plant, lambda: svc.state is SafetyState.RUN, 2.0)
        assert plant.clock() - t0 >= 0.6
        assert t_rec <= 0.6 + AMP_CONFIRM_S + cfg.recovery_s + 0.2
        await plant.close()

    asyncio.run(main())


def test_uniformity_loop_never_learns_from_board_cut_while_not_tracking(tmp_path):
    """A ramp shorter than the confirmation time: no safe state, but nothing learnt from it."""

    async def main():
        plant, svc = await _running(tmp_path, seconds=2.0)
        loop = svc.uniformity_loop
        orig = loop.update
        cut_times = []

        def recording(**kw):
            cut_times.append(kw.get("cut_at_s"))
            return orig(**kw)

        loop.update = recording
        amp = plant.machine.amp
        untracked = []
        t_fault = plant.clock()
        plant.can_fault("can_drop", 0.15)  # the amplifier's 0.1 s timeout runs out briefly
        end = t_fault + 3.0
        while plant.clock() < end:
            await plant.step()
            if amp.state != 1:
                untracked.append(plant.clock())
        assert untracked, "the amplifier never left tracking: the fault did not bite"
        assert svc.counters["safe_entries"] == 0 and svc.state is SafetyState.RUN
        assert max(untracked) - min(untracked) < AMP_CONFIRM_S
        speed = plant.machine.register_values()["feed_actual_mm_s"]
        window_s = svc.feed_loop.cfg.window_mm / speed
        lo = min(untracked) - plant.cfg.safety.cycle_s - window_s
        hi = max(untracked) + loop.cfg.settle_s
        assert None not in cut_times
        bad = [c for c in cut_times if lo <= c <= hi]
        assert not bad, f"learnt from board cut at {bad} (untracked {lo:.3f}..{hi:.3f})"
        assert any(c > hi for c in cut_times)  # and it learns again afterwards
        await plant.close()

    asyncio.run(main())
