"""The simulated machine as a register bus in the same process (no Modbus server between).

Simulated-time tests and the in-process HIL reach the machine's registers through
:class:`MachineRegisterBus`, which applies the same rules as the PLC server.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from core.errors import FieldbusError
from plant_sim.interfaces.register_image import (
    RegisterImage,
    apply,
    head_values,
    heads_served,
)
from protocol.register_bus import BusRefused
from protocol.registers import RegisterAccessError, RegisterMap, RegisterRangeError

__all__ = ["MachineRegisterBus"]


class MachineRegisterBus:
    """:class:`RegisterBus` straight onto a simulated machine in the same process.

    The machine is a :class:`plant_sim.machine.machine.Machine` (or the tests' stand-in).

    Reads encode ``machine.register_values()`` (the single map) and
    ``machine.head_register_values(i)`` (head ``i``'s block; :func:`~plant_sim.interfaces.
    register_image.heads_served` heads) with the register map; writes are checked exactly as
    the PLC server checks them (read-only -> exception 2, out of range -> exception 3) and
    applied as the server applies them (:class:`~plant_sim.interfaces.register_image.
    RegisterImage`). Function 23 (:meth:`read_write`) writes, then reads. Set :attr:`down` to
    make it behave like an unreachable PLC (fault injection in tests and HIL).

    Parameters
    ----------
    machine : Machine
        The simulated machine.
    regmap : RegisterMap
        The register map (a head's view serves its whole map).
    """

    def __init__(self, machine: Any, regmap: RegisterMap) -> None:
        self.machine = machine
        self.regmap = regmap
        self.heads = heads_served(machine, regmap)
        """Head blocks served (0 for a machine without ``head_register_values``)."""
        self._img = RegisterImage(regmap, self.heads)
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

    def _image(self) -> RegisterImage:
        """The register image (built once) loaded with the machine's values now."""
        image = self._img
        image.load(self.machine.register_values(), head_values(self.machine, self.heads))
        return image

    async def read(self, address: int, count: int) -> list[int]:
        """Read words of the single map's span or of one head's block (function 3)."""
        self._check()
        try:
            return self._image().read(address, count)
        except RegisterAccessError as exc:
            raise BusRefused(exc.exception_code, str(exc)) from None

    async def write(self, address: int, words: Sequence[int]) -> None:
        """Write words: checked by the register map, then applied to the machine."""
        self._check()
        self._write(self._image(), address, words)

    async def read_write(
        self, read_address: int, read_count: int, write_address: int, words: Sequence[int]
    ) -> list[int]:
        """Function 23: write ``words`` at ``write_address``, then read (one request)."""
        self._check()
        image = self._image()
        self._write(image, write_address, words)
        image = self._image()
        try:
            return image.read(read_address, read_count)
        except RegisterAccessError as exc:
            raise BusRefused(exc.exception_code, str(exc)) from None

    def _write(self, image: RegisterImage, address: int, words: Sequence[int]) -> None:
        try:
            apply(self.machine, image.parse_write(address, words))
        except (RegisterAccessError, RegisterRangeError) as exc:
            raise BusRefused(exc.exception_code, str(exc)) from None

    def close(self) -> None:
        """Close (idempotent)."""
        self._open = False
