"""The moulder's frame-to-setpoint latency over the heads' pair rate (where the target holds).

``planer bench --only moulder`` runs the four heads at 100 pairs/s each. Whether a machine
carries that is one number; where its latency turns up is what a buyer choosing the machine
needs. This runs :func:`planer.benchmarks.moulder.run` at several rates per head, one after
the other on the same machine, and reports per rate the pairs served, dropped, the p50 / p99 /
max latency, the CPU a pair and the cores busy, with the highest rate that meets the target
(p99 <= :data:`planer.benchmarks.moulder.TARGET_P99_MS`, nothing dropped) and a figure::

    python -m planer.benchmarks.moulder_rates --rates 25,50,75,100 --figure r.png [--json]

Each rate takes as long as a moulder run (its pairs rendered first, then fed for 6 s; 30-40 s
on a 2-core VM); a line per rate on stderr says where it is.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from core.errors import ConfigError

DEFAULT_RATES_HZ = (25.0, 50.0, 75.0, 100.0)
"""Pairs per second of each head a bare sweep runs."""
ROW_KEYS = ("rate_hz_per_head", "pairs_per_s", "pairs_in", "handled", "dropped", "p50_ms",
            "p99_ms", "max_ms", "cpu_ms_per_pair", "cores_busy", "meets")
"""The keys of each rate's row (``meets``: p99 within the target and nothing dropped)."""
TICKS_FROM_MS = 20.0
"""The figure's latency ticks run at least to this, ms (past the target)."""


class RatesError(ConfigError):
    """A rate list that is not a list of positive numbers."""


def parse_rates(text: str) -> tuple[float, ...]:
    """Rates per head from ``"25,50,100"``: positive, finite, distinct; sorted.

    Raises
    ------
    RatesError
        Naming the bad entry (``rates: 'x' is not a number``).
    """
    parts = [p.strip() for p in str(text).split(",")]
    if not parts or parts == [""]:
        raise RatesError("rates: give at least one rate, e.g. 25,50,100")
    out: list[float] = []
    for p in parts:
        try:
            v = float(p)
        except ValueError:
            raise RatesError(f"rates: {p!r} is not a number") from None
        if not (math.isfinite(v) and v > 0):
            raise RatesError(f"rates: {p!r} must be a positive, finite number of pairs/s")
        if v in out:
            raise RatesError(f"rates: {p!r} is given twice")
        out.append(v)
    return tuple(sorted(out))


def row(result: dict[str, Any]) -> dict[str, Any]:
    """One rate's row (:data:`ROW_KEYS`) from a :func:`planer.benchmarks.moulder.run` result."""
    o = result["overall"]
    meets = result.get("meets", {})
    return {
        "rate_hz_per_head": result["rate_hz_per_head"],
        "pairs_per_s": o.get("pairs_per_s"),
        "pairs_in": o["pairs_in"],
        "handled": o["handled"],
        "dropped": o["dropped"],
        "p50_ms": o.get("p50_ms"),
        "p99_ms": o.get("p99_ms"),
        "max_ms": o.get("max_ms"),
        "cpu_ms_per_pair": o.get("cpu_ms_per_pair"),
        "cores_busy": o.get("cores_busy"),
        "meets": bool(meets.get("p99")) and bool(meets.get("nothing_dropped")),
    }


def highest_meeting(rows: Sequence[dict[str, Any]]) -> float | None:
    """The highest rate per head whose run met the target, and every slower rate's too.

    A rate that met it above one that did not is not counted (the machine's speed swung
    between the runs: the lower, failed rate bounds what it carries). ``None``: none met.
    """
    best = None
    for r in sorted(rows, key=lambda r: r["rate_hz_per_head"]):
        if not r["meets"]:
            break
        best = r["rate_hz_per_head"]
    return best


def sweep(rates_hz: Sequence[float] = DEFAULT_RATES_HZ, *, quick: bool = False,
          progress: Callable[[str], None] | None = None,
          run: Callable[..., dict[str, Any]] | None = None) -> dict[str, Any]:
    """The moulder bench at each rate per head, slowest first.

    Parameters
    ----------
    rates_hz : sequence of float
        Pairs per second of each head (:func:`parse_rates`' checks).
    quick : bool
        Short runs (:data:`planer.benchmarks.moulder.QUICK_PAIRS` pairs a head).
    progress : callable, optional
        Given a line before and after each rate.
    run : callable, optional
        The run of one rate (default :func:`planer.benchmarks.moulder.run`).

    Returns
    -------
    dict
        ``rows`` (one per rate, :data:`ROW_KEYS`), ``heads``, ``workers``, ``target_p99_ms``,
        ``highest_meeting_hz_per_head`` and ``_pairs_per_s`` (``None``: no rate met it),
        ``machine`` (the first run's cores and load before, the last one's load after).
    """
    from planer.benchmarks import moulder

    rates = parse_rates(",".join(repr(float(r)) for r in rates_hz))
    run_one = moulder.run if run is None else run
    say = progress or (lambda line: None)
    rows, results = [], []
    for i, rate in enumerate(rates):
        say(f"moulder rates: {i + 1}/{len(rates)}: {rate:g} pairs/s a head ...")
        res = run_one(quick, rate_hz=rate)
        results.append(res)
        rows.append(row(res))
        r = rows[-1]
        say(f"moulder rates: {rate:g} pairs/s a head: p99 {_ms(r['p99_ms'])} ms, "
            f"{r['dropped']} dropped, {r['cpu_ms_per_pair'] or 0:.2f} ms CPU a pair "
            f"({'meets' if r['meets'] else 'MISSES'} the target)")
    heads = len(results[0]["heads"])
    best = highest_meeting(rows)
    first, last = results[0].get("machine", {}), results[-1].get("machine", {})
    return {
        "rows": rows,
        "heads": heads,
        "workers": results[0].get("workers"),
        "target_p99_ms": results[0].get("target_p99_ms", moulder.TARGET_P99_MS),
        "highest_meeting_hz_per_head": best,
        "highest_meeting_pairs_per_s": None if best is None else best * heads,
        "machine": {"cores": first.get("cores"), "load_avg": first.get("load_avg"),
                    "load_avg_after": last.get("load_avg_after")},
    }


def _ms(v: Any) -> str:
    return "-" if v is None else f"{v:.1f}"


def text(result: dict[str, Any]) -> str:
    """The readable table of a sweep."""
    m = result["machine"]
    best = result["highest_meeting_pairs_per_s"]
    lines = [
        f"moulder rates ({result['heads']} heads, {result['workers']} worker process(es); "
        f"machine: {m.get('cores')} cores, load {m.get('load_avg')} -> "
        f"{m.get('load_avg_after')}): target p99 <= {result['target_p99_ms']:g} ms, "
        "nothing dropped",
        "  per head | pairs/s served | dropped | p50 / p99 / max ms | CPU ms a pair | "
        "cores busy | target",
    ]
    for r in result["rows"]:
        lines.append(
            f"  {r['rate_hz_per_head']:8g} | {r['pairs_per_s'] or 0:14.0f} | "
            f"{r['dropped']:7d} | {_ms(r['p50_ms'])} / {_ms(r['p99_ms'])} / "
            f"{_ms(r['max_ms'])} | {r['cpu_ms_per_pair'] or 0:13.2f} | "
            f"{r['cores_busy'] or 0:10.2f} | {'met' if r['meets'] else 'MISSED'}")
    lines.append("  highest rate meeting the target: " + (
        "none of these" if best is None else
        f"{result['highest_meeting_hz_per_head']:g} pairs/s a head ({best:g} pairs/s)"))
    return "\n".join(lines)


def figure(result: dict[str, Any]) -> Any:
    """p50 and p99 latency over the pairs/s offered, the target, the cores busy (a Figure)."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    rows = result["rows"]
    heads = result["heads"]
    x = [r["rate_hz_per_head"] * heads for r in rows]
    fig = Figure(figsize=(6.4, 3.8), layout="constrained")
    ax = fig.add_subplot()
    for key, label, style in (("p99_ms", "p99", "o-"), ("p50_ms", "p50", "s--")):
        pts = [(xi, r[key]) for xi, r in zip(x, rows, strict=True) if r[key] is not None]
        if pts:
            ax.plot(*zip(*pts, strict=True), style, label=f"{label} pair -> setpoints")
    ax.axhline(result["target_p99_ms"], color="tab:red", lw=1,
               label=f"target p99 {result['target_p99_ms']:g} ms")
    missed = [(xi, r["p99_ms"]) for xi, r in zip(x, rows, strict=True)
              if not r["meets"] and r["p99_ms"] is not None]
    if missed:
        ax.plot(*zip(*missed, strict=True), "x", color="tab:red", ms=10, label="missed")
    ax.set_yscale("log")
    ax.yaxis.set_major_formatter(ScalarFormatter())
    ax.yaxis.set_minor_formatter(NullFormatter())
    ax.set_yticks([t for t in (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000)
                   if t <= 2 * max([r["max_ms"] or 0 for r in rows] + [TICKS_FROM_MS])])
    ax.set_xlabel(f"pairs/s offered ({heads} heads)")
    ax.set_ylabel("frame -> setpoints latency, ms")
    handles, labels = ax.get_legend_handles_labels()
    busy = [(xi, r["cores_busy"]) for xi, r in zip(x, rows, strict=True)
            if r["cores_busy"] is not None]
    if busy:
        ax2 = ax.twinx()
        ax2.plot(*zip(*busy, strict=True), "^:", color="tab:gray", label="cores busy")
        ax2.set_ylabel("cores busy (service + workers)", color="tab:gray")
        ax2.set_ylim(0, max(float(result["machine"].get("cores") or 2), *[b for _, b in busy]))
        more = ax2.get_legend_handles_labels()
        handles, labels = handles + more[0], labels + more[1]
    m = result["machine"]
    load = m.get("load_avg")
    load_text = f"{load[0]:.1f}" if isinstance(load, list | tuple) and load else "?"
    ax.set_title(f"moulder service on {m.get('cores')} cores, {result['workers']} workers "
                 f"(load {load_text})", fontsize=9)
    ax.legend(handles, labels, fontsize=8, loc="upper left")
    return fig


def save_figure(result: dict[str, Any], path: str | Path) -> Path:
    """Write :func:`figure` as a PNG at ``path`` (atomically); the path."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from core.fileio import atomic_writer

    fig = figure(result)
    FigureCanvasAgg(fig)
    out = Path(path)
    with atomic_writer(out, binary=True) as fh:
        fig.savefig(fh, format="png", dpi=90)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m planer.benchmarks.moulder_rates``: the sweep, its table or JSON, a figure."""
    parser = argparse.ArgumentParser(
        prog="python -m planer.benchmarks.moulder_rates",
        description="The moulder bench at several pair rates per head: where the "
                    "frame-to-setpoint target holds on this machine.")
    parser.add_argument("--rates", default=",".join(f"{r:g}" for r in DEFAULT_RATES_HZ),
                        help="pairs/s of each head, comma-separated (default %(default)s)")
    parser.add_argument("--quick", action="store_true", help="shorter runs (less precise)")
    parser.add_argument("--figure", type=Path, help="write the latency figure (PNG) here")
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    args = parser.parse_args(argv)
    try:
        rates = parse_rates(args.rates)
    except RatesError as exc:
        parser.exit(2, f"{parser.prog}: error: {exc}\n")
    if args.figure is not None and not args.figure.parent.is_dir():
        parser.exit(2, f"{parser.prog}: error: --figure: folder {args.figure.parent} "
                       "does not exist\n")
    result = sweep(rates, quick=args.quick,
                   progress=lambda line: print(line, file=sys.stderr, flush=True))
    if args.figure is not None:
        result["figure"] = str(save_figure(result, args.figure))
    print(json.dumps(result, indent=2) if args.json else text(result))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
