"""A moulder's four amplifiers as CANopen nodes on ONE bus, driven by the MoulderDriver.

Both ends are the real ``canopen`` library over python-can (a virtual bus): the service's master
(:class:`controller.fieldbus.canopen_amp.AmpBus`, one amplifier per node id) and the simulator's
local nodes (:meth:`MoulderDriver.amp_core`: one node per head, each answering as its own id),
stepped on machine time (no sleeps).
"""

from __future__ import annotations

import itertools

import can
import pytest

from config.sim import load_sim
from controller.fieldbus.canopen_amp import AmpBus
from plant_sim.interfaces.amp_node import AmpNode
from plant_sim.machine.moulder import Moulder
from plant_sim.run.driver import MoulderDriver
from protocol.piezo_canopen import AmpFault, NmtState, cob_ids

_channels = itertools.count()


class MoulderRig:
    """The moulder, its driver with every amplifier on one bus, and a master for each node."""

    def __init__(self) -> None:
        channel = f"moulder-can-test-{next(_channels)}"
        self.moulder = Moulder(load_sim("config/sim_moulder.toml"), seed=1, render_images=False)
        self.core = MoulderDriver.amp_core(self.moulder)
        self.node = AmpNode(can.Bus(interface="virtual", channel=channel), self.core,
                            own_bus=True)
        self.driver = MoulderDriver(self.moulder, amp=self.node)
        self.master = AmpBus(can.Bus(interface="virtual", channel=channel))
        self.amps = {name: self.master.amplifier(nid, knives=self.moulder.heads[name].knives)
                     for name, nid in self.moulder.node_ids.items()}
        self.spy = can.Bus(interface="virtual", channel=channel)
        self.frames: list[can.Message] = []

    @property
    def t(self) -> float:
        return self.driver.t_s

    def step(self, dt_s: float = 0.01, steps: int = 1) -> None:
        for _ in range(steps):
            self.driver.step(dt_s)
            self.master.poll(self.t)
        while (msg := self.spy.recv(timeout=0.0)) is not None:
            self.frames.append(msg)

    def start(self) -> None:
        for _ in range(100):
            self.step()
            if all(a.nmt_state is NmtState.OPERATIONAL for a in self.amps.values()):
                return
        raise AssertionError("the nodes did not become operational")

    def close(self) -> None:
        self.spy.shutdown()
        self.node.close()
        self.master.close()


@pytest.fixture
def rig():
    r = MoulderRig()
    yield r
    r.close()


def test_each_head_is_its_own_node_on_the_one_bus(rig):
    assert [n.node_id for n in rig.core.nodes] == [2, 3, 4, 5]
    assert [n.knives for n in rig.core.nodes] == [4, 2, 2, 6]
    rig.start()
    heartbeats = {f.arbitration_id for f in rig.frames if 0x700 < f.arbitration_id <= 0x77F}
    assert heartbeats == {cob_ids(n)["heartbeat"] for n in (2, 3, 4, 5)}
    for amp in rig.amps.values():
        assert amp.limits is not None and amp.limits.stroke_um > 0


def test_a_table_for_one_node_reaches_only_its_head(rig):
    rig.start()
    for i, amp in enumerate(rig.amps.values()):
        amp.command(enable=True, alive_counter=i)
    rig.amps["right"].set_offsets([1.5, -1.0])
    rig.amps["top"].set_offsets([0.5, 0.0, 0.0, 0.0, 0.0, -0.5])
    rig.step()
    heads = rig.moulder.heads
    assert heads["right"].amp.offsets_um == pytest.approx([1.5, -1.0], abs=1e-3)
    assert heads["top"].amp.offsets_um == pytest.approx([0.5, 0, 0, 0, 0, -0.5], abs=1e-3)
    assert heads["bottom"].amp.offsets_um == pytest.approx([0.0] * 4)
    assert heads["left"].amp.offsets_um == pytest.approx([0.0] * 2)
    assert rig.core.refused == 0 and rig.master.counts["foreign"] == 0


def test_a_silenced_head_amplifier_is_lost_and_the_others_are_not(rig):
    rig.start()
    rig.step(0.1, steps=2)
    rig.driver.inject("can_silence", head="top", duration_s=1.0)
    assert rig.driver.faults == [f"can_silence[top]@{rig.t:.3f}"]
    rig.step(0.1, steps=5)
    lost = {name: amp.lost(rig.t) for name, amp in rig.amps.items()}
    assert lost == {"bottom": False, "right": False, "left": False, "top": True}
    rig.step(0.1, steps=8)
    assert not rig.amps["top"].lost(rig.t) and rig.amps["top"].restarts == 1
    assert all(rig.amps[n].restarts == 0 for n in ("bottom", "right", "left"))


def test_a_dropped_command_stream_times_out_only_that_head(rig):
    rig.start()

    def command(steps: int, first: int) -> None:
        for i in range(first, first + steps):
            for amp in rig.amps.values():
                amp.command(enable=True, alive_counter=i % 256)
            rig.step(0.02)

    command(10, 0)
    assert not any(AmpFault(h.piezo_status().fault) for h in rig.moulder.heads.values())
    rig.driver.inject("can_drop", head="left", duration_s=5.0)
    command(20, 10)
    timed_out = {name: AmpFault.SETPOINT_TIMEOUT in AmpFault(h.piezo_status().fault)
                 for name, h in rig.moulder.heads.items()}
    assert timed_out == {"bottom": False, "right": False, "left": True, "top": False}


def test_faults_from_the_moulder_reach_the_driver_by_head(rig):
    rig.start()
    rig.moulder.inject("can_silence", head="right", duration_s=0.5, at_s=rig.t + 0.05)
    rig.step(0.05, steps=3)
    assert rig.driver.faults and rig.driver.faults[0].startswith("can_silence[right]@")
    with pytest.raises(ValueError, match="head must be one of"):
        rig.driver.inject("can_drop", head="side", duration_s=1.0)


def test_a_registry_can_fault_plays_as_the_nodes_own_on_one_node_or_all(rig):
    """AmpNodeCore.play: the one mapping of can_drop / can_silence (driver and HIL alike)."""
    from plant_sim.interfaces.amp_node import _Window

    core = rig.core
    core.play("can_drop", {"fraction": 0.5, "duration_s": 2.0}, start_s=1.0, node_id=5)
    core.play("can_silence", {"duration_s": 0.5}, start_s=4.0)
    assert core._drop == [_Window(1.0, 3.0, 0.5, 5)]
    assert core._silence == [_Window(4.0, 4.5, 1.0, None)]
    with pytest.raises(ValueError, match="fault must be one of can_drop, can_silence"):
        core.play("modbus_restart", {"duration_s": 1.0}, start_s=0.0)
    # the driver's moulder fault on a head and on every node go through it
    core.inject("clear")
    rig.driver.inject("can_drop", head="right", fraction=0.25, duration_s=1.0)
    rig.driver.inject("can_silence", duration_s=1.0)
    t = rig.t
    assert core._drop == [_Window(t, t + 1.0, 0.25, 3)]
    assert core._silence == [_Window(t, t + 1.0, 1.0, None)]
    assert rig.driver.faults == [f"can_drop[right]@{t:.3f}", f"can_silence@{t:.3f}"]
