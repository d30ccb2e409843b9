"""The report of a moulder's log per cutterhead (pure: records in, dicts / text / figures out).

A moulder's heads write into one log, each record naming its head (schema version 8). The
heads cut different faces to different targets, so every summary, table and figure of
:mod:`controller.quality.report` is made per head: :func:`head_summaries` (the whole summary
of each head's records with its own quality class), :func:`format_heads` (a comparison table,
then each head's summary), :func:`build_head_figures` (each head's figures, saved as
``<stem>_<head>_<figure>.png``). A log of one head is reported as before (with a head line).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from matplotlib.figure import Figure

from controller.quality.log import QualityClass, QualityRecord
from controller.quality.report import (
    build_figures,
    figure_paths,
    format_summary,
    save_figures,
    summarise,
)

__all__ = [
    "build_head_figures",
    "format_heads",
    "head_figure_paths",
    "head_stem",
    "head_summaries",
    "records_by_head",
    "save_head_figures",
]


def records_by_head(records: Sequence[QualityRecord]) -> dict[str, list[QualityRecord]]:
    """Each head's records in append order, heads in order of their first record."""
    out: dict[str, list[QualityRecord]] = {}
    for r in records:
        out.setdefault(r.head, []).append(r)
    return out


def head_summaries(
    records: Sequence[QualityRecord],
    quality_classes: Mapping[str, QualityClass | None] | None = None,
) -> dict[str, dict[str, Any]]:
    """:func:`~controller.quality.report.summarise` of each head's records.

    Parameters
    ----------
    records : sequence of QualityRecord
        The log's records (any heads) in append order.
    quality_classes : mapping of str to QualityClass or None, optional
        Each head's stored class (``QualityLog.quality_class(head)``); a head without one is
        summarised without a class (its records' targets are shown).

    Returns
    -------
    dict of str to dict
        Head name -> its summary (every key of ``summarise``), heads in order of first record.
    """
    classes = quality_classes or {}
    return {head: summarise(rs, quality_class=classes.get(head))
            for head, rs in records_by_head(records).items()}


def _f(v: float | None, fmt: str) -> str:
    return "-" if v is None else f"{v:{fmt}}"


def _table(per_head: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """One row per head: counts, pass rate, pitch against its target, CV, grades, knives."""
    lines = [f"{'head':<10} {'meas':>5} {'failed':>6} {'pass':>7} {'pitch mm':>9} "
             f"{'target mm':>9} {'unif. CV':>8} {'depth µm':>8} {'board grades 1..5':>17} "
             f" jointing"]
    for head, s in per_head.items():
        qc = s["quality_class"]
        target = (qc["target_pitch_mm"] if qc else
                  ", ".join(f"{t:.3f}" for t in s["target_pitch_mm"]) or None)
        target_text = f"{target:.3f}" if isinstance(target, float) else (target or "-")
        rate = "-" if s["pass_rate"] is None else f"{100 * s['pass_rate']:.1f} %"
        grades = s.get("defects")
        grade_text = ("-" if not grades else
                      " ".join(str(n) for n in grades["board_grades"].values()))
        knives = s.get("knife_condition")
        jointing = "-" if not knives else (knives["last"].get("state") or "-")
        lines.append(f"{head:<10} {s['n_records']:>5} {s['n_failed']:>6} {rate:>7} "
                     f"{_f(s['mean_pitch_mm'], '.3f'):>9} {target_text:>9} "
                     f"{_f(s['mean_uniformity_cv'], '.3f'):>8} "
                     f"{_f(s['mean_depth_um'], '.2f'):>8} {grade_text:>17}  {jointing}")
    return lines


def format_heads(summary: Mapping[str, Any], *, title: str = "Quality log") -> str:
    """The text report of a log with several heads: totals, a table of the heads, each head.

    Parameters
    ----------
    summary : mapping
        ``summarise`` of all records with ``per_head`` (:func:`head_summaries`).
    title : str
        First words of the first line.
    """
    per_head = summary["per_head"]
    line = (f"{title}: {summary['n_records']} measurements of {len(per_head)} heads "
            f"({', '.join(per_head)})")
    if summary["wall_time"]:
        line += f", {summary['wall_time']['first']} .. {summary['wall_time']['last']}"
    lines = [line, "", "Per head (pass rate against each head's class; pitch: mean of the "
             "successful measurements):", *_table(per_head)]
    for head, s in per_head.items():
        # the section's title names the head: no head line under it
        lines += ["", "=" * 78, format_summary({**s, "heads": []}, title=f"Head {head}")]
    return "\n".join(lines)


def build_head_figures(
    records: Sequence[QualityRecord],
    quality_classes: Mapping[str, QualityClass | None] | None = None,
    *,
    safe_periods_s: Mapping[str, Sequence[Sequence[Any]]] | None = None,
) -> dict[str, dict[str, Figure]]:
    """Each head's figures (:func:`~controller.quality.report.build_figures` of its records).

    ``safe_periods_s``: each head's own safe periods (optional, by head name).
    """
    classes = quality_classes or {}
    periods = safe_periods_s or {}
    return {head: build_figures(rs, quality_class=classes.get(head),
                                safe_periods_s=periods.get(head))
            for head, rs in records_by_head(records).items()}


def head_figure_paths(out_dir: str | Path, *, stem: str,
                      heads: Sequence[str]) -> dict[str, Path]:
    """Where each head's figures go: ``<out_dir>/<stem>_<head>_<figure>.png``, keyed likewise.

    The keys (``<head>_<figure>``) are those of ``planer report --json``'s ``figures`` for a
    log of several heads.
    """
    return {f"{head}_{name}": path for head in heads
            for name, path in figure_paths(out_dir, stem=head_stem(stem, head)).items()}


def head_stem(stem: str, head: str) -> str:
    """The file-name stem of ``head``'s figures (``<stem>_<head>``)."""
    return f"{stem}_{head}"


def save_head_figures(figures: Mapping[str, Mapping[str, Figure]], out_dir: str | Path, *,
                      stem: str) -> dict[str, dict[str, str]]:
    """Write each head's figures where :func:`head_figure_paths` says, each atomically.

    ``figures``: :func:`build_head_figures`.

    Returns
    -------
    dict of str to dict
        By head, its figures' paths by figure name (:func:`save_figures` of the head's stem);
        ``{f"{head}_{name}": path}`` of them all is ``planer report --json``'s ``figures``.
    """
    return {head: save_figures(dict(figs), out_dir, stem=head_stem(stem, head))
            for head, figs in figures.items()}
