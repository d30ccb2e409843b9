"""The moulder's feed coordinator on the simulated moulder: machine-wide safe state, per-head safe
state, and the heads' services leaving the feed and the heartbeat to it."""

from __future__ import annotations

import asyncio
from dataclasses import replace
from pathlib import Path

import pytest

from config.faults import parse_faults
from planer.hil import load_scenario
from planer.hil.moulder import MoulderPlant
from planer.hil.scenario import machine_config_for, sim_config_for


def _plant(tmp_path: Path, faults: list[dict]) -> MoulderPlant:
    sc = replace(load_scenario("moulder"), faults=parse_faults(faults, "faults",
                                                               default_at_s=0.0))
    cfg = machine_config_for(sc, log_path=tmp_path / "m.sqlite")
    return MoulderPlant(cfg, sim_config_for(sc), seed=0, log_path=tmp_path / "m.sqlite",
                        render_images=True)


async def _steps(plant: MoulderPlant, until_s: float) -> list:
    seen = []
    try:
        while plant.clock() < until_s:
            await plant.step()
            d = plant.service.feed.last
            states = {n: svc.keeper.state.value for n, svc in plant.service.heads.items()}
            seen.append((plant.clock(), d.safe, d.feed_mm_s, states))
    finally:
        await plant.close()
    return seen


def test_an_estop_is_machine_wide_and_every_head_recovers(tmp_path):
    plant = _plant(tmp_path, [{"kind": "estop", "at_s": 1.5}, {"kind": "reset", "at_s": 2.5}])
    seen = asyncio.run(_steps(plant, 7.0))
    during = [s for s in seen if 1.7 <= s[0] <= 2.5]
    assert during and all(s[1] for s in during), "the feed was not in the safe state"
    assert all(set(s[3].values()) == {"safe"} for s in during)
    after = seen[-1]
    assert after[1] is False and set(after[3].values()) == {"run"}
    # from the safe feed in force back to the heads' feed without a jump (rate-limited)
    feeds = [s[2] for s in seen if s[0] > 2.0]
    assert max(abs(b - a) for a, b in zip(feeds, feeds[1:], strict=False)) <= 500.0 * 0.02 + 1e-6


def test_one_head_safe_does_not_touch_the_feed(tmp_path):
    plant = _plant(tmp_path, [{"kind": "can_silence", "head": "top", "at_s": 1.0,
                               "duration_s": 1.0}])
    pending = True
    seen = []

    async def go():
        nonlocal pending
        try:
            while plant.clock() < 3.0:
                if pending and plant.clock() >= 1.0:
                    plant.inject(plant_fault)
                    pending = False
                await plant.step()
                d = plant.service.feed.last
                seen.append((plant.clock(), d.safe, d.feed_mm_s,
                             plant.service.heads["top"].keeper.state.value))
        finally:
            await plant.close()

    plant_fault = parse_faults([{"kind": "can_silence", "head": "top", "at_s": 1.0,
                                 "duration_s": 1.0}], "faults")[0]
    asyncio.run(go())
    top_safe = [s for s in seen if s[3] == "safe"]
    assert top_safe, "the top head never went to its safe state"
    started = [s for s in seen if s[0] > 0.5]  # all heads start safe until they recover
    assert not any(s[1] for s in started), "one head's fault put the whole feed in safe state"
    feeds = [s[2] for s in top_safe if s[2] is not None]
    assert min(feeds) > 400.0  # no ramp down to the safe feed


def test_a_head_service_writes_neither_feed_nor_heartbeat(tmp_path):
    plant = _plant(tmp_path, [])

    async def go():
        try:
            for _ in range(20):
                await plant.step()
        finally:
            await plant.close()

    asyncio.run(go())
    for svc in plant.service.heads.values():
        assert svc.out.owns_feed is False
        assert svc.out.heartbeat == 0  # never beat: the coordinator does
    assert plant.service.feed.heartbeat == 20
    with pytest.raises(ValueError, match="owns_feed"):
        from controller.moulder.service import MoulderService

        svc = next(iter(plant.service.heads.values()))
        svc.out.owns_feed = True
        MoulderService({"bottom": svc}, plant.cfg.heads[:1], feed=plant.service.feed)


def test_the_coordinators_own_error_holds_the_feed_safe_then_it_resumes(tmp_path):
    """An unexpected error of the law itself: reported (the first head's SERVICE_ERROR), the
    feed on the safe path for the recovery time, then the law again from the feed in force."""
    plant = _plant(tmp_path, [])
    law = plant.service.feed.law
    real = law.update
    broken = {"left": 1}

    def once(*args, **kwargs):
        if plant.clock() > 1.0 and broken["left"]:
            broken["left"] -= 1
            raise RuntimeError("a bug in the law")
        return real(*args, **kwargs)

    law.update = once
    seen = asyncio.run(_steps(plant, 2.5))
    after = [s for s in seen if s[0] > 1.0]
    safe = [s for s in after if s[1]]
    hold = plant.cfg.safety.recovery_s
    assert safe and safe[-1][0] - safe[0][0] == pytest.approx(hold, abs=0.05)
    assert after[-1][1] is False  # the law governs again
    assert plant.service.feed.counts["faults"] == 1
    errors = [e for e in plant.service.first.events if e.kind.value == "service_error"]
    assert errors and "a bug in the law" in errors[0].text
