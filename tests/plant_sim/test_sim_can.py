"""The simulated piezo amplifier (a CANopen node) over python-can (virtual bus; udp_multicast
across processes), driven by hand-packed frames (``tests/support/canopen_frames.py``)."""

from __future__ import annotations

import itertools
import subprocess
import sys
import textwrap
from pathlib import Path

import can
import numpy as np
import pytest

from core.errors import FieldbusError
from plant_sim.interfaces.amp_node import AmpNode, AmpNodeCore
from protocol import can_transport
from protocol.piezo_canopen import AmpFault, AmpState, NmtState
from tests.support import canopen_frames as cf
from tests.support.fake_machine import FakeMachine

_channels = itertools.count()
REPO = Path(__file__).resolve().parents[2]
STATUS, HEARTBEAT = 0x182, 0x702


class Rig:
    """Amplifier node and a master's bus on one virtual channel, machine time by hand."""

    def __init__(self, knives: int = 4, *, start: bool = True, **core_kw) -> None:
        channel = f"test-amp-{next(_channels)}"
        self.machine = FakeMachine(knives=knives)
        self.core = AmpNodeCore(self.machine, knives=knives, **core_kw)
        self.node = AmpNode(can_transport.open_bus("virtual", channel), self.core, own_bus=True)
        self.service = can_transport.open_bus("virtual", channel)
        self.alive = 0
        if start:
            self.send(cf.start())

    def send(self, frame) -> None:
        fid, data = frame
        self.service.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))

    def command(self, enable: bool = True) -> None:
        self.alive = (self.alive + 1) % 256
        self.send(cf.command(enable, self.machine.knives, self.alive))

    def offsets(self, offs) -> None:
        for f in cf.offsets(offs):
            self.send(f)

    def run(self, duration_s: float, *, step_s: float = 0.001, command_every_s=None):
        """Step machine time; the frames the master received: ``(t, id, data)``."""
        out = []
        n = round(duration_s / step_s)
        every = None if command_every_s is None else round(command_every_s / step_s)
        for i in range(n):
            if every and i % every == 0:
                self.command()
            self.machine.advance(step_s)
            self.node.pump(self.machine.t_s)
            while (msg := self.service.recv(timeout=0.0)) is not None:
                out.append((self.machine.t_s, msg.arbitration_id, bytes(msg.data)))
        return out

    def close(self) -> None:
        self.node.close()
        self.service.shutdown()


def statuses(frames):
    return [(t, cf.status(d)) for t, fid, d in frames if fid == STATUS]


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def test_offsets_reach_the_machine(rig):
    offs = [1.5, -2.25, 3.001, -0.0004]
    rig.command()
    rig.offsets(offs)
    rig.run(0.002)
    assert rig.machine.enable and rig.machine.alive_counters == [1]
    np.testing.assert_allclose(rig.machine.offsets_um, offs, atol=0.0005 + 1e-12)


def test_offsets_of_six_knives_take_two_pdos():
    r = Rig(knives=6)
    try:
        offs = [1.0, 2.0, 3.0, 4.0, 5.0, -6.0]
        r.offsets(offs)
        r.run(0.002)
        np.testing.assert_allclose(r.machine.offsets_um, offs, atol=1e-9)
        assert r.core.offsets_um[6:] == [0.0, 0.0]
    finally:
        r.close()


def test_before_nmt_start_only_heartbeats_and_no_pdo_is_acted_on():
    r = Rig(start=False)
    try:
        r.command()
        r.offsets([1.0, 1.0, 1.0, 1.0])
        frames = r.run(0.3)
        assert r.machine.alive_counters == [] and list(r.machine.offsets_um) == [0.0] * 4
        assert [fid for _, fid, _ in frames] == [HEARTBEAT] * 4  # boot-up + 0, 0.1, 0.2 s
        assert [d for _, _, d in frames] == [bytes([0])] + [bytes([127])] * 3
        assert r.core.node.nmt_state is NmtState.PRE_OPERATIONAL
    finally:
        r.close()


def test_status_every_10_ms_and_heartbeat_every_100_ms_of_machine_time(rig):
    frames = rig.run(1.0, command_every_s=0.02)
    status = statuses(frames)
    beats = [(t, d) for t, fid, d in frames if fid == HEARTBEAT]
    assert len(status) == 100 and len(beats) == 1 + 10  # the boot-up, then every 100 ms
    np.testing.assert_allclose(np.diff([t for t, _ in status]), 0.01, atol=1e-9)
    np.testing.assert_allclose(np.diff([t for t, _ in beats[1:]]), 0.1, atol=1e-9)
    assert all(d == bytes([NmtState.OPERATIONAL]) for _, d in beats[2:])
    assert all(s["state"] == AmpState.ENABLED and s["fault"] == 0 for _, s in status[2:])


def test_late_poll_does_not_burst(rig):
    rig.node.receive(0.0)  # NMT start
    rig.core.poll(0.0)
    assert len(rig.core.poll(0.5)) == 2  # one status, one heartbeat, not 50 + 5
    assert rig.core.poll(0.505) == []
    assert len(rig.core.poll(0.51)) == 1


def test_timeout_ramp_reported_when_commands_stop(rig):
    rig.command()
    rig.offsets([10.0, -5.0, 2.0, 0.0])
    rig.run(0.2, command_every_s=0.02)  # commands flowing: enabled, no fault
    flowing = [s for _, s in statuses(rig.run(0.02, command_every_s=0.02))]
    assert all(s["fault"] == 0 and s["state"] == 1 for s in flowing)
    assert flowing[-1]["displacement_nm"] == 10000
    status = statuses(rig.run(0.5))  # commands stop
    timeout_s = rig.machine.timeout_s
    last_cmd = rig.machine.last_cmd_s
    after = [(t, s) for t, s in status if t > last_cmd + timeout_s + 0.002]
    assert after and all(s["fault"] & AmpFault.SETPOINT_TIMEOUT for _, s in after)
    disp = np.array([s["displacement_nm"] for _, s in after])
    assert np.all(np.diff(disp) <= 0) and disp[-1] == 0
    ramping = [s["state"] for _, s in after if s["displacement_nm"] > 0]
    assert ramping and all(st == AmpState.RAMPING for st in ramping)
    # ramp rate as the machine says (50 um/s): 10 um take 0.2 s
    t_zero = next(t for t, s in after if s["displacement_nm"] == 0)
    assert t_zero - (last_cmd + timeout_s) == pytest.approx(10.0 / 50.0, abs=0.015)
    emcy = [d for _, fid, d in rig.run(0.001) if fid == 0x082]
    assert emcy == []  # the setpoint timeout's EMCY went out once, when it rose


def test_drop_fraction_of_received_frames():
    r = Rig(seed=7)
    try:
        r.run(0.001)  # the start gets through
        r.core.inject("drop_rx", fraction=0.5)
        n = 200  # below the 8-bit alive counter wrap
        for _ in range(n):
            r.command()
            r.machine.advance(0.001)
            r.node.pump(r.machine.t_s)
        got = len(r.machine.alive_counters)
        assert r.core.received == n + 1 and r.core.dropped == n - got
        assert 0.4 * n < r.core.dropped < 0.6 * n
        # the commands that did arrive are exactly the ones not dropped, in order
        assert r.machine.alive_counters == sorted(r.machine.alive_counters)
    finally:
        r.close()


def test_drop_window_loses_the_commands_inside_it_and_times_out(rig):
    rig.run(0.1, command_every_s=0.01)
    n_before = len(rig.machine.alive_counters)
    rig.core.inject("drop_rx", start_s=rig.machine.t_s, duration_s=0.3)
    frames = rig.run(0.3, command_every_s=0.01)
    assert len(rig.machine.alive_counters) == n_before  # none got through
    assert rig.core.dropped == 30
    assert statuses(frames)[-1][1]["fault"] & AmpFault.SETPOINT_TIMEOUT
    rig.run(0.05, command_every_s=0.01)  # the window is over: commands arrive again
    assert len(rig.machine.alive_counters) == n_before + 5


def test_silence_window_sends_nothing(rig):
    rig.run(0.05)
    rig.core.inject("silence", start_s=rig.machine.t_s, duration_s=0.2)
    rig.send(cf.sdo_read(0x1018, 1))  # not even an SDO answer
    assert rig.run(0.2) == []
    assert statuses(rig.run(0.02))
    with pytest.raises(ValueError, match="fault"):
        rig.core.inject("explode")
    with pytest.raises(ValueError, match="fraction"):
        rig.core.inject("drop_rx", fraction=1.5)


def test_offsets_beyond_stroke_refused_and_flagged(rig):
    rig.offsets([1.0, 2.0, 3.0, 4.0])
    rig.run(0.002)
    rig.offsets([1.0, 25.0, 3.0, 4.0])  # 25 um > 20 um stroke: inside the wire's range though
    frames = rig.run(0.011)
    np.testing.assert_allclose(rig.machine.offsets_um, [1.0, 2.0, 3.0, 4.0])
    assert rig.core.refused == 1
    assert statuses(frames)[-1][1]["fault"] & AmpFault.STROKE_LIMIT
    assert (0x082, bytes([0x01, 0xFF, 1, 0, 0, 0, 0, 0])) in [(f, d) for _, f, d in frames]
    rig.offsets([0.0, 0.0, 0.0, 0.0])
    frames = rig.run(0.011)
    assert not statuses(frames)[-1][1]["fault"] & AmpFault.STROKE_LIMIT


def test_command_for_another_knife_count_refused(rig):
    rig.send(cf.command(True, 3, 5))
    rig.run(0.001)
    assert rig.machine.alive_counters == [] and rig.core.refused == 1
    assert rig.core.last_command == {"enable": 1, "knives": 3, "alive_counter": 5}


def test_own_unknown_and_malformed_frames_ignored(rig):
    rig.run(0.001)
    ignored = rig.core.ignored
    rig.send(cf.status_frame())  # its own status, echoed
    rig.send((0x123, b"\x01\x02"))  # no service of the node
    rig.send((0x402, b"\x01"))  # a command too short
    rig.send((0x403, b"\x01\x04\x01"))  # another node's command
    rig.run(0.001)
    assert rig.core.ignored == ignored + 4 and rig.machine.alive_counters == []


def test_the_limits_are_read_by_sdo(rig):
    rig.send(cf.sdo_read(0x2200, 1))
    rig.send(cf.sdo_read(0x2200, 5))
    answers = [(fid, d) for _, fid, d in rig.run(0.001) if fid == 0x582]
    assert answers == [cf.answer(0x2200, 1, (20000).to_bytes(2, "little")),
                       cf.answer(0x2200, 5, (100).to_bytes(2, "little"))]


def test_open_bus_errors():
    with pytest.raises(FieldbusError):
        can_transport.open_bus("no_such_interface", "x")
    if not can_transport.only_loopback():
        with pytest.raises(FieldbusError, match="namespace"):
            can_transport.open_bus("udp_multicast")
    argv = can_transport.netns_argv(["echo", "a b"])
    assert argv[0] == "unshare" and argv[1] in ("-rn", "-n") and argv[-2:] == ["echo", "a b"]
    with pytest.raises(ValueError):
        can_transport.netns_argv([])


# ---------------------------------------------------------------------- across processes
AMP_SCRIPT = textwrap.dedent(
    """
    import time
    from types import SimpleNamespace
    from protocol.can_transport import open_bus, in_private_netns
    from plant_sim.interfaces.amp_node import AmpNode, AmpNodeCore
    assert in_private_netns()
    class M:
        offs = [0.0] * 4
        def piezo_command(self, *, enable, alive_counter): pass
        def set_piezo_offsets(self, o): self.offs = list(o)
        def piezo_status(self):
            return SimpleNamespace(displacement_um=max(self.offs), temperature_c=30.0,
                                   fault=0, state=1)
    node = AmpNode(open_bus("udp_multicast"), AmpNodeCore(M(), knives=4), own_bus=True)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 60.0:  # until the test kills it (a backstop, not a timing)
        node.pump(time.monotonic() - t0)
        time.sleep(0.001)
    node.close()
    """
)

SERVICE_SCRIPT = textwrap.dedent(
    """
    import sys, time
    from protocol.can_transport import open_bus
    from controller.fieldbus.piezo_client import PiezoClient
    c = PiezoClient(open_bus("udp_multicast"), knives=4)
    t0 = time.monotonic(); alive = 0; n_status = 0; seen = None
    while time.monotonic() - t0 < 40.0:  # a loaded machine may start the amplifier late
        now = time.monotonic() - t0
        c.poll(now_s=now)
        alive += 1
        c.set_enable(True, now_s=now)
        c.set_offsets([1.5, -2.25, 3.125, 0.5], now_s=now)
        c.tick(alive_counter=alive, now_s=now)
        if c.status is not None and c.status is not seen:
            seen = c.status; n_status += 1
            if seen.displacement_um == 3.125 and n_status >= 20 and c.stroke_um == 20.0:
                print("OK", n_status, c.counts); c.close(); sys.exit(0)
        time.sleep(0.005)
    print("FAIL", n_status, c.stroke_um, c.counts); c.close(); sys.exit(1)
    """
)


def test_udp_multicast_between_two_processes_in_a_private_netns():
    if not can_transport.private_netns_available():
        pytest.skip("unshare -rn is not permitted here")
    try:
        import msgpack  # noqa: F401
    except ImportError:
        pytest.skip("udp_multicast needs msgpack (python-can[multicast]), not installed")
    py = sys.executable
    script = (
        f'"{py}" -c "$AMP" & amp=$!; sleep 0.3; "{py}" -c "$SVC"; rc=$?; '
        "kill $amp 2>/dev/null; wait $amp 2>/dev/null; exit $rc"
    )
    env = {**__import__("os").environ, "AMP": AMP_SCRIPT, "SVC": SERVICE_SCRIPT}
    proc = can_transport.run_in_private_netns(
        ["sh", "-c", script],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, (out, err)
    assert out.startswith("OK")
