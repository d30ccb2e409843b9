"""PLC client: sans-I/O protocol, back-off, error mapping, and the real Modbus server."""

from __future__ import annotations

import asyncio
import math

import pytest

from controller.fieldbus.plc_client import PlcClient
from controller.fieldbus.plc_protocol import Backoff, PlcProtocol
from core.errors import FieldbusError, ModbusRefused
from plant_sim.interfaces.register_bus import MachineRegisterBus
from protocol.register_bus import BusRefused
from protocol.registers import MachineState, PlcFault, RegisterMap
from tests.support.fake_machine import FakeMachine as FakeMachineBase

RMAP = RegisterMap.load()


class FakeMachine(FakeMachineBase):
    """The shared stand-in with the PLC side these tests were written for."""

    def __init__(self) -> None:
        super().__init__(feed_setpoint=300.0, cutter_to_camera_mm=350.0, machine_state=0b11011,
                         board_position_mm=812.5, feed_accel_max_mm_s2=0.0, watchdog_ms=0,
                         cutterhead_radius_mm=0.0)


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


# ---------------------------------------------------------------------------------- pure parts
@pytest.mark.parametrize("initial,cap", [(0.05, 2.0), (0.1, 0.4), (1.0, 1.0)])
def test_backoff_doubles_and_caps(initial, cap):
    b = Backoff(initial, cap)
    assert b.may_attempt(0.0)
    delays = []
    t = 0.0
    for _ in range(10):
        nxt = b.failed(t)
        delays.append(nxt - t)
        assert not b.may_attempt(t + delays[-1] * 0.99)
        assert b.may_attempt(nxt)
        t = nxt
    for i, d in enumerate(delays):
        assert d == pytest.approx(min(cap, initial * 2**i))
    assert max(delays) <= cap
    b.succeeded()
    assert b.may_attempt(t) and b.failed(t) - t == pytest.approx(initial)


@pytest.mark.parametrize("initial,cap", [(0.0, 1.0), (1.0, 0.5), (-1, 2)])
def test_backoff_rejects_bad_values(initial, cap):
    with pytest.raises(ValueError):
        Backoff(initial, cap)


def test_protocol_reads_whole_span_and_round_trips_feed():
    p = PlcProtocol(RMAP)
    first, count = RMAP.span()
    assert (p.read_address, p.read_count) == (first, count)
    m = FakeMachine()
    words = RMAP.encode_block(m.register_values())
    vals = p.decode_read(words)
    assert set(vals) == {r.name for r in RMAP}
    assert vals["encoder_counts"] == 4_000_000_000
    addr, ws = p.feed_request(412.25, vals)
    assert addr == RMAP["feed_setpoint_mm_s"].address and len(ws) == 2
    assert RMAP.decode("feed_setpoint_mm_s", ws) == 412.25
    with pytest.raises(ValueError, match="feed_setpoint_mm_s"):
        p.feed_request(5000.0, vals)  # outside [feed_min, feed_max] of the snapshot
    addr, ws = p.heartbeat_request(65537)
    assert addr == RMAP["heartbeat_service"].address and ws == [1]
    with pytest.raises(FieldbusError):
        p.decode_read(words[:-1])


# ---------------------------------------------------------------------------------- client/fakes
class FlakyBus:
    """A RegisterBus that can be down, refuse, and counts connection attempts."""

    def __init__(self, machine: FakeMachine) -> None:
        self.inner = MachineRegisterBus(machine, RMAP)
        self.connects = 0
        self.refuse_code: int | None = None

    @property
    def connected(self) -> bool:
        return self.inner.connected

    async def connect(self) -> None:
        self.connects += 1
        await self.inner.connect()

    async def read(self, address, count):
        if self.refuse_code is not None:
            raise BusRefused(self.refuse_code)
        return await self.inner.read(address, count)

    async def write(self, address, words):
        if self.refuse_code is not None:
            raise BusRefused(self.refuse_code)
        await self.inner.write(address, words)

    def close(self) -> None:
        self.inner.close()


def test_client_reads_and_writes_through_in_process_bus():
    async def main():
        m = FakeMachine()
        clock = Clock()
        c = PlcClient(MachineRegisterBus(m, RMAP), RMAP, clock=clock)
        snap = await c.read()
        assert snap.spindle_rpm == 6000.0 and snap.knives == 4
        assert snap.board_present and not snap.estop and snap.spindle_running
        assert snap.index_latch_counts == 123_456
        await c.write_feed(512.5)
        await c.write_heartbeat(70_000)
        assert m.feed_setpoint == 512.5 and m.heartbeat_service == 70_000 % 65536
        assert c.last_ok_s == clock.t

    asyncio.run(main())


def test_refusals_name_the_register():
    async def main():
        m = FakeMachine()
        bus = MachineRegisterBus(m, RMAP)
        c = PlcClient(bus, RMAP, clock=Clock())
        await c.read()
        # the map refuses a write to a read-only register with exception 02
        with pytest.raises(ModbusRefused, match=r"spindle_rpm.*02 ILLEGAL DATA ADDRESS"):
            await c._do(
                "writing",
                RMAP["spindle_rpm"].address,
                2,
                lambda: bus.write(RMAP["spindle_rpm"].address, RMAP.encode("spindle_rpm", 1.0)),
            )
        # the machine refuses a value; the client checks limits first (ValueError, no request)
        before = bus.requests
        with pytest.raises(ValueError, match="feed_setpoint_mm_s"):
            await c.write_feed(1e4)
        assert bus.requests == before
        c.last = None  # without known limits the PLC itself refuses: exception 03
        with pytest.raises(ModbusRefused, match=r"feed_setpoint_mm_s.*03 ILLEGAL DATA VALUE"):
            await c.write_feed(1e4)
        assert c.connected  # a refusal keeps the connection

    asyncio.run(main())


@pytest.mark.parametrize("state", range(0, 32, 3))
def test_snapshot_flags_are_the_register_maps_bits(state):
    async def main():
        m = FakeMachine()
        m.values.update(machine_state=state, faults=31 - state)
        snap = await PlcClient(MachineRegisterBus(m, RMAP), RMAP, clock=Clock()).read()
        assert snap.machine_state == MachineState(state) and snap.faults == PlcFault(31 - state)
        assert snap.board_present == bool(state & 0b10)
        assert snap.estop == bool(state & 0b100)
        assert snap.spindle_running == bool(state & 0b1000)

    asyncio.run(main())


def test_a_value_the_machine_refuses_inside_the_map_limits_is_exception_03():
    class Picky(FakeMachine):
        def set_feed_setpoint(self, feed_mm_s: float) -> None:
            raise ValueError("the drive is busy")

    async def main():
        m = Picky()
        c = PlcClient(MachineRegisterBus(m, RMAP), RMAP, clock=Clock())
        await c.read()
        with pytest.raises(ModbusRefused, match=r"feed_setpoint_mm_s.*03 ILLEGAL DATA VALUE"):
            await c.write_feed(500.0)
        assert m.feed_setpoint == 300.0

    asyncio.run(main())


def test_connection_loss_arms_backoff_then_reconnects():
    async def main():
        m = FakeMachine()
        bus = FlakyBus(m)
        clock = Clock()
        c = PlcClient(bus, RMAP, backoff=Backoff(0.1, 0.4), clock=clock)
        await c.read()
        assert bus.connects == 1
        bus.inner.down = True
        with pytest.raises(FieldbusError):
            await c.read()  # connection lost
        # during the back-off no connection attempt is made
        attempts = bus.connects
        for dt in (0.0, 0.05, 0.09):
            clock.t = 1e-9 + dt
            with pytest.raises(FieldbusError, match="next reconnect"):
                await c.read()
        assert bus.connects == attempts
        # attempts after that fail (still down) and the wait doubles up to the cap
        waits = []
        t = c.backoff.next_attempt_s
        for _ in range(5):
            clock.t = t
            with pytest.raises(FieldbusError):
                await c.read()
            waits.append(c.backoff.next_attempt_s - t)
            t = c.backoff.next_attempt_s
        assert waits == pytest.approx([0.2, 0.4, 0.4, 0.4, 0.4])
        bus.inner.down = False
        clock.t = t
        snap = await c.read()
        assert snap.knives == 4 and c.backoff.failures == 0
        assert bus.connects == attempts + 6, (attempts, bus.connects)

    asyncio.run(main())


# ---------------------------------------------------------------------------------- real server
def _server_cls():
    from plant_sim.interfaces.plc_server import PlcServer

    return PlcServer


def test_against_real_modbus_server_with_restart():
    PlcServer = _server_cls()

    async def main():
        m = FakeMachine()
        server = PlcServer(m, port=0)
        host, port = await server.start()
        try:
            c = PlcClient.tcp(host, port, timeout_s=0.5, backoff=Backoff(0.01, 0.05))
            snap = await c.read()
            assert snap.values["encoder_counts"] == 4_000_000_000
            assert math.isclose(snap["board_position_mm"], 812.5)
            await c.write_feed(444.5)
            await c.write_heartbeat(7)
            assert m.feed_setpoint == 444.5 and m.heartbeat_service == 7
            c.last = None
            with pytest.raises(ModbusRefused, match="feed_setpoint_mm_s"):
                await c.write_feed(2000.0)
            assert c.connected
            # the server goes away: the next request fails as FieldbusError, not a hang
            await server.stop()
            with pytest.raises(FieldbusError):
                await c.read()
                await c.read()
            await server.start()
            deadline = asyncio.get_running_loop().time() + 30.0  # a backstop, not a timing
            while True:  # the back-off is short: a few attempts reconnect
                try:
                    await c.read()
                    break
                except FieldbusError:
                    assert asyncio.get_running_loop().time() < deadline, "never reconnected"
                    await asyncio.sleep(0.01)
            server.refresh()
            assert c.connected and c.reconnects >= 2
            await c.write_feed(333.0)
            assert m.feed_setpoint == 333.0
            c.close()
        finally:
            await server.stop()

    asyncio.run(main())


def test_requests_from_two_tasks_never_overlap_on_the_bus():
    """One owner per bus: the PLC task and the pair task share one client, one request at a time.

    The bus yields to the event loop inside every request (as a socket would); a second request
    started meanwhile must wait, and a reconnect is attempted once, not by both.
    """

    class SlowBus(FlakyBus):
        def __init__(self, machine):
            super().__init__(machine)
            self.busy = 0
            self.overlaps = 0
            self.order = []

        async def _enter(self, what):
            self.busy += 1
            self.overlaps += self.busy > 1
            self.order.append(what)
            for _ in range(3):
                await asyncio.sleep(0)

        async def connect(self):
            await self._enter("connect")
            self.busy -= 1
            await super().connect()

        async def read(self, address, count):
            await self._enter("read")
            try:
                return await super().read(address, count)
            finally:
                self.busy -= 1

        async def write(self, address, words):
            await self._enter("write")
            try:
                await super().write(address, words)
            finally:
                self.busy -= 1

    async def main():
        m = FakeMachine()
        bus = SlowBus(m)
        c = PlcClient(bus, RMAP, clock=Clock())
        await asyncio.gather(c.read(), c.write_heartbeat(5), c.read(), c.write_feed(400.0))
        assert bus.overlaps == 0
        assert bus.order.count("connect") == 1 and len(bus.order) == 5
        assert m.feed_setpoint == 400.0 and m.heartbeat_service == 5

    asyncio.run(main())
