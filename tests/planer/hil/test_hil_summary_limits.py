"""The HIL summary's limits: the stroke in force (the amplifier's when smaller), refused tables
and safe-state entries. A run that cycles through the safe state, or leaves a refused table
un-planned, is not "limits OK"; events are read by kind and data, never by their text."""

from __future__ import annotations

import pytest

from controller.service.events import EventKind, ServiceEvent
from planer.hil import FaultEvent
from planer.hil.summary import limits_report, refused_tables
from tests.planer.hil.test_hil_summary import _result, _summary

AMP = {"stroke_um": 10.0, "source": "amplifier", "amp_stroke_um": 10.0, "limit_um": 10.0}


def _safe(t, missing, text="safe state: (text is for people)"):
    return ServiceEvent(t, EventKind.SAFE_STATE, text, ", ".join(missing),
                        {"missing": list(missing), "recovery_s": 0.3})


def _refused(t, table, replanned):
    limit = None if replanned is None else max(map(abs, replanned))
    return ServiceEvent(t, EventKind.OFFSETS_REFUSED, "refused (text not parsed)", None,
                        {"table_um": table, "limit_um": limit, "replanned_um": replanned})


RES = [_result(i, offs=(4.0, -4.0)) for i in range(100)]  # 10 s, offsets 4 um
FAULT = FaultEvent("can_silence", 4.0, {"duration_s": 0.5})


@pytest.mark.parametrize(
    ("results", "events", "faults", "piezo", "ok", "reason"),
    [
        (RES, [], [], None, True, None),
        (RES, [], [], AMP, True, None),
        ([_result(i, offs=(12.0, -12.0)) for i in range(10)], [], [], AMP, False,
         "20 piezo offset(s) beyond the stroke 10 µm"),
        ([_result(i, offs=(12.0, -12.0)) for i in range(10)], [], [], None, True, None),
        (RES, [_refused(2.0, [12.0, -12.0], [8.0, -8.0])], [], AMP, True, None),
        (RES, [_refused(2.0, [0.0, 0.0], None)], [], AMP, False,
         "1 refused offset table(s) not re-planned"),
        (RES, [_safe(2.0 + 0.3 * i, ["amplifier"]) for i in range(25)], [], AMP, False,
         "25 safe-state entries not explained by an injected fault"),
        (RES, [_safe(4.1, ["can"])], [FAULT], AMP, True, None),
        (RES, [_safe(3.0, ["amplifier"]), _safe(4.1, ["can"])], [FAULT], AMP, False,
         "1 safe-state entry not explained"),
    ],
)
def test_limits_ok_only_without_unplanned_refusals_and_unexplained_safe_entries(
    results, events, faults, piezo, ok, reason
):
    s = _summary(results, faults=faults, events=events) if piezo is None else _summary_with(
        results, faults=faults, events=events, piezo=piezo)
    lim = s["limits"]
    assert lim["ok"] is ok and s["done"]["setpoints_within_limits"] is ok
    if reason is not None:
        assert any(reason in r for r in lim["reasons"]), lim["reasons"]
    assert lim["stroke_um"] == (10.0 if piezo else 20.0)
    assert lim["stroke_source"] == (piezo or {}).get("source", "machine.toml")
    assert lim["safe_entries"] == s["safe_entries"]["count"]
    assert lim["tables_refused"] == sum(e.kind is EventKind.OFFSETS_REFUSED for e in events)


def _summary_with(results, *, faults, events, piezo):
    from config.machine import SafetyConfig
    from planer.hil import summarize

    return summarize(results, target_pitch_mm=1.5, counts_per_mm=20.0,
                     feed_limits_mm_s=(50.0, 1000.0), stroke_um=20.0, faults=faults,
                     events=events, safety=SafetyConfig(), piezo_limits=piezo)


def test_every_safe_entry_is_listed_with_what_was_missing():
    events = [_safe(2.0, ["amplifier"]), _safe(4.1, ["can", "measurement"])]
    s = _summary(RES, faults=[FAULT], events=events)
    entries = s["safe_entries"]["entries"]
    assert [e["missing"] for e in entries] == [["amplifier"], ["can", "measurement"]]
    assert [e["fault"] for e in entries] == [None, "can_silence@4"]


def test_conditions_are_read_from_the_events_data_not_their_text():
    """The reason's words may say anything: the data's ``missing`` decides what was tripped."""
    misleading = ServiceEvent(4.1, EventKind.SAFE_STATE, "safe state: can gone", "can gone",
                              {"missing": ["plc"]})
    (rep,) = _summary(RES, faults=[FAULT], events=[misleading])["faults"]
    assert not rep["tripped"]
    honest = ServiceEvent(4.1, EventKind.SAFE_STATE, "safe state: ???", "???", {"missing": ["can"]})
    (rep,) = _summary(RES, faults=[FAULT], events=[honest])["faults"]
    assert rep["tripped"]
    # an event without data (an older service) is still read from its reason
    old = ServiceEvent(4.1, EventKind.SAFE_STATE, "safe state: can gone", "can gone")
    (rep,) = _summary(RES, faults=[FAULT], events=[old])["faults"]
    assert rep["tripped"]


def test_refused_tables_are_listed_in_order():
    events = [_refused(1.0, [12.0, -12.0], [9.6, -9.6]),
              ServiceEvent(1.5, EventKind.RECOVERED, "recovered"),
              _refused(2.0, [9.6, -9.6], [7.68, -7.68])]
    got = refused_tables(events)
    assert [r["t_s"] for r in got] == [1.0, 2.0]
    assert got[1]["table_um"] == got[0]["replanned_um"]
    lim = limits_report(RES, 50.0, 1000.0, 20.0, events=events, piezo_limits=AMP)
    assert lim["tables_refused"] == 2 and lim["tables_unplanned"] == 0 and lim["ok"]
