"""The PLC's Modbus server in a process of its own, fed through shared memory.

Why a process: a server thread in the process that steps the machine shares its interpreter
lock; on a busy host the stepping thread is often descheduled *while holding it*, and every
Modbus answer then waits for the scheduler (measured: p99 18-65 ms, max 160 ms on a loaded
2-core host). A process that sleeps until a request arrives is woken at once by the scheduler and
answers in well under a millisecond whatever the stepping, rendering and spool writing do.

The discipline between the two sides:

* **registers, stepping side -> server**: a shared-memory block with a sequence lock. The
  stepping side (:meth:`PlcProcess.refresh`, once per PLC cycle) writes the encoded register
  words (the single map's span, then each served head's block:
  :meth:`~plant_sim.interfaces.register_image.RegisterImage.flat`) and the number of writes it
  has applied, between two increments of a sequence counter (odd while writing); the server
  copies the block when the counter is even and unchanged across the copy, so it always serves
  one consistent snapshot.
* **writes, server -> stepping side**: the server checks a write against the map and the current
  snapshot (exceptions 02/03 answered at once), serves the written value from then on, and sends
  the accepted values over a pipe; :meth:`PlcProcess.apply_writes` applies them to the machine in
  the order they were accepted, before the next step.
* **control**: ``up`` / ``down`` (listen, or stop and drop every client: the ``modbus_restart``
  fault) and ``exit`` over a second pipe, each answered; the server exits by itself when the
  stepping side goes away (pipe closed).

Request and refusal counts live in the shared block too (for the progress lines).
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import struct
import time
from collections.abc import Mapping
from multiprocessing.shared_memory import SharedMemory
from typing import Any

from plant_sim.interfaces.register_image import RegisterImage, apply, head_values, heads_served
from protocol.registers import RegisterMap

log = logging.getLogger(__name__)

_HEAD = struct.Struct("<QQQQ")  # seq, applied writes, requests, refused
START_TIMEOUT_S = 120.0
"""How long the stepping side waits for the server process to answer (a loaded host), s."""
READ_RETRY_S = 0.0001
"""Pause before reading the shared block again while the stepping side writes it, s."""


class _Block:
    """The shared register block: header and ``count`` big-endian words."""

    def __init__(self, buf: memoryview, count: int) -> None:
        self.buf = buf
        self.count = count
        self.words = struct.Struct(f">{count}H")

    @staticmethod
    def size(count: int) -> int:
        return _HEAD.size + 2 * count

    # stepping side
    def publish(self, words: list[int], applied: int) -> None:
        seq = struct.unpack_from("<Q", self.buf, 0)[0]
        struct.pack_into("<Q", self.buf, 0, seq + 1)  # odd: writing
        struct.pack_into("<Q", self.buf, 8, applied)
        self.words.pack_into(self.buf, _HEAD.size, *words)
        struct.pack_into("<Q", self.buf, 0, seq + 2)

    def counts(self) -> tuple[int, int]:
        _, _, requests, refused = _HEAD.unpack_from(self.buf, 0)
        return requests, refused

    # server side
    def seq(self) -> int:
        return struct.unpack_from("<Q", self.buf, 0)[0]

    def try_read(self) -> tuple[int, int, tuple[int, ...]] | None:
        """``(seq, applied, words)`` of one consistent snapshot, or ``None`` while written.

        The caller then serves the snapshot it has: it never waits for the stepping side.
        """
        seq = self.seq()
        if seq % 2:
            return None
        applied = struct.unpack_from("<Q", self.buf, 8)[0]
        words = self.words.unpack_from(self.buf, _HEAD.size)
        return (seq, applied, words) if self.seq() == seq else None

    def read(self) -> tuple[int, int, tuple[int, ...]]:
        """``(seq, applied, words)`` of one consistent snapshot; waits while it is written.

        Sleeping, not spinning: a real-time reader never keeps the writer off its core.
        """
        while True:
            snap = self.try_read()
            if snap is not None:
                return snap
            time.sleep(READ_RETRY_S)

    def set_counts(self, requests: int, refused: int) -> None:
        struct.pack_into("<QQ", self.buf, 16, requests, refused)


class _Published:
    """The machine as the server process first sees it: the snapshot decoded in ``image``.

    What the :class:`~plant_sim.interfaces.plc_server.PlcServer` reads when it is built (later
    snapshots reach it through ``load_words``); it never writes to it (its writes are
    queued to the stepping side).
    """

    def __init__(self, image: RegisterImage) -> None:
        self._image = image

    def register_values(self) -> dict[str, float | int]:
        return dict(self._image.values)

    def head_register_values(self, i: int) -> dict[str, float | int]:
        return dict(self._image.head_values[i])


def _snapshot_server(block: _Block, image: RegisterImage, rmap: RegisterMap, heads: int,
                     host: str, port: int, unit_id: int) -> tuple[Any, int]:
    """The server process's server over the snapshot published before it started.

    The block is read and decoded once (into ``image``); the server and that snapshot's
    sequence number are returned.
    """
    from plant_sim.interfaces.plc_server import PlcServer

    seq, _applied, words = block.read()
    image.load_flat(words)
    server = PlcServer(_Published(image), register_map=rmap, host=host, port=port,
                       unit_id=unit_id, queue_writes=True, heads=heads)
    return server, seq


def _serve(shm_name: str, rmap: RegisterMap, heads: int, host: str, port: int, unit_id: int,
           control: Any, writes: Any, realtime: bool) -> None:  # pragma: no cover - child
    """The server process: serve the shared snapshot; obey ``control``; send writes."""
    import signal

    from core.realtime import guard_realtime, raise_priority

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    priority = "normal (not asked)"
    if realtime:  # a real PLC does not stop answering because a PC is busy
        priority = raise_priority()
        if priority.startswith("SCHED_FIFO"):
            guard_realtime()
    logging.getLogger("asyncio").setLevel(logging.CRITICAL)
    shm = SharedMemory(name=shm_name)
    try:
        image = RegisterImage(rmap, heads)
        block = _Block(shm.buf, image.size)
        server, first = _snapshot_server(block, image, rmap, heads, host, port, unit_id)
        seen = [first]

        def sync() -> None:
            if block.seq() != seen[0]:
                # mid-write: serve the snapshot loaded before (one PLC cycle old, consistent)
                snap = block.try_read()
                if snap is not None:
                    seq, applied, words = snap
                    server.load_words(words, applied=applied)
                    seen[0] = seq

        def counted(write: Any) -> None:
            writes.send(write)

        server.before_request = sync
        server.on_queued = counted
        respond = server.respond

        def respond_and_count(unit: int, pdu: bytes) -> bytes:
            reply = respond(unit, pdu)
            block.set_counts(server.requests, server.refused)
            return reply

        server.respond = respond_and_count  # type: ignore[method-assign]
        asyncio.run(_control_loop(server, control, priority))
    finally:
        block = None  # type: ignore[assignment]
        shm.close()


async def _control_loop(server: Any, control: Any,
                        priority: str) -> None:  # pragma: no cover - child
    loop = asyncio.get_running_loop()
    done = asyncio.Event()
    queue: asyncio.Queue[Any] = asyncio.Queue()

    def readable() -> None:
        try:
            queue.put_nowait(control.recv())
        except (EOFError, OSError):  # the stepping side went away
            loop.remove_reader(control.fileno())
            queue.put_nowait("exit")

    loop.add_reader(control.fileno(), readable)
    while not done.is_set():
        cmd = await queue.get()
        if cmd == "exit":
            await server.stop()
            done.set()
            _reply(control, ("ok", server.port))
        elif cmd == "up":
            try:
                host, port = await server.start()
            except OSError as exc:  # FieldbusError
                _reply(control, ("error", str(exc)))
            else:
                _reply(control, ("ok", port))
        elif cmd == "priority":
            _reply(control, ("ok", priority))
        elif cmd == "down":
            await server.stop()
            _reply(control, ("ok", server.port))


def _reply(control: Any, msg: tuple[str, Any]) -> None:  # pragma: no cover - child
    try:
        control.send(msg)
    except (OSError, EOFError):
        pass


class PlcProcess:
    """The PLC's Modbus TCP server in its own process; the machine stays here.

    Same surface as :class:`~plant_sim.interfaces.plc_server.PlcServer` for the runner and the
    driver:
    :meth:`refresh` (publish), :meth:`apply_writes` (queued writes, in order), async
    :meth:`start` / :meth:`stop`, :meth:`set_up`, :attr:`values`, :attr:`requests`,
    :attr:`refused`; plus :meth:`close` (ends the process).

    Parameters
    ----------
    machine : PlcMachine
        The machine model.
    register_map : RegisterMap, optional
        Default: ``config/registers.toml``.
    host : str
        Address to bind (default loopback only).
    port : int
        TCP port; 0 picks a free one (kept across restarts).
    unit_id : int, optional
        Modbus unit id served; default the map's.
    realtime : bool
        The server process asks for real-time scheduling (``SCHED_FIFO``, else a raised nice
        value: :func:`core.realtime.raise_priority`); :attr:`priority` says what it got.

    Attributes
    ----------
    priority : str or None
        What the server process was granted (``"SCHED_FIFO 10"``, ``"nice -10"``,
        ``"normal (...)"`` with the reason), once it listens.
    write_errors : int
        Accepted writes the machine refused when they were applied.
    """

    queue_writes = True

    def __init__(
        self,
        machine: Any,
        *,
        register_map: RegisterMap | None = None,
        host: str = "127.0.0.1",
        port: int = 502,
        unit_id: int | None = None,
        realtime: bool = False,
    ) -> None:
        if not 0 <= int(port) <= 65535:
            raise ValueError(f"port must be in 0..65535, got {port!r}")
        self.machine = machine
        self.rmap = register_map if register_map is not None else RegisterMap.load()
        self.host = host
        self.port = int(port)
        self.unit_id = self.rmap.unit_id if unit_id is None else int(unit_id)
        self.heads = heads_served(machine, self.rmap)
        """Head blocks served (:func:`~plant_sim.interfaces.register_image.heads_served`)."""
        self._image = RegisterImage(self.rmap, self.heads)
        self._count = self._image.size
        self._values: dict[str, float | int] = {}
        self._applied = 0
        self._shm: SharedMemory | None = None
        self._block: _Block | None = None
        self._proc: Any = None
        self._control: Any = None
        self._writes: Any = None
        self._running = False
        self.write_errors = 0
        self.realtime = bool(realtime)
        self.priority: str | None = None

    # ------------------------------------------------------------------ the process
    def _launch(self) -> None:
        if self._proc is not None:
            return
        ctx = multiprocessing.get_context("spawn")  # no fork of a process with threads
        self._shm = SharedMemory(create=True, size=_Block.size(self._count))
        self._block = _Block(self._shm.buf, self._count)
        self.refresh()
        control, child_control = ctx.Pipe(duplex=True)
        writes_in, writes_out = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(
            target=_serve, name="plc-modbus", daemon=True,
            args=(self._shm.name, self.rmap, self.heads, self.host, self.port, self.unit_id,
                  child_control, writes_out, self.realtime),
        )
        self._proc.start()
        child_control.close()
        writes_out.close()
        self._control, self._writes = control, writes_in

    def _ask(self, cmd: str) -> Any:
        from core.errors import FieldbusError

        assert self._control is not None
        self._control.send(cmd)
        if not self._control.poll(START_TIMEOUT_S):
            raise FieldbusError(f"the Modbus server process did not answer {cmd!r}")
        status, arg = self._control.recv()
        if status != "ok":
            raise FieldbusError(arg)
        return arg

    def set_up(self, up: bool) -> None:
        """Listen (``True``) or stop listening and drop every client (``False``); synchronous.

        Raises
        ------
        FieldbusError
            The address cannot be bound.
        """
        if up:
            self._launch()
            self.port = int(self._ask("up"))
            if self.priority is None:
                self.priority = str(self._ask("priority"))
            self._running = True
            log.info("Modbus server listening on %s:%d", self.host, self.port)
        elif self._proc is not None and self._running:
            self._ask("down")
            self._running = False

    async def start(self) -> tuple[str, int]:
        """Start the process (once) and listen; returns ``(host, port)`` bound."""
        await asyncio.get_running_loop().run_in_executor(None, self.set_up, True)
        return self.host, self.port

    async def stop(self) -> None:
        """Stop listening and drop every client (idempotent; the process stays)."""
        self.set_up(False)

    def close(self) -> None:
        """End the server process and free the shared block (idempotent)."""
        proc, self._proc = self._proc, None
        if proc is not None:
            try:
                self._control.send("exit")
                self._control.poll(10.0)
            except (OSError, EOFError):
                pass
            proc.join(timeout=10)
            if proc.is_alive():
                proc.kill()
                proc.join()
            self._control.close()
            self._writes.close()
        self._running = False
        if self._shm is not None:
            self._block = None
            self._shm.close()
            self._shm.unlink()
            self._shm = None

    # ------------------------------------------------------------------ stepping side
    @property
    def running(self) -> bool:
        """Whether the server listens."""
        return self._running

    @property
    def values(self) -> Mapping[str, float | int]:
        """Register values as last published."""
        return self._values

    @property
    def requests(self) -> int:
        """Requests answered so far."""
        return self._block.counts()[0] if self._block is not None else 0

    @property
    def refused(self) -> int:
        """Requests answered with an exception so far."""
        return self._block.counts()[1] if self._block is not None else 0

    def refresh(self) -> None:
        """Publish the machine's register values and head blocks (once per PLC cycle)."""
        values = dict(self.machine.register_values())
        self._values = values
        self._image.load(values, head_values(self.machine, self.heads))
        if self._block is not None:
            self._block.publish(self._image.flat(), self._applied)

    def apply_writes(self) -> int:
        """Apply the writes the server accepted to the machine, in order; returns how many."""
        n = 0
        while self._writes is not None and self._writes.poll():
            try:
                write = self._writes.recv()
            except EOFError:
                break
            try:
                apply(self.machine, write)
            except ValueError as exc:
                self.write_errors += 1
                log.warning("Modbus write not applied: %s", exc)
            self._applied += 1
            n += 1
        return n
