"""``planer report``: summarise a quality log, draw its figures, optionally export CSV.

``planer report LOG [--machine ID] [--out DIR] [--csv FILE] [--json]``. LOG is an SQLite file
or a PostgreSQL URL ``postgresql://USER@HOST:PORT/DB`` (a fleet's shared log; ``--machine``
picks one machine's records). The log may be growing (the service appending) while this reads
it: the report shows the records committed when it started. A record journal left on local
disk (records the log could not take yet) is named with its record count; its records are not
in the summary. An unreachable database is one line naming ``host:port/db`` (exit 2).

The report never writes to what it reads: the log is opened read-only (SQLite ``mode=ro``; an
empty or foreign file stays as it is), and ``--csv`` or a figure that is the log or its journal
(the same path after symlinks, or the same inode) is refused before any work. A write that
fails (a full disk) names the file.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def configure(parser: argparse.ArgumentParser) -> None:
    """Add this command's arguments."""
    parser.add_argument("log", metavar="LOG",
                        help="quality log written by the service: an SQLite file or "
                             "postgresql://USER@HOST:PORT/DB")
    parser.add_argument("--machine", metavar="ID", default=None,
                        help="only the records of this machine id (a log shared by a fleet)")
    parser.add_argument("--out", metavar="DIR", default=None,
                        help="folder for the PNG figures (default: the log's folder; the "
                             "current folder for a database)")
    parser.add_argument("--csv", metavar="FILE", default=None,
                        help="also export every record to this CSV file")
    parser.add_argument("--json", action="store_true",
                        help="print the summary as one JSON object instead of text")


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    from controller.quality.journal import default_journal_path, read_journal
    from controller.quality.log import is_database_url, log_target, open_quality_log
    from controller.quality.report import (
        build_figures,
        figure_paths,
        format_summary,
        save_figures,
        summarise,
    )
    from planer.cli import output_file, output_folder
    from planer.outputs import not_an_input, writing

    if "://" in args.log and not is_database_url(args.log):
        scheme = args.log.split("://", 1)[0]
        raise ValueError(f"LOG {args.log}: {scheme}:// is not a quality log; give an SQLite "
                         "file or a postgresql://USER@HOST:PORT/DB URL")
    log_path = log_target(args.log)
    if isinstance(log_path, Path) and log_path.is_dir():
        raise ValueError(f"LOG {log_path}: is a folder, expected a quality log file")
    if is_database_url(log_path):
        default_out, stem = Path.cwd(), _database_stem(str(log_path))
    else:
        default_out, stem = Path(log_path).absolute().parent, Path(log_path).stem
    out_dir = Path(args.out) if args.out is not None else default_out
    journal = default_journal_path(log_path)
    inputs = {"LOG": None if is_database_url(log_path) else log_path,
              "the log's record journal": journal}
    if args.csv is not None:
        not_an_input("--csv", args.csv, inputs)
    out_opt = "--out" if args.out is not None else "figure folder (next to LOG; see --out)"
    for fig in figure_paths(out_dir, stem=stem).values():
        not_an_input(out_opt, fig, inputs)
    output_folder(out_opt, out_dir)
    if args.csv is not None:
        output_file("--csv", args.csv)

    with open_quality_log(log_path, create=False) as log:
        shown = str(log.path)
        records = log.records(machine_id=args.machine)
        quality_class = log.quality_class()
        csv_path, n_csv = None, 0
        if args.csv is not None:
            csv_path = Path(args.csv)
            with writing("--csv", csv_path):
                n_csv = log.export_csv(csv_path, machine_id=args.machine)

    try:
        held, bad = read_journal(journal)
        journal_info = {"path": str(journal), "records": len(held), "unreadable_lines": bad}
    except FileNotFoundError:
        journal_info = None
    except OSError as exc:
        journal_info = {"path": str(journal), "records": None, "error": exc.strerror or str(exc)}

    summary = summarise(records, quality_class=quality_class)
    with writing(out_opt, out_dir):
        written = save_figures(build_figures(records, quality_class=quality_class), out_dir,
                               stem=stem)  # each PNG written atomically

    if args.json:
        summary = {"log": shown, "machine": args.machine, **summary, "figures": written,
                   "csv": None if csv_path is None else str(csv_path), "journal": journal_info}
        print(json.dumps(summary, allow_nan=False))
    else:
        title = f"Quality log {shown}" + (f", machine {args.machine}" if args.machine else "")
        print(format_summary(summary, title=title))
        if written:
            print("\nFigures:")
            for path in written.values():
                print(f"  {path}")
        else:
            print("\nNo figures: the log holds no measurements.")
        if csv_path is not None:
            print(f"CSV: {csv_path} ({n_csv} rows)")
        if journal_info is not None:
            n = journal_info["records"]
            print(f"\nNote: the record journal {journal} holds "
                  f"{'an unknown number of' if n is None else n} record(s) not yet in this "
                  "log (not in this report); the service writes them in at its next start.")
    return 0


def _database_stem(url: str) -> str:
    """File-name stem of a database log's figures: the database name (``quality`` without)."""
    from urllib.parse import urlsplit

    name = urlsplit(url).path.strip("/")
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name) or "quality"
