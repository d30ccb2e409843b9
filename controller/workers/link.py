"""The service's end of one measurement worker: its process, pipe, slots and open pairs.

:class:`controller.workers.pool.MeasureWorkerPool` keeps one :class:`WorkerLink` per worker
process: the process (:meth:`WorkerLink.spawn`, :meth:`WorkerLink.end`, :meth:`WorkerLink.reap`),
the pipe's messages (:meth:`WorkerLink.messages`), the shared-memory block of ``depth`` slots
the pairs' images go into (:meth:`WorkerLink.place`) and the replies come back in
(:meth:`WorkerLink.outcome`, :meth:`WorkerLink.told`, :meth:`WorkerLink.salvage`), and the pairs
it holds (``jobs``, by ticket, in the order they were sent). The worker's side of the wire is
:mod:`controller.workers.process`.
"""

from __future__ import annotations

import os
import signal
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from controller.workers.process import (
    READ_BYTES,
    SLOT_HEAD,
    _Packed,
    _reply_from_slot,
    _unpickled,
    _whole_messages,
    _worker_main,
)


class OpenPair(Protocol):
    """What a link needs of a pair it holds: its ticket and slot."""

    ticket: int
    slot: int | None


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



@dataclass
class WorkerLink:
    """The service's end of measurement worker ``index`` (module docstring)."""

    index: int
    process: Any = None
    conn: Any = None
    ready: bool = False
    block: Any = None  # SharedMemory of `depth` slots
    slot_bytes: int = 0
    free: list[int] = field(default_factory=list)
    jobs: dict[int, Any] = field(default_factory=dict)
    started: int = 0
    rbuf: bytearray = field(default_factory=bytearray)  # replies read, not yet whole

    def place(self, frame: Any, depth: int) -> tuple[tuple, int | None]:
        """Copy the pair into a free slot of the shared memory: where it is, and the slot.

        Images that are not a pair of equal 2-D arrays, or that do not fit while the slots are
        in use, go through the pipe instead (no slot).
        """
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
        slot = self.free.pop(0)  # freed longest ago: the worker's caches hold least of it
        offset = slot * self.slot_bytes
        buf = self.block.buf
        np.copyto(np.ndarray(a.shape, a.dtype, buffer=buf, offset=offset), a)
        np.copyto(np.ndarray(b.shape, b.dtype, buffer=buf, offset=offset + a.nbytes), b)
        return ("shm", self.block.name, offset, a.shape, a.dtype.str), slot

    def outcome(self, msg: tuple, slot: int | None) -> WorkerOutcome:
        """The :class:`WorkerOutcome` of a ``done`` reply (arrays copied out of ``slot``)."""
        _, _, error, meas, estimates, measure_s, _ = msg
        if type(meas) is _Packed:
            if meas.blob is None:  # in the pair's slot, after its record (_pack_into_slot)
                n = sum(meas.lengths)
                if slot is None or self.block is None or 8 * n > self.slot_bytes - SLOT_HEAD:
                    return WorkerOutcome(f"measurement failed: measurement worker {self.index} "
                                         "sent a reply without its arrays", worker=self.index)
                meas = meas.unpack(np.ndarray((n,), np.float64, buffer=self.block.buf,
                                              offset=slot * self.slot_bytes + SLOT_HEAD).copy())
            else:
                meas = meas.unpack()
        return WorkerOutcome(error, meas, estimates, self.index, measure_s)

    def slotted(self, job: OpenPair) -> tuple | None:
        """``job``'s reply as the worker wrote it into the pair's slot (``None``: not there)."""
        if job.slot is None or self.block is None:
            return None
        return _reply_from_slot(self.block.buf, job.slot * self.slot_bytes, self.slot_bytes,
                                job.ticket)

    def told(self, tickets: tuple[int, ...]) -> list[tuple]:
        """The replies a ``("slotted", tickets)`` message announces, read from their slots.

        A pair given up meanwhile is skipped; one whose slot holds no reply fails.
        """
        out = []
        for ticket in tickets:
            job = self.jobs.get(ticket)
            if job is not None:
                out.append(self.slotted(job) or (
                    "done", ticket, f"measurement failed: measurement worker {self.index} "
                    "said its reply was in the pair's slot; it was not", None, (), 0.0, None))
        return out

    def salvage(self) -> list[tuple]:
        """The replies in the slots of the pairs still open (a worker that died holding them)."""
        return [r for r in map(self.slotted, list(self.jobs.values())) if r is not None]

    def take(self, ticket: int) -> Any:
        """The open pair ``ticket``, no longer open (its slot free); ``None``: given up."""
        job = self.jobs.pop(ticket, None)
        if job is not None and job.slot is not None:
            self.free.append(job.slot)
        return job

    def drop_jobs(self) -> list[Any]:
        """The open pairs, in the order they were sent; none open after."""
        jobs, self.jobs = list(self.jobs.values()), {}
        return jobs

    def messages(self) -> tuple[list[tuple], str | None]:
        """The whole messages one read of the pipe brought, and why the worker is gone if it is.

        The messages are ``Connection.send``'s (a 4-byte length, or -1 and an 8-byte one, then
        the pickle): one ``os.read`` of all there is instead of ``poll`` (a new selector each
        call) and two reads per message; a message split over reads waits in ``rbuf``.
        """
        try:
            data = os.read(self.conn.fileno(), READ_BYTES)
        except BlockingIOError:
            return [], None
        except OSError:
            data = b""
        if not data:
            return [], self.reap()
        self.rbuf += data
        out = []
        for raw in _whole_messages(self.rbuf):
            msg, why = _unpickled(raw)
            if why is not None:
                return out, f"sent a reply that cannot be read ({why})"
            out.append(msg)
        return out, None

    def free_block(self) -> None:
        """Close and unlink the shared-memory block (the next pair makes a new one)."""
        if self.block is not None:
            try:
                self.block.close()
                self.block.unlink()
            except (OSError, BufferError):
                pass
            self.block = None
            self.slot_bytes = 0

    def spawn(self, ctx: Any, args: tuple, *, depth: int) -> None:
        """Start the worker's process (:func:`_worker_main` with the pipe's end and ``args``)."""
        parent, child = ctx.Pipe(duplex=True)
        proc = ctx.Process(target=_worker_main, args=(child, *args),
                           name=f"planer-measure-{self.index}", daemon=True)
        proc.start()
        child.close()
        self.process, self.conn, self.ready, self.jobs = proc, parent, False, {}
        self.rbuf, self.free = bytearray(), list(range(depth))
        self.started += 1

    def end(self, *, wait_s: float) -> None:
        """Close the pipe and end the process: waits ``wait_s`` for it to stop, then kills it."""
        if self.conn is not None:
            self.conn.close()
            self.conn = None
        proc, self.process = self.process, None
        if proc is not None:
            if wait_s > 0:
                proc.join(wait_s)
            if proc.is_alive():
                proc.kill()
            proc.join(0.5 if wait_s <= 0 else wait_s)

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
