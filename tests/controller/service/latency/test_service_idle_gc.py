"""The garbage collector runs between pairs, not in the middle of one.

Judged by what the collector reports (``gc.callbacks``) and the order of events, never by time:
with :class:`controller.service.latency.IdleCollector` installed, collections happen, as many as the
normal thresholds make due, and none starts while a pair's control runs.
"""

from __future__ import annotations

import asyncio
import gc
from dataclasses import replace

import pytest

from config.machine import load_machine
from controller.service import latency
from controller.service.latency import IdleCollector, collect_between_pairs, tune_for_latency
from controller.service.supervisor import SafetyState
from planer.hil import InProcessPlant, Scenario, sim_config_for
from tests.support.plant_support import record_frames, run_for, truth_measurer


@pytest.fixture
def thresholds():
    """The collector's thresholds and state as they were, whatever the test did."""
    before = gc.get_threshold()
    yield before
    if latency.idle_collector() is not None:
        latency.idle_collector().uninstall()
    gc.set_threshold(*before)


def _collections(generations: list[int]):
    def note(phase, info):
        if phase == "start":
            generations.append(int(info["generation"]))
    return note


@pytest.mark.parametrize("backstop", [0, 1, -3, 2.5, True, "20"])
def test_a_backstop_below_two_or_not_an_int_is_refused_by_name(backstop):
    with pytest.raises(ValueError, match="backstop"):
        IdleCollector(backstop=backstop)


def test_install_raises_the_automatic_threshold_and_uninstall_restores_it(thresholds):
    gc.set_threshold(300, 7, 9)
    idle = IdleCollector(backstop=5).install()
    assert gc.get_threshold() == (1500, 7, 9) and latency.idle_collector() is idle
    idle.uninstall()
    assert gc.get_threshold() == (300, 7, 9) and latency.idle_collector() is None
    assert collect_between_pairs() is None  # none installed: nothing happens


def test_installing_a_second_collector_restores_the_first_ones_thresholds(thresholds):
    gc.set_threshold(300, 7, 9)
    IdleCollector(backstop=5).install()
    second = IdleCollector(backstop=3).install()
    assert gc.get_threshold() == (900, 7, 9) and latency.idle_collector() is second


def test_collections_wait_for_the_idle_call_and_follow_the_normal_generations(thresholds):
    gc.set_threshold(200, 2, 2)
    idle = IdleCollector(backstop=50).install()
    seen: list[int] = []
    keep = []
    gc.collect()
    gc.callbacks.append(_collections(seen))
    try:
        assert idle.collect_due() is None  # nothing made since: nothing due
        got = []
        for _ in range(16):
            keep += [[] for _ in range(300)]  # over the normal threshold, under the backstop
            assert len(seen) == len(got)  # the automatic collection did not run ...
            got.append(idle.collect_due())  # ... the idle call did, and only then
    finally:
        gc.callbacks.pop()
    # as the automatic collection counts (a count over its threshold): the middle generation
    # after every 3rd young one, the oldest after every 3rd of those
    assert got == [0, 0, 0, 1] * 3 + [0, 0, 0, 2]
    assert seen == got and idle.collections == [12, 3, 1]


def test_tune_for_latency_installs_the_idle_collector_unless_told_not_to(thresholds):
    import sys

    interval = sys.getswitchinterval()
    try:
        assert tune_for_latency(idle_gc=False)["idle_gc"] is False
        assert latency.idle_collector() is None
        out = tune_for_latency()
        assert out["idle_gc"] is True and latency.idle_collector() is not None
        assert gc.get_threshold()[0] == thresholds[0] * latency.IDLE_GC_BACKSTOP
    finally:
        gc.unfreeze()
        sys.setswitchinterval(interval)


def test_the_service_collects_between_pairs_never_during_a_pairs_control(thresholds, tmp_path):
    cfg = load_machine()
    cfg = cfg.with_changes(log=replace(cfg.log, path=tmp_path / "q.sqlite"))
    gc.set_threshold(100, 3, 3)  # due every few pairs
    idle = IdleCollector(backstop=1000).install()
    in_control = [False]
    during_control: list[int] = []
    seen: list[int] = []

    def note(phase, info):
        if phase == "start":
            seen.append(int(info["generation"]))
            if in_control[0]:
                during_control.append(int(info["generation"]))

    async def main():
        frames: dict = {}
        plant = InProcessPlant(cfg, sim_config_for(Scenario(runout_um=(0.0, 4.0, -2.0, 2.0))),
                               render_images=False, log=None,
                               measurer_factory=lambda shape: truth_measurer(frames))
        record_frames(plant, frames)
        loops = plant.service.pipeline.loops
        apply = loops.apply

        async def noting_apply(*args, **kwargs):
            in_control[0] = True
            try:
                return await apply(*args, **kwargs)
            finally:
                in_control[0] = False

        loops.apply = noting_apply
        gc.callbacks.append(note)
        try:
            results = await run_for(plant, 3.0)
        finally:
            gc.callbacks.remove(note)
            state = plant.service.state
            await plant.close()
        return results, state

    results, state = asyncio.run(main())
    assert state is SafetyState.RUN and sum(r.applied for r in results) >= 20
    assert sum(idle.collections) > 0  # the collections were run, by the idle calls ...
    assert during_control == []  # ... and none inside a pair's control
    assert len(seen) >= sum(idle.collections)
