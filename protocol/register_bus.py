"""The transport of holding-register reads and writes to one Modbus unit (an interface).

:class:`RegisterBus` is what the service's PLC client talks through: the real Modbus TCP client
(``controller.fieldbus.plc_client.ModbusTcpBus``) or the simulated machine in the same process
(``plant_sim.interfaces.register_bus.MachineRegisterBus``). :class:`BusRefused` is its answer
when the server refuses a request with a Modbus exception code.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

__all__ = ["BusRefused", "RegisterBus"]


class BusRefused(Exception):
    """Raised by a :class:`RegisterBus` when the server answers with a Modbus exception code."""

    def __init__(self, code: int, message: str = "") -> None:
        super().__init__(message or f"exception {code}")
        self.code = int(code)




class RegisterBus(Protocol):
    """Transport of holding-register reads and writes to one Modbus unit."""

    async def connect(self) -> None:
        """Open the connection; raise ``FieldbusError`` when it cannot be opened."""

    async def read(self, address: int, count: int) -> list[int]:
        """Read holding registers (function 3); ``BusRefused`` or ``FieldbusError`` on failure."""

    async def write(self, address: int, words: Sequence[int]) -> None:
        """Write holding registers (function 6 for one word, 16 for more)."""

    async def read_write(
        self, read_address: int, read_count: int, write_address: int, words: Sequence[int]
    ) -> list[int]:
        """Write ``words`` at ``write_address``, then read, in one request (function 23).

        Optional: a client falls back to function 3 on a bus without it.
        """

    def close(self) -> None:
        """Close the connection (idempotent)."""

    @property
    def connected(self) -> bool:
        """Whether the connection is open."""
