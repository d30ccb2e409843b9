"""``planer report``: summarise a quality log, draw its figures, optionally export CSV.

``planer report LOG [--machine ID] [--head NAME] [--out DIR] [--csv FILE] [--json]``. LOG is an
SQLite file or a PostgreSQL URL ``postgresql://USER@HOST:PORT/DB`` (a fleet's shared log;
``--machine`` picks one machine's records). The log may be growing (the service appending) while
this reads it: the report shows the records committed when it started. A record journal left on
local disk (records the log could not take yet) is named with its record count; its records are
not in the summary. An unreachable database is one line naming ``host:port/db`` (exit 2).

A moulder's log holds the records of several cutterheads: the report then gives a table of the
heads and every summary, table and figure per head (``<stem>_<head>_<figure>.png``; JSON
``per_head``); ``--head NAME`` reports that head only (a head the log does not hold is one line
naming it, exit 2). A log of one head is reported as before, with a head line.

The report never writes to what it reads: the log is opened read-only (SQLite ``mode=ro``; an
empty or foreign file stays as it is), and ``--csv`` or a figure that is the log or its journal
(the same path after symlinks, or the same inode) is refused before any work. A write that
fails (a full disk) names the file.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any


def configure(parser: argparse.ArgumentParser) -> None:
    """Add this command's arguments."""
    parser.add_argument("log", metavar="LOG",
                        help="quality log written by the service: an SQLite file or "
                             "postgresql://USER@HOST:PORT/DB")
    parser.add_argument("--machine", metavar="ID", default=None,
                        help="only the records of this machine id (a log shared by a fleet)")
    parser.add_argument("--head", metavar="NAME", default=None,
                        help="only the records of this cutterhead (a moulder's head, e.g. "
                             "top; a single-head planer's is main)")
    parser.add_argument("--out", metavar="DIR", default=None,
                        help="folder for the PNG figures (default: the log's folder; the "
                             "current folder for a database)")
    parser.add_argument("--csv", metavar="FILE", default=None,
                        help="also export every record to this CSV file")
    parser.add_argument("--json", action="store_true",
                        help="print the summary as one JSON object instead of text")


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    from controller.quality.journal import default_journal_path
    from controller.quality.log import is_database_url, log_target, open_quality_log
    from controller.quality.report import figure_paths
    from controller.quality.schema import check_head
    from planer.cli import output_file, output_folder
    from planer.outputs import not_an_input, writing

    if "://" in args.log and not is_database_url(args.log):
        scheme = args.log.split("://", 1)[0]
        raise ValueError(f"LOG {args.log}: {scheme}:// is not a quality log; give an SQLite "
                         "file or a postgresql://USER@HOST:PORT/DB URL")
    if args.head is not None:
        check_head("--head", args.head)
    log_path = log_target(args.log)
    if isinstance(log_path, Path) and log_path.is_dir():
        raise ValueError(f"LOG {log_path}: is a folder, expected a quality log file")
    if is_database_url(log_path):
        default_out, stem = Path.cwd(), _database_stem(str(log_path))
    else:
        default_out, stem = Path(log_path).absolute().parent, Path(log_path).stem
    if args.head is not None:  # one head's figures beside the whole log's
        from controller.quality.head_report import head_stem

        stem = head_stem(stem, args.head)
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
        records = log.records(machine_id=args.machine, head=args.head)
        if args.head is not None and not records:
            raise ValueError(_unknown_head(args.head, log, args.machine, shown))
        heads = list(dict.fromkeys(r.head for r in records))
        classes = {h: log.quality_class(h) for h in heads}
        quality_class = (classes[heads[0]] if len(heads) == 1 and heads[0] != "main"
                         else log.quality_class())
        csv_path, n_csv = None, 0
        if args.csv is not None:
            csv_path = Path(args.csv)
            with writing("--csv", csv_path):
                n_csv = log.export_csv(csv_path, machine_id=args.machine, head=args.head)

    journals = {h: default_journal_path(log_path, head=h) for h in heads if h != "main"}
    several = len(heads) > 1
    if several:  # each head's figures: checked against the inputs before any is written
        from controller.quality.head_report import head_figure_paths

        inputs.update({f"head {h}'s record journal": p for h, p in journals.items()})
        for fig in head_figure_paths(out_dir, stem=stem, heads=heads).values():
            not_an_input(out_opt, fig, inputs)
    summary, written = _summary_and_figures(records, quality_class, classes, out_dir, stem,
                                            out_opt, several=several)
    journal_info = _journal_info(journal)
    head_journals = {h: info for h, p in journals.items()
                     if (info := _journal_info(p)) is not None}

    if args.json:
        summary = {"log": shown, "machine": args.machine, **summary,
                   "head": args.head if args.head is not None else (
                       heads[0] if len(heads) == 1 else None),
                   "figures": written, "csv": None if csv_path is None else str(csv_path),
                   "journal": journal_info, "head_journals": head_journals}
        print(json.dumps(summary, allow_nan=False))
        return 0
    title = (f"Quality log {shown}" + (f", machine {args.machine}" if args.machine else "")
             + (f", head {args.head}" if args.head else ""))
    if several:
        from controller.quality.head_report import format_heads

        print(format_heads(summary, title=title))
    else:
        from controller.quality.report import format_summary

        print(format_summary(summary, title=title))
    _print_files(written, csv_path, n_csv)
    for path, info in ([(journal, journal_info)] if journal_info is not None else []) + [
            (journals[h], info) for h, info in head_journals.items()]:
        n = info["records"]
        print(f"\nNote: the record journal {path} holds "
              f"{'an unknown number of' if n is None else n} record(s) not yet in this "
              "log (not in this report); the service writes them in at its next start.")
    return 0


def _summary_and_figures(records: list, quality_class: Any, classes: dict, out_dir: Path,
                         stem: str, out_opt: str, *, several: bool) -> tuple[dict, dict]:
    """The summary (with ``per_head`` of several heads) and the figures written, by name."""
    from controller.quality.report import build_figures, save_figures, summarise
    from planer.outputs import writing

    summary = summarise(records, quality_class=quality_class)
    written: dict[str, str] = {}
    if not several:
        summary["per_head"] = None
        with writing(out_opt, out_dir):
            written = save_figures(build_figures(records, quality_class=quality_class),
                                   out_dir, stem=stem)  # each PNG written atomically
        return summary, written
    from controller.quality.head_report import (
        build_head_figures,
        head_summaries,
        save_head_figures,
    )

    per_head = head_summaries(records, classes)
    with writing(out_opt, out_dir):
        saved = save_head_figures(build_head_figures(records, classes), out_dir, stem=stem)
    for head, mine in saved.items():
        per_head[head]["figures"] = mine
        written.update({f"{head}_{name}": path for name, path in mine.items()})
    summary["per_head"] = per_head
    return summary, written


def _unknown_head(head: str, log: Any, machine: str | None, shown: str) -> str:
    """The one-line error of ``--head`` naming a head the log holds no records of."""
    held = list(dict.fromkeys(r.head for r in log.records(machine_id=machine)))
    where = f"{shown}" + (f" (machine {machine})" if machine else "")
    return (f"--head {head}: no records of head {head!r} in {where}; "
            + (f"its heads: {', '.join(held)}" if held else "it holds no records"))


def _journal_info(path: Path) -> dict[str, Any] | None:
    """What a record journal holds (``None``: none there)."""
    from controller.quality.journal import read_journal

    try:
        held, bad = read_journal(path)
    except FileNotFoundError:
        return None
    except OSError as exc:
        return {"path": str(path), "records": None, "error": exc.strerror or str(exc)}
    return {"path": str(path), "records": len(held), "unreadable_lines": bad}


def _print_files(written: dict[str, str], csv_path: Path | None, n_csv: int) -> None:
    if written:
        print("\nFigures:")
        for path in written.values():
            print(f"  {path}")
    else:
        print("\nNo figures: the log holds no measurements.")
    if csv_path is not None:
        print(f"CSV: {csv_path} ({n_csv} rows)")


def _database_stem(url: str) -> str:
    """File-name stem of a database log's figures: the database name (``quality`` without)."""
    from urllib.parse import urlsplit

    name = urlsplit(url).path.strip("/")
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name) or "quality"
