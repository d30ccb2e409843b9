"""The simulated amplifier's PDOs packed and unpacked by byte range (CanopenAmpNode._slots) are
pinned to the library's per-variable ``var.raw`` path they replace: for any sequence of received
frames, NMT commands and statuses, a node with the byte ranges and one without send the same
frames and hand the machine the same commands and offsets."""

from __future__ import annotations

from types import SimpleNamespace

from hypothesis import given, settings
from hypothesis import strategies as st

from plant_sim.interfaces.amp_node import AmpNodeCore
from protocol.piezo_canopen import cob_ids
from tests.support.fake_machine import FakeMachine

NODE = 2
IDS = cob_ids(NODE)


class StatusMachine(FakeMachine):
    """A fake machine whose amplifier status the test sets (no random numbers drawn)."""

    status = SimpleNamespace(displacement_um=0.0, temperature_c=25.0, fault=0, state=0)

    def piezo_status(self):
        return self.status


statuses = st.builds(
    SimpleNamespace,
    displacement_um=st.floats(-40.0, 40.0),
    temperature_c=st.floats(-20.0, 150.0),
    fault=st.integers(0, 0x0F),
    state=st.integers(0, 3),
)
steps = st.one_of(
    st.tuples(st.just("rpdo1"), st.binary(min_size=8, max_size=8)),
    st.tuples(st.just("rpdo2"), st.binary(min_size=8, max_size=8)),
    st.tuples(st.just("rpdo3"), st.tuples(st.integers(0, 1), st.sampled_from([3, 4]),
                                          st.integers(0, 255)).map(bytes)),
    st.tuples(st.just("nmt"), st.sampled_from([1, 2, 0x80, 0x81])),
    st.tuples(st.just("poll"), statuses),
)


def _core(fast: bool) -> AmpNodeCore:
    core = AmpNodeCore(StatusMachine(knives=4, stroke_um=20.0), knives=4, node_id=NODE)
    if not fast:
        core.node._slots = {}  # every PDO through var.raw
    return core


def _play(core: AmpNodeCore, program) -> list:
    out, t = [], 0.0
    core.on_frame(0x000, bytes([1, NODE]), t)  # started
    for kind, arg in program:
        if kind == "poll":
            t += 0.01
            core.machine.status = arg
            out.append(("sent", core.poll(t)))
        elif kind == "nmt":
            core.on_frame(0x000, bytes([arg, NODE]), t)
        else:
            core.on_frame(IDS[kind], arg, t)
        m = core.machine
        out.append((list(m.offsets_um), list(m.alive_counters), m.enable, core.node.refused,
                    core.node.last_command, list(core.node.offsets_um)))
    return out


@settings(max_examples=200, deadline=None)
@given(program=st.lists(steps, min_size=1, max_size=40))
def test_byte_ranges_give_what_var_raw_gives(program):
    assert _play(_core(True), program) == _play(_core(False), program)


def test_the_amplifiers_pdos_are_byte_ranges():
    node = _core(True).node
    assert all(node._slots[id(p)] is not None
               for p in (node.node.rpdo[1], node.node.rpdo[2], node.node.rpdo[3],
                         node.node.tpdo[1]))


def _nmt_run(core: AmpNodeCore) -> list:
    """Boot, then NMT commands between polls: every frame sent and the state after each."""
    out = [("boot", core.poll(0.0), core.node.nmt_state)]
    t = 0.0
    for cmd in (1, 2, 1, 0x80, 0x81, 1, 0x82, 1, 2):
        core.on_frame(0x000, bytes([cmd, NODE]), t)
        for _ in range(12):  # past one heartbeat period (0.1 s)
            t = round(t + 0.01, 9)
            out.append((cmd, core.poll(t), core.node.nmt_state))
    return out


def test_nmt_through_the_librarys_public_state():
    """The node's NMT goes through the library's public ``nmt.state`` (not its ``_state``):
    the boot-up message, a reset (0x81) or a reset of communication (0x82) booting it again
    (boot-up, then pre-operational), the heartbeat carrying each state, the status only when
    operational; the same frames as the node that set ``nmt._state`` itself sent."""
    from protocol.piezo_canopen import NmtState

    core = AmpNodeCore(StatusMachine(knives=4, stroke_um=20.0), knives=4, node_id=NODE)
    run = _nmt_run(core)
    hb = IDS["heartbeat"]
    beats = [(cmd, f[1]) for cmd, frames, _ in run for f in frames if f[0] == hb]
    assert beats == [("boot", b"\x00"), ("boot", b"\x7f"),  # boot-up, then pre-operational
                     (1, b"\x05"), (2, b"\x04"), (1, b"\x05"), (0x80, b"\x7f"),
                     (0x81, b"\x00"), (0x81, b"\x7f"), (0x81, b"\x7f"), (1, b"\x05"),
                     (0x82, b"\x00"), (0x82, b"\x7f"), (1, b"\x05"), (2, b"\x04")]
    states = {cmd: state for cmd, _, state in run}  # each command's last state
    assert states == {"boot": NmtState.PRE_OPERATIONAL, 1: NmtState.OPERATIONAL,
                      2: NmtState.STOPPED, 0x80: NmtState.PRE_OPERATIONAL,
                      0x81: NmtState.PRE_OPERATIONAL, 0x82: NmtState.PRE_OPERATIONAL}
    statuses = {cmd for cmd, frames, _ in run for f in frames if f[0] == IDS["tpdo1"]}
    assert statuses == {1}  # the status only while operational
