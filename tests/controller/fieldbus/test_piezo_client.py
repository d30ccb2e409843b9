"""Piezo CAN client over python-can's virtual bus: cyclic frames, offsets, status, silence."""

from __future__ import annotations

import itertools

import can
import pytest

from controller.fieldbus.piezo_client import PiezoClient
from core.errors import FieldbusError
from protocol.piezo_can import COMMAND, OFFSETS, STATE_ENABLED, PiezoCodec

CODEC = PiezoCodec.load()
_chan = itertools.count()


@pytest.fixture
def buses():
    name = f"piezo-test-{next(_chan)}"
    service = can.Bus(interface="virtual", channel=name)
    amp = can.Bus(interface="virtual", channel=name)
    yield service, amp
    service.shutdown()
    amp.shutdown()


def drain(bus):
    out = []
    while (msg := bus.recv(timeout=0.0)) is not None:
        out.append(CODEC.decode(msg.arbitration_id, bytes(msg.data)))
    return out


def report_limits(c, *, stroke_um, now_s, lo=None, hi=None, timeout_ms=100):
    """The amplifier's PIEZO_LIMITS, handed to the client as if received at ``now_s``."""
    frame = CODEC.encode_limits(
        stroke_um=stroke_um,
        offset_min_um=-stroke_um if lo is None else lo,
        offset_max_um=stroke_um if hi is None else hi,
        setpoint_timeout_ms=timeout_ms,
    )
    return c.handle(*frame, now_s=now_s)


def test_command_is_cyclic_and_offsets_on_change_and_periodic(buses):
    service, amp = buses
    c = PiezoClient(service, CODEC, knives=4, command_period_s=0.02, offsets_period_s=0.2)
    report_limits(c, stroke_um=25.0, now_s=0.0)  # larger than machine.toml's 20 um
    (note,) = c.take_notes()
    assert note.kind == "limits" and note.data["source"] == "machine.toml"
    assert c.stroke_um == note.data["limit_um"] == 20.0
    c.set_enable(True, now_s=0.0)
    t = 0.0
    counts = {COMMAND: 0, OFFSETS[0]: 0}
    alive = []
    for i in range(50):  # 1 s at 20 ms
        t = i * 0.02
        c.tick(alive_counter=250 + i, now_s=t)
        for name, sig in drain(amp):
            counts[name] += 1
            if name == COMMAND:
                alive.append(sig["alive_counter"])
                assert sig["enable"] == 1 and sig["knives"] == 4
    assert counts[COMMAND] == 50
    assert alive == [(250 + i) % 256 for i in range(50)]  # the counter wraps at 8 bits
    assert 5 <= counts[OFFSETS[0]] <= 6  # once at start, then every 0.2 s
    # a change goes out at once, rounded to 0.001 um; inside machine.toml's 20 um (smaller
    # than the amplifier's 25 um) it is only rounded
    sent = c.set_offsets([1.23456, -3.0, 20.0, 0.0], now_s=t + 0.001)
    assert sent == (1.235, -3.0, 20.0, 0.0)
    frames = drain(amp)
    assert [n for n, _ in frames] == [OFFSETS[0]]
    got = CODEC.offsets_from(*frames[0])
    assert [got[k] for k in range(4)] == list(sent)
    # unchanged offsets are not resent before the period
    c.set_offsets([1.235, -3.0, 20.0, 0.0], now_s=t + 0.002)
    assert drain(amp) == []


def test_eight_knives_use_two_offset_frames(buses):
    service, amp = buses
    c = PiezoClient(service, CODEC, knives=8)
    report_limits(c, stroke_um=10.0, now_s=0.0)
    c.set_offsets([float(k) for k in range(8)], now_s=0.0)
    frames = drain(amp)
    assert [n for n, _ in frames] == list(OFFSETS)
    merged = {}
    for n, s in frames:
        merged.update(CODEC.offsets_from(n, s))
    assert merged == {k: float(k) for k in range(8)}
    with pytest.raises(ValueError, match="8 values"):
        c.set_offsets([0.0] * 4, now_s=0.1)
    with pytest.raises(ValueError, match=r"offsets_um\[2\]"):
        c.set_offsets([0.0, 0.0, float("nan")] + [0.0] * 5, now_s=0.1)


def test_status_and_heartbeat_tracked_and_silence_measured(buses):
    service, amp = buses
    c = PiezoClient(service, CODEC, knives=4)
    assert c.silent_for(0.0) == float("inf")
    arb, data = CODEC.encode_status(
        displacement_um=3.5, temperature_c=31.2, fault=0, state=STATE_ENABLED, alive_counter=9
    )
    amp.send(can.Message(arbitration_id=arb, data=data, is_extended_id=False))
    arb, data = CODEC.encode_heartbeat(nmt_state=5)
    amp.send(can.Message(arbitration_id=arb, data=data, is_extended_id=False))
    amp.send(can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False))  # foreign
    assert c.poll(now_s=1.0) == 2
    assert c.status.displacement_um == 3.5 and c.status.state == STATE_ENABLED
    assert c.status.temperature_c == pytest.approx(31.2) and not c.status.setpoint_timeout
    assert c.nmt_state == 5 and c.last_heard_s == 1.0
    assert c.poll(now_s=1.5) == 0
    assert c.silent_for(1.5) == pytest.approx(0.5)


def test_send_failure_is_fieldbus_error():
    class BrokenBus:
        def send(self, msg, timeout=None):
            raise can.CanOperationError("bus off")

        def recv(self, timeout=None):
            raise OSError("gone")

        def shutdown(self):
            raise OSError("already closed")

    c = PiezoClient(BrokenBus(), CODEC, knives=4)
    with pytest.raises(FieldbusError, match="0x200"):
        c.tick(alive_counter=1, now_s=0.0)
    with pytest.raises(FieldbusError):
        c.poll(now_s=0.0)
    c.close()  # never raises
    assert c.send_errors == 1


@pytest.mark.parametrize("kw", [{"knives": 0}, {"knives": 9}, {"knives": 4, "stroke_um": -1}])
def test_bad_parameters(kw, buses):
    with pytest.raises(ValueError):
        PiezoClient(buses[0], CODEC, **kw)


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
    c = PiezoClient(bus, CODEC, knives=8, command_period_s=0.02)
    report_limits(c, stroke_um=10.0, now_s=0.0)
    c.set_enable(True, now_s=0.0)
    c.tick(alive_counter=1, now_s=0.0)
    c.set_offsets([1.0] * 8, now_s=0.001)
    c.send_command(alive_counter=2, now_s=0.002)
    assert len(bus.timeouts) == 1 + 2 + 2 + 1  # command, offsets (2 frames) twice, command
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
def test_the_smaller_stroke_is_used_and_said(config_um, amp_um, amp_range, limit, source):
    c = PiezoClient(can.Bus(interface="virtual", channel=f"lim-{next(_chan)}"), CODEC,
                    knives=4, stroke_um=config_um)
    try:
        # before the amplifier has reported its limits nothing but zeros goes out
        assert c.set_offsets([3.0, -3.0, 1.0, -1.0], now_s=0.0) == (0.0,) * 4
        lo, hi = amp_range or (None, None)
        report_limits(c, stroke_um=amp_um, lo=lo, hi=hi, now_s=0.01)
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
        # the same report again changes nothing and says nothing
        report_limits(c, stroke_um=amp_um, lo=lo, hi=hi, now_s=0.1)
        assert c.take_notes() == []
    finally:
        c.close()


def test_limits_are_read_anew_after_a_reconnect(buses):
    service, amp = buses
    c = PiezoClient(service, CODEC, knives=4, stroke_um=20.0, reconnect_after_s=0.3)
    report_limits(c, stroke_um=10.0, now_s=0.0)
    c.set_offsets([6.0, -6.0, 2.0, -2.0], now_s=0.0)
    c.take_notes()
    status = CODEC.encode_status(displacement_um=0.0, temperature_c=30.0, fault=0,
                                 state=STATE_ENABLED, alive_counter=1)
    c.handle(*status, now_s=0.25)  # a short gap: nothing changes
    assert c.reconnects == 0 and c.stroke_um == 10.0
    c.handle(*status, now_s=0.7)  # silent for 0.45 s: a reconnect, limits unknown again
    assert c.reconnects == 1 and c.stroke_um == 0.0 and c.offsets_um == (0.0,) * 4
    (note,) = c.take_notes()
    assert note.kind == "limits" and note.data["source"] == "unknown"
    # a replaced amplifier with a smaller stroke: the wish is re-planned inside it
    report_limits(c, stroke_um=4.0, now_s=0.71)
    assert c.stroke_um == 4.0
    _planned_ok(c.offsets_um, (6.0, -6.0, 2.0, -2.0), 4.0)


@pytest.mark.parametrize(
    ("signals", "word"),
    [
        ({"stroke_um": 0.0}, "stroke_um"),
        ({"offset_min_um": 1.0}, "offset_min_um"),
        ({"offset_max_um": -1.0}, "offset_max_um"),
    ],
)
def test_a_nonsense_limits_report_holds_the_offsets_at_zero(buses, signals, word):
    c = PiezoClient(buses[0], CODEC, knives=4, stroke_um=20.0)
    report_limits(c, stroke_um=10.0, now_s=0.0)
    c.set_offsets([5.0, -5.0, 0.0, 0.0], now_s=0.0)
    c.take_notes()
    good = {"stroke_um": 10.0, "offset_min_um": -10.0, "offset_max_um": 10.0,
            "setpoint_timeout_ms": 100}
    frame = CODEC.encode_limits(**{**good, **signals})
    c.handle(*frame, now_s=0.1)
    (note,) = c.take_notes()
    assert "invalid" in note.text and word in note.text
    assert c.stroke_um == 0.0 and c.offsets_um == (0.0,) * 4


def _refusing_status(now_s, c, *, fault=2):
    frame = CODEC.encode_status(displacement_um=0.0, temperature_c=30.0, fault=fault,
                                state=STATE_ENABLED, alive_counter=1)
    c.handle(*frame, now_s=now_s)


def test_a_refused_table_is_replanned_never_resent_unchanged(buses):
    """An amplifier that reports 10 um but takes only 3 um: each refusal narrows the bound."""
    service, amp = buses
    c = PiezoClient(service, CODEC, knives=4, stroke_um=20.0, refusal_grace_s=0.05)
    report_limits(c, stroke_um=10.0, now_s=0.0)
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
        sent = [CODEC.offsets_from(n, s) for n, s in drain(amp) if n == OFFSETS[0]]
        for table in sent:
            row = tuple(table[k] for k in range(4))
            assert row not in refused_tables, "a refused table went out again"
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
    c = PiezoClient(buses[0], CODEC, knives=4, stroke_um=20.0)
    report_limits(c, stroke_um=10.0, now_s=0.0)
    c.take_notes()
    c.set_offsets([0.0] * 4, now_s=0.0)
    _refusing_status(0.2, c)
    (note,) = c.take_notes()
    assert note.kind == "refused" and note.data["limit_um"] is None
    assert note.data["replanned_um"] is None and c.offsets_um == (0.0,) * 4
