"""The simulator's PLC Modbus server, driven by an independent Modbus client (pyModbusTCP)."""

from __future__ import annotations

import asyncio
import math
import struct
import threading
from types import SimpleNamespace

import pytest
from pyModbusTCP import constants as mbc
from pyModbusTCP.client import ModbusClient
from pyModbusTCP.utils import decode_ieee, encode_ieee, long_list_to_word, word_list_to_long

from plant_sim.interfaces.plc_server import PlcServer
from protocol.registers import RegisterMap
from tests.support.fake_machine import FakeMachine

RMAP = RegisterMap.load()


class LoopThread:
    """An asyncio loop in a thread, so the blocking pyModbusTCP client can talk to the server."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()

    def call(self, coro):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout=10)

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(timeout=5)
        self.loop.close()


@pytest.fixture
def plc():
    lt = LoopThread()
    machine = FakeMachine()
    server = PlcServer(machine, port=0)
    host, port = lt.call(server.start())
    client = ModbusClient(host=host, port=port, unit_id=RMAP.unit_id, auto_open=True, timeout=2.0)
    yield SimpleNamespace(lt=lt, machine=machine, server=server, client=client, port=port)
    client.close()
    lt.call(server.stop())
    lt.close()


def _read(client: ModbusClient, name: str) -> list[int]:
    reg = RMAP[name]
    words = client.read_holding_registers(reg.address, reg.count)
    assert words is not None, client.last_error_as_txt
    return words


def test_binds_loopback_on_an_ephemeral_port(plc):
    assert plc.server.host == "127.0.0.1"
    assert 0 < plc.port < 65536 and plc.server.port == plc.port


def test_whole_map_reads_as_the_machine_says(plc):
    first, count = RMAP.span()
    words = plc.client.read_holding_registers(first, count)
    assert words is not None and len(words) == count
    assert RMAP.decode_block(words, first) == pytest.approx(
        {k: v for k, v in plc.machine.register_values().items()}, rel=1e-7
    )


@pytest.mark.parametrize("name", [r.name for r in RMAP if r.type == "f32"])
def test_float32_big_endian_words_decoded_independently(plc, name):
    words = _read(plc.client, name)
    expect = plc.machine.register_values()[name]
    # pyModbusTCP's own decoders: high word first (big_endian=True), IEEE-754 single
    got = decode_ieee(word_list_to_long(words, big_endian=True)[0])
    assert got == pytest.approx(expect, rel=1e-7)
    assert struct.pack(">HH", *words) == struct.pack(">f", expect)


@pytest.mark.parametrize("name", [r.name for r in RMAP if r.type == "u32"])
def test_uint32_words_decoded_independently(plc, name):
    words = _read(plc.client, name)
    assert word_list_to_long(words, big_endian=True)[0] == plc.machine.register_values()[name]


def test_int32_register_decoded_independently():
    # the shipped map has no i32; serve a one-register map with a negative value
    from protocol.registers import Register

    rmap = RegisterMap([Register("position_counts", 0, "i32", "ro", 2)])
    machine = SimpleNamespace(register_values=lambda: {"position_counts": -123_456_789})
    lt = LoopThread()
    try:
        server = PlcServer(machine, register_map=rmap, port=0)
        host, port = lt.call(server.start())
        c = ModbusClient(host=host, port=port, unit_id=1, auto_open=True, timeout=2.0)
        words = c.read_holding_registers(0, 2)
        raw = word_list_to_long(words, big_endian=True)[0]
        assert raw - (1 << 32) == -123_456_789
        c.close()
        lt.call(server.stop())
    finally:
        lt.close()


@pytest.mark.parametrize("name", [r.name for r in RMAP if r.access == "ro"])
def test_write_to_read_only_register_refused_with_exception_02(plc, name):
    reg = RMAP[name]
    before = plc.machine.register_values()
    ok = plc.client.write_multiple_registers(reg.address, [1] * reg.count)
    assert not ok
    assert plc.client.last_except == mbc.EXP_DATA_ADDRESS
    assert _read(plc.client, name) == RMAP.encode(name, before[name])


@pytest.mark.parametrize("value", [49.9, 1000.5, -5.0, 1e9, math.nan])
def test_out_of_range_setpoint_refused_with_exception_03_never_clamped(plc, value):
    before = plc.machine.feed_setpoint
    words = long_list_to_word([encode_ieee(value)], big_endian=True)
    assert not plc.client.write_multiple_registers(RMAP["feed_setpoint_mm_s"].address, words)
    assert plc.client.last_except == mbc.EXP_DATA_VALUE
    assert plc.machine.feed_setpoint == before
    got = decode_ieee(word_list_to_long(_read(plc.client, "feed_setpoint_mm_s"))[0])
    assert got == before


@pytest.mark.parametrize("value", [50.0, 333.25, 1000.0])
def test_accepted_setpoint_reaches_the_machine_and_reads_back(plc, value):
    words = long_list_to_word([encode_ieee(value)], big_endian=True)
    assert plc.client.write_multiple_registers(RMAP["feed_setpoint_mm_s"].address, words)
    assert plc.machine.feed_setpoint == value
    assert decode_ieee(word_list_to_long(_read(plc.client, "feed_setpoint_mm_s"))[0]) == value


def test_heartbeat_write_reaches_machine_and_half_float_write_refused(plc):
    assert plc.client.write_single_register(RMAP["heartbeat_service"].address, 4242)
    assert plc.machine.heartbeat_service == 4242
    # function 6 on the first word of a float: a partial write, illegal address
    assert not plc.client.write_single_register(RMAP["feed_setpoint_mm_s"].address, 0x4248)
    assert plc.client.last_except == mbc.EXP_DATA_ADDRESS
    # a read past the map
    first, count = RMAP.span()
    assert plc.client.read_holding_registers(first + count, 1) is None
    assert plc.client.last_except == mbc.EXP_DATA_ADDRESS
    # other tables than holding registers are not served
    assert plc.client.read_input_registers(0, 1) is None
    assert plc.client.last_except == mbc.EXP_ILLEGAL_FUNCTION


def test_wrong_unit_id_is_not_answered_as_the_plc(plc):
    c = ModbusClient(
        host="127.0.0.1", port=plc.port, unit_id=RMAP.unit_id + 1, auto_open=True, timeout=2.0
    )
    assert c.read_holding_registers(0, 1) is None
    assert c.last_except == mbc.EXP_GATEWAY_TARGET_DEVICE_FAILED_TO_RESPOND
    c.close()


def test_refresh_publishes_the_machine_cycle(plc):
    hb0 = _read(plc.client, "heartbeat_plc")[0]
    plc.machine.advance(0.001)
    assert _read(plc.client, "heartbeat_plc")[0] == hb0  # not before the PLC cycle
    plc.lt.call(_async(plc.server.refresh))
    assert _read(plc.client, "heartbeat_plc")[0] == (hb0 + 1) & 0xFFFF


async def _async(fn):
    return fn()


def test_server_restart_drops_clients_and_serves_again_on_the_same_port(plc):
    assert _read(plc.client, "knives") == [4]
    plc.lt.call(plc.server.stop())
    assert not plc.server.running
    assert plc.client.read_holding_registers(0, 1) is None  # connection refused
    host, port = plc.lt.call(plc.server.start())
    assert port == plc.port
    assert _read(plc.client, "knives") == [4]  # auto_open reconnects
    host, port = plc.lt.call(plc.server.restart())
    assert port == plc.port
    # the restart closed the client's connection: its next request fails, then it reconnects
    first = plc.client.read_holding_registers(RMAP["knives"].address, 1)
    assert first is None or first == [4]
    assert _read(plc.client, "knives") == [4]


def test_port_in_use_is_a_fieldbus_error(plc):
    from core.errors import FieldbusError

    other = PlcServer(FakeMachine(), port=plc.port)
    with pytest.raises(FieldbusError, match=str(plc.port)):
        plc.lt.call(other.start())


def test_real_machine_register_values_match_the_map():
    from config.sim import default_sim
    from plant_sim.machine import machine as sim

    m = sim.Machine(default_sim(), seed=0, render_images=False)
    m.advance(0.01)
    values = m.register_values()
    assert set(values) == set(RMAP.registers)
    server = PlcServer(m, port=0)
    words = RMAP.encode_block(server.values)
    assert RMAP.decode_block(words)["knives"] == values["knives"]


# ------------------------------------------------------------------ raw Modbus TCP frames
def raw_exchange(port: int, pdu: bytes, *, unit: int = 1, tid: int = 7) -> bytes | None:
    """Send one ADU over a fresh socket; the response PDU, or ``None`` if the server closed."""
    import socket

    with socket.create_connection(("127.0.0.1", port), timeout=5.0) as s:
        s.sendall(struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu)
        return read_adu(s, tid=tid, unit=unit)


def read_adu(sock, *, tid: int, unit: int) -> bytes | None:
    """Read one response ADU; checks its header; the PDU (``None``: connection closed)."""
    head = b""
    while len(head) < 7:
        chunk = sock.recv(7 - len(head))
        if not chunk:
            return None
        head += chunk
    r_tid, pid, length, r_unit = struct.unpack(">HHHB", head)
    assert (r_tid, pid, r_unit) == (tid, 0, unit) and 2 <= length <= 254
    body = b""
    while len(body) < length - 1:
        chunk = sock.recv(length - 1 - len(body))
        assert chunk, "connection closed inside a response"
        body += chunk
    return body


# every function code the map does not offer: coils, inputs, diagnostics, report server id,
# file records, FIFO, encapsulated interface (device identification), user codes
NOT_OFFERED = [1, 2, 4, 5, 7, 8, 11, 12, 15, 17, 20, 21, 22, 24, 43, 65, 100, 127]


@pytest.mark.parametrize("fc", NOT_OFFERED)
def test_function_codes_the_map_does_not_offer_get_exception_01_and_reveal_nothing(plc, fc):
    for body in (b"", b"\x00\x00\x00\x01", bytes(range(20))):
        reply = raw_exchange(plc.port, bytes([fc]) + body)
        assert reply == bytes([fc | 0x80, 0x01]), reply  # nothing else: no library name
    assert plc.client.read_holding_registers(0, 1) is not None  # still serving


@pytest.mark.parametrize("count", [0, 126, 2000, 0xFFFF])
def test_read_quantity_outside_1_to_125_is_exception_03(plc, count):
    assert raw_exchange(plc.port, struct.pack(">BHH", 3, 0, count)) == b"\x83\x03"


@pytest.mark.parametrize(
    "pdu, code",
    [
        (struct.pack(">BH", 3, 0), 0x03),  # short body
        (struct.pack(">BHHB", 3, 0, 1, 0), 0x03),  # long body
        (struct.pack(">BHHB", 16, 2, 2, 3) + b"\x00" * 3, 0x03),  # byte count != 2 * qty
        (struct.pack(">BHHB", 16, 2, 0, 0), 0x03),  # no registers
        (struct.pack(">BHHB", 16, 2, 124, 248) + b"\x00" * 248, 0x03),  # 124 > 123
        (struct.pack(">BHHB", 16, 2, 2, 4) + b"\x00" * 2, 0x03),  # fewer bytes than said
        (struct.pack(">BHH", 6, 40000, 1), 0x02),  # write past the map
        (struct.pack(">BHH", 3, 37, 2), 0x02),  # read past the map
    ],
)
def test_malformed_requests_get_the_spec_exception(plc, pdu, code):
    assert raw_exchange(plc.port, pdu) == bytes([pdu[0] | 0x80, code])


def _oversize_write(fc: int, qty: int, nbytes: int | None = None) -> bytes:
    nbytes = 2 * qty if nbytes is None else nbytes
    head = struct.pack(">BHH", fc, 0, 4) if fc == 23 else bytes([fc])
    feed = RMAP["feed_setpoint_mm_s"]
    return head + struct.pack(">HHB", feed.address, qty, nbytes) + b"\x44" * nbytes


@pytest.mark.parametrize(
    "pdu",
    [_oversize_write(16, q) for q in (124, 125, 126, 127)]
    + [_oversize_write(16, 127, 255), _oversize_write(16, 124, 10) + b"\x00" * 238]
    + [_oversize_write(23, q) for q in (122, 124, 127)] + [_oversize_write(23, 127, 255)],
    ids=lambda pdu: f"fc{pdu[0]}-{len(pdu)}B",
)
def test_write_multiple_longer_than_an_adu_is_exception_03_on_a_connection_that_goes_on(plc, pdu):
    """A write of 124..127 registers (PDU 254..265 bytes): 03, nothing written, still in step."""
    import socket

    assert len(pdu) > 253  # longer than Modbus TCP carries (ADU > 260 bytes)
    before = plc.machine.feed_setpoint
    with socket.create_connection(("127.0.0.1", plc.port), timeout=5.0) as s:
        s.sendall(struct.pack(">HHHB", 9, 0, len(pdu) + 1, 1) + pdu)
        assert read_adu(s, tid=9, unit=1) == bytes([pdu[0] | 0x80, 0x03])
        read = struct.pack(">BHH", 3, RMAP["knives"].address, 1)
        s.sendall(struct.pack(">HHHB", 10, 0, len(read) + 1, 1) + read)
        assert read_adu(s, tid=10, unit=1) == b"\x03\x02\x00\x04"  # the same stream goes on
    assert plc.machine.feed_setpoint == before
    assert plc.server.refused == 1


@pytest.mark.parametrize(
    "fc, length",
    [(3, 255), (6, 260), (1, 262), (16, 263), (23, 267), (16, 300), (23, 0xFFFF)],
)
def test_oversize_header_of_anything_but_a_fitting_write_multiple_still_closes(plc, fc, length):
    import socket

    with socket.create_connection(("127.0.0.1", plc.port), timeout=5.0) as s:
        body = bytes([fc]) + b"\x00" * min(length - 2, 300)
        s.sendall(struct.pack(">HHHB", 1, 0, length, 1) + body)
        assert s.recv(100) == b""  # closed without an answer
    assert _read(plc.client, "knives") == [4]


def test_read_write_multiple_writes_then_reads(plc):
    reg = RMAP["feed_setpoint_mm_s"]
    words = RMAP.encode("feed_setpoint_mm_s", 612.5)
    first, count = RMAP.span()
    pdu = struct.pack(">BHHHHB", 23, first, count, reg.address, 2, 4) + struct.pack(">2H", *words)
    reply = raw_exchange(plc.port, pdu)
    assert reply[:2] == bytes([23, 2 * count])
    got = RMAP.decode_block(list(struct.unpack(f">{count}H", reply[2:])), first)
    assert got["feed_setpoint_mm_s"] == 612.5 and plc.machine.feed_setpoint == 612.5


def test_not_modbus_tcp_header_closes_only_that_connection(plc):
    import socket

    for head in (struct.pack(">HHHB", 1, 1, 6, 1), struct.pack(">HHHB", 1, 0, 0, 1),
                 struct.pack(">HHHB", 1, 0, 300, 1)):
        with socket.create_connection(("127.0.0.1", plc.port), timeout=5.0) as s:
            s.sendall(head + b"\x03\x00\x00\x00\x01")
            assert s.recv(100) == b""  # closed without an answer
    assert _read(plc.client, "knives") == [4]


def test_queued_writes_served_at_once_applied_in_order_by_the_stepping_side():
    """``queue_writes``: the snapshot shows a write at once; the machine gets it on apply."""
    machine = FakeMachine()
    lt = LoopThread()
    server = PlcServer(machine, port=0, queue_writes=True)
    try:
        host, port = lt.call(server.start())
        c = ModbusClient(host=host, port=port, unit_id=1, auto_open=True, timeout=2.0)
        for value in (100.0, 250.0, 333.5):
            words = long_list_to_word([encode_ieee(value)], big_endian=True)
            assert c.write_multiple_registers(RMAP["feed_setpoint_mm_s"].address, words)
        assert machine.feed_setpoint == 800.0  # not applied yet
        server.refresh()  # a publish before the apply keeps the written value
        got = decode_ieee(word_list_to_long(_read(c, "feed_setpoint_mm_s"))[0])
        assert got == 333.5
        applied: list[float] = []
        orig = machine.set_feed_setpoint
        machine.set_feed_setpoint = lambda v: (applied.append(v), orig(v))[1]
        assert server.apply_writes() == 3 and applied == [100.0, 250.0, 333.5]
        server.refresh()
        assert decode_ieee(word_list_to_long(_read(c, "feed_setpoint_mm_s"))[0]) == 333.5
        c.close()
    finally:
        lt.call(server.stop())
        lt.close()
