"""One sweep run: its configurations (checked by the project's loaders) and its outcome row.

A :class:`Job` carries plain data (the scenario and the two parsed TOML documents with the
point's values applied) so it pickles to any Dask worker; :func:`run_job` builds the
configurations again there and runs the scenario as an in-process HIL on simulated time
(:class:`planer.hil.InProcessHil`), then reduces its summary to one CSV row
(:func:`outcome_row`).
"""

from __future__ import annotations

import asyncio
import copy
import math
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from config.loading import default_path, load_over_shipped
from core.errors import ConfigError
from planer.hil.scenario import (
    FINAL_MEASUREMENTS,
    Scenario,
    load_scenario,
    scenario_from_table,
    sim_document,
)
from planer.sweep.design import SCENARIO_KEYS, Point, canonical

OUTCOME_COLUMNS = (
    "target_pitch_mm",
    "final_true_cv",
    "final_measured_cv",
    "final_pitch_error",
    "cv_settled_after_mm",
    "cv_003_settled_after_mm",
    "pitch_settled_after_mm",
    "final_feed_mm_s",
    "fastest_feed_mm_s",
    "feed_ratio",
    "max_offset_um",
    "stroke_um",
    "offset_ratio",
    "safe_entries",
    "measurements",
    "ok_measurements",
    "sim_time_s",
    "board_travel_m",
    "loop_closed_at_mm",
    "ramp_end_mm",
    "pitch_verdict",
    "error",
)
"""The outcome columns of ``results.csv``, after ``run``, ``seed`` and the varied keys.

``final_*``: the mean of the last ``FINAL_MEASUREMENTS`` measurements (true values from the
simulator; ``final_pitch_error`` = true pitch / target - 1). ``*_settled_after_mm``: board
travel after the loop closed from which every true value stayed within CV <= 0.05 / CV <= 0.03
(``cv_003_``, the closed-loop target) / pitch within 2 % (empty: never). ``feed_ratio`` = final feed
setpoint / the fastest feed the quality class allows (target pitch under the depth ceiling
times n Z, at most the machine's ``feed.max_mm_s``). ``offset_ratio`` = largest piezo offset /
stroke. ``loop_closed_at_mm``: board travel of the measurement the settling distances count
from. ``ramp_end_mm``: board travel at which the feed drive, at its acceleration limit and
bandwidth, could be within 1 % of the fastest feed from the initial one (the physical ramp's
earliest end, :func:`planer.sweep.judge.drive_ramp_end_mm`). ``pitch_verdict``: ``in band``
within 1.5 m after that, ``late``, ``off``, or ``ramp not finished`` (the run shorter than
the ramp and 1.5 m), ``capped, `` in front when the target pitch lies beyond the feed cap
(:func:`planer.sweep.judge.pitch_verdict`). ``error``: why the run failed (then the outcome
cells are empty)."""


@dataclass(frozen=True)
class Job:
    """Everything a worker needs for one run (plain, picklable data).

    Attributes
    ----------
    point : Point
        Which run.
    scenario : Scenario
        The base scenario with the point's scenario keys and seed applied.
    sim_doc, machine_doc : dict
        The simulator's and the service's TOML documents with the point's dotted keys applied.
    sim_dir, machine_dir : Path or None
        Folders relative paths in those documents resolve from.
    target_from_scenario : bool
        Apply the scenario's ``target_pitch_mm`` to the service (unless the point sets
        ``machine.quality.target_pitch_mm``).
    """

    point: Point
    scenario: Scenario
    sim_doc: dict[str, Any]
    machine_doc: dict[str, Any]
    sim_dir: Path | None
    machine_dir: Path | None
    target_from_scenario: bool


def _set_dotted(doc: dict[str, Any], parts: Sequence[str], value: Any, key: str) -> None:
    node = doc
    for i, part in enumerate(parts[:-1]):
        nxt = node.setdefault(part, {})
        if not isinstance(nxt, dict):
            raise ConfigError(f"{key}: {'.'.join(parts[:i + 1])} is a value, not a table")
        node = nxt
    node[parts[-1]] = copy.deepcopy(value)


def _get_dotted(doc: Mapping[str, Any], obj: Any, parts: Sequence[str]) -> Any:
    """The value at ``parts`` in ``doc``, else the loaded configuration's attribute, else None."""
    node: Any = doc
    for part in parts:
        if not isinstance(node, Mapping) or part not in node:
            node = None
            break
        node = node[part]
    if node is not None:
        return node
    for part in parts:
        obj = getattr(obj, part, None)
        if obj is None:
            return None
    return obj if isinstance(obj, (int, float, str, bool, tuple, list)) else None


def _named(prefix: str, exc: ConfigError) -> str:
    """A loader's message with its key prefixed (``cutterhead.knives`` -> ``sim.cutterhead...``)."""
    text = str(exc)
    if text.startswith("unknown key "):
        return f"unknown key {prefix}.{text[len('unknown key '):]}"
    if text.startswith("missing key "):
        return f"missing key {prefix}.{text[len('missing key '):]}"
    return f"{prefix}.{text}"


def _machine_path(sc: Scenario) -> Path:
    return Path(sc.machine_config) if sc.machine_config else default_path("machine.toml")


def build_sim_config(job: Job) -> Any:
    """The :class:`config.sim.SimConfig` of a job (the scenario's machine faults added)."""
    from config.sim import sim_from_dict

    doc = copy.deepcopy(job.sim_doc)
    extra = [f.table() for f in job.scenario.faults if not f.kind.interface]
    if extra:
        doc.setdefault("faults", {}).setdefault("inject", [])
        doc["faults"]["inject"] = list(doc["faults"]["inject"]) + extra
    try:
        return sim_from_dict(doc, base_dir=job.sim_dir)
    except ConfigError as exc:
        raise ConfigError(_named("sim", exc)) from None


def build_machine_config(job: Job, *, log_path: Path | None = None) -> Any:
    """The service's :class:`config.machine.MachineConfig` of a job (target pitch, log path)."""
    from config.machine import machine_from_dict

    try:
        cfg = machine_from_dict(job.machine_doc, base=job.machine_dir)
    except ConfigError as exc:
        raise ConfigError(_named("machine", exc)) from None
    if job.target_from_scenario and job.scenario.target_pitch_mm is not None:
        cfg = cfg.with_changes(
            quality=replace(cfg.quality, target_pitch_mm=job.scenario.target_pitch_mm)
        )
    if log_path is not None:
        cfg = cfg.with_changes(log=replace(cfg.log, path=Path(log_path)))
    return cfg


def label(values: Mapping[str, Any], seed: int) -> str:
    """``key=value, ..., seed N`` for messages."""
    parts = [f"{k}={canonical(v)}" for k, v in values.items()]
    return ", ".join([*parts, f"seed {seed}"])


def make_job(point: Point, base: Scenario) -> Job:
    """The job of one point; every value checked by the project's loaders now (not on a worker).

    Raises
    ------
    ConfigError
        A value the scenario, simulator or service loader refuses; the message names the run,
        its values and the dotted key (``run 3 (sim.cutterhead.knives=2, seed 0):
        sim.cutterhead.runout_um must have 2 values, got 4``).
    """
    where = f"run {point.index} ({label(point.values, point.seed)})"
    try:
        table = {k: v for k, v in point.values.items() if k in SCENARIO_KEYS}
        sc = scenario_from_table("grid", table, base) if table else base
        sc = replace(sc, name=f"{base.name}#{point.index}", seed=point.seed)
        sim_doc = copy.deepcopy(sim_document(sc))
        mpath = _machine_path(sc)
        machine_doc = load_over_shipped(mpath, "machine.toml")[1]  # a fresh document
        for key, value in point.values.items():
            head, _, rest = key.partition(".")
            if head == "sim":
                _set_dotted(sim_doc, rest.split("."), value, key)
            elif head == "machine":
                _set_dotted(machine_doc, rest.split("."), value, key)
        job = Job(
            point=point,
            scenario=sc,
            sim_doc=sim_doc,
            machine_doc=machine_doc,
            sim_dir=Path(sc.sim_config).parent if sc.sim_config else None,
            machine_dir=mpath.parent,
            target_from_scenario="machine.quality.target_pitch_mm" not in point.values,
        )
        build_sim_config(job)
        build_machine_config(job)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    return job


def base_values(base: Scenario, keys: Sequence[str]) -> dict[str, Any]:
    """The base scenario's value of every key (for the cells a grid leaves out).

    Scenario keys from the scenario; ``sim.*`` / ``machine.*`` from the TOML documents, else
    the loaded configuration's defaults; ``None`` when neither has it.
    """
    from config.machine import load_machine
    from config.sim import sim_from_dict

    sim_doc = sim_document(base)
    sim_cfg = sim_from_dict(sim_doc, base_dir=Path(base.sim_config).parent
                            if base.sim_config else None)
    mpath = _machine_path(base)
    machine_doc = load_over_shipped(mpath, "machine.toml")[1]
    machine_cfg = load_machine(mpath)
    out: dict[str, Any] = {}
    for key in keys:
        head, _, rest = key.partition(".")
        if key in SCENARIO_KEYS:
            v = getattr(base, key)
            out[key] = list(v) if isinstance(v, tuple) else v
        elif head == "sim":
            out[key] = _get_dotted(sim_doc, sim_cfg, rest.split("."))
        else:
            out[key] = _get_dotted(machine_doc, machine_cfg, rest.split("."))
    if "machine.quality.target_pitch_mm" in out and base.target_pitch_mm is not None:
        out["machine.quality.target_pitch_mm"] = base.target_pitch_mm
    return out


def prepare(sweep: Any) -> tuple[list[Job], dict[str, Any]]:
    """Every job of a sweep (checked) and the base values of its keys.

    Raises
    ------
    ConfigError
        The base scenario or a point's value is refused (the first one; names the run).
    """
    from planer.sweep.design import expand

    base = load_scenario(sweep.base)
    bases = base_values(base, sweep.keys)
    return [make_job(p, base) for p in expand(sweep, bases)], bases


# ---------------------------------------------------------------------------------- outcome
def _mean_last(values: Sequence[float | None], n: int = FINAL_MEASUREMENTS) -> float | None:
    vals = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return float(sum(vals[-n:]) / len(vals[-n:])) if vals else None


TIGHT_CV = 0.03
"""The closed loop's uniformity target (``cv_003_settled_after_mm``)."""


def settled_after_mm(
    measurements: Sequence[Mapping[str, Any]], reference_at_mm: float | None, *, max_cv: float
) -> float | None:
    """Board travel after the reference from which every later true CV is ``<= max_cv``.

    Parameters
    ----------
    measurements : sequence of mapping
        The HIL summary's measurements (``board_travel_mm``, ``true_uniformity_cv``), in order.
    reference_at_mm : float or None
        Board travel of the reference measurement (the loop closed), mm; ``None``: never.
    max_cv : float
        The CV limit.

    Returns
    -------
    float or None
        mm after the reference (0 when every value is within), ``None`` when the last value
        with a truth is above the limit or there is none.
    """
    if reference_at_mm is None:
        return None
    after = [(float(m["board_travel_mm"]) - reference_at_mm, m.get("true_uniformity_cv"))
             for m in measurements
             if m.get("board_travel_mm") is not None
             and float(m["board_travel_mm"]) >= reference_at_mm]
    vals = [(d, float(v)) for d, v in after if v is not None and math.isfinite(float(v))]
    if not vals or vals[-1][1] > max_cv:
        return None
    last_bad = max((i for i, (_, v) in enumerate(vals) if v > max_cv), default=None)
    return 0.0 if last_bad is None else round(vals[last_bad + 1][0], 1)


def fastest_feed_mm_s(sim_cfg: Any, machine_cfg: Any) -> float:
    """The fastest feed the quality class allows on this plant, mm/s.

    ``min(target, sqrt(8 R depth_max)) * n * Z`` at the nominal spindle speed, at most the
    machine's ``feed.max_mm_s``.
    """
    from controller.laws.feed_loop import pitch_ceiling_mm

    head = sim_cfg.cutterhead
    q = machine_cfg.quality
    pitch = min(q.target_pitch_mm, pitch_ceiling_mm(q.depth_max_um, head.radius_mm))
    return float(min(pitch * sim_cfg.spindle.rpm / 60.0 * head.knives, sim_cfg.feed.max_mm_s))


def _pitch_judgement(summary: Mapping[str, Any], sim_cfg: Any, machine_cfg: Any,
                     fastest: float) -> dict[str, Any]:
    """The cells ``loop_closed_at_mm``, ``ramp_end_mm``, ``pitch_verdict`` of a run."""
    from controller.laws.feed_loop import pitch_ceiling_mm
    from planer.sweep.judge import drive_ramp_end_mm, pitch_verdict

    head, feed, q = sim_cfg.cutterhead, sim_cfg.feed, machine_cfg.quality
    per_mm = sim_cfg.spindle.rpm / 60.0 * head.knives  # knife passes per mm/s of feed
    wanted = min(q.target_pitch_mm, pitch_ceiling_mm(q.depth_max_um, head.radius_mm)) * per_mm
    capped = wanted > fastest * (1.0 + 1e-9)
    ramp = drive_ramp_end_mm(feed.initial_mm_s, fastest, accel_mm_s2=feed.accel_max_mm_s2,
                             bandwidth_hz=feed.bandwidth_hz)
    conv = summary.get("converged") or {}
    pitch = (summary.get("final") or {}).get("pitch_mm")
    goal = (fastest if capped else wanted) / per_mm
    travel = float(summary.get("board_travel_m") or 0.0) * 1e3
    verdict = pitch_verdict(
        travel_mm=travel, ramp_end_mm=ramp,
        in_band_from_mm=_in_band_from_mm(summary.get("measurements") or [], goal),
        final_pitch_error=None if pitch is None else float(pitch) / goal - 1.0, capped=capped)
    return {"loop_closed_at_mm": conv.get("reference_at_mm"), "ramp_end_mm": ramp,
            "pitch_verdict": verdict}


def _in_band_from_mm(measurements: Sequence[Mapping[str, Any]], goal_mm: float,
                     tol: float = 0.02) -> float | None:
    """Board travel from which every true pitch is within ``tol`` of ``goal_mm``, mm.

    Counted from the start of the run, not from the loop's reference (which a later event
    moves); ``None`` when the last one is not within.
    """
    vals = [(float(m["board_travel_mm"]), float(m["true_pitch_mm"])) for m in measurements
            if m.get("board_travel_mm") is not None and m.get("true_pitch_mm") is not None]
    if not vals or abs(vals[-1][1] / goal_mm - 1.0) > tol:
        return None
    last_bad = max((i for i, (_, p) in enumerate(vals) if abs(p / goal_mm - 1.0) > tol),
                   default=None)
    return vals[0][0] if last_bad is None else vals[last_bad + 1][0]


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return f"{v:.6g}" if math.isfinite(v) else ""
    return str(v)


def outcome_row(summary: Mapping[str, Any], sim_cfg: Any, machine_cfg: Any) -> dict[str, str]:
    """The outcome cells of one finished run (see ``OUTCOME_COLUMNS``) from its HIL summary."""
    target = float(summary["target_pitch_mm"])
    final = summary.get("final") or {}
    conv = summary.get("converged") or {}
    meas = summary.get("measurements") or []
    lim = summary.get("limits") or {}
    pitch = final.get("pitch_mm")
    feed = _mean_last([m.get("feed_setpoint_mm_s") for m in meas])
    fastest = fastest_feed_mm_s(sim_cfg, machine_cfg)
    stroke = float(machine_cfg.stroke_um)
    max_off = lim.get("max_abs_offset_um")
    cells: dict[str, Any] = {
        "target_pitch_mm": target,
        "final_true_cv": final.get("uniformity_cv"),
        "final_measured_cv": _mean_last([m.get("uniformity_cv") for m in meas]),
        "final_pitch_error": None if pitch is None else pitch / target - 1.0,
        "cv_settled_after_mm": conv.get("uniformity_settled_after_mm"),
        "cv_003_settled_after_mm": settled_after_mm(
            meas, conv.get("reference_at_mm"), max_cv=TIGHT_CV
        ),
        "pitch_settled_after_mm": conv.get("pitch_settled_after_mm"),
        "final_feed_mm_s": feed,
        "fastest_feed_mm_s": fastest,
        "feed_ratio": None if feed is None else feed / fastest,
        "max_offset_um": max_off,
        "stroke_um": stroke,
        "offset_ratio": None if max_off is None else float(max_off) / stroke,
        "safe_entries": int((summary.get("safe_entries") or {}).get("count", 0)),
        "measurements": len(meas),
        "ok_measurements": sum(bool(m.get("ok")) for m in meas),
        "sim_time_s": summary.get("sim_time_s"),
        "board_travel_m": summary.get("board_travel_m"),
        **_pitch_judgement(summary, sim_cfg, machine_cfg, fastest),
        "error": None,
    }
    return {k: _cell(cells[k]) for k in OUTCOME_COLUMNS}


def input_cells(point: Point, keys: Sequence[str], bases: Mapping[str, Any]) -> dict[str, str]:
    """``run``, ``seed`` and every varied key's value for this run (the base's where unset)."""
    row = {"run": str(point.index), "seed": str(point.seed)}
    for k in keys:
        v = point.values.get(k, bases.get(k))
        row[k] = "" if v is None else canonical(v)
    return row


def error_row(message: str) -> dict[str, str]:
    """The outcome cells of a failed run: empty, and the error (one line)."""
    row = {k: "" for k in OUTCOME_COLUMNS}
    row["error"] = " ".join(str(message).split())[:500] or "failed"
    return row


RUN_ERRORS = (ArithmeticError, AssertionError, AttributeError, LookupError, OSError,
              RuntimeError, TypeError, ValueError)
"""What a run may raise and still be a row (a Dask worker turns anything else into a row too)."""


def run_job(job: Job) -> tuple[int, dict[str, str], float]:
    """Run one job as an in-process HIL on simulated time; never raises for a failed run.

    Returns
    -------
    (int, dict, float)
        The run's index, its outcome cells (``error`` set when it failed) and its wall time, s.
    """
    from planer.hil.in_process import InProcessHil

    t0 = time.perf_counter()
    try:
        sim_cfg = build_sim_config(job)
        with tempfile.TemporaryDirectory(prefix="planer-sweep-") as tmp:
            log_path = Path(tmp) / "quality.sqlite"
            cfg = build_machine_config(job, log_path=log_path)
            hil = InProcessHil(job.scenario, log_path=log_path)
            hil.cfg, hil.sim_cfg = cfg, sim_cfg  # the point's configurations, not the files'
            summary = asyncio.run(hil.run())
        row = outcome_row(summary, sim_cfg, cfg)
    except RUN_ERRORS as exc:
        row = error_row(f"{type(exc).__name__}: {exc}")
    return job.point.index, row, time.perf_counter() - t0
