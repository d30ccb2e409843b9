"""``planer report`` of a moulder's log: every summary, table and figure per cutterhead.

Two heads cut to different targets (bottom 1.5 mm, top 1.0 mm) with different pass rates; the
report's numbers per head are checked against counts made here from the records themselves.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import random
import sqlite3

import numpy as np
import pytest

from controller.quality.head_report import (
    build_head_figures,
    format_heads,
    head_figure_paths,
    head_summaries,
    records_by_head,
)
from controller.quality.log import QualityClass, QualityLog, QualityRecord, judge, utc_iso
from controller.quality.report import FIGURE_NAMES, format_summary, heads_of, summarise
from planer.cli import main
from tests.support.old_logs import downgrade

CLASSES = {"bottom": QualityClass("bottom-1.5", 1.5, 0.02, 0.05),
           "top": QualityClass("top-1.0", 1.0, 0.02, 0.05)}
#: Each head's pitch scatter: the top head passes less often.
SCATTER = {"bottom": 0.005, "top": 0.03}


def moulder_run(seed: int = 0, *, boards=(1, 2, 3), per_board: int = 20,
                heads=("bottom", "top")) -> list[QualityRecord]:
    """Records of the heads interleaved pair by pair, as their services append them."""
    rng = random.Random(seed)
    recs: list[QualityRecord] = []
    seq, t = 0, 0.0
    for b in boards:
        for j in range(per_board):
            t += 0.1
            for head in heads:
                seq += 1
                qc = CLASSES[head]
                common = dict(t_s=t, wall_time=utc_iso(1.75e9 + t), seq=seq, board_id=b,
                              board_position_mm=30.0 + 60.0 * j, feed_setpoint_mm_s=600.0,
                              piezo_offsets_um=[0.5, -0.5], target_pitch_mm=qc.target_pitch_mm,
                              head=head, extra={"state": "run"})
                if rng.random() < 0.1:
                    recs.append(QualityRecord(ok=False, error="registration failed: c 0.2",
                                              **common))
                    continue
                m = dict(pitch_mm=qc.target_pitch_mm * (1 + rng.gauss(0, SCATTER[head])),
                         uniformity_cv=abs(rng.gauss(0.02, 0.01)), depth_um=3.0)
                recs.append(QualityRecord(ok=True, mark_widths_mm=[m["pitch_mm"]] * 2,
                                          passed=judge(m, qc), **m, **common))
    return recs


def _expected(recs: list[QualityRecord], head: str) -> dict:
    mine = [r for r in recs if r.head == head]
    ok = [r for r in mine if r.ok]
    judged = [r.passed for r in mine if r.passed is not None]
    return {"n_records": len(mine), "n_failed": len(mine) - len(ok),
            "pass_rate": sum(judged) / len(judged),
            "mean_pitch_mm": float(np.mean([r.pitch_mm for r in ok])),
            "mean_uniformity_cv": float(np.mean([r.uniformity_cv for r in ok]))}


@pytest.fixture
def moulder_log(tmp_path):
    path = tmp_path / "moulder.db"
    with QualityLog(path) as log:
        for head, qc in CLASSES.items():
            log.set_quality_class(qc, head=head)
        log.append_many(moulder_run(4))
    return path


# --------------------------------------------------------------------------------------------
# pure


def test_the_summaries_per_head_are_each_heads_own_numbers():
    recs = moulder_run(1)
    assert heads_of(recs) == ["bottom", "top"]
    assert [len(v) for v in records_by_head(recs).values()] == [60, 60]
    per = head_summaries(recs, CLASSES)
    assert list(per) == ["bottom", "top"]
    for head in per:
        want = _expected(recs, head)
        got = per[head]
        assert {k: got[k] for k in ("n_records", "n_failed")} == {
            k: want[k] for k in ("n_records", "n_failed")}
        for key in ("pass_rate", "mean_pitch_mm", "mean_uniformity_cv"):
            assert got[key] == pytest.approx(want[key], rel=1e-12)
        assert got["quality_class"]["name"] == CLASSES[head].name
        assert got["heads"] == [head]
        assert [b["board_id"] for b in got["boards"]] == [1, 2, 3]
    # the heads really differ: the summary of the mix is neither
    assert per["top"]["pass_rate"] < per["bottom"]["pass_rate"]
    assert per["bottom"]["mean_pitch_mm"] == pytest.approx(1.5, abs=0.01)
    assert per["top"]["mean_pitch_mm"] == pytest.approx(1.0, abs=0.02)


def test_the_text_has_a_table_of_the_heads_then_each_head():
    recs = moulder_run(2)
    summary = {**summarise(recs), "per_head": head_summaries(recs, CLASSES)}
    text = format_heads(summary, title="Quality log m.db")
    lines = text.splitlines()
    assert lines[0].startswith("Quality log m.db: 120 measurements of 2 heads (bottom, top)")
    for head in ("bottom", "top"):
        want = _expected(recs, head)
        row = next(ln for ln in lines if ln.startswith(f"{head:<10} "))
        assert f" {want['n_records']:>5} {want['n_failed']:>6} " in row
        assert f"{100 * want['pass_rate']:.1f} %" in row
        assert f"{want['mean_pitch_mm']:.3f}" in row
        assert f"{CLASSES[head].target_pitch_mm:.3f}" in row
        assert f"Head {head}: {want['n_records']} measurements" in text
        assert f"Quality class {CLASSES[head].name}" in text


def test_one_head_is_reported_as_before_with_a_head_line():
    recs = [r for r in moulder_run(3) if r.head == "bottom"]
    as_main = [dataclasses.replace(r, head="main") for r in recs]
    text = format_summary(summarise(as_main), title="Q")
    lines = text.splitlines()
    assert "Head: main" in lines
    without = [ln for ln in lines if ln != "Head: main"]
    s = summarise(as_main)
    s["heads"] = []
    assert without == format_summary(s, title="Q").splitlines()


def test_figures_are_drawn_per_head_from_its_own_records():
    recs = moulder_run(5)
    figs = build_head_figures(recs, CLASSES)
    assert set(figs) == {"bottom", "top"}
    for head, by_name in figs.items():
        assert set(by_name) == {"pitch_uniformity", "setpoints"}
        ax = by_name["pitch_uniformity"].axes[0]
        target = next(ln for ln in ax.get_lines() if ln.get_label() == "target")
        assert set(np.asarray(target.get_ydata(), float)) == {CLASSES[head].target_pitch_mm}
        n_points = sum(len(ln.get_xdata()) for ln in ax.get_lines()
                       if str(ln.get_label()).startswith("measured"))
        assert n_points == sum(r.head == head and r.ok for r in recs)
    paths = head_figure_paths("/x", stem="m", heads=["bottom", "top"])
    assert len(paths) == 2 * len(FIGURE_NAMES)
    assert str(paths["top_setpoints"]) == "/x/m_top_setpoints.png"


# --------------------------------------------------------------------------------------------
# planer report


def test_cli_json_per_head(moulder_log, tmp_path, capsys):
    out = tmp_path / "figs"
    assert main(["report", str(moulder_log), "--json", "--out", str(out)]) == 0
    s = json.loads(capsys.readouterr().out)
    recs = moulder_run(4)
    assert s["heads"] == ["bottom", "top"] and s["head"] is None
    assert s["n_records"] == len(recs)  # the whole log's keys are kept
    for head in ("bottom", "top"):
        want, got = _expected(recs, head), s["per_head"][head]
        assert got["n_records"] == want["n_records"]
        assert got["pass_rate"] == pytest.approx(want["pass_rate"], rel=1e-12)
        assert got["mean_pitch_mm"] == pytest.approx(want["mean_pitch_mm"], rel=1e-12)
        assert got["quality_class"]["name"] == CLASSES[head].name
        assert set(got["figures"]) == {"pitch_uniformity", "setpoints"}
        for name, path in got["figures"].items():
            assert path == str(out / f"moulder_{head}_{name}.png")
            assert s["figures"][f"{head}_{name}"] == path
            with open(path, "rb") as fh:
                assert fh.read(8) == b"\x89PNG\r\n\x1a\n"
    assert not (out / "moulder_pitch_uniformity.png").exists()  # no figure of the mix


def test_cli_head_filter_reports_that_head_only(moulder_log, tmp_path, capsys):
    out = tmp_path / "f"
    csv_path = tmp_path / "top.csv"
    assert main(["report", str(moulder_log), "--head", "top", "--json", "--out", str(out),
                 "--csv", str(csv_path)]) == 0
    s = json.loads(capsys.readouterr().out)
    want = _expected(moulder_run(4), "top")
    assert s["head"] == "top" and s["heads"] == ["top"] and s["per_head"] is None
    assert s["n_records"] == want["n_records"] and s["n_failed"] == want["n_failed"]
    assert s["pass_rate"] == pytest.approx(want["pass_rate"], rel=1e-12)
    assert s["quality_class"]["name"] == "top-1.0"
    assert s["figures"]["pitch_uniformity"] == str(out / "moulder_top_pitch_uniformity.png")
    with open(csv_path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == want["n_records"] and {r["head"] for r in rows} == {"top"}
    assert main(["report", str(moulder_log), "--head", "top", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert text.startswith(f"Quality log {moulder_log}, head top: {want['n_records']} ")
    assert "Head: top" in text and "Head bottom" not in text


def test_cli_text_per_head(moulder_log, tmp_path, capsys):
    assert main(["report", str(moulder_log), "--out", str(tmp_path / "f")]) == 0
    text = capsys.readouterr().out
    assert "of 2 heads (bottom, top)" in text
    assert "Head bottom: 60 measurements" in text and "Head top: 60 measurements" in text
    assert str(tmp_path / "f" / "moulder_top_setpoints.png") in text


@pytest.mark.parametrize("args, words", [
    (["--head", "left"], "--head left: no records of head 'left' in {log}; its heads: "
                         "bottom, top"),
    (["--head", "top", "--machine", "other"], "--head top: no records of head 'top' in "
                                              "{log} (machine other); it holds no records"),
    (["--head", "Top"], "--head must be a head name"),
])
def test_cli_unknown_head_is_one_line_naming_it(moulder_log, tmp_path, capsys, args, words):
    assert main(["report", str(moulder_log), *args, "--out", str(tmp_path / "f")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("planer report: error: ")
    assert words.format(log=moulder_log) in err
    assert not list((tmp_path / "f").glob("*.png"))


def test_cli_single_head_log_is_unchanged_but_for_the_head(tmp_path, capsys):
    path = tmp_path / "run.db"
    recs = [dataclasses.replace(r, head="main") for r in moulder_run(6, heads=("bottom",))]
    with QualityLog(path) as log:
        log.set_quality_class(CLASSES["bottom"])
        log.append_many(recs)
    assert main(["report", str(path), "--json", "--out", str(tmp_path / "f")]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["head"] == "main" and s["heads"] == ["main"] and s["per_head"] is None
    assert set(s["figures"]) == {"pitch_uniformity", "setpoints"}
    assert s["figures"]["setpoints"] == str(tmp_path / "f" / "run_setpoints.png")
    assert s["pass_rate"] == pytest.approx(_expected(recs, "main")["pass_rate"], rel=1e-12)


def test_cli_reports_a_version_7_log_as_head_main(tmp_path, capsys):
    path = tmp_path / "old.db"
    recs = [dataclasses.replace(r, head="main") for r in moulder_run(7, heads=("top",))]
    with QualityLog(path) as log:
        log.append_many(recs)
    with sqlite3.connect(path) as conn:
        downgrade(conn.execute, 7)
    assert main(["report", str(path), "--head", "main", "--json",
                 "--out", str(tmp_path / "f")]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["n_records"] == len(recs) and s["heads"] == ["main"]
    assert main(["report", str(path), "--head", "top", "--out", str(tmp_path / "f")]) == 2
    assert "its heads: main" in capsys.readouterr().err


def test_each_heads_figures_are_written_where_their_paths_are_told(tmp_path):
    """One rule of a figure's file (report.figure_path): the paths checked before writing are
    those written, a head's as the whole log's with the head's stem."""
    from pathlib import Path

    from controller.quality.head_report import head_stem, save_head_figures
    from controller.quality.report import figure_paths

    recs = moulder_run(2)
    saved = save_head_figures(build_head_figures(recs, CLASSES), tmp_path, stem="m")
    told = head_figure_paths(tmp_path, stem="m", heads=["bottom", "top"])
    written = {f"{head}_{name}": path for head, mine in saved.items()
               for name, path in mine.items()}
    assert written and written == {k: str(p) for k, p in told.items() if k in written}
    assert all(Path(p).is_file() for p in written.values())
    assert {f"top_{n}": p for n, p in figure_paths(tmp_path, stem=head_stem("m", "top")).items()
            } == {k: p for k, p in told.items() if k.startswith("top_")}
