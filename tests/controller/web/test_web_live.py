"""The operator page's pure view (controller/web/live.py): JSON of results, events, snapshots."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from controller.quality.log import QualityClass
from controller.service.events import EventKind, ServiceEvent
from controller.service.frame_result import FrameResult
from controller.service.status import ServiceStatus
from controller.web.live import (
    UNAMBIGUOUS_MARGIN,
    LiveView,
    event_json,
    knife_match_margin,
    mark_knives,
    result_json,
    status_json,
)


def _measurement(rng: np.random.Generator, *, marks: int = 6, n: int = 2000) -> SimpleNamespace:
    x = np.linspace(0.0, 12.0, n)
    widths = rng.uniform(1.3, 1.7, marks)
    cusps = np.concatenate([[1.0], 1.0 + np.cumsum(widths)])
    return SimpleNamespace(
        x_mm=x, height_um=np.sin(x * 4.0) * 3.0, pitch_mm=float(widths.mean()),
        mark_widths_mm=widths, mark_depths_um=rng.uniform(2, 4, marks), cusps_mm=cusps,
        bottoms_mm=(cusps[:-1] + cusps[1:]) / 2, uniformity_cv=float(widths.std() / widths.mean()),
        depth_um=3.0, confidence=0.93, roll_deg=0.4, roll_confidence=math.nan,
        calibration=SimpleNamespace(gain=1.02, gain_confidence=0.8, scatter_mm=0.1,
                                    trusted=True, deblurred=False))


def _result(seq: int, meas, *, ok: bool = True, knife_widths=(1.5, 1.4, 1.6, 1.5), counts=0,
            extra=None) -> FrameResult:
    return FrameResult(seq=seq, ok=ok, error=None if ok else "registration failed: low",
                       measurement=meas, knife_widths_mm=tuple(knife_widths), applied=ok,
                       feed_setpoint_mm_s=600.0, offsets_um=(0.5, -1.0, math.nan, 0.0),
                       state="run", t_s=1.0 + seq * 0.05, latency_s=0.004, counts_a=counts,
                       extra=extra or {})


def _status(t_s: float, *, feed=600.0, state="run") -> ServiceStatus:
    return ServiceStatus(t_s=t_s, state=state, safe_reason=None if state == "run" else "plc gone",
                         missing=() if state == "run" else ("plc",), feed_setpoint_mm_s=feed,
                         feed_actual_mm_s=math.nan, offsets_um=(0.0, 1.0),
                         amplifier_enabled=True, last_measurement=None,
                         counters=ServiceStatus.freeze({"frames": 3}))


@pytest.mark.parametrize("knives", [2, 3, 4, 6])
@pytest.mark.parametrize("k0", [0, 1, 5])
def test_mark_knives_recovers_the_cyclic_phase_from_distinct_widths(knives, k0):
    rng = np.random.default_rng(knives * 10 + k0)
    kw = np.linspace(1.2, 1.8, knives)
    rng.shuffle(kw)
    i = np.arange(2 * knives + 1)
    truth = (k0 - i) % knives
    widths = kw[truth] + rng.normal(0, 0.01, i.size)
    assert mark_knives(widths, kw) == truth.tolist()
    kw_nan = kw.copy()
    kw_nan[(k0 + 1) % knives] = math.nan  # a knife without marks does not spoil the others
    assert mark_knives(widths, kw_nan) == truth.tolist()


def test_match_margin_is_large_for_distinct_knives_and_near_one_for_equal_ones():
    rng = np.random.default_rng(7)
    kw = np.array([1.2, 1.5, 1.8, 1.35])
    i = np.arange(9)
    widths = kw[(2 - i) % 4] + rng.normal(0, 0.005, i.size)
    assert knife_match_margin(widths, kw) > 100 * UNAMBIGUOUS_MARGIN
    equal = np.full(4, 1.5)
    assert knife_match_margin(1.5 + rng.normal(0, 0.005, i.size), equal) == pytest.approx(1.0)
    assert knife_match_margin(widths, [1.5]) == 1.0


def test_mark_knives_of_nothing_is_empty():
    assert mark_knives([], [1.0, 2.0]) == []
    assert mark_knives([1.0, 2.0], []) == []


def test_result_json_is_strict_json_with_decimated_profile_and_every_mark():
    rng = np.random.default_rng(1)
    meas = _measurement(rng)
    d = result_json(_result(7, meas), max_points=300)
    text = json.dumps(d, allow_nan=False)  # no NaN anywhere
    assert json.loads(text) == d
    prof = d["profile"]
    assert 2 <= len(prof["x_mm"]) <= 300 and len(prof["x_mm"]) == len(prof["height_um"])
    assert prof["x_mm"][0] == pytest.approx(meas.x_mm[0])
    assert prof["x_mm"][-1] == pytest.approx(meas.x_mm[-1])
    assert len(d["marks"]) == meas.mark_widths_mm.size
    for m, lo, hi, w in zip(d["marks"], meas.cusps_mm[:-1], meas.cusps_mm[1:],
                            meas.mark_widths_mm, strict=True):
        assert m["lo_mm"] == pytest.approx(lo, abs=1e-3)
        assert m["hi_mm"] == pytest.approx(hi, abs=1e-3)
        assert m["width_mm"] == pytest.approx(w, abs=1e-4)
        assert 0 <= m["knife"] < 4
    assert d["knife_source"] in ("widths", "widths-ambiguous")
    assert d["offsets_um"][2] is None and d["roll_confidence"] is None
    assert d["calibration"]["trusted"] is True
    assert d["pitch_mm"] == pytest.approx(meas.pitch_mm, abs=1e-4)


def test_result_json_prefers_the_services_attribution_and_its_reported_figures():
    # The page shows what the quality record holds: the attribution's pitch and CV (the travel
    # per pass and the kinematic CV when a knife left no mark), not the vision's.
    meas = _measurement(np.random.default_rng(2), marks=3)
    named = [2, 1, 0]
    passes = {"pass_pitch_mm": 1.55, "pitch_mm": 1.5, "uniformity_cv": 0.75, "knife": named}
    d = result_json(_result(1, meas, extra={"passes": passes}))
    assert [m["knife"] for m in d["marks"]] == named
    assert d["knife_source"] == "attribution"
    assert d["pitch_mm"] == pytest.approx(1.5)
    assert d["uniformity_cv"] == pytest.approx(0.75)
    assert d["uniformity_cv"] != pytest.approx(meas.uniformity_cv)


def test_failed_pair_has_no_metrics_profile_or_marks():
    d = result_json(_result(3, None, ok=False, knife_widths=()))
    assert d["ok"] is False and d["error"].startswith("registration failed")
    assert d["pitch_mm"] is None and d["uniformity_cv"] is None
    assert d["profile"] is None and d["marks"] == []
    json.dumps(d, allow_nan=False)


def test_status_and_event_json_are_plain():
    s = status_json(_status(2.0))
    assert s["feed_actual_mm_s"] is None and s["state"] == "run"
    e = event_json(ServiceEvent(1.25, EventKind.SAFE_STATE, "safe state: plc gone", "plc gone"))
    assert e == {"t_s": 1.25, "kind": "safe_state", "text": "safe state: plc gone",
                 "reason": "plc gone"}


class _FakeService:
    def __init__(self, *, keep: bool = True, counts_per_mm: float = 100.0) -> None:
        self.events: list = []
        self.results: list = []
        self.keep_results = keep
        self.pipeline = SimpleNamespace(last=None)
        self.plc = SimpleNamespace(last=SimpleNamespace(counts_per_mm=counts_per_mm))
        self.quality_class = QualityClass(name="fine", target_pitch_mm=1.5, pitch_tolerance=0.02,
                                          uniformity_max_cv=0.05)
        self.t = 0.0

    def status(self) -> ServiceStatus:
        return _status(self.t)


def test_live_view_follows_events_results_and_status_once_each():
    rng = np.random.default_rng(3)
    svc = _FakeService()
    view = LiveView(history=5)
    seen: dict = {}
    view.follow_once(svc, seen)
    snap = view.snapshot()
    assert snap["status"]["t_s"] == 0.0 and snap["last"] is None
    assert snap["quality_class"]["pitch_lo_mm"] == pytest.approx(1.47)
    v0 = snap["version"]
    for k in range(8):
        svc.results.append(_result(k, _measurement(rng), counts=5000 + 1500 * k))
        svc.events.append(ServiceEvent(k * 0.1, EventKind.FEED_ACCEPTED, f"event {k}"))
        svc.t = k * 0.1
        view.follow_once(svc, seen)
        view.follow_once(svc, seen)  # nothing new: nothing taken twice
    snap = view.snapshot()
    assert snap["version"] > v0
    assert [e["text"] for e in snap["events"]] == [f"event {k}" for k in range(8)]
    assert [r["seq"] for r in snap["trace"]] == [3, 4, 5, 6, 7]  # history keeps the newest 5
    # along the board: counts from the first pair over counts_per_mm
    assert [r["board_m"] for r in snap["trace"]] == pytest.approx(
        [1500 * k / 100.0 / 1000.0 for k in range(3, 8)])
    assert snap["last"]["seq"] == 7
    json.dumps(snap, allow_nan=False)


def test_live_view_without_result_list_takes_the_newest_result_and_restarts_on_new_service():
    rng = np.random.default_rng(4)
    svc = _FakeService(keep=False)
    view = LiveView()
    seen: dict = {}
    svc.pipeline.last = _result(10, _measurement(rng))
    view.follow_once(svc, seen)
    view.follow_once(svc, seen)
    assert [r["seq"] for r in view.snapshot()["trace"]] == [10]
    svc2 = _FakeService()
    svc2.events.append(ServiceEvent(0.0, EventKind.RECOVERED, "recovered"))
    view.follow_once(svc2, seen)
    view.follow_once(svc2, seen)
    assert [e["text"] for e in view.snapshot()["events"]] == ["recovered"]


def test_wait_changed_returns_the_new_version_at_once_when_changed():
    view = LiveView()
    v = view.version
    view.event(ServiceEvent(0.0, EventKind.RECOVERED, "recovered"))
    assert view.wait_changed(v, timeout_s=30.0) == v + 1


@pytest.mark.parametrize("bad", [{"history": 0}, {"max_events": 0}])
def test_live_view_rejects_bad_sizes(bad):
    with pytest.raises(ValueError):
        LiveView(**bad)
