"""Soak: a long in-process HIL run on simulated time, with faults, watching for slow leaks.

The simulated machine and the service run in one process (:class:`InProcessPlant`) for at
least an hour of machine time; every ``fault_every_s`` machine seconds the next fault of
:data:`FAULT_CYCLE` is injected (Modbus restart, CAN silence, belt slip, knot, ...). Every
``sample_every_s`` machine seconds one :class:`SoakSample` is taken: the process's resident
memory (``/proc/self/status`` VmRSS), the Python heap traced by :mod:`tracemalloc`, the Python
objects the garbage collector tracks (a leak of results or frames shows there), the open
file descriptors (``/proc/self/fd``), the wall time the service took per image pair
(``Service.handle_frame``; median and 99th percentile over the window), the safe-state entries
and the quality records so far. They must stay flat: :func:`flatness` compares the end of the
run with its start (after a warm-up).

Run it with ``python -m planer.hil.soak --minutes 60`` (``--no-render``: frames carry the
simulator's truth only and a measurer reads it -- about seven times faster; ``--json``).
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import math
import os
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from config.faults import Fault, FaultKind
from controller.service.events import EventKind
from planer.hil.scenario import Scenario, load_scenario, machine_config_for, sim_config_for

__all__ = [
    "FAULT_CYCLE",
    "SoakSample",
    "TruthMeasurer",
    "flatness",
    "format_table",
    "main",
    "open_fds",
    "rss_bytes",
    "run_soak",
]

FAULT_CYCLE: tuple[Fault, ...] = (
    Fault(FaultKind.MODBUS_RESTART, params={"duration_s": 1.5}),
    Fault(FaultKind.BELT_SLIP, params={"px": 12.0}),
    Fault(FaultKind.CAN_SILENCE, params={"duration_s": 1.0}),
    Fault(FaultKind.KNOT, params={"at_mm": 1500.0, "length_mm": 40.0, "width_mm": 30.0}),
    Fault(FaultKind.CAN_DROP, params={"duration_s": 1.0, "fraction": 0.5}),
    Fault(FaultKind.ENCODER_WRAP, params={"counts_before_wrap": 5000}),
)
"""The faults injected in turn (each at the time it comes due)."""


def rss_bytes() -> int:
    """Resident memory of this process, bytes (``/proc/self/status`` VmRSS; 0 if unknown)."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def open_fds() -> int:
    """Open file descriptors of this process (``/proc/self/fd``; -1 if unknown)."""
    try:
        return len(os.listdir("/proc/self/fd"))
    except OSError:
        return -1


class TruthMeasurer:
    """A measurer that returns the simulator's truth of each pair (no images needed).

    Frames are filed by :meth:`file` under their encoder counts and forgotten once measured,
    so it holds nothing for long.
    """

    def __init__(self) -> None:
        self._frames: dict[tuple[int, int], Any] = {}

    def file(self, frames: Sequence[Any]) -> None:
        """Remember the truth of frames just captured."""
        for f in frames:
            self._frames[(f.counts_a, f.counts_b)] = f.truth

    def measure(self, image_a: Any, image_b: Any, *, counts_a: int, counts_b: int,
                speed_mm_s: float | None = None) -> Any:
        """The pair's true pitch, mark widths and uniformity (``Measurer.measure``'s shape)."""
        tr = self._frames.pop((counts_a, counts_b))
        return SimpleNamespace(
            pitch_mm=float(tr["pitch_mm"]),
            mark_widths_mm=np.asarray(tr["mark_widths_mm"], dtype=float),
            bottoms_mm=np.asarray(tr["bottoms_mm"], dtype=float),
            uniformity_cv=float(tr["uniformity_cv"]),
            depth_um=float(tr["depth_um"]),
            shift_px=float(tr["shift_px"]),
            confidence=1.0,
        )


@dataclass(frozen=True)
class SoakSample:
    """One sample of a soak run (see the module docstring)."""

    machine_s: float
    wall_s: float
    rss_mb: float
    traced_mb: float
    objects: int
    fds: int
    pairs: int
    pair_ms_p50: float | None
    pair_ms_p99: float | None
    safe_entries: int
    records: int
    faults: int


def _pct(values: Sequence[float], q: float) -> float | None:
    return round(float(np.percentile(values, q)), 3) if values else None


async def run_soak(
    *,
    duration_s: float = 3600.0,
    fault_every_s: float = 180.0,
    sample_every_s: float = 60.0,
    render_images: bool = True,
    scenario: Scenario | None = None,
    log_path: Path | None = None,
    trace: bool = True,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run the soak; return ``{"samples": [...], "flatness": {...}, ...}``.

    Parameters
    ----------
    duration_s : float
        Machine time to run, s.
    fault_every_s : float
        Machine seconds between injected faults (the first one after one interval).
    sample_every_s : float
        Machine seconds between samples (one more at the start and at the end).
    render_images : bool
        Render the images and measure them with the vision pipeline (``False``: a
        :class:`TruthMeasurer` reads the simulator's truth).
    scenario : Scenario, optional
        Machine and service set-up (default: the ``default`` scenario of ``config/hil.toml``).
    log_path : Path, optional
        Quality log (default: in a temporary folder, removed afterwards).
    trace : bool
        Trace the Python heap with :mod:`tracemalloc` (slows allocation somewhat).
    progress : callable, optional
        Receives one line per sample.
    """
    for name, v in (("duration_s", duration_s), ("fault_every_s", fault_every_s),
                    ("sample_every_s", sample_every_s)):
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
    if log_path is None:
        with tempfile.TemporaryDirectory(prefix="planer-soak-") as tmp:
            return await _run_soak(duration_s, fault_every_s, sample_every_s, render_images,
                                   scenario, Path(tmp) / "soak.sqlite", trace, progress)
    return await _run_soak(duration_s, fault_every_s, sample_every_s, render_images, scenario,
                           Path(log_path), trace, progress)


async def _soak_plant(scenario: Scenario | None, log_path: Path, render_images: bool) -> Any:
    """The in-process plant of the soak, started (faults off: the soak plays its own).

    Without images the measurement is the machine's truth (:class:`TruthMeasurer`), filed as
    the machine hands its frames out.
    """
    from planer.hil.in_process import InProcessPlant

    sc = scenario if scenario is not None else load_scenario("default")
    sc = replace(sc, faults=())
    cfg = machine_config_for(sc, log_path=log_path)
    truth = None if render_images else TruthMeasurer()
    plant = InProcessPlant(
        cfg, sim_config_for(sc), seed=sc.seed, render_images=render_images, plc_transport="tcp",
        measurer_factory=None if truth is None else (lambda shape: truth),
    )
    if truth is not None:
        advance = plant.machine.advance

        def filing_advance(dt_s: float) -> list[Any]:
            frames = advance(dt_s)
            truth.file(frames)
            return frames

        plant.machine.advance = filing_advance  # type: ignore[method-assign]
    try:
        await plant.start()
    except BaseException:
        await plant.close()
        raise
    return plant


def _time_pairs(service: Any) -> list[float]:
    """Wrap the service's pair handling to note each pair's wall time, ms (the list returned)."""
    pair_ms: list[float] = []
    handle = service.handle_frame

    async def timed_handle(frame: Any, **kw: Any) -> Any:
        t0 = time.perf_counter()
        out = await handle(frame, **kw)
        pair_ms.append((time.perf_counter() - t0) * 1e3)
        return out

    service.handle_frame = timed_handle  # type: ignore[method-assign]
    return pair_ms


async def _run_soak(
    duration_s: float,
    fault_every_s: float,
    sample_every_s: float,
    render_images: bool,
    scenario: Scenario | None,
    log_path: Path,
    trace: bool,
    progress: Callable[[str], None] | None,
) -> dict[str, Any]:
    say = progress or (lambda _line: None)
    plant = await _soak_plant(scenario, log_path, render_images)
    service = plant.service
    assert service is not None
    service.keep_results = False  # the soak must not hold what it measures
    pair_ms = _time_pairs(service)
    counts = {"pairs": 0, "failed": 0, "faults": 0}
    errors: dict[str, int] = {}

    def on_result(r: Any) -> None:
        counts["pairs"] += 1
        if not r.ok:
            counts["failed"] += 1
            key = str(r.error).split(":")[0][:60]
            errors[key] = errors.get(key, 0) + 1

    service.on_result = on_result
    samples: list[SoakSample] = []
    window: list[float] = []
    wall0 = time.perf_counter()
    if trace and not tracemalloc.is_tracing():
        tracemalloc.start()
        own_trace = True
    else:
        own_trace = False

    def sample() -> None:
        gc.collect()
        window.extend(pair_ms)
        pair_ms.clear()
        s = SoakSample(
            machine_s=round(plant.clock(), 3),
            wall_s=round(time.perf_counter() - wall0, 2),
            rss_mb=round(rss_bytes() / 2**20, 2),
            traced_mb=round(tracemalloc.get_traced_memory()[0] / 2**20, 3)
            if tracemalloc.is_tracing() else -1.0,
            objects=len(gc.get_objects()),
            fds=open_fds(),
            pairs=counts["pairs"],
            pair_ms_p50=_pct(window, 50),
            pair_ms_p99=_pct(window, 99),
            safe_entries=sum(e.kind is EventKind.SAFE_STATE for e in service.events),
            records=(plant.log.last_id - plant.start_id) if plant.log is not None else -1,
            faults=counts["faults"],
        )
        window.clear()
        samples.append(s)
        say(format_table([s], header=len(samples) == 1))

    next_fault = fault_every_s
    next_sample = sample_every_s
    i_fault = 0
    try:
        sample()
        while plant.clock() < duration_s - 1e-9:
            t = plant.clock()
            if t >= next_fault - 1e-9:
                fault = FAULT_CYCLE[i_fault % len(FAULT_CYCLE)]
                i_fault += 1
                next_fault += fault_every_s
                counts["faults"] += 1
                # the plant driver plays interface faults and hands the others to the machine
                plant.driver.inject(fault.kind.value, **fault.params)
            await plant.step()
            if plant.clock() >= next_sample - 1e-9:
                next_sample += sample_every_s
                sample()
        if samples[-1].machine_s < plant.clock() - 1e-6:
            sample()
    finally:
        if own_trace:
            tracemalloc.stop()
        await plant.close()
    return {
        "duration_s": duration_s,
        "render_images": render_images,
        "fault_every_s": fault_every_s,
        "faults": counts["faults"],
        "pairs": counts["pairs"],
        "failed_pairs": counts["failed"],
        "failures": errors,
        "safe_reasons": _safe_reasons(service.events),
        "wall_s": round(time.perf_counter() - wall0, 1),
        "samples": [asdict(s) for s in samples],
        "flatness": flatness(samples),
    }


def _safe_reasons(events: Sequence[Any]) -> dict[str, int]:
    out: dict[str, int] = {}
    for e in events:
        if e.kind is EventKind.SAFE_STATE:
            why = e.reason or "unknown"
            out[why] = out.get(why, 0) + 1
    return out


def flatness(samples: Sequence[SoakSample], *, warmup: float = 0.25) -> dict[str, Any]:
    """Growth from the first sample after the warm-up to the last one.

    Parameters
    ----------
    samples : sequence of SoakSample
        The run's samples in order.
    warmup : float
        Fraction of the run's machine time treated as warm-up (caches, first boards).

    Returns
    -------
    dict
        ``from_s``, ``to_s`` (machine time), ``rss_mb`` and ``traced_mb`` growth,
        ``traced_mb_per_h`` (growth rate), ``objects`` (Python objects the garbage collector
        tracks) and ``objects_per_pair`` growth, ``fds`` growth, ``pair_ms_p50`` of the first
        and the last window.
    """
    if len(samples) < 2:
        return {}
    end = samples[-1].machine_s
    first = next(s for s in samples if s.machine_s >= warmup * end)
    if first is samples[-1]:
        first = samples[-2]
    last = samples[-1]
    hours = max(last.machine_s - first.machine_s, 1e-9) / 3600.0
    return {
        "from_s": first.machine_s,
        "to_s": last.machine_s,
        "rss_mb": round(last.rss_mb - first.rss_mb, 2),
        "traced_mb": round(last.traced_mb - first.traced_mb, 3),
        "traced_mb_per_h": round((last.traced_mb - first.traced_mb) / hours, 3),
        "objects": last.objects - first.objects,
        "objects_per_pair": round((last.objects - first.objects)
                                  / max(last.pairs - first.pairs, 1), 4),
        "fds": last.fds - first.fds,
        "pair_ms_p50": [first.pair_ms_p50, last.pair_ms_p50],
    }


def format_table(samples: Sequence[SoakSample], *, header: bool = True) -> str:
    """Samples as a Markdown table (``header``: with the column names)."""
    lines = []
    if header:
        lines.append("| machine time | wall | RSS MB | traced MB | objects | fds | pairs "
                     "| per pair p50 / p99 ms | safe entries | records | faults |")
        lines.append("|---|---|---|---|---|---|---|---|---|---|---|")

    def ms(v: float | None) -> str:
        return "-" if v is None else f"{v:.1f}"

    for s in samples:
        lines.append(
            f"| {s.machine_s / 60:.1f} min | {s.wall_s:.0f} s | {s.rss_mb:.1f} | "
            f"{s.traced_mb:.2f} | {s.objects} | {s.fds} | {s.pairs} | {ms(s.pair_ms_p50)} / "
            f"{ms(s.pair_ms_p99)} | {s.safe_entries} | {s.records} | {s.faults} |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m planer.hil.soak``: run the soak, print the table (or ``--json``)."""
    p = argparse.ArgumentParser(prog="python -m planer.hil.soak",
                                description=(__doc__ or "").split("\n")[0])
    p.add_argument("--minutes", type=float, default=60.0, help="machine minutes (default 60)")
    p.add_argument("--fault-every-s", type=float, default=180.0, help="machine s between faults")
    p.add_argument("--sample-every-s", type=float, default=300.0, help="machine s between samples")
    p.add_argument("--no-render", action="store_true",
                   help="no images: a measurer reads the simulator's truth")
    p.add_argument("--no-trace", action="store_true", help="do not trace the heap (tracemalloc)")
    p.add_argument("--log", default=None, help="quality log (default: temporary)")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")
    args = p.parse_args(argv)
    import logging

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    try:
        out = asyncio.run(run_soak(
            duration_s=args.minutes * 60.0, fault_every_s=args.fault_every_s,
            sample_every_s=args.sample_every_s, render_images=not args.no_render,
            log_path=Path(args.log) if args.log else None, trace=not args.no_trace,
            progress=lambda line: print(line, file=sys.stderr, flush=True),
        ))
    except ValueError as exc:
        print(f"soak: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(out, allow_nan=False))
    else:
        print(json.dumps({k: v for k, v in out.items() if k != "samples"}))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
