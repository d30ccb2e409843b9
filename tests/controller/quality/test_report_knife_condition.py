"""``planer report`` on the knife condition: the last forecast, wear and reserve, the trend figure.

A log whose records carry the knife condition (schema version 6) gets a summary of it (the last
forecast in words, where the forecasts put the jointing, each knife's wear and reserve) and a
figure along the board travelled; a log without it gets neither.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from controller.quality.knife_report import forecast_text, knife_summary
from controller.quality.log import QualityLog, QualityRecord, utc_iso
from controller.quality.report import build_figures, format_summary, summarise
from planer.cli import main

STROKE = 6.0
WEAR = -0.2  # knife 0's drift, um of offset per m of board


def _records(n: int = 40) -> list[QualityRecord]:
    """Pairs every 0.75 m: knife 0 wears, fitted from 3 m on, out of stroke at 30 m."""
    recs = []
    for i in range(n):
        x = 0.75 * i
        fitted = x >= 3.0
        offset0 = max(WEAR * x, -STROKE)
        reserves = (STROKE + offset0, STROKE, STROKE, STROKE)
        drifts = (WEAR, 0.05, 0.05, 0.05) if fitted else (np.nan,) * 4
        kw = {}
        if not fitted:
            kw["jointing_state"] = "fitting"
        elif reserves[0] > 0:
            due_m = 30.0 - x + (0.5 if i % 2 else -0.5)  # the forecast wobbles by 0.5 m
            kw.update(jointing_state="due", jointing_due_m=due_m, jointing_due_boards=due_m / 4,
                      jointing_due_h=due_m / 0.6 / 3600, jointing_knife=0)
        else:
            kw.update(jointing_state="due", jointing_due_m=0.0, jointing_due_boards=0.0,
                      jointing_due_h=0.0, jointing_knife=0)
        recs.append(QualityRecord(
            t_s=1.25 * i, wall_time=utc_iso(1.7e9 + 1.25 * i), seq=i, board_id=1 + i // 6,
            board_position_mm=750.0 * (i % 6), ok=True, pitch_mm=1.5, uniformity_cv=0.01,
            mark_widths_mm=(1.5,) * 4, depth_um=4.0, piezo_offsets_um=(offset0, 0.0, 0.0, 0.0),
            board_travel_m=x, knife_drift_um_per_m=drifts, knife_reserve_um=reserves, **kw))
    return recs


def test_the_summary_holds_the_last_forecast_and_where_the_forecasts_put_the_jointing():
    recs = _records(36)  # to 26.25 m: still due ahead
    ks = summarise(recs)["knife_condition"]
    last = recs[-1]
    assert ks["n_records"] == 36
    assert ks["board_travel_m"] == {"first": 0.0, "last": 26.25}
    assert ks["last"]["state"] == "due" and ks["last"]["knife"] == 0
    assert ks["last"]["due_at_m"] == pytest.approx(last.board_travel_m + last.jointing_due_m)
    assert ks["due_at_m"]["min"] == pytest.approx(29.5) and ks["due_at_m"]["max"] == 30.5
    k0 = ks["knives"][0]
    assert k0["drift_um_per_m"] == WEAR
    assert k0["reserve_um"] == pytest.approx(STROKE + WEAR * 26.25)
    assert k0["min_reserve_um"] == k0["reserve_um"]  # it only went down
    assert ks["knives"][1]["reserve_um"] == STROKE
    text = format_summary(summarise(recs))
    assert (f"Knife condition at 26.2 m of board: jointing due in "
            f"{last.jointing_due_boards:.0f} boards / {last.jointing_due_h:.2f} h") in text
    assert "knife 0: wear -0.200 µm/m, reserve 0.75 µm" in text
    assert "jointing due at 29.5 .. 30.5 m of board" in text


def test_due_now_fitting_and_not_due_are_said_in_words():
    recs = _records(44)  # past 30 m: knife 0 at the end of its stroke
    assert knife_summary(recs)["last"]["text"].startswith("jointing due now (knife 0)")
    assert forecast_text(recs[0]).startswith("fitting")
    assert "no jointing due" in forecast_text(
        QualityRecord(t_s=0.0, wall_time=utc_iso(1.7e9), seq=0, board_id=0,
                      board_position_mm=0.0, ok=True, board_travel_m=1.0,
                      jointing_state="not_due"))


def test_the_figure_draws_reserve_wear_and_forecast_along_the_board_travelled():
    recs = _records(44)
    fig = build_figures(recs)["knife_condition"]
    ax_r, ax_w, ax_f = fig.axes
    x = np.array([r.board_travel_m for r in recs])

    def series(ax, label):
        (ln,) = [ln for ln in ax.get_lines() if ln.get_label() == label]
        return np.asarray(ln.get_xdata(), float), np.asarray(ln.get_ydata(), float)

    rx, ry = series(ax_r, "knife 0")
    np.testing.assert_allclose(rx, x)
    np.testing.assert_allclose(ry, [r.knife_reserve_um[0] for r in recs])
    wx, wy = series(ax_w, "knife 0")
    assert np.isnan(wy[:4]).all() and np.all(wy[4:] == WEAR)  # fitting: no wear drawn
    fx, fy = series(ax_f, "jointing due at (m of board)")
    due = [r.board_travel_m + r.jointing_due_m if r.jointing_state == "due" else np.nan
           for r in recs]
    np.testing.assert_allclose(fy, due)
    nx, _ = series(ax_f, "due now (a knife at the end of its stroke)")
    assert nx.min() > 30.0 - 1e-9  # the reserve is gone from 30 m on
    assert "jointing due now" in ax_f.get_title()
    assert "µm" in ax_r.get_ylabel() and "(m)" in ax_f.get_xlabel()


def test_a_log_without_the_knife_condition_has_no_summary_nor_figure():
    recs = [QualityRecord(t_s=0.1 * i, wall_time=utc_iso(1.7e9), seq=i, board_id=1,
                          board_position_mm=10.0 * i, ok=True) for i in range(3)]
    assert summarise(recs)["knife_condition"] is None
    assert "knife_condition" not in build_figures(recs)
    assert "Knife condition" not in format_summary(summarise(recs))


def test_planer_report_prints_the_forecast_and_writes_the_figure(tmp_path, capsys):
    log = tmp_path / "run.sqlite"
    with QualityLog(log) as q:
        for r in _records(36):
            q.append(r)
    assert main(["report", str(log), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["knife_condition"]["last"]["knife"] == 0
    png = out["figures"]["knife_condition"]
    assert png.endswith("run_knife_condition.png") and (tmp_path / png).stat().st_size > 10_000
