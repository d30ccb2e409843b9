"""The piezo amplifiers as CANopen devices: the service's master against the simulator's nodes.

Both ends are the real ``canopen`` library over python-can (a virtual bus: the two notifiers'
threads deliver the frames), built from the shipped EDS. The simulated nodes are driven by a
real machine model; time on the node side is the machine's (``pump``), the master stamps with
its own clock. Waiting is for frames, never a fixed time.
"""

from __future__ import annotations

import itertools
import threading
import time

import can
import canopen
import numpy as np
import pytest

from config.sim import default_sim
from controller.fieldbus.canopen_amp import AmpBus
from plant_sim.interfaces.canopen_node import CanopenAmpNode, SlaveBus
from plant_sim.machine.machine import Machine
from protocol.piezo_canopen import (
    EMCY_CODES,
    LIMITS,
    AmpFault,
    NmtState,
    describe_frame,
    load_od,
)

_channels = itertools.count()


class _Frames(can.Listener):
    """Every frame on the bus (a candump), and a condition to wait on."""

    def __init__(self) -> None:
        self.frames: list[can.Message] = []
        self.cond = threading.Condition()

    def on_message_received(self, msg: can.Message) -> None:
        with self.cond:
            self.frames.append(msg)
            self.cond.notify_all()

    def until(self, pred, timeout_s: float = 10.0) -> None:
        end = time.monotonic() + timeout_s
        with self.cond:
            while not pred():
                left = end - time.monotonic()
                assert left > 0, "the condition did not come true while frames arrived"
                self.cond.wait(min(left, 0.05))


class Rig:
    """A master and ``n`` simulated amplifiers (nodes 2, 3, ...) on one virtual bus."""

    def __init__(self, n: int = 1, knives: int = 4) -> None:
        channel = f"canopen-test-{next(_channels)}"
        self.channel = channel
        self.t = 0.0
        self.master = AmpBus(can.Bus(interface="virtual", channel=channel),
                             clock=lambda: self.t)
        self.slaves = SlaveBus(can.Bus(interface="virtual", channel=channel))
        self.spy_bus = can.Bus(interface="virtual", channel=channel)
        self.spy = _Frames()
        self.notifier = can.Notifier(self.spy_bus, [self.spy], 0.05)
        self.machines = [Machine(default_sim(), seed=i, render_images=False) for i in range(n)]
        self.nodes = [CanopenAmpNode(self.slaves, 2 + i, m, knives=knives)
                      for i, m in enumerate(self.machines)]
        self.amps = [self.master.amplifier(2 + i, knives=knives) for i in range(n)]
        self.inject = can.Bus(interface="virtual", channel=channel)

    def pump(self, dt_s: float = 0.01, steps: int = 1) -> None:
        for _ in range(steps):
            self.t += dt_s
            for m in self.machines:
                m.advance(dt_s)
            self.slaves.pump(self.t)

    def close(self) -> None:
        self.notifier.stop()
        for b in (self.spy_bus, self.inject):
            b.shutdown()
        self.slaves.close()
        self.master.close()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def _started(rig: Rig) -> None:
    for amp in rig.amps:
        amp.start()
    rig.spy.until(lambda: all(n.nmt_state is NmtState.OPERATIONAL for n in rig.nodes))
    rig.pump(0.1)  # a heartbeat period: each node says so
    rig.spy.until(lambda: all(a.nmt_state is NmtState.OPERATIONAL for a in rig.amps))


def test_the_libraries_own_master_reads_the_simulated_nodes_dictionary(rig):
    """An independent check: canopen's plain RemoteNode, not our client, reads the node."""
    plain = canopen.Network(can.Bus(interface="virtual", channel=rig.channel))
    plain.connect()
    try:
        node = plain.add_node(2, load_od(2))
        node.sdo.RESPONSE_TIMEOUT = 2.0
        assert node.sdo[0x1018][1].raw == 0x539  # vendor id of the EDS
        lim = rig.machines[0].amp.limits()
        assert node.sdo[LIMITS][1].raw == round(lim.stroke_um * 1000)
        assert node.sdo[LIMITS][5].raw == round(lim.setpoint_timeout_ms)
        assert node.sdo[0x1017].raw == 100
    finally:
        plain.disconnect()


def test_nmt_start_and_stop_and_the_heartbeat_carries_the_state(rig):
    amp = rig.amps[0]
    rig.pump()
    rig.spy.until(lambda: amp.nmt_state is NmtState.PRE_OPERATIONAL)
    limits = amp.start()
    assert limits.stroke_um == pytest.approx(rig.machines[0].amp.limits().stroke_um, abs=1e-3)
    rig.spy.until(lambda: rig.nodes[0].nmt_state is NmtState.OPERATIONAL)
    rig.pump(0.1)
    rig.spy.until(lambda: amp.nmt_state is NmtState.OPERATIONAL)
    amp.stop()
    rig.spy.until(lambda: rig.nodes[0].nmt_state is NmtState.STOPPED)
    rig.pump(0.1)
    rig.spy.until(lambda: amp.nmt_state is NmtState.STOPPED)
    # stopped: a table is not acted on
    before = rig.nodes[0].pdos
    amp.set_offsets([1.0, -1.0, 0.5, -0.5])
    rig.spy.until(lambda: any(f.arbitration_id == 0x202 for f in rig.spy.frames))
    assert rig.nodes[0].pdos == before


def test_offset_tables_and_commands_reach_the_machine_and_the_status_comes_back(rig):
    _started(rig)
    amp, machine = rig.amps[0], rig.machines[0]
    amp.command(enable=True, alive_counter=1)
    table = [1.5, -2.0, 0.25, 0.251]
    amp.set_offsets(table)
    rig.spy.until(lambda: rig.nodes[0].pdos >= 2)
    np.testing.assert_allclose(machine.amp.offsets_um, table, atol=5e-4)  # 1 nm per bit
    seen = amp.counts["statuses"]
    rig.pump(0.01, steps=5)
    rig.spy.until(lambda: amp.counts["statuses"] >= seen + 5)
    st = machine.piezo_status()
    assert amp.status.temperature_c == pytest.approx(st.temperature_c, abs=0.05)
    assert int(amp.status.state) == int(st.state)


def test_a_silent_amplifier_is_lost_by_its_heartbeat(rig):
    _started(rig)
    amp = rig.amps[0]
    rig.pump(0.1, steps=3)
    rig.spy.until(lambda: amp.last_heard_s is not None and amp.last_heard_s >= 0.3 - 1e-9)
    assert not amp.lost(rig.t)
    rig.nodes[0].silent = True
    rig.pump(0.1, steps=2)
    assert not amp.lost(rig.t)  # 0.2 s of silence: within 3 heartbeat periods
    rig.pump(0.1, steps=2)
    assert amp.lost(rig.t)
    rig.nodes[0].silent = False
    rig.pump(0.1)
    rig.spy.until(lambda: not amp.lost(rig.t))


def test_a_rising_fault_is_an_emergency_naming_it_and_its_end_a_reset(rig):
    _started(rig)
    amp, node = rig.amps[0], rig.nodes[0]
    node._stroke_fault = True  # what a refused table sets
    rig.pump()
    rig.spy.until(lambda: amp.counts["emergencies"] >= 1)
    (e,) = amp.take_emergencies()
    assert e.code == EMCY_CODES[AmpFault.STROKE_LIMIT] and e.fault is AmpFault.STROKE_LIMIT
    node._stroke_fault = False
    rig.pump()
    rig.spy.until(lambda: amp.counts["emergencies"] >= 2)
    (e,) = amp.take_emergencies()
    assert e.cleared and e.fault is None


def test_a_table_beyond_the_range_is_refused_and_raises_the_stroke_bit(rig):
    _started(rig)
    amp = rig.amps[0]
    amp.command(enable=True, alive_counter=1)
    amp.set_offsets([30.0, 0.0, 0.0, 0.0])  # inside the wire's range, beyond the stroke
    rig.spy.until(lambda: rig.nodes[0].refused >= 1)
    rig.pump()
    rig.spy.until(lambda: amp.status is not None and AmpFault.STROKE_LIMIT in amp.status.fault)


@pytest.mark.parametrize("frame", [
    can.Message(arbitration_id=0x182, data=b"\x01\x02\x03", is_extended_id=False),  # short TPDO
    can.Message(arbitration_id=0x702, data=b"\x05\x00", is_extended_id=False),  # long heartbeat
    can.Message(arbitration_id=0x123, data=b"\xff" * 8, is_extended_id=False),  # foreign id
    can.Message(arbitration_id=0x182, data=b"\x00" * 6, is_extended_id=True),  # extended id
])
def test_a_malformed_or_foreign_frame_changes_nothing_and_is_counted(rig, frame):
    _started(rig)
    amp = rig.amps[0]
    seen = amp.counts["statuses"]
    rig.pump()  # one status (no heartbeat due): wait until the master has it
    rig.spy.until(lambda: amp.counts["statuses"] > seen)
    before = (amp.status, amp.nmt_state, amp.last_heard_s, dict(amp.counts))
    counts = rig.master.counts
    rig.inject.send(frame)
    rig.spy.until(lambda: rig.master.counts["frames"] > counts["frames"])
    after = rig.master.counts
    assert after["foreign"] + after["malformed"] == counts["foreign"] + counts["malformed"] + 1
    assert (amp.status, amp.nmt_state, amp.last_heard_s, dict(amp.counts)) == before


def test_several_amplifiers_share_one_bus():
    rig = Rig(n=3)
    try:
        _started(rig)
        for i, amp in enumerate(rig.amps):
            amp.command(enable=True, alive_counter=i)
            amp.set_offsets([0.1 * (i + 1), 0.0, 0.0, -0.1 * (i + 1)])
        rig.spy.until(lambda: all(n.pdos >= 2 for n in rig.nodes))
        for i, node in enumerate(rig.nodes):
            assert node.offsets_um[0] == pytest.approx(0.1 * (i + 1), abs=1e-3)
    finally:
        rig.close()


def test_every_frame_of_a_run_decodes_against_the_eds(rig):
    """A candump of a short run read against the EDS: every frame is a known service."""
    _started(rig)
    amp = rig.amps[0]
    for i in range(20):
        amp.command(enable=True, alive_counter=i)
        amp.set_offsets([0.01 * i, -0.01 * i, 0.0, 0.0])
        rig.pump()
    rig.spy.until(lambda: sum(f.arbitration_id == 0x182 for f in rig.spy.frames) >= 20)
    ods = {2: load_od(2)}
    decoded = [describe_frame(f.arbitration_id, f.data, ods) for f in list(rig.spy.frames)]
    assert all(d.service != "foreign" and d.problem is None for d in decoded), [
        d for d in decoded if d.service == "foreign" or d.problem]
    services = {d.service for d in decoded}
    assert {"nmt", "heartbeat", "sdo_rx", "sdo_tx", "rpdo1", "rpdo3", "tpdo1"} <= services
    tables = [d.fields for d in decoded if d.service == "rpdo1"]
    assert tables[-1]["Offset table.Offset knife 1"] == 190  # 0.19 um, 1 nm per bit


def test_describe_frame_names_what_does_not_fit():
    ods = {2: load_od(2)}
    assert describe_frame(0x182, b"\x00", ods).problem.startswith("1 bytes")
    assert describe_frame(0x183, b"\x00" * 6, ods).service == "foreign"  # node 3 unknown
    assert describe_frame(0x702, b"\x05", ods).fields == {"state": "OPERATIONAL"}
    assert describe_frame(0x082, bytes([0x10, 0x42, 1, 0, 0, 0, 0, 0]), ods).fields["code"] \
        == "0x4210"


@pytest.mark.parametrize("node_id", [0, 128, -1, True, 2.0])
def test_a_bad_node_id_is_refused_naming_it(node_id):
    with pytest.raises(ValueError, match="node_id"):
        load_od(node_id)
