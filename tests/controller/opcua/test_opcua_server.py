"""The OPC UA server with an asyncua client: finds the WwMachineType instance, reads everything
the machine shows, sees values change as status snapshots, results and events are fed, and
cannot write. The server runs in its own thread and loop (one start for the module)."""

from __future__ import annotations

import asyncio
import math
import socket
import threading
import time
from datetime import datetime, timedelta, timezone
from types import SimpleNamespace

import pytest

pytest.importorskip("asyncua")

from asyncua import Client, ua  # noqa: E402

from controller.opcua.nodes import OWN_URI, WW_URI  # noqa: E402
from controller.opcua.server import OpcUaServer  # noqa: E402
from controller.opcua.view import FLAG_NAMES, MANUFACTURER_NAMES, VALUE_NAMES  # noqa: E402
from controller.quality.log import QualityClass  # noqa: E402
from controller.service.events import EventKind, ServiceEvent  # noqa: E402
from controller.service.frame_result import FrameResult  # noqa: E402
from controller.service.status import ServiceStatus  # noqa: E402

IDENT = {"Manufacturer": "ACME Planers", "Model": "SP-4", "SerialNumber": "SN-0042",
         "YearOfConstruction": 2026, "ProductInstanceUri": "urn:acme:sp4:0042"}
QC = QualityClass(name="fine-1.5", target_pitch_mm=1.5, pitch_tolerance=0.02,
                  uniformity_max_cv=0.05, depth_max_um=20.0)
WAIT_S = 30.0  # an upper bound for a condition to hold, never a speed assertion


class Wall:
    """Injected source-timestamp clock."""

    def __init__(self) -> None:
        self.now = datetime(2026, 11, 24, 1, 0, 0, tzinfo=timezone.utc)

    def __call__(self) -> datetime:
        return self.now


def status(*, t_s, state="run", feed=400.0, missing=(), reason=None, offsets=(1.0, -1.0, 0.5, 0.0),
           log_problem=None) -> ServiceStatus:
    return ServiceStatus(
        t_s=t_s, state=state, safe_reason=reason, missing=tuple(missing),
        feed_setpoint_mm_s=feed, feed_actual_mm_s=feed, offsets_um=tuple(offsets),
        amplifier_enabled=state == "run", last_measurement=None,
        counters=ServiceStatus.freeze({"frames": 0}), log_problem=log_problem)


def result(seq, *, t_s, pitch=1.5, cv=0.02, depth=5.0, ok=True) -> FrameResult:
    m = SimpleNamespace(pitch_mm=pitch, uniformity_cv=cv, depth_um=depth, confidence=0.9)
    return FrameResult(seq=seq, ok=ok, error=None if ok else "registration failed: test",
                       measurement=m, knife_widths_mm=(1.4, 1.5, 1.6, 1.5), applied=ok,
                       feed_setpoint_mm_s=400.0, offsets_um=(1.0, -1.0, 0.5, 0.0), state="run",
                       t_s=t_s, latency_s=0.01)


@pytest.fixture(scope="module")
def served():
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    wall = Wall()
    srv = OpcUaServer("opc.tcp://127.0.0.1:0", identification=IDENT, quality_class=QC, knives=4,
                      wall_clock=wall)
    asyncio.run_coroutine_threadsafe(srv.start(), loop).result(timeout=120)
    yield SimpleNamespace(srv=srv, wall=wall, loop=loop)
    asyncio.run_coroutine_threadsafe(srv.stop(), loop).result(timeout=60)
    loop.call_soon_threadsafe(loop.stop)
    thread.join(timeout=60)


async def _until(cond, what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not await cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"never became true: {what}")
        await asyncio.sleep(0.005)


async def _machine(c: Client):
    ns_ma = await c.get_namespace_index("http://opcfoundation.org/UA/Machinery/")
    machines = await c.nodes.objects.get_child(f"{ns_ma}:Machines")
    ns_ww = await c.get_namespace_index(WW_URI)
    found = []
    for child in await machines.get_children():
        td = await child.read_type_definition()
        if td == ua.NodeId(2, ns_ww):
            found.append(child)
    assert len(found) == 1, "exactly one WwMachineType instance under Objects/Machines"
    return found[0], ns_ww


def feed_and_wait(served, fn) -> None:
    before = served.srv.published
    fn()
    deadline = time.monotonic() + WAIT_S
    while served.srv.published == before:
        assert time.monotonic() < deadline, "the server never published the update"
        time.sleep(0.002)


async def _read(machine, ns_ww, ns_own, path: str):
    ns_di = None
    parts = []
    for i, p in enumerate(path.split("/")):
        if p == "Identification" and i == 0:
            ns_di = await machine.session.get_namespace_index("http://opcfoundation.org/UA/DI/")
            parts.append(f"{ns_di}:Identification")
        elif path.startswith("ManufacturerSpecific/") and i == 1:
            parts.append(f"{ns_own}:{p}")
        else:
            parts.append(f"{ns_ww}:{p}")
    return await machine.get_child(parts)


def read_manufacturer(srv, names) -> dict:
    """The values of ``ManufacturerSpecific/<name>`` for each of ``names``, read by a client."""
    async def go():
        async with Client(srv.endpoint) as c:
            machine, ns_ww = await _machine(c)
            ns_own = await c.get_namespace_index(OWN_URI)
            return {n: await (await _read(machine, ns_ww, ns_own,
                                          f"ManufacturerSpecific/{n}")).read_value()
                    for n in names}
    return asyncio.run(go())


def test_client_finds_the_machine_and_reads_identification(served):
    async def go():
        async with Client(served.srv.endpoint) as c:
            machine, ns_ww = await _machine(c)
            ns_di = await c.get_namespace_index("http://opcfoundation.org/UA/DI/")
            ns_ma = await c.get_namespace_index("http://opcfoundation.org/UA/Machinery/")
            idn = await machine.get_child(f"{ns_di}:Identification")
            man = await (await idn.get_child(f"{ns_di}:Manufacturer")).read_value()
            assert man.Text == IDENT["Manufacturer"]
            assert await (await idn.get_child(f"{ns_di}:SerialNumber")).read_value() == "SN-0042"
            year = await idn.get_child(f"{ns_ma}:YearOfConstruction")
            assert await year.read_value() == 2026
            assert await year.read_data_type() == ua.NodeId(ua.ObjectIds.UInt16)
            # read-only for clients
            for node in (year, await machine.get_child(
                    [f"{ns_ww}:State", f"{ns_ww}:Machine", f"{ns_ww}:Flags", f"{ns_ww}:Error"])):
                with pytest.raises(ua.UaStatusCodeError):
                    await node.write_value(ua.DataValue(ua.Variant(True, ua.VariantType.Boolean)))
    asyncio.run(go())


def test_values_follow_the_service(served):
    srv, wall = served.srv, served.wall

    async def read_all(c):
        machine, ns_ww = await _machine(c)
        ns_own = await c.get_namespace_index(OWN_URI)
        out = {}
        paths = (["State/Machine/Overview/CurrentState", "State/Machine/Overview/CurrentMode"]
                 + [f"State/Machine/Flags/{n}" for n in FLAG_NAMES]
                 + [f"State/Machine/Values/{n}" for n in VALUE_NAMES]
                 + [f"ManufacturerSpecific/{n}" for n in MANUFACTURER_NAMES])
        for p in paths:
            node = await _read(machine, ns_ww, ns_own, p)
            out[p] = await node.read_data_value()
        return out

    async def go():
        async with Client(srv.endpoint) as c:
            return await read_all(c)

    wall.now += timedelta(seconds=10)
    feed_and_wait(served, lambda: srv.update(status(t_s=100.0, feed=400.0)))
    feed_and_wait(served, lambda: srv.update(status(t_s=101.0, feed=400.0)))
    v1 = asyncio.run(go())
    assert v1["State/Machine/Overview/CurrentState"].Value.Value == 3  # WORKING
    assert v1["State/Machine/Overview/CurrentMode"].Value.Value == 1  # AUTOMATIC
    assert v1["State/Machine/Flags/FeedRuns"].Value.Value is True
    assert v1["State/Machine/Flags/Error"].Value.Value is False
    assert math.isclose(v1["State/Machine/Values/FeedSpeed"].Value.Value, 400.0 * 60 / 1000)
    assert v1["State/Machine/Values/AbsoluteLength"].Value.Value == 400  # 1 s at 400 mm/s
    first = v1["State/Machine/Flags/FeedRuns"].SourceTimestamp
    assert first.replace(tzinfo=timezone.utc) == wall.now  # the injected source time

    # a measured pair: ManufacturerSpecific and the runs
    wall.now += timedelta(seconds=1)
    feed_and_wait(served, lambda: srv.result(result(1, t_s=101.5)))
    feed_and_wait(served, lambda: srv.result(result(2, t_s=101.6, pitch=1.7)))  # out of class
    # safe state with the PLC gone: ERROR, flags follow
    wall.now += timedelta(seconds=1)
    feed_and_wait(served, lambda: srv.update(status(t_s=103.0, state="safe", feed=0.0,
                                                    missing=("plc",), reason="plc gone")))
    v2 = asyncio.run(go())
    assert v2["State/Machine/Overview/CurrentState"].Value.Value == 4  # ERROR
    assert v2["State/Machine/Overview/CurrentMode"].Value.Value == 2  # SEMIAUTOMATIC
    assert v2["State/Machine/Flags/Error"].Value.Value is True
    assert v2["State/Machine/Flags/MachineOn"].Value.Value is False
    assert v2["State/Machine/Flags/FeedRuns"].Value.Value is False
    assert v2["State/Machine/Values/AbsoluteRunsTotal"].Value.Value == 2
    assert v2["State/Machine/Values/AbsoluteRunsGood"].Value.Value == 1
    assert v2["State/Machine/Values/AbsolutePiecesIn"].Value.Value == 1
    assert v2["State/Machine/Values/AbsolutePiecesOut"].Value.Value == 1  # no pair for > 1 s
    assert v2["ManufacturerSpecific/PitchMm"].Value.Value == pytest.approx(1.7)
    assert v2["ManufacturerSpecific/Passed"].Value.Value is False
    assert v2["ManufacturerSpecific/KnifeWidthsMm"].Value.Value == [1.4, 1.5, 1.6, 1.5]
    assert v2["ManufacturerSpecific/LastBoardPairs"].Value.Value == 2
    assert v2["ManufacturerSpecific/LastBoardPassRate"].Value.Value == pytest.approx(0.5)
    assert v2["ManufacturerSpecific/SafeReason"].Value.Value == "plc gone"
    changed = v2["State/Machine/Flags/Error"].SourceTimestamp
    assert changed.replace(tzinfo=timezone.utc) == wall.now  # source time of the change
    kept = v2["State/Machine/Flags/MachineInitialized"].SourceTimestamp  # unchanged since v1
    assert kept == first and kept < changed


def test_events_reach_a_subscriber(served):
    srv = served.srv
    received: list = []

    class Handler:
        def event_notification(self, event):
            received.append(event)

    async def go():
        async with Client(srv.endpoint) as c:
            machine, ns_ww = await _machine(c)
            events = await machine.get_child(f"{ns_ww}:Events")
            etype = c.get_node(ua.NodeId(13, ns_ww))
            sub = await c.create_subscription(20, Handler())
            await sub.subscribe_events(events, etype)
            await asyncio.sleep(0)  # let the subscription settle before feeding
            srv.event(ServiceEvent(200.0, EventKind.SAFE_STATE, "safe state: plc gone",
                                   "plc gone"))
            srv.event(ServiceEvent(201.0, EventKind.RECOVERED, "recovered"))

            async def two():
                return len(received) >= 2
            await _until(two, "two events received")
            await sub.delete()

    asyncio.run(go())
    first, second = received[:2]
    assert first.MessageId == "safe_state"
    assert first.EventCategory == 5  # ERROR
    assert first.Message.Text == "safe state: plc gone"
    assert second.MessageId == "recovered" and second.EventCategory == 2  # INFORMATION
    assert first.Severity > second.Severity


def test_busy_port_is_one_line_naming_it(served):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        srv = OpcUaServer(f"opc.tcp://127.0.0.1:{port}")
        with pytest.raises(OSError) as info:
            asyncio.run(srv.start())
    msg = str(info.value)
    assert "\n" not in msg and str(port) in msg and "busy" in msg


@pytest.mark.parametrize("endpoint", ["opc.tcp://0.0.0.0:4840", "opc.tcp://192.168.1.5:4840"])
def test_non_loopback_needs_certificates_and_users(endpoint):
    with pytest.raises(ValueError, match="non-loopback.*certificate"):
        OpcUaServer(endpoint)


@pytest.mark.parametrize("endpoint", ["http://127.0.0.1:4840", "opc.tcp://127.0.0.1", "4840",
                                      "opc.tcp://:4840", "opc.tcp://127.0.0.1:99999"])
def test_bad_endpoints_are_refused(endpoint):
    with pytest.raises(ValueError, match="opcua endpoint"):
        OpcUaServer(endpoint)


def test_follow_polls_a_service_without_taking_its_callbacks(served):
    srv = served.srv
    runs0 = srv.view.values()["AbsoluteRunsTotal"]
    fake = SimpleNamespace(events=[], results=[], on_event=None, on_result=None,
                           status=lambda: status(t_s=300.0, state="run", feed=0.0))
    task = asyncio.run_coroutine_threadsafe(srv.follow(lambda: fake, period_s=0.01), served.loop)
    try:
        fake.results.append(result(7, t_s=299.9, pitch=1.49))
        fake.results.append(result(8, t_s=300.0, pitch=1.51))
        deadline = time.monotonic() + WAIT_S
        while srv.view.values()["AbsoluteRunsTotal"] < runs0 + 2:
            assert time.monotonic() < deadline, "follow never took the results"
            time.sleep(0.005)
        assert srv.view.values()["AbsoluteRunsTotal"] == runs0 + 2  # each result once
        assert srv.view.manufacturer()["PitchMm"] == pytest.approx(1.51)
        assert srv.view.current_state.name == "READY"  # run, feed stopped
        assert fake.on_event is None and fake.on_result is None
    finally:
        task.cancel()
