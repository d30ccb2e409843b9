"""The HIL run's summary: true and measured values, settling, limits, faults; progress lines."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from config.machine import MachineConfig
from controller.service.events import EventKind, ServiceEvent
from controller.service.service import FrameResult, Service
from core.units import counter_difference
from planer.hil.scenario import (
    CONVERGE_WITHIN_MM,
    FINAL_MEASUREMENTS,
    PITCH_TOL,
    UNIFORMITY_MAX_CV,
    FaultEvent,
)


# ---------------------------------------------------------------------------------- summary
def _truth(r: FrameResult, key: str) -> float | None:
    if not r.truth:
        return None
    v = r.truth.get(key)
    try:
        f = float(v)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _unwrapped_mm(results: Sequence[FrameResult], counts_per_mm: float, bits: int = 32) -> list:
    out, acc, prev = [], 0.0, None
    for r in results:
        if prev is not None:
            acc += counter_difference(r.counts_a, prev, bits=bits) / counts_per_mm
        prev = r.counts_a
        out.append(acc)
    return out


def _settled_at(values: Sequence[float | None], ok: Callable[[float], bool], pos: Sequence[float]):
    """Board position from which every later value is ``ok`` (None if the last is not)."""
    last_bad = None
    for i, v in enumerate(values):
        if v is None:
            continue
        if not ok(v):
            last_bad = i
    valid = [i for i, v in enumerate(values) if v is not None]
    if not valid or (last_bad is not None and last_bad >= valid[-1]):
        return None
    nxt = [i for i in valid if last_bad is None or i > last_bad]
    return pos[nxt[0]] if nxt else None


def summarize(
    results: Sequence[FrameResult],
    *,
    target_pitch_mm: float,
    counts_per_mm: float,
    feed_limits_mm_s: tuple[float, float],
    stroke_um: float,
    faults: Sequence[FaultEvent] = (),
    events: Sequence[ServiceEvent] = (),
    safety: Any = None,
    time_offset_s: float = 0.0,
    extra: Mapping[str, Any] | None = None,
    piezo_limits: Mapping[str, Any] | None = None,
    final_cv_max: float = UNIFORMITY_MAX_CV,
) -> dict[str, Any]:
    """The HIL summary (the ``--json`` object of ``planer hil``).

    Parameters
    ----------
    results : sequence of FrameResult
        Every measurement of the run, in order.
    target_pitch_mm : float
        The quality class's target, mm.
    counts_per_mm : float
        Encoder resolution (board travel from ``counts_a``).
    feed_limits_mm_s : (float, float)
        The machine's feed limits.
    stroke_um : float
        ``machine.toml``'s piezo stroke (offsets must stay within +-stroke, or within the
        amplifier's smaller one when ``piezo_limits`` says it reported one).
    faults : sequence of FaultEvent
        Injected faults (machine time).
    events : sequence of ServiceEvent
        The service's events (service time).
    safety : SafetyConfig, optional
        For the timeouts the fault checks compare against.
    time_offset_s : float
        Service time minus machine time.
    extra : mapping, optional
        Added to the summary.
    piezo_limits : mapping, optional
        The service's bound on the offsets at the end (``Actuators.limits()``): the stroke it
        used (``stroke_um``, the smaller of the amplifier's and ``machine.toml``'s) and why.
    final_cv_max : float
        The scenario's bound on the final (and settled) true CV; the ``done`` key names it
        (``final_uniformity_le_0.05`` by default).

    Returns
    -------
    dict
        Keys ``measurements``, ``initial``, ``final``, ``target_pitch_mm`` (the contract), and
        ``converged``, ``limits`` (see :func:`limits_report`: ``ok`` only with every setpoint
        inside the limits, no refused table left un-planned and no safe-state entry that an
        injected fault does not explain; ``reasons``),
        ``faults`` (per fault what it tripped), ``safe_entries`` (every safe-state entry, laid
        to the fault that explains it), ``counts``, ``latency_ms``, ``done`` ... Values may be
        NaN; :func:`json_ready` makes it strict JSON.
    """
    faults = [f if f.at_s is not None else replace(f, at_s=0.0) for f in faults]  # "now": 0
    pos = _unwrapped_mm(results, counts_per_mm)
    lo, hi = feed_limits_mm_s
    meas = _measurement_rows(results, pos)
    closed = next((i for i, r in enumerate(results) if r.applied), None)
    out: dict[str, Any] = {"target_pitch_mm": float(target_pitch_mm)}
    out.update(_initial_and_final(results, pos, target_pitch_mm))
    out["measurements"] = meas

    reach = _reachable_pitch(events)
    pitch_goal = float(target_pitch_mm) if reach is None else reach
    conv = _convergence(results, pos, closed, faults=faults, events=events,
                        time_offset_s=time_offset_s, pitch_goal=pitch_goal,
                        final_cv_max=final_cv_max)
    out["converged"] = conv

    lat = [r.latency_s * 1e3 for r in results if r.ok]
    out["latency_ms"] = (
        {"median": float(np.median(lat)), "p99": float(np.percentile(lat, 99)), "n": len(lat)}
        if lat
        else None
    )
    out["counts"] = {
        "measurements": len(results),
        "ok": sum(r.ok for r in results),
        "failed": sum(not r.ok for r in results),
        "applied": sum(r.applied for r in results),
    }
    out["faults"] = [
        _fault_report(f, results, events, safety, time_offset_s) for f in faults
    ]
    out["safe_entries"] = _safe_entries(results, events, faults, safety, time_offset_s)
    out["limits"] = limits_report(results, lo, hi, stroke_um, events=events,
                                  safe_entries=out["safe_entries"], piezo_limits=piezo_limits)
    cv0 = out["initial"].get("uniformity_cv")
    cv1 = out["final"].get("uniformity_cv")
    p1 = out["final"].get("pitch_mm")
    out["alerts"] = alert_counts(events)
    out["reachable_pitch_mm"] = reach
    done = _done(out, conv, cv0=cv0, cv1=cv1, p1=p1, pitch_goal=pitch_goal,
                 final_cv_max=final_cv_max)
    out["done"] = done
    out["checks"] = check_texts(done, out, final_cv_max=final_cv_max, pitch_goal=pitch_goal,
                                target_pitch_mm=float(target_pitch_mm))
    out["passed"] = all(done.values())
    if extra:
        out.update(extra)
    return out


def _measurement_rows(results: Sequence[FrameResult], pos: Sequence[float]) -> list[dict]:
    """One row per measurement: measured and true pitch and CV, setpoints, latency."""
    meas = []
    for r, d in zip(results, pos, strict=True):
        meas.append(
            {
                "seq": r.seq,
                "t_s": round(r.t_s, 4),
                "board_travel_mm": round(d, 2),
                "ok": r.ok,
                "error": r.error,
                "state": r.state,
                "applied": r.applied,
                "pitch_mm": _num(r.reported_pitch_mm) if r.ok else None,
                "uniformity_cv": _num(r.reported_uniformity_cv) if r.ok else None,
                "true_pitch_mm": _truth(r, "pitch_mm"),
                "true_uniformity_cv": _truth(r, "uniformity_cv"),
                "feed_setpoint_mm_s": _num(r.feed_setpoint_mm_s),
                "piezo_offsets_um": [round(float(v), 3) for v in r.offsets_um],
                "knife_widths_mm": [_num(w) for w in r.knife_widths_mm],
                "latency_ms": round(r.latency_s * 1e3, 3),
            }
        )
    return meas


def _initial_and_final(results: Sequence[FrameResult], pos: Sequence[float],
                       target_pitch_mm: float) -> dict[str, Any]:
    """The true finish at the first measurement and over the last ones."""
    out: dict[str, Any] = {}
    with_truth = [i for i, r in enumerate(results) if _truth(r, "uniformity_cv") is not None]
    if with_truth:
        first = with_truth[0]
        out["initial"] = {
            "uniformity_cv": _truth(results[first], "uniformity_cv"),
            "pitch_mm": _truth(results[first], "pitch_mm"),
            "board_travel_mm": round(pos[first], 2),
        }
        tail = with_truth[-FINAL_MEASUREMENTS:]
        out["final"] = {
            "uniformity_cv": float(np.mean([_truth(results[i], "uniformity_cv") for i in tail])),
            "pitch_mm": float(np.mean([_truth(results[i], "pitch_mm") for i in tail])),
            "uniformity_cv_max": float(
                np.max([_truth(results[i], "uniformity_cv") for i in tail])
            ),
            "pitch_error_max": float(
                np.max([abs(_truth(results[i], "pitch_mm") / target_pitch_mm - 1) for i in tail])
            ),
            "measurements": len(tail),
        }
    else:
        out["initial"] = {"uniformity_cv": None, "pitch_mm": None}
        out["final"] = {"uniformity_cv": None, "pitch_mm": None}
    return out


def _convergence(results: Sequence[FrameResult], pos: Sequence[float], closed: int | None, *,
                 faults: Sequence[FaultEvent], events: Sequence[ServiceEvent],
                 time_offset_s: float, pitch_goal: float, final_cv_max: float
                 ) -> dict[str, Any]:
    """Where the true finish settled after the loop closed (or recovered, or a knife chipped)."""
    # convergence after the loop closed (true values, board travel from the closing measurement);
    # with faults: after the recovery from the last one
    conv: dict[str, Any] = {"loop_closed_at_mm": None}
    ref, ref_name = closed, "loop closed"
    if closed is not None and faults:
        last_fault = max(f.at_s + _local_offset(results, f.at_s, time_offset_s) for f in faults)
        recs = [e.t_s for e in events if e.kind is EventKind.RECOVERED and e.t_s >= last_fault]
        if recs:
            ref = next((i for i, r in enumerate(results) if r.t_s > recs[0] and r.applied), None)
            ref_name = "recovery after the last fault"
    chips = [e.t_s for e in events if e.kind is EventKind.KNIFE_CHIPPED]
    if closed is not None and chips:  # the knives changed: settling counts from then
        after_chip = next((i for i, r in enumerate(results) if r.t_s > chips[-1] and r.applied),
                          None)
        if after_chip is not None and (ref is None or after_chip > ref):
            ref, ref_name = after_chip, "knife chip"
    if closed is not None and ref is not None:
        c0 = pos[ref]
        after = list(range(ref, len(results)))
        rel = [pos[i] - c0 for i in after]
        cv_vals = [_truth(results[i], "uniformity_cv") for i in after]
        p_vals = [_truth(results[i], "pitch_mm") for i in after]
        cv_at = _settled_at(cv_vals, lambda v: v <= final_cv_max, rel)
        p_at = _settled_at(
            p_vals, lambda v: abs(v / pitch_goal - 1.0) <= PITCH_TOL, rel
        )
        conv = {
            "loop_closed_at_mm": round(pos[closed], 2),
            "reference": ref_name,
            "reference_at_mm": round(c0, 2),
            "uniformity_settled_after_mm": None if cv_at is None else round(cv_at, 1),
            "pitch_settled_after_mm": None if p_at is None else round(p_at, 1),
            "run_after_reference_mm": round(rel[-1], 1) if rel else 0.0,
        }
    return conv


def _done(out: Mapping[str, Any], conv: Mapping[str, Any], *, cv0: float | None,
          cv1: float | None, p1: float | None, pitch_goal: float, final_cv_max: float
          ) -> dict[str, bool]:
    """The run's checks, by key (the ``done`` object)."""
    done = {
        # a run that starts with something to correct, or one that starts within the band and
        # ends there: only a run that starts good and ends bad fails here
        "initial_uniformity_ge_0.10": cv0 is not None and (
            cv0 >= 0.10 or (cv1 is not None and cv1 <= final_cv_max)),
        f"final_uniformity_le_{final_cv_max:g}": cv1 is not None and cv1 <= final_cv_max,
        # against the pitch the machine can hold when the service said the target is not
        # reachable (the feed at its limit, the depth ceiling), else against the target
        "final_pitch_within_2pct": p1 is not None
        and abs(p1 / pitch_goal - 1.0) <= PITCH_TOL,
        "settled_within_3m": conv.get("uniformity_settled_after_mm") is not None
        and conv.get("pitch_settled_after_mm") is not None
        and max(conv["uniformity_settled_after_mm"], conv["pitch_settled_after_mm"])
        <= CONVERGE_WITHIN_MM,
        "setpoints_within_limits": out["limits"]["ok"],
        "faults_handled": all(f.get("handled", True) for f in out["faults"]),
        "no_unexplained_safe_state": out["safe_entries"]["unexplained"] == 0,
    }
    return done


ALERT_KINDS = {
    "target_unreachable": EventKind.TARGET_UNREACHABLE,
    "knife_chipped": EventKind.KNIFE_CHIPPED,
    "measurements_failing": EventKind.MEASUREMENTS_FAILING,
    "learned_state_resumed": EventKind.LEARNED_STATE_RESUMED,
    "learned_state_discarded": EventKind.LEARNED_STATE_DISCARDED,
}
"""The operator's alerts (and the memory's word) the summary counts, by their JSON name."""


def alert_counts(events: Sequence[ServiceEvent]) -> dict[str, Any]:
    """How often the service told the operator each alert, and the chips it named."""
    out: dict[str, Any] = {name: sum(e.kind is kind for e in events)
                           for name, kind in ALERT_KINDS.items()}
    out["chips"] = [{"t_s": round(e.t_s, 3), **dict(e.data or {})} for e in events
                    if e.kind is EventKind.KNIFE_CHIPPED]
    return out


def _reachable_pitch(events: Sequence[ServiceEvent]) -> float | None:
    """The pitch the machine can hold, when the service last said the target is not reachable.

    ``None``: reachable, or never said.
    """
    last = None
    for e in events:
        if e.kind is EventKind.TARGET_UNREACHABLE:
            last = e
        elif e.kind is EventKind.TARGET_REACHABLE:
            last = None
    if last is None:
        return None
    v = (last.data or {}).get("reachable_pitch_mm")
    return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None


def check_texts(done: Mapping[str, bool], summary: Mapping[str, Any], *, final_cv_max: float,
                pitch_goal: float, target_pitch_mm: float) -> dict[str, dict[str, Any]]:
    """Each ``done`` check as a sentence (``{"ok", "text"}`` by the same key)."""
    ini, fin = summary.get("initial") or {}, summary.get("final") or {}
    conv = summary.get("converged") or {}

    def f(v: Any, spec: str = ".3f") -> str:
        return "-" if v is None else format(v, spec)

    goal = (f"the target {target_pitch_mm:g} mm" if pitch_goal == target_pitch_mm else
            f"{pitch_goal:.3f} mm, the pitch the machine can hold (target {target_pitch_mm:g} mm"
            " not reachable)")
    texts = {
        "initial_uniformity_ge_0.10":
            f"The run started with CV {f(ini.get('uniformity_cv'))}: something to correct "
            "(>= 0.10), or within the band and ending there.",
        f"final_uniformity_le_{final_cv_max:g}":
            f"The board ended at CV {f(fin.get('uniformity_cv'))}, at most {final_cv_max:g}.",
        "final_pitch_within_2pct":
            f"The board ended at pitch {f(fin.get('pitch_mm'))} mm, within 2 % of {goal}.",
        "settled_within_3m":
            f"After the {conv.get('reference', 'loop closed')} the CV settled after "
            f"{f(conv.get('uniformity_settled_after_mm'), '.0f')} mm and the pitch after "
            f"{f(conv.get('pitch_settled_after_mm'), '.0f')} mm of board, both within 3 m.",
        "setpoints_within_limits":
            "Every feed setpoint and piezo offset stayed within the machine's limits, no refused "
            "table was left un-planned and no safe state was unexplained.",
        "faults_handled":
            "Every injected fault that should trip a safe state did, in time, with zero offsets,"
            " and control resumed.",
        "no_unexplained_safe_state":
            "Every safe-state entry came with an injected fault to explain it "
            f"({(summary.get('safe_entries') or {}).get('unexplained', 0)} did not).",
        "quality_log_intact": "Every measurement is in the quality log once, none torn.",
    }
    return {k: {"ok": bool(v), "text": texts.get(k, k.replace("_", " "))}
            for k, v in done.items()}


def _num(v: Any) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return round(f, 6) if math.isfinite(f) else None


def refused_tables(events: Sequence[ServiceEvent]) -> list[dict[str, Any]]:
    """Every offset table the amplifier refused (``OFFSETS_REFUSED`` events), in order.

    Each: ``t_s`` (service time), ``table_um`` (refused), ``limit_um`` and ``replanned_um``
    (the narrowed bound and the table sent instead; ``None``: nothing smaller existed, the
    refusal was left un-planned).
    """
    out = []
    for e in events:
        if e.kind is not EventKind.OFFSETS_REFUSED:
            continue
        data = dict(e.data or {})
        out.append({"t_s": round(e.t_s, 3), "table_um": data.get("table_um"),
                    "limit_um": data.get("limit_um"), "replanned_um": data.get("replanned_um")})
    return out


def limits_report(
    results: Sequence[FrameResult],
    lo: float,
    hi: float,
    stroke_um: float,
    *,
    events: Sequence[ServiceEvent] = (),
    safe_entries: Mapping[str, Any] | None = None,
    piezo_limits: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Whether the run kept to the machine's limits; never ``ok`` without a setpoint.

    The criterion: ``ok`` only when a setpoint was written, every feed setpoint lies within the
    PLC's limits, every piezo offset within the stroke in force (the smaller of the amplifier's
    reported stroke and ``machine.toml``'s ``stroke_um``), no refused offset table was left
    un-planned (re-planned within a narrower bound, never resent unchanged), and every
    safe-state entry is explained by an injected fault (``safe_entries["unexplained"] == 0``):
    a run that cycles through the safe state is not "limits OK" whatever its setpoints.
    ``reasons`` lists what failed.

    Parameters
    ----------
    results : sequence of FrameResult
        The run's measurements.
    lo, hi : float
        The PLC's feed limits, mm/s (NaN: unknown).
    stroke_um : float
        ``machine.toml``'s stroke, um.
    events : sequence of ServiceEvent
        The service's events (the refused tables).
    safe_entries : mapping, optional
        :func:`_safe_entries`' report (``count``, ``unexplained``).
    piezo_limits : mapping, optional
        ``Actuators.limits()`` at the end of the run (the stroke used and why).

    Returns
    -------
    dict
        ``ok``, ``reasons``, the limits (``stroke_um`` is the one in force), the extremes of
        the setpoints, ``tables_refused`` / ``tables_unplanned`` / ``refused`` (list),
        ``safe_entries`` / ``safe_entries_unexplained``, ``stroke_source``.
    """
    reasons: list[str] = []
    pl = dict(piezo_limits or {})
    amp_stroke = pl.get("stroke_um")  # min(amplifier, machine.toml) once the amplifier reported
    in_force = stroke_um if amp_stroke is None else min(float(amp_stroke), stroke_um)
    applied = sum(bool(r.applied) for r in results)
    given = [r.feed_setpoint_mm_s for r in results if r.feed_setpoint_mm_s is not None]
    feeds = [float(f) for f in given if math.isfinite(f)]
    offs = [abs(float(v)) for r in results for v in r.offsets_um]
    limits_known = math.isfinite(lo) and math.isfinite(hi)
    if not applied:
        reasons.append("no setpoint was written: no measurement was applied")
    if not feeds:
        reasons.append("no feed setpoint known")
    if len(feeds) < len(given):
        reasons.append(f"{len(given) - len(feeds)} feed setpoint(s) not a number")
    if not limits_known:
        reasons.append("feed limits unknown: no PLC data")
    else:
        outside = sum(not lo - 1e-6 <= f <= hi + 1e-6 for f in feeds)
        if outside:
            reasons.append(f"{outside} feed setpoint(s) outside [{lo:g}, {hi:g}] mm/s")
    if any(not math.isfinite(o) for o in offs):
        reasons.append("piezo offsets not a number")
    beyond = sum(o > in_force + 1e-9 for o in offs if math.isfinite(o))
    if beyond:
        reasons.append(f"{beyond} piezo offset(s) beyond the stroke {in_force:g} µm")
    refused = refused_tables(events)
    unplanned = sum(r["replanned_um"] is None for r in refused)
    if unplanned:
        reasons.append(f"{unplanned} refused offset table(s) not re-planned")
    entries = dict(safe_entries or {})
    unexplained = int(entries.get("unexplained", 0))
    if unexplained:
        reasons.append(f"{unexplained} safe-state entr{'y' if unexplained == 1 else 'ies'} "
                       f"not explained by an injected fault (of {entries.get('count', 0)})")
    finite_offs = [o for o in offs if math.isfinite(o)]
    return {
        "feed_min_mm_s": lo if math.isfinite(lo) else None,
        "feed_max_mm_s": hi if math.isfinite(hi) else None,
        "stroke_um": in_force,
        "stroke_source": pl.get("source", "machine.toml"),
        "config_stroke_um": stroke_um,
        "amp_stroke_um": pl.get("amp_stroke_um"),
        "feed_setpoint_range_mm_s": [min(feeds), max(feeds)] if feeds else None,
        "max_abs_offset_um": max(finite_offs) if finite_offs else 0.0,
        "applied": applied,
        "tables_refused": len(refused),
        "tables_unplanned": unplanned,
        "refused": refused,
        "safe_entries": int(entries.get("count", 0)),
        "safe_entries_unexplained": unexplained,
        "ok": not reasons,
        "reasons": reasons,
    }


def _names_condition(event: ServiceEvent, condition: str | None) -> bool:
    """Whether a ``SAFE_STATE`` event names ``condition`` among the sources it misses.

    From the event's ``data["missing"]`` (``controller.service.supervisor.SOURCES`` names); an event
    without it (an older service) is read from its ``reason`` (``"plc gone, can gone"``).
    """
    if condition is None:
        return False
    missing = (event.data or {}).get("missing")
    if missing is not None:
        return condition in missing
    return condition.replace("_", " ") in (event.reason or "")


SAFE_ENTRY_SLACK_S = 5.0
"""Seconds after a fault's end (plus the timeouts and ``recovery_s``) within which a safe-state
entry is laid to it."""


def _fault_window(
    f: FaultEvent, results: Sequence[FrameResult], safety: Any, offset_s: float
) -> tuple[float, float]:
    """Service-time window in which a safe-state entry is explained by fault ``f``."""
    t0 = f.at_s + _local_offset(results, f.at_s, offset_s)
    t1 = t0 + f.duration_s
    slack = SAFE_ENTRY_SLACK_S
    if safety is not None:
        slack += max(safety.plc_timeout_s, safety.can_timeout_s, safety.measurement_timeout_s,
                     safety.recovery_s)
    return t0 - 1e-9, t1 + slack


def _safe_entries(
    results: Sequence[FrameResult],
    events: Sequence[ServiceEvent],
    faults: Sequence[FaultEvent],
    safety: Any,
    offset_s: float,
) -> dict[str, Any]:
    """Every safe-state entry of the run (machine time, reason) and which fault explains it.

    An entry is explained by a fault that should trip a service condition (``FaultKind.trips``)
    when it came while the fault acted or within its timeouts and ``recovery_s`` (plus
    ``SAFE_ENTRY_SLACK_S``) after; a run with unexplained entries did not run cleanly, whatever
    its final values.
    """
    tripping = [f for f in faults if f.kind.trips is not None]
    windows = [(f, *_fault_window(f, results, safety, offset_s)) for f in tripping]
    listed = []
    for e in events:
        if e.kind is not EventKind.SAFE_STATE:
            continue
        why = e.reason or "unknown"
        near = [(f, a) for f, a, b in windows if a <= e.t_s <= b]
        # the fault whose condition the reason names, else the one that began last
        near.sort(key=lambda fa: (_names_condition(e, fa[0].kind.trips), fa[1]))
        by = near[-1][0] if near else None
        listed.append({
            "t_s": round(e.t_s - offset_s, 3),
            "reason": why,
            "missing": list((e.data or {}).get("missing", ())),
            "fault": None if by is None else f"{by.kind.value}@{by.at_s:g}",
        })
    return {
        "count": len(listed),
        "unexplained": sum(x["fault"] is None for x in listed),
        "entries": listed,
    }


def _fault_report(
    f: FaultEvent,
    results: Sequence[FrameResult],
    events: Sequence[ServiceEvent],
    safety: Any,
    offset_s: float,
) -> dict[str, Any]:
    """What fault ``f`` did: for a kind that should trip a condition, the safe state it caused.

    Every report has ``kind``, ``at_s``, the parameters, ``interface`` and ``trips`` (the
    condition of :attr:`config.faults.FaultKind.trips`). A tripping kind adds ``safe_after_s``,
    ``safe_reason`` and ``tripped`` (the reason names the condition); a kind that ends by itself
    (``duration_s``) also ``recovered_after_end_s``, ``resumed_measurements``, ``timeout_s`` and
    ``offsets_zero_in_safe``. ``handled``: the right safe state came in time, the offsets were
    zero in it, and (for a fault that ends) control resumed.
    """
    kind = f.kind
    t0 = f.at_s + _local_offset(results, f.at_s, offset_s)
    t1 = t0 + f.duration_s
    rep: dict[str, Any] = {"kind": kind.value, "at_s": f.at_s, **dict(f.params),
                           "interface": kind.interface, "trips": kind.trips}
    if kind.trips is None:
        return rep
    safe_ev = next((e for e in events
                    if e.kind is EventKind.SAFE_STATE and e.t_s >= t0 - 1e-9), None)
    safe = None if safe_ev is None else safe_ev.t_s
    reason = None if safe_ev is None else (safe_ev.reason or "")
    rep["safe_after_s"] = None if safe is None else round(safe - t0, 3)
    rep["safe_reason"] = reason
    rep["tripped"] = safe_ev is not None and _names_condition(safe_ev, kind.trips)
    rec = next(
        (e.t_s for e in events
         if e.kind is EventKind.RECOVERED and safe is not None and e.t_s > safe),
        None,
    )
    # every pair handled while in the safe state (state and offsets are read at one instant)
    in_safe = [r for r in results if safe is not None and r.t_s >= t0 and r.state == "safe"
               and (rec is None or r.t_s < rec)]
    rep["offsets_zero_in_safe"] = all(all(v == 0 for v in r.offsets_um) for r in in_safe)
    timeout = None if safety is None else getattr(safety, f"{kind.trips}_timeout_s", None)
    rep["timeout_s"] = timeout
    slack = 0.1 + (safety.cycle_s if safety is not None else 0.02)
    since = t0
    if kind.trips == "measurement" and safe is not None:
        # the measurement timeout runs from the last valid pair, which may be one the camera
        # took just before the fault and the service measured just after it
        since = max([t0] + [r.t_s for r in results if r.ok and r.t_s <= safe])
    in_time = safe is not None and (timeout is None or safe - since <= timeout + slack)
    handled = in_time and rep["tripped"] and rep["offsets_zero_in_safe"]
    if kind.lasts:
        rep["recovered_after_end_s"] = None if rec is None else round(rec - t1, 3)
        resumed = [r for r in results if rec is not None and r.t_s > rec and r.applied]
        rep["resumed_measurements"] = len(resumed)
        handled = handled and rec is not None and len(resumed) > 0
    rep["handled"] = handled
    return rep


def json_ready(summary: Mapping[str, Any]) -> dict[str, Any]:
    """The summary for strict JSON: every non-finite number becomes ``null`` with a reason.

    Each replaced value is listed in ``null_reasons`` (``{"limits.feed_min_mm_s": "nan: not a
    number"}``), so ``json.dumps(..., allow_nan=False)`` never meets a NaN or an infinity.
    """
    reasons: dict[str, str] = dict(summary.get("null_reasons") or {})

    def walk(v: Any, path: str) -> Any:
        if isinstance(v, float) and not math.isfinite(v):
            reasons[path] = f"{v!r}: not a finite number"
            return None
        if isinstance(v, Mapping):
            return {k: walk(x, f"{path}.{k}" if path else str(k)) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [walk(x, f"{path}[{i}]") for i, x in enumerate(v)]
        return v

    out = walk({k: v for k, v in summary.items() if k != "null_reasons"}, "")
    out["null_reasons"] = reasons
    return out


def safe_periods(
    events: Sequence[ServiceEvent],
    *,
    start_s: float,
    end_s: float,
    offset_s: float = 0.0,
) -> list[list[float]]:
    """When the service was in the safe state, in machine time, from its events.

    The service starts in the safe state; a ``SAFE_STATE`` event enters it, ``RECOVERED``
    leaves it (by kind; the text is never read). Unlike the records' states this also covers
    safe states between boards, when no pair is measured.

    Parameters
    ----------
    events : sequence of ServiceEvent
        The service's events in order.
    start_s, end_s : float
        Service time at the start and the end of the run.
    offset_s : float
        Service time minus machine time.

    Returns
    -------
    list of [float, float, str]
        ``[start, end, reason]`` of each safe period: machine times, s (rounded to 1 ms), and
        why it was entered (``"plc gone"``; ``"starting up"`` for the first one).
    """
    out: list[list[Any]] = []
    since: float | None = start_s
    why = "starting up"
    for ev in events:
        t = ev.t_s
        if ev.kind is EventKind.SAFE_STATE and since is None:
            since, why = t, ev.reason or "unknown"
        elif ev.kind is EventKind.RECOVERED and since is not None:
            out.append([since, t, why])
            since = None
    if since is not None and end_s > since:
        out.append([since, end_s, why])
    return [[round(a - offset_s, 3), round(b - offset_s, 3), w] for a, b, w in out]


def check_log(path: Path, n_expected: int, *, after_id: int = 0) -> dict[str, Any]:
    """Integrity of the quality log after a run: every measurement once, none torn.

    Parameters
    ----------
    path : Path
        The quality log.
    n_expected : int
        Measurements the run handled.
    after_id : int
        Id of the last record before the run (a log may be continued).

    Returns
    -------
    dict
        ``path``, ``after_id`` (the run's records have larger ids), ``records`` (count),
        ``expected``, ``ids_consecutive``, ``ok``.
    """
    from controller.quality.log import QualityLog, database_url, is_database_url

    with QualityLog(path, create=False) as log:
        entries = log.entries(after_id=after_id)
    ids = [i for i, _ in entries]
    consecutive = ids == list(range(ids[0], ids[0] + len(ids))) if ids else True
    return {
        "path": database_url(path) if is_database_url(path) else str(path),  # '//' kept
        "after_id": int(after_id),
        "records": len(entries),
        "expected": n_expected,
        "ids_consecutive": consecutive,
        "ok": len(entries) == n_expected and consecutive,
    }


def _service_summary(
    service: Service,
    cfg: MachineConfig,
    faults: Sequence[FaultEvent],
    *,
    counts_per_mm: float,
    log_path: Path,
    start_id: int,
    time_offset_s: float = 0.0,
    t_start_s: float = 0.0,
    extra: Mapping[str, Any] | None = None,
    final_cv_max: float = UNIFORMITY_MAX_CV,
) -> dict[str, Any]:
    """:func:`summarize` a finished run of ``service`` and check its quality log."""
    results = service.results
    snap = service.plc.last
    lim = (snap.feed_min_mm_s, snap.feed_max_mm_s) if snap else (math.nan, math.nan)
    summary = summarize(
        results,
        target_pitch_mm=cfg.quality.target_pitch_mm,
        counts_per_mm=counts_per_mm,
        feed_limits_mm_s=lim,
        stroke_um=cfg.stroke_um,
        piezo_limits=service.out.limits() if service.piezo is not None else None,
        final_cv_max=final_cv_max,
        faults=faults,
        events=service.events,
        safety=cfg.safety,
        time_offset_s=time_offset_s,
        extra={
            **dict(extra or {}),
            "events": [[round(e.t_s - t_start_s, 3), e.text] for e in service.events],
            "service": dict(service.counters),
        },
    )
    end_s = max([t_start_s] + [r.t_s for r in results] + [e.t_s for e in service.events])
    summary["safe_periods_s"] = safe_periods(service.events, start_s=t_start_s, end_s=end_s,
                                             offset_s=time_offset_s)
    summary["quality_log"] = check_log(Path(log_path), len(results), after_id=start_id)
    summary["done"]["quality_log_intact"] = summary["quality_log"]["ok"]
    summary["checks"]["quality_log_intact"] = {
        "ok": bool(summary["quality_log"]["ok"]),
        "text": f"Every measurement is in the quality log once, none torn "
                f"({summary['quality_log']['records']} records).",
    }
    summary["defects"] = defects_of_run(Path(log_path), results, after_id=start_id)
    summary["passed"] = all(summary["done"].values())
    return summary


def defects_of_run(path: Path, results: Sequence[FrameResult], *,
                   after_id: int = 0) -> dict[str, Any] | None:
    """The run's planing defects and D1666 grades from its quality log, beside the truth.

    Returns
    -------
    dict or None
        :func:`controller.quality.defect_report.defect_summary` of the run's records
        (defects per kind, the pairs' and boards' grade histograms, each board's grade and
        counts) with ``truth_counts`` (the simulator's defects per kind over the pairs, each
        seen once per pair it is in: ``Frame.truth["defects"]``); ``None`` when the service
        did not look for defects.
    """
    from controller.quality.defect_fields import DEFECT_KINDS
    from controller.quality.defect_report import defect_summary
    from controller.quality.log import QualityLog

    with QualityLog(path, create=False) as log:
        records = [r for _, r in log.entries(after_id=after_id)]
    out = defect_summary(records)
    if out is None:
        return None
    truth = dict.fromkeys(DEFECT_KINDS, 0)
    for r in results:
        for d in (r.truth or {}).get("defects") or ():
            if d.get("kind") in truth:
                truth[d["kind"]] += 1
    return {**out, "truth_counts": truth}




class BoardTravel:
    """Board measured since the loop closed, from the results' encoder counts (progress lines).

    Both HIL modes report this distance, so the same state reads the same in either: the
    board travel (unwrapped ``counts_a``) from the first result whose setpoints were applied.

    Parameters
    ----------
    counts_per_mm : float
        Encoder counts per mm of board travel.
    bits : int
        Width of the encoder counter (wrap-around).
    """

    def __init__(self, counts_per_mm: float, *, bits: int = 32) -> None:
        if not (counts_per_mm > 0 and math.isfinite(counts_per_mm)):
            raise ValueError(f"counts_per_mm must be a finite number > 0, got {counts_per_mm!r}")
        self.counts_per_mm = float(counts_per_mm)
        self._bits = int(bits)
        self._prev: int | None = None
        self.measured_mm = 0.0
        """Board travel from the first result to the last one added, mm."""
        self.closed_at_mm: float | None = None
        """``measured_mm`` at the first applied result (the loop closed), mm."""

    def add(self, result: FrameResult) -> None:
        """Account for the next result (in order)."""
        if self._prev is not None:
            d = counter_difference(result.counts_a, self._prev, bits=self._bits)
            self.measured_mm += d / self.counts_per_mm
        self._prev = result.counts_a
        if self.closed_at_mm is None and result.applied:
            self.closed_at_mm = self.measured_mm

    @property
    def since_closed_mm(self) -> float | None:
        """Board measured since the loop closed, mm (``None`` while it has not closed)."""
        return None if self.closed_at_mm is None else self.measured_mm - self.closed_at_mm


PROGRESS_LEGEND = ("progress: metres of board measured since the loop closed, state, measured "
                   "pitch and CV (true), feed setpoint, piezo offsets, pair number")


def _progress_line(r: FrameResult, travel: BoardTravel) -> str:
    tp = _truth(r, "pitch_mm")
    tc = _truth(r, "uniformity_cv")
    pitch = f"{r.reported_pitch_mm:.3f}" if r.ok and r.reported_pitch_mm is not None else "  -  "
    cv = (f"{r.reported_uniformity_cv:.3f}" if r.ok and r.reported_uniformity_cv is not None
          else "  -  ")
    feed = f"{r.feed_setpoint_mm_s:6.1f}" if r.feed_setpoint_mm_s is not None else "   -  "
    offs = " ".join(f"{v:+5.2f}" for v in r.offsets_um)
    truth = f" (true {tp:.3f} / {tc:.3f})" if tp is not None and tc is not None else ""
    d = travel.since_closed_mm
    dist = "  -  " if d is None else f"{d / 1000:5.2f}"
    return (
        f"{dist} m  {r.state:4s}  pitch {pitch} mm  cv {cv}{truth}  "
        f"feed {feed} mm/s  offsets [{offs}] µm  pair {r.seq}"
    )


LOCAL_OFFSET_WINDOW_S = 2.0
"""Machine seconds before a fault whose frames map its time onto the service clock."""


def _local_offset(results: Sequence[FrameResult], at_s: float, default: float) -> float:
    """Service time minus machine time at machine time ``at_s``.

    From the pairs taken in the ``LOCAL_OFFSET_WINDOW_S`` before it: a simulator that fell
    behind real time (a loaded machine) shifts the mapping, and a fault's timing is judged
    against the mapping in force when it happened. The simulated clock also runs slower than
    the service's while the host cannot keep up (it slows itself), so the rate
    counts too. Pairs stamped by ``planer sim`` with the host clock at their
    capture (``truth["sim_clock_s"]``, the service's clock in the cross-process HIL; used when
    every stamp precedes its pair's arrival) give the mapping directly: the last one before
    ``at_s``, carried on at the stamps' rate. Otherwise the lowest arrival delay of the pairs
    (exact in simulated time), carried to ``at_s`` at rate 1.
    """
    win = [r for r in results if at_s - LOCAL_OFFSET_WINDOW_S <= r.frame_t_s <= at_s]
    stamped = [(r.frame_t_s, float(r.truth["sim_clock_s"]), r.t_s) for r in win
               if isinstance(r.truth, dict) and "sim_clock_s" in r.truth]
    if stamped and all(c <= t for _, c, t in stamped):
        stamped.sort()
        f1, c1, _ = stamped[-1]
        rate = 1.0  # service seconds per machine second, from the stamps
        if len(stamped) >= 2 and f1 - stamped[0][0] > 0:
            rate = max((c1 - stamped[0][1]) / (f1 - stamped[0][0]), 1e-3)
        return c1 + (at_s - f1) * rate - at_s
    offs = [r.t_s - r.frame_t_s for r in win]
    return max(min(offs), default) if offs else default
