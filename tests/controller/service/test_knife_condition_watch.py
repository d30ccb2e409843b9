"""The service's knife condition: tables noted on the pair path, the forecast only between pairs.

:meth:`KnifeConditionWatch.note` (inside a pair's control) only files the table in force; the
forecast (1-2 ms) is :meth:`KnifeConditionWatch.renew`'s, which the pipeline calls after a pair's
record (``ControlLoops.between_pairs``): when no later pair waits, or when it is long overdue.
Simulated time throughout.
"""

from __future__ import annotations

import numpy as np
import pytest

from config.machine import machine_from_dict
from controller.fieldbus.plc_protocol import PlcSnapshot
from controller.laws.knife_condition import KnifeConditionTracker
from controller.laws.limits import project_zero_mean_box
from controller.service.events import EventKind, EventLog
from controller.service.loops import (
    CONDITION_EVERY_S,
    CONDITION_LATE_S,
    JOINTING_WARN_BOARDS,
    KnifeConditionWatch,
)

FEED = 600.0  # mm/s
STROKE = 6.0
RATES = np.array([-0.12, 0.04, 0.04, 0.04])  # knife 0 wears back, um of offset per m of board


def _snap():
    return PlcSnapshot(values={
        "knives": 4, "feed_min_mm_s": 50.0, "feed_max_mm_s": 1000.0, "spindle_rpm": 6000.0,
        "cutterhead_radius_mm": 60.0, "cutter_to_camera_mm": 300.0, "feed_setpoint_mm_s": FEED,
        "feed_actual_mm_s": FEED}, t_s=0.0)


def _watch():
    cfg = machine_from_dict({"piezo": {"stroke_um": STROKE}})
    report = EventLog()
    return KnifeConditionWatch(cfg, report), report


def _pairs(watch, *, until_s, dt=0.1, t0=0.0, renew=None):
    """Pairs every ``dt`` s: the board travels, the loop's table follows the wear."""
    snap = _snap()
    t = t0
    while t < until_s - 1e-9:
        t += dt
        watch.travel(t, snap)
        needed = RATES * watch.board_travel_m
        watch.note(t, project_zero_mean_box(needed - needed.mean(), bound=STROKE),
                   limit_um=STROKE)
        if renew is not None:
            renew(t)
    return t


def test_noting_tables_never_computes_a_forecast(monkeypatch):
    watch, _ = _watch()
    calls = []
    real = KnifeConditionTracker.forecast
    monkeypatch.setattr(KnifeConditionTracker, "forecast",
                        lambda self, **kw: calls.append(kw) or real(self, **kw))
    _pairs(watch, until_s=30.0)  # 18 m of board, 300 tables: the pair path only
    assert calls == [] and watch.describe() is None and watch.due
    assert watch.tracker.span_m == pytest.approx(10.0, abs=0.1)  # the tables were filed


def test_between_pairs_the_forecast_is_renewed_every_period_and_matches_the_tracker():
    watch, _ = _watch()
    renewed = []
    t = _pairs(watch, until_s=30.0,
               renew=lambda t: renewed.append(t) if watch.renew(t, idle=True) else None)
    gaps = np.diff(renewed)
    assert len(renewed) >= 14 and np.all(gaps >= CONDITION_EVERY_S - 1e-9)
    assert np.all(gaps <= CONDITION_EVERY_S + 0.1 + 1e-9)  # within a pair of the period
    kc = watch.describe()
    q = watch.cfg.quality
    direct = watch.tracker.forecast(pitch_mm=q.target_pitch_mm, radius_mm=60.0,
                                    cv_max=q.uniformity_max_cv, feed_mm_s=FEED,
                                    board_length_mm=q.board_length_mm)
    assert kc["t_s"] == renewed[-1] and t - kc["t_s"] < CONDITION_EVERY_S
    assert kc["state"] == direct.state.value == "due" and kc["knife"] == 0
    # the tables since the last forecast moved the figures by less than a pair's travel
    assert kc["due_in_m"] == pytest.approx(direct.due_in_m + (t - kc["t_s"]) * FEED * 1e-3,
                                           abs=0.2)
    assert kc["knives"][0]["drift_um_per_m"] == pytest.approx(RATES[0] - RATES.mean(), rel=0.05)


def test_while_pairs_wait_the_forecast_waits_until_it_is_long_overdue():
    watch, _ = _watch()
    busy = []
    _pairs(watch, until_s=30.0,
           renew=lambda t: busy.append(t) if watch.renew(t, idle=False) else None)
    # due from the first table at 0.1 s: renewed at the first pair CONDITION_LATE_S later
    assert busy[0] == pytest.approx(0.1 + CONDITION_LATE_S, abs=0.1 + 1e-9)
    assert np.all(np.diff(busy) >= CONDITION_EVERY_S + CONDITION_LATE_S - 1e-9)
    assert watch.renew(busy[-1] + CONDITION_EVERY_S, idle=True)  # idle: at once


def test_without_a_new_table_nothing_is_renewed_and_the_operator_is_told_once():
    watch, report = _watch()
    t = _pairs(watch, until_s=60.0, renew=lambda t: watch.renew(t, idle=True))
    told = [e for e in report.events if e.kind is EventKind.JOINTING_DUE]
    assert len(told) == 1 and told[0].data["knife"] == 0
    assert told[0].data["due_in_boards"] <= JOINTING_WARN_BOARDS
    assert watch.due and watch.renew(t + CONDITION_EVERY_S, idle=True)  # the last tables'
    assert not watch.due
    assert not watch.renew(t + 100.0, idle=True)  # no table came: the last forecast stands
    assert len([e for e in report.events if e.kind is EventKind.JOINTING_DUE]) == 1


def test_without_wear_the_forecast_says_no_trend_not_due_wherever_it_shows():
    """No wear: the loop's tables wander (0.05 um, correlated 0.8 from pair to pair) about a
    fixed table. Every forecast after the fit's span is not due for want of a trend, with no
    figures and no JOINTING_DUE; the OPC UA values, the quality record's fields and the
    report's words say so."""
    from controller.opcua.view import knife_condition_values
    from controller.quality.knife_report import forecast_text
    from controller.quality.log import QualityRecord, utc_iso
    from controller.quality.schema import knife_condition_fields
    from controller.service.status import ServiceStatus

    watch, report = _watch()
    rng = np.random.default_rng(7)
    base, wander = np.array([1.5, -2.0, 0.3, 0.2]), np.zeros(4)
    snap, t, shown = _snap(), 0.0, []
    while t < 60.0:  # 36 m of board
        t += 0.1
        watch.travel(t, snap)
        wander = 0.8 * wander + rng.normal(0.0, 0.05 * 0.6, 4)
        table = base + wander
        watch.note(t, table - table.mean(), limit_um=STROKE)
        if watch.renew(t):
            shown.append(watch.describe())
    fitted = [kc for kc in shown if kc["state"] != "fitting"]
    assert len(fitted) >= 25 and all(kc["trend"] == "unknown" for kc in shown
                                     if kc["state"] == "fitting")
    for kc in fitted:
        assert (kc["state"], kc["trend"]) == ("not_due", "none"), kc
        assert kc["due_in_m"] is None and kc["due_in_boards"] is None and kc["knife"] is None
        assert kc["text"].startswith("knife condition: no wear trend") and "not due" in kc["text"]
    assert not [e for e in report.events if e.kind is EventKind.JOINTING_DUE]

    kc = fitted[-1]
    status = ServiceStatus(
        t_s=t, state="run", safe_reason=None, missing=(), feed_setpoint_mm_s=FEED,
        feed_actual_mm_s=FEED, offsets_um=(0.0,) * 4, amplifier_enabled=True,
        last_measurement=None, counters=ServiceStatus.freeze({}), alerts={},
        knife_condition=kc)
    ua = knife_condition_values(status)
    assert (ua["JointingState"], ua["JointingTrend"]) == ("not_due", "none")
    assert ua["JointingForecast"] == kc["text"] and ua["JointingKnife"] == -1
    assert np.isnan(ua["JointingDueM"]) and np.isnan(ua["JointingDueBoards"])
    fields = knife_condition_fields(kc)
    assert fields["jointing_state"] == "not_due" and fields.get("jointing_due_m") is None
    rec = QualityRecord(t_s=t, wall_time=utc_iso(1.7e9), seq=0, board_id=0,
                        board_position_mm=0.0, ok=True, **fields)
    assert forecast_text(rec).startswith("no jointing due: no wear trend")
