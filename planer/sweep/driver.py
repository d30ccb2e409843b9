"""Running a sweep: jobs on Dask distributed (or in this process), rows into ``results.csv``.

``results.csv`` is written as the runs finish (one flushed line each, so Ctrl-C keeps every
finished row) and sorted by run number once the sweep is complete. Dask is imported only here.
"""

from __future__ import annotations

import csv
import io
import logging
import sys
import time
import uuid
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any, TextIO

from core.fileio import atomic_write_text
from planer.sweep.point import OUTCOME_COLUMNS, Job, error_row, input_cells, run_job

RESULTS_NAME = "results.csv"
CONNECT_TIMEOUT_S = 30.0
"""How long to wait for a scheduler given by ``--scheduler``, and for its first worker."""


def columns(keys: Sequence[str]) -> list[str]:
    """The CSV header: ``run``, ``seed``, the varied keys, then ``OUTCOME_COLUMNS``.

    An outcome column that is also a varied key (``target_pitch_mm``) is there once, among
    the keys (the run's value: the same number).
    """
    return ["run", "seed", *keys, *(c for c in OUTCOME_COLUMNS if c not in keys)]


def _line(row: Mapping[str, str], header: Sequence[str]) -> str:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow([row.get(c, "") for c in header])
    return buf.getvalue()


class ResultsWriter:
    """``results.csv`` written one finished run at a time.

    Parameters
    ----------
    path : Path
        The file (replaced).
    header : sequence of str
        Its columns.
    """

    def __init__(self, path: Path, header: Sequence[str]) -> None:
        self.path = Path(path)
        self.header = list(header)
        self.rows: list[dict[str, str]] = []
        self._fh: TextIO | None = self.path.open("w", encoding="utf-8", newline="")
        self._fh.write(_line({c: c for c in self.header}, self.header))
        self._fh.flush()

    def add(self, row: Mapping[str, str]) -> None:
        """Append one row now (flushed: an interrupted sweep keeps it)."""
        assert self._fh is not None, "closed"
        self.rows.append(dict(row))
        self._fh.write(_line(row, self.header))
        self._fh.flush()

    def close(self, *, sort: bool) -> None:
        """Close; with ``sort`` rewrite the file (atomically) ordered by run number."""
        if self._fh is not None:
            self._fh.close()
            self._fh = None
        if sort:
            rows = sorted(self.rows, key=lambda r: int(r["run"]))
            text = "".join(_line(r, self.header) for r in [{c: c for c in self.header}, *rows])
            atomic_write_text(self.path, text)


def read_results(path: str | Path) -> list[dict[str, str]]:
    """The rows of a ``results.csv`` (as strings)."""
    with Path(path).open(encoding="utf-8", newline="") as fh:
        return list(csv.DictReader(fh))


class ProgressBar:
    """A one-line progress bar (``[####....] 12/80 runs, 1 failed, 2:10 left``).

    On a terminal the line is redrawn in place; otherwise one line per finished run.
    """

    def __init__(self, total: int, *, stream: TextIO | None = None, width: int = 30,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.total = int(total)
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.clock = clock
        self.t0 = clock()
        self.done = self.failed = 0
        isatty = getattr(self.stream, "isatty", None)
        self.tty = bool(isatty and isatty())

    def text(self) -> str:
        """The bar's current text."""
        frac = self.done / self.total if self.total else 1.0
        filled = int(round(frac * self.width))
        elapsed = self.clock() - self.t0
        left = elapsed / self.done * (self.total - self.done) if self.done else None
        eta = "" if left is None else f", {int(left) // 60}:{int(left) % 60:02d} left"
        return (f"sweep [{'#' * filled}{'.' * (self.width - filled)}] {self.done}/{self.total} "
                f"runs, {self.failed} failed, {int(elapsed) // 60}:{int(elapsed) % 60:02d}{eta}")

    def update(self, *, failed: bool) -> None:
        """One more run finished."""
        self.done += 1
        self.failed += bool(failed)
        end = "\n" if not self.tty or self.done == self.total else ""
        self.stream.write(("\r" if self.tty else "") + self.text() + end)
        self.stream.flush()


CANCEL_NOISE = (
    ("distributed.worker.state_machine", "ended with CancelledError"),
    ("distributed.nanny", "Worker process still alive after"),
    ("distributed.worker", "Failed to communicate with scheduler during heartbeat"),
    ("distributed.worker", "Connection to scheduler broken"),
)
"""Dask's own warnings when a sweep is stopped (Ctrl-C): the runs cancelled on the workers, the
workers still busy with a run ended by their nanny, a worker's heartbeat that found the local
scheduler gone. Stopping is asked for: nothing to warn. (Attached to a local cluster's workers
only: its scheduler is this process's, so it is gone only when the sweep stops.)"""


class _DropCancelNoise(logging.Filter):
    """Drops the :data:`CANCEL_NOISE` records of the logger it is attached to."""

    def __init__(self, logger: str) -> None:
        super().__init__()
        self.texts = tuple(text for name, text in CANCEL_NOISE if name == logger)

    def filter(self, record: logging.LogRecord) -> bool:
        msg = record.getMessage()
        return not any(text in msg for text in self.texts)


def quiet_cancel_noise() -> None:
    """Attach the :data:`CANCEL_NOISE` filters in this process (idempotent)."""
    for name, _ in CANCEL_NOISE:
        logger = logging.getLogger(name)
        if not any(isinstance(f, _DropCancelNoise) for f in logger.filters):
            logger.addFilter(_DropCancelNoise(name))


def _quiet_workers() -> Any:
    """A worker plugin for the local cluster's worker processes: Ctrl-C is the sweep's.

    Ctrl-C in a terminal reaches every process of the group; a worker process interrupted
    mid-run tears its event loop down with tracebacks. The plugin makes each worker process
    ignore SIGINT (the sweep stops them: its runs cancelled, the cluster closed) and attaches
    :func:`quiet_cancel_noise`.
    """
    from distributed.diagnostics.plugin import WorkerPlugin

    class QuietWorkers(WorkerPlugin):
        name = "planer-sweep-quiet-cancel"

        def setup(self, worker: Any) -> None:
            import signal
            import threading

            from planer.sweep.driver import quiet_cancel_noise

            if threading.current_thread() is threading.main_thread():
                signal.signal(signal.SIGINT, signal.SIG_IGN)
            quiet_cancel_noise()

    return QuietWorkers()


@contextmanager
def dask_client(*, workers: int, scheduler: str | None) -> Iterator[Any]:
    """A Dask client: on ``scheduler`` (``tcp://HOST:PORT``) or on a new local cluster.

    The local cluster binds 127.0.0.1 only (its HTTP servers too), has ``workers`` worker
    processes of one thread each and no dashboard; it is closed on the way out.
    """
    from distributed import Client, LocalCluster

    if scheduler:
        if not scheduler.startswith("tcp://"):
            raise ValueError(f"--scheduler must be tcp://HOST:PORT, got {scheduler!r}")
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except OSError as exc:
            raise OSError(f"--scheduler {scheduler}: cannot connect: {exc}") from None
        try:
            try:
                client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
            except TimeoutError:
                raise TimeoutError(f"--scheduler {scheduler}: no worker joined within "
                                   f"{CONNECT_TIMEOUT_S:g} s") from None
            yield client
        finally:
            client.close()
        return
    loop = _loop_without_ctrl_c()
    cluster = None
    try:
        with _ctrl_c_held():  # a Ctrl-C now stops the sweep once the cluster can be closed
            # no dashboard; the scheduler's and workers' HTTP servers (health, metrics) still
            # start, so give them a free port on the loopback interface
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   host="127.0.0.1", dashboard_address="127.0.0.1:0",
                                   worker_dashboard_address="127.0.0.1:0",
                                   scheduler_kwargs={"dashboard": False}, loop=loop.loop)
        quiet_cancel_noise()  # the nannies run in this process
        client = Client(cluster)
        client.register_plugin(_quiet_workers())  # our own workers only, not a shared cluster's
        try:
            yield client
        finally:
            client.close()
    finally:
        if cluster is not None:
            cluster.close()
        loop.stop()


def _loop_without_ctrl_c() -> Any:
    """A running Dask event loop (``LoopRunner``) on a thread that never takes SIGINT.

    Its thread starts with SIGINT blocked; a thread inherits its creator's signal mask and a
    process the mask of the thread that forked it, so the local cluster's worker processes
    (started from this loop's threads) are born deaf to the terminal's Ctrl-C too: not only
    once :func:`_quiet_workers` ran in them, also while they import (a Ctrl-C in a sweep's
    first seconds otherwise left a worker's ``KeyboardInterrupt`` traceback). Ctrl-C goes to
    this process's main thread, which stops the sweep.
    """
    import signal
    from multiprocessing import resource_tracker

    from distributed.utils import LoopRunner

    # started now, from this thread: multiprocessing starts its resource tracker from the
    # thread of the first spawn and unblocks SIGINT in that thread afterwards (bpo-33613)
    resource_tracker.ensure_running()
    runner = LoopRunner()
    held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})  # pending, not lost
    try:
        runner.start()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)
    return runner


@contextmanager
def _ctrl_c_held() -> Iterator[None]:
    """Hold a Ctrl-C until the block ends, then raise ``KeyboardInterrupt``; a second one at once.

    Dask's ``LocalCluster`` interrupted while it starts is left half-started (its exit handler
    then fails with ``AssertionError: Status.init``); held, the first Ctrl-C ends the sweep as
    soon as the cluster is up and can be closed. Outside the main thread, or where SIGINT is
    not Python's default handler (ignored by the caller, or the caller's own), nothing is held.
    """
    import signal
    import threading

    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
        yield
        return
    presses: list[int] = []

    def hold(signum: int, frame: object) -> None:
        presses.append(signum)
        if len(presses) > 1:  # asked twice: do not wait any longer
            raise KeyboardInterrupt

    signal.signal(signal.SIGINT, hold)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if presses:
        raise KeyboardInterrupt


def _dask_results(jobs: Sequence[Job], client: Any) -> Iterator[tuple[int, dict[str, str]]]:
    """Yield ``(index, outcome)`` as runs finish; a run whose task failed is an error row."""
    from distributed import as_completed

    tag = uuid.uuid4().hex[:8]  # task keys unique on a shared scheduler
    futures = {
        client.submit(run_job, job, key=f"planer-sweep-{tag}-{job.point.index}", pure=False):
            job.point.index
        for job in jobs
    }
    try:
        for fut in as_completed(futures):
            if fut.status == "finished":
                index, row, _ = fut.result()
                yield index, row
            else:  # the worker died or the task raised what run_job does not catch
                exc = fut.exception()
                yield futures[fut], error_row(f"{type(exc).__name__}: {exc}")
    finally:
        client.cancel(list(futures))


def _local_results(jobs: Sequence[Job]) -> Iterator[tuple[int, dict[str, str]]]:
    for job in jobs:
        index, row, _ = run_job(job)
        yield index, row


def run_sweep(
    jobs: Sequence[Job],
    out_dir: str | Path,
    *,
    keys: Sequence[str],
    bases: Mapping[str, Any],
    workers: int = 2,
    scheduler: str | None = None,
    progress: TextIO | None = None,
    results: Callable[[Sequence[Job]], Iterable[tuple[int, dict[str, str]]]] | None = None,
) -> list[dict[str, str]]:
    """Run every job and write ``out_dir/results.csv``; return its rows, ordered by run.

    Parameters
    ----------
    jobs : sequence of Job
        From :func:`planer.sweep.point.prepare`.
    out_dir : str or Path
        Output folder (created).
    keys : sequence of str
        The varied keys (the input columns).
    bases : mapping
        Base value of each key (cells a run's grid leaves out).
    workers : int
        Local cluster size; 0 runs the jobs one after the other in this process (no Dask).
    scheduler : str, optional
        ``tcp://HOST:PORT`` of a running Dask scheduler (``workers`` is then ignored).
    progress : text stream, optional
        Where the progress bar goes (default stderr).
    results : callable, optional
        ``results(jobs)`` yielding ``(index, outcome cells)`` as runs finish (tests; default
        Dask or, with ``workers=0``, this process).

    Returns
    -------
    list of dict
        The rows of ``results.csv``. Interrupted (Ctrl-C), the file keeps the finished rows
        in the order they finished and ``KeyboardInterrupt`` propagates.
    """
    if workers < 0:
        raise ValueError(f"workers must be >= 0, got {workers}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    by_index = {job.point.index: job for job in jobs}
    writer = ResultsWriter(out / RESULTS_NAME, columns(keys))
    bar = ProgressBar(len(jobs), stream=progress)
    complete = False
    try:
        with ExitStack() as stack:
            if results is not None:
                stream: Any = results(jobs)
            elif scheduler or workers > 0:
                client = stack.enter_context(dask_client(workers=workers, scheduler=scheduler))
                stream = _dask_results(jobs, client)
            else:
                stream = _local_results(jobs)
            if hasattr(stream, "close"):
                stack.callback(stream.close)  # runs before the client closes
            for index, outcome in stream:
                # a varied key that is an outcome too keeps the run's input (a failed run's
                # outcome cells are empty)
                writer.add({**outcome, **input_cells(by_index[index].point, keys, bases)})
                bar.update(failed=bool(outcome.get("error")))
        complete = True
    finally:
        writer.close(sort=complete)
    return sorted(writer.rows, key=lambda r: int(r["run"]))
