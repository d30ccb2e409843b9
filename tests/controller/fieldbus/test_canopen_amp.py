"""The piezo amplifiers as CANopen devices: the service's master against the simulator's nodes.

Both ends are the real ``canopen`` library over python-can (a virtual bus), built from the
shipped EDS: the master (:class:`AmpBus`, :class:`CanopenAmplifier`) polls its bus with the
service's time, the simulated nodes (:class:`AmpNodeCore`: ``canopen`` local nodes) run on machine
time, driven by a real machine model. Each step advances the machine, pumps the nodes and polls
the master, so a test runs on simulated time, deterministically. A third bus on the channel
records every frame (a candump).
"""

from __future__ import annotations

import itertools
import threading

import can
import canopen
import numpy as np
import pytest

from config.sim import default_sim
from controller.fieldbus.canopen_amp import AmpBus
from plant_sim.interfaces.amp_node import AmpNode, AmpNodeCore
from plant_sim.machine.machine import Machine
from protocol.piezo_canopen import (
    EMCY_CODES,
    LIMITS,
    AmpFault,
    AmpState,
    NmtState,
    describe_frame,
    load_od,
    um_from_nm,
)

_channels = itertools.count()


class Rig:
    """A master and ``n`` simulated amplifiers (nodes 2, 3, ...) on one virtual bus."""

    def __init__(self, n: int = 1, knives: int = 4, cfg=None) -> None:
        channel = f"canopen-test-{next(_channels)}"
        self.channel = channel
        cfg = cfg or default_sim()
        self.machines = [Machine(cfg, seed=i, render_images=False) for i in range(n)]
        core = AmpNodeCore(self.machines[0], knives=knives, node_id=2)
        for i, m in enumerate(self.machines[1:], 1):
            core.add_node(2 + i, m, knives=knives)
        self.core = core
        self.nodes = core.nodes
        self.sim = AmpNode(can.Bus(interface="virtual", channel=channel), core, own_bus=True)
        self.master = AmpBus(can.Bus(interface="virtual", channel=channel))
        self.amps = [self.master.amplifier(2 + i, knives=knives) for i in range(n)]
        self.spy = can.Bus(interface="virtual", channel=channel)
        self.inject = can.Bus(interface="virtual", channel=channel)
        self.t = 0.0
        self.frames: list[can.Message] = []

    def step(self, dt_s: float = 0.01, steps: int = 1) -> None:
        for _ in range(steps):
            self.t += dt_s
            for m in self.machines:
                m.advance(dt_s)
            self.sim.pump(self.t)
            self.master.poll(self.t)
        while (msg := self.spy.recv(timeout=0.0)) is not None:
            self.frames.append(msg)

    def start(self) -> None:
        """Until every node is operational and its master knows it (a heartbeat said so)."""
        for _ in range(100):
            self.step()
            if all(a.nmt_state is NmtState.OPERATIONAL for a in self.amps):
                return
        raise AssertionError("the nodes did not become operational")

    def close(self) -> None:
        for b in (self.spy, self.inject):
            b.shutdown()
        self.sim.close()
        self.master.close()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def test_the_libraries_own_master_reads_the_simulated_nodes_dictionary(rig):
    """An independent check: canopen's plain RemoteNode (blocking SDO, its own notifier thread),
    not our master, reads the simulated node's dictionary."""
    stop = threading.Event()

    def serve() -> None:  # the simulated node answers whatever arrives (machine time stands)
        while not stop.is_set():
            msg = rig.sim.bus.recv(timeout=0.05)
            if msg is not None:
                rig.core.on_frame(msg.arbitration_id, bytes(msg.data), rig.t)
                for fid, data in rig.core.poll(rig.t):
                    rig.sim.bus.send(can.Message(arbitration_id=fid, data=data,
                                                 is_extended_id=False))

    server = threading.Thread(target=serve, daemon=True)
    server.start()
    plain = canopen.Network(can.Bus(interface="virtual", channel=rig.channel))
    plain.connect()
    try:
        node = plain.add_node(2, load_od(2))
        node.sdo.RESPONSE_TIMEOUT = 5.0
        assert node.sdo[0x1018][1].raw == 0x539  # vendor id of the EDS
        assert node.sdo[0x1018][2].raw == 8  # product
        lim = rig.machines[0].amp.limits()
        assert node.sdo[LIMITS][1].raw == round(lim.stroke_um * 1000)
        assert node.sdo[LIMITS][2].raw == round(lim.offset_min_um * 1000)
        assert node.sdo[LIMITS][3].raw == round(lim.offset_max_um * 1000)
        assert node.sdo[LIMITS][5].raw == round(lim.setpoint_timeout_ms)
        assert node.sdo[0x1017].raw == 100
        st = rig.machines[0].piezo_status()
        assert node.sdo[0x2100][2].raw == round(st.temperature_c * 10)  # live status by SDO
        assert node.sdo[0x2100][4].raw == int(st.state)
        with pytest.raises(canopen.SdoAbortedError):
            node.sdo.upload(0x3000, 0)  # no such object: an abort, not silence
    finally:
        plain.disconnect()
        stop.set()
        server.join(5)


def test_the_master_reads_the_limits_by_sdo_then_starts_the_node():
    cfg = default_sim()
    import dataclasses

    cfg = dataclasses.replace(cfg, piezo=dataclasses.replace(cfg.piezo, stroke_um=7.5))
    rig = Rig(cfg=cfg)
    try:
        amp, node = rig.amps[0], rig.nodes[0]
        rig.step()
        assert node.nmt_state is NmtState.PRE_OPERATIONAL and amp.limits is None
        rig.start()
        assert amp.limits.stroke_um == pytest.approx(7.5, abs=1e-3)
        assert amp.limits.offset_min_um == pytest.approx(-7.5, abs=1e-3)
        assert amp.limits.setpoint_timeout_s == pytest.approx(
            rig.machines[0].amp.limits().setpoint_timeout_ms / 1000.0)
        assert amp.heartbeat_period_s == pytest.approx(0.1)
        assert amp.counts["sdo_reads"] == 6 and amp.counts["sdo_retries"] == 0
        decoded = [describe_frame(f.arbitration_id, f.data, {2: node.od}) for f in rig.frames]
        services = [d.service for d in decoded]
        # boot-up, heartbeat, then six reads answered in turn, and only then NMT start
        assert services.index("nmt") > max(i for i, s in enumerate(services) if s == "sdo_tx")
        assert services.count("sdo_rx") == services.count("sdo_tx") == 6
        assert decoded[0].service == "heartbeat" and decoded[0].fields == {"state": "BOOT_UP"}
    finally:
        rig.close()


def test_nmt_stop_and_the_heartbeat_carries_the_state(rig):
    amp, node = rig.amps[0], rig.nodes[0]
    rig.start()
    amp.stop()
    rig.step()
    assert node.nmt_state is NmtState.STOPPED
    rig.step(0.1)
    assert amp.nmt_state is NmtState.STOPPED
    before = node.pdos
    amp.set_offsets([1.0, -1.0, 0.5, -0.5])  # stopped: a table is not acted on
    rig.step()
    assert node.pdos == before and any(f.arbitration_id == 0x202 for f in rig.frames)
    statuses = amp.counts["statuses"]
    rig.step(0.01, steps=5)
    assert amp.counts["statuses"] == statuses  # and no status leaves a stopped node
    amp.start()  # read again and started again
    for _ in range(10):
        rig.step()
    assert node.nmt_state is NmtState.OPERATIONAL


def test_offset_tables_and_commands_reach_the_machine_and_the_status_comes_back(rig):
    rig.start()
    amp, machine = rig.amps[0], rig.machines[0]
    amp.command(enable=True, alive_counter=1)
    table = [1.5, -2.0, 0.25, 0.251]
    amp.set_offsets(table)
    rig.step()
    np.testing.assert_allclose(machine.amp.offsets_um, table, atol=5e-4)  # 1 nm per bit
    assert rig.core.last_command == {"enable": 1, "knives": 4, "alive_counter": 1}
    seen = amp.counts["statuses"]
    rig.step(0.01, steps=5)
    assert amp.counts["statuses"] == seen + 5  # every 10 ms of machine time
    st = machine.piezo_status()
    assert amp.status.temperature_c == pytest.approx(st.temperature_c, abs=0.05)
    assert int(amp.status.state) == int(st.state) and amp.status.t_s == pytest.approx(rig.t)


def test_the_status_is_the_librarys_own_reading_of_the_pdo(rig):
    """The status decoded from the PDO's bytes (its layout) is what ``var.raw`` reads, every
    frame: displacement, temperature, fault bits and state, with a table and a fault on."""
    rig.start()
    amp = rig.amps[0]
    amp.command(enable=True, alive_counter=1)
    amp.set_offsets([1.5, -2.0, 0.25, 0.251])
    pdo = amp.node.tpdo[1]
    seen = []
    pdo.add_callback(lambda p: seen.append((tuple(v.raw for v in p), amp.status)))
    for _ in range(8):
        rig.step()
    assert len(seen) >= 5
    for raws, status in seen:
        disp, temp, fault, state = raws
        assert status.displacement_um == um_from_nm(disp)
        assert status.temperature_c == temp / 10.0
        assert status.fault == AmpFault(fault & 0x0F)
        assert status.state == AmpState(min(state, AmpState.FAULT))


def test_a_silent_amplifier_is_lost_by_its_heartbeat_and_read_again_when_back(rig):
    rig.start()
    amp = rig.amps[0]
    rig.step(0.1, steps=3)
    assert not amp.lost(rig.t) and amp.limits is not None
    rig.core.inject("silence", start_s=rig.t, duration_s=0.45)
    rig.step(0.1, steps=2)
    assert not amp.lost(rig.t)  # 0.2 s of silence: within 3 heartbeat periods
    rig.step(0.1, steps=2)
    assert amp.lost(rig.t)
    rig.step(0.1)
    assert not amp.lost(rig.t) and amp.restarts == 1
    reads = amp.counts["sdo_reads"]
    for _ in range(10):
        rig.step()
    assert amp.counts["sdo_reads"] == reads + 5 and amp.limits is not None  # read anew


def test_a_node_reset_by_nmt_boots_again_and_is_read_and_started_again(rig):
    rig.start()
    amp, node = rig.amps[0], rig.nodes[0]
    amp.node.nmt.send_command(0x81)  # NMT reset node
    rig.step()
    assert amp.restarts == 1  # its boot-up said so
    for _ in range(10):
        rig.step()
    assert node.nmt_state is NmtState.OPERATIONAL and amp.limits is not None


def test_a_rising_fault_is_an_emergency_naming_it_and_its_end_a_reset(rig):
    rig.start()
    amp = rig.amps[0]
    amp.command(enable=True, alive_counter=1)
    amp.set_offsets([30.0, 0.0, 0.0, 0.0])  # inside the wire's range, beyond the stroke
    rig.step()
    assert rig.core.refused == 1 and AmpFault.STROKE_LIMIT in amp.status.fault
    (e,) = amp.take_emergencies()
    assert e.code == EMCY_CODES[AmpFault.STROKE_LIMIT] and e.fault is AmpFault.STROKE_LIMIT
    amp.command(enable=True, alive_counter=2)
    amp.set_offsets([0.0, 0.0, 0.0, 0.0])
    rig.step()
    (e,) = amp.take_emergencies()
    assert e.cleared and e.fault is None and amp.status.fault == AmpFault(0)


def test_the_setpoint_timeout_is_an_emergency_when_commands_stop(rig):
    rig.start()
    amp = rig.amps[0]
    for i in range(10):
        amp.command(enable=True, alive_counter=i)
        rig.step(0.02)
    amp.take_emergencies()
    rig.step(0.02, steps=10)  # 200 ms without a command: the amplifier ramps to zero
    assert AmpFault.SETPOINT_TIMEOUT in amp.status.fault
    assert [e.fault for e in amp.take_emergencies()] == [AmpFault.SETPOINT_TIMEOUT]


@pytest.mark.parametrize("frame", [
    can.Message(arbitration_id=0x182, data=b"\x01\x02\x03", is_extended_id=False),  # short TPDO
    can.Message(arbitration_id=0x702, data=b"\x05\x00", is_extended_id=False),  # long heartbeat
    can.Message(arbitration_id=0x123, data=b"\xff" * 8, is_extended_id=False),  # foreign id
    can.Message(arbitration_id=0x182, data=b"\x00" * 6, is_extended_id=True),  # extended id
    can.Message(arbitration_id=0x402, data=b"\x01\x04", is_extended_id=False),  # short command
    can.Message(arbitration_id=0x202, data=b"\x00" * 9, is_extended_id=False),  # long table
    can.Message(arbitration_id=0x000, data=b"\x01", is_extended_id=False),  # short NMT
])
def test_a_malformed_or_foreign_frame_changes_nothing_and_is_counted(rig, frame):
    rig.start()
    amp, node, machine = rig.amps[0], rig.nodes[0], rig.machines[0]
    amp.command(enable=True, alive_counter=1)
    amp.set_offsets([1.0, -1.0, 0.5, -0.5])
    rig.step()
    before = (amp.status, amp.nmt_state, amp.last_heard_s, dict(amp.counts),
              list(machine.amp.offsets_um), node.pdos, node.nmt_state, rig.core.last_command)
    counts, ignored = rig.master.counts, rig.core.ignored
    rig.inject.send(frame)
    rig.sim.receive(rig.t)  # both ends take it (no time passes, nothing is due)
    rig.master.poll(rig.t)
    after = (amp.status, amp.nmt_state, amp.last_heard_s, dict(amp.counts),
             list(machine.amp.offsets_um), node.pdos, node.nmt_state, rig.core.last_command)
    assert after == before
    m = rig.master.counts  # the master refuses it (ids it sends itself: counted as its own)
    refused = ("foreign", "malformed", "own")
    assert sum(m[k] for k in refused) == sum(counts[k] for k in refused) + 1
    assert rig.core.ignored == ignored + 1  # and so does the node


def test_several_amplifiers_share_one_bus():
    rig = Rig(n=3)
    try:
        rig.start()
        for i, amp in enumerate(rig.amps):
            amp.command(enable=True, alive_counter=i)
            amp.set_offsets([0.1 * (i + 1), 0.0, 0.0, -0.1 * (i + 1)])
        rig.step()
        for i, node in enumerate(rig.nodes):
            assert node.offsets_um[0] == pytest.approx(0.1 * (i + 1), abs=1e-3)
            assert rig.machines[i].amp.offsets_um[3] == pytest.approx(-0.1 * (i + 1), abs=1e-3)
        assert all(a.counts["statuses"] >= 1 for a in rig.amps)
        assert rig.master.counts["foreign"] == 0
    finally:
        rig.close()


def test_an_sdo_answer_lost_is_asked_again(rig):
    rig.core.inject("drop_rx", start_s=0.0, duration_s=0.025)  # the first read is lost
    rig.start()
    amp = rig.amps[0]
    assert amp.counts["sdo_retries"] >= 1 and amp.limits is not None


def test_every_frame_of_a_run_decodes_against_the_eds(rig):
    """A candump of a short run read against the EDS: every frame is a known service."""
    rig.start()
    amp = rig.amps[0]
    for i in range(20):
        amp.command(enable=True, alive_counter=i)
        amp.set_offsets([0.01 * i, -0.01 * i, 0.0, 0.0])
        rig.step()
    ods = {2: load_od(2)}
    decoded = [describe_frame(f.arbitration_id, f.data, ods) for f in rig.frames]
    assert all(d.service != "foreign" and d.problem is None for d in decoded), [
        d for d in decoded if d.service == "foreign" or d.problem]
    services = {d.service for d in decoded}
    assert {"nmt", "heartbeat", "sdo_rx", "sdo_tx", "rpdo1", "rpdo3", "tpdo1"} <= services
    tables = [d.fields for d in decoded if d.service == "rpdo1"]
    assert tables[-1]["Offset table.Offset knife 1"] == 190  # 0.19 um, 1 nm per bit
    statuses = [d.fields for d in decoded if d.service == "tpdo1"]
    st = rig.machines[0].piezo_status()
    assert statuses[-1]["Status.Temperature"] == round(st.temperature_c * 10)
    lines = [amp.describe(f.arbitration_id, f.data) for f in rig.frames[-3:]]
    assert all(line[:3].strip() for line in lines)


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


def test_a_poll_waits_for_the_sdo_answers_while_the_limits_are_read(rig):
    """A node that answers at once (here served on a thread of its own, as ``planer sim`` does)
    has its limits read within one poll; the wait ends with the last answer, not a fixed time."""
    rig.sim.pump(0.0)  # boot-up and the first heartbeat
    stop = threading.Event()

    def serve() -> None:
        while not stop.is_set():
            msg = rig.sim.bus.recv(timeout=0.05)
            if msg is not None:
                rig.core.on_frame(msg.arbitration_id, bytes(msg.data), 0.0)
                for fid, data in rig.core.poll(0.0):
                    rig.sim.bus.send(can.Message(arbitration_id=fid, data=data,
                                                 is_extended_id=False))

    server = threading.Thread(target=serve, daemon=True)
    server.start()
    try:
        rig.master.sdo_wait_s = 30.0  # a backstop for a loaded host
        rig.master.poll(0.0)
        amp = rig.amps[0]
        assert amp.limits is not None and not amp.reading
        assert amp.counts["sdo_reads"] == 6 and amp.counts["nmt_starts"] == 1
    finally:
        stop.set()
        server.join(5)


def test_the_status_decoded_when_asked_is_the_one_decoded_on_arrival():
    """Random TPDO1s to two amplifiers, one decoding through the library's ``var.raw`` on
    arrival (its layout withdrawn: the path of a map off the byte grid), one keeping the bytes
    until ``status`` is asked for: read after any number of frames, the same status, a new
    object after each new frame and the same one until then."""
    import random

    rng = random.Random(3)
    master = AmpBus(can.Bus(interface="virtual", channel=f"canopen-test-{next(_channels)}"))
    try:
        lazy, eager = master.amplifier(2), master.amplifier(3)
        eager._status_layout = None
        last = None
        for i in range(3000):
            data = bytes(rng.randrange(256) for _ in range(6))  # TPDO1: 2 + 2 + 1 + 1 bytes
            if rng.random() < 0.3:  # the states and faults a node sends
                data = data[:4] + bytes([rng.randrange(16), rng.randrange(5)])
            t = i * 0.001
            master.deliver(0x180 + 2, data, t)
            master.deliver(0x180 + 3, data, t)
            if rng.random() < 0.4:
                got = lazy.status
                assert got == eager.status and got.t_s == t
                disp, temp, fault, state = (v.raw for v in eager.node.tpdo[1])  # the library's
                assert (got.displacement_um, got.temperature_c, got.fault, got.state) == (
                    um_from_nm(disp), temp / 10.0, AmpFault(fault & 0x0F),
                    AmpState(min(state, AmpState.FAULT)))
                assert got is not last and lazy.status is got
                last = got
        assert lazy.counts["statuses"] == eager.counts["statuses"] == 3000
    finally:
        master.close()


def test_pdos_packed_in_one_struct_are_the_bytes_value_by_value():
    """RPDO1/2/3 packed by one ``struct`` each: for random values (in range, out of range,
    floats, bools, bytes (raw, even those int() would read), strings) the same frames and the
    same errors as each value through its object's ``encode_raw`` (the packers withdrawn)."""
    import random

    rng = random.Random(5)
    channel = f"canopen-test-{next(_channels)}"
    master = AmpBus(can.Bus(interface="virtual", channel=channel))
    spy = can.Bus(interface="virtual", channel=channel)
    try:
        fast, slow = master.amplifier(2), master.amplifier(3)
        assert all(p is not None for p in fast._packers.values())
        slow._packers = dict.fromkeys(slow._packers)

        def value(size: int):
            kind = rng.random()
            if kind < 0.7:
                return rng.randrange(-40000, 70000)
            # bytes of the object's size (others would resize the PDO's data for good)
            return rng.choice([rng.uniform(-5e4, 5e4), True, False, b"\x01" * size,
                               b"7" * size, bytearray(b"1" * size), "7", "x", None])

        def outcome(amp, no, values):
            try:
                amp._transmit(no, values)
            except Exception as exc:  # noqa: BLE001 - the error is what is compared
                return type(exc), bytes(amp.node.rpdo[no].data)
            msg = spy.recv(timeout=1.0)
            return msg.arbitration_id - amp.node_id, bytes(msg.data)

        seen = set()
        for _ in range(3000):
            no = rng.choice([1, 2, 3])
            values = [value(len(od) // 8) for _, od in fast._layouts[no]]
            if no == 3 and rng.random() < 0.5:  # what command() sends
                values = [rng.randrange(2), rng.randrange(1, 9), rng.randrange(256)]
            got = outcome(fast, no, values)
            assert got == outcome(slow, no, values), values
            seen.add(type(got[0]))
        assert seen == {int, type}  # frames sent and values refused
        assert spy.recv(timeout=0.0) is None
    finally:
        spy.shutdown()
        master.close()


@pytest.mark.parametrize("data_type,size", [(0x10, 3), (0x12, 5), (0x13, 6), (0x14, 7),
                                            (0x16, 3), (0x18, 5)])
def test_no_struct_for_objects_whose_struct_packs_more_bytes_than_they_have(
        data_type: int, size: int) -> None:
    """INTEGER24/40/48/56 (and unsigned): canopen's struct for them packs 4 or 8 bytes, so a
    PDO holding one goes value by value through ``encode_raw`` (no one-struct packer)."""
    from types import SimpleNamespace

    from canopen.objectdictionary import INTEGER16, ODVariable

    from controller.fieldbus.canopen_amp import _pdo_packer

    odd = ODVariable("odd", 0x2000, 1)
    odd.data_type = data_type
    plain = ODVariable("plain", 0x2000, 2)
    plain.data_type = INTEGER16
    assert len(odd) == 8 * size
    layout = ((0, odd), (size, plain))
    pdo = SimpleNamespace(data=bytearray(size + 2))
    assert _pdo_packer(pdo, layout) is None
    assert _pdo_packer(SimpleNamespace(data=bytearray(2)), ((0, plain),)) is not None
