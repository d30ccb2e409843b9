"""Stress: ``planer hil`` run N times, optionally against CPU-bound competitors, tabulated.

The README's main job must pass on a 2-core machine with six CPU-bound processes
competing with it. :func:`run_stress` runs ``planer hil --json --scenario NAME`` (the
cross-process real-time run, as the README runs it) ``runs`` times per scenario, each in a
fresh process with its own quality log, while ``hogs`` busy loops (``sh -c 'while :; do :;
done'``, started and ended here by their process ids) compete for the CPU; every run becomes
one :class:`StressRun` row: passed, final true CV, faults handled, safe-state entries, the
simulated clock's achieved factor, wall time and, for a failed run, the checks that failed
and the last lines of its stderr.

Run it with::

    python -m planer.hil.stress --runs 5 --hogs 6                  # default and faults
    python -m planer.hil.stress --runs 3 --scenario faults --json  # one JSON object

It is a measurement, not a test: it takes minutes and its result depends on the host (see
``docs/reliability.md`` for the numbers measured here).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

__all__ = ["StressRun", "cpu_hogs", "format_table", "main", "parse_run", "run_once",
           "run_stress"]

HOG_SCRIPT = "while :; do :; done"
"""The competitor: one shell busy loop (one core's worth of demand)."""
HOG_LIFETIME_S = 3600
"""A hog ends by itself after this long even if this process is killed (``timeout``)."""
RUN_TIMEOUT_S = 600.0
"""Wall seconds one ``planer hil`` run may take before it is stopped and counted as failed."""
STDERR_TAIL = 12
"""Lines of a failed run's stderr kept in its row."""


@dataclass
class StressRun:
    """One ``planer hil`` run of a stress series.

    Attributes
    ----------
    run : int
        Number in the series (1-based, per scenario).
    scenario : str
        Scenario name.
    passed : bool
        The summary's ``passed`` (and exit code 0).
    exit_code : int
        ``planer hil``'s exit code.
    final_cv : float or None
        Final true uniformity (CV of the mark widths).
    final_pitch_mm : float or None
        Final true pitch, mm.
    faults_handled : int
        Injected faults judged handled.
    faults : int
        Injected faults.
    safe_entries : int
        Safe-state entries of the run.
    unexplained : int
        Safe-state entries no injected fault explains.
    time_factor : float or None
        Simulated seconds per wall second the simulator achieved (``sim_time_factor``).
    wall_s : float
        Wall time of the whole command (namespace, simulator start, run, summary), s.
    failed_checks : list of str
        The ``done`` checks that failed.
    stderr_tail : list of str
        Last lines of stderr of a failed run (empty when it passed).
    """

    run: int
    scenario: str
    passed: bool
    exit_code: int
    final_cv: float | None = None
    final_pitch_mm: float | None = None
    faults_handled: int = 0
    faults: int = 0
    safe_entries: int = 0
    unexplained: int = 0
    time_factor: float | None = None
    wall_s: float = 0.0
    failed_checks: list[str] = field(default_factory=list)
    stderr_tail: list[str] = field(default_factory=list)


def parse_run(stdout: str, stderr: str, *, exit_code: int, run: int, scenario: str,
              wall_s: float) -> StressRun:
    """One row from a ``planer hil --json`` run's output.

    A run whose stdout is not one JSON object (it crashed, it was stopped) is a failed row whose
    ``failed_checks`` says so.
    """
    tail = [line for line in stderr.splitlines() if line.strip()][-STDERR_TAIL:]
    try:
        summary = json.loads(stdout.strip().splitlines()[-1]) if stdout.strip() else None
    except (json.JSONDecodeError, IndexError):
        summary = None
    if not isinstance(summary, dict):
        return StressRun(run=run, scenario=scenario, passed=False, exit_code=exit_code,
                         wall_s=wall_s, failed_checks=["no summary (exit code "
                                                       f"{exit_code})"], stderr_tail=tail)
    final = summary.get("final") or {}
    faults = summary.get("faults") or []
    safe = summary.get("safe_entries") or {}
    done = summary.get("done") or {}
    passed = bool(summary.get("passed")) and exit_code == 0
    return StressRun(
        run=run,
        scenario=scenario,
        passed=passed,
        exit_code=exit_code,
        final_cv=final.get("uniformity_cv"),
        final_pitch_mm=final.get("pitch_mm"),
        faults_handled=sum(1 for f in faults if f.get("handled")),
        faults=len(faults),
        safe_entries=int(safe.get("count") or 0),
        unexplained=int(safe.get("unexplained") or 0),
        time_factor=summary.get("sim_time_factor"),
        wall_s=wall_s,
        failed_checks=[k for k, ok in done.items() if not ok],
        stderr_tail=[] if passed else tail,
    )


def run_once(scenario: str, *, run: int = 1, planer: Sequence[str] | None = None,
             extra_args: Sequence[str] = (), timeout_s: float = RUN_TIMEOUT_S,
             folder: Path | None = None) -> StressRun:
    """Run ``planer hil --json --scenario <scenario>`` once in a fresh process; its row.

    Parameters
    ----------
    scenario : str
        Scenario name (``config/hil.toml``) or ``FILE.toml[:NAME]``.
    run : int
        Number of the run in its series (for the row).
    planer : sequence of str, optional
        The command that is ``planer`` (default ``python -m planer.cli`` of this interpreter).
    extra_args : sequence of str
        More arguments for ``planer hil``.
    timeout_s : float
        Wall time after which the run is stopped (and fails).
    folder : Path, optional
        Where the quality log, stdout (``.json``) and stderr (``.err``) are kept (default: a
        temporary folder, removed).
    """
    cmd = list(planer) if planer is not None else [sys.executable, "-m", "planer.cli"]
    with contextlib.ExitStack() as stack:
        where = folder if folder is not None else Path(
            stack.enter_context(tempfile.TemporaryDirectory(prefix="planer-stress-")))
        log = where / f"{scenario.replace('/', '_')}-{run}.sqlite"
        argv = [*cmd, "hil", "--json", "--scenario", scenario, "--log", str(log), *extra_args]
        t0 = time.perf_counter()
        try:
            res = subprocess.run(argv, capture_output=True, text=True, timeout=timeout_s,
                                 check=False)
            out, err, code = res.stdout, res.stderr, res.returncode
        except subprocess.TimeoutExpired as exc:
            out = exc.stdout.decode() if isinstance(exc.stdout, bytes) else (exc.stdout or "")
            err = exc.stderr.decode() if isinstance(exc.stderr, bytes) else (exc.stderr or "")
            err += f"\nstress: stopped after {timeout_s:g} s"
            code = -int(signal.SIGKILL)
        wall = time.perf_counter() - t0
        if folder is not None:  # kept for a look afterwards
            (where / f"{log.stem}.json").write_text(out)
            (where / f"{log.stem}.err").write_text(err)
    return parse_run(out, err, exit_code=code, run=run, scenario=scenario, wall_s=wall)


@contextlib.contextmanager
def cpu_hogs(count: int) -> Iterator[list[int]]:
    """``count`` CPU-bound busy loops for the duration of the ``with`` block; their pids.

    Each is ``timeout <HOG_LIFETIME_S> sh -c 'while :; do :; done'`` in its own process group;
    on leaving the block each group is ended by its id (nothing else is touched).
    """
    if count < 0:
        raise ValueError(f"count must be >= 0, got {count!r}")
    procs: list[subprocess.Popen] = []
    try:
        for _ in range(count):
            procs.append(subprocess.Popen(
                ["timeout", str(HOG_LIFETIME_S), "sh", "-c", HOG_SCRIPT],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                start_new_session=True,
            ))
        yield [p.pid for p in procs]
    finally:
        for p in procs:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait()


def run_stress(scenarios: Sequence[str], *, runs: int, hogs: int = 0,
               extra_args: Sequence[str] = (), planer: Sequence[str] | None = None,
               folder: Path | None = None,
               on_row: Callable[[StressRun], None] | None = None) -> list[StressRun]:
    """Run every scenario ``runs`` times (interleaved) with ``hogs`` busy loops competing.

    Parameters
    ----------
    scenarios : sequence of str
        Scenario names.
    runs : int
        Runs per scenario (>= 1).
    hogs : int
        CPU-bound competitors running during the whole series (>= 0).
    extra_args, planer, folder
        See :func:`run_once`.
    on_row : callable, optional
        Receives each row as soon as its run ended.
    """
    if int(runs) < 1:
        raise ValueError(f"runs must be >= 1, got {runs!r}")
    if not scenarios:
        raise ValueError("scenarios must not be empty")
    rows: list[StressRun] = []
    with cpu_hogs(int(hogs)):
        for i in range(1, int(runs) + 1):
            for name in scenarios:
                row = run_once(name, run=i, planer=planer, extra_args=extra_args,
                               folder=folder)
                rows.append(row)
                if on_row is not None:
                    on_row(row)
    return rows


def _fmt(v: float | None, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def format_row(r: StressRun) -> str:
    """One table line (see :func:`format_table`)."""
    return (f"| {r.scenario:<8} | {r.run:>3} | {'yes' if r.passed else 'NO':<6} | "
            f"{_fmt(r.final_cv, '.3f'):>8} | {r.faults_handled}/{r.faults:<4} | "
            f"{r.safe_entries:>2} ({r.unexplained} unexpl.) | {_fmt(r.time_factor, '.2f'):>6} | "
            f"{r.wall_s:>6.1f} |")


TABLE_HEAD = ("| scenario | run | passed | final CV | faults | safe entries | factor | wall s |"
              "\n|---|---|---|---|---|---|---|---|")


def format_table(rows: Sequence[StressRun]) -> str:
    """A Markdown table of the rows, then one tally line per scenario and each failure."""
    lines = [TABLE_HEAD, *map(format_row, rows)]
    for name in dict.fromkeys(r.scenario for r in rows):
        mine = [r for r in rows if r.scenario == name]
        lines.append(f"{name}: {sum(r.passed for r in mine)}/{len(mine)} passed")
    for r in rows:
        if not r.passed:
            lines.append(f"{r.scenario} run {r.run} failed: {', '.join(r.failed_checks)}")
            lines.extend(f"    {line}" for line in r.stderr_tail)
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m planer.hil.stress``: exit code 0 when every run passed."""
    p = argparse.ArgumentParser(prog="python -m planer.hil.stress", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", type=int, default=5, help="runs per scenario (default 5)")
    p.add_argument("--hogs", type=int, default=6,
                   help="CPU-bound busy loops competing during the series (default 6)")
    p.add_argument("--scenario", action="append", default=None,
                   help="scenario (repeatable; default: default and faults)")
    p.add_argument("--json", action="store_true", help="print the rows as one JSON object")
    p.add_argument("--keep", type=Path, default=None, metavar="DIR",
                   help="keep each run's quality log, stdout and stderr in DIR")
    p.add_argument("hil_args", nargs="*", help="more arguments for planer hil (after --)")
    args = p.parse_args(argv)
    if args.runs < 1 or args.hogs < 0:
        p.error("--runs must be >= 1 and --hogs >= 0")
    scenarios = args.scenario or ["default", "faults"]

    def progress(r: StressRun) -> None:
        print(format_row(r), file=sys.stderr, flush=True)

    info = {"nproc": os.cpu_count(), "hogs": args.hogs, "runs": args.runs}
    print(f"stress: {args.runs} run(s) of {', '.join(scenarios)} with {args.hogs} CPU hog(s) "
          f"on {info['nproc']} CPU(s)", file=sys.stderr, flush=True)
    if args.keep is not None:
        args.keep.mkdir(parents=True, exist_ok=True)
    rows = run_stress(scenarios, runs=args.runs, hogs=args.hogs, extra_args=args.hil_args,
                      folder=args.keep, on_row=progress)
    if args.json:
        print(json.dumps({**info, "rows": [asdict(r) for r in rows]}))
    else:
        print(format_table(rows))
    return 0 if all(r.passed for r in rows) else 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
