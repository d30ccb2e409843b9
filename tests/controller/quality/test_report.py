"""``planer report`` and controller.quality.report: summary numbers, figures, command line."""

from __future__ import annotations

import csv
import json
import random

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.quality.log import QualityClass, QualityLog, QualityRecord, judge, utc_iso
from controller.quality.report import (
    DEFAULT_PITCH_TOLERANCE,
    KINEMATIC_LABEL,
    UNTRUSTED_LABEL,
    board_axis,
    build_figures,
    failure_reason,
    format_summary,
    last_profile,
    record_state,
    safe_spans,
    summarise,
)
from planer.cli import main

QC = QualityClass("furniture-1.5", 1.5, 0.02, 0.05, 8.0)
REASONS = ("registration failed: confidence 0.2", "unreadable pair: saturated",
           "registration failed: shift out of range", "implausible metrics: pitch 9 mm")


def make_run(seed: int = 0, *, boards=(11, 12, 13), per_board: int = 25, knives: int = 4,
             profile_every: int = 7, board_gap_s: float = 0.0,
             safe_seqs=()) -> list[QualityRecord]:
    """A synthetic run: pitch settling on 1.5 mm, offsets learning, some failures, profiles.

    ``board_gap_s``: pause between boards; ``safe_seqs``: records taken in the safe state.
    """
    rng = random.Random(seed)
    recs, seq, t = [], 0, 0.0
    offs = np.zeros(knives)
    for n, b in enumerate(boards):
        t += board_gap_s if n else 0.0
        for j in range(per_board):
            seq += 1
            t += 0.1
            feed = 600.0 * (1 - 0.2 * np.exp(-seq / 10))
            offs = offs + 0.2 * (np.arange(knives) - offs)
            common = dict(t_s=t, wall_time=utc_iso(1.75e9 + t), seq=seq, board_id=b,
                          board_position_mm=30.0 + 60.0 * j, feed_setpoint_mm_s=feed,
                          piezo_offsets_um=offs.copy(), target_pitch_mm=1.5,
                          true_pitch_mm=feed / 400, true_uniformity_cv=0.1 * np.exp(-seq / 15))
            state = {"state": "safe" if seq in safe_seqs else "run"}
            if rng.random() < 0.12:
                recs.append(QualityRecord(ok=False, error=rng.choice(REASONS), extra=state,
                                          **common))
                continue
            m = dict(pitch_mm=feed / 400 * (1 + rng.gauss(0, 0.01)),
                     uniformity_cv=abs(0.1 * np.exp(-seq / 15) + rng.gauss(0, 0.005)),
                     depth_um=4.7 + rng.gauss(0, 0.3))
            extra = dict(state)
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
        # plain text for any terminal: ASCII but for the unit µm (Latin-1, and UTF-8)
        assert set(text.encode("ascii", "ignore").decode()) | {"µ"} >= set(text), text
        text.encode("latin-1")


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


def _data_axes(fig):
    """The figure's panels (the board labels' secondary axes are their children)."""
    return list(fig.axes)


def _series(ax, label):
    """x, y of the line drawn with ``label`` (empty arrays when there is none)."""
    for ln in ax.get_lines():
        if ln.get_label() == label:
            return np.asarray(ln.get_xdata(), float), np.asarray(ln.get_ydata(), float)
    return np.array([]), np.array([])


def test_figures_have_units_legends_and_the_last_profile():
    recs = make_run(4)
    figs = build_figures(recs, quality_class=QC)
    assert set(figs) == {"pitch_uniformity", "setpoints", "profile"}
    pu = _data_axes(figs["pitch_uniformity"])
    assert [a.get_ylabel() for a in pu] == [
        "pitch (mm)", "uniformity: CV of mark widths (-)", "mark depth (µm)"]
    assert "(m)" in pu[-1].get_xlabel()
    labels = pu[0].get_legend_handles_labels()[1]
    assert {"target", "true (simulator)", "measured, within tolerance",
            "failed measurement"} <= set(labels)
    assert any(lab.startswith("tolerance ±2 %") for lab in labels)
    sp = _data_axes(figs["setpoints"])
    assert sp[0].get_ylabel() == "feed setpoint (mm/s)" and "(µm" in sp[1].get_ylabel()
    assert sp[1].get_legend_handles_labels()[1] == [f"knife {k}" for k in range(4)]
    for fig in figs.values():
        assert fig.get_suptitle()  # says what the figure is about
        for ax in _data_axes(fig):
            assert ax.get_title()  # says what to look at
            assert _legend_outside(fig, ax)  # legends never cover data
    # the profile figure draws the newest record with a profile
    newest = [r for r in recs if "profile" in r.extra][-1]
    (line,) = [ln for ln in figs["profile"].axes[0].get_lines()
               if ln.get_label() == "measured height"]
    assert np.allclose(line.get_ydata(), newest.extra["profile"]["height_um"])
    assert last_profile(recs)[0] is newest


def test_each_panel_colours_points_by_its_own_verdict():
    """Pitch by the tolerance band, uniformity and depth by their limits, not by ``passed``."""
    qc = QualityClass("tight", 1.5, 0.02, uniformity_max_cv=0.03, depth_max_um=4.8)
    recs = [QualityRecord(**{**vars(r), "passed": judge(r, qc) if r.ok else None})
            for r in make_run(9)]
    figs = build_figures(recs, quality_class=qc)
    ax_p, ax_u, ax_d = _data_axes(figs["pitch_uniformity"])
    # records whose pitch is on target but which fail the class through uniformity or depth
    assert any(r.passed is False and abs(r.pitch_mm / 1.5 - 1) <= 0.02 for r in recs if r.ok)
    for ax, name, ok in (
        (ax_p, "pitch_mm", lambda r: abs(r.pitch_mm / r.target_pitch_mm - 1) <= 0.02 + 1e-9),
        (ax_u, "uniformity_cv", lambda r: r.uniformity_cv <= qc.uniformity_max_cv),
        (ax_d, "depth_um", lambda r: r.depth_um <= qc.depth_max_um),
    ):
        good = sorted(getattr(r, name) for r in recs if r.ok and ok(r))
        bad = sorted(getattr(r, name) for r in recs if r.ok and not ok(r))
        assert good and bad  # both verdicts occur in this run
        labels = ("measured, within tolerance", "measured, outside tolerance") \
            if name == "pitch_mm" else ("measured, within limit", "measured, above limit")
        assert sorted(_series(ax, labels[0])[1]) == good, name
        assert sorted(_series(ax, labels[1])[1]) == bad, name


def test_safe_state_is_shaded_on_both_figures():
    safe = set(range(1, 4)) | set(range(30, 38))
    recs = make_run(2, safe_seqs=safe, board_gap_s=2.0)
    assert [record_state(r) for r in recs].count("safe") == len(safe)
    figs = build_figures(recs, quality_class=QC)
    x, _, _ = board_axis(recs)
    t = np.array([r.t_s for r in recs])
    for fig, coord in ((figs["pitch_uniformity"], x), (figs["setpoints"], t)):
        spans = safe_spans(coord, [r.seq in safe for r in recs])
        assert len(spans) == 2
        axes = _data_axes(fig)
        assert "safe state (control paused)" in axes[0].get_legend_handles_labels()[1]
        for ax in axes:
            drawn = sorted((p.get_x(), p.get_x() + p.get_width()) for p in ax.patches)
            assert np.allclose(drawn, spans)


def test_setpoints_shade_the_services_own_safe_periods():
    """Safe states between boards leave no record; the service's periods show them."""
    recs = make_run(2, board_gap_s=3.0)
    t_end = max(r.t_s for r in recs if r.board_id == 11)
    periods = [(t_end + 0.5, t_end + 2.0)]  # inside the pause: no record was taken then
    assert not any(periods[0][0] <= r.t_s <= periods[0][1] for r in recs)
    figs = build_figures(recs, quality_class=QC, safe_periods_s=[(*periods[0], "can gone")])
    for ax in _data_axes(figs["setpoints"]):
        assert [(p.get_x(), p.get_x() + p.get_width()) for p in ax.patches] == periods
    labels = _data_axes(figs["setpoints"])[0].get_legend_handles_labels()[1]
    assert any(lab.startswith("safe state") and lab.endswith("because: can gone")
               for lab in labels)
    # on the board axis it lies in the gap between the two boards
    x, _, _ = board_axis(recs)
    end_11 = max(x[[r.board_id == 11 for r in recs]])
    start_12 = min(x[[r.board_id == 12 for r in recs]])
    for ax in _data_axes(figs["pitch_uniformity"]):
        ((a, b),) = [(p.get_x(), p.get_x() + p.get_width()) for p in ax.patches]
        assert end_11 < a < b < start_12


def test_safe_legend_names_the_reasons():
    recs = make_run(3, safe_seqs={5, 6, 40})
    recs = [QualityRecord(**{**vars(r), "extra": {**r.extra, "safe_reason": "plc gone, can gone"
                                                  if r.seq < 10 else "confirming recovery"}})
            for r in recs]
    labels = _data_axes(build_figures(recs)["setpoints"])[0].get_legend_handles_labels()[1]
    (label,) = [lab for lab in labels if lab.startswith("safe state")]
    assert label.endswith("because: plc gone, can gone")


def test_record_state_reads_either_layout():
    r = make_run(0)[0]
    plain = QualityRecord(**{**vars(r), "extra": {"state": "SAFE"}})
    nested = QualityRecord(**{**vars(r), "extra": {"supervisor": {"state": "safe"},
                                                   "state": "run"}})
    none = QualityRecord(**{**vars(r), "extra": {}})
    assert [record_state(x) for x in (plain, nested, none)] == ["safe", "safe", None]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0.01, 5.0), st.booleans()), min_size=1, max_size=40))
def test_safe_spans_cover_safe_records_only(steps):
    x = np.cumsum([d for d, _ in steps])
    safe = [s for _, s in steps]
    spans = safe_spans(x, safe)
    runs = sum(1 for i, s in enumerate(safe) if s and (i == 0 or not safe[i - 1]))
    assert len(spans) == runs
    assert all(a <= b for a, b in spans)
    assert all(b1 < a2 for (_, b1), (a2, _) in zip(spans, spans[1:], strict=False))
    half = 0.5 * float(np.median(np.diff(x))) if x.size > 1 else 0.0
    for xi, si in zip(x, safe, strict=True):
        inside = [a <= xi <= b for a, b in spans]
        assert any(inside) if si else not any(a < xi < b for a, b in spans)
    for a, b in spans:  # never widened beyond half the typical spacing into a pause
        lo = min(v for v, s in zip(x, safe, strict=True) if s and a <= v <= b)
        hi = max(v for v, s in zip(x, safe, strict=True) if s and a <= v <= b)
        assert lo - a <= half + 1e-9 and b - hi <= half + 1e-9


def test_board_labels_sit_above_the_data():
    figs = build_figures(make_run(4), quality_class=QC)
    fig = figs["pitch_uniformity"]
    fig.canvas.draw()
    top = _data_axes(fig)[0]
    (sec,) = top.child_axes
    texts = [lab for lab in sec.get_xticklabels() if lab.get_text()]
    assert [lab.get_text() for lab in texts] == ["board 11", "board 12", "board 13"]
    box = top.get_window_extent()
    title = top.title.get_window_extent()
    for lab in texts:
        ext = lab.get_window_extent()
        assert ext.y0 >= box.y1 - 1  # above the panel, not on the points
        assert ext.y1 <= title.y0 + 1 or not ext.overlaps(title)


def test_setpoints_show_pauses_failures_and_boards():
    recs = make_run(5, board_gap_s=3.0)
    fig = build_figures(recs)["setpoints"]
    ax_f, ax_z = _data_axes(fig)
    labels = ax_f.get_legend_handles_labels()[1]
    assert "failed measurement" in labels
    assert "no measurements here: setpoint not recorded" in labels
    # the setpoint steps never bridge a pause: every stepped line stays inside one board
    t = np.array([r.t_s for r in recs])
    per_board = [(t[m].min(), t[m].max())
                 for m in (np.array([r.board_id == b for r in recs]) for b in (11, 12, 13))]
    stepped = [ln for ln in ax_f.get_lines() + ax_z.get_lines()
               if ln.get_drawstyle() == "steps-post"]
    assert len(stepped) == 3 * (1 + 4)  # feed and four knives, one line per board
    for ln in stepped:
        xs = np.asarray(ln.get_xdata(), float)
        assert any(lo <= xs.min() and xs.max() <= hi for lo, hi in per_board)
    failed = _series(ax_f, "failed measurement")[0]
    assert sorted(failed) == sorted(r.t_s for r in recs if not r.ok)


def test_long_profile_gets_an_enlarged_panel_of_two_turns():
    r = [x for x in make_run(4) if x.ok][-1]
    x = np.linspace(0.0, 50.0, 400)
    h = np.cos(2 * np.pi * x / r.pitch_mm)
    rec = QualityRecord(**{**vars(r), "extra": {"profile": {"x_mm": x.tolist(),
                                                            "height_um": h.tolist()}}})
    ax_all, ax_zoom = build_figures([rec])["profile"].axes
    (_, y_all), (xz, yz) = _series(ax_all, "measured height"), _series(ax_zoom, "measured height")
    assert np.allclose(y_all, h)  # the whole profile on top
    width = 2 * len(r.mark_widths_mm) * r.pitch_mm  # two turns of the cutterhead
    assert xz.max() - xz.min() == pytest.approx(width, abs=2 * (x[1] - x[0]))
    assert np.allclose(yz, np.interp(xz, x, h))  # the same samples, enlarged
    assert "shown enlarged below" in ax_all.get_legend_handles_labels()[1]


def test_figures_without_quality_class_or_profile():
    recs = [QualityRecord(**{**vars(r), "extra": {}}) for r in make_run(6)]
    figs = build_figures(recs)
    assert set(figs) == {"pitch_uniformity", "setpoints"}
    ax_p, ax_u, _ = _data_axes(figs["pitch_uniformity"])
    labels = ax_p.get_legend_handles_labels()[1]
    assert f"tolerance ±{100 * DEFAULT_PITCH_TOLERANCE:g} % (default)" in labels
    # without a class the uniformity has no limit: no point is called good or bad
    assert ax_u.get_legend_handles_labels()[1] == ["true (simulator)", "measured, no limit set"]
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


def test_cli_names_a_journal_left_beside_the_log(log_file, tmp_path, capsys):
    from controller.quality.journal import RecordSink, default_journal_path

    assert main(["report", str(log_file), "--json", "--out", str(tmp_path / "f")]) == 0
    assert json.loads(capsys.readouterr().out)["journal"] is None
    closed = QualityLog(log_file)
    closed.close()
    sink = RecordSink(closed, journal_path=default_journal_path(log_file))
    held = make_run(1)
    for r in held:
        sink.append(r)  # the log is closed: all go to the journal
    assert sink.close() == default_journal_path(log_file)
    assert main(["report", str(log_file), "--json", "--out", str(tmp_path / "f")]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["journal"]["records"] == len(held) and s["n_records"] == len(make_run(8))
    assert main(["report", str(log_file), "--out", str(tmp_path / "f")]) == 0
    assert f"holds {len(held)} record(s) not yet in this log" in capsys.readouterr().out


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


def test_cli_figures_are_written_whole_or_not_at_all(log_file, tmp_path, capsys, monkeypatch):
    import core.fileio

    out = tmp_path / "figs"
    out.mkdir()
    (out / "run_setpoints.png").write_bytes(b"old figure")

    def disk_full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(core.fileio.os, "fsync", disk_full)
    assert main(["report", str(log_file), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("planer report: error:") and "No space left" in err
    assert "\n" not in err
    assert sorted(p.name for p in out.iterdir()) == ["run_setpoints.png"]  # no temp files
    assert (out / "run_setpoints.png").read_bytes() == b"old figure"


# --------------------------------------------------------------------------------------------
# orientation, self-calibration, kinematic depth (schema version 4)


def _with_vision(recs, seed: int = 0):
    """``recs`` with orientation and calibration: untrusted early on each board, then applied;
    the kinematic depth 10 % above the photometric depth (fibre spring-back, say)."""
    rng = random.Random(seed)
    out = []
    for r in recs:
        k = r.board_position_mm / 60.0  # pair index on the board
        state = "untrusted" if k < 3 else "applied"
        vis = dict(roll_deg=0.4 + rng.gauss(0, 0.01), roll_confidence=0.9,
                   calibration_state=state, calibration_gain=0.8 + rng.gauss(0, 0.01),
                   calibration_gain_confidence=0.3 if state == "untrusted" else 0.9)
        if r.ok:
            vis.update(kinematic_depth_um=1.1 * r.depth_um, uncalibrated_depth_um=0.8 * r.depth_um)
        out.append(QualityRecord(**{**vars(r), **vis}))
    return out


def test_summary_of_orientation_and_calibration_matches_independent_counts():
    recs = _with_vision(make_run(5))
    s = summarise(recs, quality_class=QC)
    ok = [r for r in recs if r.ok]
    assert s["mean_kinematic_depth_um"] == pytest.approx(np.mean([1.1 * r.depth_um for r in ok]))
    v = s["vision"]
    assert v["calibration_states"] == {
        st: sum(r.calibration_state == st for r in recs) for st in ("applied", "untrusted")}
    assert v["roll_deg"] == {"min": min(r.roll_deg for r in recs),
                             "max": max(r.roll_deg for r in recs), "last": recs[-1].roll_deg}
    assert v["mean_calibration_gain"] == pytest.approx(
        np.mean([r.calibration_gain for r in recs if r.calibration_state == "applied"]))
    assert v["mean_uncalibrated_depth_um"] == pytest.approx(np.mean([0.8 * r.depth_um
                                                                     for r in ok]))
    for b in s["boards"]:
        good = [r for r in ok if r.board_id == b["board_id"]]
        assert b["mean_kinematic_depth_um"] == pytest.approx(np.mean(
            [r.kinematic_depth_um for r in good]))
    json.dumps(s, allow_nan=False)
    text = format_summary(s)
    assert "Orientation and self-calibration" in text and "kin. depth" in text
    assert f"applied x{v['calibration_states']['applied']}" in text
    # a log before version 4: no such line, no such column, nothing invented
    old = summarise(make_run(5), quality_class=QC)
    assert old["vision"] == {"roll_deg": None, "calibration_states": {},
                             "mean_calibration_gain": None, "mean_uncalibrated_depth_um": None}
    assert "self-calibration" not in format_summary(old) and "kin. depth" not in \
        format_summary(old)


def test_depth_panel_shows_the_kinematic_depth_and_the_untrusted_calibration():
    recs = _with_vision(make_run(6))
    figs = build_figures(recs, quality_class=QC)
    ax_d = _data_axes(figs["pitch_uniformity"])[2]
    x, _, _ = board_axis(recs)
    kx, ky = _series(ax_d, KINEMATIC_LABEL)
    want = sorted((xi, r.kinematic_depth_um) for xi, r in zip(x, recs, strict=True) if r.ok)
    assert np.allclose(kx, [w[0] for w in want]) and np.allclose(ky, [w[1] for w in want])
    ux, uy = _series(ax_d, UNTRUSTED_LABEL)
    untrusted = [r for r in recs if r.ok and r.calibration_state == "untrusted"]
    assert untrusted and sorted(uy) == sorted(r.depth_um for r in untrusted)
    assert "kinematic" in ax_d.get_title()
    assert _legend_outside(figs["pitch_uniformity"], ax_d)
    # without the columns the panel is as before
    plain = build_figures(make_run(6), quality_class=QC)["pitch_uniformity"]
    ax_plain = _data_axes(plain)[2]
    assert _series(ax_plain, KINEMATIC_LABEL)[0].size == 0
    assert _series(ax_plain, UNTRUSTED_LABEL)[0].size == 0
    assert "kinematic" not in ax_plain.get_title()
