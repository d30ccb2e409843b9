"""CANopen frames of the piezo amplifier packed by hand from docs/piezo_canopen.md's PDO map.

Independent of the project's master (``controller.fieldbus.canopen_amp``): tests that drive the
simulated node directly, or read what it sends, use these to check the node against the
documented layout rather than against our own encoder.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

NODE_ID = 2


def nmt(command: int, node_id: int = NODE_ID) -> tuple[int, bytes]:
    """NMT command (1 start, 2 stop, 0x80 pre-operational, 0x81 reset node) to ``node_id``."""
    return 0x000, bytes([command, node_id])


def start(node_id: int = NODE_ID) -> tuple[int, bytes]:
    """NMT start (operational)."""
    return nmt(0x01, node_id)


def command(enable: bool, knives: int, alive: int, node_id: int = NODE_ID) -> tuple[int, bytes]:
    """RPDO3: enable, knives, alive counter (three UNSIGNED8)."""
    return 0x400 + node_id, struct.pack("<BBB", int(enable), knives, alive & 0xFF)


def offsets(table_um: Sequence[float], node_id: int = NODE_ID) -> list[tuple[int, bytes]]:
    """RPDO1 (knives 1-4) and, for more than four knives, RPDO2: INTEGER16, 1 nm per bit."""
    nm = [round(v * 1000.0) for v in table_um] + [0] * (8 - len(table_um))
    frames = [(0x200 + node_id, struct.pack("<4h", *nm[:4]))]
    if len(table_um) > 4:
        frames.append((0x300 + node_id, struct.pack("<4h", *nm[4:])))
    return frames


def sdo_read(index: int, subindex: int, node_id: int = NODE_ID) -> tuple[int, bytes]:
    """SDO upload request (expedited read) of ``index``/``subindex``."""
    return 0x600 + node_id, struct.pack("<BHB4x", 0x40, index, subindex)


def status(data: bytes) -> dict[str, int]:
    """TPDO1's fields: displacement (nm), temperature (0.1 degC), fault bits, state."""
    disp, temp, fault, state = struct.unpack("<hhBB", bytes(data))
    return {"displacement_nm": disp, "temperature_dC": temp, "fault": fault, "state": state}


# ---------------------------------------------------------------- what an amplifier sends
def heartbeat(state: int, node_id: int = NODE_ID) -> tuple[int, bytes]:
    """Heartbeat with the NMT state (0 boot-up, 4 stopped, 5 operational, 127 pre-operational)."""
    return 0x700 + node_id, bytes([state])


def sdo_abort(index: int, subindex: int, code: int = 0x06020000,
              node_id: int = NODE_ID) -> tuple[int, bytes]:
    """SDO abort of ``index``/``subindex`` (default: object does not exist)."""
    return 0x580 + node_id, struct.pack("<BHBL", 0x80, index, subindex, code)


def status_frame(*, displacement_nm: int = 0, temperature_dC: int = 300, fault: int = 0,
                 state: int = 1, node_id: int = NODE_ID) -> tuple[int, bytes]:
    """TPDO1: displacement (nm), temperature (0.1 degC), fault bits, state."""
    return 0x180 + node_id, struct.pack("<hhBB", displacement_nm, temperature_dC, fault, state)


def emcy(code: int, register: int = 1, node_id: int = NODE_ID) -> tuple[int, bytes]:
    """EMCY: error code, error register, five manufacturer bytes (zero)."""
    return 0x080 + node_id, struct.pack("<HB5x", code, register)


def limit_values(*, stroke_um: float, lo_um: float, hi_um: float, slew: int = 0,
                 timeout_ms: int = 100, heartbeat_ms: int = 100) -> dict[tuple[int, int], bytes]:
    """What an amplifier answers to the reads of its limits (0x2200) and heartbeat time."""
    return {(0x2200, 1): struct.pack("<H", round(stroke_um * 1000)),
            (0x2200, 2): struct.pack("<h", round(lo_um * 1000)),
            (0x2200, 3): struct.pack("<h", round(hi_um * 1000)),
            (0x2200, 4): struct.pack("<H", slew),
            (0x2200, 5): struct.pack("<H", timeout_ms),
            (0x1017, 0): struct.pack("<H", heartbeat_ms)}


def read_request(data: bytes) -> tuple[int, int] | None:
    """``(index, subindex)`` of an SDO upload request, ``None`` for anything else."""
    if len(data) != 8 or data[0] != 0x40:
        return None
    index, sub = struct.unpack_from("<HB", data, 1)
    return index, sub


def answer(index: int, subindex: int, raw: bytes, node_id: int = NODE_ID) -> tuple[int, bytes]:
    """Expedited SDO upload response carrying the bytes ``raw`` (1..4)."""
    command = 0x43 | ((4 - len(raw)) << 2)
    return 0x580 + node_id, struct.pack("<BHB", command, index, subindex) + raw.ljust(4, b"\0")
