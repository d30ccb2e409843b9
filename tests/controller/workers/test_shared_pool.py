"""One pool of measurement workers shared by several services (the heads of a moulder).

Each head hears of a worker's problem; a worker keeps a measurer per machine's facts, so the
heads' pairs taking turns never rebuild one another's set-up; the pairs of two services
interleaved through one pool each come back to their own service, in their own order.
"""

from __future__ import annotations

import asyncio
import os
import signal
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from controller.service.measurement import MachineFacts
from controller.workers.pool import MeasureWorkerPool, PoolForFactory
from controller.workers.process import KEEP_FACTS, _Stages
from protocol.frames import Frame


@dataclass(frozen=True)
class CountingFactory:
    """A facts-taking factory that notes each build (shape, facts key) in ``built``."""

    built: list
    takes_facts = True

    def __call__(self, shape, facts=None):
        self.built.append((shape, None if facts is None else facts.key))
        return object()


@dataclass(frozen=True)
class Tagged:
    """A factory whose measurements say which factory made them (one head's rig)."""

    tag: str

    def __call__(self, shape):
        return TagMeasurer(self.tag)


class TagMeasurer:
    def __init__(self, tag):
        self.tag = tag

    def measure(self, image_a, image_b, *, counts_a, counts_b, speed_mm_s=None):
        return SimpleNamespace(tag=self.tag, counts_a=counts_a, pid=os.getpid())


def _pair(k: int) -> Frame:
    img = np.full((8, 8), k % 250, dtype=np.uint8)
    return Frame(seq=k, t_s=0.01 * k, image_a=img, image_b=img.copy(), counts_a=100 * k,
                 counts_b=100 * k + 5, speed_mm_s=600.0)


def _facts(knives: int, radius_mm: float = 60.0) -> MachineFacts:
    return MachineFacts(radius_mm=radius_mm, knives=knives, spindle_rpm=6000.0)


def test_heads_taking_turns_build_each_measurer_once():
    built: list = []
    stages = _Stages(CountingFactory(built))
    heads = [_facts(4), _facts(2), _facts(2, 70.0), _facts(6)]
    for _ in range(5):  # four heads' pairs in turn
        for facts in heads:
            stages.stage(facts).measurer((493, 659), facts)
    assert sorted(built) == sorted(((493, 659), f.key) for f in heads)  # once each
    assert len(stages) == len(heads)


def test_the_facts_used_longest_ago_go_first_beyond_the_limit():
    built: list = []
    stages = _Stages(CountingFactory(built), keep=2)
    a, b, c = _facts(2), _facts(4), _facts(6)
    for facts in (a, b, a, c):  # b is the one used longest ago when c comes
        stages.stage(facts).measurer((10, 10), facts)
    stages.stage(a).measurer((10, 10), a)
    stages.stage(b).measurer((10, 10), b)  # built again
    assert [k for _, k in built] == [a.key, b.key, c.key, b.key]
    assert len(stages) == 2
    assert KEEP_FACTS >= 4  # the moulder's four heads fit


class _DeadEnd:
    """A worker's pipe end that is already gone (close does nothing)."""

    def close(self) -> None:
        pass


def test_every_listener_hears_of_a_worker_problem_once_after_on_problem():
    heard: list = []
    pool = MeasureWorkerPool(CountingFactory([]), workers=1,
                             on_problem=lambda t: heard.append(("on_problem", t)))
    first = lambda t: heard.append(("first", t))  # noqa: E731
    pool.listen(first)
    pool.listen(lambda t: heard.append(("second", t)))
    pool.listen(first)  # twice: told once
    w = pool._workers[0]
    w.conn, w.ready = _DeadEnd(), False  # a worker that died while setting up
    pool._died(w, "died (exit code 1)")
    assert [who for who, _ in heard] == ["on_problem", "first", "second"]
    assert len({t for _, t in heard}) == 1 and "measurement worker 0 died" in heard[0][1]
    pool.close()


def test_each_heads_pairs_are_measured_with_its_own_factory_also_by_a_restarted_worker():
    async def main():
        pool = MeasureWorkerPool(Tagged("bottom"), workers=1, timeout_s=30.0).start()
        gone = asyncio.Event()
        pool.listen(lambda text: gone.set())
        heads = {"bottom": pool, "right": PoolForFactory(pool, Tagged("right")),
                 "top": PoolForFactory(pool, Tagged("top"))}
        try:
            async def round_(start):
                futs = {(name, start + i): heads[name].submit(_pair(start + i))
                        for i, name in enumerate(heads)}
                return {key: (await f).measurement for key, f in futs.items()}

            before = await round_(0)
            os.kill(pool.pids[0], signal.SIGKILL)
            await asyncio.wait_for(gone.wait(), 30.0)  # the pool saw it and starts another
            after = await round_(10)
            return before, after, pool.restarts, heads["right"].capacity
        finally:
            pool.close()

    before, after, restarts, capacity = asyncio.run(main())
    assert restarts == 1 and capacity > 0  # the pool's own attributes through the view
    for got in (before, after):
        assert {name: m.tag for (name, _), m in got.items()} == {
            "bottom": "bottom", "right": "right", "top": "top"}
        assert all(m.counts_a == 100 * k for (_, k), m in got.items())
    assert len({m.pid for m in before.values()} | {m.pid for m in after.values()}) == 2


def test_two_services_on_one_pool_each_get_their_own_pairs_in_order(tmp_path):
    from tests.controller.workers.test_service_workers import (
        BACKSTOP_S,
        _collect_pairs,
        _pool,
        _running_plant,
        _truth_of,
    )

    async def main():
        plants = [await _running_plant(tmp_path / name) for name in ("a", "b")]
        pairs = [await _collect_pairs(p, 4) for p in plants]
        table = {(f.counts_a, f.counts_b): _truth_of(f) for ps in pairs for f in ps}
        pool = _pool(table, {}, workers=2)
        before = [len(p.service.results) for p in plants]
        try:
            for p in plants:
                p.service.pipeline.use_workers(pool)
            for fa, fb in zip(*pairs, strict=True):  # the heads' pairs interleaved
                await plants[0].service.pipeline.submit(fa)
                await plants[1].service.pipeline.submit(fb)
            for p in plants:
                await asyncio.wait_for(p.service.pipeline.drain(), BACKSTOP_S)
        finally:
            pool.close()
        res = [p.service.results[n:] for p, n in zip(plants, before, strict=True)]
        for p in plants:
            await p.close()
        return pairs, res

    for name in ("a", "b"):
        (tmp_path / name).mkdir()
    pairs, res = asyncio.run(main())
    for ps, rs in zip(pairs, res, strict=True):
        assert [r.seq for r in rs] == [f.seq for f in ps]
        assert all(r.ok for r in rs), [r.error for r in rs]
        assert [r.counts_a for r in rs] == [int(f.counts_a) for f in ps]


ROLL_CONFIDENCE = 0.3


@dataclass(frozen=True)
class RollHead:
    """A head's factory whose measurers report whether the pair searched for the roll."""

    tag: str

    def __call__(self, shape):
        return RollMeasurer(self.tag)


class RollMeasurer:
    """Searches when the calibrator has no roll for the pair (as the vision's ``_orient``).

    Pair ``k``'s search finds roll ``0.001 k``, confident but on one pair in five and on a
    board's first pair (``counts_b`` = 1: not confident), so a board's first search finds
    nothing and the next pairs must search too.
    """

    def __init__(self, tag):
        self.tag = tag

    def measure(self, image_a, image_b, *, counts_a, counts_b, speed_mm_s=None,
                calibrator=None):
        known = calibrator.known_roll()
        if known is None:
            conf = 0.1 if counts_b == 1 or counts_a % 5 == 0 else 0.9
            calibrator.note_roll(0.001 * counts_a, conf, min_confidence=ROLL_CONFIDENCE)
        return SimpleNamespace(tag=self.tag, k=counts_a, used=known)


def _head_pairs(head: int, boards: int, per_board: int) -> list[tuple[int, Frame]]:
    """A head's pairs: (board, frame), the pair's number unique over the heads."""
    img = np.zeros((4, 6), dtype=np.uint8)
    out = []
    for b in range(boards):
        for i in range(per_board):
            k = 10_000 * head + 100 * b + i
            out.append((b, Frame(seq=k, t_s=0.0, image_a=img, image_b=img, counts_a=k,
                                 counts_b=1 if i == 0 else 2, speed_mm_s=600.0)))
    return out


def _in_process(pairs, every):
    """Pair number -> whether it searched, one calibrator per board as the service does."""
    from vision.calibration.selfcal import SelfCalibrator

    measurer, out, cals = RollMeasurer("-"), {}, {}
    for board, frame in pairs:
        cal = cals.setdefault(board, SelfCalibrator(roll_every=every))
        m = measurer.measure(frame.image_a, frame.image_b, counts_a=frame.counts_a,
                             counts_b=frame.counts_b, calibrator=cal)
        out[m.k] = m.used is None
    return out


def test_four_heads_on_two_workers_search_for_the_roll_on_the_pairs_in_process_would():
    from vision.calibration.selfcal import SelfCalibrator

    every, boards, per_board = 8, 4, 30
    names = ["bottom", "right", "left", "top"]
    pairs = {h: _head_pairs(h, boards, per_board) for h in range(len(names))}

    async def run_all():
        pool = MeasureWorkerPool(RollHead(names[0]), workers=2, timeout_s=60.0).start()
        views = [pool] + [PoolForFactory(pool, RollHead(n)) for n in names[1:]]
        cals = {(h, b): SelfCalibrator(roll_every=every) for h in pairs for b in range(boards)}
        try:
            futures = []
            for k in range(boards * per_board):  # the heads' pairs in turn, many in flight
                for h, view in enumerate(views):
                    board, frame = pairs[h][k]
                    futures.append(view.submit(frame, calibrator=cals[(h, board)]))
            return [await asyncio.wait_for(f, 60.0) for f in futures]
        finally:
            pool.close()

    outcomes = asyncio.run(run_all())
    got = {o.measurement.k: o.measurement for o in outcomes}
    assert all(o.error is None for o in outcomes) and len(got) == 4 * boards * per_board
    for h, name in enumerate(names):
        expected = _in_process(pairs[h], every)
        mine = {k: m for k, m in got.items() if k // 10_000 == h}
        assert {m.tag for m in mine.values()} == {name}  # its own factory
        searched = {k: m.used is None for k, m in mine.items()}
        assert searched == expected, name  # the same pairs search, so as many
        assert sum(searched.values()) < len(searched) / 3  # not every pair in flight
        for k, m in mine.items():  # the others use a confident roll of their own board
            if m.used is not None:
                found = round(m.used[0] / 0.001)
                assert found < k and found // 100 == k // 100 and searched[found]
