"""``planer sweep``: a grid of HIL scenarios (in-process, simulated time) on Dask distributed.

``planer sweep FILE [--workers N] [--scheduler tcp://HOST:PORT] --out DIR``. FILE is a sweep
file (``config/sweeps/robustness.toml``; layout in :mod:`planer.sweep.design`). The runs go to
a local Dask cluster of N worker processes on 127.0.0.1 (``--workers 0``: one after the other in
this process), or to a running cluster by its scheduler's address. ``DIR/results.csv`` gets one
row per run as it finishes (Ctrl-C keeps the finished rows), a progress bar goes to stderr, and
``DIR/sweep_<outcome>.png`` show the outcome over the grid.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def configure(parser: argparse.ArgumentParser) -> None:
    """Add this command's arguments."""
    parser.add_argument("file", metavar="FILE",
                        help="sweep file: base scenario, seeds, [grid] (e.g. "
                             "config/sweeps/robustness.toml)")
    parser.add_argument("--workers", metavar="N", type=int, default=2,
                        help="worker processes of the local Dask cluster (default 2; 0: run "
                             "in this process without Dask)")
    parser.add_argument("--scheduler", metavar="tcp://HOST:PORT", default=None,
                        help="run on this existing Dask scheduler instead of a local cluster")
    parser.add_argument("--out", metavar="DIR", required=True,
                        help="output folder: results.csv and the PNG plots")
    parser.add_argument("--no-plots", action="store_true", help="write results.csv only")


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    from planer.cli import output_folder
    from planer.sweep.design import canonical, load_sweep
    from planer.sweep.driver import RESULTS_NAME, run_sweep
    from planer.sweep.plots import save_plots
    from planer.sweep.point import prepare

    if args.workers < 0:
        raise ValueError(f"--workers must be >= 0, got {args.workers}")
    if args.scheduler is not None and not args.scheduler.startswith("tcp://"):
        raise ValueError(f"--scheduler must be tcp://HOST:PORT, got {args.scheduler!r}")
    sweep = load_sweep(args.file)
    out = Path(output_folder("--out", args.out))
    jobs, bases = prepare(sweep)
    where = (f"scheduler {args.scheduler}" if args.scheduler else
             f"a local cluster of {args.workers} worker(s)" if args.workers else "this process")
    print(f"planer sweep: {len(jobs)} runs of {sweep.base} ({len(sweep.seeds)} seed(s)) on "
          f"{where}", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    rows = run_sweep(jobs, out, keys=sweep.keys, bases=bases, workers=args.workers,
                     scheduler=args.scheduler)
    wall = time.perf_counter() - t0
    failed = sum(bool(r["error"]) for r in rows)
    if not args.no_plots:
        base_text = {k: "" if v is None else canonical(v) for k, v in bases.items()}
        groups = [group for grid in sweep.grids for group, _ in grid]
        save_plots(rows, sweep.keys, base_text, out, groups=groups)
    print(f"{out / RESULTS_NAME}: {len(rows)} runs, {failed} failed, {wall:.1f} s wall "
          f"({wall / max(len(rows), 1):.1f} s per run)")
    return 0
