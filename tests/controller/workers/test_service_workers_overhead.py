"""The workers' per-pair machinery: replies read whole however they arrive, the roll plan.

The service reads each worker's replies with one ``os.read`` per wake-up and cuts the messages
out itself: a reply split over reads, or several in one, must reach their own pairs, in any
order of completion, with failures reported as such. The camera's roll is searched for on the
pairs the service picks in sequence order (:class:`controller.workers.pool._RollPlan`):
exactly the pairs the board's calibrator picks in process, however the pairs in flight overlap
(a board's first pairs, before a confident roll came back, go as one worker's chain); without a
worker to chain on, never less often (at most the pairs in flight more).
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import pickle
import struct
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.workers.pool import MeasurementWorkerError, MeasureWorkerPool, _RollPlan
from controller.workers.process import RollChain, _chain_keeper
from vision.calibration.selfcal import SelfCalibrator

MIN_CONFIDENCE = 0.3
BACKSTOP_S = 30.0  # a reply never matched to its pair fails the test instead of hanging it


# ---------------------------------------------------------------------------------------------
# the roll plan against the calibrator


@settings(max_examples=60, deadline=None)
@given(every=st.integers(1, 10),
       confidences=st.lists(st.sampled_from([0.0, 0.2, 0.5, 0.9]), min_size=1, max_size=40))
def test_roll_plan_searches_as_the_calibrator_does_when_pairs_do_not_overlap(every,
                                                                             confidences):
    plan, cal = _RollPlan(), SelfCalibrator(roll_every=every)
    for i, conf in enumerate(confidences, start=1):
        roll_here = (0.01 * i, conf)
        known = cal.known_roll()
        if known is None:
            cal.note_roll(*roll_here, min_confidence=MIN_CONFIDENCE)
        directive = plan.next(every)
        assert (directive == ()) == (known is None), i  # the same pairs search
        if directive:
            assert directive == known  # and the others use the same roll
        else:
            plan.found(i, roll_here if conf >= MIN_CONFIDENCE else None)


@settings(max_examples=60, deadline=None)
@given(every=st.integers(1, 10), capacity=st.integers(1, 6), n=st.integers(1, 60),
       data=st.data())
def test_roll_plan_with_pairs_in_flight_never_searches_less_and_at_most_capacity_more(
        every, capacity, n, data):
    plan = _RollPlan()
    in_flight: list[tuple[int, tuple]] = []
    searches, newest_done = 0, 0
    for ticket in range(1, n + 1):
        if len(in_flight) == capacity:  # a pair in flight comes back, in any order
            k = data.draw(st.integers(0, len(in_flight) - 1))
            done, directive = in_flight.pop(k)
            if directive == ():
                plan.found(done, (float(done), 1.0))
                newest_done = max(newest_done, done)
        directive = plan.next(every)
        if directive == ():
            searches += 1
        else:  # the newest search that came back, never an older one
            assert directive == (float(newest_done), 1.0)
        in_flight.append((ticket, directive))
    in_process = -(-n // every)  # pairs 0, every, 2 every, ... search
    assert in_process <= searches <= in_process + capacity - 1


def _in_process_searches(confidences: list[float], every: int) -> list[bool]:
    """Which pairs the board's calibrator searches on in process (pair i finds 0.01 i)."""
    cal, out = SelfCalibrator(roll_every=every), []
    for i, conf in enumerate(confidences, start=1):
        known = cal.known_roll()
        if known is None:
            cal.note_roll(0.01 * i, conf, min_confidence=MIN_CONFIDENCE)
        out.append(known is None)
    return out


@settings(max_examples=100, deadline=None)
@given(every=st.integers(1, 10), capacity=st.integers(1, 8),
       confidences=st.lists(st.sampled_from([0.0, 0.2, 0.9, 0.9, 0.9]), min_size=1,
                            max_size=50),
       data=st.data())
def test_roll_plan_with_pairs_in_flight_searches_on_the_pairs_in_process_would(
        every, capacity, confidences, data):
    n = len(confidences)
    plan, chains, link = _RollPlan(), {}, object()  # one worker holds the chains' pairs
    in_flight: list[tuple[int, tuple]] = []
    searched: dict[int, bool] = {}
    confident: set[float] = set()

    def measure(ticket: int, directive: tuple) -> None:
        conf = confidences[ticket - 1]
        if type(directive) is RollChain:  # the worker decides, as the calibrator would
            keeper = _chain_keeper(chains, directive, SelfCalibrator(roll_every=every))
            known = keeper.known_roll()
            if known is None:
                keeper.note_roll(0.01 * ticket, conf, min_confidence=MIN_CONFIDENCE)
        else:
            known = directive or None
            if known is not None:  # a roll a search found before, a confident one
                assert known[0] in confident, (ticket, known)
        searched[ticket] = known is None
        found = (0.01 * ticket, conf) if known is None and conf >= MIN_CONFIDENCE else None
        if found is not None:
            confident.add(found[0])
        plan.found(ticket, found)

    def finish_one() -> None:  # any pair in flight, but a chain's pairs in their order
        k = data.draw(st.integers(0, len(in_flight) - 1))
        if type(in_flight[k][1]) is RollChain:
            k = next(i for i, (_, d) in enumerate(in_flight) if type(d) is RollChain)
        measure(*in_flight.pop(k))

    for ticket in range(1, n + 1):
        if len(in_flight) == capacity:
            finish_one()
        in_flight.append((ticket, plan.next(every, ticket, lambda: link)))
    while in_flight:
        finish_one()
    assert [searched[t] for t in range(1, n + 1)] == _in_process_searches(confidences, every)


def test_a_roll_plan_keeps_the_newest_result_whatever_order_they_come_in():
    plan = _RollPlan()
    plan.found(7, (0.7, 0.9))
    plan.found(3, (0.3, 0.9))  # older: ignored
    plan.found(9, None)  # not confident: ignored
    assert plan.roll == (0.7, 0.9) and plan.ticket == 7


# ---------------------------------------------------------------------------------------------
# the roll plan through real worker processes


class RollCounting:
    """Factory of measurers that report whether they searched for the roll (picklable)."""

    takes_facts = False

    def __call__(self, shape):
        return RollCountingMeasurer()


class RollCountingMeasurer:
    def measure(self, image_a, image_b, *, counts_a, counts_b, speed_mm_s=None,
                calibrator=None):
        known = calibrator.known_roll()
        if known is None:
            calibrator.note_roll(0.001 * counts_a, 0.9, min_confidence=MIN_CONFIDENCE)
        return SimpleNamespace(seq=counts_a, used=known, pid=os.getpid())


def test_workers_search_for_the_roll_on_the_pairs_the_plan_picks():
    n, every = 40, 8
    image = np.zeros((6, 8), np.uint8)

    async def main(pool):
        cal = SelfCalibrator(roll_every=every)
        futures, out = [], []
        for i in range(n):
            frame = SimpleNamespace(image_a=image, image_b=image, counts_a=i, counts_b=i,
                                    speed_mm_s=1.0)
            futures.append(pool.submit(frame, calibrator=cal))
            if len(futures) >= pool.capacity:
                out.append(await futures.pop(0))
        out += [await f for f in futures]
        return out

    with MeasureWorkerPool(RollCounting(), workers=2, timeout_s=60.0) as pool:
        pool.start()
        out = asyncio.run(main(pool))
        capacity = pool.capacity
    assert [o.measurement.seq for o in out] == list(range(n))  # in sequence order
    assert len({o.measurement.pid for o in out}) == 2  # both workers measured
    searched = [o.measurement.seq for o in out if o.measurement.used is None]
    # as in process: the first pair, then one in `every` (the first pairs in flight, before
    # its roll came back, wait for it in its worker)
    assert capacity > every and searched == list(range(0, n, every))
    for o in out:  # the others used a roll a search found
        if o.measurement.used is not None:
            assert round(o.measurement.used[0] / 0.001) in searched


# ---------------------------------------------------------------------------------------------
# replies read whole however they arrive


def _message(obj) -> bytes:
    body = pickle.dumps(obj)
    return struct.pack("!i", len(body)) + body


def _fake_pool(workers: int) -> tuple[MeasureWorkerPool, list]:
    """A pool whose workers are the far ends of pipes (the test answers for them)."""
    pool = MeasureWorkerPool(RollCounting(), workers=workers, timeout_s=60.0, depth=2)
    ends = []
    for w in pool._workers:  # noqa: SLF001 - the pool's own bookkeeping, wired by hand
        near, far = multiprocessing.Pipe()
        w.conn, w.ready, w.free = near, True, list(range(pool.depth))
        ends.append(far)
    return pool, ends


@settings(max_examples=25, deadline=None)
@given(n=st.integers(1, 12), workers=st.integers(1, 3), data=st.data())
def test_replies_split_or_joined_in_any_way_reach_their_own_pairs_in_order(n, workers, data):
    image = np.zeros((4, 5), np.uint8)
    kinds = data.draw(st.lists(st.sampled_from(["ok", "ok", "failed", "fault"]), min_size=n,
                               max_size=n))

    async def main():
        pool, ends = _fake_pool(workers)
        futures: list = []
        try:
            futures += [pool.submit(SimpleNamespace(image_a=image, image_b=image + i,
                                                   counts_a=i, counts_b=i, speed_mm_s=1.0))
                       for i in range(n)]
            held: list[tuple[int, int, int]] = []  # (worker, ticket, pair) taken, not answered
            pending = b""
            answered = 0
            while answered < n:
                for k, far in enumerate(ends):
                    while far.poll():
                        job = far.recv()
                        held.append((k, job[1], job[3]))  # ticket, counts_a = the pair
                if held:
                    k, ticket, pair = held.pop(data.draw(st.integers(0, len(held) - 1)))
                    kind = kinds[pair]
                    if kind == "fault":
                        msg = ("fault", ticket, f"bug in pair {pair}")
                    else:
                        msg = ("done", ticket, None if kind == "ok" else f"failed {pair}",
                               ("measured", pair) if kind == "ok" else None, (), 0.0, None)
                    pending = _message(msg)
                    while pending:  # in pieces of any size, the loop reading in between
                        cut = data.draw(st.integers(1, len(pending)))
                        os.write(ends[k].fileno(), pending[:cut])
                        pending = pending[cut:]
                        for _ in range(3):
                            await asyncio.sleep(0)
                    answered += 1
                else:
                    await asyncio.sleep(0)
            results = []
            for f in futures:  # consumed in sequence order, as the service does
                try:
                    results.append(await asyncio.wait_for(f, BACKSTOP_S))
                except MeasurementWorkerError as exc:
                    results.append(exc)
            return results
        finally:
            pool.close()
            for far in ends:
                far.close()
            for f in futures:  # an example hypothesis cut short: nothing left unretrieved
                if f.done() and not f.cancelled():
                    f.exception()

    results = asyncio.run(main())
    for pair, (kind, got) in enumerate(zip(kinds, results, strict=True)):
        if kind == "ok":
            assert got.error is None and got.measurement == ("measured", pair)
        elif kind == "failed":
            assert got.error == f"failed {pair}" and got.measurement is None
        else:
            assert isinstance(got, MeasurementWorkerError) and f"bug in pair {pair}" in str(got)


def _submit_pairs(pool, n: int) -> list:
    """``n`` small pairs submitted to ``pool`` (counts 0..n-1); their futures."""
    image = np.zeros((4, 5), np.uint8)
    return [pool.submit(SimpleNamespace(image_a=image, image_b=image, counts_a=i, counts_b=i,
                                        speed_mm_s=1.0)) for i in range(n)]


def test_several_replies_in_one_read_all_reach_their_pairs():
    async def main():
        pool, (far,) = _fake_pool(1)
        try:
            futures = _submit_pairs(pool, 2)
            jobs = [far.recv(), far.recv()]
            blob = b"".join(_message(("done", j[1], None, ("m", j[3]), (), 0.0, None))
                            for j in reversed(jobs))  # the later pair first, one write
            os.write(far.fileno(), blob)
            return [await asyncio.wait_for(f, BACKSTOP_S) for f in futures]
        finally:
            pool.close()
            far.close()

    out = asyncio.run(main())
    assert [o.measurement for o in out] == [("m", 0), ("m", 1)]



def test_a_reply_that_cannot_be_read_fails_its_pair_and_the_next_goes_to_the_new_worker():
    async def main():
        pool, (far,) = _fake_pool(1)
        try:
            futures = _submit_pairs(pool, 2)
            far.recv()
            os.write(far.fileno(), struct.pack("!i", 5) + b"\x80\x05junk")  # not a pickle
            out = [await asyncio.wait_for(f, BACKSTOP_S) for f in futures]
            return out, pool.restarts, list(pool.problems)
        finally:
            pool.close()
            far.close()

    out, restarts, problems = asyncio.run(main())
    first, second = out
    assert first.measurement is None  # the pair it was on fails, naming why; nothing hangs
    assert first.error.startswith("measurement failed: measurement worker 0 sent a reply that "
                                  "cannot be read (")
    assert "UnpicklingError" in first.error
    # the pair behind it was never started: the worker started again measured it
    assert second.measure_s > 0 and "cannot be read" not in (second.error or "")
    assert restarts == 1 and "1 pair(s) failed; worker started again" in problems[-1]


# ---------------------------------------------------------------------------------------------
# the bench's figures


def test_scaling_reports_both_ratios_and_where_the_time_goes():
    from config.machine import load_machine, rig_path
    from config.rig import load_rig
    from config.sim import default_sim
    from controller.service.measurement import MachineFacts
    from planer.benchmarks.scaling import scaling
    from plant_sim.machine.machine import Machine

    machine = Machine(default_sim(), seed=3)
    frames: list = []
    while len(frames) < 3:
        frames += [f for f in machine.advance(0.05) if f.image_a is not None]
    regs = machine.register_values()
    facts = MachineFacts(float(regs["cutterhead_radius_mm"]), int(regs["knives"]),
                         float(regs["spindle_rpm"]))
    out = scaling(frames[:3], load_rig(rig_path(load_machine())), facts, max_workers=2,
                  repeat=1, rounds=2)
    rows = out["rows"]
    assert [r["workers"] for r in rows] == [1, 2] and out["pairs"] == 3
    base, here = rows[0]["pairs_per_s"], out["in_process_pairs_per_s"]
    for r in rows:
        assert len(r["rounds_pairs_per_s"]) == 2 and r["pairs_per_s"] > 0
        assert r["ratio"] == pytest.approx(r["pairs_per_s"] / base)
        assert r["per_worker"] == pytest.approx(r["ratio"] / r["workers"])
        assert r["ratio_to_in_process"] == pytest.approx(r["pairs_per_s"] / here)
        assert r["service_cpu_us_per_pair"] > 0
        assert r["worker_cpu_us_per_pair"] is None or r["worker_cpu_us_per_pair"] >= 0
    assert rows[0]["ratio"] == 1.0 and out["in_process_cpu_us_per_pair"] > 0
    assert len(out["load_avg"]) == 3


# ---------------------------------------------------------------------------------------------
# the reply's measurement, its float arrays in one


@dataclass(frozen=True)
class _Meas:
    x_mm: np.ndarray
    pitch_mm: float
    widths_mm: np.ndarray
    counts: np.ndarray  # not float64: stays as it is
    note: str = "m"
    knife_mm: np.ndarray | None = None


_floats = st.lists(st.floats(allow_nan=False, width=64), max_size=8).map(
    lambda v: np.asarray(v, dtype=np.float64))


@settings(max_examples=80, deadline=None)
@given(x=_floats, widths=_floats, knife=st.none() | _floats, pitch=st.floats(allow_nan=False))
def test_a_packed_measurement_comes_back_field_for_field(x, widths, knife, pitch):
    from controller.workers.process import _pack, _Packed

    meas = _Meas(x, pitch, widths, np.arange(3, dtype=np.int32), knife_mm=knife)
    packed = _pack(meas)
    assert type(packed) is _Packed  # two or more float arrays: packed
    back = pickle.loads(pickle.dumps(packed)).unpack()
    assert type(back) is _Meas and list(vars(back)) == list(vars(meas))  # fields in order
    for name, value in vars(meas).items():
        got = getattr(back, name)
        if isinstance(value, np.ndarray):
            assert got.dtype == value.dtype and got.shape == value.shape
            np.testing.assert_array_equal(got, value)
            assert got.flags.writeable
        else:
            assert got == value


@pytest.mark.parametrize("meas", [
    SimpleNamespace(x_mm=np.zeros(3), slope=np.zeros(3)),  # not a dataclass
    _Meas(np.zeros(3), 1.0, np.zeros(2, np.float32), np.zeros(1, int)),  # one float64 array
    ("a", "tuple"),
    None,
])
def test_what_is_not_a_plain_dataclass_of_float_arrays_goes_as_it_is(meas):
    from controller.workers.process import _pack

    assert _pack(meas) is meas


def test_a_roll_chains_pairs_search_on_another_worker_when_the_chains_worker_dies():
    image = np.zeros((4, 5), np.uint8)

    def pair(i):
        return SimpleNamespace(image_a=image, image_b=image, counts_a=i, counts_b=i,
                               speed_mm_s=1.0)

    def done(job, found=None):
        return _message(("done", job[1], None, ("m", job[3]), (), 0.0, found))

    async def main():
        pool, ends = _fake_pool(2)  # depth 2
        cal = SelfCalibrator(roll_every=8)
        try:
            futures = [pool.submit(pair(i), calibrator=cal) for i in range(5)]
            held = [ends[0].recv(), ends[0].recv()]  # the chain: all wait for one worker
            assert not ends[1].poll()
            assert [j[9] for j in held] == [RollChain(held[0][9].key, True),
                                            RollChain(held[0][9].key, False)]
            w = pool._workers[0]  # noqa: SLF001 - it dies while setting up anew: gone
            w.ready = False
            pool._died(w, "died (test)")  # noqa: SLF001
            moved = []
            while len(moved) < 4:
                for _ in range(10_000):  # a pair never handed on fails the test, no hang
                    if ends[1].poll():
                        break
                    await asyncio.sleep(0)
                job = ends[1].recv() if ends[1].poll() else None
                assert job is not None, f"pairs handed on: {len(moved)} of 4"
                moved.append(job)
                found = (0.5, 0.9) if job[3] == 2 else None
                os.write(ends[1].fileno(), done(job, found))
            outs = [await asyncio.wait_for(f, BACKSTOP_S) for f in futures]
            later = pool.submit(pair(5), calibrator=cal)
            last = ends[1].recv()
            os.write(ends[1].fileno(), done(last))
            await asyncio.wait_for(later, BACKSTOP_S)
            return outs, moved, last
        finally:
            pool.close()
            for far in ends:
                far.close()

    outs, moved, last = asyncio.run(main())
    assert "died (test)" in outs[0].error  # the pair it was measuring
    assert [o.measurement for o in outs[1:]] == [("m", i) for i in range(1, 5)]
    assert [(j[3], j[9]) for j in moved] == [(i, ()) for i in range(1, 5)]  # all search
    assert last[9] == (0.5, 0.9)  # then the roll one of them found
