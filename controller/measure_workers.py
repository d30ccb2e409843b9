"""Measurement in worker processes (``[service] workers``, ``planer serve --workers N``).

:class:`MeasureWorkerPool` runs the service's measurer factory in N processes. Each worker sets
up once (its initializer builds the measurer for the configured image shape: undistortion
maps, FFT plans; and once more per change of the machine's facts), then measures the pairs it
is given. A pair's two images go through shared memory (one block per worker holding
``depth`` slots; the service copies the images into a free slot), its numbers, the machine's
facts and the board's calibrator state through a pipe; the result (the ``Measurement`` and the
calibration estimates the pair contributed) comes back through the pipe and is read on the
service's event loop (``loop.add_reader``: no thread in between).

The pool only measures; the service consumes the results in sequence order
(:meth:`controller.pair_pipeline.PairPipeline.submit`), so the control loops see the pairs in
order even when workers finish out of order. A worker that dies (crash, ``SIGKILL``) or takes
longer than ``timeout_s`` for a pair is killed and started again; its pairs come back as failed
measurements naming the reason (never a hang); a measurer that raises what the vision never
raises (a bug) is reported to the service (its supervisor boundary: the safe state, as in
process) and the worker ends with the traceback on stderr and is started again. Fewer cores
than workers is a one-line warning and the pool uses one process per core
(:func:`plan_workers`): more processes than cores would only share them.
"""

from __future__ import annotations

import asyncio
import itertools
import math
import os
import signal
import struct
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.reduction import ForkingPickler
from typing import Any

from controller.events import exc_name
from controller.measurement import VISION_ERRORS, MachineFacts, MeasurementStage, failure_reason

__all__ = [
    "MeasureWorkerPool",
    "MeasurementWorkerError",
    "WorkerOutcome",
    "available_cores",
    "open_worker_pool",
    "plan_workers",
]

DEFAULT_DEPTH = 2
"""Pairs a worker holds at once (one measured, one waiting: the worker never idles for a round
trip)."""
WAIT_FOR_WORKER_S = 60.0
"""Longest a pair waits for a free worker (one being started again after a crash on a loaded
machine takes seconds), s."""


class MeasurementWorkerError(Exception):
    """A worker's measurement raised something the vision never raises (a bug, not a pair).

    Deliberately not one of :data:`controller.measurement.VISION_ERRORS`: the service's
    supervisor boundary reports it and goes to the safe state, as for the same error in process.
    """


@dataclass(frozen=True)
class WorkerOutcome:
    """What a worker made of one pair.

    Attributes
    ----------
    error : str or None
        Why there is no measurement (``measurement failed: ...``, ``registration failed: ...``,
        ``measurement worker 1 died (killed by SIGKILL) ...``); ``None`` when measured.
    measurement : object or None
        The vision's ``Measurement``.
    estimates : tuple
        The calibration estimates the pair folded into the board's calibrator (for the
        service's own calibrator, folded in sequence order).
    worker : int
        Which worker (0-based; -1: none took it).
    measure_s : float
        Wall time of the measurement inside the worker, s (0 when it did not run).
    """

    error: str | None
    measurement: Any = None
    estimates: tuple[Any, ...] = ()
    worker: int = -1
    measure_s: float = 0.0


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def plan_workers(requested: int, *, cores: int) -> tuple[int, str | None]:
    """How many worker processes to start for ``requested``, and the warning if fewer.

    Parameters
    ----------
    requested : int
        Workers asked for (``[service] workers`` or ``--workers``), >= 1.
    cores : int
        Cores available (:func:`available_cores`).

    Returns
    -------
    (int, str or None)
        ``min(requested, cores)``, and one line saying so when that is fewer than asked: more
        processes than cores would only share them, a slower pair for no more throughput.

    Raises
    ------
    ValueError
        ``requested`` or ``cores`` < 1.
    """
    if isinstance(requested, bool) or not isinstance(requested, int) or requested < 1:
        raise ValueError(f"requested must be an integer >= 1, got {requested!r}")
    if isinstance(cores, bool) or not isinstance(cores, int) or cores < 1:
        raise ValueError(f"cores must be an integer >= 1, got {cores!r}")
    if requested <= cores:
        return requested, None
    return cores, (f"warning: {requested} measurement workers asked for, but only {cores} "
                   f"core{'s' if cores != 1 else ''} available: measuring in {cores} "
                   f"process{'es' if cores != 1 else ''}")


class _RecordingCalibrator:
    """The board's calibrator as the worker got it, noting each estimate folded in."""

    def __init__(self, calibrator: Any) -> None:
        self.calibrator = calibrator
        self.estimates: list[Any] = []

    def update(self, estimate: Any) -> Any:
        self.estimates.append(estimate)
        return self.calibrator.update(estimate)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.calibrator, name)


# ---------------------------------------------------------------------------------------------
# the worker process


def _send_whole(conn: Any, obj: Any) -> None:
    """``conn.send(obj)`` as one write of header and body (what ``conn.recv`` reads).

    ``Connection.send`` writes a message over 16 KB as two writes (header, then body); a
    worker descheduled between them (normal priority on a busy host) keeps the service's
    real-time bus thread waiting in ``recv`` for the body: 9-40 ms per pair measured under six
    CPU hogs (docs/reliability.md). One write of both lands at once.
    """
    body = ForkingPickler.dumps(obj)
    if len(body) > 0x7FFFFFFF:  # the long header form: leave it to the library
        conn.send(obj)
        return
    view = memoryview(struct.pack("!i", len(body)) + bytes(body))
    fd = conn.fileno()
    while view:
        view = view[os.write(fd, view):]


def _worker_main(conn: Any, factory: Any, shape: tuple[int, int] | None, index: int,
                 threads: int = 1, nice: int | None = None) -> None:
    """A worker: set up once, then measure the pairs the pipe brings until told to stop."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the service's to handle
    if nice is not None:
        from core.realtime import lower_priority

        lower_priority(nice)
    import gc

    import cv2

    cv2.setNumThreads(threads)  # the cores shared out: the pool spreads the pairs over them
    stage = MeasurementStage(None, factory, threaded=False)
    if shape is not None:
        try:  # set-up once: imports, undistortion maps, FFT plans
            stage.measurer(shape)
        except VISION_ERRORS:
            pass  # the first pair says why, as a failed measurement
    gc.collect()
    gc.freeze()  # the set-up's objects never need collecting
    blocks: dict[str, Any] = {}
    conn.send(("ready", index, os.getpid()))
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):  # the service is gone
            break
        if msg is None:
            break
        if msg[0] == "prepare":
            try:
                stage.measurer(msg[1], msg[2])
            except VISION_ERRORS:
                pass
            continue
        try:
            reply = _run_job(stage, blocks, msg)
        except BaseException as exc:  # a bug: told to the service, then ends with its traceback
            conn.send(("fault", msg[1], f"{exc_name(exc)}: {exc}"))
            raise
        _send_whole(conn, reply)
    for block in blocks.values():
        block.close()


def _attach(blocks: dict[str, Any], name: str) -> Any:
    from multiprocessing import shared_memory

    block = blocks.get(name)
    if block is None:
        for old in list(blocks):  # the service replaced the block: the old one goes
            blocks.pop(old).close()
        block = blocks[name] = shared_memory.SharedMemory(name=name)
    return block


def _run_job(stage: MeasurementStage, blocks: dict[str, Any], msg: tuple) -> tuple:
    """Measure one pair; the reply for the service."""
    import numpy as np

    from protocol.frames import Frame

    (_, ticket, where, counts_a, counts_b, speed_mm_s, facts, calibrator) = msg
    if where[0] == "shm":
        _, name, offset, shape, dtype = where
        buf = _attach(blocks, name).buf
        nbytes = math.prod(shape) * np.dtype(dtype).itemsize
        image_a = np.ndarray(shape, dtype, buffer=buf, offset=offset)
        image_b = np.ndarray(shape, dtype, buffer=buf, offset=offset + nbytes)
    else:  # images that did not fit a slot came through the pipe
        image_a, image_b = where[1], where[2]
    frame = Frame(seq=0, t_s=0.0, image_a=image_a, image_b=image_b, counts_a=counts_a,
                  counts_b=counts_b, speed_mm_s=speed_mm_s)
    kwargs: dict[str, Any] = {}
    recorder = None
    if calibrator is not None:
        recorder = _RecordingCalibrator(calibrator)
        kwargs["calibrator"] = recorder
    t0 = time.perf_counter()
    try:
        meas = stage.measure_now(frame, facts, kwargs)
    except VISION_ERRORS as exc:
        return ("done", ticket, failure_reason(exc), None, (), time.perf_counter() - t0)
    finally:
        del image_a, image_b, frame  # no view of the slot outlives the job
    estimates = tuple(recorder.estimates) if recorder is not None else ()
    return ("done", ticket, None, meas, estimates, time.perf_counter() - t0)


# ---------------------------------------------------------------------------------------------
# the service's side


@dataclass
class _Job:
    ticket: int
    future: asyncio.Future
    frame: Any
    facts: MachineFacts | None
    calibrator: Any
    timer: asyncio.TimerHandle | None = None
    slot: int | None = None


@dataclass
class _Worker:
    index: int
    process: Any = None
    conn: Any = None
    ready: bool = False
    block: Any = None  # SharedMemory of `depth` slots
    slot_bytes: int = 0
    free: list[int] = field(default_factory=list)
    jobs: dict[int, _Job] = field(default_factory=dict)
    started: int = 0

    def place(self, frame: Any, depth: int) -> tuple[tuple, int | None]:
        """Copy the pair into a free slot of the shared memory: where it is, and the slot.

        Images that are not a pair of equal 2-D arrays, or that do not fit while the slots are
        in use, go through the pipe instead (no slot).
        """
        import numpy as np

        a, b = frame.image_a, frame.image_b
        if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)
                and a.shape == b.shape and a.dtype == b.dtype and a.ndim == 2):
            return ("pickled", a, b), None  # the worker's measurer says what is wrong
        need = 2 * a.nbytes
        if need > self.slot_bytes:
            if self.jobs:  # slots in use: this pair goes through the pipe, later ones fit
                return ("pickled", a, b), None
            self.free_block()
            from multiprocessing import shared_memory

            self.slot_bytes = need
            self.block = shared_memory.SharedMemory(create=True, size=need * depth)
        slot = self.free.pop()
        offset = slot * self.slot_bytes
        buf = self.block.buf
        np.copyto(np.ndarray(a.shape, a.dtype, buffer=buf, offset=offset), a)
        np.copyto(np.ndarray(b.shape, b.dtype, buffer=buf, offset=offset + a.nbytes), b)
        return ("shm", self.block.name, offset, a.shape, a.dtype.str), slot

    def free_block(self) -> None:
        if self.block is not None:
            try:
                self.block.close()
                self.block.unlink()
            except (OSError, BufferError):
                pass
            self.block = None
            self.slot_bytes = 0

    def reap(self) -> str:
        """How the worker ended (waits a moment for it to be gone)."""
        proc = self.process
        if proc is None:
            return "gone"
        proc.join(0.5)
        code = proc.exitcode
        if code is None:
            proc.kill()
            proc.join(0.5)
            return "stopped answering (killed)"
        if code < 0:
            try:
                return f"died (killed by {signal.Signals(-code).name})"
            except ValueError:
                return f"died (killed by signal {-code})"
        return f"died (exit code {code})"


class MeasureWorkerPool:
    """N processes measuring image pairs with the service's measurer factory.

    Parameters
    ----------
    factory : callable
        The service's measurer factory (picklable: e.g.
        :class:`controller.measurement.VisionMeasurers`); each worker builds its measurers with
        it, once per image shape and machine facts.
    workers : int
        Worker processes (see :func:`plan_workers` for more than the cores).
    shape : tuple of int, optional
        ``(height, width)`` of the images: set up in each worker before the first pair.
    timeout_s : float
        A pair not measured this long after a worker took it fails; the worker holding it is
        killed and started again, s. (A pair waiting for a free worker fails after
        :data:`WAIT_FOR_WORKER_S`.)
    depth : int
        Pairs one worker holds at once (shared-memory slots).
    start_method : str
        ``multiprocessing`` start method (``spawn``: nothing of the service's threads or
        sockets is inherited).
    on_problem : callable, optional
        ``on_problem(text)`` when a worker died or timed out (the service reports it).
    threads_per_worker : int, optional
        OpenCV threads in each worker; default: the cores available over ``workers`` (at
        least 1).
    nice : int, optional
        Nice value of the workers (``None``: as started; :func:`controller.latency.prioritize`).

    Notes
    -----
    Use from one event loop: :meth:`submit` returns an ``asyncio.Future`` of a
    :class:`WorkerOutcome`. :meth:`close` stops the processes and frees the shared memory.
    """

    def __init__(
        self,
        factory: Callable[..., Any],
        *,
        workers: int,
        shape: tuple[int, int] | None = None,
        timeout_s: float = 2.0,
        depth: int = DEFAULT_DEPTH,
        start_method: str = "spawn",
        on_problem: Callable[[str], None] | None = None,
        threads_per_worker: int | None = None,
        nice: int | None = None,
    ) -> None:
        import multiprocessing

        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
        if isinstance(depth, bool) or not isinstance(depth, int) or depth < 1:
            raise ValueError(f"depth must be an integer >= 1, got {depth!r}")
        if not (isinstance(timeout_s, (int, float)) and math.isfinite(timeout_s)
                and timeout_s > 0):
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        self.factory = factory
        self.takes_facts = bool(getattr(factory, "takes_facts", False))
        self.shape = None if shape is None else (int(shape[0]), int(shape[1]))
        self.timeout_s = float(timeout_s)
        self.depth = depth
        self.on_problem = on_problem
        self.nice = nice
        self._ctx = multiprocessing.get_context(start_method)
        self.threads_per_worker = (max(1, available_cores() // workers)
                                   if threads_per_worker is None else int(threads_per_worker))
        """OpenCV threads of each worker (default: the cores shared out among the workers)."""
        self._workers = [_Worker(i) for i in range(workers)]
        self._backlog: deque[_Job] = deque()
        self._tickets = itertools.count(1)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._closed = False
        self.restarts = 0
        """Workers started again after dying or timing out."""
        self.problems: list[str] = []
        """What went wrong with workers, in order (also given to ``on_problem``)."""

    @property
    def workers(self) -> int:
        """Worker processes."""
        return len(self._workers)

    @property
    def capacity(self) -> int:
        """Pairs the workers hold at once (``workers * depth``)."""
        return len(self._workers) * self.depth

    @property
    def in_flight(self) -> int:
        """Pairs submitted and not yet answered."""
        return sum(len(w.jobs) for w in self._workers) + len(self._backlog)

    @property
    def pids(self) -> list[int | None]:
        """The worker processes' ids (``None`` while one is being started again)."""
        return [w.process.pid if w.process is not None else None for w in self._workers]

    # ------------------------------------------------------------------ start and stop
    def start(self, *, timeout_s: float = 120.0) -> MeasureWorkerPool:
        """Start every worker and wait until each finished its set-up.

        Raises
        ------
        RuntimeError
            A worker did not report ready within ``timeout_s`` (it is stopped; the message says
            whether it died).
        """
        from multiprocessing.connection import wait

        for w in self._workers:
            self._spawn(w)
        deadline = time.monotonic() + timeout_s
        waiting = {w.conn: w for w in self._workers}
        while waiting:
            left = deadline - time.monotonic()
            ready = wait(list(waiting), timeout=max(0.0, left)) if left > 0 else []
            if not ready:
                self.close()
                raise RuntimeError(f"measurement workers not ready after {timeout_s:g} s")
            for conn in ready:
                w = waiting.pop(conn)
                try:
                    msg = conn.recv()
                except (EOFError, OSError):
                    code = w.reap()
                    self.close()
                    raise RuntimeError(
                        f"measurement worker {w.index} {code} while setting up") from None
                w.ready = msg[0] == "ready"
        return self

    def _spawn(self, w: _Worker) -> None:
        parent, child = self._ctx.Pipe(duplex=True)
        proc = self._ctx.Process(
            target=_worker_main,
            args=(child, self.factory, self.shape, w.index, self.threads_per_worker, self.nice),
            name=f"planer-measure-{w.index}", daemon=True,
        )
        proc.start()
        child.close()
        w.process, w.conn, w.ready, w.jobs = proc, parent, False, {}
        w.free = list(range(self.depth))
        w.started += 1
        if self._loop is not None:
            self._loop.add_reader(parent.fileno(), self._on_readable, w)

    def close(self) -> None:
        """Stop the workers (at most about a second), free the shared memory; idempotent.

        Pairs still waiting get a failed outcome (``measurement workers closed``).
        """
        if self._closed:
            return
        self._closed = True
        for w in self._workers:
            self._fail_jobs(w, "measurement workers closed")
        while self._backlog:
            self._finish(self._backlog.popleft(), WorkerOutcome("measurement workers closed"))
        for w in self._workers:
            self._detach(w)
            if w.conn is not None:
                try:
                    w.conn.send(None)
                except (OSError, ValueError):
                    pass
        for w in self._workers:
            if w.process is not None:
                w.process.join(1.0)
                if w.process.is_alive():
                    w.process.kill()
                    w.process.join(1.0)
            if w.conn is not None:
                w.conn.close()
                w.conn = None
            w.free_block()

    def __enter__(self) -> MeasureWorkerPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ measuring
    def prepare(self, shape: tuple[int, int], facts: MachineFacts | None) -> None:
        """Have every worker set up for ``shape`` and ``facts`` now (before their next pair)."""
        for w in self._workers:
            if w.conn is not None and w.ready:
                try:
                    w.conn.send(("prepare", tuple(shape), facts))
                except (OSError, ValueError):
                    pass  # a dead worker: the reader notices

    def submit(self, frame: Any, *, facts: MachineFacts | None = None,
               calibrator: Any = None) -> asyncio.Future:
        """Hand one pair to a worker (or queue it until one is free); its outcome's future.

        Parameters
        ----------
        frame : protocol.frames.Frame
            The pair (images, counts, speed).
        facts : MachineFacts, optional
            The machine's facts, for a factory that takes them.
        calibrator : vision.selfcal.SelfCalibrator, optional
            The board's calibrator as it stands (the worker measures with a copy).

        Returns
        -------
        asyncio.Future
            Of a :class:`WorkerOutcome`; raises :class:`MeasurementWorkerError` when the
            measurement raised what the vision never raises.
        """
        loop = asyncio.get_running_loop()
        self._attach_loop(loop)
        job = _Job(next(self._tickets), loop.create_future(), frame, facts, calibrator)
        if self._closed:
            self._finish(job, WorkerOutcome("measurement workers closed"))
            return job.future
        if not any(w.conn is not None for w in self._workers):
            self._finish(job, WorkerOutcome(f"measurement failed: {self._gone()}"))
            return job.future
        job.timer = loop.call_later(WAIT_FOR_WORKER_S, self._timed_out, job)
        self._backlog.append(job)
        self._pump()
        return job.future

    def _gone(self) -> str:
        return "no measurement worker left: " + ("; ".join(self.problems[-2:]) or "none started")

    def _attach_loop(self, loop: asyncio.AbstractEventLoop) -> None:
        if self._loop is loop:
            return
        for w in self._workers:
            self._detach(w)
        self._loop = loop
        for w in self._workers:
            if w.conn is not None:
                loop.add_reader(w.conn.fileno(), self._on_readable, w)

    def _detach(self, w: _Worker) -> None:
        if self._loop is not None and w.conn is not None and not self._loop.is_closed():
            self._loop.remove_reader(w.conn.fileno())

    def _pump(self) -> None:
        """Hand waiting pairs to free workers (the least busy first, then the lowest index)."""
        while self._backlog:
            free = [w for w in self._workers if w.ready and len(w.jobs) < self.depth]
            if not free:
                return
            w = min(free, key=lambda x: (len(x.jobs), x.index))
            job = self._backlog.popleft()
            self._send(w, job)

    def _send(self, w: _Worker, job: _Job) -> None:
        frame = job.frame
        where, job.slot = w.place(frame, self.depth)
        msg = ("job", job.ticket, where, frame.counts_a, frame.counts_b, frame.speed_mm_s,
               job.facts, job.calibrator)
        job.frame = None  # the images are in the slot (or the message) now
        if job.timer is not None:
            job.timer.cancel()  # from now on the measurement's own time limit
        assert self._loop is not None
        job.timer = self._loop.call_later(self.timeout_s, self._timed_out, job)
        w.jobs[job.ticket] = job
        try:
            w.conn.send(msg)
        except (OSError, ValueError) as exc:  # the worker is gone: its reader tells why
            self._died(w, f"not reachable ({exc_name(exc)})")

    # ------------------------------------------------------------------ answers
    def _on_readable(self, w: _Worker) -> None:
        conn = w.conn
        try:
            while conn is not None and conn.poll():
                self._handle(w, conn.recv())
                conn = w.conn
        except (EOFError, OSError):
            self._died(w, w.reap())

    def _handle(self, w: _Worker, msg: tuple) -> None:
        kind = msg[0]
        if kind == "ready":
            w.ready = True
            self._pump()
            return
        job = w.jobs.pop(msg[1], None)
        if job is None:
            return  # answered after it was given up
        self._release_slot(w, job)
        if kind == "done":
            _, _, error, meas, estimates, measure_s = msg
            self._finish(job, WorkerOutcome(error, meas, estimates, w.index, measure_s))
        else:
            self._finish(job, MeasurementWorkerError(f"measurement worker {w.index}: {msg[2]}"))
        self._pump()

    def _release_slot(self, w: _Worker, job: _Job) -> None:
        if job.slot is not None:
            w.free.append(job.slot)

    def _finish(self, job: _Job, outcome: WorkerOutcome | BaseException) -> None:
        if job.timer is not None:
            job.timer.cancel()
            job.timer = None
        job.frame = None
        if job.future.done():
            return
        try:
            if isinstance(outcome, BaseException):
                job.future.set_exception(outcome)
            else:
                job.future.set_result(outcome)
        except RuntimeError:  # its event loop is closed (closing after the service's loop)
            pass

    def _timed_out(self, job: _Job) -> None:
        job.timer = None
        if job in self._backlog:
            self._backlog.remove(job)
            self._finish(job, WorkerOutcome(
                f"measurement failed: no measurement worker free for {WAIT_FOR_WORKER_S:g} s"))
            return
        for w in self._workers:
            if job.ticket in w.jobs:
                if w.process is not None:
                    w.process.kill()
                self._died(w, f"took longer than {self.timeout_s:g} s for a pair (killed)")
                return

    def _fail_jobs(self, w: _Worker, reason: str) -> int:
        jobs = list(w.jobs.values())
        w.jobs = {}
        for job in jobs:
            self._finish(job, WorkerOutcome(reason, worker=w.index))
        return len(jobs)

    def _died(self, w: _Worker, why: str) -> None:
        """A worker is gone: its pairs fail with the reason, another one starts."""
        if w.conn is None:
            return
        self._detach(w)
        w.conn.close()
        w.conn = None
        if w.process is not None and w.process.is_alive():
            w.process.kill()
        if w.process is not None:
            w.process.join(0.5)
        w.process = None
        was_ready, w.ready = w.ready, False
        text = f"measurement worker {w.index} {why}"
        n = self._fail_jobs(w, f"measurement failed: {text}")
        if self._closed:
            return
        if was_ready:
            self.restarts += 1
            problem = f"{text}: {n} pair(s) failed; worker started again"
        else:  # it cannot even set up: starting it again would only loop
            problem = f"{text} while setting up: not started again"
        self.problems.append(problem)
        if self.on_problem is not None:
            self.on_problem(problem)
        if was_ready:
            self._spawn(w)
        elif not any(x.conn is not None for x in self._workers):
            while self._backlog:  # nobody left to measure them
                self._finish(self._backlog.popleft(),
                             WorkerOutcome(f"measurement failed: {self._gone()}"))


def open_worker_pool(
    factory: Callable[..., Any],
    requested: int,
    *,
    shape: tuple[int, int] | None = None,
    timeout_s: float = 2.0,
    cores: int | None = None,
    nice: int | None = None,
) -> tuple[MeasureWorkerPool | None, str | None]:
    """Start the measurement workers a configuration asks for.

    Parameters
    ----------
    factory : callable
        The service's measurer factory (picklable).
    requested : int
        ``[service] workers`` / ``--workers``: 0 measures in the service's process (no pool).
    shape : tuple of int, optional
        ``(height, width)`` of the images (each worker sets up for it before the first pair).
    timeout_s : float
        Longest a pair may take in a worker, s.
    cores : int, optional
        Cores available (default :func:`available_cores`).
    nice : int, optional
        Nice value of the workers.

    Returns
    -------
    (MeasureWorkerPool or None, str or None)
        The started pool (``None`` for 0) and the warning of :func:`plan_workers`.
    """
    if isinstance(requested, bool) or not isinstance(requested, int) or requested < 0:
        raise ValueError(f"workers must be an integer >= 0, got {requested!r}")
    if requested == 0:
        return None, None
    n, warning = plan_workers(requested, cores=available_cores() if cores is None else cores)
    pool = MeasureWorkerPool(factory, workers=n, shape=shape, timeout_s=timeout_s, nice=nice)
    return pool.start(), warning
