"""Reading the PLC's trigger latches over Modbus TCP for the camera's pairing (I/O edge).

A blocking pymodbus client of its own (the acquisition thread polls it; the service's
``PlcClient`` stays the owner of the control registers). One request reads the latch block
``trigger_a_counts`` .. ``board_position_mm`` and ``feed_actual_mm_s`` with the register map's
codec (``protocol/registers.py``).
"""

from __future__ import annotations

import time
from pathlib import Path

from pymodbus.exceptions import ModbusException

from controller.frames.camera.pairing import TriggerLatch
from core.checks import check_int
from protocol.registers import RegisterMap

__all__ = ["ModbusLatchReader", "parse_host_port"]


def parse_host_port(text: str, *, default_port: int = 502) -> tuple[str, int]:
    """``"HOST:PORT"`` (or ``"HOST"``) as ``(host, port)``; ``ValueError`` naming ``--plc``."""
    text = str(text)
    host, _, port = text.rpartition(":") if ":" in text else (text, "", str(default_port))
    try:
        number = int(port)
    except ValueError:
        raise ValueError(f"--plc must be HOST:PORT, got {text!r}") from None
    if not host or not 1 <= number <= 65535:
        raise ValueError(f"--plc must be HOST:PORT with a port 1..65535, got {text!r}")
    return host, number


class ModbusLatchReader:
    """``reader() -> TriggerLatch | None``: the PLC's last pair latch, ``None`` when unreachable.

    Parameters
    ----------
    host, port : str, int
        The PLC's Modbus TCP server.
    unit_id : int, keyword-only
        Modbus unit id.
    registers : Path, keyword-only, optional
        Register map (default: the shipped ``config/registers.toml``).
    timeout_s : float, keyword-only
        Time limit of one request, seconds.
    clock : callable, keyword-only
        Seconds for the latch's ``t_s`` (the PLC gives no time stamp).
    """

    def __init__(self, host: str, port: int, *, unit_id: int = 1, registers: Path | None = None,
                 timeout_s: float = 0.25, clock=time.monotonic) -> None:
        from pymodbus.client import ModbusTcpClient

        self.map = RegisterMap.load(registers)
        self.unit_id = check_int("unit_id", unit_id, lo=0, hi=255)
        names = ("feed_actual_mm_s", "trigger_a_counts", "board_position_mm")
        self._first = min(self.map[n].address for n in names)
        self._count = max(self.map[n].last_address for n in names) - self._first + 1
        self.clock = clock
        self.client = ModbusTcpClient(host, port=int(port), timeout=timeout_s, retries=0)
        self.errors = 0

    def __call__(self) -> TriggerLatch | None:
        """Read the latch block now (``None`` if the PLC does not answer)."""
        try:
            if not self.client.connected and not self.client.connect():
                self.errors += 1
                return None
            rr = self.client.read_holding_registers(self._first, count=self._count,
                                                    device_id=self.unit_id)
        except (ModbusException, OSError, ValueError):  # unreachable, refused, garbled
            self.errors += 1
            return None
        if rr.isError():
            self.errors += 1
            return None
        v = self.map.decode_block(rr.registers, start=self._first)
        return TriggerLatch(seq=int(v["trigger_seq"]), counts_a=int(v["trigger_a_counts"]),
                            counts_b=int(v["trigger_b_counts"]),
                            index_latch_counts=int(v["index_latch_counts"]),
                            board_id=int(v["board_id"]),
                            board_position_mm=float(v["board_position_mm"]),
                            speed_mm_s=float(v["feed_actual_mm_s"]), t_s=float(self.clock()),
                            counts_per_mm=float(v["counts_per_mm"]))

    def close(self) -> None:
        """Close the connection."""
        self.client.close()
