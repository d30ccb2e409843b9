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
