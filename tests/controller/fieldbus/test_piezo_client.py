"""The piezo client (a CANopen master) over python-can's virtual bus, against a scripted node.

The amplifier's side is played by hand from the documented frames (``tests/support/
canopen_frames.py``: heartbeat, SDO answers, TPDO1 status): cyclic command, offsets, the limits
read by SDO, reconnects, refused tables. The simulated node itself is tested against the client
in ``test_canopen_amp.py``.
"""

from __future__ import annotations

import itertools
import struct

import can
import pytest

from controller.fieldbus.piezo_client import PiezoClient
from core.errors import FieldbusError
from tests.support import canopen_frames as cf

_chan = itertools.count()
RPDO1, RPDO2, RPDO3 = 0x202, 0x302, 0x402


@pytest.fixture
def buses():
    name = f"piezo-test-{next(_chan)}"
    service = can.Bus(interface="virtual", channel=name)
    amp = can.Bus(interface="virtual", channel=name)
    yield service, amp
    service.shutdown()
    amp.shutdown()


def drain(bus):
    """Frames the client sent: ``(id, data)``."""
    out = []
    while (msg := bus.recv(timeout=0.0)) is not None:
        out.append((msg.arbitration_id, bytes(msg.data)))
    return out


def table_of(data: bytes) -> tuple[float, ...]:
    return tuple(v / 1000.0 for v in struct.unpack("<4h", data))


def report_limits(c, amp, *, stroke_um, now_s, lo=None, hi=None, timeout_ms=100, state=127):
    """The amplifier is heard and answers the client's SDO reads of its limits, in order."""
    values = cf.limit_values(stroke_um=stroke_um, lo_um=-stroke_um if lo is None else lo,
                             hi_um=stroke_um if hi is None else hi, timeout_ms=timeout_ms)
    c.handle(*cf.heartbeat(state), now_s=now_s)
    asked, others = [], []
    for _ in range(2 * len(values)):
        frames = drain(amp)
        reads = [r for fid, data in frames if fid == 0x602 and (r := cf.read_request(data))]
        others += [(fid, data) for fid, data in frames if fid != 0x602]
        if not reads:
            break
        for index, sub in reads:
            asked.append((index, sub))
            c.handle(*cf.answer(index, sub, values[(index, sub)]), now_s=now_s)
    assert sorted(asked) == sorted(values)  # each read once, no more
    return others


def test_command_is_cyclic_and_offsets_on_change_and_periodic(buses):
    service, amp = buses
    c = PiezoClient(service, knives=4, command_period_s=0.02, offsets_period_s=0.2)
    sent = report_limits(c, amp, stroke_um=25.0, now_s=0.0)  # larger than machine.toml's 20 um
    (note,) = c.take_notes()
    assert note.kind == "limits" and note.data["source"] == "machine.toml"
    assert c.stroke_um == note.data["limit_um"] == 20.0
    assert sent == [(0x000, bytes([1, 2]))]  # NMT start once the limits are in
    c.set_enable(True, now_s=0.0)
    commands, tables = [], []
    for i in range(50):  # 1 s at 20 ms
        t = i * 0.02
        c.tick(alive_counter=250 + i, now_s=t)
        if i == 10:
            c.set_offsets([1.0, -2.0, 0.5, 0.5], now_s=t)
        for fid, data in drain(amp):
            if fid == RPDO3:
                commands.append(data)
            elif fid == RPDO1:
                tables.append(table_of(data))
    assert len(commands) == 50
    assert all(d[0] == 1 and d[1] == 4 for d in commands)  # enable, knives
    alive = [d[2] for d in commands]
    assert all(b == (a + 1) % 256 for a, b in zip(alive[:-1], alive[1:], strict=True))
    assert tables[0] == (0.0,) * 4 and (1.0, -2.0, 0.5, 0.5) in tables
    assert 6 <= len(tables) <= 8  # on change and every 0.2 s, not every cycle


def test_eight_knives_use_two_offset_pdos(buses):
    service, amp = buses
    c = PiezoClient(service, knives=8)
    report_limits(c, amp, stroke_um=10.0, now_s=0.0)
    drain(amp)
    c.set_offsets([1.0, 2.0, 3.0, 4.0, -1.0, -2.0, -3.0, -4.0], now_s=0.01)
    sent = dict(drain(amp))
    assert table_of(sent[RPDO1]) == (1.0, 2.0, 3.0, 4.0)
    assert table_of(sent[RPDO2]) == (-1.0, -2.0, -3.0, -4.0)


def test_status_and_heartbeat_tracked_and_silence_measured(buses):
    service, amp = buses
    c = PiezoClient(service, knives=4)
    assert c.silent_for(0.0) == float("inf") and c.last_heard_s is None
    amp.send(can.Message(arbitration_id=0x702, data=b"\x05", is_extended_id=False))
    amp.send(can.Message(arbitration_id=0x182, data=struct.pack("<hhBB", 250, 312, 4, 2),
                         is_extended_id=False))
    assert c.poll(now_s=1.0) == 2
    assert c.nmt_state == 5 and c.last_heard_s == 1.0
    st = c.status
    assert (st.displacement_um, st.temperature_c, st.fault, st.state) == (0.25, 31.2, 4, 2)
    assert st.setpoint_timeout and st.t_s == 1.0
    c.handle(*cf.status_frame(), now_s=1.2)  # a status is heard too
    assert c.silent_for(1.25) == pytest.approx(0.05) and c.amp.last_heard_s == 1.0
    c.handle(*cf.status_frame(), now_s=1.5)  # statuses alone do not keep the node from loss
    assert c.amp.lost(1.5) and c.silent_for(1.5) == 0.0


def test_send_failure_is_fieldbus_error():
    class Broken:
        def send(self, msg, timeout=None):
            raise can.CanOperationError("bus off")

        def recv(self, timeout=None):
            return None

        def shutdown(self):
            pass

    c = PiezoClient(Broken(), knives=4)
    with pytest.raises(FieldbusError, match="0x402"):
        c.tick(alive_counter=1, now_s=0.0)
    assert c.send_errors == 1


@pytest.mark.parametrize("kw", [{"knives": 0}, {"knives": 9}, {"knives": 4, "command_period_s": 0},
                                {"knives": 4, "node_id": 0}, {"knives": 4, "node_id": 128},
                                {"knives": 4, "stroke_um": -1.0}])
def test_bad_parameters(kw, buses):
    with pytest.raises(ValueError):
        PiezoClient(buses[0], **kw)


def test_every_send_is_bounded_in_time():
    """A full transmit queue must not hold up the heartbeat: every send carries a short timeout."""

    class RecordingBus:
        def __init__(self):
            self.timeouts = []

        def send(self, msg, timeout=None):
            self.timeouts.append(timeout)

        def recv(self, timeout=None):
            return None

        def shutdown(self):
            pass

    bus = RecordingBus()
    c = PiezoClient(bus, knives=8, command_period_s=0.02)
    c.set_enable(True, now_s=0.0)
    c.tick(alive_counter=1, now_s=0.0)
    c.set_offsets([1.0] * 8, now_s=0.001)  # held at zero (no limits yet): not a new table
    c.handle(*cf.heartbeat(127), now_s=0.001)  # heard: the first SDO read goes out
    c.send_command(alive_counter=2, now_s=0.002)
    assert len(bus.timeouts) == 1 + 2 + 1 + 1  # command, offsets (2 PDOs), SDO read, command
    assert all(t is not None and 0 < t <= 0.01 for t in bus.timeouts)
    assert c.send_timeout_s <= c.command_period_s / 2


# ------------------------------------------------------------------ limits from the amplifier
def _planned_ok(sent, wanted, limit):
    """A sent table: inside the bound, unchanged (rounded) when the wish was inside it."""
    assert max(abs(v) for v in sent) <= limit + 1e-9
    if max(abs(v) for v in wanted) <= limit:
        assert sent == pytest.approx(wanted, abs=5e-4)


@pytest.mark.parametrize(
    ("config_um", "amp_um", "amp_range", "limit", "source"),
    [
        (20.0, 10.0, None, 10.0, "amplifier"),  # machine.toml wrong: the amplifier's wins
        (20.0, 25.0, None, 20.0, "machine.toml"),
        (12.0, 12.0, None, 12.0, "machine.toml"),
        (20.0, 30.0, (-8.0, 15.0), 8.0, "amplifier"),  # the accepted range narrows it
        (20.0, 30.0, (-32.768, 32.767), 20.0, "machine.toml"),
    ],
)
def test_the_smaller_stroke_is_used_and_said(buses, config_um, amp_um, amp_range, limit,
                                              source):
    service, amp = buses
    c = PiezoClient(service, knives=4, stroke_um=config_um)
    # before the amplifier has reported its limits nothing but zeros goes out
    assert c.set_offsets([3.0, -3.0, 1.0, -1.0], now_s=0.0) == (0.0,) * 4
    lo, hi = amp_range or (None, None)
    report_limits(c, amp, stroke_um=amp_um, lo=lo, hi=hi, now_s=0.01)
    (note,) = c.take_notes()
    assert note.data["source"] == source and note.data["limit_um"] == limit
    assert f"{limit:.3f} µm" in note.text and source.split(".")[0] in note.text
    assert c.stroke_um == limit
    # the table asked for before is re-planned into the bound (zero mean kept)
    c.tick(alive_counter=1, now_s=0.02)
    _planned_ok(c.offsets_um, (3.0, -3.0, 1.0, -1.0), limit)
    for wanted in ([50.0, -50.0, 0.0, 0.0], [limit, -limit, 1.0, -1.0], [9.0, 0.5, -9.5, 0.0]):
        sent = c.set_offsets(wanted, now_s=0.03)
        _planned_ok(sent, wanted, limit)
        assert sum(sent) == pytest.approx(0.0, abs=2e-3)
    # heartbeats go on: the limits are not read again, nothing is said
    for k in range(1, 4):
        c.handle(*cf.heartbeat(5), now_s=0.01 + 0.1 * k)
    assert c.take_notes() == [] and not [f for f, _ in drain(amp) if f == 0x602]


def test_an_unanswered_read_is_asked_again(buses):
    service, amp = buses
    c = PiezoClient(service, knives=4)
    c.handle(*cf.heartbeat(127), now_s=0.0)
    first = [cf.read_request(d) for f, d in drain(amp) if f == 0x602]
    c.poll(now_s=0.05)
    assert [f for f, _ in drain(amp) if f == 0x602] == []  # within the SDO time-out: waits
    c.poll(now_s=0.2)
    again = [cf.read_request(d) for f, d in drain(amp) if f == 0x602]
    assert first == again == [(0x2200, 1)] and c.counts["sdo_retries"] == 1
    c.handle(*cf.sdo_abort(0x2200, 1), now_s=0.21)  # an abort: no limits, asked again later
    assert c.counts["sdo_errors"] == 1 and c.stroke_um == 0.0


def test_limits_are_read_anew_after_a_reconnect(buses):
    service, amp = buses
    c = PiezoClient(service, knives=4, stroke_um=20.0)
    report_limits(c, amp, stroke_um=10.0, now_s=0.0)
    c.set_offsets([6.0, -6.0, 2.0, -2.0], now_s=0.0)
    c.take_notes()
    c.handle(*cf.heartbeat(5), now_s=0.25)  # a gap within 3 heartbeat periods: nothing changes
    assert c.reconnects == 0 and c.stroke_um == 10.0
    reads = c.counts["sdo_reads"]
    c.handle(*cf.heartbeat(5), now_s=0.7)  # silent for 0.45 s: lost, and found again
    assert c.reconnects == 1 and c.stroke_um == 0.0 and c.offsets_um == (0.0,) * 4
    (note,) = c.take_notes()
    assert note.kind == "limits" and note.data["source"] == "unknown"
    assert c.counts["sdo_reads"] == reads + 1  # reading the limits anew
    # a replaced amplifier with a smaller stroke: the wish is re-planned inside it
    values = cf.limit_values(stroke_um=4.0, lo_um=-4.0, hi_um=4.0)
    while reads := [cf.read_request(d) for f, d in drain(amp) if f == 0x602]:
        for index, sub in reads:
            c.handle(*cf.answer(index, sub, values[(index, sub)]), now_s=0.71)
    assert c.stroke_um == 4.0
    _planned_ok(c.offsets_um, (6.0, -6.0, 2.0, -2.0), 4.0)


def test_a_node_that_boots_again_is_read_and_started_again(buses):
    service, amp = buses
    c = PiezoClient(service, knives=4)
    report_limits(c, amp, stroke_um=10.0, now_s=0.0)
    c.handle(*cf.heartbeat(5), now_s=0.1)
    c.take_notes()
    c.handle(*cf.heartbeat(0), now_s=0.15)  # boot-up: a restart, however short the gap
    assert c.reconnects == 1 and c.stroke_um == 0.0
    sent = report_limits(c, amp, stroke_um=10.0, now_s=0.16)
    assert c.stroke_um == 10.0 and (0x000, bytes([1, 2])) in sent


@pytest.mark.parametrize(
    ("limits", "word"),
    [
        ({"stroke_um": 0.0}, "stroke_um"),
        ({"lo": 1.0}, "offset_min_um"),
        ({"hi": -1.0}, "offset_max_um"),
    ],
)
def test_a_nonsense_limits_report_holds_the_offsets_at_zero(buses, limits, word):
    service, amp = buses
    c = PiezoClient(service, knives=4, stroke_um=20.0)
    report_limits(c, amp, stroke_um=10.0, now_s=0.0)
    c.set_offsets([5.0, -5.0, 0.0, 0.0], now_s=0.0)
    c.take_notes()
    c.handle(*cf.heartbeat(0), now_s=0.1)  # rebooted with other limits
    c.take_notes()
    sent = report_limits(c, amp, **{"stroke_um": 10.0, "lo": -10.0, "hi": 10.0, **limits},
                         now_s=0.1)
    (note,) = c.take_notes()
    assert "invalid" in note.text and word in note.text
    assert c.stroke_um == 0.0 and c.offsets_um == (0.0,) * 4
    assert (0x000, bytes([1, 2])) not in sent  # not started on limits that make no sense


def test_an_emergency_is_a_note(buses):
    service, amp = buses
    c = PiezoClient(service, knives=4)
    c.handle(*cf.emcy(0x4210), now_s=0.5)
    c.handle(*cf.emcy(0x0000, register=0), now_s=0.6)
    notes = c.take_notes()
    assert [n.kind for n in notes] == ["emergency", "emergency"]
    assert notes[0].data["fault"] == "over-temperature" and "0x4210" in notes[0].text
    assert notes[1].data["fault"] == "cleared"


def _refusing_status(now_s, c, *, fault=2):
    c.handle(*cf.status_frame(fault=fault, state=1), now_s=now_s)


def test_a_refused_table_is_replanned_never_resent_unchanged(buses):
    """An amplifier that reports 10 um but takes only 3 um: each refusal narrows the bound."""
    service, amp = buses
    c = PiezoClient(service, knives=4, stroke_um=20.0, refusal_grace_s=0.05)
    report_limits(c, amp, stroke_um=10.0, now_s=0.0)
    c.take_notes()
    c.set_enable(True, now_s=0.0)
    wanted = (9.0, -7.0, 4.0, -6.0)
    t = 0.0
    c.set_offsets(wanted, now_s=t)
    drain(amp)
    refused_tables = []
    for _ in range(40):  # 20 ms cycles; the amplifier refuses anything beyond 3 um
        t += 0.02
        if max(abs(v) for v in c.offsets_um) > 3.0:
            _refusing_status(t, c)
        c.tick(alive_counter=1, now_s=t)
        for table in [table_of(d) for f, d in drain(amp) if f == RPDO1]:
            assert table not in refused_tables, "a refused table went out again"
        for note in c.take_notes():
            assert note.kind == "refused"
            refused_tables.append(tuple(note.data["table_um"]))
            # the re-planned table: inside the narrowed bound, below the refused one
            new = note.data["replanned_um"]
            assert max(map(abs, new)) <= note.data["limit_um"] + 1e-9
            assert note.data["limit_um"] < max(map(abs, note.data["table_um"]))
            assert sum(new) == pytest.approx(0.0, abs=2e-3)
    assert refused_tables and c.tables_refused == len(refused_tables)
    assert max(abs(v) for v in c.offsets_um) <= 3.0  # ended inside what it takes
    assert c.limit.source == "refused table"
    # a status before the grace is over speaks of the table before: not a refusal of this one
    n = c.tables_refused
    c.set_offsets([2.0, -2.0, 1.0, -1.0], now_s=t + 0.001)
    _refusing_status(t + 0.01, c)
    assert c.tables_refused == n


def test_a_refused_zero_table_is_reported_and_nothing_smaller_is_invented(buses):
    service, amp = buses
    c = PiezoClient(service, knives=4, stroke_um=20.0)
    report_limits(c, amp, stroke_um=10.0, now_s=0.0)
    c.take_notes()
    c.set_offsets([0.0] * 4, now_s=0.0)
    _refusing_status(0.2, c)
    (note,) = c.take_notes()
    assert note.kind == "refused" and note.data["limit_um"] is None
    assert note.data["replanned_um"] is None and c.offsets_um == (0.0,) * 4


@pytest.mark.parametrize("frame", [
    (0x182, b"\x01\x02\x03"),  # a status too short
    (0x702, b"\x05\x00"),  # a heartbeat too long
    (0x123, b"\xff" * 8),  # no service of the node
    (0x183, b"\x00" * 6),  # another node's status
    (0x402, b"\x01\x04\x07"),  # our own command, echoed by the transport
    ("0x182", b"\x00" * 6),  # not an id
    (0x182, "not bytes"),
])
def test_a_malformed_or_foreign_frame_changes_nothing_and_is_counted(buses, frame):
    service, amp = buses
    c = PiezoClient(service, knives=4)
    report_limits(c, amp, stroke_um=10.0, now_s=0.0)
    c.tick(alive_counter=7, now_s=0.0)
    c.handle(*cf.status_frame(), now_s=0.01)
    drain(amp)
    before = (c.status, c.nmt_state, c.last_heard_s, c.stroke_um, c.received)
    counts = c.counts
    assert c.handle(*frame, now_s=0.02) == 0
    after = c.counts
    refused = sum(after[k] - counts[k] for k in ("foreign", "malformed", "own"))
    assert refused == 1 and after["frames"] == counts["frames"] + 1
    assert (c.status, c.nmt_state, c.last_heard_s, c.stroke_um, c.received) == before
    assert drain(amp) == []


def test_heads_share_one_master_each_frame_taken_once(buses):
    """A moulder's heads on one CAN connection: every frame decoded once, each head its own."""
    from controller.fieldbus.canopen_amp import AmpBus

    service, amp = buses
    master = AmpBus(service)
    a = PiezoClient(None, knives=4, node_id=2, ampbus=master)
    b = PiezoClient(service, knives=2, node_id=3, ampbus=master)
    elsewhere = can.Bus(interface="virtual", channel=f"piezo-test-{next(_chan)}")
    with pytest.raises(ValueError, match="shared master"):
        PiezoClient(elsewhere, knives=2, node_id=4, ampbus=master)
    elsewhere.shutdown()
    with pytest.raises(ValueError, match="send_timeout_s.*0.001"):  # the master's rules
        PiezoClient(None, knives=2, node_id=4, ampbus=master, send_timeout_s=0.001)
    assert a.send_timeout_s == b.send_timeout_s == master.network.send_timeout_s
    assert a.bus is b.bus is service
    for node, state in ((2, 5), (3, 5), (3, 5)):
        fid, data = cf.heartbeat(state, node_id=node)
        amp.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
    fid, data = cf.status_frame(displacement_nm=1500, node_id=3)
    amp.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
    assert a.poll(now_s=1.0) == 1  # a drained the bus: its node's one frame ...
    assert b.status is None  # ... b's frames went to b's node, b takes them at its poll
    assert b.poll(now_s=1.001) == 3 and b.received == 3 and a.received == 1
    assert b.status is not None and b.status.displacement_um == pytest.approx(1.5)
    assert a.status is None and a.last_heard_s == 1.0 and b.last_heard_s == 1.0
    assert master.counts["frames"] == 4 and master.counts["foreign"] == 0  # once, none foreign
    assert a.poll(now_s=1.02) == 0 and b.poll(now_s=1.02) == 0
    a.close()  # a shared bus stays open for the other heads
    b.send_command(alive_counter=9, now_s=1.03)
    assert (0x403, bytes([0, 2, 9])) in drain(amp)
    b.close()
    master.close()


def test_pdo_frames_are_the_librarys_bytes(buses):
    """The command and the offset tables go out byte for byte as canopen's ``var.raw`` sets."""
    import random

    service, amp = buses
    c = PiezoClient(service, knives=8, node_id=2)
    rng = random.Random(5)
    cases = [(rng.random() < 0.5, rng.randrange(0, 600),
              [round(rng.uniform(-32.767, 32.767), 3) for _ in range(8)]) for _ in range(200)]

    def frames() -> list:
        for enable, alive, table in cases:
            c.amp.command(enable=enable, alive_counter=alive)
            c.amp.set_offsets(table)
        return drain(amp)

    fast = frames()
    c.amp._layouts = {1: None, 2: None, 3: None}  # the library's own path
    slow = frames()
    assert len(fast) == 3 * len(cases) and fast == slow
    assert fast[0] == cf.command(cases[0][0], 8, cases[0][1] & 0xFF)
    assert fast[1:3] == cf.offsets(cases[0][2])


def test_clamp_is_the_replanned_table_rounded_to_the_wire(buses):
    """Tables inside and beyond the bound, as arrays, tuples and lists: the offsets sent are
    ``replan_offsets`` rounded to 1 nm and clipped to the wire's grid, bit for bit; a value that
    is no finite number is refused naming its place."""
    import math
    import random

    import numpy as np

    from controller.laws.limits import replan_offsets

    service, amp = buses
    c = PiezoClient(service, knives=4, stroke_um=20.0)
    report_limits(c, amp, stroke_um=6.0, now_s=0.0)
    lim = c.limit.limit_um
    s = math.floor(lim * 1000.0 + 1e-6) / 1000.0
    rng = random.Random(7)
    for i in range(300):
        table = [rng.uniform(-2.0, 2.0) * rng.choice([0.5, 2.0, 4.0]) for _ in range(4)]
        if i % 5 == 0:
            table[rng.randrange(4)] = rng.choice([lim, -lim])  # exactly on the bound
        want = tuple(min(max(round(float(v), 3), -s), s) + 0.0
                     for v in replan_offsets(table, limit_um=lim))
        for given in (table, tuple(table), np.array(table)):
            assert c.clamp(given) == want
    for bad in ([1.0, math.nan, 0.0, 0.0], [0.0, 0.0, math.inf, 0.0], [0.0, "x", 0.0, 0.0]):
        with pytest.raises(ValueError, match=r"offsets_um\[\d\]"):
            c.clamp(bad)
    with pytest.raises(ValueError, match="4 values"):
        c.clamp([0.0, 0.0])
