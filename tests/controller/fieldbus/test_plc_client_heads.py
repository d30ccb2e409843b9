"""The PLC client over a head's view of the map: one function 23 per block, head writes."""

from __future__ import annotations

import asyncio

import pytest

from config.loading import default_path
from controller.fieldbus.plc_client import PlcClient
from controller.fieldbus.plc_protocol import Backoff
from core.errors import ModbusRefused
from plant_sim.interfaces.plc_server import PlcServer
from plant_sim.interfaces.register_bus import MachineRegisterBus
from protocol.registers import HeadFault, RegisterMap
from tests.support.head_target import HeadTarget

RMAP = RegisterMap.load()


class Clock:
    t = 0.0

    def __call__(self) -> float:
        return self.t


def _recording(server: PlcServer) -> list[int]:
    """The function code of every request the server answers."""
    seen: list[int] = []
    respond = server.respond

    def wrapped(unit: int, pdu: bytes) -> bytes:
        seen.append(pdu[0])
        return respond(unit, pdu)

    server.respond = wrapped  # type: ignore[method-assign]
    return seen


async def _serve(target, rmap=RMAP):
    server = PlcServer(target, register_map=rmap, port=0)
    host, port = await server.start()
    return server, host, port


def test_a_head_client_reads_common_then_its_block_in_one_function_23():
    async def main():
        target = HeadTarget()
        server, host, port = await _serve(target)
        seen = _recording(server)
        try:
            c = PlcClient.tcp(host, port, timeout_s=2.0, head=3, backoff=Backoff(0.01, 0.05))
            snap = await c.read()
            assert seen == [3, 23]  # the common span, then the whole block in one transaction
            assert snap.knives == 6 and snap.spindle_rpm == 6003.0 and snap.trigger_seq == 103
            assert snap.cutter_to_camera_mm == 360.0 and snap.index_latch_counts == 0xFFFF_0003
            assert snap["spindle_rpm_min"] == 4000.0 and snap["spindle_rpm_max"] == 8000.0
            assert snap.feed_max_mm_s == 1000.0 and snap["encoder_counts"] == 123_456_789
            assert snap.problem() is None
            # the function 23 wrote the heartbeat back unchanged (the value just read: 0)
            assert target.heartbeat_service == 0
            await c.write_heartbeat(7)
            target.heartbeat_service = 8  # another writer meanwhile
            server.refresh()
            await c.read()
            assert target.heartbeat_service == 7  # this client's last heartbeat, no new value
            c.close()
        finally:
            await server.stop()

    asyncio.run(main())


def test_read_head_reads_any_head_and_keeps_last_for_its_own():
    async def main():
        target = HeadTarget()
        server, host, port = await _serve(target)
        try:
            c = PlcClient.tcp(host, port, timeout_s=2.0, head=3)
            own = await c.read()
            other = await c.read_head(2)
            assert other.trigger_seq == 102 and other.knives == 2
            assert HeadFault(int(other["head_faults"])) == HeadFault.CAMERA_SILENT
            assert c.last is own
            again = await c.read_head(3)
            assert c.last is again and again.trigger_seq == 103
            with pytest.raises(ValueError, match="head 8"):
                await c.read_head(8)
            with pytest.raises(ModbusRefused, match="exception 02"):  # the PLC has 4 heads
                await c.read_head(4)
            c.close()
        finally:
            await server.stop()

    asyncio.run(main())


def test_spindle_setpoint_goes_to_the_heads_block_and_out_of_range_is_refused():
    async def main():
        target = HeadTarget()
        server, host, port = await _serve(target)
        try:
            c = PlcClient.tcp(host, port, timeout_s=2.0, head=3)
            await c.read()
            await c.write_spindle_setpoint(7250.0)
            assert target.setpoints == [(3, 7250.0)]
            n = server.requests
            with pytest.raises(ValueError, match="spindle_setpoint_rpm"):
                await c.write_spindle_setpoint(8500.0)  # refused before the wire
            assert server.requests == n
            c.last = None  # no limits known: the PLC refuses it
            with pytest.raises(ModbusRefused, match="spindle_setpoint_rpm: exception 03"):
                await c.write_spindle_setpoint(3000.0)
            fixed = PlcClient.tcp(host, port, timeout_s=2.0, head=1)
            with pytest.raises(ModbusRefused, match="exception 03"):
                await fixed.write_spindle_setpoint(8000.0)  # head 1 runs 9000 rpm fixed
            await fixed.write_spindle_setpoint(9000.0)
            assert target.setpoints == [(3, 7250.0), (1, 9000.0)]
            single = PlcClient.tcp(host, port, timeout_s=2.0)
            with pytest.raises(ValueError, match="no head's view"):
                await single.write_spindle_setpoint(6000.0)
            for client in (c, fixed, single):
                client.close()
        finally:
            await server.stop()

    asyncio.run(main())


def test_function_3_where_the_map_offers_no_23(tmp_path):
    text = default_path("registers.toml").read_text()
    old = "function_codes = [3, 6, 16, 23]"
    assert old in text
    path = tmp_path / "registers.toml"
    path.write_text(text.replace(old, "function_codes = [3, 6, 16]"))
    rmap = RegisterMap.load(path)

    async def main():
        target = HeadTarget()
        server, host, port = await _serve(target, rmap)
        seen = _recording(server)
        try:
            c = PlcClient.tcp(host, port, timeout_s=2.0, regmap=rmap, head=2)
            snap = await c.read()
            assert seen == [3, 3] and snap.trigger_seq == 102
            c.close()
        finally:
            await server.stop()
        assert server.respond(1, bytes([23]) + bytes(9)) == bytes([23 | 0x80, 1])

    asyncio.run(main())


def test_in_process_bus_and_a_bus_without_function_23():
    class ReadOnlyBus:  # a RegisterBus without read_write: the client falls back to function 3
        def __init__(self, inner):
            self.inner = inner
            self.calls = []

        @property
        def connected(self):
            return self.inner.connected

        async def connect(self):
            await self.inner.connect()

        async def read(self, address, count):
            self.calls.append(("read", address, count))
            return await self.inner.read(address, count)

        async def write(self, address, words):
            await self.inner.write(address, words)

        def close(self):
            self.inner.close()

    async def main():
        target = HeadTarget()
        view = RMAP.for_head(1)
        direct = PlcClient(MachineRegisterBus(target, view), view, clock=Clock())
        snap = await direct.read()
        assert snap.knives == 2 and snap.trigger_seq == 101 and snap.problem() is None
        bus = ReadOnlyBus(MachineRegisterBus(target, RMAP))
        fallback = PlcClient(bus, view, clock=Clock())
        assert (await fallback.read()).values == snap.values
        assert bus.calls == [("read", 0, 38), ("read", *RMAP.head_span(1))]

    asyncio.run(main())


def test_the_single_head_machine_through_head_zero():
    from config.sim import default_sim
    from plant_sim.machine.machine import Machine

    async def main():
        machine = Machine(default_sim(), seed=3, render_images=False)
        machine.advance(0.05)
        view = RMAP.for_head(0)
        head = await PlcClient(MachineRegisterBus(machine, RMAP), view, clock=Clock()).read()
        single = await PlcClient(MachineRegisterBus(machine, RMAP), RMAP, clock=Clock()).read()
        for name in ("knives", "spindle_rpm", "cutter_to_camera_mm", "cutterhead_radius_mm",
                     "trigger_seq", "index_latch_counts", "counts_per_mm", "feed_max_mm_s"):
            assert head[name] == single[name], name
        assert head["spindle_rpm_min"] <= head["spindle_setpoint_rpm"] <= head["spindle_rpm_max"]

    asyncio.run(main())


def test_offered_common_words_spare_the_heads_read_of_them_once():
    """A moulder's coordinator reads the common span once and offers it to every head."""
    async def main():
        target = HeadTarget()
        server, host, port = await _serve(target)
        seen = _recording(server)
        try:
            common = PlcClient.tcp(host, port, timeout_s=2.0)
            head = PlcClient.tcp(host, port, timeout_s=2.0, head=3)
            own = await head.read()  # what the head reads by itself
            seen.clear()
            await common.read()
            assert seen == [3] and len(common.last_common) == common.protocol.read_count
            head.offer_common(common.last_common)
            shared = await head.read()
            assert seen == [3, 23]  # the coordinator's read, then only the head's block
            assert shared.values == own.values
            assert head.last_common == common.last_common
            seen.clear()
            target.feed_setpoint = 321.0
            server.refresh()
            again = await head.read()  # the offer was used once: the PLC's words again
            assert seen == [3, 23] and again.feed_setpoint_mm_s == pytest.approx(321.0)
            head.offer_common(common.last_common)
            head.offer_common(None)  # withdrawn before a read took it
            seen.clear()
            await head.read()
            assert seen == [3, 23]
            with pytest.raises(ValueError, match="common span"):
                head.offer_common([0] * 3)
            common.close()
            head.close()
        finally:
            await server.stop()

    asyncio.run(main())


def _one_block_map() -> RegisterMap:
    """The shipped map whose PLC reads no further than one block (no ``read_across``)."""
    from config.loading import load_toml

    doc = load_toml(default_path("registers.toml"))
    doc["heads"]["read_across"] = False
    return RegisterMap.from_dict(doc)


def test_blocks_reads_group_consecutive_heads_where_the_map_reads_across():
    from controller.fieldbus.plc_protocol import MAX_READ_WORDS, PlcProtocol

    assert RMAP.heads.read_across
    p = PlcProtocol(RMAP)
    base, stride, used = RMAP.heads.base, RMAP.heads.stride, RMAP.heads.used
    assert p.blocks_reads([0, 1, 2, 3]) == ((base, 3 * stride + used, (0, 1, 2, 3)),)
    assert p.blocks_reads([3, 1, 0, 1]) == ((base, stride + used, (0, 1)),
                                            (base + 3 * stride, used, (3,)))
    eight = p.blocks_reads(range(8))  # 8 blocks do not fit one read of 125 words
    assert [r[2] for r in eight] == [(0, 1, 2, 3), (4, 5, 6, 7)]
    assert all(n <= MAX_READ_WORDS for _, n, _ in eight)
    single = PlcProtocol(_one_block_map())
    assert single.blocks_reads([0, 1]) == ((base, used, (0,)), (base + stride, used, (1,)))
    with pytest.raises(ValueError, match="head"):
        p.blocks_reads([8])
    words = list(range(stride + used))
    got = p.split_blocks((base, stride + used, (0, 1)), words)
    assert got == {0: words[:used], 1: words[stride:]}
    from core.errors import FieldbusError

    with pytest.raises(FieldbusError, match="expected"):
        p.split_blocks((base, stride + used, (0, 1)), words[:-1])


@pytest.mark.parametrize("across", [True, False])
def test_offered_blocks_spare_the_heads_every_request(across):
    """The coordinator reads every head's block (one request where the map reads across) and
    offers each head its block with the common span: the head then asks the PLC nothing, and
    decodes what it would have read itself."""
    rmap = RMAP if across else _one_block_map()

    async def main():
        target = HeadTarget(4)
        server, host, port = await _serve(target, rmap)
        seen = _recording(server)
        try:
            common = PlcClient.tcp(host, port, timeout_s=2.0, regmap=rmap)
            heads = [PlcClient.tcp(host, port, timeout_s=2.0, regmap=rmap, head=i)
                     for i in range(4)]
            own = [(await h.read()).values for h in heads]
            seen.clear()
            await common.read()
            blocks = await common.read_blocks([0, 1, 2, 3])
            assert seen == ([3, 3] if across else [3, 3, 3, 3, 3])
            seen.clear()
            for i, h in enumerate(heads):
                h.offer_common(common.last_common)
                h.offer_block(blocks[i])
                assert (await h.read()).values == own[i]
            assert seen == []  # nothing asked of the PLC
            heads[2].offer_block(blocks[2])  # a block without the common span: not used
            await heads[2].read()
            assert seen == [3, 23]
            seen.clear()
            heads[1].offer_common(common.last_common)
            heads[1].offer_block(blocks[1])
            heads[1].offer_block(None)  # withdrawn: its own block read
            await heads[1].read()
            assert seen == [23]
            with pytest.raises(ValueError, match="block's"):
                heads[0].offer_block([0] * 3)
            with pytest.raises(ValueError, match="no head's view"):
                common.offer_block(blocks[0])
            for c in (common, *heads):
                c.close()
        finally:
            await server.stop()

    asyncio.run(main())


def test_beat_and_read_is_one_function_23_writing_before_it_reads():
    async def main():
        target = HeadTarget()
        server, host, port = await _serve(target)
        seen = _recording(server)
        try:
            c = PlcClient.tcp(host, port, timeout_s=2.0)
            snap = await c.beat_and_read(70000)  # wrapped to 16 bits
            assert seen == [23]
            assert target.heartbeat_service == 70000 & 0xFFFF
            assert snap["heartbeat_service"] == 70000 & 0xFFFF  # the write came first
            assert c.last is snap
            words = list(c.last_common)
            assert (await c.read()).values == snap.values and c.last_common == words
            head = PlcClient.tcp(host, port, timeout_s=2.0, head=1)
            seen.clear()
            await head.beat_and_read(5)  # a head's view: its heartbeat write, then its read
            assert seen == [6, 3, 23] and target.heartbeat_service == 5
            c.close()
            head.close()
        finally:
            await server.stop()

    asyncio.run(main())


def test_beat_and_read_without_function_23_is_the_two_requests():
    from config.loading import load_toml

    doc = load_toml(default_path("registers.toml"))
    doc["map"]["function_codes"] = [3, 6, 16]
    rmap = RegisterMap.from_dict(doc)

    async def main():
        target = HeadTarget()
        server, host, port = await _serve(target, rmap)
        seen = _recording(server)
        try:
            c = PlcClient.tcp(host, port, timeout_s=2.0, regmap=rmap)
            snap = await c.beat_and_read(9)
            assert seen == [6, 3] and snap["heartbeat_service"] == 9
            c.close()
        finally:
            await server.stop()

    asyncio.run(main())


def _blocks_reads_before(p, heads):
    """``PlcProtocol.blocks_reads`` as it was before its plans were kept (re-planned each call)."""
    from controller.fieldbus.plc_protocol import MAX_READ_WORDS

    block = p.regmap.heads
    if block is None:
        raise ValueError("heads: the register map has no [heads] blocks")
    for h in heads:
        block.address(h)
    order = sorted({int(h) for h in heads})
    out, run = [], []

    def one(run):
        return block.address(run[0]), (len(run) - 1) * block.stride + block.used, tuple(run)

    for h in order:
        fits = (block.read_across and run and h == run[-1] + 1
                and (h - run[0]) * block.stride + block.used <= MAX_READ_WORDS)
        if run and not fits:
            out.append(one(run))
            run = []
        run.append(h)
    if run:
        out.append(one(run))
    return tuple(out)


def test_blocks_reads_planned_once_are_the_plans_worked_out_each_time():
    """Random sequences of heads, asked again and again (lists, tuples, ranges, numpy
    integers, bad indices among them): the kept plan is the one worked out each time, a bad
    index is refused every time (a bool is no head even after head 1 was planned), and the
    caller's list may change afterwards."""
    import random

    import numpy as np

    from controller.fieldbus.plc_protocol import PlcProtocol

    rng = random.Random(7)
    maps = (RMAP, _one_block_map())
    for _ in range(400):
        m = rng.choice(maps)
        p = PlcProtocol(m)
        for _ in range(6):
            heads = [rng.randrange(-1, 10) for _ in range(rng.randrange(0, 9))]
            if rng.random() < 0.1:
                heads.append(rng.choice([True, 1.0, np.int64(2), "1"]))
            shape = rng.choice([list, tuple])
            try:
                want = _blocks_reads_before(p, heads)
            except (ValueError, TypeError) as exc:
                with pytest.raises(type(exc)):
                    p.blocks_reads(shape(heads))
                continue
            asked = shape(heads)
            assert p.blocks_reads(asked) == want
            if isinstance(asked, list):
                asked.append(9)  # the caller's list changed: the kept plan did not
            assert p.blocks_reads(shape(heads)) == want
    p = PlcProtocol(RMAP)
    assert p.blocks_reads([1]) is p.blocks_reads((1,))  # planned once
    with pytest.raises(ValueError, match="integer"):
        p.blocks_reads([True])
    assert p.blocks_reads(range(4)) == _blocks_reads_before(p, range(4))


def test_int_words_is_int_of_each_word():
    """``int_words`` against ``[int(w) for w in words]`` for random words of every kind a
    caller might pass (ints, bools, numpy integers and arrays, floats, strings, None, tuples,
    ranges): the same list (a new one, plain ints) or the same error."""
    import random

    import numpy as np

    from controller.fieldbus.plc_protocol import int_words

    rng = random.Random(11)
    kinds = [lambda: rng.randrange(0, 65536), lambda: rng.randrange(-5, 5), lambda: True,
             lambda: np.uint16(rng.randrange(65536)), lambda: rng.uniform(-1e5, 1e5),
             lambda: str(rng.randrange(100)), lambda: "x", lambda: None, lambda: 2 ** 70]
    for _ in range(3000):
        n = rng.randrange(0, 40)
        if rng.random() < 0.6:
            words = [rng.randrange(0, 65536) for _ in range(n)]
        else:
            words = [rng.choice(kinds)() for _ in range(n)]
        shaped = rng.choice([list, tuple, lambda w: w])(words)
        if rng.random() < 0.1 and all(type(w) is int and 0 <= w < 65536 for w in words):
            shaped = np.array(words, dtype=np.uint16)
        try:
            want = [int(w) for w in shaped]
        except Exception as exc:  # noqa: BLE001 - the error is what is compared
            with pytest.raises(type(exc)):
                int_words(shaped)
            continue
        got = int_words(shaped)
        assert got == want and all(type(w) is int for w in got)
        assert got is not shaped
    assert int_words(range(3)) == [0, 1, 2]


def test_blocks_reads_keeps_at_most_max_plans_and_stays_right_past_them():
    """A caller asking ever new sequences of heads: at most MAX_PLANS kept, every answer the
    plan worked out afresh (before and after the kept plans are dropped)."""
    import itertools

    from controller.fieldbus.plc_protocol import MAX_PLANS, PlcProtocol

    p = PlcProtocol(RMAP)
    seqs = [s for n in range(1, 5) for s in itertools.permutations(range(8), n)]
    assert len(seqs) > 3 * MAX_PLANS
    for s in seqs[:3 * MAX_PLANS]:
        assert p.blocks_reads(s) == _blocks_reads_before(p, s)
        assert 1 <= len(p._blocks_reads) <= MAX_PLANS
    again = seqs[3 * MAX_PLANS - 1]
    assert p.blocks_reads(again) is p.blocks_reads(list(again))  # the last one still kept
