"""The short paths of a pair, judged by order and by thread, never by time.

* the spool reader is woken by a commit (inotify), not by its poll interval; the commit filter;
* the fast spool image format (raw ``.npy``) reads back the same pixels;
* a measurement on the event loop's own thread once the recent ones were short, never while a
  set-up is under way, never when switched off; under the fair scheduler for its duration;
* the feed's Modbus request is on the wire before the uniformity loop computes, and the pair's
  control returns only once the write returned (a refused write is taken back);
* the Modbus call's time limit runs in the calling task.
"""

from __future__ import annotations

import asyncio
import os
import struct
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from controller.frames.spool_watch import IN_MOVED_TO, IN_Q_OVERFLOW, SpoolWatch, summarize
from protocol.frames import Frame

BACKSTOP_S = 60.0


def _event(name: bytes, mask: int = IN_MOVED_TO) -> bytes:
    padded = name + b"\0" * (16 - len(name) % 16) if name else b""
    return struct.pack("iIII", 1, mask, 0, len(padded)) + padded


@pytest.mark.parametrize(("names", "commit"), [
    ([b"pair-000000000001.json"], True),
    ([b"pair-000000000001.a.png", b"pair-000000000001.b.npy"], False),
    ([b".tmp-pair-000000000001.json"], False),  # the writer's temporary name
    ([b"pair-000000000001.a.png", b"pair-000000000001.json"], True),
    ([], False),
])
def test_only_a_metadata_file_is_a_commit(names, commit):
    assert summarize(b"".join(_event(n) for n in names)).commit is commit


def test_an_overflowed_event_queue_counts_as_a_commit():
    # events were lost: the reader must look at the folder
    assert summarize(_event(b"", IN_Q_OVERFLOW)).commit


def test_a_watch_wakes_for_a_commit_and_not_for_images(tmp_path):
    watch = SpoolWatch(tmp_path)
    if not watch.active:
        pytest.skip("no inotify here")
    try:
        (tmp_path / "pair-000000000000.a.png").write_bytes(b"x")  # close-write of an image
        assert watch.wait(0.0) is False
        (tmp_path / ".tmp").write_bytes(b"{}")
        os.rename(tmp_path / ".tmp", tmp_path / "pair-000000000000.json")  # the commit
        assert watch.wait(BACKSTOP_S) is True
        assert watch.wait(0.0) is False  # read once
    finally:
        watch.close()
    watch.close()  # idempotent


def test_a_folder_that_is_not_there_is_polled(tmp_path):
    stop = threading.Event()
    stop.set()
    watch = SpoolWatch(tmp_path / "missing", stop=stop)
    assert not watch.active and not watch.retry()
    assert watch.wait(BACKSTOP_S) is False  # returns at once: stop is set
    (tmp_path / "missing").mkdir()
    again = SpoolWatch(tmp_path / "missing")
    assert watch.retry() is again.active
    again.close()


def _frame(seq: int, image: np.ndarray) -> Frame:
    return Frame(seq=seq, t_s=0.01 * seq, image_a=image, image_b=image[::-1].copy(),
                 counts_a=seq, counts_b=seq + 1, speed_mm_s=600.0)


def test_a_committed_pair_wakes_the_reader_thread_without_its_poll_interval(tmp_path):
    # poll interval one hour: only the commit's wake-up can deliver the pair in time
    from controller.frames.source import SpoolFrameSource
    from protocol.spool import SpoolReader, SpoolWriter

    spool = tmp_path / "spool"
    spool.mkdir()
    if not SpoolWatch(spool).active:
        pytest.skip("no inotify here")
    image = np.arange(8 * 12, dtype=np.uint8).reshape(8, 12)
    source = SpoolFrameSource(SpoolReader(spool), poll_s=3600.0)
    writer = SpoolWriter(spool, keep=4, fsync=False)

    async def main():
        waiting = asyncio.ensure_future(source.next())
        for _ in range(20):
            await asyncio.sleep(0)
        writer.write(_frame(7, image))
        return await asyncio.wait_for(waiting, BACKSTOP_S)

    try:
        frame = asyncio.run(main())
    finally:
        source.close()
    assert frame.seq == 7 and np.array_equal(frame.image_a, image)
    assert not source._thread.is_alive()  # close() ended the long wait


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_raw_spool_images_read_back_the_same_pixels(tmp_path, dtype):
    from protocol.spool import SpoolReader, SpoolWriter

    rng = np.random.default_rng(3)
    image = rng.integers(0, np.iinfo(dtype).max, size=(9, 13)).astype(dtype)
    writer = SpoolWriter(tmp_path, keep=4, fsync=False, image_format="npy")
    meta = writer.write(_frame(3, image))
    assert sorted(p.suffix for p in tmp_path.glob(meta.name.split(".")[0] + ".*")) == [
        ".json", ".npy", ".npy"]
    frame = SpoolReader(tmp_path, start="all").poll()
    assert frame is not None and frame.error is None
    assert frame.image_a.dtype == dtype
    assert np.array_equal(frame.image_a, image) and np.array_equal(frame.image_b, image[::-1])


def test_an_unknown_spool_image_format_is_refused(tmp_path):
    from protocol.spool import SpoolWriter

    with pytest.raises(ValueError, match="image_format"):
        SpoolWriter(tmp_path, image_format="jpeg")


# ------------------------------------------------------------------ measurement on the loop


class _Measurer:
    def __init__(self, threads: list):
        self.threads = threads

    def measure(self, image_a, image_b, **_kw):
        self.threads.append(threading.get_ident())
        return SimpleNamespace(pitch_mm=1.0)


def _stage(threads: list, **kw):
    from config.machine import load_machine
    from controller.service.measurement import MeasurementStage

    return MeasurementStage(load_machine().plausibility, lambda shape: _Measurer(threads),
                            threaded=True, **kw)


def _measure_all(stage, n: int) -> int:
    image = np.zeros((4, 6), np.uint8)

    async def main():
        for i in range(n):
            error, _ = await stage.measure(_frame(i, image))
            assert error is None
        return threading.get_ident()

    return asyncio.run(main())


def test_after_a_few_short_measurements_the_loop_measures_itself():
    from controller.service.measurement import INLINE_START

    threads: list = []
    stage = _stage(threads)
    stage.inline_max_s = 1e9  # every measurement counts as short
    loop_thread = _measure_all(stage, INLINE_START + 3)
    assert loop_thread not in threads[:INLINE_START]  # the first ones: the worker thread
    assert threads[INLINE_START:] == [loop_thread] * 3
    assert stage.inline_count == 3


def test_switched_off_every_measurement_goes_to_the_worker_thread():
    from controller.service.measurement import INLINE_WINDOW

    threads: list = []
    stage = _stage(threads)
    stage.inline_max_s = 0.0
    loop_thread = _measure_all(stage, INLINE_WINDOW + 3)
    assert loop_thread not in threads and stage.inline_count == 0


@pytest.mark.parametrize("long_ones, inline", [(0, True), (1, True), (2, False), (8, False)])
def test_more_long_measurements_in_the_window_than_the_spare_send_the_next_to_the_thread(
        long_ones, inline):
    from controller.service.measurement import INLINE_SPARE, INLINE_WINDOW

    assert INLINE_SPARE == 1  # the table below is written for one spare
    threads: list = []
    stage = _stage(threads)
    stage.inline_max_s = 1e9
    _measure_all(stage, INLINE_WINDOW)
    for _ in range(long_ones):
        stage._recent_s.append(2e9)  # a measurement beyond the limit
    loop_thread = _measure_all(stage, 1)
    assert (threads[-1] == loop_thread) is inline


def test_the_decision_counts_the_measurements_cpu_time_not_its_wall_time():
    from config.machine import load_machine
    from controller.service.measurement import INLINE_WINDOW, MeasurementStage

    class Waiting(_Measurer):
        def measure(self, image_a, image_b, **_kw):
            time.sleep(0.02)  # held up by the world (a busy host): wall time, no CPU time
            return super().measure(image_a, image_b)

    threads: list = []
    stage = MeasurementStage(load_machine().plausibility, lambda shape: Waiting(threads),
                             threaded=True)
    stage.inline_max_s = 0.01  # less than each measurement's wall time, more than its CPU time
    loop_thread = _measure_all(stage, INLINE_WINDOW)
    assert threads[-1] == loop_thread and stage.inline_count > 0
    assert stage.last_measure_s >= 0.02  # the record still says how long it took


def test_no_measurement_on_the_loop_while_a_set_up_holds_the_build_lock():
    from controller.service.measurement import INLINE_WINDOW

    threads: list = []
    stage = _stage(threads)
    stage.inline_max_s = 1e9
    _measure_all(stage, INLINE_WINDOW)
    frame = _frame(99, np.zeros((4, 6), np.uint8))
    with stage._build_lock:  # a set-up under way in another thread
        assert stage._inline_measurer(frame, None) is None
    assert stage._inline_measurer(frame, None) is not None
    other = _frame(98, np.zeros((5, 6), np.uint8))  # a shape never built: not on the loop
    assert stage._inline_measurer(other, None) is None


def test_the_loops_own_measurement_keeps_the_loops_real_time_priority():
    # the pair's own path: a busy host must not take the core from it mid-measurement
    if not hasattr(os, "SCHED_FIFO"):
        pytest.skip("no SCHED_FIFO here")
    seen: dict = {}

    class Noting(_Measurer):
        def measure(self, image_a, image_b, **_kw):
            seen.setdefault("policies", []).append(
                (threading.get_ident(), os.sched_getscheduler(0)))
            return super().measure(image_a, image_b)

    from config.machine import load_machine
    from controller.service.measurement import INLINE_START, MeasurementStage

    threads: list = []
    stage = MeasurementStage(load_machine().plausibility, lambda shape: Noting(threads),
                             threaded=True)
    stage.inline_max_s = 1e9

    def in_thread():
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        except OSError:
            seen["skip"] = True
            return
        try:
            seen["loop"] = _measure_all(stage, INLINE_START + 2)
            seen["after"] = os.sched_getscheduler(0)
        finally:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))

    t = threading.Thread(target=in_thread)
    t.start()
    t.join(BACKSTOP_S)
    if seen.get("skip"):
        pytest.skip("real time not permitted here")
    on_loop = [p for ident, p in seen["policies"] if ident == seen["loop"]]
    assert len(on_loop) == 2 and set(on_loop) == {os.SCHED_FIFO}
    assert seen["after"] == os.SCHED_FIFO


# ------------------------------------------------------------------ the feed write's overlap


def _loops(out):
    from config.machine import machine_from_dict
    from controller.service.events import EventLog
    from controller.service.loops import ControlLoops

    cfg = machine_from_dict({"piezo": {"stroke_um": 20.0}})
    rig = SimpleNamespace(camera=SimpleNamespace(cx=320.0, px_per_mm=16.0))
    return ControlLoops(cfg, rig, out, EventLog(), SimpleNamespace(untracked_s=None),
                        pairs_per_s=10.0)


def _snap():
    from controller.fieldbus.plc_protocol import PlcSnapshot

    return PlcSnapshot(values={
        "knives": 4, "feed_min_mm_s": 50.0, "feed_max_mm_s": 1000.0, "spindle_rpm": 6000.0,
        "cutterhead_radius_mm": 60.0, "cutter_to_camera_mm": 300.0, "feed_setpoint_mm_s": 600.0,
        "feed_actual_mm_s": 600.0}, t_s=0.0)


class _OrderedActuators:
    """The feed write: request out at once, the PLC's answer when ``answer`` is set."""

    def __init__(self, events: list, taken: bool = True):
        self.events = events
        self.taken = taken
        self.answer: asyncio.Event | None = None
        self.offsets_um = ()
        self.feed_setpoint_mm_s = None
        self.piezo = SimpleNamespace(knives=4)

    def set_knives(self, knives):
        self.piezo.knives = knives

    def set_offsets(self, offsets_um, t):
        self.events.append("offsets sent")
        self.offsets_um = tuple(float(v) for v in offsets_um)
        return self.offsets_um

    async def write_feed(self, feed_mm_s, t):
        self.events.append("feed request on the wire")
        self.answer = asyncio.Event()
        asyncio.get_running_loop().call_soon(self.answer.set)  # the PLC answers
        await self.answer.wait()
        self.events.append("feed write returned")
        if self.taken:
            self.feed_setpoint_mm_s = feed_mm_s
        return self.taken


WIDTHS_MM = np.array([0.37, 0.38, 0.36, 0.37])


def _apply(out, widths=WIDTHS_MM):
    loops = _loops(out)
    loops.ensure(_snap())
    events = out.events
    orig = loops.uniformity_loop.update
    loops.uniformity_loop.update = lambda **kw: events.append("uniformity update") or orig(**kw)
    att = SimpleNamespace(pass_pitch_mm=1.5, knife_widths_mm=widths, bdc_pitch_mm=1.5)
    applied = asyncio.run(loops.apply(att, 5.0, _snap(), 5.0))
    return loops, applied


def test_the_feed_request_goes_out_before_the_uniformity_loop_computes():
    events: list = []
    loops, applied = _apply(_OrderedActuators(events))
    assert events == ["feed request on the wire", "uniformity update", "offsets sent",
                      "feed write returned"]
    assert applied and loops.out.feed_setpoint_mm_s is not None


_UNMARKED = SimpleNamespace(pass_pitch_mm=1.5, knife_widths_mm=np.full(4, np.nan),
                            bdc_pitch_mm=1.5)  # a pair whose knives left no mark: feed only


def _loops_noting_rejects(out):
    """The loops on ``out``, set up; the list the feed loop's take-backs are noted in."""
    loops = _loops(out)
    loops.ensure(_snap())
    rejected: list = []
    loops.feed_loop.reject = lambda: rejected.append(True)
    return loops, rejected


def test_a_refused_feed_write_is_taken_back_after_the_overlap():
    events: list = []
    out = _OrderedActuators(events, taken=False)
    loops, rejected = _loops_noting_rejects(out)
    att = _UNMARKED
    assert asyncio.run(loops.apply(att, 5.0, _snap(), 5.0)) is False
    assert rejected == [True] and events[-1] == "feed write returned"


def test_an_error_of_the_uniformity_loop_still_waits_for_the_feed_write():
    events: list = []
    out = _OrderedActuators(events)
    loops = _loops(out)
    loops.ensure(_snap())

    def broken(**_kw):
        events.append("uniformity update")
        raise ArithmeticError("broken law")

    loops.uniformity_loop.update = broken
    att = SimpleNamespace(pass_pitch_mm=1.5, knife_widths_mm=np.full(4, 0.37), bdc_pitch_mm=1.5)
    with pytest.raises(ArithmeticError):
        asyncio.run(loops.apply(att, 5.0, _snap(), 5.0))
    assert events == ["feed request on the wire", "uniformity update", "feed write returned"]


def test_the_modbus_time_limit_runs_in_the_calling_task():
    from controller.fieldbus.plc_client import _within

    if not hasattr(asyncio, "timeout"):
        pytest.skip("Python 3.10: asyncio.wait_for")

    async def main():
        me = asyncio.current_task()

        async def request():
            return asyncio.current_task() is me

        assert await _within(request, 1.0) is True

        async def never():
            await asyncio.Event().wait()

        with pytest.raises(asyncio.TimeoutError):
            await _within(never, 0.0)

    asyncio.run(main())


def test_the_bench_names_the_spool_image_format():
    from planer.benchmarks import service as bench

    assert bench.SPOOL_IMAGE_FORMAT in ("png", "npy")
    mode = {"workers": 0, "rate_hz": 100.0, "via": "spool", "spool_image_format": "npy",
            "failed": 1}
    text = bench.text({"width": 8, "height": 4, "rate_hz": 100.0, "transport": "t",
                       "modes": [mode], "machine": {}})
    assert "through a spool (npy)" in text


def test_prioritize_schedules_the_spool_reader_thread_with_the_bus_thread(tmp_path):
    from controller.frames.source import SpoolFrameSource
    from controller.service.latency import MEASURE_NICE, prioritize
    from core.realtime import BUS_RT_PRIORITY
    from protocol.spool import SpoolReader, SpoolWriter

    spool = tmp_path / "spool"
    spool.mkdir()
    source = SpoolFrameSource(SpoolReader(spool), poll_s=0.01)
    service = SimpleNamespace(measurement=SimpleNamespace(), records=SimpleNamespace())
    prioritize(service, source=source)
    assert service.measurement.thread_nice == MEASURE_NICE
    assert source.reader_priority[0] == BUS_RT_PRIORITY
    SpoolWriter(spool, keep=4, fsync=False).write(_frame(1, np.zeros((4, 6), np.uint8)))

    async def main():
        return await asyncio.wait_for(source.next(), BACKSTOP_S)

    try:
        frame = asyncio.run(main())
        granted = source.reader_granted
    finally:
        source.close()
    assert frame.seq == 1
    # the thread asked before reading the pair: what it got, or why not
    assert granted.startswith(("SCHED_FIFO", "nice", "normal ("))
    prioritize(service, source=object())  # a source without a reader thread: nothing to do


def test_a_watch_whose_folder_went_says_so_and_a_new_one_is_possible(tmp_path):
    spool = tmp_path / "spool"
    spool.mkdir()
    watch = SpoolWatch(spool)
    if not watch.active:
        pytest.skip("no inotify here")
    spool.rmdir()  # the folder itself goes
    assert watch.wait(BACKSTOP_S) is True  # the reader looks (and finds no folder)
    assert not watch.active and not watch.retry()
    spool.mkdir()
    assert watch.retry()
    again = SpoolWatch(spool)
    assert again.active
    again.close()


def test_an_error_of_the_feed_write_itself_reaches_the_caller_and_is_taken_back():
    events: list = []
    out = _OrderedActuators(events)

    async def broken_write(feed_mm_s, t):
        events.append("feed request on the wire")
        raise RuntimeError("a bug in the write")

    out.write_feed = broken_write
    loops, rejected = _loops_noting_rejects(out)
    att = _UNMARKED
    with pytest.raises(RuntimeError, match="a bug"):
        asyncio.run(loops.apply(att, 5.0, _snap(), 5.0))
    assert rejected == [True]


def test_the_bench_camera_prunes_one_pair_after_taking_its_commit_time(tmp_path):
    from planer.benchmarks.service import _prune_slot

    for slot in (3, 4):
        for suffix in (".a.npy", ".b.npy", ".json"):
            (tmp_path / f"pair-{slot:012d}{suffix}").write_bytes(b"x")
    _prune_slot(tmp_path, 3)
    _prune_slot(tmp_path, -1)  # nothing that old yet
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "pair-000000000004.a.npy", "pair-000000000004.b.npy", "pair-000000000004.json"]


class _QuietWatch:
    """A stand-in for ``SpoolWatch`` whose events name no slots; tests give it ``wait``."""

    active = True

    def __init__(self, directory, *, stop=None):
        self.stop = stop

    def retry(self):
        return True

    def take_committed(self):
        return []

    def close(self):
        pass



def _run_reader(monkeypatch, watch_cls, reader, done: threading.Event) -> None:
    """A spool source's reader thread on ``reader`` with ``watch_cls`` as its watch, until
    ``done``."""
    import controller.frames.source as fs

    monkeypatch.setattr(fs, "SpoolWatch", watch_cls)
    source = fs.SpoolFrameSource(reader, poll_s=0.002)
    try:
        assert done.wait(BACKSTOP_S)
    finally:
        source.close()

@pytest.mark.parametrize("events_come", [True, False])
def test_the_reader_polls_rarely_only_once_the_events_announced_a_pair(tmp_path, monkeypatch,
                                                                       events_come):
    import controller.frames.source as fs
    from protocol.spool import SpoolReader

    timeouts: list = []
    done = threading.Event()

    class FakeWatch(_QuietWatch):
        def wait(self, timeout_s):
            timeouts.append(timeout_s)
            if len(timeouts) >= 6:
                done.set()
                self.stop.wait(BACKSTOP_S)
            return events_come

    class Pairs(SpoolReader):
        calls = 0

        def poll(self):
            self.calls += 1
            if self.calls in (2, 4):  # a pair after the first and after the third wait
                return _frame(self.calls, np.zeros((4, 6), np.uint8))
            return None

    _run_reader(monkeypatch, FakeWatch, Pairs(tmp_path), done)
    assert timeouts[0] == 0.002  # nothing proved yet
    if events_come:  # announced: the fallback polls are rare from then on
        assert timeouts[1:] == [fs.WATCHED_POLL_S] * (len(timeouts) - 1)
    else:  # the polls found the pairs: the events are not trusted
        assert timeouts == [0.002] * len(timeouts)


@pytest.mark.parametrize(("pending", "after_a_pair"), [(0, "wait"), (1, "poll")])
def test_after_a_pair_the_reader_waits_for_the_next_event_unless_pairs_are_pending(
        tmp_path, monkeypatch, pending, after_a_pair):
    from protocol.spool import SpoolReader

    calls: list = []
    done = threading.Event()

    class FakeWatch(_QuietWatch):
        def wait(self, timeout_s):
            calls.append("wait")
            if calls.count("wait") >= 4:
                done.set()
                self.stop.wait(BACKSTOP_S)
            return True  # every wait ended by a commit's event

    class Pairs(SpoolReader):
        n = 0

        @property
        def pending(self):
            return pending

        def poll(self):
            calls.append("poll")
            self.n += 1
            return _frame(self.n, np.zeros((4, 6), np.uint8)) if self.n in (2, 4) else None

    _run_reader(monkeypatch, FakeWatch, Pairs(tmp_path), done)
    # poll (none), wait (an event), poll (pair 2: the events proved), then: wait for the next
    # event, or read the pairs the listing left pending first
    assert calls[:4] == ["poll", "wait", "poll", after_a_pair]


@pytest.mark.parametrize("layout", ["C", "F", "big-endian"])
def test_a_raw_spool_image_reads_back_whatever_its_layout(layout):
    import io

    from protocol.spool_files import SpoolLimits, decode_spool_image

    rng = np.random.default_rng(5)
    image = rng.integers(0, 65535, size=(7, 11)).astype(np.uint16)
    stored = {"C": image, "F": np.asfortranarray(image),
              "big-endian": image.astype(">u2")}[layout]
    bio = io.BytesIO()
    np.save(bio, stored, allow_pickle=False)
    out = decode_spool_image(bio.getvalue(), "pair-000000000001.a.npy", limits=SpoolLimits())
    assert np.array_equal(out, image) and out.shape == (7, 11)
    out[0, 0] = 1  # writable, its own memory
