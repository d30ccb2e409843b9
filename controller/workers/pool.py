"""Measurement in worker processes (``[service] workers``, ``planer serve --workers N``).

:class:`MeasureWorkerPool` runs the service's measurer factory in N processes. Each worker sets
up once (its initializer builds the measurer for the configured image shape: undistortion
maps, FFT plans; and once more per change of the machine's facts), then measures the pairs it
is given. A pair's two images go through shared memory (one block per worker holding
``depth`` slots; the service copies the images into a free slot), its numbers, the machine's
facts and the board's calibrator (its fields' values: :func:`_cal_state`) through a pipe. The
worker writes the result (the ``Measurement``, its float arrays, and the calibration estimates
the pair contributed) into the pair's slot as soon as it is made, and tells the service which
slots hold results through the pipe: at once when fewer than 2 pairs wait behind (the latency
path), in batches of ``depth // 2`` while it is saturated (one wake-up of the service for
several pairs: what lets two workers on two cores scale). The service reads the pipe on its
event loop (``loop.add_reader``: no thread in between; one ``os.read`` per wake-up, the whole
messages cut out of it). The camera's roll is searched for on the pairs the service picks in
sequence order (:class:`_RollPlan`: the pairs the board's calibrator searches on in process;
a board's pairs handed out before its first confident roll came back go to one worker, which
decides for them as in process), and one deadline timer watches all pairs in flight (none per
pair).

The pool only measures; the service consumes the results in sequence order
(:meth:`controller.service.pipeline.PairPipeline.submit`), so the control loops see the pairs in
order even when workers finish out of order. A worker that dies (crash, ``SIGKILL``) or takes
longer than ``timeout_s`` for a pair is killed and started again: the pair it was measuring
comes back as a failed measurement naming the reason (never a hang), the results it had made
count (they are in their slots), and the pairs waiting behind go to the next free worker. A
measurer that raises what the vision never raises (a bug) is reported to the service (its
supervisor boundary: the safe state, as in process) and the worker ends with the traceback on
stderr and is started again. Fewer cores than workers is a one-line warning and the pool uses
one process per core (:func:`plan_workers`): more processes than cores would only share them.

One worker's process, pipe and slots as the service sees them:
:mod:`controller.workers.link`; the worker's side: :mod:`controller.workers.process`.
"""

from __future__ import annotations

import asyncio
import itertools
import math
import os
import time
import weakref
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from controller.service.events import exc_name
from controller.service.measurement import MachineFacts
from controller.workers.link import WorkerLink, WorkerOutcome
from controller.workers.process import RollChain, _cal_state, _send_whole

__all__ = [
    "MeasureWorkerPool",
    "MeasurementWorkerError",
    "PoolForFactory",
    "WorkerOutcome",
    "available_cores",
    "open_worker_pool",
    "plan_workers",
]

DEFAULT_DEPTH = 12
"""Pairs a worker holds at once (one measured, the rest waiting: the worker never idles for a
round trip). A saturated worker answers in batches of ``depth // 2`` (one wake-up of the
service for them, :class:`controller.workers.process._Replies`) and still has half its
pairs to measure while the service refills the other half. 2 workers on 2 cores, pairs/s over
one worker's, alternating runs: depth 2 (no batches) 1.44-1.62, median 1.55; 8: 1.44-1.76,
1.57; 12: 1.54-1.78, 1.61-1.70 (docs/service.md, "Workers"). The slots cost ``depth`` pairs of
shared memory per worker (8 MB at 659 x 493, 55 MB at 1920 x 1200)."""
WAIT_FOR_WORKER_S = 60.0
"""Longest a pair waits for a free worker (one being started again after a crash on a loaded
machine takes seconds), s."""


class MeasurementWorkerError(Exception):
    """A worker's measurement raised something the vision never raises (a bug, not a pair).

    Deliberately not one of :data:`controller.service.measurement.VISION_ERRORS`: the service's
    supervisor boundary reports it and goes to the safe state, as for the same error in process.
    """


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


class _Chain:
    """A board's pairs handed out before its first confident roll came back: one worker's.

    Whether such a pair searches depends on what the searches before it found, which the
    service does not know yet: they all go to ``link``'s worker, which measures them in order
    and decides as the board's calibrator in process would (:class:`RollChain`). ``tickets``:
    the chain's pairs not answered yet.
    """

    __slots__ = ("key", "link", "tickets")

    def __init__(self, key: int, link: WorkerLink) -> None:
        self.key = key
        self.link = link
        self.tickets: list[int] = []


class _RollPlan:
    """When a board's pairs search for the camera's roll, decided in sequence order.

    In process the board's calibrator searches on one pair in ``roll_every`` and the pairs
    between use the last confident roll (on every pair while it has none). A worker's copy of
    the calibrator cannot count the pairs in flight, so the service decides at
    :meth:`MeasureWorkerPool.submit` (sequence order): once a confident roll came back, a
    search every ``roll_every`` pairs as in process, the pairs between given the newest
    confident roll that came back (any worker measures them). Before that (a board's first
    pairs, in flight at once) the pairs form a :class:`_Chain`: one worker decides for them
    as in process, and the first confident roll to come back tells the service where the
    chain's count stands (:meth:`found`). The same pairs search as in process, whatever the
    timing (without the chain every pair in flight before the first roll came back searched:
    twice the searches of in process in the moulder's bench).
    """

    __slots__ = ("age", "chain", "every", "roll", "ticket")

    def __init__(self) -> None:
        self.age = 0  # pairs handed the roll since the last search was handed out
        self.roll: tuple[float, float] | None = None
        self.ticket = 0  # the pair that found it
        self.chain: _Chain | None = None
        self.every = 1

    def next(self, roll_every: int, ticket: int = 0,
             link: Callable[[], WorkerLink | None] | None = None) -> tuple[Any, ...]:
        """The next pair's directive: ``()`` search, ``(roll_deg, confidence)`` use it.

        Without a confident roll yet: a :class:`RollChain` (the pair ``ticket`` joins the
        chain, started on the worker ``link()`` picks), or ``()`` when there is no ``link``
        or it picks none.
        """
        self.every = roll_every
        if self.roll is None:
            chain = self.chain
            start = chain is None
            if start:
                w = None if link is None else link()
                if w is None:
                    return ()
                chain = self.chain = _Chain(next(_CHAIN_KEYS), w)
            chain.tickets.append(ticket)
            return RollChain(chain.key, start)
        if self.age + 1 >= roll_every:
            self.age = 0
            return ()
        self.age += 1
        return self.roll

    def found(self, ticket: int, roll: tuple[float, float] | None) -> None:
        """A pair came back (any order) with its search's confident roll (or ``None``).

        The newest confident roll by sequence is kept. A chain's first confident roll ends
        the chain: the count goes on from it over the chain's pairs behind it, as their
        worker counts. A chain whose pairs all came back without one ends too (the next
        pair searches).
        """
        chain = self.chain
        if chain is not None and ticket in chain.tickets:
            chain.tickets.remove(ticket)
            if roll is not None and self.roll is not None:  # one came another way (a pair
                self.chain = None  # handed on from a gone chain's worker): counted from it
                if ticket > self.ticket:
                    self.roll, self.ticket = roll, ticket
            elif roll is not None:
                self.chain = None
                self.roll, self.ticket, self.age = roll, ticket, 0
                for _ in range(sum(1 for t in chain.tickets if t > ticket)):
                    self.next(self.every)  # the chain's pairs behind it, as counted there
            elif not chain.tickets:
                self.chain = None
            return
        if roll is not None and ticket > self.ticket:
            self.roll, self.ticket = roll, ticket

    def lost(self, ticket: int) -> None:
        """Pair ``ticket`` will not come back (failed while waiting for a worker)."""
        chain = self.chain
        if chain is not None and ticket in chain.tickets:
            chain.tickets.remove(ticket)
            if not chain.tickets:
                self.chain = None


_CHAIN_KEYS = itertools.count(1)


@dataclass
class _Job:
    ticket: int
    future: asyncio.Future
    frame: Any
    facts: MachineFacts | None
    calibrator: Any
    deadline: float = math.inf  # event-loop time it fails at (waiting, then measuring)
    slot: int | None = None
    roll: tuple[Any, ...] | None = None  # the roll directive (_RollPlan.next)
    plan: _RollPlan | None = None
    factory: int = 0  # which factory measures it (MeasureWorkerPool.factory_index)
    chain: _Chain | None = None  # its roll chain: only its worker measures it


def _settle(job: _Job, outcome: WorkerOutcome | BaseException) -> None:
    """Give ``job``'s future its outcome (once; not on a closed event loop)."""
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


class PoolForFactory:
    """A shared pool as one service sees it: that service's pairs measured with its factory.

    The heads of a moulder share one :class:`MeasureWorkerPool`, each with its own measurer
    factory (its own rig: camera, encoder): each head's pipeline is given
    ``PoolForFactory(pool, its_measurement.factory)``. ``submit`` and ``prepare`` name the
    factory (the workers are given it once, :meth:`MeasureWorkerPool.factory_index`);
    everything else is the pool's (``capacity``, ``workers``, ``shape``, ``listen`` ...).
    """

    def __init__(self, pool: MeasureWorkerPool, factory: Callable[..., Any]) -> None:
        self.pool = pool
        self.factory = factory
        self.index = pool.factory_index(factory)

    def submit(self, frame: Any, *, facts: MachineFacts | None = None,
               calibrator: Any = None) -> asyncio.Future:
        """:meth:`MeasureWorkerPool.submit` with this service's factory."""
        return self.pool.submit(frame, facts=facts, calibrator=calibrator, factory=self.factory)

    def prepare(self, shape: tuple[int, int], facts: MachineFacts | None) -> None:
        """:meth:`MeasureWorkerPool.prepare` with this service's factory."""
        self.pool.prepare(shape, facts, factory=self.factory)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.pool, name)


class MeasureWorkerPool:
    """N processes measuring image pairs with the service's measurer factory.

    Parameters
    ----------
    factory : callable
        The service's measurer factory (picklable: e.g.
        :class:`controller.service.measurement.VisionMeasurers`); each worker builds its measurers
        with
        it, once per image shape and machine facts.
    workers : int
        Worker processes (see :func:`plan_workers` for more than the cores).
    shape : tuple of int, optional
        ``(height, width)`` of the images: set up in each worker before the first pair.
    timeout_s : float
        A pair not measured this long after a worker took it fails; the worker holding it is
        killed and started again, s (checked every quarter of it: within 1.25 times it). (A
        pair waiting for a free worker fails after :data:`WAIT_FOR_WORKER_S`.)
    depth : int
        Pairs one worker holds at once (shared-memory slots); a saturated worker answers in
        batches of ``depth // 2``.
    start_method : str
        ``multiprocessing`` start method (``spawn``: nothing of the service's threads or
        sockets is inherited).
    on_problem : callable, optional
        ``on_problem(text)`` when a worker died or timed out (the service reports it).
    threads_per_worker : int, optional
        OpenCV threads in each worker; default: the cores available over ``workers`` (at
        least 1).
    nice : int, optional
        Nice value of the workers (``None``: as started;
        :func:`controller.service.latency.prioritize`).

    Notes
    -----
    Use from one event loop: :meth:`submit` returns an ``asyncio.Future`` of a
    :class:`WorkerOutcome`. :meth:`close` stops the processes and frees the shared memory.
    Several services on that loop may share one pool (the heads of a moulder): each pair
    carries its own facts and calibrator, the workers keep a measurer per machine's facts
    (:data:`controller.workers.process.KEEP_FACTS`), the pairs are measured in the order
    submitted, whichever service they are of, and each service :meth:`listen` s for the
    workers' problems.
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
        self.hold = max(1, depth // 2)
        """Most replies a saturated worker holds to send together (``depth // 2``)."""
        self.on_problem = on_problem
        self.nice = nice
        self._ctx = multiprocessing.get_context(start_method)
        self.threads_per_worker = (max(1, available_cores() // workers)
                                   if threads_per_worker is None else int(threads_per_worker))
        """OpenCV threads of each worker (default: the cores shared out among the workers)."""
        self._workers = [WorkerLink(i) for i in range(workers)]
        self._backlog: deque[_Job] = deque()
        self._tickets = itertools.count(1)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._closed = False
        self._watchdog: asyncio.TimerHandle | None = None
        self._tick_s = min(self.timeout_s, WAIT_FOR_WORKER_S) / 4.0
        self._rolls: weakref.WeakKeyDictionary[Any, _RollPlan] = weakref.WeakKeyDictionary()
        self.restarts = 0
        """Workers started again after dying or timing out."""
        self.problems: list[str] = []
        """What went wrong with workers, in order (also given to ``on_problem``)."""
        self._listeners: list[Callable[[str], None]] = []
        self._factories: list[Callable[..., Any]] = []  # others' factories: index = place + 1

    def factory_index(self, factory: Callable[..., Any] | None) -> int:
        """The number the workers know ``factory`` by (0: the pool's own, or ``None``).

        Another service's factory (another head's rig) is given to every worker once, when
        first named, and again to a worker started anew; known by identity.
        """
        if factory is None or factory is self.factory:
            return 0
        for i, known in enumerate(self._factories, 1):
            if known is factory:
                return i
        self._factories.append(factory)
        index = len(self._factories)
        for w in self._workers:
            self._tell_factory(w, index, factory)
        return index

    @staticmethod
    def _tell_factory(w: WorkerLink, index: int, factory: Callable[..., Any]) -> None:
        if w.conn is not None:
            try:
                w.conn.send(("factory", index, factory))
            except (OSError, ValueError):
                pass  # a dead worker: the reader notices, the new one is told at its start

    def listen(self, fn: Callable[[str], None]) -> None:
        """Tell ``fn(text)`` too when a worker died or timed out (each head sharing the pool).

        ``on_problem`` is told first, then every listener in the order they were added (one
        added twice is told once).
        """
        if fn not in self._listeners:
            self._listeners.append(fn)

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

    def _spawn(self, w: WorkerLink) -> None:
        w.spawn(self._ctx, (self.factory, self.shape, w.index, self.threads_per_worker,
                            self.nice, self.hold), depth=self.depth)
        for index, factory in enumerate(self._factories, 1):
            self._tell_factory(w, index, factory)
        if self._loop is not None:
            self._loop.add_reader(w.conn.fileno(), self._on_readable, w)

    def close(self) -> None:
        """Stop the workers (at most about a second), free the shared memory; idempotent.

        Pairs still waiting get a failed outcome (``measurement workers closed``).
        """
        if self._closed:
            return
        self._closed = True
        if self._watchdog is not None:
            self._watchdog.cancel()
            self._watchdog = None
        for w in self._workers:
            for job in w.drop_jobs():
                _settle(job, WorkerOutcome("measurement workers closed", worker=w.index))
        while self._backlog:
            _settle(self._backlog.popleft(), WorkerOutcome("measurement workers closed"))
        for w in self._workers:
            self._detach(w)
            if w.conn is not None:
                try:
                    w.conn.send(None)
                except (OSError, ValueError):
                    pass
        for w in self._workers:
            w.end(wait_s=1.0)
            w.free_block()

    def __enter__(self) -> MeasureWorkerPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ measuring
    def prepare(self, shape: tuple[int, int], facts: MachineFacts | None, *,
                factory: Callable[..., Any] | None = None) -> None:
        """Have every worker set up for ``shape`` and ``facts`` now (before their next pair).

        ``factory``: another service's factory sharing the pool (default: the pool's).
        """
        index = self.factory_index(factory)
        for w in self._workers:
            if w.conn is not None and w.ready:
                try:
                    w.conn.send(("prepare", tuple(shape), facts, index))
                except (OSError, ValueError):
                    pass  # a dead worker: the reader notices

    def submit(self, frame: Any, *, facts: MachineFacts | None = None,
               calibrator: Any = None,
               factory: Callable[..., Any] | None = None) -> asyncio.Future:
        """Hand one pair to a worker (or queue it until one is free); its outcome's future.

        Parameters
        ----------
        frame : protocol.frames.Frame
            The pair (images, counts, speed).
        facts : MachineFacts, optional
            The machine's facts, for a factory that takes them.
        calibrator : vision.calibration.selfcal.SelfCalibrator, optional
            The board's calibrator as it stands (the worker measures with a copy).
        factory : callable, optional
            The measurer factory of the service the pair is of, when several share the pool
            (:class:`PoolForFactory`); default the pool's own.

        Returns
        -------
        asyncio.Future
            Of a :class:`WorkerOutcome`; raises :class:`MeasurementWorkerError` when the
            measurement raised what the vision never raises.
        """
        loop = asyncio.get_running_loop()
        self._attach_loop(loop)
        job = _Job(next(self._tickets), loop.create_future(), frame, facts, calibrator,
                   factory=self.factory_index(factory))
        if self._closed:
            _settle(job, WorkerOutcome("measurement workers closed"))
            return job.future
        if not any(w.conn is not None for w in self._workers):
            _settle(job, WorkerOutcome(f"measurement failed: {self._gone()}"))
            return job.future
        self._plan_roll(job)
        job.deadline = loop.time() + WAIT_FOR_WORKER_S
        self._backlog.append(job)
        self._pump()
        self._watch()
        return job.future

    def _plan_roll(self, job: _Job) -> None:
        """``job``'s roll directive, decided in sequence order (:class:`_RollPlan`).

        One plan per calibrator (weakly: a board's, of one head); a calibrator without a roll
        schedule, or one not weakly referable, is left to decide itself.
        """
        cal = job.calibrator
        every = getattr(cal, "roll_every", None)
        if cal is None or isinstance(every, bool) or not isinstance(every, int):
            return
        try:
            plan = self._rolls.get(cal)
            if plan is None:
                plan = self._rolls[cal] = _RollPlan()
        except TypeError:
            return
        job.plan, job.roll = plan, plan.next(every, job.ticket, self._least_busy)
        if type(job.roll) is RollChain:
            job.chain = plan.chain

    def _least_busy(self) -> WorkerLink | None:
        """The ready worker holding the fewest pairs (the lowest index first), or ``None``."""
        best = None
        for w in self._workers:
            if w.ready and w.conn is not None and (best is None or len(w.jobs) < len(best.jobs)):
                best = w
        return best

    def _gone(self) -> str:
        return "no measurement worker left: " + ("; ".join(self.problems[-2:]) or "none started")

    def _attach_loop(self, loop: asyncio.AbstractEventLoop) -> None:
        if self._loop is loop:
            return
        for w in self._workers:
            self._detach(w)
        self._loop = loop
        self._watchdog = None  # a timer of the loop before never fires
        for w in self._workers:
            if w.conn is not None:
                loop.add_reader(w.conn.fileno(), self._on_readable, w)

    def _detach(self, w: WorkerLink) -> None:
        if self._loop is not None and w.conn is not None and not self._loop.is_closed():
            self._loop.remove_reader(w.conn.fileno())

    def _pump(self) -> None:
        """Hand waiting pairs to free workers (the least busy first, then the lowest index).

        A pair of a roll chain goes only to its chain's worker: while that one is full the
        pairs behind it go on to the others.
        """
        depth = self.depth
        backlog = self._backlog
        at = 0
        while at < len(backlog):
            job = backlog[at]
            if job.chain is not None:
                w = job.chain.link
                if not (w.ready and len(w.jobs) < depth):
                    at += 1
                    continue
            else:
                w = None
                for x in self._workers:
                    if x.ready and len(x.jobs) < depth and (w is None
                                                            or len(x.jobs) < len(w.jobs)):
                        w = x
                if w is None:
                    return
            del backlog[at]
            self._send(w, job)
            if not w.ready:  # it died (being started again): the pump comes again (_died)
                return

    def _send(self, w: WorkerLink, job: _Job) -> None:
        frame = job.frame
        where, job.slot = w.place(frame, self.depth)
        msg = ("job", job.ticket, where, frame.counts_a, frame.counts_b, frame.speed_mm_s,
               job.facts, *_cal_state(job.calibrator), job.roll, job.factory)
        assert self._loop is not None
        job.deadline = self._loop.time() + self.timeout_s  # the measurement's own limit
        w.jobs[job.ticket] = job
        try:
            _send_whole(w.conn, msg)  # the C pickler, one write (Connection.send's framing)
        except (OSError, ValueError) as exc:  # the worker is gone: its reader tells why
            self._died(w, f"not reachable ({exc_name(exc)})")

    # ------------------------------------------------------------------ answers
    def _on_readable(self, w: WorkerLink) -> None:
        """Handle what the worker wrote (:meth:`WorkerLink.messages`), then its end if it ended."""
        conn = w.conn
        if conn is None:
            return
        msgs, gone = w.messages()
        for msg in msgs:
            self._handle(w, msg)
            if w.conn is not conn:  # it died or was stopped meanwhile: the rest is moot
                return
        if gone is not None:
            self._died(w, gone)

    def _handle(self, w: WorkerLink, msg: tuple) -> None:
        if msg[0] == "ready":
            w.ready = True
            self._pump()
        elif msg[0] == "slotted":  # replies the worker wrote into their pairs' slots
            for reply in w.told(msg[1]):
                self._answer(w, reply)
        else:
            self._answer(w, msg)

    def _answer(self, w: WorkerLink, msg: tuple) -> None:
        """Settle the pair a ``done`` or ``fault`` reply is for; hand out the next pairs."""
        job = w.take(msg[1])
        if job is None:
            return  # answered after it was given up
        if msg[0] == "done":
            if job.plan is not None:
                job.plan.found(job.ticket, msg[6])
            _settle(job, w.outcome(msg, job.slot))
        else:
            _settle(job, MeasurementWorkerError(f"measurement worker {w.index}: {msg[2]}"))
        self._pump()

    def _watch(self) -> None:
        """Arm the one deadline timer (while pairs are in flight; none per pair)."""
        if self._watchdog is None and self._loop is not None and not self._closed:
            self._watchdog = self._loop.call_later(self._tick_s, self._check_deadlines)

    def _check_deadlines(self) -> None:
        """Fail the pairs past their deadline: a worker holding one is killed (and restarted).

        Checked every :attr:`_tick_s` while pairs are in flight: a pair fails between its
        limit and a quarter of it later.
        """
        self._watchdog = None
        assert self._loop is not None
        now = self._loop.time()
        for job in [j for j in self._backlog if j.deadline <= now]:
            self._backlog.remove(job)
            if job.plan is not None:
                job.plan.lost(job.ticket)
            _settle(job, WorkerOutcome(
                f"measurement failed: no measurement worker free for {WAIT_FOR_WORKER_S:g} s"))
        for w in self._workers:
            if any(j.deadline <= now for j in w.jobs.values()):
                if w.process is not None:
                    w.process.kill()
                self._died(w, f"took longer than {self.timeout_s:g} s for a pair (killed)")
        if self.in_flight:
            self._watch()

    def _hand_on(self, w: WorkerLink, reason: str) -> int:
        """A dead worker's pairs: the one it was measuring fails, the rest wait for another.

        The worker measured its pairs in the order they were sent, so the first unanswered one
        is the pair it died on (or hung on); those behind it were never started and go back to
        the front of the queue, in order (all fail once the pool is closed). Returns the pairs
        failed.
        """
        jobs = w.drop_jobs()
        failed = jobs if self._closed or self._loop is None else jobs[:1]
        for job in failed:
            _settle(job, WorkerOutcome(reason, worker=w.index))
        if len(failed) < len(jobs):
            deadline = self._loop.time() + WAIT_FOR_WORKER_S
            for job in reversed(jobs[1:]):
                job.slot, job.deadline = None, deadline
                self._backlog.appendleft(job)
        return len(failed)

    def _unchain(self, w: WorkerLink) -> None:
        """End the roll chains of the gone worker ``w``: their pairs left search (never less)."""
        for plan in list(self._rolls.values()):
            if plan.chain is not None and plan.chain.link is w:
                plan.chain = None
        for job in self._backlog:
            if job.chain is not None and job.chain.link is w:
                job.chain, job.roll = None, ()

    def _died(self, w: WorkerLink, why: str) -> None:
        """A worker is gone: another one starts; what it held is answered or handed on.

        Replies it had written into their slots count (:meth:`WorkerLink.slotted`); the pair it
        was measuring fails with the reason; the pairs behind it go to the next free worker
        (:meth:`_hand_on`).
        """
        if w.conn is None:
            return
        self._detach(w)
        w.end(wait_s=0.0)
        was_ready, w.ready = w.ready, False
        for reply in w.salvage():  # measured, held, not yet told: not lost
            self._answer(w, reply)
        text = f"measurement worker {w.index} {why}"
        n = self._hand_on(w, f"measurement failed: {text}")
        self._unchain(w)
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
        for fn in list(self._listeners):
            fn(problem)
        if was_ready:
            self._spawn(w)
        elif not any(x.conn is not None for x in self._workers):
            while self._backlog:  # nobody left to measure them
                _settle(self._backlog.popleft(),
                        WorkerOutcome(f"measurement failed: {self._gone()}"))
        if self._backlog and self._loop is not None:
            self._loop.call_soon(self._pump)  # the pairs handed on, to the workers still up


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
