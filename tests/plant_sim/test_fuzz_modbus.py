"""Raw Modbus TCP fuzz of the simulated PLC (127.0.0.1 only; bounded count, no timing).

Hypothesis sends well-framed requests with arbitrary function codes and bodies, writes of more
registers than an ADU holds (124..127: exception 03), broken headers
and plain garbage, each on its own connection. Every answer must be a well-formed Modbus TCP
response to one of the requests sent (the data asked for, or ``function | 0x80`` with one of the
exception codes the map documents); a header that is not Modbus TCP closes the connection. The
server must neither crash nor hang, and afterwards it still serves the map as the machine says.
"""

from __future__ import annotations

import socket
import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pyModbusTCP.client import ModbusClient

from plant_sim.interfaces.plc_server import FUNCTION_CODES, PlcServer
from protocol.registers import RegisterMap
from tests.plant_sim.test_sim_plc import LoopThread
from tests.support.fake_machine import FakeMachine

RMAP = RegisterMap.load()
EXCEPTIONS = {0x01, 0x02, 0x03, 0x0B}


@pytest.fixture(scope="module")
def server():
    lt = LoopThread()
    machine = FakeMachine()
    plc = PlcServer(machine, port=0)
    lt.call(plc.start())
    yield machine, plc
    lt.call(plc.stop())
    lt.close()


def _adu(tid: int, pid: int, unit: int, pdu: bytes, length: int | None = None) -> bytes:
    n = len(pdu) + 1 if length is None else length
    return struct.pack(">HHHB", tid, pid, n, unit) + pdu


function_codes = st.one_of(st.sampled_from(sorted(FUNCTION_CODES)), st.integers(0, 255))
first, count = RMAP.span()
addresses = st.one_of(st.integers(first, first + count + 2), st.integers(0, 0xFFFF))
quantities = st.one_of(st.integers(0, 130), st.integers(0, 0xFFFF))


@st.composite
def requests(draw) -> tuple[list[int], bytes]:
    """``(transaction ids that must be answered or dropped, bytes to send)``."""
    kind = draw(st.sampled_from(["structured", "random_pdu", "oversize_write", "bad_header",
                                 "garbage"]))
    tid = draw(st.integers(0, 0xFFFF))
    unit = draw(st.sampled_from([1, 1, 1, 0, 2, 255]))
    if kind == "structured":
        fc = draw(function_codes)
        start, qty = draw(addresses), draw(quantities)
        if fc in (16, 23):
            words = draw(st.lists(st.integers(0, 0xFFFF), max_size=6))
            nbytes = draw(st.sampled_from([2 * len(words), 2 * qty & 0xFF, 0]))
            body = struct.pack(">HHB", start, qty, nbytes) + struct.pack(f">{len(words)}H", *words)
            if fc == 23:
                body = struct.pack(">HH", draw(addresses), draw(quantities)) + body
        else:
            body = struct.pack(">HH", start, qty)
        return [tid], _adu(tid, 0, unit, bytes([fc]) + body)
    if kind == "random_pdu":
        pdu = draw(st.binary(min_size=1, max_size=253))
        return [tid], _adu(tid, 0, unit, pdu)
    if kind == "oversize_write":  # 124..127 registers: longer than an ADU, the count fits
        fc = draw(st.sampled_from([16, 23]))
        qty = draw(st.integers(124 if fc == 16 else 122, 127))
        nbytes = draw(st.sampled_from([2 * qty, 255, 2 * qty - 2]))
        body = struct.pack(">HHB", draw(addresses), qty, nbytes) + draw(
            st.binary(min_size=2 * qty, max_size=2 * qty))
        if fc == 23:
            body = struct.pack(">HH", draw(addresses), draw(quantities)) + body
        return [tid], _adu(tid, 0, unit, bytes([fc]) + body)
    if kind == "bad_header":
        pid = draw(st.integers(1, 0xFFFF))
        length = draw(st.one_of(st.just(0), st.just(1), st.integers(255, 0xFFFF)))
        use_pid = draw(st.booleans())
        pdu = draw(st.binary(min_size=1, max_size=20))
        return [], _adu(tid, pid if use_pid else 0, unit, pdu, None if use_pid else length)
    return [], draw(st.binary(min_size=1, max_size=300))


def _responses(data: bytes) -> list[tuple[int, int, bytes]]:
    """Split what the server sent into ``(tid, unit, pdu)``; asserts each is well formed."""
    out = []
    i = 0
    while i < len(data):
        assert len(data) - i >= 9, data[i:]
        tid, pid, length, unit = struct.unpack_from(">HHHB", data, i)
        assert pid == 0 and 3 <= length <= 254
        pdu = data[i + 7 : i + 6 + length]
        assert len(pdu) == length - 1
        out.append((tid, unit, pdu))
        i += 6 + length
    return out


def _check_pdu(request: bytes, pdu: bytes) -> None:
    fc = request[7]
    if len(request) - 7 > 253:  # longer than Modbus TCP carries: only ever refused
        assert pdu[0] & 0x80, pdu
    if pdu[0] & 0x80:
        assert pdu[0] == (fc | 0x80) & 0xFF and len(pdu) == 2 and pdu[1] in EXCEPTIONS, pdu
        return
    assert pdu[0] == fc and fc in FUNCTION_CODES
    if fc in (3, 23):
        assert pdu[1] == len(pdu) - 2 and pdu[1] % 2 == 0 and 2 <= pdu[1] <= 250
    else:  # 6 and 16 echo address and value / quantity
        assert pdu[1:5] == request[8:12]


@settings(max_examples=250, deadline=None, suppress_health_check=[HealthCheck.too_slow],
          derandomize=True)
@given(case=requests())
def test_raw_adus_never_crash_or_hang_and_every_answer_is_well_formed(server, case):
    _machine, plc = server
    tids, data = case
    with socket.create_connection(("127.0.0.1", plc.port), timeout=10.0) as s:
        s.sendall(data)
        s.shutdown(socket.SHUT_WR)  # the server sees the end: it answers what is whole, closes
        got = b""
        while chunk := s.recv(4096):
            got += chunk
    answers = _responses(got)
    assert len(answers) <= 1
    for tid, unit, pdu in answers:
        assert tids == [tid] and unit == data[6]
        _check_pdu(data, pdu)
    if tids and len(data) == 6 + struct.unpack_from(">H", data, 4)[0] and not answers:
        pytest.fail(f"a whole, well-framed request got no answer: {data!r}")


def test_after_the_fuzz_the_map_still_reads_as_the_machine_says(server):
    machine, plc = server
    c = ModbusClient(host="127.0.0.1", port=plc.port, unit_id=RMAP.unit_id, auto_open=True,
                     timeout=5.0)
    plc.refresh()
    words = c.read_holding_registers(first, count)
    c.close()
    assert words is not None and len(words) == count
    assert RMAP.decode_block(words, first) == pytest.approx(machine.register_values(), rel=1e-7)
    assert plc.running
