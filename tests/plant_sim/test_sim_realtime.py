"""The simulator's real-time structure: PLC in its own process, images in workers, a clock that
slows itself, CAN read on its own thread. Simulated time throughout (no sleeping, no timing)."""

from __future__ import annotations

import asyncio
import dataclasses
import socket
import struct
import threading

import numpy as np
import pytest

from plant_sim.interfaces.amp_node import AmpNode, AmpNodeCore
from plant_sim.interfaces.plc_process import PlcProcess
from plant_sim.run.driver import PlantDriver
from plant_sim.run.runner import SimRunner
from protocol import can_transport
from protocol.frame_queue import InProcessSource
from protocol.registers import RegisterMap
from tests.plant_sim.test_sim_plc import read_adu
from tests.plant_sim.test_sim_runner import FakeClock
from tests.support import canopen_frames
from tests.support.fake_machine import FakeMachine

RMAP = RegisterMap.load()


def _read_all(sock: socket.socket, tid: int) -> dict:
    first, count = RMAP.span()
    sock.sendall(struct.pack(">HHHBBHH", tid, 0, 6, 1, 3, first, count))
    pdu = read_adu(sock, tid=tid, unit=1)
    assert pdu is not None and pdu[:2] == bytes([3, 2 * count])
    return RMAP.decode_block(list(struct.unpack(f">{count}H", pdu[2:])), first)


def _write_feed(sock: socket.socket, tid: int, value: float) -> bytes | None:
    reg = RMAP["feed_setpoint_mm_s"]
    words = RMAP.encode("feed_setpoint_mm_s", value)
    pdu = struct.pack(">BHHB2H", 16, reg.address, 2, 4, *words)
    sock.sendall(struct.pack(">HHHB", tid, 0, len(pdu) + 1, 1) + pdu)
    return read_adu(sock, tid=tid, unit=1)


@pytest.fixture
def plc_process():
    machine = FakeMachine()
    plc = PlcProcess(machine, port=0)
    plc.set_up(True)
    try:
        yield machine, plc
    finally:
        plc.close()


def test_plc_process_serves_the_published_snapshot_while_the_machine_stands(plc_process):
    """Nothing on the stepping side runs: the server process still answers, consistently."""
    machine, plc = plc_process
    with socket.create_connection(("127.0.0.1", plc.port), timeout=10.0) as s:
        before = _read_all(s, 1)
        assert before["heartbeat_plc"] == machine.heartbeat_plc
        machine.advance(0.001)  # not published yet: the server keeps the snapshot
        assert _read_all(s, 2)["heartbeat_plc"] == before["heartbeat_plc"]
        plc.refresh()
        assert _read_all(s, 3)["heartbeat_plc"] == (before["heartbeat_plc"] + 1) & 0xFFFF
        for tid in range(4, 40):  # many requests with no stepping at all
            assert _read_all(s, tid)["knives"] == machine.knives
    assert plc.requests >= 39 and plc.refused == 0


def test_plc_process_writes_shown_at_once_applied_in_order(plc_process):
    machine, plc = plc_process
    with socket.create_connection(("127.0.0.1", plc.port), timeout=10.0) as s:
        for tid, value in enumerate((120.0, 640.25, 333.5), start=1):
            assert _write_feed(s, tid, value)[:1] == b"\x10"
        assert _write_feed(s, 9, 5000.0) == b"\x90\x03"  # out of range: refused at once
        assert machine.feed_setpoint == 800.0  # the stepping side has not applied them
        plc.refresh()  # a publish before the apply: the written value stays served
        assert _read_all(s, 10)["feed_setpoint_mm_s"] == 333.5
        seen: list[float] = []
        orig = machine.set_feed_setpoint
        machine.set_feed_setpoint = lambda v: (seen.append(v), orig(v))[1]
        n = 0
        for _ in range(1000):  # the pipe delivers them; poll the stepping side's queue
            n += plc.apply_writes()
            if n == 3:
                break
        assert seen == [120.0, 640.25, 333.5]
        plc.refresh()
        assert _read_all(s, 11)["feed_setpoint_mm_s"] == 333.5 == machine.feed_setpoint


def test_plc_process_restart_drops_clients_keeps_port_and_port_in_use_is_named(plc_process):
    from core.errors import FieldbusError

    machine, plc = plc_process
    port = plc.port
    s = socket.create_connection(("127.0.0.1", port), timeout=10.0)
    plc.set_up(False)
    assert not plc.running
    try:
        assert s.recv(10) == b""  # dropped
    except ConnectionResetError:  # dropped before the server had accepted it
        pass
    s.close()
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=10.0)
    plc.set_up(True)
    assert plc.port == port
    with socket.create_connection(("127.0.0.1", port), timeout=10.0) as s2:
        assert _read_all(s2, 1)["knives"] == machine.knives
    other = PlcProcess(FakeMachine(), port=port)
    try:
        with pytest.raises(FieldbusError, match=str(port)):
            other.set_up(True)
    finally:
        other.close()
    assert other._proc is None and other._shm is None


# ------------------------------------------------------------------ rendering in workers
@pytest.mark.parametrize("workers, to_spool", [(1, True), (2, True)])
def test_worker_images_equal_the_machines_own(tmp_path, workers, to_spool):
    """The images the machine would render itself, handed back or written to the spool by the
    workers in order: one worker with the machine's own noise stream; several with each pair's
    noise seeded from (seed, seq)."""
    from config.sim import default_sim
    from plant_sim.machine.machine import Machine
    from plant_sim.rendering.camera import render_images
    from plant_sim.run.render_worker import RenderPool, noise_seed
    from protocol.spool import SpoolReader, SpoolWriter

    cfg = default_sim()
    own = Machine(cfg, seed=3, render_images=True)
    deferred = Machine(cfg, seed=3, render_images=False)
    deferred.assembler.defer_rendering()
    writer = SpoolWriter(tmp_path / "spool", keep=10, fsync=False) if to_spool else None
    pool = RenderPool(cfg, seed=3, workers=workers, writer=writer)
    pool.start()
    try:
        expect, jobs = [], {}
        while len(expect) < 4:
            expect += own.advance(0.05)
            for f in deferred.advance(0.05):
                assert f.image_a is None
                jobs[f.seq] = deferred.assembler.take_job(f.seq)
                pool.submit(f, jobs[f.seq])
        got = pool.take(wait=True)
    finally:
        pool.close()
    assert [f.seq for f in got] == [f.seq for f in expect]
    if workers > 1:  # seeded per pair: independent of which worker rendered it
        expect = [
            dataclasses.replace(f, **dict(zip(("image_a", "image_b"), render_images(
                own.renderer, jobs[f.seq], rng_seed=noise_seed(3, f.seq)), strict=True)))
            for f in expect
        ]
    if to_spool:
        assert all(f.image_a is None for f in got)  # written there, not handed back
        reader = SpoolReader(tmp_path / "spool", start="all")
        got = [reader.poll() for _ in expect]
        assert [f.seq for f in got] == [f.seq for f in expect] and reader.poll() is None
    for a, b in zip(expect, got, strict=True):
        assert np.array_equal(a.image_a, b.image_a) and np.array_equal(a.image_b, b.image_b)
        assert a.truth["pitch_mm"] == b.truth["pitch_mm"] and a.counts_b == b.counts_b


# ------------------------------------------------------------------ the clock slows itself
class SlowHostMachine(FakeMachine):
    """Each step costs ``cost`` x its machine time of (fake) wall time: a host too slow."""

    def __init__(self, clock: FakeClock, cost: float) -> None:
        super().__init__()
        self.clock = clock
        self.cost = cost

    def advance(self, dt_s: float):
        self.clock.now += self.cost * dt_s
        return super().advance(dt_s)


@pytest.mark.parametrize("cost", [2.0, 4.0])
def test_slow_host_slows_the_clock_says_so_once_and_never_bursts(cost):
    from plant_sim.run import runner as runner_mod

    clock, lines = FakeClock(), []
    m = SlowHostMachine(clock, cost)
    runner = SimRunner(m, sink=InProcessSource(maxlen=1000), clock=clock, sleep=clock.sleep,
                       out=lines.append, progress_every_s=100.0, time_scale=1.0)
    bursts: list[int] = []
    orig = runner._step
    count = [0]

    def counting_step():
        count[0] += 1
        orig()

    async def watch():
        while not runner._stop.is_set():
            bursts.append(count[0])
            count[0] = 0
            await asyncio.sleep(0)

    runner._step = counting_step

    async def main():
        w = asyncio.create_task(watch())
        s = await runner.run(duration_s=8.0)
        w.cancel()
        return s

    summary = asyncio.run(main())
    slow = [ln for ln in lines if ln.startswith("slow host")]
    assert len(slow) == 1, lines
    achieved = float(slow[0].split("slowed itself to ")[1].split()[0])
    assert achieved == pytest.approx(1.0 / cost, rel=0.1)
    assert summary.real_time_factor == pytest.approx(1.0 / cost, rel=0.1)
    assert summary.frames == 80 and summary.slowed_s > 0  # every pair, none skipped
    # never more than one slice of catching up at once; further behind, the clock resets
    assert max(bursts) <= runner_mod.MAX_STEPS_PER_ITERATION


class SlowRender:
    """A render pool whose worker finishes one frame per ``per`` runner iterations."""

    workers = 1
    writes_spool = False

    def __init__(self, per: int) -> None:
        self.per = per
        self.queue: list = []
        self.calls = 0
        self.max_pending = 0

    def start(self) -> None: ...

    def close(self) -> None: ...

    @property
    def pending(self) -> int:
        return len(self.queue)

    def submit(self, frame, job) -> None:
        self.queue.append(frame)
        self.max_pending = max(self.max_pending, len(self.queue))

    def take(self, *, wait: bool = False):
        self.calls += 1
        if wait:
            out, self.queue = self.queue, []
            return out
        if self.queue and self.calls % self.per == 0:
            return [self.queue.pop(0)]
        return []


def test_render_backlog_slows_the_machine_instead_of_dropping_frames():
    from plant_sim.run import runner as runner_mod

    clock, lines = FakeClock(), []
    m = FakeMachine(pairs_per_s=200.0)  # more pairs than the slow renderer takes
    m.assembler = type("A", (), {"take_job": staticmethod(lambda seq: None)})()
    sink = InProcessSource(maxlen=10_000)
    render = SlowRender(per=10)
    runner = SimRunner(m, sink=sink, render=render, clock=clock, sleep=clock.sleep,
                       out=lines.append, progress_every_s=100.0)
    summary = asyncio.run(runner.run(duration_s=2.0))
    seqs = [sink.poll().seq for _ in range(len(sink))]
    assert seqs == list(range(1, len(seqs) + 1)) and len(seqs) == m.seq  # in order, all
    assert render.max_pending <= 2 * runner_mod.MAX_RENDER_BACKLOG + 1
    assert summary.real_time_factor < 0.9 and any(ln.startswith("slow host") for ln in lines)


# ------------------------------------------------------------------ CAN on its own thread
def test_amp_node_receiving_thread_hands_frames_over_at_machine_time():
    m = FakeMachine()
    bus = can_transport.open_bus("virtual", "rt-rx")
    svc = can_transport.open_bus("virtual", "rt-rx")
    node = AmpNode(bus, AmpNodeCore(m, knives=4), own_bus=True)
    node.start_receiving()
    driver = PlantDriver(m, amp=node)
    try:
        import can

        frames = [canopen_frames.start()] + [canopen_frames.command(True, 4, a) for a in (5, 6, 7)]
        for fid, data in frames:
            svc.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
        for _ in range(100_000):  # the thread queues them; the machine sees them on a step
            driver.step(0.001)
            if len(m.alive_counters) == 3:
                break
        assert m.alive_counters == [5, 6, 7]
        assert m.last_cmd_s is not None and m.last_cmd_s < m.t_s
    finally:
        node.close()
        svc.shutdown()
    assert not node._rx_thread.is_alive() and bus._is_shutdown


# ------------------------------------------------------------------ priority
class _FakeOs:
    """An ``os`` stand-in: records what was asked, refuses what it is told to."""

    SCHED_FIFO = 1
    PRIO_PROCESS = 0

    def __init__(self, *, fifo_ok: bool, nice_ok: bool) -> None:
        self.fifo_ok, self.nice_ok = fifo_ok, nice_ok
        self.asked: list[tuple] = []

    @staticmethod
    def sched_param(priority: int) -> tuple:
        return ("param", priority)

    def sched_setscheduler(self, pid: int, policy: int, param: tuple) -> None:
        self.asked.append(("sched", pid, policy, param))
        if not self.fifo_ok:
            raise PermissionError(1, "Operation not permitted")

    def setpriority(self, which: int, who: int, value: int) -> None:
        self.asked.append(("nice", which, who, value))
        if not self.nice_ok:
            raise PermissionError(13, "Permission denied")


@pytest.mark.parametrize(("fifo_ok", "nice_ok", "granted"), [
    (True, True, "SCHED_FIFO 7"),
    (False, True, "nice -5"),
    (False, False, "normal"),
])
def test_raise_priority_falls_back_fifo_then_nice_then_says_why(fifo_ok, nice_ok, granted):
    from plant_sim.interfaces.thread import raise_priority

    fake = _FakeOs(fifo_ok=fifo_ok, nice_ok=nice_ok)
    got = raise_priority(rt_priority=7, nice=-5, os_module=fake)
    assert got.startswith(granted)
    assert fake.asked[0] == ("sched", 0, fake.SCHED_FIFO, ("param", 7))  # the calling thread
    if fifo_ok:
        assert len(fake.asked) == 1  # nothing else touched once real time is granted
    else:
        assert fake.asked[1] == ("nice", fake.PRIO_PROCESS, 0, -5)
    if granted == "normal":
        assert "Operation not permitted" in got and "Permission denied" in got


def test_lower_priority_sets_the_nice_value_or_says_why():
    from plant_sim.interfaces.thread import lower_priority

    ok = _FakeOs(fifo_ok=False, nice_ok=True)
    assert lower_priority(12, os_module=ok) == "nice 12"
    assert ok.asked == [("nice", ok.PRIO_PROCESS, 0, 12)]  # never real time
    refused = lower_priority(12, os_module=_FakeOs(fifo_ok=False, nice_ok=False))
    assert refused.startswith("normal") and "Permission denied" in refused


def test_shared_block_mid_write_is_never_served_nor_waited_for():
    """The server serves its last snapshot while the stepping side writes (no spinning)."""
    from multiprocessing.shared_memory import SharedMemory

    from plant_sim.interfaces.plc_process import _Block

    shm = SharedMemory(create=True, size=_Block.size(3))
    try:
        block = _Block(shm.buf, 3)
        block.publish([1, 2, 3], applied=4)
        seq, applied, words = block.try_read()
        assert (applied, words) == (4, (1, 2, 3)) and seq % 2 == 0
        struct.pack_into("<Q", shm.buf, 0, seq + 1)  # the writer is descheduled mid-write
        assert block.try_read() is None
        struct.pack_into("<Q", shm.buf, 0, seq + 2)
        assert block.read()[0] == seq + 2
    finally:
        block = None
        shm.close()
        shm.unlink()


def test_runner_banner_says_what_priority_the_interfaces_got(plc_process):
    """The priority line names each interface's grant; refused ones are said once."""
    _machine, plc = plc_process
    assert plc.priority is not None and plc.priority.startswith("normal")  # not asked
    lines: list[str] = []
    runner = SimRunner(FakeMachine(), plc=plc, out=lines.append)
    assert runner._priority_line() is None  # nothing asked, nothing said
    plc.realtime = True
    line = runner._priority_line()
    assert line.startswith("modbus normal") and "not permitted to raise it" in line
    plc.priority = "SCHED_FIFO 10"
    assert runner._priority_line() == "modbus SCHED_FIFO 10"


def test_plc_process_realtime_reports_its_grant_and_still_serves():
    machine = FakeMachine()
    plc = PlcProcess(machine, port=0, realtime=True)
    plc.set_up(True)
    try:
        assert plc.priority.startswith(("SCHED_FIFO", "nice", "normal ("))
        with socket.create_connection(("127.0.0.1", plc.port), timeout=30) as sock:
            assert _read_all(sock, 1) == dict(plc.values)
    finally:
        plc.close()


def test_render_workers_run_at_the_nice_value_asked():
    """``RenderPool(nice=...)``: the heavy part runs at the priority it is given, no higher."""
    import os

    from config.sim import default_sim
    from plant_sim.run.render_worker import RenderPool

    base = os.nice(0)
    pool = RenderPool(default_sim(), seed=0, workers=1, nice=min(base + 3, 19))
    pool.start()
    try:
        assert pool._pool.submit(os.nice, 0).result(timeout=60) == min(base + 3, 19)
    finally:
        pool.close()


# ------------------------------------------------------------------ bounded catch-up
class StallMachine(FakeMachine):
    """Steps are free, except that the host stalls ``stall_s`` of (fake) wall time at each of
    ``stall_at`` (machine times): a stepping thread starved by CPU hogs."""

    def __init__(self, clock: FakeClock, stall_at: tuple[float, ...], stall_s: float) -> None:
        super().__init__()
        self.clock = clock
        self.stalls = sorted(stall_at)
        self.stall_s = stall_s

    def advance(self, dt_s: float):
        if self.stalls and self.t_s >= self.stalls[0]:
            self.stalls.pop(0)
            self.clock.now += self.stall_s
        return super().advance(dt_s)

    def register_values(self):
        return {}


@pytest.mark.parametrize("stall_s", [0.3, 0.9])
def test_after_a_stall_the_clock_slows_instead_of_bursting_and_faults_last_on_the_wall(stall_s):
    """A stall shorter than the old one-second catch-up: machine time never runs ahead of
    the wall clock by more than MAX_LAG_S, below the smallest timeout of the interfaces (the
    amplifier's 0.1 s), so a modbus_restart lasts its duration on the wall clock instead of
    being squeezed below the service's timeout."""
    from plant_sim.run import runner as runner_mod

    smallest_timeout_s = 0.1  # the amplifier's setpoint timeout
    assert runner_mod.MAX_LAG_S < smallest_timeout_s
    clock = FakeClock()
    m = StallMachine(clock, stall_at=(0.6, 1.0, 1.4), stall_s=stall_s)
    runner = SimRunner(m, clock=clock, sleep=clock.sleep, out=None, progress_every_s=100.0)
    switched: list[tuple[float, float, bool]] = []
    runner.set_up = lambda up: switched.append((clock(), m.t_s, up))  # the PLC's switch
    runner.schedule(0.5, "modbus_restart", duration_s=1.5)
    marks: list[tuple[float, float]] = []
    sleep = clock.sleep

    async def marking_sleep(dt: float) -> None:
        marks.append((clock(), m.t_s))
        await sleep(dt)

    runner.sleep = marking_sleep
    summary = asyncio.run(runner.run(duration_s=3.0))
    (w_down, t_down, down), (w_up, t_up, up) = switched
    assert (down, up) == (False, True) and t_up - t_down == pytest.approx(1.5, abs=0.002)
    assert w_up - w_down >= 1.5 + 3 * (stall_s - smallest_timeout_s)  # slowed, not squeezed
    for (w0, s0), (w1, s1) in zip(marks, marks[1:], strict=False):  # no burst between sleeps
        assert s1 - s0 <= (w1 - w0) + smallest_timeout_s
    assert summary.slowed_s > 0 and summary.real_time_factor < 1.0


class TruthMachine(FakeMachine):
    """Frames with a truth table, as the real machine's."""

    def advance(self, dt_s: float):
        frames = super().advance(dt_s)
        return [dataclasses.replace(f, truth={"pitch_mm": 1.5}) for f in frames]


def test_runner_stamps_each_pair_with_its_clock_at_capture():
    from plant_sim.run.runner import CLOCK_KEY

    clock = FakeClock()
    m = TruthMachine()
    sink = InProcessSource(maxlen=100)
    runner = SimRunner(m, sink=sink, clock=clock, sleep=clock.sleep, out=None,
                       progress_every_s=100.0, time_scale=2.0)
    assert runner.machine_time_at(clock()) == -np.inf  # no mapping before the run
    wall0 = clock()
    asyncio.run(runner.run(duration_s=1.0))
    frames = [sink.poll() for _ in range(len(sink))]
    assert len(frames) == 10
    stamps = [f.truth[CLOCK_KEY] for f in frames]
    assert stamps == sorted(stamps) and wall0 <= stamps[0] and stamps[-1] <= clock()
    for f, stamp in zip(frames, stamps, strict=True):  # machine time = 2 x wall time from t0
        assert (stamp - wall0) * 2.0 == pytest.approx(f.t_s, abs=0.01)
        assert runner.machine_time_at(stamp) == pytest.approx(f.t_s, abs=0.01)


def test_amp_node_hands_a_frame_over_only_once_the_machine_reached_its_arrival():
    """Stamped on arrival: frames received while the machine ran behind reach it at the
    machine time they arrived, in order (not all at once before a gap)."""
    import can

    m = FakeMachine()
    bus = can_transport.open_bus("virtual", "rt-stamp")
    svc = can_transport.open_bus("virtual", "rt-stamp")
    node = AmpNode(bus, AmpNodeCore(m, knives=4), own_bus=True)
    arrivals = iter([10.000, 10.010, 10.020, 10.030])  # NMT start, then three commands
    node.set_timebase(lambda: next(arrivals), lambda wall: wall - 10.0)
    node.start_receiving()
    try:
        frames = [canopen_frames.start()] + [canopen_frames.command(True, 4, a) for a in (5, 6, 7)]
        for fid, data in frames:
            svc.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
        for _ in range(100_000):  # the thread takes them off the bus (no timing asserted)
            if node._rx.qsize() == 4:
                break
            threading.Event().wait(0.001)
        delivered = []
        for now in (0.005, 0.015, 0.0199, 0.020, 0.5):
            m.t_s = now
            delivered.append(node.receive(now))
        assert delivered == [1, 1, 0, 1, 1]  # the start and the first command, ...
        assert m.alive_counters == [5, 6, 7]
        assert node.take_command_gap() == pytest.approx(0.010)  # the longest gap, once
        assert node.take_command_gap() == 0.0
    finally:
        node.close()
        svc.shutdown()
