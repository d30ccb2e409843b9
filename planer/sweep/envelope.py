"""The envelope's verdict: a sweep's runs per plant against the references the plant allows.

``python -m planer.sweep.envelope config/sweeps/envelope.toml runs/sweep-envelope/results.csv
[--plot FILE.png]`` prints one Markdown row per plant (the seeds together) and, with
``--plot``, the piezo corners' final true CV beside their references. References per plant:

- the zero table's true CV at the target pitch (the loop's "initial" finish, at the pitch the
  feed loop drives to; :func:`planer.sweep.optimum.true_cv`);
- the constrained optimum (:func:`planer.sweep.optimum.constrained_optimum_cv`): the best table
  the loop may command (the knife patterns whose gain reaches the loop's ``[uniformity_loop]
  gain_min``, the others held at zero as the loop holds them) within the stroke that keeps the
  amplifier within its temperature limit in steady state; where the limit binds, the optimum
  regardless of the heat and its temperature are given too; where patterns are held, the
  optimum over every pattern (within the heat) beside it.

Criteria (``docs/control_design.md``, section 8): in every run the final true CV at most 10 %
above the zero table's and the optimum's (:data:`CV_REL_TOL`, plus :data:`CV_ABS_TOL` for
optima near zero); no safe state; where the optimum is below :data:`TIGHT_CV`, CV <= 0.03 within
3 m of board after the camera's delay; the pitch's verdict (``pitch_verdict``) ``in band`` or
``ramp not finished``.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

CV_REL_TOL = 0.10
"""The final true CV may exceed a reference by this fraction."""
CV_ABS_TOL = 0.005
"""... and by this much in CV (a sixth of the closed loop's target), for references near 0."""
TIGHT_CV = 0.03
"""The closed loop's uniformity target."""
CONVERGE_MM = 3000.0
"""Board after the camera's delay within which CV <= 0.03 must hold, mm."""
HOT_MARGIN_C = 0.5
"""An optimum this close to the temperature limit is limited by it."""


@dataclass(frozen=True)
class PlantRefs:
    """The references of one plant."""

    zero_cv: float
    optimum_cv: float
    optimum_c: float
    hot_cv: float | None  # the optimum regardless of the heat, where the limit binds
    hot_c: float | None
    camera_mm: float
    patterns: tuple[int, ...] = ()  # the knife patterns the optimum may use
    held: tuple[int, ...] = ()  # the patterns below the loop's gain_min, held at zero
    every_cv: float | None = None  # the optimum over every pattern, where some are held
    every_c: float | None = None


def references(sim_cfg: Any, machine_cfg: Any) -> PlantRefs:
    """Zero table and constrained optima of one plant (a few seconds of Nelder-Mead)."""
    from planer.sweep.optimum import constrained_optimum_cv, true_cv

    z = sim_cfg.cutterhead.knives
    feed = machine_cfg.quality.target_pitch_mm * sim_cfg.spindle.rpm / 60.0 * z
    zero = true_cv(sim_cfg, np.zeros(z), feed_mm_s=feed)
    opt = constrained_optimum_cv(sim_cfg, machine_cfg)
    hot_cv = hot_c = every_cv = every_c = None
    if opt.temperature_c >= opt.temperature_limit_c - HOT_MARGIN_C:
        free = constrained_optimum_cv(sim_cfg, machine_cfg, temperature_limit_c=math.inf)
        hot_cv, hot_c = free.cv, free.temperature_c
    held = tuple(m for m in range(1, z // 2 + 1) if m not in opt.patterns)
    if held:
        every = constrained_optimum_cv(sim_cfg, machine_cfg, gain_min=0.0)
        every_cv, every_c = every.cv, every.temperature_c
    return PlantRefs(zero_cv=zero, optimum_cv=opt.cv, optimum_c=opt.temperature_c,
                     hot_cv=hot_cv, hot_c=hot_c,
                     camera_mm=float(sim_cfg.camera.cutter_to_camera_mm),
                     patterns=tuple(opt.patterns), held=held, every_cv=every_cv,
                     every_c=every_c)


def _f(text: str) -> float | None:
    try:
        v = float(text)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _span(values: Sequence[float | None], fmt: str, scale: float = 1.0) -> str:
    vals = [v * scale for v in values if v is not None]
    if not vals:
        return "-"
    lo, hi = format(min(vals), fmt), format(max(vals), fmt)
    text = lo if lo == hi else f"{lo}-{hi}"
    return text if len(vals) == len(values) else f"{text} ({len(values) - len(vals)} never)"


def judge_plant(rows: Sequence[Mapping[str, str]], refs: PlantRefs) -> dict[str, Any]:
    """The plant's cells and its verdict from its runs (one per seed)."""
    finals = [_f(r["final_true_cv"]) for r in rows]
    settled = []
    for r in rows:
        after, closed = _f(r["cv_003_settled_after_mm"]), _f(r.get("loop_closed_at_mm", ""))
        settled.append(None if after is None else after + (closed or 0.0))
    safe = [int(r["safe_entries"] or 0) for r in rows]
    pitch = sorted({r.get("pitch_verdict", "") or "-" for r in rows})
    errors = [r["error"] for r in rows if r.get("error")]
    misses = []
    if errors:
        misses.append(f"{len(errors)} failed")
    worst = max((v for v in finals if v is not None), default=math.inf)
    for name, ref in (("zero table", refs.zero_cv), ("optimum", refs.optimum_cv)):
        if worst > ref * (1.0 + CV_REL_TOL) + CV_ABS_TOL:
            misses.append(f"CV above the {name}")
    if any(safe):
        misses.append("safe entries")
    # a plant can converge when its optimum is below the target, or a run showed it can
    can_converge = refs.optimum_cv < TIGHT_CV or worst < TIGHT_CV
    limit = refs.camera_mm + CONVERGE_MM
    if can_converge:
        late = sum(1 for s in settled if s is None or s > limit)
        if late:
            misses.append(f"CV <= 0.03 late in {late} of {len(rows)}")
    bad_pitch = [p for p in pitch if p not in ("in band", "ramp not finished", "-")]
    if bad_pitch:
        misses.append("pitch " + ", ".join(bad_pitch))
    offsets = [_f(r["max_offset_um"]) for r in rows]
    errs = [_f(r["final_pitch_error"]) for r in rows]
    return {
        "final": _span(finals, ".4f"),
        "settled": _span(settled, ".2f", 1e-3) if can_converge else "-",
        "safe": _span([float(s) for s in safe], ".0f"),
        "offset": _span(offsets, ".1f"),
        "pitch": ", ".join(pitch) + f" ({_span(errs, '+.1f', 100.0)} %)",
        "verdict": "pass" if not misses else "; ".join(misses),
    }


def _label(values: Mapping[str, Any]) -> str:
    if not values:
        return "base"
    parts = []
    for key, v in values.items():
        names = key.split(",")
        vals = v if len(names) > 1 else [v]
        for name, val in zip(names, vals, strict=True):
            if name.endswith("runout_um"):
                continue
            parts.append(f"{name.rsplit('.', 1)[-1]} {val:g}" if isinstance(val, float)
                         else f"{name.rsplit('.', 1)[-1]} {val}")
    return ", ".join(parts)


def envelope_table(sweep_path: str | Path, results_path: str | Path,
                   *, progress: Any = None, cache: str | Path | None = None
                   ) -> list[dict[str, Any]]:
    """One dict per plant: label, references, the cells of :func:`judge_plant`.

    ``cache``: a JSON file of the references by plant label, read when it exists and written
    after (the references depend on the plant only, not on the runs).
    """
    import json

    from planer.sweep.design import load_sweep
    from planer.sweep.driver import read_results
    from planer.sweep.point import build_machine_config, build_sim_config, prepare

    sweep = load_sweep(sweep_path)
    jobs, _ = prepare(sweep)
    by_run = {str(j.point.index): j for j in jobs}
    plants: dict[str, tuple[Any, list[dict[str, str]]]] = {}
    for row in read_results(results_path):
        job = by_run.get(row["run"])
        if job is None:
            continue
        label = _label({k: v for k, v in job.point.values.items() if k in sweep.keys})
        plants.setdefault(label, (job, []))[1].append(row)
    known: dict[str, Any] = {}
    if cache is not None and Path(cache).exists():
        known = json.loads(Path(cache).read_text())
    fields = set(PlantRefs.__dataclass_fields__)
    out = []
    for label, (job, rows) in plants.items():
        if label in known and set(known[label]) == fields:  # else an older cache: again
            entry = dict(known[label])
            entry["patterns"], entry["held"] = tuple(entry["patterns"]), tuple(entry["held"])
            refs = PlantRefs(**entry)
        else:
            if progress is not None:
                progress(label)
            refs = references(build_sim_config(job), build_machine_config(job))
            known[label] = refs.__dict__
            if cache is not None:
                Path(cache).write_text(json.dumps(known, indent=1))
        values = {k: v for k, v in job.point.values.items() if k in sweep.keys}
        out.append({"plant": label, "values": values, "refs": refs,
                    "rows": rows, **judge_plant(rows, refs)})
    return out


def markdown(table: Sequence[Mapping[str, Any]]) -> str:
    """The plants as the Markdown table of ``docs/control_design.md``, section 8."""
    lines = ["| plant | zero table | optimum | final true CV | to CV <= 0.03, m | safe entries "
             "| largest offset µm | pitch | verdict |",
             "|---|---:|---:|---:|---:|---:|---:|---|---|"]
    for p in table:
        r: PlantRefs = p["refs"]
        opt = f"{r.optimum_cv:.3f}"
        notes = []
        if r.held:
            notes.append("pattern " + ", ".join(str(m) for m in r.held) + " held")
        if r.hot_cv is not None:
            notes.append(f"{r.optimum_c:.0f} °C; {r.hot_cv:.3f} at {r.hot_c:.0f} °C")
        if r.every_cv is not None:
            notes.append(f"every pattern: {r.every_cv:.3f} at {r.every_c:.0f} °C")
        if notes:
            opt += " (" + "; ".join(notes) + ")"
        lines.append(f"| {p['plant']} | {r.zero_cv:.3f} | {opt} | {p['final']} | {p['settled']} "
                     f"| {p['safe']} | {p['offset']} | {p['pitch']} | {p['verdict']} |")
    return "\n".join(lines)


def plot_piezo_corners(table: Sequence[Mapping[str, Any]], path: str | Path) -> Path | None:
    """The plants that vary the piezo: final true CV per seed beside the references (PNG)."""
    from matplotlib.figure import Figure

    rows = [p for p in table if any(k.startswith("sim.piezo.") for k in p["values"])]
    if not rows:
        return None
    fig = Figure(figsize=(9.0, 4.2), dpi=110)
    ax = fig.add_subplot(1, 1, 1)
    for i, p in enumerate(rows):
        r: PlantRefs = p["refs"]
        finals = [_f(x["final_true_cv"]) for x in p["rows"]]
        ax.scatter([i] * len(finals), [max(v, 1e-4) for v in finals if v is not None],
                   color="tab:blue", zorder=3, label="final true CV (per seed)" if i == 0 else None)
        ax.scatter([i + 0.15], [r.zero_cv], marker="x", color="tab:gray",
                   label="zero table" if i == 0 else None)
        ax.scatter([i - 0.15], [max(r.optimum_cv, 1e-4)], marker="D", color="tab:green",
                   label="optimum: patterns the loop moves, within 70 °C" if i == 0 else None)
        if r.every_cv is not None:
            ax.scatter([i - 0.3], [max(r.every_cv, 1e-4)], marker="s", facecolors="none",
                       edgecolors="tab:orange", label="optimum over every pattern" if not any(
                           q["refs"].every_cv is not None for q in rows[:i]) else None)
        if r.hot_cv is not None:
            ax.scatter([i - 0.15], [max(r.hot_cv, 1e-4)], marker="D", facecolors="none",
                       edgecolors="tab:red", label="optimum that overheats" if not any(
                           q["refs"].hot_cv is not None for q in rows[:i]) else None)
    ax.axhline(TIGHT_CV, color="k", lw=0.8, ls="--")
    ax.set_yscale("log")
    ax.set_ylabel("true uniformity CV")
    ax.set_xticks(range(len(rows)))
    ax.set_xticklabels([p["plant"].replace("resonance_hz ", "").replace(", hysteresis ", " Hz\nh ")
                        .replace(", damping ", ", z ") for p in rows], fontsize=7)
    ax.legend(fontsize=7, loc="upper right")
    ax.set_title("Envelope sweep, piezo corners (8 m, 3 seeds; a CV of 0 drawn at 1e-4)",
                 fontsize=9)
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m planer.sweep.envelope SWEEP RESULTS [--plot PNG]``."""
    ap = argparse.ArgumentParser(prog="python -m planer.sweep.envelope", description=__doc__)
    ap.add_argument("sweep", help="the sweep file (config/sweeps/envelope.toml)")
    ap.add_argument("results", help="its results.csv")
    ap.add_argument("--plot", help="write the piezo corners' figure here (PNG)")
    ap.add_argument("--cache", help="keep the plants' references in this JSON file")
    args = ap.parse_args(argv)
    table = envelope_table(args.sweep, args.results, cache=args.cache,
                           progress=lambda s: print(f"references: {s}", file=sys.stderr))
    print(markdown(table))
    if args.plot:
        print(f"figure: {plot_piezo_corners(table, args.plot)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
