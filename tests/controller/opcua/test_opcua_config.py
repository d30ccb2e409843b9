"""``[opcua]`` and ``[identification]`` in machine.toml, and the pure OPC UA view of the service."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from config.machine import IDENTIFICATION_KEYS, load_machine, machine_from_dict
from controller.opcua.view import MachineView, UnitMode, UnitState, WwEventCategory
from controller.quality.log import QualityClass
from controller.service.events import EventKind, ServiceEvent
from controller.service.frame_result import FrameResult
from controller.service.status import ServiceStatus

QC = QualityClass(name="fine-1.5", target_pitch_mm=1.5, pitch_tolerance=0.02,
                  uniformity_max_cv=0.05, depth_max_um=20.0)


def test_shipped_config_leaves_the_server_off():
    cfg = load_machine()
    assert cfg.opcua.endpoint == ""


def test_opcua_and_identification_tables_load():
    cfg = machine_from_dict({
        "opcua": {"endpoint": "opc.tcp://127.0.0.1:4841", "certificate": "c.der",
                  "private_key": "k.pem", "users_file": "users.txt"},
        "identification": {"Manufacturer": "ACME", "SerialNumber": "7",
                           "YearOfConstruction": 2025, "MonthOfConstruction": 3},
    })
    assert cfg.opcua.endpoint == "opc.tcp://127.0.0.1:4841"
    assert cfg.opcua.certificate.name == "c.der" and cfg.opcua.users_file.name == "users.txt"
    assert dict(cfg.identification) == {"Manufacturer": "ACME", "SerialNumber": "7",
                                        "YearOfConstruction": 2025, "MonthOfConstruction": 3}


@pytest.mark.parametrize(("doc", "key"), [
    ({"opcua": {"endpoint": "http://127.0.0.1:4840"}}, "opcua.endpoint"),
    ({"opcua": {"endpoint": 4840}}, "opcua.endpoint"),
    ({"opcua": {"port": 4840}}, "opcua.port"),
    ({"identification": {"Manufactur": "x"}}, "identification.Manufactur"),
    ({"identification": {"YearOfConstruction": "2025"}}, "identification.YearOfConstruction"),
    ({"identification": {"MonthOfConstruction": 13}}, "identification.MonthOfConstruction"),
    ({"identification": {"Model": 5}}, "identification.Model"),
])
def test_bad_values_name_the_key(doc, key):
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        machine_from_dict(doc)


def test_identification_keys_are_the_served_ones():
    pytest.importorskip("asyncua", reason="the OPC UA extra (asyncua) is not installed")
    from controller.opcua import nodes

    assert tuple(nodes.IDENTIFICATION_FIELDS) == IDENTIFICATION_KEYS
    assert set(nodes.MANDATORY_IDENTIFICATION) <= set(IDENTIFICATION_KEYS)


def _status(t_s, *, state="run", feed=500.0, missing=(), reason=None, log_problem=None):
    return ServiceStatus(
        t_s=t_s, state=state, safe_reason=reason, missing=tuple(missing),
        feed_setpoint_mm_s=feed, feed_actual_mm_s=feed, offsets_um=(0.0, 0.0),
        amplifier_enabled=state == "run", last_measurement=None,
        counters=ServiceStatus.freeze({}), log_problem=log_problem)


def _result(t_s, *, pitch=1.5, ok=True):
    m = SimpleNamespace(pitch_mm=pitch, uniformity_cv=0.01, depth_um=3.0, confidence=0.8)
    return FrameResult(seq=0, ok=ok, error=None if ok else "implausible: test", measurement=m,
                       knife_widths_mm=(1.5, 1.5), applied=ok, feed_setpoint_mm_s=500.0,
                       offsets_um=(0.0, 0.0), state="run", t_s=t_s, latency_s=0.0)


@pytest.mark.parametrize(("kw", "state", "mode"), [
    ({"state": "run", "feed": 500.0}, UnitState.WORKING, UnitMode.AUTOMATIC),
    ({"state": "run", "feed": 0.0}, UnitState.READY, UnitMode.AUTOMATIC),
    ({"state": "safe", "missing": ("plc",)}, UnitState.ERROR, UnitMode.SEMIAUTOMATIC),
    ({"state": "safe", "missing": (), "reason": "confirming recovery"}, UnitState.STANDBY,
     UnitMode.SEMIAUTOMATIC),
])
def test_state_and_mode_follow_the_service(kw, state, mode):
    v = MachineView()
    assert (v.current_state, v.current_mode) == (UnitState.OFFLINE, UnitMode.OTHER)
    v.update(_status(1.0, **kw))
    assert (v.current_state, v.current_mode) == (state, mode)
    flags = v.flags()
    assert flags["Error"] == (state is UnitState.ERROR)
    assert flags["RecipeInRun"] == (kw["state"] == "run")


def test_length_integrates_the_actual_feed_and_boards_are_counted():
    v = MachineView(quality_class=QC, workpiece_gap_s=0.5)
    feeds = [(0.0, 400.0), (0.25, 400.0), (1.0, 200.0), (2.0, 0.0), (3.0, 100.0)]
    for t, f in feeds:
        v.update(_status(t, feed=f))
    # left-hold integration: the feed of a snapshot holds until the next one
    expected = sum(f0 * (t1 - t0) for (t0, f0), (t1, _) in zip(feeds, feeds[1:], strict=False))
    assert v.values()["AbsoluteLength"] == round(expected)
    assert math.isclose(v.values()["FeedSpeed"], 100.0 * 0.06)
    for i, t in enumerate((3.1, 3.2, 3.3)):  # one board: three pairs, one out of class
        v.result(_result(t, pitch=1.5 if i != 1 else 1.6))
    assert v.flags()["WorkpiecePresent"] and v.values()["AbsolutePiecesIn"] == 1
    v.update(_status(3.7, feed=100.0))  # 0.4 s after the last pair: still there
    assert v.values()["AbsolutePiecesOut"] == 0
    v.update(_status(3.9, feed=100.0))  # 0.6 s: gone
    vals, ms = v.values(), v.manufacturer()
    assert vals["AbsolutePiecesOut"] == 1 and not v.flags()["WorkpiecePresent"]
    assert (vals["AbsoluteRunsTotal"], vals["AbsoluteRunsGood"]) == (3, 2)
    assert ms["LastBoardPairs"] == 3 and math.isclose(ms["LastBoardPassRate"], 2 / 3)
    assert math.isclose(ms["LastBoardMeanPitchMm"], (1.5 + 1.6 + 1.5) / 3)


def test_warning_on_log_trouble_and_failed_pairs():
    v = MachineView(quality_class=QC)
    v.update(_status(1.0))
    assert not v.flags()["Warning"]
    v.update(_status(1.1, log_problem="database gone"))
    assert v.flags()["Warning"]
    v.update(_status(1.2))
    v.result(_result(1.2, ok=False))
    assert v.flags()["Warning"] and not v.manufacturer()["MeasurementOk"]
    assert v.manufacturer()["MeasurementError"] == "implausible: test"


@pytest.mark.parametrize(("kind", "category"), [
    (EventKind.SAFE_STATE, WwEventCategory.ERROR),
    (EventKind.RECOVERED, WwEventCategory.INFORMATION),
    (EventKind.AMPLIFIER_PROBLEM, WwEventCategory.ALARM),
    (EventKind.LOG_FAILED, WwEventCategory.WARNING),
    (EventKind.OFFSETS_REFUSED, WwEventCategory.WARNING),
    (EventKind.PIEZO_LIMITS, WwEventCategory.INFORMATION),
])
def test_events_get_a_category_and_keep_the_text(kind, category):
    ev = MachineView().event(ServiceEvent(4.0, kind, "some text"))
    assert ev.category is category and ev.message == "some text" and ev.message_id == kind.value
    assert 1 <= ev.severity <= 1000


def test_every_event_kind_maps():
    v = MachineView()
    for kind in EventKind:
        assert v.event(ServiceEvent(0.0, kind, "x")).category in WwEventCategory
