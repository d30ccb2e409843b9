"""The service's Modbus TCP client of the PLC: the pure protocol at its core, pymodbus at the edge.

* :class:`ModbusTcpBus` — the real :class:`protocol.register_bus.RegisterBus` (pymodbus
  ``AsyncModbusTcpClient``); the simulator's in-process one is
  :class:`plant_sim.interfaces.register_bus.MachineRegisterBus`.
* :class:`PlcClient` — what the service uses: ``read()``, ``write_feed()``,
  ``write_heartbeat()`` (and, over a head's view of the map, ``write_spindle_setpoint()``;
  ``read_head(i)`` for tools); requests and answers by
  :class:`~controller.fieldbus.plc_protocol.PlcProtocol`,
  reconnects paced by :class:`~controller.fieldbus.plc_protocol.Backoff`; Modbus exceptions
  become :class:`core.errors.ModbusRefused` naming the register, a lost or unanswered connection
  :class:`core.errors.FieldbusError`; after a failure the next request reconnects, but not
  before the back-off delay has passed.

One owner per bus: the service creates one ``PlcClient`` and nothing else talks to the PLC; the
client lets one request at a time onto the bus.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Sequence
from typing import Any

from config.machine import PlcConfig
from controller.fieldbus.plc_protocol import (
    MODBUS_EXCEPTIONS,
    Backoff,
    PlcProtocol,
    PlcSnapshot,
    int_words,
)
from core.checks import check_int, check_positive
from core.errors import FieldbusError, ModbusRefused
from protocol.register_bus import BusRefused, RegisterBus
from protocol.registers import RegisterMap

_DEFAULTS = PlcConfig()
"""Time-outs, back-off and unit id when none are given: ``[plc]`` of ``config/machine.toml``."""


class ModbusTcpBus:
    """:class:`RegisterBus` over pymodbus ``AsyncModbusTcpClient`` (pymodbus 3.16 API).

    pymodbus' own reconnect loop is switched off (``reconnect_delay=0``): :class:`PlcClient`
    decides when to reconnect. Each request is bounded by ``timeout_s``.

    Parameters
    ----------
    host, port, unit_id
        Modbus TCP endpoint and device id.
    timeout_s : float
        Connect and request time limit, seconds.
    """

    def __init__(
        self,
        host: str,
        port: int,
        *,
        unit_id: int = _DEFAULTS.unit_id,
        timeout_s: float = _DEFAULTS.timeout_s,
    ) -> None:
        self.host = host
        self.port = check_int("port", port, lo=1, hi=65535)
        self.unit_id = check_int("unit_id", unit_id, lo=0, hi=255)
        self.timeout_s = check_positive("timeout_s", timeout_s)
        self._client: Any = None

    @property
    def connected(self) -> bool:
        """Whether the TCP connection is open."""
        return self._client is not None and bool(self._client.connected)

    async def connect(self) -> None:
        """Open a new TCP connection (closing any old one)."""
        from pymodbus.client import AsyncModbusTcpClient

        self.close()
        client = AsyncModbusTcpClient(
            self.host,
            port=self.port,
            timeout=self.timeout_s,
            retries=0,
            reconnect_delay=0,
            reconnect_delay_max=0,
        )
        try:
            ok = await asyncio.wait_for(client.connect(), timeout=self.timeout_s * 2)
        except (asyncio.TimeoutError, OSError) as exc:
            client.close()
            raise FieldbusError(f"PLC {self.host}:{self.port}: cannot connect: {exc}") from None
        if not ok:
            client.close()
            raise FieldbusError(f"PLC {self.host}:{self.port}: connection refused")
        self._client = client

    async def _call(self, what: str, coro_fn: Callable[[], Any]) -> Any:
        from pymodbus.exceptions import ModbusException

        if not self.connected:
            self.close()
            raise FieldbusError(f"PLC {self.host}:{self.port}: not connected ({what})")
        try:
            resp = await _within(coro_fn, self.timeout_s * 1.5)
        except (ModbusException, asyncio.TimeoutError, OSError) as exc:
            self.close()
            raise FieldbusError(f"PLC {self.host}:{self.port}: {what}: {exc}") from None
        if resp.isError():
            code = int(getattr(resp, "exception_code", 0))
            raise BusRefused(code, f"{what}: exception {code}")
        return resp

    async def read(self, address: int, count: int) -> list[int]:
        """Read ``count`` holding registers from ``address`` (function 3)."""
        resp = await self._call(
            f"read {count} registers at {address}",
            lambda: self._client.read_holding_registers(
                address, count=count, device_id=self.unit_id
            ),
        )
        words = list(resp.registers)
        if len(words) != count:
            raise FieldbusError(f"PLC answered {len(words)} registers, expected {count}")
        return words

    async def write(self, address: int, words: Sequence[int]) -> None:
        """Write ``words`` from ``address`` (function 6 for one word, 16 otherwise)."""
        ws = [int(w) for w in words]
        if len(ws) == 1:
            await self._call(
                f"write register {address}",
                lambda: self._client.write_register(address, ws[0], device_id=self.unit_id),
            )
        else:
            await self._call(
                f"write {len(ws)} registers at {address}",
                lambda: self._client.write_registers(address, ws, device_id=self.unit_id),
            )

    async def read_write(
        self, read_address: int, read_count: int, write_address: int, words: Sequence[int]
    ) -> list[int]:
        """Write ``words`` at ``write_address``, then read ``read_count`` words (function 23)."""
        ws = [int(w) for w in words]
        resp = await self._call(
            f"write {len(ws)} at {write_address} and read {read_count} registers at "
            f"{read_address}",
            lambda: self._client.readwrite_registers(
                read_address=read_address, read_count=read_count, write_address=write_address,
                values=ws, device_id=self.unit_id,
            ),
        )
        got = list(resp.registers)
        if len(got) != read_count:
            raise FieldbusError(f"PLC answered {len(got)} registers, expected {read_count}")
        return got

    def close(self) -> None:
        """Close the connection (idempotent)."""
        if self._client is not None:
            try:
                self._client.close()
            finally:
                self._client = None


async def _within(coro_fn: Callable[[], Any], timeout_s: float) -> Any:
    """``await coro_fn()`` bounded by ``timeout_s`` (``asyncio.TimeoutError`` beyond it).

    On Python 3.11+ in the calling task (``asyncio.timeout``): the request goes on the wire in
    the same turn of the event loop as the call, which lets a caller overlap its own work with
    the PLC's answer (``ControlLoops.apply``); ``asyncio.wait_for`` would start a task first.
    """
    timeout = getattr(asyncio, "timeout", None)
    if timeout is None:  # pragma: no cover - Python 3.10
        return await asyncio.wait_for(coro_fn(), timeout=timeout_s)
    async with timeout(timeout_s):
        return await coro_fn()


# ---------------------------------------------------------------------------------- client
class PlcClient:
    """The service's one connection to the PLC.

    Parameters
    ----------
    bus : RegisterBus
        Transport (:class:`ModbusTcpBus` on a machine, :class:`MachineRegisterBus` in-process).
    regmap : RegisterMap
        The register map (``RegisterMap.load()``).
    backoff : Backoff, optional
        Reconnect policy; default ``[plc] backoff_initial_s`` doubling up to ``backoff_max_s``
        as :class:`config.machine.PlcConfig` defines them (0.05 s, 2 s).
    clock : callable, optional
        Returns seconds (monotonic); default ``time.monotonic``. Tests pass simulated time.

    Notes
    -----
    Every request first makes sure the bus is connected; a failed (re)connect or a lost
    connection raises :class:`FieldbusError` and arms the back-off, during which requests fail
    at once without touching the network. A Modbus exception answer raises
    :class:`ModbusRefused` naming the register; it leaves the connection up.

    Requests from several tasks (the service's PLC cycle and its pair task) are serialised:
    one request (with its connect) on the bus at a time, in the order they were made.

    Over a head's view of the map (``RegisterMap.for_head(i)``) a read is two requests: the
    common span (function 3), then the head's whole block in ONE function 23 transaction that
    writes the service heartbeat again (the value this client last wrote, else the one just
    read: no change the watchdog could mistake for life) and reads the block; function 3 where
    the map does not offer 23 or the bus cannot send it. The snapshot then holds the head's
    ``spindle_rpm``, ``knives``, ... under their usual names. A moulder's coordinator reads
    the common span once (:meth:`beat_and_read`) and every head's block in as few requests as
    the map allows (:meth:`read_blocks`) and offers each head its words
    (:meth:`offer_common`, :meth:`offer_block`): that head's read then asks for nothing.
    """

    def __init__(
        self,
        bus: RegisterBus,
        regmap: RegisterMap,
        *,
        backoff: Backoff | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.bus = bus
        self.protocol = PlcProtocol(regmap)
        self.backoff = backoff or Backoff(_DEFAULTS.backoff_initial_s, _DEFAULTS.backoff_max_s)
        self.clock = clock
        self.last: PlcSnapshot | None = None
        """The last successful read."""
        self.last_ok_s: float | None = None
        """Time of the last answered request (read or write)."""
        self.reconnects = 0
        self.failures = 0
        self._heartbeat: int | None = None
        self._offered: list[int] | None = None  # the common span's words of another read
        self._offered_block: list[int] | None = None  # this view's block, of another read
        self.last_common: list[int] | None = None
        """The words of the common span (``protocol.ranges[0]``) of the last read."""
        self._views: dict[int, PlcProtocol] = {}
        self._lock: asyncio.Lock | None = None
        self._lock_loop: Any = None

    def _bus_lock(self) -> asyncio.Lock:
        """The lock of the running event loop (a client may outlive one ``asyncio.run``)."""
        loop = asyncio.get_running_loop()
        if self._lock is None or self._lock_loop is not loop:
            self._lock = asyncio.Lock()
            self._lock_loop = loop
        return self._lock

    @classmethod
    def tcp(
        cls,
        host: str,
        port: int,
        *,
        unit_id: int = _DEFAULTS.unit_id,
        timeout_s: float = _DEFAULTS.timeout_s,
        regmap: RegisterMap | None = None,
        backoff: Backoff | None = None,
        clock: Callable[[], float] = time.monotonic,
        head: int | None = None,
    ) -> PlcClient:
        """A client over Modbus TCP (pymodbus, :class:`ModbusTcpBus`).

        ``head``: the client reads and writes over that head's view of the map.
        """
        rm = regmap or RegisterMap.load()
        if head is not None:
            rm = rm.for_head(head)
        bus = ModbusTcpBus(host, port, unit_id=unit_id, timeout_s=timeout_s)
        return cls(bus, rm, backoff=backoff, clock=clock)

    @property
    def connected(self) -> bool:
        """Whether the bus is connected now."""
        return bool(self.bus.connected)

    async def _ensure(self) -> None:
        if self.bus.connected:
            return
        now = self.clock()
        if not self.backoff.may_attempt(now):
            raise FieldbusError(
                f"PLC unreachable; next reconnect in {self.backoff.next_attempt_s - now:.2f} s"
            )
        try:
            await self.bus.connect()
        except FieldbusError:
            self.backoff.failed(self.clock())
            self.failures += 1
            raise
        self.reconnects += 1

    async def _do(self, what: str, address: int, count: int, fn: Callable[[], Any]) -> Any:
        async with self._bus_lock():
            return await self._do_locked(what, address, count, fn)

    async def _do_locked(
        self, what: str, address: int, count: int, fn: Callable[[], Any],
        protocol: PlcProtocol | None = None,
    ) -> Any:
        await self._ensure()
        try:
            out = await fn()
        except BusRefused as exc:
            name = MODBUS_EXCEPTIONS.get(exc.code, "exception")
            regs = (protocol or self.protocol).names_at(address, count)
            self.last_ok_s = self.clock()  # it answered
            raise ModbusRefused(
                f"PLC refused {what} {regs}: exception {exc.code:02d} {name}"
            ) from None
        except FieldbusError:
            self.bus.close()
            self.backoff.failed(self.clock())
            self.failures += 1
            raise
        self.backoff.succeeded()
        self.last_ok_s = self.clock()
        return out

    async def read(self) -> PlcSnapshot:
        """Read every register in one request and decode it.

        Returns
        -------
        PlcSnapshot
            The decoded registers; also kept in :attr:`last`.

        Raises
        ------
        FieldbusError
            Not connected, connection lost or no answer.
        ModbusRefused
            The PLC answered with an exception.
        """
        async with self._bus_lock():
            offered, self._offered = self._offered, None
            block, self._offered_block = self._offered_block, None
            snap = await self._sample(self.protocol, common=offered,
                                      block=block if offered is not None else None)
        self.last = snap
        return snap

    async def beat_and_read(self, value: int) -> PlcSnapshot:
        """Write the service heartbeat, then read every register.

        :meth:`write_heartbeat` and :meth:`read` in ONE function 23 transaction where this
        client's map is no head's view, offers 23 and the bus can send it (else the two
        requests).

        The write comes first (function 23 writes before it reads), so the snapshot holds
        ``value`` (wrapped to 16 bits) as ``heartbeat_service``; a refused or failed
        transaction writes nothing and reads nothing (the heartbeat is not taken).
        """
        p = self.protocol
        rw = getattr(self.bus, "read_write", None)
        if p.block is not None or rw is None or 23 not in p.regmap.function_codes:
            await self.write_heartbeat(value)
            return await self.read()
        wa, ww = p.heartbeat_request(value)
        a, n = p.ranges[0]
        async with self._bus_lock():
            self._offered = None
            words = await self._do_locked(
                "writing the heartbeat and reading (function 23)", a, n,
                lambda: rw(a, n, wa, ww), p)
            self._heartbeat = ww[0]
            snap = PlcSnapshot(values=p.decode_range(0, words), t_s=self.clock())
            self.last_common = list(words)
        self.last = snap
        return snap

    async def read_blocks(self, heads: Sequence[int]) -> dict[int, list[int]]:
        """The words of the blocks of ``heads`` (each its used words), for their clients.

        In as few requests as the map allows (:meth:`PlcProtocol.blocks_reads`: one for
        consecutive heads where the map's ``[heads] read_across`` says so); the heads' clients
        take them through :meth:`offer_block`.

        Raises
        ------
        FieldbusError
            Not connected, connection lost or no answer (no words of any head then).
        ModbusRefused
            The PLC answered with an exception.
        """
        p = self.protocol
        out: dict[int, list[int]] = {}
        async with self._bus_lock():
            for read in p.blocks_reads(heads):
                a, n, _ = read
                words = await self._do_locked(
                    "reading", a, n, lambda a=a, n=n: self.bus.read(a, n), p)
                out.update(p.split_blocks(read, words))
        return out

    def offer_block(self, words: Sequence[int] | None) -> None:
        """The words of the block of the client's view another client has just read.

        Read by :meth:`read_blocks`.

        With an offer of the common span (:meth:`offer_common`) the next :meth:`read` asks the
        PLC for nothing: both ranges are taken from the offers. Used once, like
        :meth:`offer_common`; ``None`` withdraws it; ``ValueError`` when ``words`` are not the
        block's length or the client is over no head's view.
        """
        if words is None:
            self._offered_block = None
            return
        if self.protocol.block is None:
            raise ValueError("words: the client's register map is no head's view "
                             "(RegisterMap.for_head(i)): it has no block to offer")
        ws = int_words(words)
        if len(ws) != self.protocol.block[1]:
            raise ValueError(f"words must be the block's {self.protocol.block[1]} words, "
                             f"got {len(ws)}")
        self._offered_block = ws

    def offer_common(self, words: Sequence[int] | None) -> None:
        """The common span's words another client has just read, for this client's next read.

        A moulder's heads read the same machine-wide registers (the common span, ``ranges[0]``
        of every head's view): the coordinator reads them once per PLC cycle and offers its
        words to each head, whose next :meth:`read` then asks the PLC only for its block. Used
        once (the read after takes the PLC's again); ``None`` withdraws an offer not yet used;
        ``ValueError`` when ``words`` are not the span's length (another map's).
        """
        if words is None:
            self._offered = None
            return
        ws = int_words(words)
        if len(ws) != self.protocol.read_count:
            raise ValueError(f"words must be the common span's {self.protocol.read_count} "
                             f"words, got {len(ws)}")
        self._offered = ws

    async def read_head(self, i: int) -> PlcSnapshot:
        """Read the common registers and head ``i``'s block (a tool's look at any head).

        Parameters
        ----------
        i : int
            Head index (``0 <= i < RegisterMap.head_count``; ``ValueError`` otherwise).

        Returns
        -------
        PlcSnapshot
            Head ``i``'s view; kept in :attr:`last` only when it is this client's own view.
        """
        view = self.protocol.regmap.for_head(i)
        p = self.protocol if view is self.protocol.regmap else self._views.get(int(i))
        if p is None:
            p = self._views[int(i)] = PlcProtocol(view)
        async with self._bus_lock():
            snap = await self._sample(p)
        if p is self.protocol:
            self.last = snap
        return snap

    async def _sample(self, p: PlcProtocol, *, common: list[int] | None = None,
                      block: list[int] | None = None) -> PlcSnapshot:
        """Read every range of ``p`` (the bus lock held): one snapshot.

        ``common``: the words of ``p.ranges[0]`` already read (:meth:`offer_common`);
        ``block``: those of ``p.block`` (:meth:`offer_block`).
        """
        a, n = p.ranges[0]
        if common is None:
            words = await self._do_locked("reading", a, n, lambda: self.bus.read(a, n), p)
        else:
            words = common
        values = p.decode_range(0, words)
        if p is self.protocol:
            self.last_common = list(words)
        if p.block is not None and block is not None:
            values.update(p.decode_range(1, block))
        elif p.block is not None:
            b, m = p.block
            rw = getattr(self.bus, "read_write", None)
            if rw is not None and 23 in p.regmap.function_codes:
                hb = self._heartbeat
                if hb is None:
                    hb = int(values["heartbeat_service"])
                wa, ww = p.heartbeat_request(hb)
                words = await self._do_locked(
                    "reading (function 23)", b, m, lambda: rw(b, m, wa, ww), p
                )
            else:
                words = await self._do_locked("reading", b, m, lambda: self.bus.read(b, m), p)
            values.update(p.decode_range(1, words))
        return PlcSnapshot(values=values, t_s=self.clock())

    async def write_feed(self, feed_mm_s: float) -> None:
        """Write the feed setpoint (float32, two registers, function 16).

        The value is checked against the limits of the last read (``ValueError`` naming the
        register) before it goes on the wire; the PLC checks it again.
        """
        current = self.last.values if self.last is not None else None
        address, words = self.protocol.feed_request(feed_mm_s, current)
        await self._do(
            f"writing {feed_mm_s:.3f} to", address, len(words),
            lambda: self.bus.write(address, words),
        )

    async def write_heartbeat(self, value: int) -> None:
        """Write the service heartbeat register (value wrapped to 16 bits, function 6)."""
        address, words = self.protocol.heartbeat_request(value)
        await self._do(
            "writing", address, len(words), lambda: self.bus.write(address, words)
        )
        self._heartbeat = words[0]

    async def write_spindle_setpoint(self, rpm: float) -> None:
        """Write the head's spindle setpoint to its block (float32, function 16).

        Only over a head's view (``ValueError`` otherwise). Checked against the head's
        ``spindle_rpm_min..spindle_rpm_max`` of the last read before it goes on the wire
        (``ValueError`` naming the register); the PLC checks it again (exception 03).
        """
        current = self.last.values if self.last is not None else None
        address, words = self.protocol.spindle_request(rpm, current)
        await self._do(
            f"writing {rpm:.1f} to", address, len(words), lambda: self.bus.write(address, words)
        )

    def close(self) -> None:
        """Close the bus."""
        self.bus.close()
