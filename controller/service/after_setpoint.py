"""The work after a pair's setpoints, done when no pair's setpoints wait for the event loop.

The service's event loop is one thread. In real time (measurement in worker processes) a pair's
stages after its setpoints went out -- the decimated profile of its record, queueing the record,
counting the pair, the garbage collector -- are bookkeeping: nothing of them changes a setpoint.
While the loop did them, a pair of another head whose measurement had come back (or this
head's next pair) waited. :class:`AfterSetpoint` is the loop's queue of that bookkeeping, one
per event loop, shared by the pair pipelines on it (a moulder's heads):

* a pair's bookkeeping runs at once when none is queued and no pipeline has a pair *ready for
  its setpoints* (its measurement back, the pairs before it through their setpoints); else it
  waits, in the order the pairs reached their setpoints (so each head's records keep their
  order), until none is ready;
* released on a timer of the loop due at once: the loop takes what the workers' pipes brought
  first (a reply read then makes its pair ready, and the bookkeeping waits for its setpoints);
  all that is queued at once (they run one after the other, in order, in the loop's next
  round), the next release once they are all done;
* bounded: with :data:`MAX_WAITING` pairs' bookkeeping queued the oldest runs whatever is
  ready (a loop that is never idle still writes its records; the pipeline's own limit of pairs
  in flight then holds the camera back as before);
* the garbage collector (:func:`controller.service.latency.collect_between_pairs`) runs when
  one is due, no bookkeeping is queued and no pair is ready (:meth:`AfterSetpoint.collect`).

Members are objects with ``setpoints_ready() -> bool`` (:class:`ReadyForSetpoints`), held
weakly. A pair handled inline (:meth:`controller.service.pipeline.PairPipeline.handle`, simulated
time) does its bookkeeping before it returns, as before: this queue is only the real-time path's.
"""

from __future__ import annotations

import asyncio
import weakref
from collections import deque
from typing import Protocol

from controller.service.latency import collect_between_pairs, idle_collector

MAX_WAITING = 8
"""Pairs' bookkeeping queued before the oldest runs whatever pair is ready (two per head of a
four-head moulder: about 20 ms of pairs at 400 pairs/s)."""


class ReadyForSetpoints(Protocol):
    """A member of the queue: a pair pipeline."""

    def setpoints_ready(self) -> bool:
        """Whether a pair of this member could go through its setpoints now."""
        ...


class AfterSetpoint:
    """One event loop's queue of the bookkeeping after pairs' setpoints (module docstring).

    Parameters
    ----------
    loop : asyncio.AbstractEventLoop
        The event loop (see :func:`after_setpoint_queue`: one queue per loop).
    max_waiting : int
        :data:`MAX_WAITING`.

    Notes
    -----
    Use: ``await queue.turn()``, the bookkeeping, then ``queue.done()`` (in a ``finally``);
    each member calls :meth:`setpoint_done` after each of its pairs' setpoints.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop, *, max_waiting: int = MAX_WAITING) -> None:
        if isinstance(max_waiting, bool) or not isinstance(max_waiting, int) or max_waiting < 1:
            raise ValueError(f"max_waiting must be an integer >= 1, got {max_waiting!r}")
        self._loop = loop
        self.max_waiting = max_waiting
        self._members: weakref.WeakSet[ReadyForSetpoints] = weakref.WeakSet()
        self._waiting: deque[asyncio.Future] = deque()
        self._running = 0  # released (or run at once) and not done
        self._check_handle: asyncio.TimerHandle | None = None
        self._gc_wanted = False

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        """The event loop this queue is of."""
        return self._loop

    def register(self, member: ReadyForSetpoints) -> None:
        """Let ``member``'s ready pairs go before the queued bookkeeping (held weakly)."""
        self._members.add(member)

    @property
    def waiting(self) -> int:
        """Pairs' bookkeeping queued (not counting one running)."""
        return len(self._waiting)

    def ready(self) -> bool:
        """Whether a pair of any member could go through its setpoints now."""
        return any(m.setpoints_ready() for m in list(self._members))

    async def turn(self) -> None:
        """Wait until this pair's bookkeeping may run (at once when nothing waits).

        The caller runs its bookkeeping and then calls :meth:`done`, also when it failed.
        """
        if not self._running and not self._waiting and not self.ready():
            self._running = 1
            return
        fut = self._loop.create_future()
        self._waiting.append(fut)
        self._check_soon()
        try:
            await fut
        except asyncio.CancelledError:
            if fut.done() and not fut.cancelled():  # released, then cancelled: the next goes
                self.done()
            else:
                try:
                    self._waiting.remove(fut)
                except ValueError:
                    pass
            raise

    def done(self) -> None:
        """The bookkeeping that had its :meth:`turn` is over: the next may go."""
        self._running = max(0, self._running - 1)
        if not self._running and (self._waiting or self._gc_wanted):
            self._check_soon()

    def setpoint_done(self) -> None:
        """A member's pair went through its setpoints: queued bookkeeping may be due."""
        if (self._waiting or self._gc_wanted) and not self._running:
            self._check_soon()

    def collect(self) -> None:
        """Run the garbage collector when one is due and the loop is idle (not now).

        Costs a ``gc.get_count`` when none is due (or no :class:`IdleCollector` is installed).
        """
        collector = idle_collector()
        if collector is None or not collector.due():
            return
        self._gc_wanted = True
        self._check_soon()

    def _check_soon(self) -> None:
        """:meth:`_check` on a timer due now: after the loop took what its pipes brought."""
        if self._check_handle is None and not self._loop.is_closed():
            self._check_handle = self._loop.call_at(self._loop.time(), self._check)

    def _check(self) -> None:
        self._check_handle = None
        if self._running:
            return  # done() checks again
        waiting = self._waiting
        while waiting and waiting[0].done():  # cancelled while waiting
            waiting.popleft()
        ready = self.ready()
        if waiting:
            if ready and len(waiting) < self.max_waiting:
                return  # setpoint_done() checks again
            if ready:  # the oldest only
                self._running = 1
                waiting.popleft().set_result(None)
                return
            while waiting:  # all queued, in order (the loop's next round runs them in turn)
                fut = waiting.popleft()
                if not fut.done():
                    self._running += 1
                    fut.set_result(None)
            return
        if self._gc_wanted and not ready:
            self._gc_wanted = False
            collect_between_pairs()


_QUEUES: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, AfterSetpoint] = (
    weakref.WeakKeyDictionary())


def after_setpoint_queue(loop: asyncio.AbstractEventLoop | None = None) -> AfterSetpoint:
    """The :class:`AfterSetpoint` queue of ``loop`` (default: the running loop), made once."""
    loop = asyncio.get_running_loop() if loop is None else loop
    queue = _QUEUES.get(loop)
    if queue is None:
        queue = _QUEUES[loop] = AfterSetpoint(loop)
    return queue
