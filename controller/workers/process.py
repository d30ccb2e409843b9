"""The measurement worker process and the messages it exchanges with its pool.

:class:`controller.workers.pool.MeasureWorkerPool` starts :func:`_worker_main` in each worker
process. A job message carries the pair's place in the pool's shared memory (or the images),
its numbers, the machine's facts and the board's calibrator as its fields' values
(:func:`_cal_state` / :func:`_cal_from`: the class and field names pickled once); the reply
carries the ``Measurement`` with its float arrays (:func:`_pack`, :meth:`_Packed.unpack`; its
class's and fields' names pickled once, :meth:`_Packed.__reduce__`) and the calibration
estimates the pair contributed (:class:`_RecordingCalibrator`). The worker
reads all that has come at once (:class:`_Inbox`: it knows how many jobs wait behind the pair
it finished). It writes each reply into the pair's slot, whose images are done with (layout:
a record of :data:`SLOT_HEAD` bytes, the float arrays, the pickled reply:
:func:`_pack_into_slot`, :func:`_reply_into_slot`, read back by :func:`_reply_from_slot`), and
tells the service which slots hold replies in ``("slotted", tickets)`` messages, several in one
while it is saturated (:class:`_Replies`). Messages go as one write each (:func:`_send_whole`)
and are cut out of what the other side reads with :func:`_whole_messages`.
"""

from __future__ import annotations

import dataclasses
import math
import os
import pickle
import signal
import struct
import time
from collections import deque
from multiprocessing.reduction import ForkingPickler
from typing import Any, NamedTuple

import numpy as np

from controller.service.events import exc_name
from controller.service.latency import IdleCollector
from controller.service.measurement import VISION_ERRORS, MeasurementStage, failure_reason
from protocol.frames import Frame

_HEADER = struct.Struct("!i")  # Connection.send's length header ...
_LONG_HEADER = struct.Struct("!Q")  # ... and its long form after -1


class RollChain(NamedTuple):
    """The roll directive of a board's pairs handed out before its first confident roll came.

    The service cannot know yet whether such a pair searches (the pairs before it may find no
    confident roll), so all of them go to one worker, in sequence order, and that worker
    decides as the board's calibrator in process would: with the calibrator of the chain's
    first pair (``start``), kept under ``key`` (:class:`controller.workers.pool._RollPlan`).
    """

    key: int
    start: bool


KEEP_CHAINS = 32
"""Roll chains a worker keeps (a chain lives only until its first confident roll reached the
service: a few per head sharing the workers)."""


def _chain_keeper(chains: dict[int, Any], chain: RollChain, calibrator: Any) -> Any:
    """The calibrator that decides the roll of ``chain``'s pairs in this worker.

    The chain's first pair's calibrator (kept); a chain this worker does not know (it cannot
    happen with the pool's pinning) starts anew with the pair's own: a search, never less.
    """
    keeper = None if chain.start else chains.get(chain.key)
    if keeper is None:
        keeper = chains[chain.key] = calibrator
        while len(chains) > KEEP_CHAINS:
            del chains[next(iter(chains))]  # the oldest
    return keeper


class _RecordingCalibrator:
    """The board's calibrator as the worker got it, noting each estimate folded in.

    ``roll`` is the service's word on the camera's roll for this pair
    (:class:`controller.workers.pool._RollPlan`): ``None`` leaves it to the calibrator,
    ``()`` has the pair search for it, ``(roll_deg, confidence)`` has it use that, a
    :class:`RollChain` leaves it to ``keeper`` (the chain's calibrator in this worker); a
    search's confident result is noted in :attr:`found`.
    """

    def __init__(self, calibrator: Any, roll: tuple[Any, ...] | None = None,
                 keeper: Any = None) -> None:
        self.calibrator = calibrator
        self.estimates: list[Any] = []
        self.roll = roll
        self.keeper = calibrator if roll is None else keeper
        self.found: tuple[float, float] | None = None

    def update(self, estimate: Any) -> Any:
        self.estimates.append(estimate)
        return self.calibrator.update(estimate)

    def known_roll(self) -> tuple[float, float] | None:
        if self.keeper is not None:
            return self.keeper.known_roll()
        return (self.roll[0], self.roll[1]) if self.roll else None

    def note_roll(self, roll_deg: float, confidence: float, *, min_confidence: float) -> None:
        if math.isfinite(confidence) and confidence >= min_confidence:
            self.found = (float(roll_deg), float(confidence))
        if self.keeper is not None:
            self.keeper.note_roll(roll_deg, confidence, min_confidence=min_confidence)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.calibrator, name)


class _Packed(NamedTuple):
    """A dataclass measurement with its 1-D float arrays in one (:func:`_pack`)."""

    cls: type
    state: dict[str, Any]  # the instance's fields, the packed arrays as None
    names: tuple[str, ...]
    lengths: tuple[int, ...]
    blob: np.ndarray | None  # None: in the pair's slot (:func:`_pack_into_slot`)

    def unpack(self, blob: np.ndarray | None = None) -> Any:
        """The measurement as pickle would rebuild it (no ``__init__``), arrays as views.

        ``blob``: the arrays when they came apart (read from the pair's slot), else
        :attr:`blob`.
        """
        if blob is None:
            blob = self.blob
        obj = self.cls.__new__(self.cls)
        d = obj.__dict__
        d.update(self.state)
        start = 0
        for name, n in zip(self.names, self.lengths, strict=True):
            d[name] = blob[start:start + n]
            start += n
        return obj

    def __reduce__(self) -> tuple[Any, tuple]:
        """Pickled as its class's and fields' names once (``schema``) and its fields' values.

        The names of a measurement's 26 fields, pickled and read back with every reply, were
        a third of the reply's pickle on each side; the schema is the same bytes each time
        (:func:`_packed_from` reads it once per process).
        """
        key = (self.cls, tuple(self.state), self.names)
        schema = _PACKED_SCHEMAS.get(key)
        if schema is None:
            schema = _PACKED_SCHEMAS[key] = pickle.dumps(key)
        return _packed_from, (schema, tuple(self.state.values()), self.lengths, self.blob)


_PACKED_SCHEMAS: dict[tuple, bytes] = {}  # the worker's side: (class, fields, arrays) -> pickle
_PACKED_BUILT: dict[bytes, tuple] = {}  # the service's side: that pickle -> its tuple


def _packed_from(schema: bytes, values: tuple, lengths: tuple[int, ...],
                 blob: np.ndarray | None) -> _Packed:
    """The :class:`_Packed` a pickled one stands for (:meth:`_Packed.__reduce__`)."""
    built = _PACKED_BUILT.get(schema)
    if built is None:
        built = _PACKED_BUILT[schema] = pickle.loads(schema)
    cls, names, arrays = built
    return _Packed(cls, dict(zip(names, values, strict=True)), arrays, lengths, blob)


_F64 = np.dtype(np.float64)
_PACKABLE: dict[type, bool] = {}  # a class's answer to _packable_state's test, once


def _packable_state(meas: Any) -> dict[str, Any] | None:
    """``meas.__dict__`` when ``meas`` is a plain dataclass pickled the default way, else ``None``.

    The class's part of the test is made once per class (:data:`_PACKABLE`).
    """
    cls = type(meas)
    ok = _PACKABLE.get(cls)
    if ok is None:
        ok = _PACKABLE[cls] = (dataclasses.is_dataclass(cls)
                               and not hasattr(cls, "__setstate__")
                               and cls.__reduce_ex__ is object.__reduce_ex__
                               and cls.__reduce__ is object.__reduce__)
    return getattr(meas, "__dict__", None) if ok else None


def _float_arrays(state: dict[str, Any]) -> list[str]:
    """The fields of ``state`` holding a 1-D float64 array, in the fields' order."""
    f64 = _F64
    return [k for k, v in state.items()
            if type(v) is np.ndarray and v.ndim == 1 and (v.dtype is f64 or v.dtype == f64)]


def _packable_arrays(meas: Any) -> tuple[dict[str, Any], list[str]] | None:
    """``(fields, names of its 1-D float64 arrays)`` of a measurement worth packing, else None.

    Worth packing: a plain dataclass (:func:`_packable_state`) with two such arrays or more.
    """
    state = _packable_state(meas)
    if state is None:
        return None
    names = _float_arrays(state)
    return None if len(names) < 2 else (state, names)


def _pack(meas: Any) -> Any:
    """A plain dataclass measurement with its 1-D float64 arrays concatenated (else as is).

    Pickling eight small arrays one by one cost a worker 20-50 us per pair (the pickler's
    path per array, cold after the measurement); one array and a dict of the rest cost a
    third of that, and the service rebuilds the same fields (:meth:`_Packed.unpack`).
    """
    found = _packable_arrays(meas)
    if found is None:
        return meas
    state, names = found
    arrays = [state[k] for k in names]
    rest = dict(state)
    for k in names:
        rest[k] = None  # keeps the fields' order
    return _Packed(type(meas), rest, tuple(names), tuple(a.size for a in arrays),
                   np.concatenate(arrays))


def _pack_into_slot(meas: Any, buf: Any, offset: int, room: int) -> Any:
    """The plain measurement, its float arrays written into the pair's slot (``blob=None``).

    The slot's images are no longer needed once measured: the service copies the arrays out
    of the slot (:meth:`controller.workers.link.WorkerLink.outcome`) instead of both sides
    pickling, writing and reading them (16 KB at 659 px a row: 15-40 us a pair over both
    processes). Each array is written straight into the slot (no concatenated copy); when
    they do not fit, :func:`_pack` (they go with the reply); not a plain dataclass: as is.
    """
    found = _packable_arrays(meas)
    if found is None:
        return meas
    state, names = found
    lengths = tuple(state[k].size for k in names)
    if 8 * sum(lengths) > room:
        return _pack(meas)  # the arrays go with the reply
    rest = dict(state)
    start = offset
    for k, n in zip(names, lengths, strict=True):
        np.ndarray((n,), np.float64, buffer=buf, offset=start)[:] = state[k]
        start += 8 * n
        rest[k] = None  # keeps the fields' order
    return _Packed(type(meas), rest, tuple(names), lengths, None)


SLOT_HEAD = 64
"""Bytes at the start of a pair's slot for its reply's record (:func:`_reply_into_slot`); the
reply's float arrays follow it, then the reply itself."""
SLOT_MAGIC = 0x31307265_6E616C70  # b"planer01" little-endian: a record, not image bytes
_SLOT_MAGIC = struct.Struct("=Q")
_SLOT_PLACE = struct.Struct("=QQQ")  # ticket, where the reply starts, its length
_SLOT_RECORD = struct.Struct("=QQQQ")


def _reply_into_slot(reply: tuple, buf: Any, offset: int, room: int) -> bool:
    """Write a ``done`` reply into its pair's slot (after its arrays); whether it fitted.

    Once written the reply outlives the worker: the service reads it from the slot when told
    (a ``("slotted", tickets)`` message) or, when the worker died holding it, on its own
    (:func:`_reply_from_slot`). The record's magic is written last.
    """
    meas = reply[3]
    used = 8 * sum(meas.lengths) if type(meas) is _Packed and meas.blob is None else 0
    at = SLOT_HEAD + -(-used // 8) * 8
    body = _dumps(reply)
    n = len(body)
    if at + n > room:
        return False
    buf[offset + at:offset + at + n] = body
    _SLOT_PLACE.pack_into(buf, offset + 8, reply[1], at, n)
    _SLOT_MAGIC.pack_into(buf, offset, SLOT_MAGIC)
    return True


def _dumps(obj: Any) -> bytes:
    """``ForkingPickler.dumps(obj)``'s bytes by the C pickler (a third faster on a reply).

    A reply or a job holds numbers, strings, tuples, arrays and dataclasses: none of the
    types ``ForkingPickler`` reduces its own way (connections, sockets: plain pickle would not
    refuse them, so they must never be put in one), so the bytes are the same; anything
    pickle itself refuses goes through ``ForkingPickler``.
    """
    try:
        return pickle.dumps(obj)
    except (pickle.PicklingError, TypeError, AttributeError):
        return bytes(ForkingPickler.dumps(obj))


def _reply_from_slot(buf: Any, offset: int, room: int, ticket: int) -> tuple | None:
    """The reply for pair ``ticket`` written into its slot, or ``None`` when there is none.

    ``None`` also for a record of another pair, one that does not fit ``room`` and one that
    cannot be read (a worker killed while writing it).
    """
    if room < SLOT_HEAD:
        return None
    magic, got, at, n = _SLOT_RECORD.unpack_from(buf, offset)
    if magic != SLOT_MAGIC or got != ticket or at < SLOT_HEAD or at + n > room:
        return None
    reply, _ = _unpickled(buf[offset + at:offset + at + n])
    return reply if type(reply) is tuple and reply[:2] == ("done", ticket) else None


def _unpickled(raw: Any) -> tuple[Any, str | None]:
    """``(pickle.loads(raw), None)``, or ``(None, why)`` when it cannot be read."""
    try:
        return pickle.loads(raw), None
    except Exception as exc:  # noqa: BLE001 - unpickling raises anything
        return None, f"{exc_name(exc)}: {exc}"


_PLAIN = (float, int, bool, str, type(None))


_PLAIN_CLASSES: dict[type, bool] = {}  # a class's part of _cal_state's test, once
_SCHEMAS: dict[tuple, bytes] = {}  # the service's side: (class, fields, arrays) -> its pickle
_BUILT: dict[bytes, tuple] = {}  # the worker's side: that pickle -> (class, fields, arrays)


def _cal_state(cal: Any) -> tuple[Any, tuple | None]:
    """A calibrator as ``(schema, values)`` when it is a plain object of numbers (else as is).

    Pickling a ``SelfCalibrator`` (its object, a 2-element array) cost the service 7-8 us per
    pair, most of the job's pickle; its fields' values as a tuple and its class and field names
    pickled once (``schema``: the same bytes each time) cost a third of it. Plain: the fields in
    ``__dict__``, pickled the default way, each a number, string, ``None``, a tuple of those or
    a 1-D float64 array (sent as a tuple). Anything else: ``(cal, None)``.
    """
    cls = type(cal)
    ok = _PLAIN_CLASSES.get(cls)
    if ok is None:
        ok = _PLAIN_CLASSES[cls] = not (
            hasattr(cls, "__setstate__") or hasattr(cls, "__slots__")
            or cls.__reduce_ex__ is not object.__reduce_ex__
            or cls.__reduce__ is not object.__reduce__)
    state = getattr(cal, "__dict__", None) if ok else None
    if state is None:
        return cal, None
    values: list[Any] = []
    arrays: list[int] = []
    for v in state.values():
        t = type(v)
        if t is np.ndarray and v.ndim == 1 and (v.dtype is _F64 or v.dtype == _F64):
            arrays.append(len(values))
            v = tuple(v.tolist())
        elif not (t in _PLAIN or (t is tuple and all(type(x) in _PLAIN for x in v))):
            return cal, None
        values.append(v)
    key = (cls, tuple(state), tuple(arrays))
    schema = _SCHEMAS.get(key)
    if schema is None:
        schema = _SCHEMAS[key] = pickle.dumps(key)
    return schema, tuple(values)


def _cal_from(schema: Any, values: tuple | None) -> Any:
    """The worker's calibrator from :func:`_cal_state` (a new object, no ``__init__``)."""
    if values is None:
        return schema
    built = _BUILT.get(schema)
    if built is None:
        built = _BUILT[schema] = pickle.loads(schema)
    cls, names, arrays = built
    obj = cls.__new__(cls)
    vals = list(values)
    for i in arrays:
        vals[i] = np.array(vals[i], dtype=np.float64)
    obj.__dict__.update(zip(names, vals, strict=True))
    return obj


# ---------------------------------------------------------------------------------------------
# the worker process


HOLD_BEHIND = 2
"""Jobs waiting behind a finished pair for the worker to count as saturated (and hold its
reply, :class:`_Replies`)."""
READ_BYTES = 1 << 16
"""Most bytes one read of a pool's pipe takes (either end). Not more: ``os.read`` allocates
what it may take before the read (1 MB: 10-12 us a read on this machine, 64 KB: 1-2 us), and a
longer message comes in several reads."""


def _framed(obj: Any) -> bytes:
    """``obj`` as ``Connection.send`` frames it (a 4-byte length, then the pickle).

    The pickle is :func:`_dumps`'s: ``ForkingPickler``'s bytes by the C pickler.
    """
    body = _dumps(obj)
    if len(body) > 0x7FFFFFFF:
        return _HEADER.pack(-1) + _LONG_HEADER.pack(len(body)) + body
    return _HEADER.pack(len(body)) + body


def _send_whole(conn: Any, obj: Any) -> None:
    """``conn.send(obj)`` as one write of header and body (what ``conn.recv`` reads).

    ``Connection.send`` writes a message over 16 KB as two writes (header, then body); a
    worker descheduled between them (normal priority on a busy host) keeps the service's
    real-time bus thread waiting in ``recv`` for the body: 9-40 ms per pair measured under six
    CPU hogs (docs/reliability.md). One write of both lands at once.
    """
    view = memoryview(_framed(obj))
    fd = conn.fileno()
    while view:
        view = view[os.write(fd, view):]


class _Inbox:
    """The pool's messages to this worker, read as they come (all there is in one read).

    The worker knows how many jobs wait behind the one it finished without blocking
    (:meth:`poll`), which :class:`_Replies` uses to hold a reply while it is saturated.
    """

    def __init__(self, conn: Any) -> None:
        import select

        self.fd = conn.fileno()
        self.pending: deque[Any] = deque()
        self._buf = bytearray()
        self._poller = select.poll()
        self._poller.register(self.fd, select.POLLIN)

    def _read(self, timeout_ms: int | None) -> None:
        if not self._poller.poll(timeout_ms):
            return
        data = os.read(self.fd, READ_BYTES)
        if not data:
            raise EOFError("the service closed the pipe")
        self._buf += data
        self.pending.extend(pickle.loads(raw) for raw in _whole_messages(self._buf))

    def poll(self) -> None:
        """Take what has come, without waiting."""
        self._read(0)

    def next(self) -> Any:
        """The next message (waits for one when none is here)."""
        while not self.pending:
            self._read(None)
        return self.pending.popleft()


class _Replies:
    """The worker's replies, held while it is saturated and announced together.

    A ``done`` reply is written into its pair's slot at once (:func:`_reply_into_slot`: a
    worker that dies after it loses no result); the service is told in a ``("slotted",
    tickets)`` message, held while at least :data:`HOLD_BEHIND` jobs wait behind the pair and
    fewer than ``hold`` are held: a saturated worker wakes the service once per ``hold`` pairs
    (one write) instead of once per pair. Each wake-up takes a core from a measuring worker
    when the workers use all cores, and costs that worker its caches (2 workers on 2 cores:
    :data:`controller.workers.pool.DEFAULT_DEPTH`). A worker with fewer jobs waiting (the
    service at its pace: the latency path) announces every reply as it is made. A reply
    without a slot (the images came through the pipe) goes through the pipe, at once.

    Parameters
    ----------
    conn : multiprocessing.connection.Connection
        The worker's end of its pipe.
    hold : int
        Most replies held (1: none held).
    """

    def __init__(self, conn: Any, *, hold: int = 1) -> None:
        self.conn = conn
        self.hold = max(1, int(hold))
        self.held: list[int] = []  # tickets whose replies are in their slots, not yet told

    def add(self, reply: tuple, *, waiting: int,
            slot: tuple[Any, int, int] | None = None) -> None:
        """Give the service ``reply``, now or with the next ones.

        Parameters
        ----------
        reply : tuple
            The reply (:func:`_run_job`).
        waiting : int
            Jobs here behind its pair.
        slot : tuple, optional
            ``(buffer, offset, room)`` of the pair's slot.
        """
        if reply[0] == "done" and slot is not None and _reply_into_slot(reply, *slot):
            self.held.append(reply[1])
            if waiting < HOLD_BEHIND or len(self.held) >= self.hold:
                self.flush()
            return
        self.flush()
        _send_whole(self.conn, reply)

    def flush(self) -> None:
        """Tell the service about the held replies (one write)."""
        if self.held:
            tickets = tuple(self.held)
            self.held.clear()
            _send_whole(self.conn, ("slotted", tickets))


KEEP_FACTS = 8
"""Machine's facts (cutting radius, knives) a worker keeps a measurer set up for at once: the
heads of a moulder share the workers, each with its own facts; one stage per facts means a pair
of one head never throws away another head's set-up (20-60 ms to build again)."""


class _Stages:
    """The worker's measurement stages, one per machine's facts (the newest used kept).

    A :class:`MeasurementStage` keeps one measurer per image shape, built again when the facts
    change: right for one machine, a rebuild on every pair when the heads of a moulder (each
    with its own knives and radius) take turns. Here each factory (each head's rig) and facts'
    key has its own stage, at most :data:`KEEP_FACTS` (the one used longest ago goes).
    """

    def __init__(self, factory: Any, keep: int = KEEP_FACTS) -> None:
        self.factories: dict[int, Any] = {0: factory}
        """The measurer factories by the number the pool gives them (0: the pool's own)."""
        self.keep = max(1, int(keep))
        self._stages: dict[Any, MeasurementStage] = {}

    def add_factory(self, index: int, factory: Any) -> None:
        """Another service's factory (``("factory", index, factory)`` from the pool)."""
        self.factories[int(index)] = factory
        for key in [k for k in self._stages if k[0] == index]:  # a factory replaced
            del self._stages[key]

    def stage(self, facts: Any, factory: int = 0) -> MeasurementStage:
        """The stage of factory ``factory`` for ``facts`` (``None``: without facts).

        Raises
        ------
        LookupError
            No factory of that number was given (a bug of the pool: the service is told).
        """
        if factory not in self.factories:
            raise LookupError(f"no measurer factory {factory} in this worker")
        key = (factory, getattr(facts, "key", None) if facts is not None else None)
        stage = self._stages.pop(key, None)
        if stage is None:
            stage = MeasurementStage(None, self.factories[factory], threaded=False)
            while len(self._stages) >= self.keep:
                del self._stages[next(iter(self._stages))]  # used longest ago
        self._stages[key] = stage  # the newest used last
        return stage

    def __len__(self) -> int:
        return len(self._stages)


def _worker_main(conn: Any, factory: Any, shape: tuple[int, int] | None, index: int,
                 threads: int = 1, nice: int | None = None, hold: int = 1) -> None:
    """A worker: set up once, then measure the pairs the pipe brings until told to stop.

    ``hold``: most replies held while the worker is saturated (:class:`_Replies`).
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the service's to handle
    if nice is not None:
        from core.realtime import lower_priority

        lower_priority(nice)
    import gc

    import cv2

    cv2.setNumThreads(threads)  # the cores shared out: the pool spreads the pairs over them
    stages = _Stages(factory)
    if shape is not None:
        try:  # set-up once: imports, undistortion maps, FFT plans
            stages.stage(None).measurer(shape)
        except VISION_ERRORS:
            pass  # the first pair says why, as a failed measurement
    gc.collect()
    gc.freeze()  # the set-up's objects never need collecting
    collector = IdleCollector().install()  # the collections after a reply, not inside a pair
    blocks: dict[str, Any] = {}
    chains: dict[int, Any] = {}  # the roll chains' calibrators (RollChain)
    conn.send(("ready", index, os.getpid()))
    inbox, replies = _Inbox(conn), _Replies(conn, hold=hold)
    try:
        while True:
            if not inbox.pending:
                replies.flush()  # about to wait: nothing stays held
            try:
                msg = inbox.next()
            except (EOFError, OSError):  # the service is gone
                break
            if msg is None:
                break
            if msg[0] == "factory":
                stages.add_factory(msg[1], msg[2])
                continue
            if msg[0] == "prepare":
                try:
                    stages.stage(msg[2], msg[3]).measurer(msg[1], msg[2])
                except (*VISION_ERRORS, LookupError):
                    pass
                continue
            try:  # a job: its factory's number last
                reply, slot = _run_job(stages.stage(msg[6], msg[-1]), blocks, msg[:-1],
                                       chains)
            except BaseException as exc:  # a bug: told to the service, then ends with it
                replies.flush()
                _send_whole(conn, ("fault", msg[1], f"{exc_name(exc)}: {exc}"))
                raise
            inbox.poll()
            replies.add(reply, waiting=len(inbox.pending), slot=slot)
            collector.collect_due()
        replies.flush()
    except (BrokenPipeError, ConnectionResetError):  # the service is gone
        pass
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


def _run_job(stage: MeasurementStage, blocks: dict[str, Any], msg: tuple,
             chains: dict[int, Any]) -> tuple[tuple, tuple[Any, int, int] | None]:
    """Measure one pair: the reply for the service, and the pair's slot (``None``: none).

    ``chains``: the worker's roll chains' calibrators (:class:`RollChain`).
    """
    (_, ticket, where, counts_a, counts_b, speed_mm_s, facts, cal, cal_values, roll) = msg
    calibrator = _cal_from(cal, cal_values)
    buf, offset, nbytes = None, 0, 0
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
        keeper = None
        if type(roll) is RollChain:
            keeper = _chain_keeper(chains, roll, calibrator)
        recorder = _RecordingCalibrator(calibrator, roll, keeper)
        kwargs["calibrator"] = recorder
    slot = None if buf is None else (buf, offset, 2 * nbytes)
    t0 = time.perf_counter()
    try:
        meas = stage.measure_now(frame, facts, kwargs)
    except VISION_ERRORS as exc:
        found = recorder.found if recorder is not None else None
        return ("done", ticket, failure_reason(exc), None, (), time.perf_counter() - t0,
                found), slot
    finally:
        del image_a, image_b, frame  # no view of the slot outlives the job
    if buf is not None:  # the slot's images are done with: the arrays go back in it
        packed = _pack_into_slot(meas, buf, offset + SLOT_HEAD, 2 * nbytes - SLOT_HEAD)
    else:
        packed = _pack(meas)
    if recorder is None:
        return ("done", ticket, None, packed, (), time.perf_counter() - t0, None), slot
    return ("done", ticket, None, packed, tuple(recorder.estimates),
            time.perf_counter() - t0, recorder.found), slot


# ---------------------------------------------------------------------------------------------
# the service's side


def _whole_messages(buf: bytearray) -> list[bytes]:
    """Take the whole ``Connection.send`` messages off the front of ``buf`` (in place).

    Each is a 4-byte length (or -1 and an 8-byte one) and that many bytes; a message not yet
    whole stays in ``buf`` for the next read.
    """
    pos, end = 0, len(buf)
    whole: list[bytes] = []
    while end - pos >= 4:
        (n,) = _HEADER.unpack_from(buf, pos)
        head = 4
        if n == -1:
            if end - pos < 12:
                break
            (n,) = _LONG_HEADER.unpack_from(buf, pos + 4)
            head = 12
        if end - pos - head < n:
            break
        whole.append(bytes(buf[pos + head:pos + head + n]))
        pos += head + n
    del buf[:pos]
    return whole
