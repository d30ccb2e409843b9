"""The service's Modbus TCP client of the PLC: register-map core, pymodbus at the edge.

Layers
------
* :class:`PlcSnapshot` and :class:`PlcProtocol` — sans-I/O: which words to read (the whole span
  of ``config/registers.toml`` in one request), how to decode them, which words to write for the
  feed setpoint (``f32``, two registers, function 16) and the heartbeat (``u16``, function 6).
* :class:`Backoff` — the reconnect policy: capped exponential back-off on an injected clock.
* :class:`RegisterBus` — the transport interface (``connect``, ``read``, ``write``, ``close``).
  The real one: :class:`ModbusTcpBus` (pymodbus ``AsyncModbusTcpClient``);
  :class:`MachineRegisterBus` talks to a :class:`plant_sim.machine.Machine` in the same process
  (simulated-time tests and the in-process HIL), applying the same rules as the PLC server.
* :class:`PlcClient` — what the service uses: ``read()``, ``write_feed()``,
  ``write_heartbeat()``; Modbus exceptions become :class:`core.errors.ModbusRefused` naming
  the register, a lost or unanswered connection :class:`core.errors.FieldbusError`; after a
  failure the next request reconnects, but not before the back-off delay has passed.

One owner per bus: the service creates one ``PlcClient`` and nothing else talks to the PLC; the
client lets one request at a time onto the bus.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from config.machine import PlcConfig
from core.checks import check_finite, check_int, check_positive
from core.errors import FieldbusError, ModbusRefused
from protocol.registers import (
    MachineState,
    ModbusException,
    PlcFault,
    RegisterAccessError,
    RegisterMap,
    RegisterRangeError,
    apply_writes,
)

_DEFAULTS = PlcConfig()
"""Time-outs, back-off and unit id when none are given: ``[plc]`` of ``config/machine.toml``."""

MODBUS_EXCEPTIONS = {int(code): code.text for code in ModbusException}
"""Exception code to the spec's name, for messages (``protocol.registers.ModbusException``)."""

class BusRefused(Exception):
    """Raised by a :class:`RegisterBus` when the server answers with a Modbus exception code."""

    def __init__(self, code: int, message: str = "") -> None:
        super().__init__(message or f"exception {code}")
        self.code = int(code)


# ---------------------------------------------------------------------------------- sans-I/O
@dataclass(frozen=True)
class PlcSnapshot:
    """All registers of one read, decoded; the fields the service uses are typed attributes.

    Attributes
    ----------
    values : mapping
        Every register by name (``config/registers.toml``).
    t_s : float
        Time of the answer on the client's clock, seconds.
    """

    values: Mapping[str, float | int]
    t_s: float

    def __getitem__(self, name: str) -> float | int:
        return self.values[name]

    @property
    def spindle_rpm(self) -> float:
        """Measured spindle speed, rpm."""
        return float(self.values["spindle_rpm"])

    @property
    def knives(self) -> int:
        """Number of knives Z."""
        return int(self.values["knives"])

    @property
    def feed_min_mm_s(self) -> float:
        """Lowest accepted feed setpoint, mm/s."""
        return float(self.values["feed_min_mm_s"])

    @property
    def feed_max_mm_s(self) -> float:
        """Highest accepted feed setpoint, mm/s."""
        return float(self.values["feed_max_mm_s"])

    @property
    def feed_setpoint_mm_s(self) -> float:
        """Feed setpoint the PLC holds now, mm/s."""
        return float(self.values["feed_setpoint_mm_s"])

    @property
    def feed_actual_mm_s(self) -> float:
        """Measured feed speed, mm/s."""
        return float(self.values["feed_actual_mm_s"])

    @property
    def cutter_to_camera_mm(self) -> float:
        """Distance L from the cutterhead axis to the camera axis, mm."""
        return float(self.values["cutter_to_camera_mm"])

    @property
    def counts_per_mm(self) -> float:
        """Feed encoder resolution, counts/mm."""
        return float(self.values["counts_per_mm"])

    @property
    def index_latch_counts(self) -> int:
        """Encoder counts at the spindle index pulse of the last pair."""
        return int(self.values["index_latch_counts"])

    @property
    def trigger_seq(self) -> int:
        """Sequence number of the last image pair (mod 2**16)."""
        return int(self.values["trigger_seq"])

    @property
    def machine_state(self) -> MachineState:
        """Machine state bits (running, board present, e-stop, spindle running, feed enabled)."""
        return MachineState(int(self.values["machine_state"]))

    @property
    def faults(self) -> PlcFault:
        """Fault bits (feed drive, spindle stopped, encoder, heartbeat lost, piezo amplifier)."""
        return PlcFault(int(self.values["faults"]))

    @property
    def board_present(self) -> bool:
        """Whether a board is under the camera."""
        return MachineState.BOARD_PRESENT in self.machine_state

    @property
    def estop(self) -> bool:
        """Whether the e-stop is active."""
        return MachineState.ESTOP in self.machine_state

    @property
    def spindle_running(self) -> bool:
        """Whether the spindle runs."""
        return MachineState.SPINDLE_RUNNING in self.machine_state

    def problem(self) -> str | None:
        """Why these registers cannot be trusted for control, or ``None`` when they can.

        A PLC that answers nonsense (NaN or infinite floats, no knives, a zero encoder scale,
        inverted feed limits...) must not drive the loops: the service
        treats such an answer like a machine that is not fit to run (safe state, no feed write).

        Returns
        -------
        str or None
            The first problem found, naming the register(s).
        """
        v = self.values
        try:
            knives = int(v["knives"])
            if not 1 <= knives <= MAX_KNIVES:
                return f"knives = {knives} (must be 1..{MAX_KNIVES})"
            for name in _POSITIVE:
                x = float(v[name])
                if not (math.isfinite(x) and x > 0):
                    return f"{name} = {x!r} (must be finite and > 0)"
            for name in _NON_NEGATIVE:
                x = float(v[name])
                if not (math.isfinite(x) and x >= 0):
                    return f"{name} = {x!r} (must be finite and >= 0)"
            if not math.isfinite(self.feed_actual_mm_s):
                return f"feed_actual_mm_s = {self.feed_actual_mm_s!r} (must be finite)"
            lo, hi = self.feed_min_mm_s, self.feed_max_mm_s
            if not lo < hi:
                return f"feed_min_mm_s {lo!r} >= feed_max_mm_s {hi!r}"
            if not math.isfinite(self.feed_setpoint_mm_s):
                return f"feed_setpoint_mm_s = {self.feed_setpoint_mm_s!r} (must be finite)"
        except KeyError as exc:
            return f"register {exc} missing"
        except (TypeError, ValueError) as exc:
            return f"unreadable value: {exc}"
        return None


MAX_KNIVES = 8
"""Most knives the piezo frames carry."""
_POSITIVE = (
    "feed_min_mm_s",
    "feed_max_mm_s",
    "counts_per_mm",
    "cutter_to_camera_mm",
    "cutterhead_radius_mm",
)
_NON_NEGATIVE = ("spindle_rpm", "feed_accel_max_mm_s2")


class PlcProtocol:
    """Sans-I/O Modbus requests and answers over a :class:`RegisterMap` (built once).

    Parameters
    ----------
    regmap : RegisterMap
        The register map.
    """

    def __init__(self, regmap: RegisterMap) -> None:
        self.regmap = regmap
        self.read_address, self.read_count = regmap.span()
        self._feed = regmap["feed_setpoint_mm_s"]
        self._hb = regmap["heartbeat_service"]

    def decode_read(self, words: Sequence[int]) -> dict[str, float | int]:
        """Decode the words of one whole-span read into every register's value."""
        if len(words) != self.read_count:
            raise FieldbusError(
                f"PLC answered {len(words)} registers, expected {self.read_count}"
            )
        return self.regmap.decode_block(words, self.read_address)

    def feed_request(
        self, feed_mm_s: float, current: Mapping[str, float | int] | None = None
    ) -> tuple[int, list[int]]:
        """Address and words writing the feed setpoint (checked against the limits if known)."""
        v = check_finite("feed_mm_s", feed_mm_s)
        if current is not None:
            self.regmap.check_write(self._feed.name, v, current)
        return self._feed.address, self.regmap.encode(self._feed.name, v)

    def heartbeat_request(self, value: int) -> tuple[int, list[int]]:
        """Address and word writing the service heartbeat (wrapped to 16 bits)."""
        return self._hb.address, self.regmap.encode(self._hb.name, int(value) & 0xFFFF)

    def names_at(self, address: int, count: int) -> str:
        """Names of the registers in ``[address, address + count)`` for error messages."""
        names: list[str] = []
        for a in range(address, address + count):
            reg = self.regmap.at(a)
            if reg is not None and reg.name not in names:
                names.append(reg.name)
        if not names:
            return f"address {address}"
        if len(names) > 3:
            return f"{names[0]}..{names[-1]} ({address}..{address + count - 1})"
        return ", ".join(names)


class Backoff:
    """Capped exponential back-off for reconnect attempts (pure; time passed in).

    Parameters
    ----------
    initial_s : float
        Wait after the first failure, seconds.
    max_s : float
        Cap of the wait, seconds.
    factor : float
        Growth per consecutive failure.
    """

    def __init__(self, initial_s: float, max_s: float, *, factor: float = 2.0) -> None:
        self.initial_s = check_positive("initial_s", initial_s)
        self.max_s = check_positive("max_s", max_s)
        if self.max_s < self.initial_s:
            raise ValueError(f"max_s {max_s} < initial_s {initial_s}")
        self.factor = check_positive("factor", factor)
        self.failures = 0
        self.next_attempt_s = float("-inf")

    def delay_s(self) -> float:
        """Wait after the current number of consecutive failures."""
        if self.failures == 0:
            return 0.0
        return min(self.max_s, self.initial_s * self.factor ** (self.failures - 1))

    def failed(self, now_s: float) -> float:
        """Record a failed attempt at ``now_s``; return the time of the next allowed attempt."""
        self.failures += 1
        self.next_attempt_s = check_finite("now_s", now_s) + self.delay_s()
        return self.next_attempt_s

    def succeeded(self) -> None:
        """Record a success: the next failure starts from ``initial_s`` again."""
        self.failures = 0
        self.next_attempt_s = float("-inf")

    def may_attempt(self, now_s: float) -> bool:
        """Whether an attempt is allowed at ``now_s``."""
        return now_s >= self.next_attempt_s


# ---------------------------------------------------------------------------------- transports
class RegisterBus(Protocol):
    """Transport of holding-register reads and writes to one Modbus unit."""

    async def connect(self) -> None:
        """Open the connection; raise ``FieldbusError`` when it cannot be opened."""

    async def read(self, address: int, count: int) -> list[int]:
        """Read holding registers (function 3); ``BusRefused`` or ``FieldbusError`` on failure."""

    async def write(self, address: int, words: Sequence[int]) -> None:
        """Write holding registers (function 6 for one word, 16 for more)."""

    def close(self) -> None:
        """Close the connection (idempotent)."""

    @property
    def connected(self) -> bool:
        """Whether the connection is open."""


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


class MachineRegisterBus:
    """:class:`RegisterBus` straight onto a :class:`plant_sim.machine.Machine` (same process).

    Reads encode ``machine.register_values()`` with the register map; writes are checked by the
    map exactly as the PLC server checks them (read-only -> exception 2, out of range ->
    exception 3) and applied by :func:`protocol.registers.apply_writes`, as the server does. Set
    :attr:`down` to make it behave like an unreachable PLC (fault injection in tests and HIL).

    Parameters
    ----------
    machine : Machine
        The simulated machine.
    regmap : RegisterMap
        The register map.
    """

    def __init__(self, machine: Any, regmap: RegisterMap) -> None:
        self.machine = machine
        self.regmap = regmap
        self.down = False
        self._open = False
        self.requests = 0

    @property
    def connected(self) -> bool:
        """Whether the (simulated) connection is open."""
        return self._open and not self.down

    async def connect(self) -> None:
        """Open, unless the simulated PLC is down."""
        if self.down:
            self._open = False
            raise FieldbusError("PLC (in-process) unreachable: connection refused")
        self._open = True

    def _check(self) -> None:
        if not self.connected:
            self._open = False
            raise FieldbusError("PLC (in-process) unreachable")
        self.requests += 1

    async def read(self, address: int, count: int) -> list[int]:
        """Read words of the register span."""
        self._check()
        first, n = self.regmap.span()
        if address < first or address + count > first + n:
            raise BusRefused(2, f"read {count} registers at {address}")
        words = self.regmap.encode_block(self.machine.register_values())
        return words[address - first : address - first + count]

    async def write(self, address: int, words: Sequence[int]) -> None:
        """Write words: checked by the register map, then applied to the machine."""
        self._check()
        try:
            accepted = self.regmap.parse_write(address, words, self.machine.register_values())
            apply_writes(self.machine, accepted)
        except (RegisterAccessError, RegisterRangeError) as exc:
            raise BusRefused(exc.exception_code, str(exc)) from None

    def close(self) -> None:
        """Close (idempotent)."""
        self._open = False


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
    ) -> PlcClient:
        """A client over Modbus TCP (pymodbus, :class:`ModbusTcpBus`)."""
        rm = regmap or RegisterMap.load()
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
        self, what: str, address: int, count: int, fn: Callable[[], Any]
    ) -> Any:
        await self._ensure()
        try:
            out = await fn()
        except BusRefused as exc:
            name = MODBUS_EXCEPTIONS.get(exc.code, "exception")
            regs = self.protocol.names_at(address, count)
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
        p = self.protocol
        words = await self._do(
            "reading",
            p.read_address,
            p.read_count,
            lambda: self.bus.read(p.read_address, p.read_count),
        )
        snap = PlcSnapshot(values=p.decode_read(words), t_s=self.clock())
        self.last = snap
        return snap

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

    def close(self) -> None:
        """Close the bus."""
        self.bus.close()
