"""The piezo amplifier as a CANopen (CiA 301) device: its object dictionary, units and frames.

The contract is the EDS file ``config/piezo_amp.eds``; both ends load it with the ``canopen``
library (the service's master, :mod:`controller.fieldbus.canopen_amp`; the simulator's slave
nodes, :mod:`plant_sim.interfaces.canopen_node`). This module holds what both read from it, once:
the object indices, the units of the raw values, the fault bits and states, the EMCY codes and
the COB-IDs of the predefined connection set, plus :func:`describe_frame`, which decodes any frame
of a run against the EDS (a candump-style trace; ``docs/piezo_canopen.md``).

Pure: no bus, no threads.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import canopen
from canopen.objectdictionary import ObjectDictionary
from canopen.sdo.constants import (
    EXPEDITED,
    REQUEST_UPLOAD,
    RESPONSE_ABORTED,
    RESPONSE_UPLOAD,
    SDO_STRUCT,
    SIZE_SPECIFIED,
)

from config.loading import default_path

__all__ = [
    "EMCY_CODES",
    "HEARTBEAT_TIME",
    "STATUS_PERIOD_S",
    "Frame",
    "SdoProblem",
    "expected_lengths",
    "sdo_upload_request",
    "sdo_upload_value",
    "LIMITS",
    "OFFSETS",
    "STATUS",
    "COMMAND",
    "AmpFault",
    "AmpState",
    "DecodedFrame",
    "NmtState",
    "cob_ids",
    "describe_frame",
    "load_od",
    "nm_from_um",
    "um_from_nm",
]

EDS_NAME = "piezo_amp.eds"
OFFSETS = 0x2000
"""Offset table, ARRAY of INTEGER16, 1 nm per bit, sub-index k = knife k (1..8); RPDO1 (1-4),
RPDO2 (5-8)."""
COMMAND = 0x2010
"""Command RECORD: 1 enable (0/1), 2 knives (1..8), 3 the master's alive counter; RPDO3."""
STATUS = 0x2100
"""Status RECORD: 1 displacement (INTEGER16, nm), 2 temperature (INTEGER16, 0.1 degC), 3 fault
bits (:class:`AmpFault`), 4 state (:class:`AmpState`); TPDO1."""
LIMITS = 0x2200
"""Limits RECORD (read by SDO at start): 1 stroke (nm), 2 offset minimum (nm), 3 offset maximum
(nm), 4 slew maximum (um/ms, 0: not limited), 5 setpoint timeout (ms)."""
HEARTBEAT_TIME = 0x1017
"""Producer heartbeat time, ms."""
STATUS_PERIOD_S = 0.010
"""TPDO1 (the status) leaves every 10 ms (the EDS's event timer, 0x1800 sub 5)."""
NM_PER_UM = 1000.0
DECI_C_PER_C = 10.0
MAX_KNIVES = 8


class AmpFault(enum.IntFlag):
    """Fault bits of the amplifier's status."""

    OVER_TEMPERATURE = 1
    STROKE_LIMIT = 2
    SETPOINT_TIMEOUT = 4
    OVERCURRENT = 8


class AmpState(enum.IntEnum):
    """The amplifier's output state."""

    DISABLED = 0
    ENABLED = 1
    RAMPING = 2
    FAULT = 3


class NmtState(enum.IntEnum):
    """NMT states as the heartbeat carries them (CiA 301)."""

    BOOT_UP = 0
    STOPPED = 4
    OPERATIONAL = 5
    PRE_OPERATIONAL = 127


EMCY_CODES: Mapping[AmpFault, int] = {
    AmpFault.OVER_TEMPERATURE: 0x4210,  # temperature, device
    AmpFault.STROKE_LIMIT: 0xFF01,  # device specific: a table beyond the offset range
    AmpFault.SETPOINT_TIMEOUT: 0x8130,  # monitoring, life guard / heartbeat (the master's)
    AmpFault.OVERCURRENT: 0x2310,  # current, device output side
}
"""The EMCY error code the amplifier sends when a fault bit rises (0x0000 when all clear)."""


Frame = tuple[int, bytes]
"""A CAN frame as ``(arbitration_id, data)``."""


def load_od(node_id: int, path: str | Path | None = None) -> ObjectDictionary:
    """The amplifier's object dictionary for ``node_id`` (1..127) from the EDS file.

    Raises
    ------
    ValueError
        ``node_id`` outside 1..127.
    OSError
        The EDS file cannot be read.
    """
    if isinstance(node_id, bool) or not isinstance(node_id, int) or not 1 <= node_id <= 127:
        raise ValueError(f"node_id must be an integer in 1..127, got {node_id!r}")
    eds = Path(path) if path is not None else default_path(EDS_NAME)
    if not eds.is_file():
        raise FileNotFoundError(f"EDS file not found: {eds}")
    return canopen.import_od(str(eds), node_id)


def nm_from_um(value_um: float, *, name: str = "value_um") -> int:
    """A length in um as the INTEGER16 nm the dictionary holds (rounded; ValueError beyond)."""
    raw = round(float(value_um) * NM_PER_UM)
    if not -32768 <= raw <= 32767:
        raise ValueError(f"{name} = {value_um!r} µm is outside -32.768..32.767 µm")
    return int(raw)


def um_from_nm(raw_nm: int) -> float:
    """An INTEGER16 nm value as um."""
    return float(raw_nm) / NM_PER_UM


def cob_ids(node_id: int) -> dict[str, int]:
    """The predefined connection set of node ``node_id`` (CiA 301), by service."""
    return {"emcy": 0x080 + node_id, "tpdo1": 0x180 + node_id, "rpdo1": 0x200 + node_id,
            "rpdo2": 0x300 + node_id, "rpdo3": 0x400 + node_id, "sdo_tx": 0x580 + node_id,
            "sdo_rx": 0x600 + node_id, "heartbeat": 0x700 + node_id}


def expected_lengths(od: ObjectDictionary, node_id: int, *, receiver: str) -> dict[int, int]:
    """The COB-IDs one end of node ``node_id`` takes, each with its data length (DLC).

    ``receiver="master"``: what the amplifier sends (heartbeat, EMCY, SDO responses, TPDO1);
    ``receiver="node"``: what the master sends (NMT, SDO requests, RPDO1..3). A frame of
    another id, or of one of these with another length, is no frame of this node's services.
    """
    ids = cob_ids(node_id)
    if receiver == "master":
        return {ids["heartbeat"]: 1, ids["emcy"]: 8, ids["sdo_tx"]: 8,
                ids["tpdo1"]: pdo_length(od, 0x1A00)}
    if receiver == "node":
        return {0x000: 2, ids["sdo_rx"]: 8, ids["rpdo1"]: pdo_length(od, 0x1600),
                ids["rpdo2"]: pdo_length(od, 0x1601), ids["rpdo3"]: pdo_length(od, 0x1602)}
    raise ValueError(f"receiver must be 'master' or 'node', got {receiver!r}")


class SdoProblem(ValueError):
    """An SDO response that is no value of the object asked for (an abort, another object)."""


def sdo_upload_request(index: int, subindex: int) -> bytes:
    """The 8 bytes of an SDO upload (read) request of ``index``/``subindex`` (CiA 301)."""
    return SDO_STRUCT.pack(REQUEST_UPLOAD, index, subindex) + bytes(4)


def sdo_upload_value(response: bytes, index: int, subindex: int) -> bytes:
    """The value bytes of an expedited SDO upload response to ``index``/``subindex``.

    Raises
    ------
    SdoProblem
        An abort (naming its code), a response of another object or service, a segmented
        transfer (the amplifier's limits are 16-bit values: always expedited), not 8 bytes.
    """
    data = bytes(response)
    if len(data) != 8:
        raise SdoProblem(f"SDO response of {len(data)} bytes, expected 8")
    command, idx, sub = SDO_STRUCT.unpack_from(data)
    if command & 0xE0 == RESPONSE_ABORTED:
        (code,) = struct.unpack_from("<L", data, 4)
        raise SdoProblem(f"SDO abort 0x{code:08X} reading 0x{idx:04X}[{sub}]")
    if command & 0xE0 != RESPONSE_UPLOAD or (idx, sub) != (index, subindex):
        raise SdoProblem(f"SDO response 0x{command:02X} to 0x{idx:04X}[{sub}], expected an "
                         f"upload of 0x{index:04X}[{subindex}]")
    if not command & EXPEDITED:
        raise SdoProblem(f"SDO upload of 0x{index:04X}[{subindex}] is segmented, expected "
                         "an expedited one")
    size = 4 - ((command >> 2) & 0x3) if command & SIZE_SPECIFIED else 4
    return data[4:4 + size]


def _pdo_layout(od: ObjectDictionary, map_index: int) -> list[tuple[int, int, int]]:
    """(index, subindex, bits) of each object a PDO maps, from the EDS's mapping defaults."""
    rec = od[map_index]
    out = []
    for sub in range(1, int(rec[0].default) + 1):
        entry = int(rec[sub].default)
        out.append((entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF))
    return out


def pdo_length(od: ObjectDictionary, map_index: int) -> int:
    """Bytes of the PDO whose mapping parameter is ``map_index`` (0x1600.., 0x1A00..)."""
    return sum(bits for _, _, bits in _pdo_layout(od, map_index)) // 8


@dataclass(frozen=True)
class DecodedFrame:
    """One CAN frame read against the EDS.

    Attributes
    ----------
    service : str
        ``nmt``, ``heartbeat``, ``emcy``, ``tpdo1``, ``rpdo1``..``rpdo3``, ``sdo_tx``,
        ``sdo_rx``, ``sync`` or ``foreign`` (no service of a known node).
    node_id : int or None
        The node it is of (``None`` for NMT, SYNC and foreign frames).
    fields : dict
        What it carries, by the dictionary's names (a PDO's mapped objects, the NMT state,
        the EMCY code).
    problem : str or None
        Why it does not fit its service (wrong length), ``None`` when it does.
    """

    service: str
    node_id: int | None
    fields: dict[str, Any] = field(default_factory=dict)
    problem: str | None = None

    def line(self, can_id: int, data: bytes) -> str:
        """The frame as one candump-style line with its meaning."""
        node = "" if self.node_id is None else f" node {self.node_id}"
        what = ", ".join(f"{k}={v}" for k, v in self.fields.items())
        bad = f" ({self.problem})" if self.problem else ""
        return f"{can_id:03X} [{len(data)}] {bytes(data).hex(' ').upper()}  {self.service}{node}" \
               f"{': ' + what if what else ''}{bad}"


def _decode_pdo(od: ObjectDictionary, map_index: int, data: bytes) -> DecodedFrame:
    layout = _pdo_layout(od, map_index)
    want = sum(bits for _, _, bits in layout) // 8
    if len(data) != want:
        return DecodedFrame("", None, {}, f"{len(data)} bytes, the PDO maps {want}")
    out: dict[str, Any] = {}
    at = 0
    for index, sub, bits in layout:
        var = od[index][sub]
        chunk = bytes(data[at:at + bits // 8])
        at += bits // 8
        out[f"{od[index].name}.{var.name}"] = var.decode_raw(chunk)
    return DecodedFrame("", None, out)


def describe_frame(can_id: int, data: bytes,
                   dictionaries: Mapping[int, ObjectDictionary]) -> DecodedFrame:
    """What a frame is, for the nodes whose dictionaries are given (by node id).

    Never raises for any id or payload: a frame of no known service is ``foreign``, a frame of
    a known service with the wrong length carries its ``problem``.
    """
    data = bytes(data)
    if can_id == 0x000:
        if len(data) != 2:
            return DecodedFrame("nmt", None, {}, f"{len(data)} bytes, NMT has 2")
        return DecodedFrame("nmt", None, {"command": data[0], "node": data[1]})
    if can_id == 0x080:
        return DecodedFrame("sync", None)
    base, node_id = can_id & 0x780, can_id & 0x7F
    od = dictionaries.get(node_id) if node_id else None
    if od is None or can_id > 0x7FF:
        return DecodedFrame("foreign", None)
    if base == 0x700:
        if len(data) != 1:
            return DecodedFrame("heartbeat", node_id, {}, f"{len(data)} bytes, heartbeat has 1")
        state = data[0] & 0x7F
        name = NmtState(state).name if state in NmtState._value2member_map_ else str(state)
        return DecodedFrame("heartbeat", node_id, {"state": name})
    if base == 0x080:
        if len(data) != 8:
            return DecodedFrame("emcy", node_id, {}, f"{len(data)} bytes, EMCY has 8")
        code, register = struct.unpack_from("<HB", data)
        return DecodedFrame("emcy", node_id, {"code": f"0x{code:04X}", "register": register})
    pdos = {0x180: ("tpdo1", 0x1A00), 0x200: ("rpdo1", 0x1600), 0x300: ("rpdo2", 0x1601),
            0x400: ("rpdo3", 0x1602)}
    if base in pdos:
        service, map_index = pdos[base]
        d = _decode_pdo(od, map_index, data)
        return DecodedFrame(service, node_id, d.fields, d.problem)
    if base in (0x580, 0x600):
        service = "sdo_tx" if base == 0x580 else "sdo_rx"
        if len(data) != 8:
            return DecodedFrame(service, node_id, {}, f"{len(data)} bytes, SDO has 8")
        index, sub = struct.unpack_from("<HB", data, 1)
        name = od[index].name if index in od else f"0x{index:04X}"
        return DecodedFrame(service, node_id, {"command": f"0x{data[0]:02X}",
                                               "object": f"{name}[{sub}]"})
    return DecodedFrame("foreign", None)
