"""The HIL summary is honest: no check passes without a setpoint, safe entries are counted and
laid to their faults, and the JSON is strict (no NaN)."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from types import SimpleNamespace

import pytest

from config.machine import SafetyConfig
from controller.service.events import EventKind, ServiceEvent
from controller.service.service import FrameResult
from planer.hil import FaultEvent, json_ready, summarize


def _result(i, *, feed=600.0, applied=True, offs=(0.0, 0.0), state="run", cv=0.02):
    return FrameResult(
        seq=i, ok=True, error=None,
        measurement=SimpleNamespace(pitch_mm=1.5, uniformity_cv=cv),
        knife_widths_mm=(1.5, 1.5), applied=applied, feed_setpoint_mm_s=feed,
        offsets_um=offs, state=state, t_s=i * 0.1, latency_s=0.002,
        truth={"pitch_mm": 1.5, "uniformity_cv": cv}, counts_a=i * 2000, frame_t_s=i * 0.1,
    )


def _summary(results, *, limits=(50.0, 1000.0), faults=(), events=()):
    return summarize(results, target_pitch_mm=1.5, counts_per_mm=20.0, feed_limits_mm_s=limits,
                     stroke_um=20.0, faults=faults, events=events, safety=SafetyConfig())


def _strict(obj):
    def refuse(name):
        raise ValueError(f"bare {name} in JSON")

    return json.loads(json.dumps(json_ready(obj), allow_nan=False), parse_constant=refuse)


def test_a_clean_run_passes_its_limits():
    s = _summary([_result(i) for i in range(10)])
    assert s["limits"]["ok"] and s["limits"]["reasons"] == [] and s["limits"]["applied"] == 10
    assert s["done"]["setpoints_within_limits"]


@pytest.mark.parametrize(
    ("results", "limits", "reason"),
    [
        ([_result(i, applied=False) for i in range(5)], (50.0, 1e3), "no setpoint was written"),
        ([_result(i, feed=None) for i in range(5)], (50.0, 1e3), "no feed setpoint known"),
        ([_result(i, feed=math.nan) for i in range(5)], (50.0, 1e3), "5 feed setpoint(s) not a"),
        ([_result(i) for i in range(5)], (math.nan, math.nan), "feed limits unknown"),
        ([_result(i, feed=1200.0 if i == 2 else 600.0) for i in range(5)], (50.0, 1e3),
         "1 feed setpoint(s) outside [50, 1000]"),
        ([_result(i, offs=(25.0, 0.0)) for i in range(3)], (50.0, 1e3), "beyond the stroke"),
        ([], (50.0, 1e3), "no setpoint was written"),
    ],
)
def test_limits_never_pass_without_a_setpoint_and_say_why(results, limits, reason):
    s = _summary(results, limits=limits)
    lim = s["limits"]
    assert not lim["ok"] and not s["done"]["setpoints_within_limits"] and not s["passed"]
    assert any(reason in r for r in lim["reasons"]), lim["reasons"]
    out = _strict(s)  # strict JSON whatever went wrong
    assert out["limits"]["reasons"] == lim["reasons"]
    for key in ("feed_min_mm_s", "feed_max_mm_s"):
        assert out["limits"][key] is None or math.isfinite(out["limits"][key])


def test_json_ready_turns_every_non_finite_number_into_null_with_a_reason():
    s = {"a": 1.0, "b": [math.nan, 2.0, {"c": math.inf}], "d": "nan", "e": None}
    out = _strict(s)
    assert out["a"] == 1.0 and out["b"] == [None, 2.0, {"c": None}] and out["d"] == "nan"
    assert set(out["null_reasons"]) == {"b[0]", "b[2].c"}
    assert "nan" in out["null_reasons"]["b[0]"] and "inf" in out["null_reasons"]["b[2].c"]
    with pytest.raises(ValueError):
        json.dumps(s, allow_nan=False)  # what json_ready protects against


def _events(*items):
    """Service events; a safe-state entry carries its reason as the service sets it."""
    return [ServiceEvent(t, k, text, text.partition(": ")[2] if k is EventKind.SAFE_STATE else None)
            for t, k, text in items]


def test_safe_entries_are_counted_listed_and_laid_to_their_faults():
    res = [_result(i) for i in range(200)]  # 20 s
    fault = FaultEvent("modbus_restart", 4.0, {"duration_s": 1.0})
    k = EventKind
    events = _events((4.3, k.SAFE_STATE, "safe state: plc gone"),
                     (5.5, k.RECOVERED, "recovered: control resumed"),
                     (14.0, k.SAFE_STATE, "safe state: measurement gone"),
                     (14.5, k.RECOVERED, "recovered: control resumed"),
                     (17.0, k.SAFE_STATE, "safe state: can gone"),
                     (17.5, k.RECOVERED, "recovered: control resumed"))
    s = _summary(res, faults=[fault], events=events)
    safe = s["safe_entries"]
    assert safe["count"] == 3 and safe["unexplained"] == 2
    assert [e["fault"] for e in safe["entries"]] == ["modbus_restart@4", None, None]
    assert [e["reason"] for e in safe["entries"]] == ["plc gone", "measurement gone", "can gone"]
    assert s["faults"][0]["handled"]  # the fault itself was handled ...
    assert not s["done"]["no_unexplained_safe_state"] and not s["passed"]  # ... the run was not
    s = _summary(res, faults=[fault], events=events[:2])
    assert s["safe_entries"]["unexplained"] == 0 and s["done"]["no_unexplained_safe_state"]
    # two faults close together: each entry goes to the fault whose condition it names
    faults = [fault, FaultEvent("can_silence", 5.0, {"duration_s": 1.0}),
              FaultEvent("modbus_restart", 5.2, {"duration_s": 1.0})]
    events = _events((4.3, k.SAFE_STATE, "safe state: plc gone"),
                     (5.1, k.RECOVERED, "recovered: control resumed"),
                     (5.4, k.SAFE_STATE, "safe state: can gone"))
    s = _summary(res, faults=faults, events=events)
    assert [e["fault"] for e in s["safe_entries"]["entries"]] == ["modbus_restart@4",
                                                                  "can_silence@5"]


def test_a_fault_that_trips_the_wrong_condition_is_not_handled():
    res = [_result(i) for i in range(100)]
    k = EventKind
    for kind, reason, ok in (("can_silence", "can gone", True),
                             ("can_silence", "plc gone", False),
                             ("modbus_restart", "plc gone, measurement gone", True)):
        fault = FaultEvent(kind, 4.0, {"duration_s": 0.5})
        events = _events((4.2, k.SAFE_STATE, f"safe state: {reason}"),
                         (5.0, k.RECOVERED, "recovered: control resumed"))
        (rep,) = _summary(res, faults=[fault], events=events)["faults"]
        assert rep["trips"] == fault.kind.trips and rep["safe_reason"] == reason
        assert rep["tripped"] is ok and rep["handled"] is ok


def test_machine_faults_are_reported_by_what_they_should_trip():
    res = [_result(i) for i in range(100)]
    events = _events((3.1, EventKind.SAFE_STATE, "safe state: machine not running"))
    s = _summary(res, faults=[FaultEvent("estop", 3.0), FaultEvent("knot")], events=events)
    estop, knot = s["faults"]
    assert estop["trips"] == "machine" and estop["tripped"] and estop["handled"]
    assert "recovered_after_end_s" not in estop  # an e-stop does not end by itself
    assert knot["trips"] is None and "handled" not in knot  # nothing to trip: ridden out
    assert knot["at_s"] == 0.0  # a fault without a time acts at the start
    assert s["safe_entries"]["unexplained"] == 0


def test_the_text_summary_shows_missing_values_and_reasons():
    from planer.commands.hil import _human

    s = _summary([_result(i, applied=False, feed=None) for i in range(3)],
                 limits=(math.nan, math.nan))
    s.update(quality_log={"path": "q.sqlite", "records": 3}, scenario="x", mode="in-process")
    text = _human(s)
    assert "feed - mm/s within [-, -]" in text and "nan" not in text
    assert "NOT OK: no setpoint was written" in text and text.endswith("NOT PASSED")


@pytest.mark.parametrize(("bound", "cv", "passes"), [
    (0.05, 0.04, True), (0.05, 0.08, False), (0.12, 0.108, True), (0.12, 0.13, False),
])
def test_the_final_cv_check_uses_the_scenarios_bound_and_names_it(bound, cv, passes):
    # A plant whose best reachable CV is above 0.05 (a stroke too small for its runout) passes
    # at its own bound; the done key says which bound was applied.
    res = [_result(i, cv=0.3 if i == 0 else cv) for i in range(60)]
    s = summarize(res, target_pitch_mm=1.5, counts_per_mm=20.0, feed_limits_mm_s=(50.0, 1e3),
                  stroke_um=20.0, safety=SafetyConfig(), final_cv_max=bound)
    key = f"final_uniformity_le_{bound:g}"
    assert set(k for k in s["done"] if k.startswith("final_uniformity")) == {key}
    assert s["done"][key] is passes
    assert (s["converged"]["uniformity_settled_after_mm"] is not None) is passes


def test_a_run_that_starts_within_the_band_and_stays_there_is_no_failure():
    """``initial_uniformity_ge_0.10`` failed every run that began below 0.10 (e.g. a resumed
    machine): a run failing it now is one that starts good and ends bad."""
    good = _summary([_result(i, cv=0.02) for i in range(10)])
    assert good["done"]["initial_uniformity_ge_0.10"] and good["passed"]
    worse = _summary([_result(i, cv=0.02 if i < 5 else 0.08) for i in range(10)])
    assert not worse["done"]["initial_uniformity_ge_0.10"]


def test_every_check_reads_as_a_sentence_under_its_key():
    s = _summary([_result(i) for i in range(10)])
    assert set(s["checks"]) == set(s["done"])
    for key, check in s["checks"].items():
        assert check["ok"] is s["done"][key]
        text = check["text"]
        assert text[0].isupper() and text.endswith(".") and "_" not in text


def test_the_pitch_is_judged_against_what_the_machine_holds_when_told_unreachable():
    results = [replace(_result(i), truth={"pitch_mm": 2.5, "uniformity_cv": 0.02})
               for i in range(10)]
    told = ServiceEvent(0.3, EventKind.TARGET_UNREACHABLE, "target not reachable",
                        reason="feed at its maximum", data={"reachable_pitch_mm": 2.49})
    s = summarize(results, target_pitch_mm=3.0, counts_per_mm=20.0,
                  feed_limits_mm_s=(50.0, 1000.0), stroke_um=20.0, events=[told])
    assert s["reachable_pitch_mm"] == 2.49 and s["done"]["final_pitch_within_2pct"]
    assert s["alerts"]["target_unreachable"] == 1
    silent = summarize(results, target_pitch_mm=3.0, counts_per_mm=20.0,
                       feed_limits_mm_s=(50.0, 1000.0), stroke_um=20.0)
    assert not silent["done"]["final_pitch_within_2pct"]  # nobody said it was out of reach
    again = ServiceEvent(0.6, EventKind.TARGET_REACHABLE, "reached again")
    back = summarize(results, target_pitch_mm=3.0, counts_per_mm=20.0,
                     feed_limits_mm_s=(50.0, 1000.0), stroke_um=20.0, events=[told, again])
    assert back["reachable_pitch_mm"] is None and not back["done"]["final_pitch_within_2pct"]
