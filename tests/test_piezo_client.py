"""Piezo CAN client over python-can's virtual bus: cyclic frames, offsets, status, silence."""

from __future__ import annotations

import itertools

import can
import pytest

from controller.piezo_client import PiezoClient
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


def test_command_is_cyclic_and_offsets_on_change_and_periodic(buses):
    service, amp = buses
    c = PiezoClient(service, CODEC, knives=4, command_period_s=0.02, offsets_period_s=0.2)
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
    # a change goes out at once, clamped to the stroke and rounded to 0.001 um
    sent = c.set_offsets([1.23456, -3.0, 50.0, 0.0], now_s=t + 0.001)
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
    c.set_enable(True, now_s=0.0)
    c.tick(alive_counter=1, now_s=0.0)
    c.set_offsets([1.0] * 8, now_s=0.001)
    c.send_command(alive_counter=2, now_s=0.002)
    assert len(bus.timeouts) == 1 + 2 + 2 + 1  # command, offsets (2 frames) twice, command
    assert all(t is not None and 0 < t <= 0.01 for t in bus.timeouts)
    assert c.send_timeout_s <= c.command_period_s / 2
