"""Fuzz of the amplifier's CANopen frames: arbitrary ids, data and lengths at both ends.

Whatever arrives on the bus: :func:`describe_frame` names it (never raises); the service's
master (``PiezoClient.handle``) and the simulated node (``AmpNodeCore.on_frame``) take it without
an exception, and a frame of no service of theirs (foreign, malformed) changes nothing and is
counted; an SDO response that is no expedited answer to the read asked is an ``SdoProblem``
(a ``ValueError``), never another type. Example counts are bounded (a few seconds in CI).
"""

from __future__ import annotations

import os

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from controller.fieldbus.piezo_client import PiezoClient
from plant_sim.interfaces.amp_node import AmpNodeCore
from protocol.piezo_canopen import SdoProblem, cob_ids, describe_frame, load_od, sdo_upload_value
from tests.support.fake_machine import FakeMachine

OD = load_od(2)
KNOWN_IDS = sorted({0x000, 0x080, *cob_ids(2).values()})

SCALE = float(os.environ.get("PLANER_FUZZ_SCALE", "1"))
"""Multiplies the example counts: ``PLANER_FUZZ_SCALE=20`` for a deep local run."""
FUZZ = settings(
    max_examples=round(150 * SCALE),
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)

can_ids = st.one_of(
    st.sampled_from(KNOWN_IDS),
    st.integers(0, 0x7FF),  # standard ids
    st.integers(0, 0x1FFF_FFFF),  # extended ids
    st.integers(-(2**40), 2**40),  # what no bus carries
)
payloads = st.binary(min_size=0, max_size=64)  # CAN FD carries up to 64 bytes


@FUZZ
@given(can_ids, payloads)
def test_describe_frame_names_any_frame(fid, data):
    d = describe_frame(fid, data, {2: OD})
    assert d.service in {"nmt", "sync", "heartbeat", "emcy", "tpdo1", "rpdo1", "rpdo2", "rpdo3",
                         "sdo_tx", "sdo_rx", "foreign"}
    if d.service == "foreign":
        assert d.node_id is None and not d.fields
    line = d.line(fid & 0x1FFF_FFFF, data)
    assert d.service in line


@pytest.fixture(scope="module")
def client():
    c = PiezoClient(can.Bus(interface="virtual", channel="fuzz-master"), knives=4)
    yield c
    c.close()


@FUZZ
@given(fid=can_ids, data=payloads)
def test_the_master_takes_any_frame_and_counts_what_is_not_the_amplifiers(client, fid, data):
    c = client
    counts = c.counts
    heard = c.handle(fid, data, now_s=1.0)
    after = c.counts
    assert after["frames"] == counts["frames"] + 1
    refused = sum(after[k] - counts[k] for k in ("foreign", "malformed", "own"))
    assert refused + heard == 1
    if refused:  # nothing of the amplifier's changed
        assert {k: after[k] for k in ("heartbeats", "statuses", "emergencies")} == {
            k: counts[k] for k in ("heartbeats", "statuses", "emergencies")}


@FUZZ
@given(can_ids, payloads)
def test_the_simulated_node_takes_any_frame(fid, data):
    m = FakeMachine()
    core = AmpNodeCore(m, knives=4)
    core.on_frame(0x000, bytes([1, 2]), 0.0)  # started: PDOs count
    took = core.on_frame(fid, data, 0.0)
    core.poll(0.0)
    assert core.received == 2 and core.ignored == (0 if took else 1)
    if not took:
        assert m.alive_counters == [] and list(m.offsets_um) == [0.0] * 4


@FUZZ
@given(st.binary(min_size=0, max_size=12), st.integers(0, 0xFFFF), st.integers(0, 0xFF))
def test_an_sdo_response_is_a_value_or_an_sdo_problem(data, index, sub):
    try:
        value = sdo_upload_value(data, index, sub)
    except SdoProblem as exc:
        assert str(exc)
    else:
        assert 1 <= len(value) <= 4 and data[1:4] == bytes([index & 0xFF, index >> 8, sub])
