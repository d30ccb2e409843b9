"""A pair's setpoints before other pairs' bookkeeping (:mod:`controller.service.after_setpoint`).

Judged by the order of events on the event loop, never by time: with two pipelines (two heads)
on one loop, a pair whose measurement is back goes through its setpoints before the other
head's record is queued; each head's records keep their order; the results are those of the
same pairs handled one at a time; the queue's limit lets bookkeeping through a loop that is
never idle; the garbage collector waits for no pair being ready.
"""

from __future__ import annotations

import asyncio
import gc
from dataclasses import replace

import pytest

from config.machine import load_machine
from controller.service import latency
from controller.service.after_setpoint import AfterSetpoint, after_setpoint_queue
from controller.service.latency import IdleCollector
from controller.service.supervisor import SafetyState
from controller.workers.link import WorkerOutcome
from planer.hil import InProcessPlant, Scenario, sim_config_for
from tests.support.plant_support import record_frames, run_for, truth_measurer

SCENARIO = Scenario(runout_um=(0.0, 4.0, -2.0, 2.0), initial_feed_mm_s=800.0)


class Member:
    """A pipeline as the queue sees it: ready for its setpoints or not."""

    def __init__(self, ready: bool = False) -> None:
        self.is_ready = ready

    def setpoints_ready(self) -> bool:
        return self.is_ready


async def _spin(n: int = 5) -> None:
    for _ in range(n):
        await asyncio.sleep(0)


def test_a_queue_refuses_a_limit_below_one_naming_it():
    loop = asyncio.new_event_loop()
    try:
        for bad in (0, -1, 1.5, True):
            with pytest.raises(ValueError, match="max_waiting"):
                AfterSetpoint(loop, max_waiting=bad)
    finally:
        loop.close()


def test_bookkeeping_runs_at_once_when_no_pair_is_ready_and_waits_while_one_is():
    async def main():
        q = after_setpoint_queue()
        assert after_setpoint_queue() is q and q.loop is asyncio.get_running_loop()
        head = Member()
        q.register(head)
        step = q.turn()
        with pytest.raises(StopIteration):  # nothing ready, nothing queued: no wait at all
            step.send(None)
        q.done()
        head.is_ready = True
        order = []

        async def book(name):
            await q.turn()
            order.append(name)
            q.done()

        task = asyncio.ensure_future(book("a"))
        await _spin()
        assert order == [] and q.waiting == 1  # a pair is ready: its setpoints go first
        head.is_ready = False
        q.setpoint_done()
        await _spin()
        assert order == ["a"] and q.waiting == 0
        await task

    asyncio.run(main())


def test_queued_bookkeeping_starts_in_the_order_it_came_once_no_pair_is_ready():
    async def main():
        q = AfterSetpoint(asyncio.get_running_loop())
        head = Member(ready=True)
        q.register(head)
        started, finished = [], []

        async def book(name):
            await q.turn()
            started.append(name)  # up to here nothing waits: the record is queued in order
            await asyncio.sleep(0)  # bookkeeping that waits (the journal's room)
            finished.append(name)
            q.done()

        tasks = [asyncio.ensure_future(book(n)) for n in "abcd"]
        await _spin()
        assert started == []
        head.is_ready = False
        q.setpoint_done()
        await asyncio.gather(*tasks)
        assert started == list("abcd") and sorted(finished) == list("abcd")
        late = asyncio.ensure_future(book("e"))  # all done, nothing ready: at once
        await late
        assert started[-1] == "e"

    asyncio.run(main())


def test_a_loop_never_idle_still_books_once_the_limit_is_queued():
    async def main():
        q = AfterSetpoint(asyncio.get_running_loop(), max_waiting=3)
        head = Member(ready=True)  # always a pair ready (held here: the queue holds it weakly)
        q.register(head)
        order = []

        async def book(name):
            await q.turn()
            order.append(name)
            q.done()

        tasks = [asyncio.ensure_future(book(n)) for n in range(5)]
        await _spin(20)
        # 3 queued: the oldest goes; again when the next makes 3; the last 2 wait for an idle loop
        assert order == [0, 1, 2] and q.waiting == 2
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        assert q.waiting == 0

    asyncio.run(main())


def test_a_cancelled_wait_leaves_the_queue_and_a_released_one_passes_its_turn_on():
    async def main():
        q = AfterSetpoint(asyncio.get_running_loop())
        head = Member(ready=True)
        q.register(head)
        order = []

        async def book(name):
            await q.turn()
            order.append(name)
            q.done()

        a, b, c = (asyncio.ensure_future(book(n)) for n in "abc")
        await _spin()
        b.cancel()
        await _spin()
        assert q.waiting == 2
        head.is_ready = False
        q.setpoint_done()
        await asyncio.gather(a, c)
        assert order == ["a", "c"] and b.cancelled()

    asyncio.run(main())


@pytest.fixture
def thresholds():
    before = gc.get_threshold()
    yield before
    if latency.idle_collector() is not None:
        latency.idle_collector().uninstall()
    gc.set_threshold(*before)


def test_the_collector_waits_until_no_pair_is_ready_and_no_bookkeeping_is_queued(thresholds):
    gc.set_threshold(200, 1000, 1000)
    IdleCollector(backstop=50).install()
    seen: list[int] = []

    def note(phase, info):
        if phase == "start":
            seen.append(int(info["generation"]))

    async def main():
        q = AfterSetpoint(asyncio.get_running_loop())
        head = Member(ready=True)
        q.register(head)
        q.collect()  # nothing due: nothing asked for
        await _spin()
        assert seen == []
        keep = [[] for _ in range(400)]  # over the normal threshold, under the backstop
        q.collect()
        await _spin()
        assert seen == []  # a pair is ready: not now
        head.is_ready = False
        q.setpoint_done()
        await _spin()
        assert seen == [0]
        return keep

    gc.collect()
    gc.callbacks.append(note)
    try:
        asyncio.run(main())
    finally:
        gc.callbacks.remove(note)


# ---------------------------------------------------------------------------------------------
# two pipelines (a moulder's heads) on one loop, measured by a pool whose answers the test gives


class HandPool:
    """A worker pool whose pairs are measured when the test says (:meth:`answer`)."""

    capacity = 24

    def __init__(self, frames: dict) -> None:
        self.measure = truth_measurer(frames).measure
        self.jobs: dict[int, tuple] = {}

    def submit(self, frame, *, facts=None, calibrator=None):
        fut = asyncio.get_running_loop().create_future()
        self.jobs[id(frame)] = (fut, frame)
        return fut

    def prepare(self, shape, facts):
        pass

    def listen(self, fn):
        pass

    def answer(self, frame) -> None:
        fut, f = self.jobs.pop(id(frame))
        fut.set_result(WorkerOutcome(None, self.measure(
            f.image_a, f.image_b, counts_a=f.counts_a, counts_b=f.counts_b), worker=0))


async def _running_head(tmp_path, frames):
    cfg = load_machine()
    cfg = cfg.with_changes(log=replace(cfg.log, path=tmp_path / "q.sqlite"))
    plant = InProcessPlant(cfg, sim_config_for(SCENARIO), render_images=False, log=None,
                           measurer_factory=lambda shape: truth_measurer(frames))
    record_frames(plant, frames)
    await plant.start()
    assert await run_for(plant, 2.0) and plant.service.state is SafetyState.RUN
    return plant


async def _pairs(plant, n):
    out = []
    while len(out) < n:
        out += plant.driver.step(plant.cfg.safety.cycle_s)
        await plant.service.tick(plant.clock())
    return out[:n]


def _noting(plants, order):
    """Note ``("set", head)`` when a pair's control starts, ``("book", head)`` at its record."""
    for name, p in plants.items():
        pipe = p.service.pipeline
        apply, append = pipe.loops.apply, pipe.records.append

        async def noting_apply(*a, _apply=apply, _name=name, **k):
            order.append(("set", _name))
            return await _apply(*a, **k)

        async def noting_append(r, *a, _append=append, _name=name, **k):
            order.append(("book", _name, r.seq))
            return await _append(r, *a, **k)

        pipe.loops.apply, pipe.records.append = noting_apply, noting_append


def _essence(r):
    return (r.seq, r.ok, r.error, r.applied, r.state, r.feed_setpoint_mm_s, r.offsets_um,
            r.knife_widths_mm, r.extra.get("passes"), "profile" in r.extra)


async def _heads(tmp_path, n):
    frames: dict = {}
    plants = {}
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        plants[name] = await _running_head(tmp_path / name, frames)
        plants[name].service.keep_results = True
    pairs = {name: await _pairs(p, n) for name, p in plants.items()}
    pool = HandPool(frames)
    for p in plants.values():
        p.service.pipeline.use_workers(pool)
    return plants, pairs, pool


def test_a_ready_pair_goes_through_its_setpoints_before_the_other_heads_record(tmp_path):
    async def main():
        plants, pairs, pool = await _heads(tmp_path, 1)
        order: list = []
        _noting(plants, order)
        fa, fb = pairs["a"][0], pairs["b"][0]
        await plants["a"].service.pipeline.submit(fa)
        await plants["b"].service.pipeline.submit(fb)
        pool.answer(fa)  # both measurements back at once
        pool.answer(fb)
        for p in plants.values():
            await p.service.pipeline.drain()
        results = {k: list(p.service.results) for k, p in plants.items()}
        for p in plants.values():
            await p.close()
        return order, results

    order, results = asyncio.run(main())
    # head b's pair was ready when head a's setpoints were out: its setpoints before a's record
    assert [o[:2] for o in order] == [("set", "a"), ("set", "b"), ("book", "a"), ("book", "b")]
    assert all(r.applied for rs in results.values() for r in rs)


def test_each_heads_records_keep_their_order_and_say_what_one_at_a_time_would(tmp_path):
    n = 3  # 6 pairs: fewer than the queue's limit

    async def run(hurry):
        plants, pairs, pool = await _heads(tmp_path / ("hurry" if hurry else "calm"), n)
        order: list = []
        _noting(plants, order)
        before = {k: len(p.service.results) for k, p in plants.items()}
        for k in range(n):
            for name in ("a", "b"):
                await plants[name].service.pipeline.submit(pairs[name][k])
                if not hurry:  # each pair measured, set, booked before the next comes
                    pool.answer(pairs[name][k])
                    await plants[name].service.pipeline.drain()
        if hurry:  # every measurement back at once, a later pair first
            for k in reversed(range(n)):
                for name in ("b", "a"):
                    pool.answer(pairs[name][k])
        for p in plants.values():
            await p.service.pipeline.drain()
        results = {k: [_essence(r) for r in p.service.results[before[k]:]]
                   for k, p in plants.items()}
        for p in plants.values():
            await p.close()
        return order, results, pairs

    (tmp_path / "hurry").mkdir()
    (tmp_path / "calm").mkdir()
    order, hurried, pairs = asyncio.run(run(True))
    _, calm, _ = asyncio.run(run(False))
    for name in ("a", "b"):
        booked = [o[2] for o in order if o[:2] == ("book", name)]
        assert booked == [f.seq for f in pairs[name]]  # in sequence order
    assert hurried == calm
    # with every measurement back, all setpoints went out before the first record was queued
    first_book = next(i for i, o in enumerate(order) if o[0] == "book")
    assert sum(1 for o in order[:first_book] if o[0] == "set") == 2 * n
