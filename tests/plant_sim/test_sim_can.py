"""The piezo amplifier's CAN node over python-can (virtual bus; udp_multicast across processes)."""

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
from protocol import can_transport, piezo_can
from protocol.piezo_can import PiezoCodec
from tests.support.fake_machine import FakeMachine

CODEC = PiezoCodec.load()
_channels = itertools.count()
REPO = Path(__file__).resolve().parents[2]


class Rig:
    """Amplifier node and a service-side bus on one virtual channel, machine time by hand."""

    def __init__(self, knives: int = 4, **core_kw) -> None:
        channel = f"test-amp-{next(_channels)}"
        self.machine = FakeMachine(knives=knives)
        self.core = AmpNodeCore(self.machine, CODEC, knives=knives, **core_kw)
        self.node = AmpNode(can_transport.open_bus("virtual", channel), self.core, own_bus=True)
        self.service = can_transport.open_bus("virtual", channel)
        self.alive = 0

    def send(self, frame) -> None:
        fid, data = frame
        self.service.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))

    def command(self, enable: bool = True) -> None:
        self.alive = (self.alive + 1) % 256
        self.send(
            CODEC.encode_command(
                enable=enable, knives=self.machine.knives, alive_counter=self.alive
            )
        )

    def offsets(self, offs) -> None:
        for f in CODEC.encode_offsets(offs):
            self.send(f)

    def run(self, duration_s: float, *, step_s: float = 0.001, command_every_s=None):
        """Step machine time; returns the decoded frames the service received, with times."""
        out = []
        n = round(duration_s / step_s)
        every = None if command_every_s is None else round(command_every_s / step_s)
        for i in range(n):
            if every and i % every == 0:
                self.command()
            self.machine.advance(step_s)
            self.node.pump(self.machine.t_s)
            while (msg := self.service.recv(timeout=0.0)) is not None:
                out.append((self.machine.t_s, *CODEC.decode(msg.arbitration_id, bytes(msg.data))))
        return out

    def close(self) -> None:
        self.node.close()
        self.service.shutdown()


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


def test_offsets_of_six_knives_take_two_frames():
    r = Rig(knives=6)
    try:
        offs = [1.0, 2.0, 3.0, 4.0, 5.0, -6.0]
        r.offsets(offs)
        r.run(0.002)
        np.testing.assert_allclose(r.machine.offsets_um, offs, atol=1e-9)
        assert r.core.offsets_um[6:] == [0.0, 0.0]
    finally:
        r.close()


def test_status_every_10_ms_and_heartbeat_every_100_ms_of_machine_time(rig):
    frames = rig.run(1.0, command_every_s=0.02)
    status = [(t, s) for t, name, s in frames if name == "PIEZO_STATUS"]
    beats = [(t, s) for t, name, s in frames if name == "AMP_HEARTBEAT"]
    assert len(status) == 100 and len(beats) == 10
    ts = np.array([t for t, _ in status])
    np.testing.assert_allclose(np.diff(ts), piezo_can.STATUS_PERIOD_S, atol=1e-9)
    np.testing.assert_allclose(np.diff([t for t, _ in beats]), 0.1, atol=1e-9)
    alive = [s["alive_counter"] for _, s in status]
    assert all((b - a) % 256 == 1 for a, b in zip(alive[:-1], alive[1:], strict=True))
    assert all(s["nmt_state"] == piezo_can.NMT_OPERATIONAL for _, s in beats)
    assert all(s["state"] == piezo_can.STATE_ENABLED and s["fault"] == 0 for _, s in status)


def test_late_poll_does_not_burst(rig):
    rig.core.poll(0.0)
    assert len(rig.core.poll(0.5)) == 2  # one status, one heartbeat, not 50 + 5
    assert rig.core.poll(0.505) == []
    assert len(rig.core.poll(0.51)) == 1


def test_timeout_ramp_reported_when_commands_stop(rig):
    rig.command()
    rig.offsets([10.0, -5.0, 2.0, 0.0])
    rig.run(0.2, command_every_s=0.02)  # commands flowing: enabled, no fault
    rig_status = [s for _, n, s in rig.run(0.02, command_every_s=0.02) if n == "PIEZO_STATUS"]
    assert all(s["fault"] == 0 and s["state"] == 1 for s in rig_status)
    assert rig_status[-1]["displacement_um"] == pytest.approx(10.0)
    frames = rig.run(0.5)  # commands stop
    status = [(t, s) for t, n, s in frames if n == "PIEZO_STATUS"]
    timeout_s = rig.machine.timeout_s
    last_cmd = rig.machine.last_cmd_s
    after = [(t, s) for t, s in status if t > last_cmd + timeout_s + 0.002]
    assert after and all(s["fault"] & piezo_can.FAULT_SETPOINT_TIMEOUT for _, s in after)
    disp = np.array([s["displacement_um"] for _, s in after])
    assert np.all(np.diff(disp) <= 1e-9) and disp[-1] == 0.0
    ramping = [s["state"] for _, s in after if s["displacement_um"] > 0]
    assert ramping and all(st == piezo_can.STATE_RAMPING for st in ramping)
    # ramp rate as the machine says (50 um/s): 10 um take 0.2 s
    t_zero = next(t for t, s in after if s["displacement_um"] == 0.0)
    assert t_zero - (last_cmd + timeout_s) == pytest.approx(10.0 / 50.0, abs=0.015)


def test_drop_fraction_of_received_frames():
    r = Rig(seed=7)
    try:
        r.core.inject("drop_rx", fraction=0.5)
        n = 200  # below the 8-bit alive counter wrap
        for _ in range(n):
            r.command()
            r.machine.advance(0.001)
            r.node.pump(r.machine.t_s)
        got = len(r.machine.alive_counters)
        assert r.core.received == n and r.core.dropped == n - got
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
    status = [s for _, n, s in frames if n == "PIEZO_STATUS"]
    assert status[-1]["fault"] & piezo_can.FAULT_SETPOINT_TIMEOUT
    rig.run(0.05, command_every_s=0.01)  # the window is over: commands arrive again
    assert len(rig.machine.alive_counters) == n_before + 5


def test_silence_window_sends_nothing(rig):
    rig.run(0.05)
    rig.core.inject("silence", start_s=rig.machine.t_s, duration_s=0.2)
    assert rig.run(0.2) == []
    assert any(n == "PIEZO_STATUS" for _, n, _s in rig.run(0.02))
    with pytest.raises(ValueError, match="fault"):
        rig.core.inject("explode")
    with pytest.raises(ValueError, match="fraction"):
        rig.core.inject("drop_rx", fraction=1.5)


def test_offsets_beyond_stroke_refused_and_flagged(rig):
    rig.offsets([1.0, 2.0, 3.0, 4.0])
    rig.run(0.002)
    rig.offsets([1.0, 25.0, 3.0, 4.0])  # 25 um > 20 um stroke: inside the DBC range though
    frames = rig.run(0.011)
    np.testing.assert_allclose(rig.machine.offsets_um, [1.0, 2.0, 3.0, 4.0])
    assert rig.core.refused == 1
    assert [s for _, n, s in frames if n == "PIEZO_STATUS"][-1]["fault"] & 2
    rig.offsets([0.0, 0.0, 0.0, 0.0])
    frames = rig.run(0.011)
    assert not [s for _, n, s in frames if n == "PIEZO_STATUS"][-1]["fault"] & 2


def test_command_for_another_knife_count_refused(rig):
    rig.send(CODEC.encode_command(enable=True, knives=3, alive_counter=5))
    rig.run(0.001)
    assert rig.machine.alive_counters == [] and rig.core.refused == 1


def test_own_and_unknown_frames_ignored(rig):
    rig.send(
        CODEC.encode_status(
            displacement_um=1.0, temperature_c=20.0, fault=0, state=1, alive_counter=0
        )
    )
    rig.send((0x123, b"\x01\x02"))
    rig.send((CODEC.command_id, b"\x01"))  # too short
    rig.run(0.001)
    assert rig.core.ignored == 3 and rig.machine.alive_counters == []


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
    from protocol.piezo_can import PiezoCodec
    from plant_sim.interfaces.amp_node import AmpNode, AmpNodeCore
    assert in_private_netns()
    class M:
        offs = [0.0] * 4
        def piezo_command(self, *, enable, alive_counter): pass
        def set_piezo_offsets(self, o): self.offs = list(o)
        def piezo_status(self):
            return SimpleNamespace(displacement_um=max(self.offs), temperature_c=30.0,
                                   fault=0, state=1)
    node = AmpNode(open_bus("udp_multicast"), AmpNodeCore(M(), PiezoCodec.load(), knives=4),
                   own_bus=True)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 60.0:  # until the test kills it (a backstop, not a timing)
        node.pump(time.monotonic() - t0)
        time.sleep(0.001)
    node.close()
    """
)

SERVICE_SCRIPT = textwrap.dedent(
    """
    import sys, time, can
    from protocol.can_transport import open_bus
    from protocol.piezo_can import PiezoCodec
    codec = PiezoCodec.load()
    bus = open_bus("udp_multicast")
    t0 = time.monotonic(); n_status = 0; alive = 0
    while time.monotonic() - t0 < 40.0:  # a loaded machine may start the amplifier late
        alive = (alive + 1) % 256
        frames = [codec.encode_command(enable=True, knives=4, alive_counter=alive)]
        frames += codec.encode_offsets([1.5, -2.25, 3.125, 0.5])
        for fid, data in frames:
            bus.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
        end = time.monotonic() + 0.01
        while (msg := bus.recv(timeout=max(0.0, end - time.monotonic()))) is not None:
            if msg.arbitration_id != codec.status_id:
                continue  # our own frames come back too
            n_status += 1
            name, sig = codec.decode(msg.arbitration_id, bytes(msg.data))
            if sig["displacement_um"] == 3.125 and n_status >= 20:
                print("OK", n_status); bus.shutdown(); sys.exit(0)
    print("FAIL", n_status); bus.shutdown(); sys.exit(1)
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
