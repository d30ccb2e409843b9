"""The knife condition in a quality log: its summary, a line of text and its trend figure.

Every record since schema version 6 carries the service's knife condition in force when it was
made (``controller.quality.schema.knife_condition_fields``): the board travelled, each knife's
wear (drift of its offset per metre of board) and offset-table reserve, and the jointing
forecast. :func:`knife_summary` gives the last forecast and the trend in brief,
:func:`format_knife_summary` its line for ``planer report``, :func:`knife_condition_figure`
the figure (reserve and wear per knife, and the forecast, along the board travelled). Pure:
records in, dict / text / matplotlib figure out. What they show: ``docs/quality_log.md``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from controller.quality.schema import QualityRecord

__all__ = ["format_knife_summary", "knife_condition_figure", "knife_records", "knife_summary"]


def knife_records(records: Sequence[QualityRecord]) -> list[QualityRecord]:
    """The records that carry the knife condition, in order of the board travelled."""
    recs = [r for r in records if r.board_travel_m is not None and r.jointing_state is not None]
    return sorted(recs, key=lambda r: (r.board_travel_m, r.t_s))


def _num(v: float) -> float | None:
    return None if not math.isfinite(v) else float(v)


def forecast_text(rec: QualityRecord) -> str:
    """The forecast of one record in words (as the service says it)."""
    if rec.jointing_state == "fitting":
        return "fitting the knives' wear (not enough board yet)"
    if rec.jointing_state == "not_due":
        return "no jointing due: no wear trend, or none within the forecast's horizon"
    knife = "" if rec.jointing_knife is None else f" (knife {rec.jointing_knife})"
    if rec.jointing_due_m == 0.0:
        return f"jointing due now{knife}: its offset is at the end of the stroke"
    boards = "-" if rec.jointing_due_boards is None else f"{rec.jointing_due_boards:.0f}"
    hours = "-" if rec.jointing_due_h is None else f"{rec.jointing_due_h:.2f}"
    return f"jointing due in {boards} boards / {hours} h at this feed{knife}"


def knife_summary(records: Sequence[QualityRecord]) -> dict[str, Any] | None:
    """The knife condition over a log (``None`` when no record carries it).

    Returns
    -------
    dict or None
        ``n_records`` (records with the condition), ``board_travel_m`` (first/last),
        ``last`` (the newest forecast: ``state``, ``due_in_m``, ``due_in_boards``,
        ``due_in_h``, ``knife``, ``due_at_m`` (board travel at which it is due), ``text``),
        ``knives`` (per knife: the last ``drift_um_per_m`` and ``reserve_um``, the least
        ``reserve_um`` seen), ``due_at_m`` (min/max/last of the board travel at which the
        forecasts said jointing is due: a steady forecast keeps it in place).
    """
    recs = knife_records(records)
    if not recs:
        return None
    last = recs[-1]
    n_knives = max(len(r.knife_reserve_um) for r in recs)
    knives = []
    for k in range(n_knives):
        reserves = [r.knife_reserve_um[k] for r in recs
                    if len(r.knife_reserve_um) > k and math.isfinite(r.knife_reserve_um[k])]
        knives.append({
            "knife": k,
            "drift_um_per_m": (_num(last.knife_drift_um_per_m[k])
                               if len(last.knife_drift_um_per_m) > k else None),
            "reserve_um": (_num(last.knife_reserve_um[k])
                           if len(last.knife_reserve_um) > k else None),
            "min_reserve_um": min(reserves) if reserves else None,
        })
    due_at = [r.board_travel_m + r.jointing_due_m for r in recs
              if r.jointing_state == "due" and r.jointing_due_m is not None]
    last_due_at = (last.board_travel_m + last.jointing_due_m
                   if last.jointing_due_m is not None else None)
    return {
        "n_records": len(recs),
        "board_travel_m": {"first": recs[0].board_travel_m, "last": last.board_travel_m},
        "last": {"state": last.jointing_state, "due_in_m": last.jointing_due_m,
                 "due_in_boards": last.jointing_due_boards, "due_in_h": last.jointing_due_h,
                 "knife": last.jointing_knife, "due_at_m": last_due_at,
                 "text": forecast_text(last)},
        "knives": knives,
        "due_at_m": ({"min": min(due_at), "max": max(due_at), "last": due_at[-1]}
                     if due_at else None),
    }


def format_knife_summary(ks: dict[str, Any] | None) -> list[str]:
    """The lines of ``planer report`` on the knife condition (none without it)."""
    if not ks:
        return []
    travel = ks["board_travel_m"]
    lines = [f"Knife condition at {travel['last']:.1f} m of board: {ks['last']['text']}"]
    due = ks["due_at_m"]
    if due is not None:
        lines.append(f"  forecasts: jointing due at {due['min']:.1f} .. {due['max']:.1f} m of "
                     f"board (last {due['last']:.1f} m)")
    for k in ks["knives"]:
        drift = "-" if k["drift_um_per_m"] is None else f"{k['drift_um_per_m']:+.3f} µm/m"
        reserve = "-" if k["reserve_um"] is None else f"{k['reserve_um']:.2f} µm"
        least = "-" if k["min_reserve_um"] is None else f"{k['min_reserve_um']:.2f} µm"
        lines.append(f"  knife {k['knife']}: wear {drift}, reserve {reserve} "
                     f"(least {least})")
    return lines


def knife_condition_figure(records: Sequence[QualityRecord]) -> Figure | None:
    """Reserve and wear per knife, and the jointing forecast, along the board travelled.

    Three panels over the board travelled (m): each knife's offset-table reserve (µm), its
    wear (drift of its offset, µm per m of board), and the forecast: the board travel at which
    the finish leaves its class (travelled + due in), with "due now" marked. ``None`` when no
    record carries the knife condition.
    """
    recs = knife_records(records)
    if not recs:
        return None
    x = np.array([r.board_travel_m for r in recs], dtype=float)
    fig = Figure(figsize=(11.0, 9.0), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    ax_r, ax_w, ax_f = fig.subplots(3, 1, sharex=True)
    n_knives = max(len(r.knife_reserve_um) for r in recs)
    for k in range(n_knives):
        res = np.array([r.knife_reserve_um[k] if len(r.knife_reserve_um) > k else np.nan
                        for r in recs], dtype=float)
        wear = np.array([r.knife_drift_um_per_m[k] if len(r.knife_drift_um_per_m) > k
                         else np.nan for r in recs], dtype=float)
        ax_r.plot(x, res, color=f"C{k % 10}", label=f"knife {k}")
        ax_w.plot(x, wear, color=f"C{k % 10}", label=f"knife {k}")
    ax_r.axhline(0.0, color="0.5", linewidth=0.7, zorder=0)
    ax_r.set_ylabel("reserve (µm of stroke)")
    ax_r.set_title("Offset-table reserve per knife: the stroke left in the direction it drifts; "
                   "at 0 the loop can no longer follow the wear", fontsize="medium")
    ax_w.axhline(0.0, color="0.5", linewidth=0.7, zorder=0)
    ax_w.set_ylabel("wear (µm of offset per m)")
    ax_w.set_title("Wear per knife: the fitted drift of its offset per metre of board "
                   "(gaps: still fitting)", fontsize="medium")
    due = np.array([r.board_travel_m + r.jointing_due_m if r.jointing_state == "due"
                    and r.jointing_due_m is not None else np.nan for r in recs])
    if np.isfinite(due).any():
        ax_f.plot(x, due, color="tab:red", marker="o", markersize=2.5, linestyle="-",
                  label="jointing due at (m of board)")
    now = np.array([r.jointing_state == "due" and r.jointing_due_m == 0.0 for r in recs])
    if now.any():
        ax_f.plot(x[now], x[now], linestyle="none", marker="x", color="black",
                  label="due now (a knife at the end of its stroke)")
    ax_f.plot(x, x, color="0.6", linewidth=0.8, label="board travelled")
    ax_f.set_ylabel("board travel (m)")
    ax_f.set_xlabel("board travelled under the cutter since the service started (m)")
    ax_f.set_title(f"Jointing forecast, last: {forecast_text(recs[-1])}", fontsize="medium")
    for ax in (ax_r, ax_w, ax_f):
        ax.grid(True, alpha=0.3)
        handles, labels = ax.get_legend_handles_labels()
        if handles:
            ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small",
                      frameon=False)
    fig.suptitle("Knife condition along the board travelled", fontweight="bold")
    return fig
