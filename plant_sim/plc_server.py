"""The PLC's Modbus TCP server: the simulated machine's registers over pymodbus 3.16.

The holding registers mirror ``machine.register_values()`` as of the last :meth:`PlcServer.refresh`
(the runner calls it every PLC cycle). Writes go through the register map
(:mod:`protocol.registers`):

* a write to a read-only register, to a gap or to half of a 32-bit register is refused with
  Modbus exception 02 (ILLEGAL DATA ADDRESS);
* a value outside the register's limits (or one the machine refuses) with exception 03
  (ILLEGAL DATA VALUE) -- never clamped;
* an accepted ``feed_setpoint_mm_s`` goes to ``machine.set_feed_setpoint``, an accepted
  ``heartbeat_service`` to ``machine.set_service_heartbeat``.

Only the holding-register functions (3, 6, 16, 23) are served; others answer exception 01. A
request for another unit id than the map's answers exception 0B (gateway target failed to
respond). The hook pymodbus 3.16 offers for this is ``SimDevice(action=...)``: an async callback
called on every access with the live register list (which it may refresh) and the values to be
written; returning an ``ExcCodes`` member refuses the request with that exception code.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any, Protocol

from pymodbus.constants import ExcCodes
from pymodbus.exceptions import NoSuchIdException
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice
from pymodbus.simulator.simcore import SimCore

from protocol.registers import RegisterAccessError, RegisterMap, RegisterRangeError

log = logging.getLogger(__name__)

HOLDING_FUNCTIONS = frozenset({3, 6, 16, 23})


class PlcMachine(Protocol):
    """What the server needs of the machine (see ``plant_sim/machine.py``)."""

    def register_values(self) -> dict[str, float | int]: ...  # noqa: D102
    def set_feed_setpoint(self, feed_mm_s: float) -> None: ...  # noqa: D102
    def set_service_heartbeat(self, value: int) -> None: ...  # noqa: D102


class _StrictCore(SimCore):
    """pymodbus' datastore answering only the configured unit ids (others: exception 0B)."""

    def _check(self, device_id: int) -> None:
        if device_id not in self.devices and 0 not in self.devices:
            raise NoSuchIdException(f"unit id {device_id} not served")

    async def async_getValues(self, device_id, func_code, address, count=1):  # noqa: D102, N802
        self._check(device_id)
        return await super().async_getValues(device_id, func_code, address, count)

    async def async_setValues(self, device_id, func_code, address, values):  # noqa: D102, N802
        self._check(device_id)
        return await super().async_setValues(device_id, func_code, address, values)


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

    Attributes
    ----------
    requests, refused : int
        Count of served requests and of those refused with an exception.
    """

    def __init__(
        self,
        machine: PlcMachine,
        *,
        register_map: RegisterMap | None = None,
        host: str = "127.0.0.1",
        port: int = 502,
        unit_id: int | None = None,
    ) -> None:
        if not 0 <= int(port) <= 65535:
            raise ValueError(f"port must be in 0..65535, got {port!r}")
        self.machine = machine
        self.rmap = register_map if register_map is not None else RegisterMap.load()
        self.host = host
        self.port = int(port)
        self.unit_id = self.rmap.unit_id if unit_id is None else int(unit_id)
        self._first, self._count = self.rmap.span()
        self._values: dict[str, float | int] = {}
        self._words: list[int] = [0] * self._count
        self._server: ModbusTcpServer | None = None
        self.requests = 0
        self.refused = 0
        self.refresh()

    # ------------------------------------------------------------------ state
    @property
    def running(self) -> bool:
        """Whether the server is listening."""
        return self._server is not None

    @property
    def values(self) -> Mapping[str, float | int]:
        """Register values as currently served."""
        return self._values

    def refresh(self) -> None:
        """Copy ``machine.register_values()`` into the served registers (once per PLC cycle)."""
        values = dict(self.machine.register_values())
        self._words = self.rmap.encode_block(values)
        self._values = values

    # ------------------------------------------------------------------ the pymodbus hook
    async def _action(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        current_registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        self.requests += 1
        if function_code not in HOLDING_FUNCTIONS:
            self.refused += 1
            return ExcCodes.ILLEGAL_FUNCTION
        off = self._first - start_address
        current_registers[off : off + self._count] = self._words
        if set_values is None or function_code == 3:
            return None
        words = [int(w) for w in set_values]
        try:
            accepted = self.rmap.parse_write(address, words, self._values)
            self._apply(accepted)
        except RegisterAccessError as exc:
            self.refused += 1
            log.info("Modbus write refused (02): %s", exc)
            return ExcCodes.ILLEGAL_ADDRESS
        except (RegisterRangeError, ValueError) as exc:
            self.refused += 1
            log.info("Modbus write refused (03): %s", exc)
            return ExcCodes.ILLEGAL_VALUE
        for name, value in accepted.items():
            reg = self.rmap[name]
            i = reg.address - self._first
            self._words[i : i + reg.count] = self.rmap.encode(name, value)
            self._values[name] = value
        return None

    def _apply(self, accepted: Mapping[str, float | int]) -> None:
        for name, value in accepted.items():
            if name == "feed_setpoint_mm_s":
                self.machine.set_feed_setpoint(float(value))
            elif name == "heartbeat_service":
                self.machine.set_service_heartbeat(int(value))

    # ------------------------------------------------------------------ life cycle
    async def start(self) -> tuple[str, int]:
        """Bind and listen; returns ``(host, port)`` actually bound.

        Raises
        ------
        FieldbusError
            The address cannot be bound (port in use).
        """
        from core.errors import FieldbusError

        if self._server is not None:
            return self.host, self.port
        device = SimDevice(
            id=self.unit_id,
            simdata=[SimData(self._first, count=self._count, datatype=DataType.REGISTERS)],
            action=self._action,
        )
        server = ModbusTcpServer(device, address=(self.host, self.port))
        server.context = _StrictCore(device)
        try:
            await server.serve_forever(background=True)
        except RuntimeError as exc:
            raise FieldbusError(
                f"Modbus server cannot listen on {self.host}:{self.port}: {exc}"
            ) from None
        sockets = getattr(server.transport, "sockets", None) or []
        if sockets:
            self.port = int(sockets[0].getsockname()[1])
        self._server = server
        log.info("Modbus server listening on %s:%d", self.host, self.port)
        return self.host, self.port

    async def stop(self) -> None:
        """Stop listening and drop every client connection (idempotent)."""
        server, self._server = self._server, None
        if server is not None:
            await server.shutdown()

    async def restart(self) -> tuple[str, int]:
        """Stop and start again on the same port (fault injection: "Modbus server restart")."""
        await self.stop()
        return await self.start()

    def describe(self) -> dict[str, Any]:
        """Where the server listens, for the runner's banner."""
        return {"host": self.host, "port": self.port, "unit_id": self.unit_id}
