"""Summary and figures of a quality log (pure: records in, dict / text / matplotlib figures out).

``planer report`` (``planer/commands/report.py``) reads the log, calls these and writes the
files. Figures are built on matplotlib's Agg canvas without pyplot, so this is safe in threads
and servers. What the figures show: ``docs/quality_log.md``.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from controller.quality_log import QualityClass, QualityRecord

__all__ = [
    "DEFAULT_PITCH_TOLERANCE",
    "failure_reason",
    "summarise",
    "format_summary",
    "board_axis",
    "build_figures",
    "last_profile",
]

#: Tolerance band drawn around the target pitch when the log stores no quality class.
DEFAULT_PITCH_TOLERANCE = 0.02

_PASS, _FAIL, _NOTJUDGED, _TRUE, _TARGET, _FAILED = (
    "tab:blue", "tab:orange", "tab:gray", "black", "tab:green", "tab:red")


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
        ``n_judged``, ``pass_rate``, ``mean_true_pitch_mm``, ``mean_true_uniformity_cv``),
        ``setpoints`` (``feed_mm_s`` min/max/last, ``piezo_offsets_um`` per knife).
        Means are over successful measurements; missing values are ``None``.
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
        "boards": board_rows,
        "setpoints": {
            "feed_mm_s": _range([r.feed_setpoint_mm_s for r in recs]),
            "piezo_offsets_um": piezo,
        },
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
    qc = s["quality_class"]
    if qc:
        parts = [f"pitch {qc['target_pitch_mm']:.3f} mm +-{100 * qc['pitch_tolerance']:.1f} %"]
        if qc["uniformity_max_cv"] is not None:
            parts.append(f"uniformity CV <= {qc['uniformity_max_cv']:.3f}")
        if qc["depth_max_um"] is not None:
            parts.append(f"depth <= {qc['depth_max_um']:.1f} um")
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
                 f"depth {_f(s['mean_depth_um'], '.2f', ' um')}")
    if s["boards"]:
        lines.append("")
        head = (f"{'board':>6} {'meas':>5} {'failed':>6} {'position mm':>15} "
                f"{'pitch mm (mean+-sd)':>20} {'unif. CV':>8} {'depth um':>8} {'pass':>7}")
        truth = any(b["mean_true_pitch_mm"] is not None for b in s["boards"])
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
        lines.append(f"  piezo offset knife {k['knife']}: {k['min']:+.2f} .. {k['max']:+.2f} um, "
                     f"last {k['last']:+.2f}")
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


def _scatter_judged(ax: Any, x: np.ndarray, y: np.ndarray, passed: list[bool | None]) -> None:
    groups = (("pass", True, _PASS, "o"), ("fail", False, _FAIL, "x"),
              ("not judged", None, _NOTJUDGED, "o"))
    for label, value, color, marker in groups:
        m = np.array([p is value for p in passed]) & np.isfinite(y)
        if m.any():
            ax.plot(x[m], y[m], linestyle="none", marker=marker, markersize=3.5, color=color,
                    label=f"measured, {label}")


def _pitch_uniformity_figure(
    recs: list[QualityRecord], qc: QualityClass | None
) -> Figure:
    x, xlabel, starts = board_axis(recs)
    order = np.argsort(x, kind="stable")
    passed = [r.passed for r in recs]
    have_depth = any(r.depth_um is not None for r in recs)
    fig, axes = _new_figure(3 if have_depth else 2, height_in=8.5 if have_depth else 6.5)
    ax_p, ax_u = axes[0], axes[1]

    # pitch: target and tolerance band (per record: the target may change during a run)
    tol = qc.pitch_tolerance if qc is not None else DEFAULT_PITCH_TOLERANCE
    target = _arr([r.target_pitch_mm if r.target_pitch_mm is not None
                   else (qc.target_pitch_mm if qc is not None else None) for r in recs])
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
    _scatter_judged(ax_p, x, _arr([r.pitch_mm for r in recs]), passed)
    failed = np.array([not r.ok for r in recs])
    if failed.any():
        ax_p.plot(x[failed], np.zeros(int(failed.sum())), linestyle="none", marker="|",
                  markersize=10, color=_FAILED, transform=ax_p.get_xaxis_transform(),
                  label="failed measurement", clip_on=False)
    ax_p.set_ylabel("pitch (mm)")
    ax_p.set_title("Mark pitch and uniformity along the boards")

    # uniformity
    if qc is not None and qc.uniformity_max_cv is not None:
        ax_u.axhline(qc.uniformity_max_cv, color=_FAILED, linestyle="--", linewidth=1.2,
                     label=f"limit CV {qc.uniformity_max_cv:g}")
    true_u = _arr([r.true_uniformity_cv for r in recs])
    if np.isfinite(true_u).any():
        ax_u.plot(x[order], true_u[order], color=_TRUE, linewidth=0.9, label="true (simulator)")
    _scatter_judged(ax_u, x, _arr([r.uniformity_cv for r in recs]), passed)
    ax_u.set_ylabel("uniformity: CV of mark widths (-)")
    ax_u.set_ylim(bottom=0.0)

    if have_depth:
        ax_d = axes[2]
        if qc is not None and qc.depth_max_um is not None:
            ax_d.axhline(qc.depth_max_um, color=_FAILED, linestyle="--", linewidth=1.2,
                         label=f"limit {qc.depth_max_um:g} µm")
        _scatter_judged(ax_d, x, _arr([r.depth_um for r in recs]), passed)
        ax_d.set_ylabel("mark depth (µm)")
        ax_d.set_ylim(bottom=0.0)

    for ax in axes:
        for i, (_, start) in enumerate(starts):
            if i:
                ax.axvline(start, color="0.6", linewidth=0.7, zorder=0)
        ax.grid(True, alpha=0.3)
        _legend(ax)
    if 0 < len(starts) <= 20:
        for bid, start in starts:
            ax_p.annotate(f"board {bid}", xy=(start, 1.0), xycoords=("data", "axes fraction"),
                          xytext=(3, -3), textcoords="offset points", va="top",
                          fontsize="x-small", color="0.35")
    axes[-1].set_xlabel(xlabel)
    return fig


def _setpoints_figure(recs: list[QualityRecord]) -> Figure:
    order = np.argsort([r.t_s for r in recs], kind="stable")
    rs = [recs[i] for i in order]
    t = np.array([r.t_s for r in rs])
    fig, (ax_f, ax_z) = _new_figure(2, height_in=6.0)
    feed = _arr([r.feed_setpoint_mm_s for r in rs])
    if np.isfinite(feed).any():
        ax_f.plot(t, feed, drawstyle="steps-post", color="tab:blue", label="feed setpoint")
    ax_f.set_ylabel("feed setpoint (mm/s)")
    ax_f.set_title("Setpoints over time")
    n_knives = max((len(r.piezo_offsets_um) for r in rs), default=0)
    for k in range(n_knives):
        y = _arr([r.piezo_offsets_um[k] if len(r.piezo_offsets_um) > k else None for r in rs])
        ax_z.plot(t, y, drawstyle="steps-post", label=f"knife {k}")
    ax_z.axhline(0.0, color="0.5", linewidth=0.7, zorder=0)
    ax_z.set_ylabel("piezo offset (µm, + = knife cuts less)")
    ax_z.set_xlabel("machine time (s)")
    for ax in (ax_f, ax_z):
        ax.grid(True, alpha=0.3)
        _legend(ax)
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
    fig, (ax,) = _new_figure(1, height_in=4.0)
    ax.plot(x, h, color="tab:blue", linewidth=1.0, label="measured height")
    true_h = rec.extra["profile"].get("true_height_um")
    try:
        th = np.asarray(true_h, dtype=float) if true_h is not None else None
    except (TypeError, ValueError):
        th = None
    if th is not None and th.shape == x.shape:
        ax.plot(x, th, color=_TRUE, linewidth=0.8, linestyle="--", label="true (simulator)")
    ax.set_xlabel("position in image A along the feed (mm)")
    ax.set_ylabel("surface height (µm)")
    title = (f"Surface profile: board {rec.board_id} at {rec.board_position_mm:.0f} mm, "
             f"measurement {rec.seq}, t = {rec.t_s:.1f} s")
    if rec.pitch_mm is not None:
        title += f" (pitch {rec.pitch_mm:.3f} mm)"
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    _legend(ax)
    return fig


def build_figures(
    records: Sequence[QualityRecord], *, quality_class: QualityClass | None = None
) -> dict[str, Figure]:
    """The report's figures (Agg canvas, not shown; the caller saves them).

    Parameters
    ----------
    records : sequence of QualityRecord
        The log's records in append order.
    quality_class : QualityClass, optional
        Draws its tolerance band and limits; without it a +-2 % band around each record's
        ``target_pitch_mm`` is drawn and marked "(default)".

    Returns
    -------
    dict of str to Figure
        ``"pitch_uniformity"`` (pitch, uniformity and, when measured, depth along the boards),
        ``"setpoints"`` (feed and piezo offsets per knife over machine time) and, when a record
        carries ``extra["profile"]``, ``"profile"`` (the newest one). Empty for no records.
    """
    recs = list(records)
    if not recs:
        return {}
    figs = {
        "pitch_uniformity": _pitch_uniformity_figure(recs, quality_class),
        "setpoints": _setpoints_figure(recs),
    }
    prof = last_profile(recs)
    if prof is not None:
        figs["profile"] = _profile_figure(*prof)
    return figs
