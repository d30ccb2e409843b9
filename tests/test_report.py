"""``planer report`` and controller.report: summary numbers, figures, command line."""

from __future__ import annotations

import csv
import json
import random

import numpy as np
import pytest

from controller.quality_log import QualityClass, QualityLog, QualityRecord, judge, utc_iso
from controller.report import (
    DEFAULT_PITCH_TOLERANCE,
    board_axis,
    build_figures,
    failure_reason,
    format_summary,
    last_profile,
    summarise,
)
from planer.cli import main

QC = QualityClass("furniture-1.5", 1.5, 0.02, 0.05, 8.0)
REASONS = ("registration failed: confidence 0.2", "unreadable pair: saturated",
           "registration failed: shift out of range", "implausible metrics: pitch 9 mm")


def make_run(seed: int = 0, *, boards=(11, 12, 13), per_board: int = 25, knives: int = 4,
             profile_every: int = 7) -> list[QualityRecord]:
    """A synthetic run: pitch settling on 1.5 mm, offsets learning, some failures, profiles."""
    rng = random.Random(seed)
    recs, seq, t = [], 0, 0.0
    offs = np.zeros(knives)
    for b in boards:
        for j in range(per_board):
            seq += 1
            t += 0.1
            feed = 600.0 * (1 - 0.2 * np.exp(-seq / 10))
            offs = offs + 0.2 * (np.arange(knives) - offs)
            common = dict(t_s=t, wall_time=utc_iso(1.75e9 + t), seq=seq, board_id=b,
                          board_position_mm=30.0 + 60.0 * j, feed_setpoint_mm_s=feed,
                          piezo_offsets_um=offs.copy(), target_pitch_mm=1.5,
                          true_pitch_mm=feed / 400, true_uniformity_cv=0.1 * np.exp(-seq / 15))
            if rng.random() < 0.12:
                recs.append(QualityRecord(ok=False, error=rng.choice(REASONS), **common))
                continue
            m = dict(pitch_mm=feed / 400 * (1 + rng.gauss(0, 0.01)),
                     uniformity_cv=abs(0.1 * np.exp(-seq / 15) + rng.gauss(0, 0.005)),
                     depth_um=4.7 + rng.gauss(0, 0.3))
            extra = {}
            if seq % profile_every == 0:
                x = np.linspace(0, 10, 50)
                extra["profile"] = {"x_mm": x.tolist(), "height_um": (np.sin(x) + seq).tolist()}
            recs.append(QualityRecord(ok=True, mark_widths_mm=[m["pitch_mm"]] * knives,
                                      passed=judge(m, QC), extra=extra, **m, **common))
    return recs


def _mean(xs):
    xs = [x for x in xs if x is not None]
    return sum(xs) / len(xs) if xs else None


# --------------------------------------------------------------------------------------------
# summary


@pytest.mark.parametrize("error, reason", [
    ("registration failed: confidence 0.2", "registration failed"),
    ("unreadable pair", "unreadable pair"), ("  x : y : z", "x"), ("", "unknown"),
    (None, "unknown"), (": nothing before", "unknown"),
])
def test_failure_reason(error, reason):
    assert failure_reason(error) == reason


def test_summary_matches_independent_counts():
    recs = make_run(3)
    s = summarise(recs, quality_class=QC)
    failed = [r for r in recs if not r.ok]
    assert s["n_records"] == len(recs) and s["n_failed"] == len(failed)
    assert s["n_ok"] + s["n_failed"] == s["n_records"]
    assert sum(s["failures"].values()) == len(failed)
    assert s["failures"] == {why: sum(failure_reason(r.error) == why for r in failed)
                             for why in {failure_reason(r.error) for r in failed}}
    counts = list(s["failures"].values())
    assert counts == sorted(counts, reverse=True)
    judged = [r.passed for r in recs if r.passed is not None]
    assert s["n_judged"] == len(judged)
    assert s["pass_rate"] == pytest.approx(sum(judged) / len(judged))
    assert [b["board_id"] for b in s["boards"]] == [11, 12, 13]
    for b in s["boards"]:
        rs = [r for r in recs if r.board_id == b["board_id"]]
        good = [r for r in rs if r.ok]
        assert b["n_records"] == len(rs) and b["n_failed"] == len(rs) - len(good)
        assert b["mean_pitch_mm"] == pytest.approx(np.mean([r.pitch_mm for r in good]))
        assert b["std_pitch_mm"] == pytest.approx(np.std([r.pitch_mm for r in good], ddof=1))
        assert b["mean_uniformity_cv"] == pytest.approx(_mean([r.uniformity_cv for r in good]))
        assert b["mean_depth_um"] == pytest.approx(_mean([r.depth_um for r in good]))
        pj = [r.passed for r in rs if r.passed is not None]
        assert b["pass_rate"] == pytest.approx(sum(pj) / len(pj))
        assert b["position_mm"]["min"] == min(r.board_position_mm for r in rs)
        assert b["mean_true_pitch_mm"] == pytest.approx(_mean([r.true_pitch_mm for r in rs]))
    feed = [r.feed_setpoint_mm_s for r in recs]
    assert s["setpoints"]["feed_mm_s"] == {"min": min(feed), "max": max(feed), "last": feed[-1]}
    for k, row in enumerate(s["setpoints"]["piezo_offsets_um"]):
        vals = [r.piezo_offsets_um[k] for r in recs]
        assert row == {"knife": k, "min": min(vals), "max": max(vals), "last": vals[-1]}
    assert s["quality_class"] == QC.to_dict() and s["target_pitch_mm"] == [1.5]
    json.dumps(s, allow_nan=False)  # JSON-ready


def test_summary_of_empty_and_all_failed():
    s = summarise([])
    assert s["n_records"] == 0 and s["boards"] == [] and s["pass_rate"] is None
    assert s["setpoints"]["feed_mm_s"] is None
    failed = [r for r in make_run(1) if not r.ok]
    s = summarise(failed)
    assert s["n_ok"] == 0 and all(b["mean_pitch_mm"] is None for b in s["boards"])
    for summary in (summarise([]), s, summarise(make_run(2), quality_class=QC)):
        text = format_summary(summary)
        text.encode("ascii")  # plain text for any terminal


def test_text_summary_lists_every_board_and_reason():
    recs = make_run(5)
    s = summarise(recs, quality_class=QC)
    text = format_summary(s)
    lines = text.splitlines()
    for b in s["boards"]:
        row = [ln for ln in lines if ln.split()[:1] == [str(b["board_id"])]]
        assert len(row) == 1 and f"{b['mean_pitch_mm']:.3f}" in row[0]
    for why, n in s["failures"].items():
        assert f"{why} x{n}" in text
    assert f"{100 * s['pass_rate']:.1f} %" in text


# --------------------------------------------------------------------------------------------
# figures


def test_board_axis_lays_boards_end_to_end():
    recs = make_run(0)
    x, label, starts = board_axis(recs)
    assert "(m)" in label and [b for b, _ in starts] == [11, 12, 13]
    assert np.all(np.diff([s for _, s in starts]) > 0)
    for (bid, start), nxt in zip(starts, [s for _, s in starts[1:]] + [np.inf], strict=True):
        xb = x[[r.board_id == bid for r in recs]]
        assert np.all(xb >= start) and np.all(xb < nxt)
        pos = np.array([r.board_position_mm for r in recs if r.board_id == bid])
        assert np.allclose(xb - start, pos / 1000)
    no_pos = [QualityRecord(**{**vars(r), "board_position_mm": 0.0}) for r in recs]
    x, label, starts = board_axis(no_pos)
    assert "time" in label and starts == [] and np.allclose(x, [r.t_s for r in recs])


def _legend_outside(fig, ax) -> bool:
    fig.canvas.draw()
    leg = ax.get_legend()
    return leg is not None and (leg.get_window_extent().x0
                                >= ax.get_window_extent().x1 - 1)


def test_figures_have_units_legends_and_the_last_profile():
    recs = make_run(4)
    figs = build_figures(recs, quality_class=QC)
    assert set(figs) == {"pitch_uniformity", "setpoints", "profile"}
    pu = figs["pitch_uniformity"].axes
    assert [a.get_ylabel() for a in pu] == [
        "pitch (mm)", "uniformity: CV of mark widths (-)", "mark depth (µm)"]
    assert "(m)" in pu[-1].get_xlabel()
    labels = pu[0].get_legend_handles_labels()[1]
    assert {"target", "true (simulator)", "measured, pass", "failed measurement"} <= set(labels)
    assert any(lab.startswith("tolerance ±2 %") for lab in labels)
    sp = figs["setpoints"].axes
    assert sp[0].get_ylabel() == "feed setpoint (mm/s)" and "(µm" in sp[1].get_ylabel()
    assert sp[1].get_legend_handles_labels()[1] == [f"knife {k}" for k in range(4)]
    for fig in figs.values():
        for ax in fig.axes:
            assert _legend_outside(fig, ax)  # legends never cover data
    # the profile figure draws the newest record with a profile
    newest = [r for r in recs if "profile" in r.extra][-1]
    (line,) = [ln for ln in figs["profile"].axes[0].get_lines()
               if ln.get_label() == "measured height"]
    assert np.allclose(line.get_ydata(), newest.extra["profile"]["height_um"])
    assert last_profile(recs)[0] is newest


def test_figures_without_quality_class_or_profile():
    recs = [QualityRecord(**{**vars(r), "extra": {}}) for r in make_run(6)]
    figs = build_figures(recs)
    assert set(figs) == {"pitch_uniformity", "setpoints"}
    labels = figs["pitch_uniformity"].axes[0].get_legend_handles_labels()[1]
    assert f"tolerance ±{100 * DEFAULT_PITCH_TOLERANCE:g} % (default)" in labels
    assert build_figures([]) == {}
    bad = [QualityRecord(**{**vars(recs[0]), "extra": {"profile": {"x_mm": [1, 2, 3],
                                                                   "height_um": [1]}}})]
    assert last_profile(bad) is None


# --------------------------------------------------------------------------------------------
# command line


@pytest.fixture
def log_file(tmp_path):
    path = tmp_path / "run.db"
    with QualityLog(path) as log:
        log.set_quality_class(QC)
        for r in make_run(8):
            log.append(r)
    return path


def test_cli_json_figures_and_csv(log_file, tmp_path, capsys):
    out = tmp_path / "figs"
    code = main(["report", str(log_file), "--out", str(out), "--csv",
                 str(tmp_path / "run.csv"), "--json"])
    assert code == 0
    s = json.loads(capsys.readouterr().out)
    recs = make_run(8)
    assert s["n_records"] == len(recs) and s["n_failed"] == sum(not r.ok for r in recs)
    assert set(s["figures"]) == {"pitch_uniformity", "setpoints", "profile"}
    for path in s["figures"].values():
        with open(path, "rb") as fh:
            assert fh.read(8) == b"\x89PNG\r\n\x1a\n"
        assert path.startswith(str(out))
    with open(s["csv"], newline="") as fh:
        assert len(list(csv.DictReader(fh))) == len(recs)


def test_cli_text_default_out_next_to_log(log_file, capsys):
    assert main(["report", str(log_file)]) == 0
    text = capsys.readouterr().out
    assert "Quality class furniture-1.5" in text and "Figures:" in text
    assert (log_file.parent / "run_pitch_uniformity.png").is_file()
    assert (log_file.parent / "run_setpoints.png").is_file()


def test_cli_empty_log(tmp_path, capsys):
    QualityLog(tmp_path / "e.db").close()
    assert main(["report", str(tmp_path / "e.db"), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["n_records"] == 0 and s["figures"] == {}


@pytest.mark.parametrize("content", [None, b"", b"not a database at all" * 100])
def test_cli_missing_or_corrupt_log(tmp_path, capsys, content):
    path = tmp_path / "bad.db"
    if content is not None:
        path.write_bytes(content)
    assert main(["report", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("planer report: error:") and "\n" not in err
    assert str(path) in err
    assert not list(tmp_path.glob("*.png"))
