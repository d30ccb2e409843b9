"""What crosses between the service and a worker per pair: the calibrator, the reply's arrays.

The board's calibrator goes to the worker as its fields' values (the class and field names
pickled once): the worker's copy must behave exactly as a pickled copy would. The reply's
float arrays come back in the pair's shared-memory slot instead of the pipe: the service must
rebuild the same measurement, and a reply that says its arrays are in a slot it has no slot for
fails its pair instead of reading garbage.
"""

from __future__ import annotations

import math
import pickle
from dataclasses import dataclass
from multiprocessing import shared_memory
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.workers.link import WorkerLink
from controller.workers.process import (
    SLOT_HEAD,
    _cal_from,
    _cal_state,
    _pack_into_slot,
    _Packed,
    _reply_from_slot,
    _reply_into_slot,
)
from vision.calibration.selfcal import Calibration, SelfCalibrator

# ---------------------------------------------------------------------------------------------
# the calibrator as values

_estimates = st.lists(st.builds(
    Calibration,
    gain=st.floats(0.05, 20.0),
    gain_confidence=st.floats(0.0, 1.0),
    scatter_mm=st.floats(0.0, 2.0),
    scatter_fraction=st.floats(0.0, 1.0),
), max_size=12)


def _through_the_pipe(cal):
    return _cal_from(*pickle.loads(pickle.dumps(_cal_state(cal))))


@settings(max_examples=60, deadline=None)
@given(before=_estimates, after=_estimates, weight=st.floats(0.05, 1.0),
       every=st.integers(1, 10), roll=st.none() | st.tuples(st.floats(-5, 5), st.floats(0, 1)))
def test_a_calibrator_sent_as_values_behaves_as_a_pickled_copy(before, after, weight, every,
                                                                roll):
    cal = SelfCalibrator(weight=weight, roll_every=every)
    for est in before:
        cal.update(est)
    if roll is not None:
        cal.note_roll(*roll, min_confidence=0.5)
    sent = _through_the_pipe(cal)
    copy = pickle.loads(pickle.dumps(cal))
    assert type(sent) is SelfCalibrator and sent is not cal
    assert list(vars(sent)) == list(vars(copy))
    for est in after:  # the worker's copy folds in and answers as the pickled one would
        a, b = sent.update(est), copy.update(est)
        assert a == b or (math.isnan(a.gain) and math.isnan(b.gain))
        assert sent.known_roll() == copy.known_roll()
    assert cal.pairs == len(before)  # the service's own calibrator is untouched


def test_the_calibrators_class_and_fields_are_pickled_once_and_its_array_comes_back():
    cal = SelfCalibrator()
    schema, values = _cal_state(cal)
    cal.update(Calibration(gain=1.5, gain_confidence=0.8, scatter_mm=0.2,
                           scatter_fraction=0.3))
    schema2, values2 = _cal_state(cal)
    assert schema2 is schema and values2 != values  # the same bytes, new values
    sent = _cal_from(schema2, values2)
    assert type(sent._scatter) is np.ndarray and sent._scatter.dtype == np.float64
    np.testing.assert_array_equal(sent._scatter, cal._scatter)
    assert sent._scatter is not cal._scatter


class _Slotted:
    __slots__ = ("gain",)

    def __init__(self) -> None:
        self.gain = 1.0


class _Reducing:
    def __init__(self) -> None:
        self.gain = 1.0

    def __reduce__(self):
        return (_Reducing, ())


class _Holder:
    def __init__(self, value) -> None:
        self.value = value


@pytest.mark.parametrize("cal", [
    None,
    _Slotted(),  # no __dict__
    _Reducing(),  # pickled its own way
    _Holder([1.0, 2.0]),  # a list: not plain
    _Holder({"a": 1.0}),
    _Holder(np.zeros((2, 2))),  # a 2-D array
    _Holder(np.zeros(2, np.float32)),  # not float64
    _Holder((1.0, [2.0])),  # a tuple holding a list
])
def test_what_is_not_a_plain_calibrator_goes_as_it_is(cal):
    schema, values = _cal_state(cal)
    assert schema is cal and values is None
    assert _cal_from(schema, values) is cal


# ---------------------------------------------------------------------------------------------
# the reply's arrays through the pair's slot


@dataclass(frozen=True)
class _Meas:
    x_mm: np.ndarray
    pitch_mm: float
    widths_mm: np.ndarray
    counts: np.ndarray
    knife_mm: np.ndarray | None = None


_floats = st.lists(st.floats(allow_nan=False, width=64), max_size=40).map(
    lambda v: np.asarray(v, dtype=np.float64))


@pytest.fixture(scope="module")
def block():
    shm = shared_memory.SharedMemory(create=True, size=3 * 1024)
    yield shm
    shm.close()
    shm.unlink()


def _worker_with(block, slot_bytes: int) -> WorkerLink:
    w = WorkerLink(3)
    w.block, w.slot_bytes = block, slot_bytes
    return w


@settings(max_examples=80, deadline=None)
@given(x=_floats, widths=_floats, knife=st.none() | _floats, pitch=st.floats(allow_nan=False),
       slot=st.integers(0, 2), estimates=st.lists(st.floats(0.1, 3.0), max_size=2))
def test_arrays_back_through_the_slot_rebuild_the_measurement(block, x, widths, knife, pitch,
                                                              slot, estimates):
    slot_bytes = 1024
    base = slot * slot_bytes
    meas = _Meas(x, pitch, widths, np.arange(3, dtype=np.int32), knife_mm=knife)
    ests = tuple(Calibration(gain=g) for g in estimates)
    packed = _pack_into_slot(meas, block.buf, base + SLOT_HEAD, slot_bytes - SLOT_HEAD)
    assert type(packed) is _Packed
    fits = 8 * sum(packed.lengths) <= slot_bytes - SLOT_HEAD
    assert (packed.blob is None) == fits  # in the slot when it fits, else in the reply
    sent = ("done", 7, None, packed, ests, 0.25, None)
    worker = _worker_with(block, slot_bytes)
    if _reply_into_slot(sent, block.buf, base, slot_bytes):  # the reply after the arrays
        reply = worker.slotted(SimpleNamespace(slot=slot, ticket=7))
    else:  # no room left in the slot: through the pipe
        reply = pickle.loads(pickle.dumps(sent))
    out = worker.outcome(reply, slot)
    assert out.error is None and out.worker == 3 and out.measure_s == 0.25
    assert out.estimates == ests
    back = out.measurement
    assert type(back) is _Meas and list(vars(back)) == list(vars(meas))
    for name, value in vars(meas).items():
        got = getattr(back, name)
        if isinstance(value, np.ndarray):
            assert got.dtype == value.dtype and got.shape == value.shape
            np.testing.assert_array_equal(got, value)
        else:
            assert got == value
    if fits and x.size:  # a copy: the slot's next pair does not change it
        before = back.x_mm.copy()
        block.buf[base:base + slot_bytes] = b"\xff" * slot_bytes
        np.testing.assert_array_equal(back.x_mm, before)


def test_a_reply_whose_arrays_are_in_a_slot_it_was_not_given_fails_its_pair(block):
    meas = _Meas(np.ones(4), 1.0, np.ones(3), np.zeros(1, np.int32))
    packed = _pack_into_slot(meas, block.buf, SLOT_HEAD, 1024 - SLOT_HEAD)
    assert packed.blob is None
    reply = ("done", 1, None, packed, (), 0.0, None)
    no_slot = _worker_with(block, 1024).outcome(reply, None)
    too_big = _worker_with(block, 80).outcome(reply, 0)  # more arrays than the slot holds
    for out in (no_slot, too_big):
        assert out.measurement is None and out.worker == 3
        assert out.error == ("measurement failed: measurement worker 3 sent a reply without "
                             "its arrays")


def test_arrays_that_do_not_fit_the_slot_stay_in_the_reply(block):
    meas = _Meas(np.ones(100), 1.0, np.ones(100), np.zeros(1, np.int32))
    block.buf[:8 * 200] = b"\xee" * (8 * 200)
    packed = _pack_into_slot(meas, block.buf, 0, 8 * 200 - 1)
    assert type(packed) is _Packed and packed.blob is not None  # the arrays go with the reply
    np.testing.assert_array_equal(packed.blob, np.ones(200))
    assert packed.lengths == (100, 100) and packed.names == ("x_mm", "widths_mm")
    assert bytes(block.buf[:8 * 200]) == b"\xee" * (8 * 200)  # the slot left as it was
    not_plain = SimpleNamespace(x_mm=np.ones(3), widths_mm=np.ones(3))
    assert _pack_into_slot(not_plain, block.buf, 0, 4096) is not_plain  # not packed: as it is


# ---------------------------------------------------------------------------------------------
# end to end: real workers, the slots used over and over


@dataclass(frozen=True)
class _Profile:
    x_mm: np.ndarray
    height_um: np.ndarray
    widths_mm: np.ndarray
    image_sum: float
    pair: int


class _ProfileOfImages:
    takes_facts = False

    def __call__(self, shape):
        return self

    def measure(self, image_a, image_b, *, counts_a, counts_b, speed_mm_s=None,
                calibrator=None):
        rows = image_a.astype(np.float64).mean(axis=1)  # from the slot's images
        return _Profile(x_mm=np.arange(counts_a + 2, dtype=np.float64) * 0.5 + counts_a,
                        height_um=rows - image_b.astype(np.float64).mean(axis=1),
                        widths_mm=np.full(counts_a % 5 + 2, float(counts_b)),
                        image_sum=float(image_a.sum()) + float(image_b.sum()), pair=counts_a)


def test_workers_give_back_each_pairs_own_arrays_through_the_slots():
    import asyncio
    from types import SimpleNamespace

    from controller.workers.pool import MeasureWorkerPool

    rng = np.random.default_rng(5)
    n = 24
    images = [(rng.integers(0, 255, (9, 16), np.uint8), rng.integers(0, 255, (9, 16), np.uint8))
              for _ in range(n)]

    async def main(pool):
        futures = [pool.submit(SimpleNamespace(image_a=a, image_b=b, counts_a=i,
                                               counts_b=2 * i, speed_mm_s=1.0))
                   for i, (a, b) in enumerate(images)]  # more than the slots: reused
        return [await asyncio.wait_for(f, 30.0) for f in futures]

    factory = _ProfileOfImages()
    with MeasureWorkerPool(factory, workers=2, timeout_s=30.0) as pool:
        pool.start()
        out = asyncio.run(main(pool))
    assert {o.worker for o in out} == {0, 1}
    for i, ((a, b), o) in enumerate(zip(images, out, strict=True)):
        want = factory.measure(a, b, counts_a=i, counts_b=2 * i)
        got = o.measurement
        assert o.error is None and type(got) is _Profile and got.pair == i
        assert got.image_sum == want.image_sum  # measured before the slot took the arrays
        for name in ("x_mm", "height_um", "widths_mm"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name))


# ---------------------------------------------------------------------------------------------
# replies in the slots: told in batches while saturated, not lost when the worker dies


def _record(ticket: int = 7) -> tuple:
    return ("done", ticket, None, {"pitch_mm": 1.5}, (), 0.001, None)


@pytest.mark.parametrize("spoil, why", [
    (None, "a whole record"),
    ("ticket", "another pair's record"),
    ("magic", "killed before the magic was written"),
    ("image", "the pair's images, no record"),
    ("length", "a record longer than the slot"),
    ("body", "a record whose body cannot be read"),
])
def test_a_reply_is_read_from_its_slot_only_when_whole_and_its_own(block, spoil, why):
    room = 1024
    block.buf[:room] = np.random.default_rng(1).integers(0, 255, room, np.uint8).tobytes()
    assert _reply_into_slot(_record(), block.buf, 0, room)
    if spoil == "magic":
        block.buf[:8] = bytes(8)
    elif spoil == "image":
        block.buf[:room] = np.random.default_rng(2).integers(0, 255, room, np.uint8).tobytes()
    elif spoil == "length":
        block.buf[24:32] = (room).to_bytes(8, "little")
    elif spoil == "body":
        block.buf[SLOT_HEAD:SLOT_HEAD + 8] = b"\x80\x05junk" + bytes(2)
    got = _reply_from_slot(block.buf, 0, room, 8 if spoil == "ticket" else 7)
    assert (got == _record()) if spoil is None else got is None, why


def test_a_reply_that_does_not_fit_its_slot_is_not_written(block):
    assert not _reply_into_slot(_record(), block.buf, 0, SLOT_HEAD + 16)
    assert not _reply_into_slot(_record(), block.buf, 0, 10)


def _told(far) -> list:
    """What the worker's side wrote so far, as messages (without waiting)."""
    out = []
    while far.poll():
        out.append(far.recv())
    return out


def test_replies_are_held_while_the_worker_is_saturated_and_told_together(block):
    import multiprocessing

    from controller.workers.process import _Replies

    near, far = multiprocessing.Pipe()
    replies = _Replies(near, hold=3)
    slot = (block.buf, 0, 1024)
    try:
        replies.add(_record(1), waiting=5, slot=slot)
        replies.add(_record(2), waiting=4, slot=slot)
        assert _told(far) == []  # saturated: held
        replies.add(_record(3), waiting=3, slot=slot)
        assert _told(far) == [("slotted", (1, 2, 3))]  # `hold` of them: told in one message
        replies.add(_record(4), waiting=2, slot=slot)
        replies.add(_record(5), waiting=1, slot=slot)  # fewer than 2 behind: no longer held
        assert _told(far) == [("slotted", (4, 5))]
        replies.add(_record(6), waiting=4, slot=slot)
        replies.add(_record(7), waiting=4, slot=None)  # no slot: the pipe, after those held
        assert _told(far) == [("slotted", (6,)), _record(7)]
        replies.add(("fault", 8, "bug"), waiting=4, slot=slot)  # never held
        assert _told(far) == [("fault", 8, "bug")]
        replies.add(_record(9), waiting=4, slot=slot)
        replies.flush()  # the worker about to wait: nothing stays held
        assert _told(far) == [("slotted", (9,))]
    finally:
        near.close()
        far.close()


class _Gated:
    """Pairs measured in a worker: pair 0 waits for ``gate`` (the test has queued the rest),
    pair ``kill`` kills its worker."""

    takes_facts = False

    def __init__(self, gate: str, kill: int = -1) -> None:
        self.gate, self.kill = gate, kill

    def __call__(self, shape):
        return self

    def measure(self, image_a, image_b, *, counts_a, counts_b, speed_mm_s=None,
                calibrator=None):
        import os
        import signal
        import time
        from pathlib import Path

        if counts_a == 0:
            give_up = time.monotonic() + 30.0
            while not Path(self.gate).exists() and time.monotonic() < give_up:
                time.sleep(0.001)
        if counts_a == self.kill:
            os.kill(os.getpid(), signal.SIGKILL)
        return _Profile(x_mm=np.arange(4, dtype=np.float64) + counts_a,
                        height_um=image_a.astype(np.float64).mean(axis=1),
                        widths_mm=np.full(3, float(counts_b)),
                        image_sum=float(image_a.sum()) + float(image_b.sum()), pair=counts_a)


def _run_gated(tmp_path, factory, n: int):
    """``n`` pairs (64 x 64) to one worker of depth 8, all queued before pair 0 ends; the
    outcomes, the messages the pool got (a batch of slotted replies as its size) and the pool's
    problems."""
    import asyncio

    from controller.workers.pool import MeasureWorkerPool

    rng = np.random.default_rng(9)
    images = [(rng.integers(0, 255, (64, 64), np.uint8), rng.integers(0, 255, (64, 64), np.uint8))
              for _ in range(n)]
    seen: list = []

    async def main(pool):
        real = pool._handle  # noqa: SLF001 - what reached the pool, in order

        def spy(w, msg):
            seen.append(len(msg[1]) if msg[0] == "slotted" else msg[0])
            real(w, msg)

        pool._handle = spy
        futures = [pool.submit(SimpleNamespace(image_a=a, image_b=b, counts_a=i,
                                               counts_b=2 * i, speed_mm_s=1.0))
                   for i, (a, b) in enumerate(images)]
        (tmp_path / "go").touch()  # every job is in the worker's pipe now
        return [await asyncio.wait_for(f, 30.0) for f in futures]

    with MeasureWorkerPool(factory, workers=1, timeout_s=30.0, depth=8) as pool:
        pool.start()
        out = asyncio.run(main(pool))
        problems = list(pool.problems)
    return images, out, seen, problems


def test_a_saturated_worker_tells_its_replies_in_batches_and_each_pair_gets_its_own(tmp_path):
    images, out, seen, _ = _run_gated(tmp_path, _Gated(str(tmp_path / "go")), 8)
    # 7 behind pair 0: held to 4 (depth 8 // 2); then 3 until fewer than 2 wait; the last alone
    assert seen == [4, 3, 1]
    for i, ((a, b), o) in enumerate(zip(images, out, strict=True)):
        assert o.error is None and o.measurement.pair == i
        assert o.measurement.image_sum == float(a.sum()) + float(b.sum())
        np.testing.assert_array_equal(o.measurement.widths_mm, np.full(3, 2.0 * i))


def test_a_worker_that_dies_holding_replies_loses_none_and_hands_on_the_pairs_behind(tmp_path):
    images, out, seen, problems = _run_gated(tmp_path, _Gated(str(tmp_path / "go"), kill=2), 6)
    # pairs 0 and 1 were measured and held (4 and 3 behind them) when pair 2 killed the worker
    assert [o.error is None for o in out] == [True, True, False, True, True, True]
    assert out[2].error.startswith("measurement failed: measurement worker 0 died (killed by "
                                   "SIGKILL)")
    for i in (0, 1, 3, 4, 5):  # read from the slots, or measured by the worker started again
        assert out[i].measurement.pair == i
        np.testing.assert_array_equal(out[i].measurement.widths_mm, np.full(3, 2.0 * i))
    assert seen[0] == "ready"  # nothing told before the death: 0 and 1 read from their slots
    assert problems == [
        "measurement worker 0 died (killed by SIGKILL): 1 pair(s) failed; worker started again"]


def test_the_inbox_counts_whole_messages_and_assembles_long_ones_over_reads():
    import multiprocessing
    import threading

    from controller.workers.process import READ_BYTES, _Inbox

    near, far = multiprocessing.Pipe()
    big = ("job", 3, ("pickled", np.arange(3 * READ_BYTES, dtype=np.uint8)))  # several reads
    try:
        inbox = _Inbox(near)
        inbox.poll()
        assert not inbox.pending  # nothing came: no wait
        far.send(("job", 1))
        far.send(("job", 2))
        writer = threading.Thread(target=far.send, args=(big,))  # blocks until it is read
        writer.start()
        assert inbox.next() == ("job", 1)
        inbox.poll()
        assert inbox.pending[0] == ("job", 2)  # the one behind it, counted without waiting
        assert inbox.next() == ("job", 2)
        got = inbox.next()  # waits for the whole long message
        writer.join(5.0)
        assert got[:2] == big[:2] and np.array_equal(got[2][1], big[2][1])
        far.close()
        with pytest.raises(EOFError):
            inbox.next()
    finally:
        near.close()
