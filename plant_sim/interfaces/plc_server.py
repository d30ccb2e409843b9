"""The PLC's Modbus TCP server: the simulated machine's registers, as a PLC serves them.

The holding registers mirror ``machine.register_values()`` (the single map) and
``machine.head_register_values(i)`` (head ``i``'s block, for the heads the machine has: a single
``Machine`` serves block 0, a ``Moulder`` one per head; blocks beyond answer exception 02) as of
the last :meth:`PlcServer.refresh` (the machine's stepping calls it every PLC cycle). A write of
``spindle_setpoint_rpm`` in block ``i`` becomes ``machine.set_spindle_setpoint(i, rpm)``, checked
against that head's ``spindle_rpm_min..spindle_rpm_max`` (exception 03 outside). The server
speaks Modbus TCP itself (asyncio streams, no Modbus library): like a PLC it offers only what the
register map offers (``docs/register_map.md``) and says nothing about its software.

* Function codes 3 (read), 6 (write one), 16 (write several) and 23 (read/write) are served
  (those of them the map's ``function_codes`` lists); every other function code answers
  exception 01 (ILLEGAL FUNCTION).
* A quantity outside the spec's range (read 1..125, write 1..123, 23: 1..125 / 1..121), a byte
  count that does not match it or a PDU of the wrong length: exception 03 (ILLEGAL DATA VALUE).
* A read outside the map (or across the single map and a block, or into a block not served,
  or, unless the map's ``[heads] read_across`` says so, across two blocks), a write to a
  read-only register, to a gap or to half of a 32-bit register: exception 02 (ILLEGAL DATA
  ADDRESS).
* A value outside the register's limits (or one the machine refuses): exception 03, never clamped.
* Another unit id than the map's: exception 0B (gateway target failed to respond).
* A PDU longer than Modbus TCP's 253 bytes (an ADU over 260) is exception 03 when it is a
  write-multiple (16 or 23) no longer than its one-byte byte count can state (16: up to 261
  bytes, 23: up to 265; a write of 124..127 registers): the PDU is read whole and refused, so
  the client learns why and the stream stays in step.
* A header that is not Modbus TCP (protocol id not 0, length outside 2..254, or longer for
  anything but such a write-multiple) closes that connection; the server and its other clients
  go on.

Accepted writes go through the register map's one dispatch
(:func:`protocol.registers.apply_writes`). Threads: the server may run on its own asyncio loop
in another thread than the one stepping the machine (``queue_writes=True``, see
:mod:`plant_sim.interfaces.thread`). Then requests only read the published register snapshot
(swapped
under a lock by :meth:`PlcServer.refresh`) and accepted writes are queued; the stepping thread
applies them, in the order received, with :meth:`PlcServer.apply_writes`. Until then the
snapshot already shows the written values.
"""

from __future__ import annotations

import asyncio
import logging
import struct
import threading
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol

from plant_sim.interfaces.register_image import (
    HeadWrite,
    RegisterImage,
    apply,
    head_values,
    heads_served,
)
from protocol.registers import (
    RegisterAccessError,
    RegisterMap,
    RegisterRangeError,
)

log = logging.getLogger(__name__)

FUNCTION_CODES = frozenset({3, 6, 16, 23})
"""The function codes the server can serve; it offers those of the map's ``function_codes``
(``docs/register_map.md``), answering the others with exception 01."""
MAX_READ = 125
MAX_WRITE = 123
MAX_RW_WRITE = 121
MAX_PDU = 253
"""The longest PDU Modbus TCP carries (an ADU of at most 260 bytes)."""
OVERSIZE_WRITE_PDU = {16: 1 + 5 + 255, 23: 1 + 9 + 255}
"""The longest PDU of a write-multiple whose byte count (one byte) fits: read and refused."""
MAX_CLIENTS = 16
"""Connections served at once (a PLC's limit); more are closed at once."""

EXC_ILLEGAL_FUNCTION = 0x01
EXC_ILLEGAL_ADDRESS = 0x02
EXC_ILLEGAL_VALUE = 0x03
EXC_GATEWAY_TARGET = 0x0B

_MBAP = struct.Struct(">HHHB")


class PlcMachine(Protocol):
    """What the server needs of the machine (see ``plant_sim/machine/machine.py``)."""

    def register_values(self) -> dict[str, float | int]: ...  # noqa: D102
    def set_feed_setpoint(self, feed_mm_s: float) -> None: ...  # noqa: D102
    def set_service_heartbeat(self, value: int) -> None: ...  # noqa: D102


class _Refused(Exception):
    """A request answered with a Modbus exception code."""

    def __init__(self, code: int, why: str = "") -> None:
        super().__init__(why)
        self.code = code


class PlcServer:
    """Modbus TCP server playing the PLC over a machine.

    Parameters
    ----------
    machine : PlcMachine
        The machine model; ``register_values()`` must return every register of the map.
    register_map : RegisterMap, optional
        Default: ``config/registers.toml``.
    host : str
        Address to bind (default loopback only).
    port : int
        TCP port; 0 picks a free port (read the actual one from :attr:`port` after :meth:`start`).
    unit_id : int, optional
        Modbus unit id served; default the map's ``unit_id``.
    queue_writes : bool
        Queue accepted writes for :meth:`apply_writes` (the server runs on another thread than
        the machine) instead of applying them at once.
    heads : int, optional
        Head blocks to serve; default what the machine has (``heads_served``).

    Attributes
    ----------
    requests, refused : int
        Count of served requests and of those refused with an exception.
    write_errors : int
        Queued writes the machine refused when they were applied (answered already).
    heads : int
        Head blocks served (:func:`~plant_sim.interfaces.register_image.heads_served`).
    on_queued : callable or None
        Called with each write queued (``queue_writes``), a ``(head, values)`` pair (head
        ``None``: the single map): a server in another process than the machine sends it on
        (:mod:`plant_sim.interfaces.plc_process`).
    before_request : callable or None
        Called before each request is answered (to load a newer snapshot).
    """

    def __init__(
        self,
        machine: PlcMachine,
        *,
        register_map: RegisterMap | None = None,
        host: str = "127.0.0.1",
        port: int = 502,
        unit_id: int | None = None,
        queue_writes: bool = False,
        heads: int | None = None,
    ) -> None:
        if not 0 <= int(port) <= 65535:
            raise ValueError(f"port must be in 0..65535, got {port!r}")
        self.machine = machine
        self.rmap = register_map if register_map is not None else RegisterMap.load()
        self.host = host
        self.port = int(port)
        self.unit_id = self.rmap.unit_id if unit_id is None else int(unit_id)
        self.queue_writes = bool(queue_writes)
        self.heads = heads_served(machine, self.rmap) if heads is None else int(heads)
        self._lock = threading.Lock()
        self._image = RegisterImage(self.rmap, self.heads)
        self._pending: deque[HeadWrite] = deque()
        self._server: asyncio.Server | None = None
        self._clients: set[asyncio.StreamWriter] = set()
        self.on_queued: Callable[[HeadWrite], None] | None = None
        self.before_request: Callable[[], None] | None = None
        self._queued = 0
        self.requests = 0
        self.refused = 0
        self.write_errors = 0
        self.refresh()

    # ------------------------------------------------------------------ state
    @property
    def running(self) -> bool:
        """Whether the server is listening."""
        return self._server is not None

    @property
    def values(self) -> Mapping[str, float | int]:
        """Register values of the single map as currently served."""
        return self._image.values

    def head_values(self, i: int) -> Mapping[str, float | int]:
        """Head ``i``'s block values as currently served."""
        return self._image.head_values[i]

    def refresh(self) -> None:
        """Publish the machine's register values (once per PLC cycle, on the stepping thread).

        Writes accepted but not yet applied keep their written value in the snapshot.
        """
        values = dict(self.machine.register_values())
        heads = head_values(self.machine, self.heads)
        with self._lock:
            self._image.load(values, heads)
            self._image.overlay(self._pending)

    def load_words(self, words: Sequence[int], *, applied: int) -> None:
        """Serve register words published by another process, as they are.

        The publisher is :mod:`plant_sim.interfaces.plc_process`.

        Parameters
        ----------
        words : sequence of int
            The words of :meth:`~plant_sim.interfaces.register_image.RegisterImage.flat` (the
            single span, then each served block): nothing is decoded or encoded until a write
            needs the values.
        applied : int
            How many of the writes this server ever queued the stepping side had applied when
            it published; those leave the overlay of written values.
        """
        with self._lock:
            self._applied(applied)
            self._image.load_flat(words)
            self._image.overlay(self._pending)

    def _applied(self, applied: int) -> None:
        """Writes the stepping side has applied leave the overlay (the lock held)."""
        done = applied - (self._queued - len(self._pending))
        for _ in range(max(0, min(done, len(self._pending)))):
            self._pending.popleft()

    def apply_writes(self) -> int:
        """Apply the queued writes to the machine, in order (on the stepping thread).

        Returns
        -------
        int
            Writes applied (a write the machine refuses now is logged and counted in
            :attr:`write_errors`).
        """
        n = 0
        while True:
            with self._lock:
                if not self._pending:
                    return n
                write = self._pending[0]
            try:
                apply(self.machine, write)
            except ValueError as exc:  # RegisterAccessError / RegisterRangeError
                self.write_errors += 1
                log.warning("queued Modbus write not applied: %s", exc)
            with self._lock:
                self._pending.popleft()
            n += 1

    # ------------------------------------------------------------------ the protocol (sans-I/O)
    def respond(self, unit_id: int, pdu: bytes) -> bytes:
        """Answer one request PDU (function code and data) with the response PDU.

        Parameters
        ----------
        unit_id : int
            The request's unit id.
        pdu : bytes
            Function code and data (at least one byte).

        Returns
        -------
        bytes
            The response PDU: the data asked for, or ``function | 0x80`` and an exception code.
        """
        fc = pdu[0]
        self.requests += 1
        if self.before_request is not None:
            self.before_request()
        try:
            if unit_id != self.unit_id:
                raise _Refused(EXC_GATEWAY_TARGET, f"unit id {unit_id} not served")
            if fc not in self.rmap.function_codes:  # the map's offer (FUNCTION_CODES at most)
                raise _Refused(EXC_ILLEGAL_FUNCTION, f"function {fc} not offered")
            return bytes([fc]) + self._dispatch(fc, pdu[1:])
        except _Refused as exc:
            self.refused += 1
            if exc.code in (EXC_ILLEGAL_ADDRESS, EXC_ILLEGAL_VALUE) and str(exc):
                log.info("Modbus request refused (%02d): %s", exc.code, exc)
            return bytes([(fc | 0x80) & 0xFF, exc.code])

    def _dispatch(self, fc: int, data: bytes) -> bytes:
        if fc == 3:
            start, qty = _fields(data, ">HH")
            return self._read(start, qty, MAX_READ)
        if fc == 6:
            address, value = _fields(data, ">HH")
            self._write(address, [value])
            return data
        if fc == 16:
            start, qty, nbytes = _fields(data[:5], ">HHB")
            words = _words(data[5:], qty, nbytes, MAX_WRITE)
            self._write(start, words)
            return data[:4]
        # 23: read/write multiple registers (the write is done before the read)
        r_start, r_qty, w_start, w_qty, nbytes = _fields(data[:9], ">HHHHB")
        if not 1 <= r_qty <= MAX_READ:
            raise _Refused(EXC_ILLEGAL_VALUE, f"read quantity {r_qty}")
        words = _words(data[9:], w_qty, nbytes, MAX_RW_WRITE)
        self._write(w_start, words)
        return self._read(r_start, r_qty, MAX_READ)

    def _read(self, start: int, qty: int, max_qty: int) -> bytes:
        if not 1 <= qty <= max_qty:
            raise _Refused(EXC_ILLEGAL_VALUE, f"read quantity {qty} (1..{max_qty})")
        with self._lock:
            try:
                words = self._image.read(start, qty)
            except RegisterAccessError as exc:
                raise _Refused(EXC_ILLEGAL_ADDRESS, str(exc)) from None
        return bytes([2 * qty]) + struct.pack(f">{qty}H", *words)

    def _write(self, address: int, words: list[int]) -> None:
        with self._lock:
            try:
                write = self._image.parse_write(address, words)
                if not self.queue_writes:
                    apply(self.machine, write)  # the one write dispatch (protocol.registers)
            except RegisterAccessError as exc:
                raise _Refused(EXC_ILLEGAL_ADDRESS, str(exc)) from None
            except (RegisterRangeError, ValueError) as exc:
                raise _Refused(EXC_ILLEGAL_VALUE, str(exc)) from None
            self._image.store(write)
            if self.queue_writes:
                self._pending.append(write)
                self._queued += 1
                if self.on_queued is not None:
                    self.on_queued(write)

    # ------------------------------------------------------------------ I/O
    async def _serve_client(self, reader: asyncio.StreamReader,
                            writer: asyncio.StreamWriter) -> None:
        if self._server is None or len(self._clients) >= MAX_CLIENTS:
            writer.close()  # stopped meanwhile, or too many clients
            return
        self._clients.add(writer)
        try:
            while True:
                header = await reader.readexactly(_MBAP.size)
                tid, pid, length, unit = _MBAP.unpack(header)
                if pid != 0 or not 2 <= length <= 1 + max(OVERSIZE_WRITE_PDU.values()):
                    log.info("not a Modbus TCP header (protocol %d, length %d): closing",
                             pid, length)
                    return
                pdu = await reader.readexactly(1)
                if length - 1 > MAX_PDU and length - 1 > OVERSIZE_WRITE_PDU.get(pdu[0], 0):
                    log.info("not a Modbus TCP header (length %d, function %d): closing",
                             length, pdu[0])
                    return
                pdu += await reader.readexactly(length - 2)
                reply = self.respond(unit, pdu)
                writer.write(_MBAP.pack(tid, 0, len(reply) + 1, unit) + reply)
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError):
            pass  # the client went away
        finally:
            self._clients.discard(writer)
            writer.close()

    async def start(self) -> tuple[str, int]:
        """Bind and listen on the running loop; returns ``(host, port)`` actually bound.

        Raises
        ------
        FieldbusError
            The address cannot be bound (port in use).
        """
        from core.errors import FieldbusError

        if self._server is not None:
            return self.host, self.port
        try:
            server = await asyncio.start_server(self._serve_client, self.host, self.port,
                                                reuse_address=True)
        except OSError as exc:
            raise FieldbusError(
                f"Modbus server cannot listen on {self.host}:{self.port}: "
                f"{exc.strerror or exc}"
            ) from None
        self.port = int(server.sockets[0].getsockname()[1])
        self._server = server
        log.info("Modbus server listening on %s:%d", self.host, self.port)
        return self.host, self.port

    def close_now(self) -> asyncio.Server | None:
        """Stop listening and drop every client at once (on the server's loop; idempotent).

        Returns the closed server (await its ``wait_closed()``) or ``None``.
        """
        server, self._server = self._server, None
        if server is not None:
            server.close()
            for writer in list(self._clients):
                writer.close()
            self._clients.clear()
        return server

    async def stop(self) -> None:
        """Stop listening and drop every client connection (idempotent)."""
        server = self.close_now()
        if server is not None:
            await server.wait_closed()

    async def restart(self) -> tuple[str, int]:
        """Stop and start again on the same port (fault injection: "Modbus server restart")."""
        await self.stop()
        return await self.start()

    def describe(self) -> dict[str, Any]:
        """Where the server listens, for the runner's banner."""
        return {"host": self.host, "port": self.port, "unit_id": self.unit_id}


def _fields(data: bytes, fmt: str) -> tuple[int, ...]:
    """Unpack a fixed request body; a body of another length is exception 03."""
    size = struct.calcsize(fmt)
    if len(data) != size:
        raise _Refused(EXC_ILLEGAL_VALUE, f"request body of {len(data)} bytes, not {size}")
    return struct.unpack(fmt, data)


def _words(data: bytes, qty: int, nbytes: int, max_qty: int) -> list[int]:
    """The values of a multiple write; quantity and byte count checked (exception 03)."""
    if not 1 <= qty <= max_qty or nbytes != 2 * qty or len(data) != nbytes:
        raise _Refused(EXC_ILLEGAL_VALUE, f"write of {qty} registers with {nbytes} bytes")
    return list(struct.unpack(f">{qty}H", data))
