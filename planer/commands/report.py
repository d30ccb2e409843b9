"""``planer report``: summarise a quality log, draw its figures, optionally export CSV.

``planer report LOG [--out DIR] [--csv FILE] [--json]``. The log may be growing (the service
appending) while this reads it: the report shows the records committed when it started.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

HELP = "summarise a quality log: text or JSON summary, PNG figures, CSV export"


def configure(parser: argparse.ArgumentParser) -> None:
    """Add this command's arguments."""
    parser.add_argument("log", metavar="LOG",
                        help="quality log file (SQLite) written by the service")
    parser.add_argument("--out", metavar="DIR", default=None,
                        help="folder for the PNG figures (default: the log's folder)")
    parser.add_argument("--csv", metavar="FILE", default=None,
                        help="also export every record to this CSV file")
    parser.add_argument("--json", action="store_true",
                        help="print the summary as one JSON object instead of text")


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    from controller.quality_log import QualityLog
    from controller.report import build_figures, format_summary, save_figures, summarise
    from planer.cli import output_file, output_folder

    log_path = Path(args.log)
    if log_path.is_dir():
        raise ValueError(f"LOG {log_path}: is a folder, expected a quality log file")
    out_dir = Path(args.out) if args.out is not None else log_path.absolute().parent
    output_folder("--out" if args.out is not None else "figure folder (next to LOG; see --out)",
                  out_dir)
    if args.csv is not None:
        output_file("--csv", args.csv)

    with QualityLog(log_path, create=False) as log:
        records = log.records()
        quality_class = log.quality_class()
        csv_path, n_csv = None, 0
        if args.csv is not None:
            csv_path = Path(args.csv)
            n_csv = log.export_csv(csv_path)

    summary = summarise(records, quality_class=quality_class)
    written = save_figures(build_figures(records, quality_class=quality_class), out_dir,
                           stem=log_path.stem)  # each PNG written atomically

    if args.json:
        summary = {"log": str(log_path), **summary, "figures": written,
                   "csv": None if csv_path is None else str(csv_path)}
        print(json.dumps(summary, allow_nan=False))
    else:
        print(format_summary(summary, title=f"Quality log {log_path}"))
        if written:
            print("\nFigures:")
            for path in written.values():
                print(f"  {path}")
        else:
            print("\nNo figures: the log holds no measurements.")
        if csv_path is not None:
            print(f"CSV: {csv_path} ({n_csv} rows)")
    return 0
