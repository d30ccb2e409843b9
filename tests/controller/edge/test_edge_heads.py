"""The servers follow a moulder head by head: two real heads' services (``heads``,
``head_configs``), one in its safe state; each head's items named, each head's values its own,
a single service's items and messages as before."""

from __future__ import annotations

import asyncio
import math
from dataclasses import replace
from pathlib import Path

import pytest

from controller.edge.feed import HEAD_KEYS, Headed, Mailbox, Translator, follow_once
from controller.edge.process import _apply_web
from controller.opcua.heads_view import HEAD_MANUFACTURER_NAMES, head_path
from controller.opcua.view import FLAG_NAMES, VALUE_NAMES, UnitState
from controller.web.live import LiveView
from tests.controller.edge.two_heads import moulder_fixture

moulder = pytest.fixture(scope="module")(moulder_fixture)


def _items(followed, seen=None):
    box, seen = Mailbox(4096), {} if seen is None else seen
    follow_once(followed, seen, box)
    assert box.dropped == 0
    return box.take(0.0), seen


def _last_ok(svc):
    return next(r for r in reversed(svc.results) if r.ok)


def test_the_composition_is_followed_head_by_head_each_item_once(moulder):
    items, seen = _items(moulder)
    assert items[0] == ("heads", [
        {"name": "bottom", "face": "bottom", "knives": 4, "rpm": 6000.0, "rpm_min": 6000.0,
         "rpm_max": 6000.0, "target_pitch_mm": 1.5, "position_mm": 0.0},
        {"name": "top", "face": "top", "knives": 4, "rpm": 6000.0, "rpm_min": 4000.0,
         "rpm_max": 8000.0, "target_pitch_mm": 1.0, "position_mm": 0.0}])
    assert set(items[0][1][0]) == set(HEAD_KEYS)
    rest = items[1:]
    assert all(isinstance(item, Headed) for _, item in rest)
    for name, svc in moulder.heads.items():
        mine = [(k, i.item) for k, i in rest if i.head == name]
        assert [r for k, r in mine if k == "result"] == svc.results
        assert [e for k, e in mine if k == "event"] == svc.events
        assert sum(k == "status" for k, _ in mine) == 1
        plc = next(i for k, i in mine if k == "plc")
        assert plc == {"spindle_rpm": float(svc.plc.last.spindle_rpm), "knives": 4.0}
    # the next look gives the heads again (a full mailbox may have dropped them), then each
    # head's status and PLC facts only: nothing twice
    again, _ = _items(moulder, seen)
    assert again[0] == items[0] and again[0][1] is items[0][1]
    assert sorted((k, i.head) for k, i in again[1:]) == [
        ("plc", "bottom"), ("plc", "top"), ("status", "bottom"), ("status", "top")]


def test_a_single_service_is_followed_as_before(moulder):
    svc = moulder.heads["bottom"]
    items, _ = _items(svc)
    assert {k for k, _ in items} == {"service", "counts_per_mm", "event", "result", "status"}
    assert not any(isinstance(i, Headed) for _, i in items)
    msg = Translator(web=True, opcua=True).message(items)
    assert set(msg["web"]) == {"status", "events", "results", "counts_per_mm", "service_qc"}
    assert all("head" not in r for r in msg["web"]["results"])
    values = msg["opcua"]["values"]
    assert not [p for p in values if "SubUnits" in p]
    assert values["ManufacturerSpecific/PitchMm"] == _last_ok(svc).reported_pitch_mm
    assert set(msg["opcua"]) == {"values", "events"}


def test_each_head_shows_its_own_values_and_the_machine_the_worst(moulder):
    items, seen = _items(moulder)
    tr = Translator(web=True, opcua=True)
    msg = tr.message(items)
    bottom, top = moulder.heads["bottom"], moulder.heads["top"]
    assert bottom.status().state == "run" and top.status().state == "safe"
    v = msg["opcua"]["values"]
    assert [h["name"] for h in msg["opcua"]["heads"]] == ["bottom", "top"]
    ms = "ManufacturerSpecific"
    for name, svc, target, safe, state in (("bottom", bottom, 1.5, False, UnitState.WORKING),
                                           ("top", top, 1.0, True, UnitState.ERROR)):
        assert v[head_path(name, f"{ms}/PitchMm")] == _last_ok(svc).reported_pitch_mm
        assert v[head_path(name, f"{ms}/UniformityCv")] == _last_ok(svc).reported_uniformity_cv
        assert v[head_path(name, f"{ms}/TargetPitchMm")] == target
        assert v[head_path(name, f"{ms}/SafeState")] is safe
        assert v[head_path(name, f"{ms}/SafeReason")] == (svc.status().safe_reason or "")
        assert v[head_path(name, f"{ms}/PiezoOffsetsUm")] == list(svc.status().offsets_um)
        assert v[head_path(name, f"{ms}/Knives")] == 4
        assert v[head_path(name, f"{ms}/SpindleRpm")] == float(svc.plc.last.spindle_rpm)
        assert v[head_path(name, f"{ms}/Face")] == name
        assert v[head_path(name, "Overview/CurrentState")] == int(state)
        assert {f"{ms}/{k}" for k in HEAD_MANUFACTURER_NAMES} | {
            f"Flags/{k}" for k in FLAG_NAMES} | {f"Values/{k}" for k in VALUE_NAMES} <= {
            p.split(f"SubUnits/{name}/", 1)[1] for p in v if f"SubUnits/{name}/" in p}
        runs = v[head_path(name, "Values/AbsoluteRunsTotal")]
        assert runs == len(svc.results)
    # the two heads' pitches differ (their targets): nothing of one head shows on the other
    assert abs(v[head_path("bottom", f"{ms}/PitchMm")] - 1.5) < 0.05
    assert abs(v[head_path("top", f"{ms}/PitchMm")] - 1.0) < 0.05
    assert v["State/Machine/Overview/CurrentState"] == int(UnitState.ERROR)
    assert v["State/Machine/Flags/Error"] is True
    assert v[head_path("bottom", "Flags/Error")] is False
    assert v["State/Machine/Values/AbsoluteRunsTotal"] == len(bottom.results) + len(top.results)
    assert v["ManufacturerSpecific/Heads"] == ["bottom", "top"]
    assert math.isnan(v["ManufacturerSpecific/FeedSetpointMmS"])  # no coordinator here
    # events name their head
    ww = msg["opcua"]["events"]
    assert len(ww) == len(bottom.events) + len(top.events)
    assert {e.path_parts for e in ww} == {("SubUnits", "bottom"), ("SubUnits", "top")}
    safe = [e for e in ww if e.message_id == "safe_state" and e.path_parts[1] == "top"]
    assert safe and safe[-1].message.startswith("top: ")
    # the page's part: results and events carry the head, statuses by head, once
    web = msg["web"]
    assert [r["head"] for r in web["results"]].count("top") == len(top.results)
    assert {e["head"] for e in web["events"]} == {"bottom", "top"}
    assert web["head_status"]["top"]["state"] == "safe"
    assert web["head_status"]["bottom"]["state"] == "run"
    assert web["status"] is None
    again = tr.message(_items(moulder, seen)[0])
    assert "head_status" not in again["web"]  # unchanged statuses are not sent again
    assert "heads" not in again["web"] and "heads" not in again["opcua"]  # nor the same heads
    assert again["opcua"]["values"][head_path("top", f"{ms}/SafeState")] is True  # views kept


def test_the_page_keeps_a_part_per_head_and_a_single_machine_looks_as_before(moulder):
    items, _ = _items(moulder)
    live = LiveView()
    _apply_web(live, Translator(web=True, opcua=False).message(items)["web"])
    snap = live.snapshot()
    assert [h["name"] for h in snap["heads"]] == ["bottom", "top"]
    for h in snap["heads"]:
        svc = moulder.heads[h["name"]]
        assert h["status"]["state"] == svc.status().state
        assert h["last"]["seq"] == svc.results[-1].seq
        assert h["last"]["pitch_mm"] == round(svc.results[-1].reported_pitch_mm, 5)
        assert len(h["trace"]) == len(svc.results)
        assert h["quality_class"]["target_pitch_mm"] == h["target_pitch_mm"]
        assert h["plc"]["spindle_rpm"] == float(svc.plc.last.spindle_rpm)
        assert h["trace"][-1]["board_m"] is not None  # each head's own encoder scale
    assert snap["status"] == snap["heads"][0]["status"]  # the top-level keys: the first head
    assert snap["last"] == snap["heads"][0]["last"]
    single = LiveView()
    _apply_web(single, Translator(web=True, opcua=False).message(
        _items(moulder.heads["top"])[0])["web"])
    one = single.snapshot()
    assert set(one) == {"version", "status", "last", "trace", "events", "quality_class", "board"}
    assert one["status"]["state"] == "safe" and one["last"]["seq"] == moulder.heads[
        "top"].results[-1].seq


def test_a_moulders_configuration_names_its_heads_for_the_servers_from_the_start():
    from config.machine import load_machine
    from controller.edge.compose import moulder_heads

    root = Path(__file__).resolve().parents[3]
    heads = moulder_heads(load_machine(root / "config" / "machine_moulder.toml"))
    assert [(h["name"], h["face"], h["target_pitch_mm"]) for h in heads] == [
        ("bottom", "bottom", 1.5), ("right", "right", 2.0), ("left", "left", 2.0),
        ("top", "top", 1.0)]
    assert (heads[3]["rpm_min"], heads[3]["rpm_max"]) == (4000.0, 8000.0)
    assert heads[0]["rpm_min"] == heads[0]["rpm_max"] == 6000.0
    assert moulder_heads(load_machine()) is None  # one head: a single machine, as before


def test_serving_a_moulders_configuration_shows_its_heads_before_any_service(tmp_path):
    pytest.importorskip("asyncua")
    pytest.importorskip("starlette")
    httpx = pytest.importorskip("httpx")
    from asyncua import Client

    from config.machine import load_machine
    from controller.edge.compose import serving
    from controller.opcua.nodes import OWN_URI, WW_URI

    root = Path(__file__).resolve().parents[3]
    cfg = load_machine(root / "config" / "machine_moulder.toml")
    cfg = cfg.with_changes(log=replace(cfg.log, path=tmp_path / "q.sqlite"))
    said: list[str] = []

    async def main():
        async with serving(cfg, lambda: None, opcua="opc.tcp://127.0.0.1:0",
                           http="127.0.0.1:0", say=said.append) as srv:
            live = await asyncio.to_thread(httpx.get, srv.url + "api/live", timeout=30.0)
            async with Client(srv.endpoint) as c:
                ns_ww = await c.get_namespace_index(WW_URI)
                ns_ma = await c.get_namespace_index("http://opcfoundation.org/UA/Machinery/")
                ns_own = await c.get_namespace_index(OWN_URI)
                sub = await c.nodes.objects.get_child([
                    f"{ns_ma}:Machines", f"{ns_own}:SmartPlaner", f"{ns_ww}:State",
                    f"{ns_ww}:SubUnits"])
                names = [(await n.read_browse_name()).Name for n in await sub.get_children()]
            return live.json(), names

    live, names = asyncio.run(main())
    assert names == ["bottom", "right", "left", "top"]
    assert [h["name"] for h in live["heads"]] == names
    assert all(h["status"] is None and h["last"] is None for h in live["heads"])
    assert any("heads under State/SubUnits" in line for line in said)


def test_the_feed_coordinators_decision_shows_on_the_machine_and_its_heads(moulder):
    decision = {"feed_mm_s": 412.5, "safe": False, "limiting": ["bottom"],
                "spindle_setpoints_rpm": {"top": 6187.5}, "cycles": 3}
    tr = Translator(web=True, opcua=True)
    msg = tr.message(_items(moulder)[0] + [("machine", decision)])
    v, ms = msg["opcua"]["values"], "ManufacturerSpecific"
    assert v[f"{ms}/FeedSetpointMmS"] == 412.5 and v[f"{ms}/LimitingHeads"] == ["bottom"]
    assert v[head_path("bottom", f"{ms}/LimitsFeed")] is True
    assert v[head_path("top", f"{ms}/LimitsFeed")] is False
    assert v[head_path("top", f"{ms}/SpindleSetpointRpm")] == 6187.5
    assert math.isnan(v[head_path("bottom", f"{ms}/SpindleSetpointRpm")])  # a fixed head
    assert msg["web"]["machine"] == decision
    again = tr.message([("machine", dict(decision))])
    assert "machine" not in again["web"]  # unchanged: not sent again
    live = LiveView()
    _apply_web(live, msg["web"])
    assert live.snapshot()["machine"] == decision
