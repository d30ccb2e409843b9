"""The simulated PLC serves one register block per head: reads, writes, function 23, refusals."""

from __future__ import annotations

import asyncio
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plant_sim.interfaces.plc_server import PlcServer
from plant_sim.interfaces.register_bus import MachineRegisterBus
from plant_sim.interfaces.register_image import RegisterImage, heads_served
from protocol.register_bus import BusRefused
from protocol.registers import RegisterAccessError, RegisterMap
from tests.support.fake_machine import FakeMachine
from tests.support.head_target import HeadTarget

RMAP = RegisterMap.load()


def _map(read_across: bool) -> RegisterMap:
    """The shipped map with ``[heads] read_across`` set as given."""
    from config.loading import default_path, load_toml

    doc = load_toml(default_path("registers.toml"))
    doc["heads"]["read_across"] = read_across
    return RegisterMap.from_dict(doc)


ONE_BLOCK = _map(False)
"""The map whose reads stay in one block (a PLC that does not read across blocks)."""


def _block(i: int) -> tuple[int, int]:
    return RMAP.head_span(i)


def _decode(i: int, words: list[int]) -> dict[str, float | int]:
    a, _ = _block(i)
    return RMAP.for_head(i).decode_block(words, a)


def run(coro):
    return asyncio.run(coro)


# ------------------------------------------------------------------ which heads are served
def test_heads_served_follow_the_machine():
    assert heads_served(HeadTarget(4), RMAP) == 4
    assert heads_served(HeadTarget(12), RMAP) == RMAP.head_count == 8  # the map's blocks at most
    assert heads_served(FakeMachine(), RMAP) == 0  # no head_register_values: no blocks

    class OneHead(HeadTarget):  # a machine with head_register_values but no head_count
        def __getattribute__(self, name):
            if name == "head_count":
                raise AttributeError(name)
            return super().__getattribute__(name)

    assert heads_served(OneHead(1), RMAP) == 1


# ------------------------------------------------------------------ the in-process bus
@pytest.mark.parametrize("head", range(4))
def test_bus_reads_each_heads_block_under_the_head_names(head):
    target = HeadTarget()
    bus = MachineRegisterBus(target, RMAP)
    run(bus.connect())
    a, n = _block(head)
    got = _decode(head, run(bus.read(a, n)))
    want = target.head_register_values(head)
    assert got == pytest.approx(want)
    assert got["trigger_seq"] == 100 + head and got["knives"] == target.heads[head]["knives"]
    # the single map still gives the first head at the legacy addresses
    first, count = RMAP.common_span()
    single = RMAP.decode_block(run(bus.read(first, count)), first)
    assert single["spindle_rpm"] == 6000.0 and single["knives"] == 4


@pytest.mark.parametrize("regmap", [RMAP, ONE_BLOCK], ids=["read_across", "one_block"])
def test_bus_refuses_blocks_beyond_the_machine_and_reads_across_ranges(regmap):
    bus = MachineRegisterBus(HeadTarget(2), regmap)
    run(bus.connect())
    for address, count in [(_block(2)[0], 4), (_block(7)[0], 1), (36, 966), (1020, 45),
                           (1000 + 63, 2)]:
        with pytest.raises(BusRefused) as err:
            run(bus.read(address, count))
        assert err.value.code == 2, (address, count)
    used = RMAP.heads.used
    assert run(bus.read(1000 + used, 32 - used)) == [0] * (32 - used)  # reserved words read 0
    if not regmap.heads.read_across:  # from one block into the next: refused
        for address, count in [(1000 + 31, 2), (1020, 20), (1000, 32 + used)]:
            with pytest.raises(BusRefused) as err:
                run(bus.read(address, count))
            assert err.value.code == 2, (address, count)
        return
    # across the served blocks: block 0 (its reserved words 0), then block 1's
    both = run(bus.read(1000, 32 + used))
    assert both[:32] == run(bus.read(1000, 32)) and both[32:] == run(bus.read(1032, used))
    assert both[used:32] == [0] * (32 - used)
    assert _decode(1, both[32:]) == pytest.approx(HeadTarget(2).head_register_values(1))


def test_bus_routes_a_spindle_setpoint_write_to_its_head_and_refuses_out_of_range():
    target = HeadTarget()
    bus = MachineRegisterBus(target, RMAP)
    run(bus.connect())
    view = RMAP.for_head(3)
    reg = view["spindle_setpoint_rpm"]
    run(bus.write(reg.address, view.encode(reg.name, 7200.0)))
    assert target.setpoints == [(3, 7200.0)]
    for bad in (3999.0, 8000.5):  # head 3's own limits 4000..8000
        with pytest.raises(BusRefused) as err:
            run(bus.write(reg.address, view.encode(reg.name, bad)))
        assert err.value.code == 3
    fixed = RMAP.for_head(1)["spindle_setpoint_rpm"]  # head 1: 9000 rpm fixed
    with pytest.raises(BusRefused) as err:
        run(bus.write(fixed.address, view.encode(reg.name, 7200.0)))
    assert err.value.code == 3
    for address, words in [(view["knives"].address, [3]), (reg.address, [0x45E1]),
                           (1000 + 31, [1])]:  # read-only, half a float, reserved
        with pytest.raises(BusRefused) as err:
            run(bus.write(address, words))
        assert err.value.code == 2
    assert target.setpoints == [(3, 7200.0)]


def test_bus_function_23_writes_then_reads_the_block():
    target = HeadTarget()
    bus = MachineRegisterBus(target, RMAP)
    run(bus.connect())
    view = RMAP.for_head(3)
    reg = view["spindle_setpoint_rpm"]
    a, n = _block(3)
    words = run(bus.read_write(a, n, reg.address, view.encode(reg.name, 5000.0)))
    assert _decode(3, words)["spindle_setpoint_rpm"] == 5000.0  # the write came first
    run(bus.read_write(a, n, 0, [42]))
    assert target.heartbeat_service == 42


def test_a_real_single_head_machine_serves_block_zero_only():
    from config.sim import default_sim
    from plant_sim.machine.machine import Machine

    machine = Machine(default_sim(), seed=1, render_images=False)
    bus = MachineRegisterBus(machine, RMAP)
    assert bus.heads == 1
    run(bus.connect())
    a, n = _block(0)
    block = _decode(0, run(bus.read(a, n)))
    single = RMAP.decode_block(run(bus.read(*RMAP.common_span())), 0)
    for name in ("knives", "cutter_to_camera_mm", "cutterhead_radius_mm", "trigger_seq"):
        assert block[name] == single[name], name
    with pytest.raises(BusRefused) as err:
        run(bus.read(*_block(1)))
    assert err.value.code == 2


# ------------------------------------------------------------------ the Modbus server (sans-I/O)
def _fc23(r_start: int, r_qty: int, w_start: int, words: list[int]) -> bytes:
    return struct.pack(">BHHHHB", 23, r_start, r_qty, w_start, len(words), 2 * len(words)) + \
        struct.pack(f">{len(words)}H", *words)


def test_server_answers_function_23_on_a_head_block():
    target = HeadTarget()
    server = PlcServer(target, port=0)
    assert server.heads == 4
    a, n = _block(2)
    reply = server.respond(1, _fc23(a, n, 0, [9]))
    assert reply[0] == 23 and reply[1] == 2 * n
    words = list(struct.unpack(f">{n}H", reply[2:]))
    assert _decode(2, words) == pytest.approx(target.head_register_values(2))
    assert target.heartbeat_service == 9
    # a block beyond the machine's heads: exception 02; a setpoint out of range: 03
    assert server.respond(1, _fc23(_block(4)[0], 4, 0, [10])) == bytes([23 | 0x80, 2])
    view = RMAP.for_head(0)
    reg = view["spindle_setpoint_rpm"]
    bad = _fc23(a, n, reg.address, view.encode(reg.name, 6100.0))  # head 0 fixed at 6000
    assert server.respond(1, bad) == bytes([23 | 0x80, 3])
    assert target.setpoints == []


def test_queued_head_writes_are_served_at_once_and_applied_in_order():
    target = HeadTarget()
    server = PlcServer(target, port=0, queue_writes=True)
    queued = []
    server.on_queued = queued.append
    view = RMAP.for_head(3)
    reg = view["spindle_setpoint_rpm"]
    for rpm in (4500.0, 7500.0):
        w = view.encode(reg.name, rpm)
        pdu = struct.pack(">BHHB", 16, reg.address, 2, 4) + struct.pack(">2H", *w)
        assert server.respond(1, pdu)[0] == 16
    assert queued == [(3, {reg.name: 4500.0}), (3, {reg.name: 7500.0})]
    server.refresh()  # the machine has not applied them yet: the written value is served
    assert server.head_values(3)[reg.name] == 7500.0 and target.setpoints == []
    assert server.apply_writes() == 2
    assert target.setpoints == [(3, 4500.0), (3, 7500.0)]


def test_image_refuses_head_values_that_are_no_block_register():
    image = RegisterImage(RMAP, 1)
    with pytest.raises(ValueError, match="'feed_actual_mm_s' is no register of the head block"):
        image.load({}, [{"feed_actual_mm_s": 1.0}])
    with pytest.raises(RegisterAccessError):
        image.read(1032, 2)  # block 1 is not served


def test_plc_process_serves_head_blocks_and_sends_head_writes_back():
    """The server in its own process: blocks through shared memory, writes over the pipe."""
    from controller.fieldbus.plc_client import PlcClient
    from plant_sim.interfaces.plc_process import PlcProcess

    target = HeadTarget()

    async def main():
        proc = PlcProcess(target, port=0)
        try:
            host, port = await proc.start()
            client = PlcClient.tcp(host, port, timeout_s=5.0, head=3)
            snap = await client.read()
            assert snap.knives == 6 and snap.trigger_seq == 103
            assert snap.spindle_rpm == 6003.0 and snap["spindle_rpm_max"] == 8000.0
            await client.write_spindle_setpoint(7000.0)
            for _ in range(1000):  # the write crosses a pipe; bounded polling, no clock
                if proc.apply_writes():
                    break
                await asyncio.sleep(0.005)
            assert target.setpoints == [(3, 7000.0)]
            client.close()
        finally:
            await proc.stop()
            proc.close()

    run(main())


def test_the_image_finds_the_block_layout_once_not_per_cycle(monkeypatch):
    """load / read / store / load_flat of every cycle use the layout found at construction."""
    from protocol.registers import HeadBlock

    target = HeadTarget()
    image = RegisterImage(RMAP, target.head_count)
    values = target.register_values()
    heads = [target.head_register_values(i) for i in range(target.head_count)]
    calls = {"names": 0, "head_span": 0, "used": 0}
    for prop in ("names", "used"):
        real = HeadBlock.__dict__[prop]
        get = getattr(real, "fget", None) or real.func  # a property or a cached_property
        monkeypatch.setattr(HeadBlock, prop, property(
            lambda self, get=get, prop=prop: calls.__setitem__(prop, calls[prop] + 1)
            or get(self)))
    real_span = RegisterMap.head_span
    monkeypatch.setattr(RegisterMap, "head_span", lambda self, i=None: calls.__setitem__(
        "head_span", calls["head_span"] + 1) or real_span(self, i))
    for _ in range(5):  # five PLC cycles
        image.load(values, heads)
        image.read(RMAP.heads.base + RMAP.heads.stride * 2, 4)
        image.store(image.parse_write(*_setpoint_words(3, 7000.0)))
        image.load_flat(image.flat())
    assert calls == {"names": 0, "head_span": 0, "used": 0}
    # and what it serves is what the map encodes
    assert image.head_values[3]["spindle_setpoint_rpm"] == 7000.0
    a, _ = _block(3)
    assert _decode(3, image.read(a, RMAP.heads.used)) == {
        k: v for k, v in image.head_values[3].items()}


def _setpoint_words(head: int, rpm: float) -> tuple[int, list[int]]:
    view = RMAP.for_head(head)
    return view["spindle_setpoint_rpm"].address, view.encode("spindle_setpoint_rpm", rpm)


def test_the_plc_process_builds_its_server_on_one_read_of_the_published_block():
    from multiprocessing.shared_memory import SharedMemory

    from plant_sim.interfaces.plc_process import _Block, _snapshot_server

    target = HeadTarget()
    image = RegisterImage(RMAP, target.head_count)
    image.load(target.register_values(),
               [target.head_register_values(i) for i in range(target.head_count)])
    shm = SharedMemory(create=True, size=_Block.size(image.size))
    try:
        block = _Block(shm.buf, image.size)
        block.publish(image.flat(), applied=0)
        reads = []
        real = block.read
        block.read = lambda: reads.append(1) or real()  # type: ignore[method-assign]
        served = RegisterImage(RMAP, target.head_count)
        server, seq = _snapshot_server(block, served, RMAP, target.head_count, "127.0.0.1", 0, 1)
        assert len(reads) == 1 and seq == block.seq()
        assert dict(server.values) == image.values
        assert [dict(server.head_values(i)) for i in range(4)] == image.head_values
    finally:
        shm.close()
        shm.unlink()


# ------------------------------------------------------------------ any read, any write (property)
_END = RMAP.heads.base + RMAP.heads.stride * RMAP.heads.count + 4


@settings(max_examples=150, deadline=None)
@given(
    start=st.one_of(st.integers(0, 60), st.integers(990, _END), st.integers(0, 0xFFFF)),
    qty=st.integers(1, 125),
    heads=st.integers(1, 4),
    across=st.booleans(),
)
def test_any_read_is_served_from_exactly_one_range_or_refused_with_02(start, qty, heads,
                                                                     across):
    regmap = RMAP if across else ONE_BLOCK
    target = HeadTarget(heads)
    server = PlcServer(target, register_map=regmap, port=0)
    reply = server.respond(1, struct.pack(">BHH", 3, start, qty))
    first, count = RMAP.common_span()
    in_common = first <= start and start + qty <= first + count
    block = RMAP.heads.head_at(start)
    last = RMAP.heads.head_at(start + qty - 1)
    in_blocks = (block is not None and last is not None and last < heads
                 and (last == block or across))
    if not (in_common or in_blocks):
        assert reply == bytes([0x83, 2])
        return
    words = list(struct.unpack(f">{qty}H", reply[2:]))
    assert reply[:2] == bytes([3, 2 * qty])
    if in_common:
        expect = RMAP.encode_block(target.register_values())[start - first : start - first + qty]
    else:
        blocks: list[int] = []  # every served block's stride of words, from block 0 on
        for i in range(heads):
            view = RMAP.for_head(i)  # its span starts at 0: list index == address
            full = view.encode_block(target.head_register_values(i))[RMAP.heads.address(i):]
            blocks += full + [0] * (RMAP.heads.stride - len(full))  # the reserved words
        off = start - RMAP.heads.base
        expect = blocks[off : off + qty]
    assert words == expect


@settings(max_examples=100, deadline=None)
@given(head=st.integers(0, 3), rpm=st.floats(3000.0, 10000.0, width=32))
def test_a_head_setpoint_write_is_applied_iff_within_that_heads_limits(head, rpm):
    target = HeadTarget()
    server = PlcServer(target, port=0)
    view = RMAP.for_head(head)
    reg = view["spindle_setpoint_rpm"]
    w = view.encode(reg.name, rpm)
    reply = server.respond(1, struct.pack(">BHHB2H", 16, reg.address, 2, 4, *w))
    h = target.heads[head]
    if h["spindle_rpm_min"] <= rpm <= h["spindle_rpm_max"]:
        assert reply[0] == 16 and target.setpoints == [(head, rpm)]
    else:
        assert reply == bytes([0x90, 3]) and target.setpoints == []
