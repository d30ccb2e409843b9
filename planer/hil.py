"""Hardware-in-the-loop runs: the service closed around the simulated planer (``planer hil``).

Two ways to run the same scenario:

* **cross-process** (default when possible): ``planer hil`` re-executes itself inside a private
  network namespace (``unshare -rn``: loopback only, multicast routed on ``lo``), starts
  ``planer sim`` there as a separate process (Modbus TCP on 127.0.0.1, CAN over python-can's
  ``udp_multicast``, frames through a spool directory) and runs the real-time service against
  it (:func:`run_cross_process`).
* **in-process** (fallback, tests): the :class:`plant_sim.machine.Machine` and the service in
  one process on *simulated time*, stepped in lockstep every control cycle: the PLC through
  :class:`~controller.plc_client.MachineRegisterBus` (or the real Modbus server on an ephemeral
  loopback port), the amplifier node on python-can's ``virtual`` bus (:class:`InProcessHil`).

Both end with :func:`summarize`: per measurement the measured and the simulator's true pitch and
uniformity (``Frame.truth``) and the setpoints; ``initial`` and ``final`` true values; where the
true values settled (board travel after the loop closed); whether every setpoint stayed inside
the machine's limits; what each injected fault did (safe state, recovery); the quality log's
integrity.
"""

from __future__ import annotations

import asyncio
import itertools
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from config.loading import Section, default_path, load_toml
from config.machine import MachineConfig, load_machine
from controller.events import EventKind, ServiceEvent
from controller.service import FrameResult, Service
from core.errors import ConfigError, FieldbusError

INTERFACE_FAULTS = ("modbus_restart", "can_silence", "can_drop")
FINAL_MEASUREMENTS = 5
"""The ``final`` true values average the last this-many measurements."""
UNIFORMITY_MAX_CV = 0.05
PITCH_TOL = 0.02
CONVERGE_WITHIN_MM = 3000.0

Progress = Callable[[str], None]


# ---------------------------------------------------------------------------------- scenario
@dataclass(frozen=True)
class FaultEvent:
    """One injected fault: ``kind`` at machine time ``at_s`` with its parameters."""

    kind: str
    at_s: float
    params: Mapping[str, float] = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        """How long the fault lasts (``down_s`` or ``duration_s``; 0 if instantaneous)."""
        return float(self.params.get("down_s", self.params.get("duration_s", 0.0)))


@dataclass(frozen=True)
class Scenario:
    """A HIL scenario (``config/hil.toml``).

    Attributes
    ----------
    name : str
        Scenario name.
    distance_m : float
        Board travel to run, m.
    seed : int
        Simulator seed.
    runout_um : tuple of float or None
        Knife runouts (override the simulator's), um.
    initial_feed_mm_s : float or None
        Feed the simulated machine starts with, mm/s.
    target_pitch_mm : float or None
        Target pitch (overrides the quality class of ``machine.toml``), mm.
    sim_config, machine_config : Path or None
        Simulator and service configuration files (``None``: the shipped ones).
    max_sim_s : float
        Time limit, machine seconds.
    time_scale : float
        Cross-process runs: simulated seconds per wall second.
    faults : tuple of FaultEvent
        Faults to inject.
    """

    name: str = "default"
    distance_m: float = 5.0
    seed: int = 0
    runout_um: tuple[float, ...] | None = None
    initial_feed_mm_s: float | None = None
    target_pitch_mm: float | None = None
    sim_config: Path | None = None
    machine_config: Path | None = None
    max_sim_s: float = 60.0
    time_scale: float = 1.0
    faults: tuple[FaultEvent, ...] = ()


def _fault_list(raw: Any, key: str) -> tuple[FaultEvent, ...]:
    from config.sim import FAULT_KINDS

    if not isinstance(raw, list):
        raise ConfigError(f"{key} must be a list of tables")
    out = []
    for i, item in enumerate(raw):
        s = Section(item, f"{key}[{i}]")
        kind = s.string("kind", choices=FAULT_KINDS)
        at_s = s.number("at_s", 0.0, lo=0.0)
        params = {}
        for name in list(item):
            if name in ("kind", "at_s"):
                continue
            params[name] = s.number(name)
        out.append(FaultEvent(kind=kind, at_s=at_s, params=params))
    return tuple(out)


def _config_file(key: str, value: str, base_dir: Path | None) -> Path:
    """The configuration file ``value`` names (relative to ``base_dir``); it must exist."""
    given = Path(value).expanduser()
    folder = None if given.is_absolute() else (base_dir if base_dir is not None else Path.cwd())
    path = given if folder is None else folder / given
    if not path.is_file():
        where = ("" if folder is None else
                 f" (relative paths are resolved from the scenario file's folder {folder})"
                 if base_dir is not None else
                 f" (relative paths are resolved from the working folder {folder})")
        what = "is a folder, not a file" if path.is_dir() else "no such file"
        raise ConfigError(f"{key} = {value!r}: {what}: {path}{where}")
    return path


def scenario_from_table(
    name: str, table: Mapping[str, Any], base: Scenario, *, base_dir: Path | None = None
) -> Scenario:
    """A scenario from one TOML table, starting from ``base`` (errors name ``name.key``).

    ``sim_config`` and ``machine_config`` given relative are resolved from ``base_dir`` (the
    scenario file's folder; default the working folder) and must exist.
    """
    s = Section(table, name)
    s.raw("base", None)
    kw: dict[str, Any] = {"name": name}
    if s.has("distance_m"):
        kw["distance_m"] = s.number("distance_m", lo=0.0, lo_open=True, hi=1000.0)
    if s.has("seed"):
        kw["seed"] = s.integer("seed", lo=0)
    if s.has("runout_um"):
        kw["runout_um"] = s.numbers("runout_um")
    if s.has("initial_feed_mm_s"):
        kw["initial_feed_mm_s"] = s.number("initial_feed_mm_s", lo=0.0, lo_open=True)
    if s.has("target_pitch_mm"):
        kw["target_pitch_mm"] = s.number("target_pitch_mm", lo=0.0, lo_open=True)
    for key in ("sim_config", "machine_config"):
        if s.has(key):
            v = s.string(key)
            kw[key] = _config_file(s.key(key), v, base_dir) if v else None
    if s.has("max_sim_s"):
        kw["max_sim_s"] = s.number("max_sim_s", lo=0.0, lo_open=True)
    if s.has("time_scale"):
        kw["time_scale"] = s.number("time_scale", lo=0.0, lo_open=True, hi=100.0)
    if s.has("faults"):
        kw["faults"] = _fault_list(s.raw("faults"), f"{name}.faults")
    s.reject_unknown()
    return replace(base, **kw)


def load_scenario(name_or_path: str | None = None) -> Scenario:
    """A scenario by name from ``config/hil.toml``, or the first table of another TOML file.

    Parameters
    ----------
    name_or_path : str, optional
        ``"default"`` (the default), another name of ``config/hil.toml``, or a path to a TOML
        file laid out the same way (``path.toml`` runs its ``default`` table or its only one;
        ``path.toml:name`` picks one).

    Raises
    ------
    ConfigError
        Unknown scenario, bad value, unknown fault kind, missing ``sim_config`` /
        ``machine_config`` file (relative to the scenario file's folder); the message names the
        file and the key (``hil.toml: default.faults[0].kind must be one of ...``).
    """
    spec = name_or_path or "default"
    path, name = default_path("hil.toml"), spec
    if spec.endswith(".toml") or ".toml:" in spec:
        p, _, nm = spec.partition(".toml")
        path = Path(p + ".toml")
        name = nm.lstrip(":") or ""
    doc = load_toml(path)
    if not name:
        name = "default" if "default" in doc else (next(iter(doc)) if len(doc) == 1 else "")
        if not doc:
            raise ConfigError(f"{path}: holds no scenario (no table)")
        if not name:
            raise ConfigError(
                f"{path}: holds several scenarios ({', '.join(sorted(doc))}) and none called "
                f"default: pick one with {path}:NAME"
            )
    if name not in doc:
        raise ConfigError(
            f"{path}: no scenario {name!r} (have: {', '.join(sorted(doc)) or 'none'})"
        )

    def build(nm: str, seen: tuple[str, ...]) -> Scenario:
        if nm in seen:
            raise ConfigError(f"{path}: scenario {nm} has a circular base")
        table = doc.get(nm)
        if not isinstance(table, Mapping):
            raise ConfigError(f"{path}: scenario {nm!r} is not a table")
        base_name = table.get("base")
        base = build(str(base_name), (*seen, nm)) if base_name else Scenario()
        try:
            return scenario_from_table(nm, table, base, base_dir=path.parent)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None

    return build(name, ())


# ---------------------------------------------------------------------------------- configs
def sim_document(scenario: Scenario) -> dict[str, Any]:
    """The simulator's TOML document for a scenario (shipped ``sim.toml`` plus overrides)."""
    doc = load_toml(scenario.sim_config or default_path("sim.toml"))
    if scenario.runout_um is not None:
        doc.setdefault("cutterhead", {})["runout_um"] = list(scenario.runout_um)
        doc["cutterhead"]["knives"] = len(scenario.runout_um)
    if scenario.initial_feed_mm_s is not None:
        doc.setdefault("feed", {})["initial_mm_s"] = scenario.initial_feed_mm_s
    return doc


def sim_config_for(scenario: Scenario, *, machine_faults: bool = True) -> Any:
    """The :class:`config.sim.SimConfig` of a scenario (machine faults in ``[faults]``)."""
    from config.sim import sim_from_dict

    doc = sim_document(scenario)
    if machine_faults:
        extra = [
            {"kind": f.kind, "at_s": f.at_s, **f.params}
            for f in scenario.faults
            if f.kind not in INTERFACE_FAULTS
        ]
        if extra:
            doc.setdefault("faults", {}).setdefault("inject", [])
            doc["faults"]["inject"] = list(doc["faults"]["inject"]) + extra
    base = Path(scenario.sim_config).parent if scenario.sim_config else None
    return sim_from_dict(doc, base_dir=base)


def machine_config_for(scenario: Scenario, *, log_path: Path | None = None) -> MachineConfig:
    """The service's configuration for a scenario (target pitch and log path applied)."""
    cfg = load_machine(scenario.machine_config)
    if scenario.target_pitch_mm is not None:
        cfg = cfg.with_changes(
            quality=replace(cfg.quality, target_pitch_mm=scenario.target_pitch_mm)
        )
    if log_path is not None:
        cfg = cfg.with_changes(log=replace(cfg.log, path=Path(log_path)))
    return cfg


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
    m = 1 << bits
    for r in results:
        if prev is not None:
            d = (r.counts_a - prev) % m
            d = d - m if d >= m // 2 else d
            acc += d / counts_per_mm
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
        The piezo stroke (offsets must stay within +-stroke).
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

    Returns
    -------
    dict
        Keys ``measurements``, ``initial``, ``final``, ``target_pitch_mm`` (the contract), and
        ``converged``, ``limits``, ``faults``, ``counts``, ``latency_ms``, ``done`` ...
    """
    pos = _unwrapped_mm(results, counts_per_mm)
    lo, hi = feed_limits_mm_s
    meas = []
    for r, d in zip(results, pos, strict=True):
        m = r.measurement
        meas.append(
            {
                "seq": r.seq,
                "t_s": round(r.t_s, 4),
                "board_travel_mm": round(d, 2),
                "ok": r.ok,
                "error": r.error,
                "state": r.state,
                "applied": r.applied,
                "pitch_mm": _num(getattr(m, "pitch_mm", None)) if r.ok else None,
                "uniformity_cv": _num(getattr(m, "uniformity_cv", None)) if r.ok else None,
                "true_pitch_mm": _truth(r, "pitch_mm"),
                "true_uniformity_cv": _truth(r, "uniformity_cv"),
                "feed_setpoint_mm_s": _num(r.feed_setpoint_mm_s),
                "piezo_offsets_um": [round(float(v), 3) for v in r.offsets_um],
                "knife_widths_mm": [_num(w) for w in r.knife_widths_mm],
                "latency_ms": round(r.latency_s * 1e3, 3),
            }
        )
    closed = next((i for i, r in enumerate(results) if r.applied), None)
    out: dict[str, Any] = {"target_pitch_mm": float(target_pitch_mm)}
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
    out["measurements"] = meas

    # convergence after the loop closed (true values, board travel from the closing measurement);
    # with faults: after the recovery from the last one
    conv: dict[str, Any] = {"loop_closed_at_mm": None}
    ref, ref_name = closed, "loop closed"
    if closed is not None and faults:
        last_fault = max(f.at_s for f in faults) + time_offset_s
        recs = [e.t_s for e in events if e.kind is EventKind.RECOVERED and e.t_s >= last_fault]
        if recs:
            ref = next((i for i, r in enumerate(results) if r.t_s > recs[0] and r.applied), None)
            ref_name = "recovery after the last fault"
    if closed is not None and ref is not None:
        c0 = pos[ref]
        after = list(range(ref, len(results)))
        rel = [pos[i] - c0 for i in after]
        cv_vals = [_truth(results[i], "uniformity_cv") for i in after]
        p_vals = [_truth(results[i], "pitch_mm") for i in after]
        cv_at = _settled_at(cv_vals, lambda v: v <= UNIFORMITY_MAX_CV, rel)
        p_at = _settled_at(
            p_vals, lambda v: abs(v / target_pitch_mm - 1.0) <= PITCH_TOL, rel
        )
        conv = {
            "loop_closed_at_mm": round(pos[closed], 2),
            "reference": ref_name,
            "reference_at_mm": round(c0, 2),
            "uniformity_settled_after_mm": None if cv_at is None else round(cv_at, 1),
            "pitch_settled_after_mm": None if p_at is None else round(p_at, 1),
            "run_after_reference_mm": round(rel[-1], 1) if rel else 0.0,
        }
    out["converged"] = conv

    feeds = [r.feed_setpoint_mm_s for r in results if r.feed_setpoint_mm_s is not None]
    offs = [abs(v) for r in results for v in r.offsets_um]
    out["limits"] = {
        "feed_min_mm_s": lo,
        "feed_max_mm_s": hi,
        "stroke_um": stroke_um,
        "feed_setpoint_range_mm_s": [min(feeds), max(feeds)] if feeds else None,
        "max_abs_offset_um": max(offs) if offs else 0.0,
        "ok": all(lo - 1e-6 <= f <= hi + 1e-6 for f in feeds)
        and all(o <= stroke_um + 1e-9 for o in offs),
    }
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
    cv0 = out["initial"].get("uniformity_cv")
    cv1 = out["final"].get("uniformity_cv")
    p1 = out["final"].get("pitch_mm")
    done = {
        "initial_uniformity_ge_0.10": cv0 is not None and cv0 >= 0.10,
        "final_uniformity_le_0.05": cv1 is not None and cv1 <= UNIFORMITY_MAX_CV,
        "final_pitch_within_2pct": p1 is not None
        and abs(p1 / target_pitch_mm - 1.0) <= PITCH_TOL,
        "settled_within_3m": conv.get("uniformity_settled_after_mm") is not None
        and conv.get("pitch_settled_after_mm") is not None
        and max(conv["uniformity_settled_after_mm"], conv["pitch_settled_after_mm"])
        <= CONVERGE_WITHIN_MM,
        "setpoints_within_limits": out["limits"]["ok"],
        "faults_handled": all(f.get("handled", True) for f in out["faults"]),
    }
    out["done"] = done
    out["passed"] = all(done.values())
    if extra:
        out.update(extra)
    return out


def _num(v: Any) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return round(f, 6) if math.isfinite(f) else None


def _fault_report(
    f: FaultEvent,
    results: Sequence[FrameResult],
    events: Sequence[ServiceEvent],
    safety: Any,
    offset_s: float,
) -> dict[str, Any]:
    t0 = f.at_s + _local_offset(results, f.at_s, offset_s)
    t1 = t0 + f.duration_s
    rep: dict[str, Any] = {"kind": f.kind, "at_s": f.at_s, **dict(f.params)}
    if f.kind not in INTERFACE_FAULTS:
        return rep
    safe = next((e.t_s for e in events
                 if e.kind is EventKind.SAFE_STATE and e.t_s >= t0 - 1e-9), None)
    rec = next(
        (e.t_s for e in events
         if e.kind is EventKind.RECOVERED and safe is not None and e.t_s > safe),
        None,
    )
    timeout = None
    if safety is not None:
        timeout = safety.plc_timeout_s if f.kind == "modbus_restart" else safety.can_timeout_s
    rep["safe_after_s"] = None if safe is None else round(safe - t0, 3)
    rep["recovered_after_end_s"] = None if rec is None else round(rec - t1, 3)
    resumed = [r for r in results if rec is not None and r.t_s > rec and r.applied]
    rep["resumed_measurements"] = len(resumed)
    # every pair handled while in the safe state (state and offsets are read at one instant)
    in_safe = [r for r in results if safe is not None and r.t_s >= t0 and r.state == "safe"
               and (rec is None or r.t_s < rec)]
    rep["offsets_zero_in_safe"] = all(all(v == 0 for v in r.offsets_um) for r in in_safe)
    rep["timeout_s"] = timeout
    slack = 0.1 + (safety.cycle_s if safety is not None else 0.02)
    rep["handled"] = (
        safe is not None
        and (timeout is None or safe - t0 <= timeout + slack)
        and rec is not None
        and len(resumed) > 0
        and rep["offsets_zero_in_safe"]
    )
    return rep


def safe_periods(
    events: Sequence[ServiceEvent],
    *,
    start_s: float,
    end_s: float,
    offset_s: float = 0.0,
) -> list[list[float]]:
    """When the service was in the safe state, in machine time, from its events.

    The service starts in the safe state; ``"safe state: ..."`` enters it, ``"recovered..."``
    leaves it. Unlike the records' states this also covers safe states between boards, when no
    pair is measured.

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
            since, why = t, ev.text.partition(":")[2].strip() or "unknown"
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
    from controller.quality_log import QualityLog

    with QualityLog(path, create=False) as log:
        entries = log.entries(after_id=after_id)
    ids = [i for i, _ in entries]
    consecutive = ids == list(range(ids[0], ids[0] + len(ids))) if ids else True
    return {
        "path": str(path),
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
    summary["passed"] = all(summary["done"].values())
    return summary


# ---------------------------------------------------------------------------------- in-process
_channels = itertools.count()


class InProcessPlant:
    """The simulated machine and the service wired together in one process (simulated time).

    Every :meth:`step` advances the machine by one control cycle, lets the amplifier node read
    and send its CAN frames, runs one :meth:`Service.tick` and hands the pairs captured in
    that cycle to :meth:`Service.handle_frame` -- all at the machine's time, so a run is
    deterministic and as fast as the CPU allows.

    Parameters
    ----------
    cfg : MachineConfig
        The service's configuration (``log.path`` is the quality log unless ``log`` is given).
    sim_cfg : SimConfig
        The simulator's configuration.
    seed : int
        Simulator seed.
    plc_transport : {"direct", "tcp"}
        ``direct``: :class:`MachineRegisterBus`; ``tcp``: the simulator's Modbus server on an
        ephemeral 127.0.0.1 port (call :meth:`start` first).
    measurer_factory : callable, optional
        ``factory(shape)``; default the vision pipeline's ``Measurer(rig, shape)``.
    log : QualityLog or None or "config"
        The quality log; ``"config"`` opens ``cfg.log.path``.
    render_images : bool
        Render the camera images (``False``: frames carry counts and truth only; for control
        tests with a measurer that reads the truth).
    """

    def __init__(
        self,
        cfg: MachineConfig,
        sim_cfg: Any,
        *,
        seed: int = 0,
        plc_transport: str = "direct",
        measurer_factory: Callable[[tuple[int, int]], Any] | None = None,
        log: Any = "config",
        render_images: bool = True,
    ) -> None:
        import can

        from config.machine import registers_path, rig_path
        from config.rig import load_rig
        from controller.piezo_client import PiezoClient
        from controller.plc_client import Backoff, MachineRegisterBus, PlcClient
        from controller.quality_log import QualityLog
        from plant_sim.amp_node import AmpNode, AmpNodeCore
        from plant_sim.machine import Machine
        from protocol.piezo_can import PiezoCodec
        from protocol.registers import RegisterMap

        if plc_transport not in ("direct", "tcp"):
            raise ValueError(f"plc_transport must be direct or tcp, got {plc_transport!r}")
        self.cfg = cfg
        self.sim_cfg = sim_cfg
        self.machine = Machine(sim_cfg, seed=seed, render_images=render_images)
        self.regmap = RegisterMap.load(registers_path(cfg))
        self.plc_transport = plc_transport
        self.server: Any = None
        self.direct_bus: Any = None
        backoff = Backoff(cfg.plc.backoff_initial_s, cfg.plc.backoff_max_s)
        if plc_transport == "direct":
            self.direct_bus = MachineRegisterBus(self.machine, self.regmap)
            self.plc = PlcClient(self.direct_bus, self.regmap, backoff=backoff, clock=self.clock)
        else:
            from plant_sim.plc_server import PlcServer

            self.server = PlcServer(self.machine, register_map=self.regmap, host="127.0.0.1",
                                    port=0)
            self.plc = None  # type: ignore[assignment]
            self._backoff = backoff
        codec = PiezoCodec.load()
        self.rig = load_rig(rig_path(cfg))
        if measurer_factory is None:
            from vision.pipeline import Measurer

            rig = self.rig

            def measurer_factory(shape: tuple[int, int]) -> Any:
                return Measurer(rig, shape)

        self._measurer_factory = measurer_factory
        opened_log = log == "config"
        if opened_log:  # before the buses: an unusable log path leaves nothing open
            path = Path(cfg.log.path)
            path.parent.mkdir(parents=True, exist_ok=True)
            log = QualityLog(path)
        self.log = log
        self.service: Service | None = None
        buses: list[Any] = []
        try:
            self.start_id = log.last_id if log is not None else 0
            channel = f"planer-hil-{os.getpid()}-{next(_channels)}"
            self.svc_bus = can.Bus(interface="virtual", channel=channel)
            buses.append(self.svc_bus)
            amp_bus = can.Bus(interface="virtual", channel=channel)
            buses.append(amp_bus)
            knives = sim_cfg.cutterhead.knives
            self.amp = AmpNode(amp_bus,
                               AmpNodeCore(self.machine, codec, knives=knives, seed=seed),
                               own_bus=True)
            self.piezo = PiezoClient(
                self.svc_bus, codec, knives=knives, command_period_s=cfg.can.command_period_s,
                offsets_period_s=cfg.can.offsets_period_s, stroke_um=cfg.stroke_um,
            )
            self._plc_up_at: float | None = None
            self.start_mm = self.machine.feed_position_mm
            if self.plc is not None:
                self._make_service()
        except BaseException:
            for bus in buses:
                bus.shutdown()
            if opened_log and log is not None:
                log.close()
            raise

    def clock(self) -> float:
        """Machine time, s (the service's injected clock)."""
        return float(self.machine.t_s)

    def _make_service(self) -> None:
        self.service = Service(
            self.cfg, plc=self.plc, piezo=self.piezo, rig=self.rig, log=self.log,
            clock=self.clock, threaded=False, measurer_factory=self._measurer_factory,
            pairs_per_s=self.sim_cfg.camera.pairs_per_s,
        )
        self.service.keep_results = True
        if self.log is not None:
            self.log.set_quality_class(self.service.quality_class)

    async def start(self) -> None:
        """Start the Modbus server (``tcp``) and connect the service's client to it."""
        from controller.plc_client import PlcClient

        if self.server is not None and self.service is None:
            host, port = await self.server.start()
            self.plc = PlcClient.tcp(
                host, port, unit_id=self.regmap.unit_id, timeout_s=self.cfg.plc.timeout_s,
                regmap=self.regmap, backoff=self._backoff, clock=self.clock,
            )
            self._make_service()

    @property
    def travelled_mm(self) -> float:
        """Table travel since the plant was made, mm."""
        return self.machine.feed_position_mm - self.start_mm

    async def plc_down(self, duration_s: float) -> None:
        """Kill the PLC's Modbus side for ``duration_s`` machine seconds (server stopped)."""
        if self.server is not None:
            await self.server.stop()
        else:
            self.direct_bus.down = True
        self._plc_up_at = self.clock() + float(duration_s)

    def can_fault(self, kind: str, duration_s: float, **params: float) -> None:
        """``can_silence`` (the amplifier sends nothing) or ``can_drop`` for ``duration_s``."""
        core_kind = {"can_silence": "silence", "can_drop": "drop_rx"}[kind]
        p = {k: float(v) for k, v in params.items() if k == "fraction"}
        self.amp.core.inject(core_kind, start_s=self.clock(), duration_s=float(duration_s), **p)

    async def step(self) -> list[FrameResult]:
        """One control cycle; returns the results of the pairs captured in it."""
        assert self.service is not None, "call start() first"
        t = self.clock()
        if self._plc_up_at is not None and t >= self._plc_up_at - 1e-9:
            self._plc_up_at = None
            if self.server is not None:
                await self.server.start()
            else:
                self.direct_bus.down = False
        self.amp.receive(t)
        frames = self.machine.advance(self.cfg.safety.cycle_s)
        t = self.clock()
        self.amp.transmit(t)
        if self.server is not None and self.server.running:
            self.server.refresh()
        await self.service.tick(t)
        out = []
        for fr in frames:
            out.append(await self.service.handle_frame(fr, now_s=t))
        return out

    async def close(self) -> None:
        """Close the service (buses, log), the amplifier node and the server."""
        if self.service is not None:
            self.service.close()
        else:
            self.svc_bus.shutdown()
            if self.log is not None:
                self.log.close()
        self.amp.close()
        if self.server is not None:
            await self.server.stop()


class InProcessHil:
    """A scenario on :class:`InProcessPlant`: simulator and service in one process.

    Parameters
    ----------
    scenario : Scenario
        What to run.
    log_path : Path
        Quality log (created or continued).
    plc_transport : {"direct", "tcp"}
        How the service reaches the PLC (see :class:`InProcessPlant`).
    progress : callable, optional
        Receives progress lines.
    progress_every : int
        Measurements between progress lines.
    """

    def __init__(
        self,
        scenario: Scenario,
        *,
        log_path: Path,
        plc_transport: str = "direct",
        progress: Progress | None = None,
        progress_every: int = 10,
    ) -> None:
        self.scenario = scenario
        self.log_path = Path(log_path)
        self.plc_transport = plc_transport
        self.progress = progress
        self.progress_every = progress_every
        self.cfg = machine_config_for(scenario, log_path=self.log_path)
        self.sim_cfg = sim_config_for(scenario)

    def _say(self, line: str) -> None:
        if self.progress is not None:
            self.progress(line)

    async def run(self) -> dict[str, Any]:
        """Run the scenario; return the summary (see :func:`summarize`)."""
        sc, cfg = self.scenario, self.cfg
        plant = InProcessPlant(cfg, self.sim_cfg, seed=sc.seed, plc_transport=self.plc_transport)
        try:
            await plant.start()
        except BaseException:  # e.g. Modbus cannot listen: close the buses and the log
            await plant.close()
            raise
        service = plant.service
        assert service is not None
        service.on_event = lambda e: self._say(f"t={e.t_s:7.3f} s  {e.text}")
        pending = sorted(sc.faults, key=lambda f: f.at_s)
        n_last = n_seen = 0
        travel = BoardTravel(self.sim_cfg.encoder.counts_per_mm)
        wall0 = time.perf_counter()
        self._say(
            f"hil (in-process, simulated time, PLC {self.plc_transport}, CAN virtual): "
            f"scenario {sc.name}, {sc.distance_m:g} m of board, target pitch "
            f"{cfg.quality.target_pitch_mm} mm"
        )
        self._say(PROGRESS_LEGEND)
        try:
            while plant.travelled_mm < sc.distance_m * 1000.0 and plant.clock() < sc.max_sim_s:
                t = plant.clock()
                while pending and pending[0].at_s <= t + 1e-9:
                    f = pending.pop(0)
                    if f.kind == "modbus_restart":
                        self._say(f"t={t:7.3f} s  fault: Modbus server down for "
                                  f"{f.duration_s:g} s")
                        await plant.plc_down(f.duration_s)
                    elif f.kind in ("can_silence", "can_drop"):
                        self._say(f"t={t:7.3f} s  fault: {f.kind} for {f.duration_s:g} s")
                        extra = {k: v for k, v in f.params.items() if k != "duration_s"}
                        plant.can_fault(f.kind, f.duration_s, **extra)
                    # machine faults are in the simulator's [faults] table already
                await plant.step()
                n = len(service.results)
                for r in service.results[n_seen:]:
                    travel.add(r)
                n_seen = n
                if n >= n_last + self.progress_every:
                    n_last = n
                    self._say(_progress_line(service.results[-1], travel))
            wall = time.perf_counter() - wall0
        finally:
            await plant.close()
        snap = plant.plc.last
        return _service_summary(
            service,
            cfg,
            sc.faults,
            counts_per_mm=snap.counts_per_mm if snap else self.sim_cfg.encoder.counts_per_mm,
            log_path=self.log_path,
            start_id=plant.start_id,
            extra={
                "mode": "in-process",
                "scenario": sc.name,
                "plc_transport": self.plc_transport,
                "sim_time_s": round(plant.clock(), 3),
                "wall_time_s": round(wall, 3),
                "board_travel_m": round(plant.travelled_mm / 1000, 3),
            },
        )


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
        self._modulus = 1 << int(bits)
        self._prev: int | None = None
        self.measured_mm = 0.0
        """Board travel from the first result to the last one added, mm."""
        self.closed_at_mm: float | None = None
        """``measured_mm`` at the first applied result (the loop closed), mm."""

    def add(self, result: FrameResult) -> None:
        """Account for the next result (in order)."""
        if self._prev is not None:
            d = (result.counts_a - self._prev) % self._modulus
            if d >= self._modulus // 2:
                d -= self._modulus
            self.measured_mm += d / self.counts_per_mm
        self._prev = result.counts_a
        if self.closed_at_mm is None and result.applied:
            self.closed_at_mm = self.measured_mm

    @property
    def since_closed_mm(self) -> float | None:
        """Board measured since the loop closed, mm (``None`` while it has not closed)."""
        return None if self.closed_at_mm is None else self.measured_mm - self.closed_at_mm


PROGRESS_LEGEND = ("progress: metres of board measured since the loop closed, state, measured "
                   "pitch and CV (true), feed setpoint, piezo offsets")


def _progress_line(r: FrameResult, travel: BoardTravel) -> str:
    m = r.measurement
    tp = _truth(r, "pitch_mm")
    tc = _truth(r, "uniformity_cv")
    pitch = f"{m.pitch_mm:.3f}" if r.ok and m is not None else "  -  "
    cv = f"{m.uniformity_cv:.3f}" if r.ok and m is not None else "  -  "
    feed = f"{r.feed_setpoint_mm_s:6.1f}" if r.feed_setpoint_mm_s is not None else "   -  "
    offs = " ".join(f"{v:+5.2f}" for v in r.offsets_um)
    truth = f" (true {tp:.3f} / {tc:.3f})" if tp is not None and tc is not None else ""
    d = travel.since_closed_mm
    dist = "  -  " if d is None else f"{d / 1000:5.2f}"
    return (
        f"{dist} m  {r.state:4s}  pitch {pitch} mm  cv {cv}{truth}  "
        f"feed {feed} mm/s  offsets [{offs}] um"
    )


# ---------------------------------------------------------------------------------- cross-process
def cross_process_possible() -> tuple[bool, str]:
    """Whether the cross-process HIL can run here, and if not, why."""
    from protocol import can_transport

    try:
        import msgpack  # noqa: F401
    except ImportError:
        return False, "python-can's udp_multicast needs the msgpack package, not installed"
    if can_transport.in_private_netns():
        return True, "inside a private network namespace"
    if not can_transport.private_netns_available():
        return False, "unshare -rn (private network namespace) is not permitted here"
    return True, "private network namespace available"


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"cannot write {v!r} to TOML")
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, Mapping):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, Path):
        return _toml_value(str(v))
    raise ValueError(f"cannot write {type(v).__name__} to TOML")


def to_toml(doc: Mapping[str, Any]) -> str:
    """Serialise a document of tables, sub-tables and plain values as TOML text."""
    lines: list[str] = []

    def table(prefix: str, t: Mapping[str, Any]) -> None:
        plain = {k: v for k, v in t.items() if not isinstance(v, Mapping)}
        subs = {k: v for k, v in t.items() if isinstance(v, Mapping)}
        if prefix:
            lines.append(f"[{prefix}]")
        for k, v in plain.items():
            lines.append(f"{k} = {_toml_value(v)}")
        lines.append("")
        for k, v in subs.items():
            table(f"{prefix}.{k}" if prefix else k, v)

    table("", doc)
    return "\n".join(lines) + "\n"


def _die_with_parent() -> None:  # pragma: no cover - runs in the child
    """Ask Linux to SIGTERM the simulator when ``planer hil`` dies (no orphaned simulators)."""
    try:
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


class _SimProcess:
    """``planer sim`` as a child process: banner parsed, output drained in a thread."""

    def __init__(self, argv: Sequence[str], progress: Progress | None) -> None:
        self.proc = subprocess.Popen(
            list(argv), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1,
            preexec_fn=_die_with_parent,
        )
        self.progress = progress
        self.lines: list[str] = []
        self.banner: dict[str, str] = {}
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._drain, daemon=True)
        self._thread.start()

    def _drain(self) -> None:
        from plant_sim.runner import parse_banner

        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            line = line.rstrip("\n")
            self.lines.append(line)
            if not self._ready.is_set():
                if line.strip() == "ready":
                    self.banner = parse_banner(self.lines)
                    self._ready.set()
            elif self.progress is not None and "fault" in line:
                self.progress(f"sim: {line}")
        self._ready.set()

    def wait_ready(self, timeout_s: float) -> dict[str, str]:
        if not self._ready.wait(timeout_s) or not self.banner:
            tail = "; ".join(self.lines[-5:])
            raise FieldbusError(f"planer sim did not become ready: {tail or 'no output'}")
        return self.banner

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._thread.join(timeout=5)
        return int(self.proc.returncode or 0)


async def run_cross_process(
    scenario: Scenario,
    *,
    log_path: Path,
    progress: Progress | None = None,
    progress_every: int = 10,
    workdir: Path | None = None,
) -> dict[str, Any]:
    """The simulator as a separate ``planer sim`` process, the service here, in real time.

    Must run where both processes share a loopback-only network (a private namespace; see
    :func:`cross_process_possible`). CAN: ``udp_multicast`` on the namespace's ``lo``; Modbus:
    127.0.0.1 on a free port; frames: a spool directory.

    Parameters
    ----------
    scenario : Scenario
        What to run.
    log_path : Path
        Quality log (created or continued).
    progress : callable, optional
        Receives progress lines.
    progress_every : int
        Measurements between progress lines.
    workdir : Path, optional
        Folder for the simulator's configuration and frame spool, kept afterwards. Default: a
        temporary folder removed when the run ends (also on errors and Ctrl-C), after the
        simulator has stopped.
    """
    if workdir is not None:
        folder = Path(workdir)
        folder.mkdir(parents=True, exist_ok=True)
        return await _run_cross_process(scenario, folder, log_path=Path(log_path),
                                        progress=progress, progress_every=progress_every)
    with tempfile.TemporaryDirectory(prefix="planer-hil-") as tmp:
        return await _run_cross_process(scenario, Path(tmp), log_path=Path(log_path),
                                        progress=progress, progress_every=progress_every)


async def _run_cross_process(
    scenario: Scenario,
    tmp: Path,
    *,
    log_path: Path,
    progress: Progress | None,
    progress_every: int,
) -> dict[str, Any]:
    from config.machine import CanConfig
    from controller.frame_source import open_frame_source
    from controller.piezo_client import open_bus
    from controller.service import open_service

    say = progress or (lambda _line: None)
    spool = tmp / "spool"
    group = "239.74.163.2"
    can_port = 43113
    doc = sim_document(scenario)
    doc["can"] = {"interface": "udp_multicast", "channel": group,
                  "options": {"port": can_port}}
    doc["frames"] = {**doc.get("frames", {}), "spool_dir": str(spool)}
    doc.setdefault("run", {})["time_scale"] = scenario.time_scale
    doc["faults"] = {
        "inject": [{"kind": f.kind, "at_s": f.at_s, **f.params} for f in scenario.faults]
    }
    cam = doc.setdefault("camera", {})
    if not cam.get("rig"):
        cam["rig"] = str(default_path("rig.toml"))
    elif scenario.sim_config is not None and not Path(cam["rig"]).is_absolute():
        cam["rig"] = str(Path(scenario.sim_config).parent / cam["rig"])  # the copy lives in tmp
    sim_toml = tmp / "sim.toml"
    sim_toml.write_text(to_toml(doc))
    sim_cfg = sim_config_for(scenario, machine_faults=False)

    cfg = machine_config_for(scenario, log_path=log_path)
    argv = [sys.executable, "-m", "planer.cli", "sim", "--config", str(sim_toml),
            "--seed", str(scenario.seed), "--port", "0"]
    say(f"hil (cross-process): starting {' '.join(argv[2:])}")
    sim = _SimProcess(argv, progress)
    service = None
    try:
        banner = sim.wait_ready(60.0)
        host, _, port = banner["modbus"].rpartition(":")
        say(f"sim ready: modbus {banner['modbus']}, can {banner.get('can')}, "
            f"frames {banner.get('frames')}")
        optics = sim_cfg.camera.optics
        cfg = cfg.with_changes(
            plc=replace(cfg.plc, host=host, port=int(port)),
            can=CanConfig(interface="udp_multicast", channel=group,
                          options={"port": can_port},
                          command_period_s=cfg.can.command_period_s,
                          offsets_period_s=cfg.can.offsets_period_s, dbc=cfg.can.dbc),
            frames=replace(cfg.frames, source="spool", spool_dir=spool,
                           pairs_per_s=sim_cfg.camera.pairs_per_s,
                           image_width=optics.width, image_height=optics.height),
        )
        # the bus is opened here so that it is shut down if the service cannot start (log)
        bus = open_bus(cfg.can.interface, cfg.can.channel, dict(cfg.can.options))
        try:
            service = open_service(cfg, threaded=True, log_path=log_path, can_bus=bus)
        except BaseException:
            bus.shutdown()
            raise
        start_id = service.log.last_id
        service.keep_results = True
        t_start = service.clock()
        service.on_event = lambda e: say(f"t={e.t_s - t_start:7.3f} s  {e.text}")
        say(PROGRESS_LEGEND)
        source = open_frame_source(cfg.frames)
        stop = asyncio.Event()
        cpm = sim_cfg.encoder.counts_per_mm
        travel = BoardTravel(cpm)
        state = {"n_last": 0}

        def on_result(r: FrameResult) -> None:
            travel.add(r)
            n = len(service.results)
            if n >= state["n_last"] + progress_every:
                state["n_last"] = n
                say(_progress_line(r, travel))
            if travel.measured_mm >= scenario.distance_m * 1000.0:
                stop.set()

        service.on_result = on_result

        async def time_limit() -> None:
            await asyncio.sleep(scenario.max_sim_s / scenario.time_scale + 10.0)
            stop.set()

        limiter = asyncio.create_task(time_limit())
        wall0 = time.perf_counter()
        try:
            await service.run(source, stop=stop)
        finally:
            limiter.cancel()
        wall = time.perf_counter() - wall0
    finally:
        if service is not None:
            service.close()
        code = sim.stop()
    summary = _service_summary(
        service,
        cfg,
        scenario.faults,
        counts_per_mm=cpm,
        log_path=log_path,
        start_id=start_id,
        time_offset_s=_estimate_offset(service.results),
        t_start_s=t_start,
        extra={
            "mode": "cross-process",
            "scenario": scenario.name,
            "wall_time_s": round(wall, 3),
            "sim_banner": banner,
        },
    )
    summary["sim_exit_code"] = code
    return summary


def _estimate_offset(results: Sequence[FrameResult]) -> float:
    """Service time minus machine time (lowest arrival delay of the frames)."""
    offs = [r.t_s - r.frame_t_s for r in results]
    return min(offs) if offs else 0.0


LOCAL_OFFSET_WINDOW_S = 2.0
"""Machine seconds before a fault whose frames map its time onto the service clock."""


def _local_offset(results: Sequence[FrameResult], at_s: float, default: float) -> float:
    """Service time minus machine time just before machine time ``at_s``.

    The lowest arrival delay of the pairs taken in the ``LOCAL_OFFSET_WINDOW_S`` before it: a
    simulator that fell behind real time for a while (a loaded machine) shifts the mapping, and
    a fault's timing is judged against the mapping in force when it happened.
    """
    offs = [r.t_s - r.frame_t_s for r in results
            if at_s - LOCAL_OFFSET_WINDOW_S <= r.frame_t_s <= at_s]
    return max(min(offs), default) if offs else default
