"""OPC UA of a moulder, read by an asyncua client: each head a unit of the machine
(``State/SubUnits/<head>``) with its own state, flags, values and ManufacturerSpecific, fed
from two real heads' services through the servers' translator; a single machine has no
``SubUnits``."""

from __future__ import annotations

import asyncio
import math
import threading
import time

import pytest

pytest.importorskip("asyncua")

from asyncua import Client, ua  # noqa: E402

from controller.edge.feed import Translator  # noqa: E402
from controller.opcua.heads_nodes import WW_SUBUNITS_INTERFACE  # noqa: E402
from controller.opcua.heads_view import HEAD_MANUFACTURER_NAMES  # noqa: E402
from controller.opcua.nodes import OWN_URI  # noqa: E402
from controller.opcua.server import OpcUaServer  # noqa: E402
from controller.opcua.view import UnitState  # noqa: E402
from tests.controller.edge.two_heads import follow_all, moulder_fixture  # noqa: E402
from tests.controller.opcua.test_opcua_server import _machine  # noqa: E402

WAIT_S = 60.0  # an upper bound for a condition to hold, never a speed assertion
moulder = pytest.fixture(scope="module")(moulder_fixture)


def _last_ok(svc):
    return next(r for r in reversed(svc.results) if r.ok)


@pytest.fixture(scope="module")
def loop():
    lp = asyncio.new_event_loop()
    thread = threading.Thread(target=lp.run_forever, daemon=True)
    thread.start()
    yield lp
    lp.call_soon_threadsafe(lp.stop)
    thread.join(timeout=60)


def _server(loop, **kw) -> OpcUaServer:
    srv = OpcUaServer("opc.tcp://127.0.0.1:0", knives=4, **kw)
    asyncio.run_coroutine_threadsafe(srv.start(), loop).result(timeout=120)
    return srv


def _stop(loop, srv) -> None:
    asyncio.run_coroutine_threadsafe(srv.stop(), loop).result(timeout=60)


def _applied(srv, msg) -> None:
    before = srv.published
    srv.apply(msg["opcua"]["values"], msg["opcua"]["events"], msg["opcua"].get("heads"))
    deadline = time.monotonic() + WAIT_S
    while srv.published == before:
        assert time.monotonic() < deadline, "the server never published the update"
        time.sleep(0.002)


async def _subunits(c):
    machine, ns_ww = await _machine(c)
    state = await machine.get_child(f"{ns_ww}:State")
    names = [(await n.read_browse_name()).Name for n in await state.get_children()]
    if "SubUnits" not in names:
        return machine, ns_ww, None
    return machine, ns_ww, await state.get_child(f"{ns_ww}:SubUnits")


async def _head_values(c, head_node, ns_ww, ns_own, names):
    ms = await head_node.get_child(f"{ns_own}:ManufacturerSpecific")
    out = {n: await (await ms.get_child(f"{ns_own}:{n}")).read_value() for n in names}
    ov = await head_node.get_child(f"{ns_ww}:Overview")
    out["CurrentState"] = await (await ov.get_child(f"{ns_ww}:CurrentState")).read_value()
    fl = await head_node.get_child(f"{ns_ww}:Flags")
    out["Error"] = await (await fl.get_child(f"{ns_ww}:Error")).read_value()
    va = await head_node.get_child(f"{ns_ww}:Values")
    out["RunsTotal"] = await (await va.get_child(f"{ns_ww}:AbsoluteRunsTotal")).read_value()
    return out


def test_each_head_is_a_unit_of_the_machine_with_its_own_values(loop, moulder):
    srv = _server(loop)  # started as a single machine: the heads come with the first message
    try:
        _applied(srv, Translator(web=False, opcua=True).message(follow_all(moulder)))
        names = ("PitchMm", "UniformityCv", "TargetPitchMm", "SpindleRpm", "SpindleRpmMin",
                 "SpindleRpmMax", "Knives", "Face", "SafeState", "SafeReason",
                 "PiezoOffsetsUm", "KnifeReserveUm", "BoardTravelM", "BoardGrade")

        async def go():
            async with Client(srv.endpoint) as c:
                ns_own = await c.get_namespace_index(OWN_URI)
                machine, ns_ww, sub = await _subunits(c)
                assert sub is not None, "no State/SubUnits in a moulder"
                ifaces = await sub.get_referenced_nodes(ua.NodeId(17603),
                                                        ua.BrowseDirection.Forward)
                assert [n.nodeid for n in ifaces] == [ua.NodeId(WW_SUBUNITS_INTERFACE, ns_ww)]
                heads = {}
                for node in await sub.get_children():
                    bn = await node.read_browse_name()
                    assert bn.NamespaceIndex == ns_own
                    assert await node.read_type_definition() == ua.NodeId(58)  # BaseObjectType
                    heads[bn.Name] = await _head_values(c, node, ns_ww, ns_own, names)
                ms = await machine.get_child(f"{ns_ww}:ManufacturerSpecific")
                order = await (await ms.get_child(f"{ns_own}:Heads")).read_value()
                st = await machine.get_child([f"{ns_ww}:State", f"{ns_ww}:Machine",
                                              f"{ns_ww}:Overview", f"{ns_ww}:CurrentState"])
                return heads, order, await st.read_value()

        heads, order, machine_state = asyncio.run(go())
    finally:
        _stop(loop, srv)
    assert list(heads) == ["bottom", "top"] and order == ["bottom", "top"]
    assert machine_state == int(UnitState.ERROR)  # the top head is in its safe state
    for name, target, safe, state in (("bottom", 1.5, False, UnitState.WORKING),
                                      ("top", 1.0, True, UnitState.ERROR)):
        svc, v = moulder.heads[name], heads[name]
        assert v["PitchMm"] == _last_ok(svc).reported_pitch_mm
        assert abs(v["PitchMm"] - target) < 0.05
        assert v["UniformityCv"] == _last_ok(svc).reported_uniformity_cv
        assert v["TargetPitchMm"] == target and v["Face"] == name and v["Knives"] == 4
        assert v["SpindleRpm"] == float(svc.plc.last.spindle_rpm)
        assert v["SafeState"] is safe and v["Error"] is safe
        assert v["SafeReason"] == (svc.status().safe_reason or "")
        assert v["CurrentState"] == int(state)
        assert v["PiezoOffsetsUm"] == pytest.approx(list(svc.status().offsets_um))
        assert v["RunsTotal"] == len(svc.results)
        kc = svc.status().knife_condition
        assert kc is not None  # each head's knife condition, its own board travel
        assert v["BoardTravelM"] == kc["board_travel_m"] and math.isfinite(v["BoardTravelM"])
        assert len(v["KnifeReserveUm"]) == len(kc["knives"])
    assert heads["bottom"]["BoardTravelM"] != heads["top"]["BoardTravelM"]
    assert any(o != 0 for o in heads["bottom"]["PiezoOffsetsUm"])  # correcting
    assert heads["top"]["PiezoOffsetsUm"] == [0.0] * 4  # its safe state zeroed its offsets
    assert (heads["bottom"]["SpindleRpmMin"], heads["top"]["SpindleRpmMax"]) == (6000.0, 8000.0)


def test_heads_known_at_start_are_there_before_any_value_and_one_head_has_none(loop, moulder):
    msg = Translator(web=False, opcua=True).message(follow_all(moulder))
    with_heads = _server(loop, heads=msg["opcua"]["heads"])
    single = _server(loop)
    try:
        async def look(srv):
            async with Client(srv.endpoint) as c:
                ns_own = await c.get_namespace_index(OWN_URI)
                _, ns_ww, sub = await _subunits(c)
                if sub is None:
                    return None
                out = {}
                for node in await sub.get_children():
                    ms = await node.get_child(f"{ns_own}:ManufacturerSpecific")
                    children = await ms.get_children()
                    out[(await node.read_browse_name()).Name] = sorted(
                        [(await n.read_browse_name()).Name for n in children])
                return out

        assert asyncio.run(look(single)) is None
        shown = asyncio.run(look(with_heads))
    finally:
        _stop(loop, with_heads)
        _stop(loop, single)
    assert list(shown) == ["bottom", "top"]
    assert all(v == sorted(HEAD_MANUFACTURER_NAMES) for v in shown.values())
    assert with_heads.nodes.heads == ["bottom", "top"] and single.nodes.heads == []
