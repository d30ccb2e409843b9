"""Summary and figures of a quality log (pure: records in, dict / text / matplotlib figures out).

``planer report`` (``planer/commands/report.py``) reads the log, calls these and writes the
files. Figures are built on matplotlib's Agg canvas without pyplot, so this is safe in threads
and servers. What the figures show: ``docs/quality_log.md``.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from controller.quality.defect_report import (
    defect_map_figure,
    defect_summary,
    format_defect_summary,
    grade_histogram_figure,
)
from controller.quality.knife_report import (
    format_knife_summary,
    knife_condition_figure,
    knife_summary,
)
from controller.quality.log import QualityClass, QualityRecord

__all__ = [
    "DEFAULT_PITCH_TOLERANCE",
    "failure_reason",
    "summarise",
    "vision_summary",
    "KINEMATIC_LABEL",
    "UNTRUSTED_LABEL",
    "format_summary",
    "heads_of",
    "board_axis",
    "build_figures",
    "last_profile",
    "record_state",
    "safe_spans",
    "save_figures",
]

#: Tolerance band drawn around the target pitch when the log stores no quality class.
DEFAULT_PITCH_TOLERANCE = 0.02

#: A pause between records longer than this many median intervals (e.g. between two boards)
#: breaks the setpoint lines: nothing was recorded there.
GAP_FACTOR = 3.0

_PASS, _FAIL, _NOTJUDGED, _TRUE, _TARGET, _FAILED, _SAFE, _KINEMATIC = (
    "tab:blue", "tab:orange", "tab:gray", "black", "tab:green", "tab:red", "tab:purple",
    "tab:brown")
#: Legend of the kinematic depth in the depth panel.
KINEMATIC_LABEL = "kinematic (R and the marks' positions)"
#: Legend of the depths measured while the self-calibration was not trusted (not applied).
UNTRUSTED_LABEL = "self-calibration untrusted (not applied)"


def failure_reason(error: str | None) -> str:
    """The reason a failed measurement is counted under: its error text before the first colon."""
    if not error:
        return "unknown"
    return error.split(":", 1)[0].strip() or "unknown"


def _mean(values: Sequence[float | None]) -> float | None:
    v = np.array([x for x in values if x is not None], dtype=float)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else None


def _std(values: Sequence[float | None]) -> float | None:
    v = np.array([x for x in values if x is not None], dtype=float)
    v = v[np.isfinite(v)]
    return float(v.std(ddof=1)) if v.size > 1 else None


def _range(values: Sequence[float | None]) -> dict[str, float] | None:
    v = [float(x) for x in values if x is not None and math.isfinite(x)]
    if not v:
        return None
    return {"min": min(v), "max": max(v), "last": v[-1]}


def _pass_rate(records: Sequence[QualityRecord]) -> tuple[int, float | None]:
    judged = [r.passed for r in records if r.passed is not None]
    return len(judged), (sum(judged) / len(judged) if judged else None)


def heads_of(records: Sequence[QualityRecord]) -> list[str]:
    """The cutterheads the records name, in order of their first record (``["main"]``: one)."""
    return list(dict.fromkeys(r.head for r in records))


def summarise(
    records: Sequence[QualityRecord], *, quality_class: QualityClass | None = None
) -> dict[str, Any]:
    """Summary of a run as a JSON-ready dict.

    Parameters
    ----------
    records : sequence of QualityRecord
        The log's records in append order.
    quality_class : QualityClass, optional
        The class the records were judged against (shown, not re-applied).

    Returns
    -------
    dict
        ``n_records``, ``n_ok``, ``n_failed``, ``failures`` (reason -> count, most frequent
        first), ``n_judged``, ``pass_rate`` (fraction of judged records that passed, or
        ``None``), ``t_s`` and ``wall_time`` (first/last), ``target_pitch_mm`` (distinct
        targets), ``quality_class``, ``boards`` (one dict per board in order of first
        appearance: ``board_id``, ``n_records``, ``n_failed``, ``position_mm`` min/max,
        ``mean_pitch_mm``, ``std_pitch_mm``, ``mean_uniformity_cv``, ``mean_depth_um``,
        ``n_judged``, ``pass_rate``, ``mean_true_pitch_mm``, ``mean_true_uniformity_cv``,
        ``mean_kinematic_depth_um``), ``setpoints`` (``feed_mm_s`` min/max/last,
        ``piezo_offsets_um`` per knife), ``mean_kinematic_depth_um``, ``vision`` (see
        :func:`vision_summary`), ``knife_condition`` (the last jointing forecast, wear and
        reserve per knife: :func:`controller.quality.knife_report.knife_summary`; ``None``
        without it), ``defects`` (the planing defects and D1666 grades: per kind, the pairs'
        and boards' grade histograms, each board's grade, reason and counts:
        :func:`controller.quality.defect_report.defect_summary`; ``None`` when no record
        looked for defects), ``heads`` (the cutterheads the records name, in order of their
        first record: :func:`heads_of`). Means are over successful measurements; missing values
        are ``None``. A log of several heads is summarised per head by
        :mod:`controller.quality.head_report`.
    """
    recs = list(records)
    ok = [r for r in recs if r.ok]
    failures = Counter(failure_reason(r.error) for r in recs if not r.ok)
    n_judged, rate = _pass_rate(recs)
    boards: dict[int, list[QualityRecord]] = {}
    for r in recs:
        boards.setdefault(r.board_id, []).append(r)
    board_rows = []
    for bid, rs in boards.items():
        good = [r for r in rs if r.ok]
        nj, br = _pass_rate(rs)
        pos = [r.board_position_mm for r in rs]
        board_rows.append({
            "board_id": bid,
            "n_records": len(rs),
            "n_failed": len(rs) - len(good),
            "position_mm": {"min": min(pos), "max": max(pos)},
            "mean_pitch_mm": _mean([r.pitch_mm for r in good]),
            "std_pitch_mm": _std([r.pitch_mm for r in good]),
            "mean_uniformity_cv": _mean([r.uniformity_cv for r in good]),
            "mean_depth_um": _mean([r.depth_um for r in good]),
            "n_judged": nj,
            "pass_rate": br,
            "mean_true_pitch_mm": _mean([r.true_pitch_mm for r in rs]),
            "mean_true_uniformity_cv": _mean([r.true_uniformity_cv for r in rs]),
            "mean_kinematic_depth_um": _mean([r.kinematic_depth_um for r in good]),
        })
    n_knives = max((len(r.piezo_offsets_um) for r in recs), default=0)
    piezo = []
    for k in range(n_knives):
        rng = _range([r.piezo_offsets_um[k] for r in recs if len(r.piezo_offsets_um) > k])
        piezo.append({"knife": k, **(rng or {"min": None, "max": None, "last": None})})
    targets = sorted({r.target_pitch_mm for r in recs if r.target_pitch_mm is not None})
    return {
        "n_records": len(recs),
        "n_ok": len(ok),
        "n_failed": len(recs) - len(ok),
        "failures": dict(failures.most_common()),
        "n_judged": n_judged,
        "pass_rate": rate,
        "t_s": {"first": recs[0].t_s, "last": recs[-1].t_s} if recs else None,
        "wall_time": ({"first": recs[0].wall_time, "last": recs[-1].wall_time}
                      if recs else None),
        "target_pitch_mm": targets,
        "quality_class": quality_class.to_dict() if quality_class is not None else None,
        "mean_pitch_mm": _mean([r.pitch_mm for r in ok]),
        "mean_uniformity_cv": _mean([r.uniformity_cv for r in ok]),
        "mean_depth_um": _mean([r.depth_um for r in ok]),
        "mean_kinematic_depth_um": _mean([r.kinematic_depth_um for r in ok]),
        "vision": vision_summary(recs),
        "boards": board_rows,
        "setpoints": {
            "feed_mm_s": _range([r.feed_setpoint_mm_s for r in recs]),
            "piezo_offsets_um": piezo,
        },
        "knife_condition": knife_summary(recs),
        "defects": defect_summary(recs),
        "heads": heads_of(recs),
    }


def vision_summary(records: Sequence[QualityRecord]) -> dict[str, Any]:
    """The orientation and self-calibration over records (those that carry them).

    Returns
    -------
    dict
        ``roll_deg`` (min/max/last, or ``None``), ``calibration_states`` (state -> count of
        records, most frequent first; records without a state not counted),
        ``mean_calibration_gain`` (over ``applied`` records), ``mean_uncalibrated_depth_um``
        (successful records).
    """
    recs = list(records)
    states = Counter(r.calibration_state for r in recs if r.calibration_state is not None)
    applied = [r for r in recs if r.calibration_state == "applied"]
    return {
        "roll_deg": _range([r.roll_deg for r in recs]),
        "calibration_states": dict(states.most_common()),
        "mean_calibration_gain": _mean([r.calibration_gain for r in applied]),
        "mean_uncalibrated_depth_um": _mean([r.uncalibrated_depth_um for r in recs if r.ok]),
    }


def _f(v: float | None, fmt: str, unit: str = "") -> str:
    return "-" if v is None else f"{v:{fmt}}{unit}"


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{100 * v:.1f} %"


def format_summary(summary: dict[str, Any], *, title: str = "Quality log") -> str:
    """The summary from :func:`summarise` as plain ASCII text for a terminal or an e-mail."""
    s = summary
    lines = [f"{title}: {s['n_records']} measurements"]
    if s["wall_time"]:
        lines[0] += f", {s['wall_time']['first']} .. {s['wall_time']['last']}"
        lines.append(f"  machine time {s['t_s']['first']:.1f} .. {s['t_s']['last']:.1f} s")
    if s.get("heads"):
        lines.append(("Head: " if len(s["heads"]) == 1 else "Heads: ") + ", ".join(s["heads"]))
    qc = s["quality_class"]
    if qc:
        parts = [f"pitch {qc['target_pitch_mm']:.3f} mm +-{100 * qc['pitch_tolerance']:.1f} %"]
        if qc["uniformity_max_cv"] is not None:
            parts.append(f"uniformity CV <= {qc['uniformity_max_cv']:.3f}")
        if qc["depth_max_um"] is not None:
            parts.append(f"depth <= {qc['depth_max_um']:.1f} µm")
        lines.append(f"Quality class {qc['name']}: " + ", ".join(parts))
    elif s["target_pitch_mm"]:
        lines.append("Target pitch: " + ", ".join(f"{t:.3f} mm" for t in s["target_pitch_mm"]))
    lines.append(f"Successful {s['n_ok']}, failed {s['n_failed']}")
    if s["failures"]:
        lines.append("  failed because: " + ", ".join(
            f"{why} x{n}" for why, n in s["failures"].items()))
    lines.append(f"Pass rate: {_pct(s['pass_rate'])} of {s['n_judged']} judged; "
                 f"mean pitch {_f(s['mean_pitch_mm'], '.3f', ' mm')}, "
                 f"uniformity CV {_f(s['mean_uniformity_cv'], '.3f')}, "
                 f"depth {_f(s['mean_depth_um'], '.2f', ' µm')}")
    vis = s.get("vision") or {}
    if vis.get("roll_deg") or vis.get("calibration_states"):
        roll = vis["roll_deg"]
        states = ", ".join(f"{k} x{n}" for k, n in vis["calibration_states"].items()) or "-"
        lines.append(
            "Orientation and self-calibration: roll "
            + ("-" if roll is None else f"{roll['min']:+.2f} .. {roll['max']:+.2f} deg")
            + f"; calibration {states}; gain {_f(vis['mean_calibration_gain'], '.3f')}; "
            f"depth uncalibrated {_f(vis['mean_uncalibrated_depth_um'], '.2f', ' µm')}, "
            f"kinematic {_f(s.get('mean_kinematic_depth_um'), '.2f', ' µm')}")
    if s["boards"]:
        lines.append("")
        head = (f"{'board':>6} {'meas':>5} {'failed':>6} {'position mm':>15} "
                f"{'pitch mm (mean+-sd)':>20} {'unif. CV':>8} {'depth µm':>8} {'pass':>7}")
        truth = any(b["mean_true_pitch_mm"] is not None for b in s["boards"])
        kin = any(b.get("mean_kinematic_depth_um") is not None for b in s["boards"])
        if kin:
            head += f" {'kin. depth':>10}"
        if truth:
            head += f" {'true pitch':>10} {'true CV':>7}"
        lines.append(head)
        for b in s["boards"]:
            pos = f"{b['position_mm']['min']:.0f}..{b['position_mm']['max']:.0f}"
            pitch = _f(b["mean_pitch_mm"], ".3f")
            if b["std_pitch_mm"] is not None:
                pitch += f" +-{b['std_pitch_mm']:.3f}"
            row = (f"{b['board_id']:>6} {b['n_records']:>5} {b['n_failed']:>6} {pos:>15} "
                   f"{pitch:>20} {_f(b['mean_uniformity_cv'], '.3f'):>8} "
                   f"{_f(b['mean_depth_um'], '.2f'):>8} {_pct(b['pass_rate']):>7}")
            if kin:
                row += f" {_f(b.get('mean_kinematic_depth_um'), '.2f'):>10}"
            if truth:
                row += (f" {_f(b['mean_true_pitch_mm'], '.3f'):>10}"
                        f" {_f(b['mean_true_uniformity_cv'], '.3f'):>7}")
            lines.append(row)
    sp = s["setpoints"]
    lines.append("")
    lines.append("Setpoints (min .. max, last):")
    feed = sp["feed_mm_s"]
    lines.append("  feed: " + ("-" if feed is None else
                               f"{feed['min']:.1f} .. {feed['max']:.1f} mm/s, "
                               f"last {feed['last']:.1f}"))
    for k in sp["piezo_offsets_um"]:
        if k["min"] is None:
            continue
        lines.append(f"  piezo offset knife {k['knife']}: {k['min']:+.2f} .. {k['max']:+.2f} µm, "
                     f"last {k['last']:+.2f}")
    knife_lines = format_knife_summary(s.get("knife_condition"))
    if knife_lines:
        lines.append("")
        lines.extend(knife_lines)
    defect_lines = format_defect_summary(s.get("defects"))
    if defect_lines:
        lines.append("")
        lines.extend(defect_lines)
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# figures


def board_axis(records: Sequence[QualityRecord]) -> tuple[np.ndarray, str, list[tuple[int, float]]]:
    """Horizontal coordinate of each record for the plots along the boards.

    Boards are laid end to end in the order they first appear: a record's coordinate is its
    ``board_position_mm`` plus the lengths of the boards before it, in metres. When the records
    carry no positions (all equal), machine time is used instead.

    Returns
    -------
    x : ndarray, shape (N,)
        Coordinate per record.
    label : str
        Axis label with unit.
    starts : list of (board_id, float)
        Start coordinate of each board (empty when the axis is time).
    """
    recs = list(records)
    pos = np.array([r.board_position_mm for r in recs], dtype=float)
    if pos.size == 0 or np.ptp(pos) == 0:
        return np.array([r.t_s for r in recs], dtype=float), "machine time (s)", []
    ends: dict[int, float] = {}
    for r in recs:
        ends[r.board_id] = max(ends.get(r.board_id, 0.0), r.board_position_mm)
    offset: dict[int, float] = {}
    acc = 0.0
    gap = 0.02 * max(ends.values()) if ends else 0.0
    for bid, end in ends.items():
        offset[bid] = acc
        acc += max(end, 0.0) + gap
    x = np.array([(offset[r.board_id] + r.board_position_mm) / 1000.0 for r in recs])
    return x, "position along the boards, laid end to end (m)", [
        (bid, off / 1000.0) for bid, off in offset.items()]


def _arr(values: Sequence[float | None]) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def record_state(record: QualityRecord) -> str | None:
    """The service's state when the record was taken (``"run"``, ``"safe"``), if it stored one.

    Read from ``extra["state"]``, or ``extra["supervisor"]["state"]`` when the supervisor's
    status is stored as a table. ``None`` for logs without it.
    """
    sup = record.extra.get("supervisor")
    state = sup.get("state") if isinstance(sup, dict) else None
    if state is None:
        state = record.extra.get("state")
    return str(state).lower() if isinstance(state, str) else None


def _safe_label(records: Sequence[QualityRecord], periods: Sequence[Sequence[Any]] = ()) -> str:
    """Legend text of the safe-state shading, with the reasons the records or periods give."""
    texts = [r.extra.get("safe_reason") for r in records if record_state(r) == "safe"]
    texts += [p[2] for p in periods if len(p) > 2]
    reasons: list[str] = []
    for why in texts:
        if isinstance(why, str) and why:
            for part in why.split(", "):
                part = "starting up" if part == "start" else part
                if part not in reasons and part != "confirming recovery":
                    reasons.append(part)
    label = "safe state (control paused)"
    if reasons:
        shown = ", ".join(reasons[:4]) + (", ..." if len(reasons) > 4 else "")
        label += f"\nbecause: {shown}"
    return label


def safe_spans(
    x: Sequence[float], safe: Sequence[bool], *, max_extend: float | None = None
) -> list[tuple[float, float]]:
    """Stretches of the horizontal axis the service spent in the safe state.

    Each run of consecutive safe records becomes one span, widened halfway to the records
    before and after it (the state changed somewhere between them), but by at most
    ``max_extend`` (across a pause without records the state there is unknown).

    Parameters
    ----------
    x : sequence of float, shape (N,)
        Coordinate of each record in record order (increasing: time, or the board axis).
    safe : sequence of bool, shape (N,)
        Whether each record was taken in the safe state.
    max_extend : float, optional
        Largest widening on each side, in units of ``x``; default: half the median distance
        between consecutive records.

    Returns
    -------
    list of (float, float)
        ``(start, end)`` of each span, in order.
    """
    xs = np.asarray(x, dtype=float)
    flags = np.asarray(safe, dtype=bool)
    if xs.shape != flags.shape:
        raise ValueError(f"x and safe must have the same length, got {xs.size} and {flags.size}")
    if max_extend is None:
        steps = np.diff(xs)
        steps = steps[steps > 0]
        max_extend = 0.5 * float(np.median(steps)) if steps.size else 0.0
    spans: list[tuple[float, float]] = []
    n, i = xs.size, 0
    while i < n:
        if not flags[i]:
            i += 1
            continue
        j = i
        while j + 1 < n and flags[j + 1]:
            j += 1
        lo, hi = float(np.min(xs[i:j + 1])), float(np.max(xs[i:j + 1]))
        if i > 0 and xs[i - 1] < lo:
            lo -= min(0.5 * (lo - float(xs[i - 1])), max_extend)
        if j + 1 < n and xs[j + 1] > hi:
            hi += min(0.5 * (float(xs[j + 1]) - hi), max_extend)
        spans.append((lo, hi))
        i = j + 1
    return spans


def _new_figure(rows: int, *, height_in: float) -> tuple[Figure, list[Any]]:
    fig = Figure(figsize=(11.0, height_in), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    return fig, list(axes)


def _legend(ax: Any) -> None:
    handles, labels = ax.get_legend_handles_labels()
    if handles:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small",
                  frameon=False)


def _scatter_verdict(
    ax: Any, x: np.ndarray, y: np.ndarray, verdict: Sequence[bool | None],
    labels: tuple[str, str, str],
) -> None:
    """Points coloured by their verdict: ``labels`` = (within, beyond, not judged)."""
    groups = ((labels[0], True, _PASS, "o"), (labels[1], False, _FAIL, "x"),
              (labels[2], None, _NOTJUDGED, "o"))
    for label, value, color, marker in groups:
        m = np.array([v is value for v in verdict], dtype=bool) & np.isfinite(y)
        if m.any():
            ax.plot(x[m], y[m], linestyle="none", marker=marker, markersize=3.5, color=color,
                    label=label)


def _within(value: float | None, limit: float | None) -> bool | None:
    if value is None or limit is None:
        return None
    return bool(value <= limit)


def _shade_safe(axes: Sequence[Any], spans: Sequence[tuple[float, float]], label: str) -> None:
    for k, ax in enumerate(axes):
        for n, (lo, hi) in enumerate(spans):
            label_k = label if k == 0 and n == 0 else None
            if hi > lo:
                ax.axvspan(lo, hi, color=_SAFE, alpha=0.12, linewidth=0, zorder=0,
                           label=label_k)
            else:
                ax.axvline(lo, color=_SAFE, alpha=0.4, linewidth=2.0, zorder=0, label=label_k)


def _failed_ticks(ax: Any, x: np.ndarray, failed: np.ndarray) -> None:
    if failed.any():
        ax.plot(x[failed], np.zeros(int(failed.sum())), linestyle="none", marker="|",
                markersize=10, color=_FAILED, transform=ax.get_xaxis_transform(),
                label="failed measurement", clip_on=False)


def _board_labels(axes: Sequence[Any], boards: list[tuple[int, float, float]]) -> None:
    """Grey lines where a board starts and its number above the top panel (outside the data).

    ``boards``: ``(board_id, start, end)`` on the horizontal axis, in order.
    """
    if not 0 < len(boards) <= 20:
        return
    for ax in axes:
        for _bid, start, _end in boards[1:]:
            ax.axvline(start, color="0.6", linewidth=0.7, zorder=0)
    top = axes[0].secondary_xaxis("top")
    top.set_xticks([0.5 * (s + e) for _b, s, e in boards],
                   labels=[f"board {b}" if b else "no board" for b, _s, _e in boards])
    top.tick_params(length=0, labelsize="small", labelcolor="0.3")


def _periods_on_axis(
    periods: Sequence[Sequence[Any]], t: np.ndarray, x: np.ndarray
) -> list[tuple[float, float]]:
    """Machine-time periods mapped onto another axis through the records' (t, x) pairs."""
    order = np.argsort(t, kind="stable")
    ts, xs = t[order], x[order]
    out = []
    for p in periods:
        lo, hi = np.interp([float(p[0]), float(p[1])], ts, xs)
        if hi > lo or ts[0] <= float(p[0]) <= ts[-1]:
            out.append((float(lo), float(hi)))
    return out


def _pitch_uniformity_figure(
    recs: list[QualityRecord], qc: QualityClass | None,
    safe_periods_s: Sequence[Sequence[Any]] | None,
) -> Figure:
    x, xlabel, starts = board_axis(recs)
    order = np.argsort(x, kind="stable")
    have_depth = any(r.depth_um is not None or r.kinematic_depth_um is not None for r in recs)
    fig, axes = _new_figure(3 if have_depth else 2, height_in=9.0 if have_depth else 7.0)
    ax_p, ax_u = axes[0], axes[1]

    # pitch: target and tolerance band (per record: the target may change during a run); each
    # point coloured by the pitch's own verdict
    tol = qc.pitch_tolerance if qc is not None else DEFAULT_PITCH_TOLERANCE
    target = _arr([r.target_pitch_mm if r.target_pitch_mm is not None
                   else (qc.target_pitch_mm if qc is not None else None) for r in recs])
    pitch = _arr([r.pitch_mm for r in recs])
    if np.isfinite(target).any():
        xs, ts = x[order], target[order]
        ax_p.fill_between(xs, ts * (1 - tol), ts * (1 + tol), step="post", color=_TARGET,
                          alpha=0.15, linewidth=0,
                          label=f"tolerance ±{100 * tol:g} %"
                          + ("" if qc is not None else " (default)"))
        ax_p.plot(xs, ts, drawstyle="steps-post", color=_TARGET, linestyle="--", linewidth=1.2,
                  label="target")
    true_p = _arr([r.true_pitch_mm for r in recs])
    if np.isfinite(true_p).any():
        ax_p.plot(x[order], true_p[order], color=_TRUE, linewidth=0.9,
                  label="true (simulator)")
    pitch_ok = [None if not (np.isfinite(p) and np.isfinite(t))
                else bool(abs(p / t - 1.0) <= tol + 1e-9)
                for p, t in zip(pitch, target, strict=True)]
    _scatter_verdict(ax_p, x, pitch, pitch_ok,
                     ("measured, within tolerance", "measured, outside tolerance",
                      "measured, no target"))
    _failed_ticks(ax_p, x, np.array([not r.ok for r in recs]))
    ax_p.set_ylabel("pitch (mm)")
    ax_p.set_title("Mark pitch (feed per knife): the points should lie in the green band",
                   fontsize="medium")

    # uniformity, coloured by the uniformity verdict
    cv_max = qc.uniformity_max_cv if qc is not None else None
    if cv_max is not None:
        ax_u.axhline(cv_max, color=_FAILED, linestyle="--", linewidth=1.2,
                     label=f"limit CV {cv_max:g}")
    true_u = _arr([r.true_uniformity_cv for r in recs])
    if np.isfinite(true_u).any():
        ax_u.plot(x[order], true_u[order], color=_TRUE, linewidth=0.9, label="true (simulator)")
    _scatter_verdict(ax_u, x, _arr([r.uniformity_cv for r in recs]),
                     [_within(r.uniformity_cv, cv_max) for r in recs],
                     ("measured, within limit", "measured, above limit",
                      "measured, no limit set"))
    ax_u.set_ylabel("uniformity: CV of mark widths (-)")
    ax_u.set_ylim(bottom=0.0)
    ax_u.set_title("Uniformity of the knives' marks (0 = every knife cuts the same mark): "
                   "the points should stay below the red line", fontsize="medium")

    if have_depth:
        ax_d = axes[2]
        depth_max = qc.depth_max_um if qc is not None else None
        if depth_max is not None:
            ax_d.axhline(depth_max, color=_FAILED, linestyle="--", linewidth=1.2,
                         label=f"limit {depth_max:g} µm")
        kin = _arr([r.kinematic_depth_um for r in recs])
        if np.isfinite(kin).any():  # from R and the marks' positions, beside the photometry
            m = np.isfinite(kin[order])
            ax_d.plot(x[order][m], kin[order][m], color=_KINEMATIC, linewidth=1.0,
                      marker=".", markersize=2.5, label=KINEMATIC_LABEL)
        untrusted = np.array([r.calibration_state == "untrusted" for r in recs], dtype=bool)
        depth = _arr([r.depth_um for r in recs])
        if (untrusted & np.isfinite(depth)).any():
            m = untrusted & np.isfinite(depth)
            ax_d.plot(x[m], depth[m], linestyle="none", marker="s", markersize=6,
                      markerfacecolor="none", color=_NOTJUDGED, label=UNTRUSTED_LABEL)
        _scatter_verdict(ax_d, x, depth,
                         [_within(r.depth_um, depth_max) for r in recs],
                         ("measured, within limit", "measured, above limit",
                          "measured, no limit set"))
        ax_d.set_ylabel("mark depth (µm)")
        ax_d.set_ylim(bottom=0.0)
        ax_d.set_title("Depth of the cutter marks (waviness): the points should stay below "
                       "the red line" if not np.isfinite(kin).any() else
                       "Depth of the cutter marks: below the red line, on the brown kinematic "
                       "depth (a gap: spring-back, tear-out)", fontsize="medium")

    if safe_periods_s is None:
        spans = safe_spans(x, [record_state(r) == "safe" for r in recs])
    else:
        spans = _periods_on_axis(safe_periods_s, np.array([r.t_s for r in recs]), x)
    _shade_safe(axes, spans, _safe_label(recs, safe_periods_s or ()))
    boards = [(bid, start, float(np.max(x[[r.board_id == bid for r in recs]])))
              for bid, start in starts]
    _board_labels(axes, boards)
    for ax in axes:
        ax.grid(True, alpha=0.3)
        _legend(ax)
    axes[-1].set_xlabel(xlabel)
    fig.suptitle("Quality along the boards" + (f", class {qc.name}" if qc is not None else ""),
                 fontweight="bold")
    return fig


def _segments(t: np.ndarray) -> list[slice]:
    """Stretches of records without a pause (a pause: e.g. the gap between two boards).

    A pause is an interval longer than ``GAP_FACTOR`` times the median interval.
    """
    n = t.size
    if n < 3:
        return [slice(0, n)]
    dt = np.diff(t)
    positive = dt[dt > 0]
    if not positive.size:
        return [slice(0, n)]
    cuts = (np.nonzero(dt > GAP_FACTOR * float(np.median(positive)))[0] + 1).tolist()
    bounds = [0, *cuts, n]
    return [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]


def _plot_with_gaps(ax: Any, t: np.ndarray, y: np.ndarray, segs: list[slice], *, color: Any,
                    label: str, gap_label: str | None) -> None:
    """``y`` as steps inside each stretch, and what is drawn across the pauses.

    Across a pause a dotted line labelled ``gap_label`` (the value there was not recorded), or
    nothing when ``gap_label`` is ``None``.
    """
    for n, s in enumerate(segs):
        ax.plot(t[s], y[s], drawstyle="steps-post", color=color, linewidth=1.3,
                label=label if n == 0 else None)
    if gap_label is None:
        return
    for n, (a, b) in enumerate(zip(segs[:-1], segs[1:], strict=True)):
        i, j = a.stop - 1, b.start
        ax.plot([t[i], t[j]], [y[i], y[j]], linestyle=":", color=color, linewidth=1.0,
                label=gap_label if n == 0 else None)


def _setpoints_figure(
    recs: list[QualityRecord], safe_periods_s: Sequence[Sequence[Any]] | None
) -> Figure:
    order = np.argsort([r.t_s for r in recs], kind="stable")
    rs = [recs[i] for i in order]
    t = np.array([r.t_s for r in rs])
    segs = _segments(t)
    fig, (ax_f, ax_z) = _new_figure(2, height_in=7.0)
    gap_label = "no measurements here: setpoint not recorded" if len(segs) > 1 else None
    feed = _arr([r.feed_setpoint_mm_s for r in rs])
    if np.isfinite(feed).any():
        _plot_with_gaps(ax_f, t, feed, segs, color="tab:blue",
                        label="feed setpoint (mm/s) at each measurement", gap_label=gap_label)
    _failed_ticks(ax_f, t, np.array([not r.ok for r in rs]))
    ax_f.set_ylabel("feed setpoint (mm/s)")
    ax_f.set_title("Feed rate commanded to the PLC: it follows the target pitch; "
                   "in the safe state it is held or ramped down", fontsize="medium")
    n_knives = max((len(r.piezo_offsets_um) for r in rs), default=0)
    for k in range(n_knives):
        y = _arr([r.piezo_offsets_um[k] if len(r.piezo_offsets_um) > k else None for r in rs])
        _plot_with_gaps(ax_z, t, y, segs, color=f"C{k % 10}", label=f"knife {k}",
                        gap_label=None)
    ax_z.axhline(0.0, color="0.5", linewidth=0.7, zorder=0)
    ax_z.set_ylabel("piezo offset (µm, + = knife cuts less)")
    ax_z.set_xlabel("machine time (s)")
    ax_z.set_title("Piezo offset per knife: levels out once each knife's runout is "
                   "compensated; 0 in the safe state; gaps: not recorded", fontsize="medium")
    if safe_periods_s is None:
        spans = safe_spans(t, [record_state(r) == "safe" for r in rs])
    else:  # the service's own account: also the safe states between boards (no records)
        spans = [(float(p[0]), float(p[1])) for p in safe_periods_s]
    _shade_safe([ax_f, ax_z], spans, _safe_label(rs, safe_periods_s or ()))
    boards: list[tuple[int, float, float]] = []
    for r in rs:
        if boards and boards[-1][0] == r.board_id:
            boards[-1] = (r.board_id, boards[-1][1], r.t_s)
        else:
            boards.append((r.board_id, r.t_s, r.t_s))
    if len(boards) > 1:
        _board_labels([ax_f, ax_z], boards)
    for ax in (ax_f, ax_z):
        ax.grid(True, alpha=0.3)
        _legend(ax)
    fig.suptitle("What the controller commanded, over machine time", fontweight="bold")
    return fig


def last_profile(
    records: Sequence[QualityRecord],
) -> tuple[QualityRecord, np.ndarray, np.ndarray] | None:
    """The newest record carrying a usable ``extra["profile"]`` and its ``x_mm``, ``height_um``.

    A profile is usable when both lists exist, have the same length >= 2 and hold numbers.
    """
    for r in reversed(list(records)):
        prof = r.extra.get("profile")
        if not isinstance(prof, dict):
            continue
        try:
            x = np.asarray(prof.get("x_mm"), dtype=float)
            h = np.asarray(prof.get("height_um"), dtype=float)
        except (TypeError, ValueError):
            continue
        if x.ndim == 1 and x.shape == h.shape and x.size >= 2:
            return r, x, h
    return None


def _profile_figure(rec: QualityRecord, x: np.ndarray, h: np.ndarray) -> Figure:
    true_h = rec.extra["profile"].get("true_height_um")
    try:
        th = np.asarray(true_h, dtype=float) if true_h is not None else None
    except (TypeError, ValueError):
        th = None
    if th is not None and th.shape != x.shape:
        th = None
    # a second panel zooms on two turns of the cutterhead when the profile holds many more
    knives = len(rec.mark_widths_mm)
    pitch = rec.pitch_mm
    zoom_mm = 2.0 * knives * pitch if pitch and knives else 0.0
    zoom = 0 < zoom_mm < 0.5 * float(np.ptp(x))
    fig = Figure(figsize=(11.0, 6.5 if zoom else 4.5), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    axes = list(fig.subplots(2 if zoom else 1, 1, squeeze=False)[:, 0])
    ranges = [(float(np.min(x)), float(np.max(x)))]
    if zoom:
        mid = 0.5 * (ranges[0][0] + ranges[0][1])
        ranges.append((mid - 0.5 * zoom_mm, mid + 0.5 * zoom_mm))
    for n, (ax, (lo, hi)) in enumerate(zip(axes, ranges, strict=True)):
        m = (x >= lo) & (x <= hi)
        ax.plot(x[m], h[m], color="tab:blue", linewidth=1.0, label="measured height",
                marker="." if n else None, markersize=3)
        if th is not None:
            ax.plot(x[m], th[m], color=_TRUE, linewidth=0.8, linestyle="--",
                    label="true (simulator)")
        ax.set_ylabel("surface height (µm)")
        ax.set_xlabel("position in image A along the feed (mm)")
        ax.grid(True, alpha=0.3)
        _legend(ax)
    if zoom:
        axes[0].axvspan(*ranges[1], color="0.5", alpha=0.12, linewidth=0,
                        label="shown enlarged below")
        _legend(axes[0])
        axes[1].set_title(f"Enlarged: two turns of the cutterhead ({2 * knives} marks); each "
                          "dip is one knife's mark, equal dips = equal knives",
                          fontsize="medium")
    what = f"board {rec.board_id} at {rec.board_position_mm:.0f} mm" if rec.board_id else \
        "no board id"
    title = f"Surface profile across the marks: {what}, measurement {rec.seq}, t = {rec.t_s:.1f} s"
    fig.suptitle(title, fontweight="bold")
    sub = "one dip per knife pass; unequal dips = unequal knives"
    if pitch is not None:
        sub = f"measured pitch {pitch:.3f} mm: " + sub
    axes[0].set_title(sub, fontsize="medium")
    return fig


def build_figures(
    records: Sequence[QualityRecord],
    *,
    quality_class: QualityClass | None = None,
    safe_periods_s: Sequence[Sequence[Any]] | None = None,
) -> dict[str, Figure]:
    """The report's figures (Agg canvas, not shown; the caller saves them).

    Parameters
    ----------
    records : sequence of QualityRecord
        The log's records in append order.
    quality_class : QualityClass, optional
        Draws its tolerance band and limits; without it a +-2 % band around each record's
        ``target_pitch_mm`` is drawn and marked "(default)".
    safe_periods_s : sequence of (float, float[, str]), optional
        ``(start, end[, reason])``: machine times the service spent in the safe state, from its
        own events (``planer hil``). Both figures then shade these (mapped onto the board axis
        through the records' times), including safe states between boards that no record
        shows; default: the spans of the records' states (:func:`record_state`).

    Returns
    -------
    dict of str to Figure
        ``"pitch_uniformity"`` (pitch, uniformity and, when measured, depth along the boards;
        each point coloured by the verdict on that quantity), ``"setpoints"`` (feed and piezo
        offsets per knife over machine time), when a record carries ``extra["profile"]``,
        ``"profile"`` (the newest one), and when records carry the knife condition (schema
        version 6), ``"knife_condition"`` (reserve, wear and the jointing forecast along the
        board travelled: :func:`controller.quality.knife_report.knife_condition_figure`), and
        when records carry planing defects (schema version 7), ``"defect_map"`` (each board's
        defects where they were, by kind) and ``"grades"`` (the pairs' and boards' D1666
        grades): :mod:`controller.quality.defect_report`.
        Both along-the-run figures shade the periods the records were taken in the safe state
        (:func:`record_state`). Empty for no records.
    """
    recs = list(records)
    if not recs:
        return {}
    figs = {
        "pitch_uniformity": _pitch_uniformity_figure(recs, quality_class, safe_periods_s),
        "setpoints": _setpoints_figure(recs, safe_periods_s),
    }
    prof = last_profile(recs)
    if prof is not None:
        figs["profile"] = _profile_figure(*prof)
    knives = knife_condition_figure(recs)
    if knives is not None:
        figs["knife_condition"] = knives
    defect_map = defect_map_figure(recs)
    if defect_map is not None:
        figs["defect_map"] = defect_map
    grades = grade_histogram_figure(recs)
    if grades is not None:
        figs["grades"] = grades
    return figs


FIGURE_NAMES = ("pitch_uniformity", "setpoints", "profile", "knife_condition", "defect_map",
                "grades")
"""The figures :func:`build_figures` may draw (``<stem>_<name>.png``)."""


def figure_path(out_dir: str | Path, *, stem: str, name: str) -> Path:
    """The one rule of a figure's file: ``<out_dir>/<stem>_<name>.png``."""
    return Path(out_dir) / f"{stem}_{name}.png"


def figure_paths(out_dir: str | Path, *, stem: str) -> dict[str, Path]:
    """Where :func:`save_figures` writes each figure it may draw, by name (for checks before)."""
    return {name: figure_path(out_dir, stem=stem, name=name) for name in FIGURE_NAMES}


def save_figures(
    figures: dict[str, Figure], out_dir: str | Path, *, stem: str
) -> dict[str, str]:
    """Write figures as ``<out_dir>/<stem>_<name>.png``, each atomically; their paths by name.

    Parameters
    ----------
    figures : dict of str to Figure
        From :func:`build_figures`.
    out_dir : str or Path
        Existing folder.
    stem : str
        Start of the file names (the log's name without suffix).
    """
    from core.fileio import atomic_writer

    written: dict[str, str] = {}
    for name, fig in figures.items():
        path = figure_path(out_dir, stem=stem, name=name)
        with atomic_writer(path, binary=True) as fh:
            fig.savefig(fh, format="png")
        written[name] = str(path)
    return written
