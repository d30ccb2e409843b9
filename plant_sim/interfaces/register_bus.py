"""The simulated machine as a register bus in the same process (no Modbus server between).

Simulated-time tests and the in-process HIL reach the machine's registers through
:class:`MachineRegisterBus`, which applies the same rules as the PLC server.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from core.errors import FieldbusError
from protocol.register_bus import BusRefused
from protocol.registers import RegisterAccessError, RegisterMap, RegisterRangeError, apply_writes

__all__ = ["MachineRegisterBus"]


class MachineRegisterBus:
    """:class:`RegisterBus` straight onto a simulated machine in the same process.

    The machine is a :class:`plant_sim.machine.machine.Machine` (or the tests' stand-in).

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
