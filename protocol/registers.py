"""The PLC's Modbus register map (``config/registers.toml``): a pure, sans-I/O codec.

The map lists holding registers; ``u16`` values take one register, ``u32``/``i32``/``f32`` two,
in the word order the TOML file names (``"big"``: the register at ``address`` holds the high
16 bits). This module turns values into register words and back, resolves the limits of
writable registers (a limit may name another register) and decides whether a write is allowed.
It imports no Modbus library; the PLC server (``plant_sim/interfaces/plc_server.py``) and the
service's
client (``controller/fieldbus/plc_client.py``) both build on it.

Errors
------
A write to a read-only register, to an address no register covers, or to half of a 32-bit
register raises :class:`RegisterAccessError` (the server answers Modbus exception 02, ILLEGAL
DATA ADDRESS). A value outside the register's limits raises :class:`RegisterRangeError`
(exception 03, ILLEGAL DATA VALUE). Both derive from ``ValueError`` and name the register.

Facts both sides share, written once here
-----------------------------------------
* :class:`MachineState` and :class:`PlcFault`: the flag bits of the ``machine_state`` and
  ``faults`` registers. The TOML file lists the same bits (``bits = [...]``, bit 0 first) for
  readers of the contract; :meth:`RegisterMap.load` refuses a file whose list differs.
* :data:`WRITE_DISPATCH` and :func:`apply_writes`: what the PLC does with an accepted write of
  each writable register (``feed_setpoint_mm_s`` -> ``set_feed_setpoint``, ``heartbeat_service``
  -> ``set_service_heartbeat``), used by the simulator's server and the service's in-process bus.
"""

from __future__ import annotations

import enum
import functools
import math
import struct
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from types import MappingProxyType
from typing import Protocol

import numpy as np

from config.loading import Section, default_path, load_toml, naming_file
from core.errors import ConfigError

TYPES: dict[str, int] = {"u16": 1, "u32": 2, "i32": 2, "f32": 2}
"""Register types and how many 16-bit registers each takes."""

ACCESS = ("ro", "rw")
WORD_ORDERS = ("big", "little")
"""Word orders of 32-bit values; the first is the default."""
DEFAULT_UNIT_ID = 1
"""Modbus unit id when the map's ``[map]`` table names none."""

_INT_RANGE: dict[str, tuple[int, int]] = {
    "u16": (0, 0xFFFF),
    "u32": (0, 0xFFFF_FFFF),
    "i32": (-0x8000_0000, 0x7FFF_FFFF),
}
_F32_MAX = float(np.finfo(np.float32).max)



class ModbusException(enum.IntEnum):
    """Modbus exception codes the PLC answers with (Modbus application protocol 1.1b3, 7).

    ``ModbusException(2).text`` is the name the spec gives (``"ILLEGAL DATA ADDRESS"``).
    """

    ILLEGAL_FUNCTION = 0x01
    ILLEGAL_DATA_ADDRESS = 0x02
    ILLEGAL_DATA_VALUE = 0x03
    SERVER_DEVICE_FAILURE = 0x04
    SERVER_DEVICE_BUSY = 0x06
    GATEWAY_TARGET_FAILED = 0x0B

    @property
    def text(self) -> str:
        """The spec's name, words separated by spaces."""
        if self is ModbusException.GATEWAY_TARGET_FAILED:
            return "GATEWAY TARGET DEVICE FAILED TO RESPOND"
        return str(self.name).replace("_", " ")


MODBUS_ILLEGAL_DATA_ADDRESS = int(ModbusException.ILLEGAL_DATA_ADDRESS)
MODBUS_ILLEGAL_DATA_VALUE = int(ModbusException.ILLEGAL_DATA_VALUE)

HOLDING_FUNCTION_CODES = (3, 6, 16, 23)
"""Modbus functions on holding registers: read (3), write one (6), write several (16),
read/write (23). A map offers these (``[map] function_codes``, default all four)."""

Value = float | int
Limit = float | int | str | None


class MachineState(enum.IntFlag):
    """Bits of the ``machine_state`` register (``config/registers.toml``, ``bits``)."""

    RUNNING = 1 << 0
    """Spindle running, feed enabled, no e-stop."""
    BOARD_PRESENT = 1 << 1
    """A board is under the camera."""
    ESTOP = 1 << 2
    """The e-stop is active."""
    SPINDLE_RUNNING = 1 << 3
    """The spindle runs at speed."""
    FEED_ENABLED = 1 << 4
    """The feed drive is enabled."""


class PlcFault(enum.IntFlag):
    """Bits of the ``faults`` register (``config/registers.toml``, ``bits``)."""

    FEED_DRIVE = 1 << 0
    """The feed drive tripped."""
    SPINDLE_STOPPED = 1 << 1
    """The spindle drive tripped (coasting or stopped)."""
    ENCODER = 1 << 2
    """The feed encoder stopped counting."""
    HEARTBEAT_LOST = 1 << 3
    """The service heartbeat did not change within ``watchdog_ms``."""
    PIEZO_AMPLIFIER = 1 << 4
    """The piezo amplifier reports a fault."""


class HeadFault(enum.IntFlag):
    """Bits of a head block's ``head_faults`` register (``[[heads.register]]``, ``bits``)."""

    AMPLIFIER = 1 << 0
    """The head's piezo amplifier reports a fault."""
    SPINDLE = 1 << 1
    """The head's spindle drive tripped (coasting or stopped)."""
    CAMERA_SILENT = 1 << 2
    """The head's camera sends no frames."""


BIT_FLAGS: Mapping[str, type[enum.IntFlag]] = MappingProxyType(
    {"machine_state": MachineState, "faults": PlcFault, "head_faults": HeadFault}
)
"""Registers whose bits are declared here, by register name."""


def flag_names(flags: type[enum.IntFlag]) -> tuple[str, ...]:
    """The TOML ``bits`` list of a flag enum: lower-case member names, bit 0 first."""
    members = sorted(flags, key=lambda m: m.value)
    if [m.value for m in members] != [1 << i for i in range(len(members))]:
        raise ValueError(f"{flags.__name__}: bits must be 0, 1, 2, ... without gaps")
    return tuple(str(m.name).lower() for m in members)


class RegisterAccessError(ValueError):
    """A write (or read) touches a read-only register, a gap, or half of a 32-bit register.

    Attributes
    ----------
    exception_code : int
        The Modbus exception code a server answers with (2, ILLEGAL DATA ADDRESS).
    """

    exception_code = MODBUS_ILLEGAL_DATA_ADDRESS


class RegisterRangeError(ValueError):
    """A value lies outside the register's type or its ``[min, max]`` limits.

    Attributes
    ----------
    exception_code : int
        The Modbus exception code a server answers with (3, ILLEGAL DATA VALUE).
    """

    exception_code = MODBUS_ILLEGAL_DATA_VALUE


@dataclass(frozen=True)
class Register:
    """One entry of the register map.

    Attributes
    ----------
    name : str
        Unique name (also the key in ``Machine.register_values()``).
    address : int
        First holding-register address (0-based protocol address).
    type : str
        ``"u16"``, ``"u32"``, ``"i32"`` or ``"f32"``.
    access : str
        ``"ro"`` (writes refused) or ``"rw"``.
    count : int
        Number of 16-bit registers (1 or 2).
    min, max : float, int, str or None
        Write limits: a number, the name of another register whose current value is the limit,
        or ``None`` (the type's own range).
    unit : str
        Physical unit (``"mm/s"``), empty when dimensionless.
    description : str
        What the register holds.
    bits : tuple of str
        Names of the flag bits, bit 0 first (``u16``/``u32`` registers only); empty otherwise.
    """

    name: str
    address: int
    type: str
    access: str
    count: int
    min: Limit = None
    max: Limit = None
    unit: str = ""
    description: str = ""
    bits: tuple[str, ...] = ()

    @property
    def last_address(self) -> int:
        """Address of the register's last 16-bit word."""
        return self.address + self.count - 1

    @property
    def writable(self) -> bool:
        """Whether the register accepts writes."""
        return self.access == "rw"


@dataclass(frozen=True)
class HeadBlock:
    """The per-head register blocks (``[heads]`` of ``config/registers.toml``).

    Block ``i`` covers ``base + i * stride`` .. ``base + (i + 1) * stride - 1``; every block
    holds :attr:`registers` at the same offsets.

    Attributes
    ----------
    base : int
        Address of block 0.
    stride : int
        Words from one block to the next.
    count : int
        Number of blocks (heads the PLC can serve).
    registers : tuple of Register
        The block's registers, ``address`` being the offset inside the block; an entry named
        like a register of the single map carries that register's type, unit and description.
    read_across : bool
        The PLC answers one read that runs across consecutive blocks it serves (the reserved
        words read 0): a client may read several heads' blocks in one request
        (``[heads] read_across``; default ``False``: a read stays in one block).
    """

    base: int
    stride: int
    count: int
    registers: tuple[Register, ...]
    read_across: bool = False

    @functools.cached_property
    def used(self) -> int:
        """Words of a block its registers cover (offset 0 to the last register's last word).

        Worked out once (a moulder's PLC cycle asks for it for every head).
        """
        return max(r.last_address for r in self.registers) + 1

    @property
    def names(self) -> tuple[str, ...]:
        """The block's register names, in offset order."""
        return tuple(r.name for r in sorted(self.registers, key=lambda r: r.address))

    def address(self, head: int) -> int:
        """First address of head ``head``'s block (``ValueError`` naming a bad index)."""
        if isinstance(head, bool) or not isinstance(head, (int, np.integer)):
            raise ValueError(f"head must be an integer, got {head!r}")
        if not 0 <= int(head) < self.count:
            raise ValueError(f"head {head!r} outside the map's blocks 0..{self.count - 1}")
        return self.base + int(head) * self.stride

    def head_at(self, address: int) -> int | None:
        """Index of the block covering ``address`` (reserved words included), or ``None``."""
        i, rest = divmod(int(address) - self.base, self.stride)
        return i if 0 <= i < self.count and rest >= 0 else None

    def placed(self, head: int) -> tuple[Register, ...]:
        """The block's registers at head ``head``'s addresses."""
        a0 = self.address(head)
        return tuple(replace(r, address=a0 + r.address) for r in self.registers)


def _check_value(reg: Register, value: object) -> Value:
    """Return ``value`` as the Python type of ``reg`` or raise ``RegisterRangeError``."""
    if isinstance(value, (bool, np.bool_)):
        raise RegisterRangeError(f"register {reg.name}: expected a number, got {value!r}")
    if reg.type == "f32":
        try:
            v = float(value)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise RegisterRangeError(
                f"register {reg.name}: expected a number, got {value!r}"
            ) from None
        if not math.isfinite(v) or abs(v) > _F32_MAX:
            raise RegisterRangeError(
                f"register {reg.name}: {value!r} is not a finite float32 value"
            )
        return v
    if isinstance(value, (int, np.integer)):
        iv = int(value)
    elif (
        isinstance(value, (float, np.floating))
        and math.isfinite(value)
        and float(value).is_integer()
    ):
        iv = int(value)
    else:
        raise RegisterRangeError(
            f"register {reg.name} ({reg.type}): expected an integer, got {value!r}"
        )
    lo, hi = _INT_RANGE[reg.type]
    if not lo <= iv <= hi:
        raise RegisterRangeError(
            f"register {reg.name} ({reg.type}): {iv} outside the type's range [{lo}, {hi}]"
        )
    return iv


class RegisterMap:
    """The register map: lookup, encoding, decoding and write checks.

    Build it with :meth:`load`; everything is set up once.

    Parameters
    ----------
    registers : sequence of Register
        The registers (validated: unique names, no overlaps, limits that resolve).
    unit_id : int
        Modbus unit (slave) id of the PLC.
    word_order : str
        ``"big"`` (high word first, the default) or ``"little"``.
    """

    def __init__(
        self,
        registers: Sequence[Register],
        *,
        unit_id: int = DEFAULT_UNIT_ID,
        word_order: str = WORD_ORDERS[0],
        function_codes: Sequence[int] = HOLDING_FUNCTION_CODES,
        heads: HeadBlock | None = None,
        head: int | None = None,
    ) -> None:
        self.heads = heads
        """The per-head blocks (``None``: the map has none); the same object in every view."""
        self.head = head
        """The head this map is the view of (:meth:`for_head`); ``None`` for the whole map."""
        if word_order not in WORD_ORDERS:
            raise ConfigError(f"map.word_order must be big or little, got {word_order!r}")
        self.unit_id = unit_id
        self.word_order = word_order
        codes = [int(c) for c in function_codes]
        bad = [c for c in codes if c not in HOLDING_FUNCTION_CODES]
        if bad or not codes or 3 not in codes:
            raise ConfigError(
                f"map.function_codes must include 3 and be among {list(HOLDING_FUNCTION_CODES)},"
                f" got {codes}"
            )
        self.function_codes: frozenset[int] = frozenset(codes)
        """The Modbus functions the PLC offers; a server answers others with exception 01."""
        self.registers: dict[str, Register] = {}
        for reg in registers:
            if reg.name in self.registers:
                raise ConfigError(f"register {reg.name}: duplicate name")
            self.registers[reg.name] = reg
        if not self.registers:
            raise ConfigError("register map has no registers")
        self._by_address: dict[int, Register] = {}
        for reg in sorted(self.registers.values(), key=lambda r: r.address):
            for a in range(reg.address, reg.address + reg.count):
                other = self._by_address.get(a)
                if other is not None:
                    raise ConfigError(
                        f"register {reg.name}: address {a} overlaps register {other.name}"
                    )
                self._by_address[a] = reg
        for reg in self.registers.values():
            self._validate_limits(reg)
            _validate_bits(reg)
        first = min(r.address for r in self.registers.values())
        last = max(r.last_address for r in self.registers.values())
        self._span = (first, last - first + 1)
        self._single = tuple(registers)
        self._common_span = self._span
        self._views: dict[int, RegisterMap] = {}
        self._whole: RegisterMap = self
        self._plans: dict[tuple[int, int], _DecodePlan | None] = {}
        if heads is not None and head is None:
            _validate_heads(self, heads)
            self._views = {i: self.for_head(i) for i in range(heads.count)}

    # ------------------------------------------------------------------ heads
    @property
    def whole(self) -> RegisterMap:
        """The whole map this is a view of (the map itself when it is no view)."""
        return self._whole

    @property
    def head_count(self) -> int:
        """Number of per-head blocks in the map (0 without ``[heads]``)."""
        return 0 if self.heads is None else self.heads.count

    def for_head(self, i: int) -> RegisterMap:
        """Head ``i``'s view of the map.

        The block's registers carry their names (``spindle_rpm``, ``knives``, ...,
        ``spindle_setpoint_rpm``) at head ``i``'s block addresses; the other registers of the
        single map (heartbeats, feed, encoder, machine state, ...) are unchanged. Encoding,
        decoding and write checks work on the view as on the map, so a
        ``controller.fieldbus.plc_protocol.PlcSnapshot`` of a view reads head ``i``'s values.

        Parameters
        ----------
        i : int
            Head index, ``0 <= i < head_count``.

        Returns
        -------
        RegisterMap
            The view (:attr:`head` is ``i``; :meth:`common_span` and :meth:`head_span` say
            where its two ranges lie). Views are built once; the same object is returned.

        Raises
        ------
        ValueError
            The map has no ``[heads]`` or ``i`` is outside ``0..head_count - 1``.
        """
        if self.heads is None:
            raise ValueError(f"head {i!r}: the register map has no [heads] blocks")
        self.heads.address(i)  # checks i
        if self._whole is not self:  # a view of a view: the whole map's
            return self._whole.for_head(i)
        view = self._views.get(int(i))
        if view is not None:
            return view
        return _head_view(self, self.heads, int(i))

    def common_span(self) -> tuple[int, int]:
        """First address and words of the single map (the whole map's :meth:`span`).

        In a view it holds the machine-wide registers; the words of the first head's legacy
        fields (``spindle_rpm`` at 12, ...) are gaps of the view.
        """
        return self._common_span

    def head_span(self, i: int | None = None) -> tuple[int, int]:
        """First address and used words of a head's block (default: the view's own head).

        Raises
        ------
        ValueError
            No ``[heads]``, no head given on the whole map, or a bad index.
        """
        if self.heads is None:
            raise ValueError("the register map has no [heads] blocks")
        head = self.head if i is None else i
        if head is None:
            raise ValueError("head_span of the whole map needs a head index")
        return self.heads.address(head), self.heads.used

    def read_ranges(self) -> tuple[tuple[int, int], ...]:
        """The ``(address, words)`` ranges a client reads to sample every register of this map.

        The whole map (or one without heads): its span, one request. A head's view: the
        common span, then the head's block.
        """
        if self.head is None:
            return (self._span,)
        return (self._common_span, self.head_span())

    # ------------------------------------------------------------------ loading
    @classmethod
    def load(cls, path: str | Path | None = None) -> RegisterMap:
        """Load and validate a register map TOML file; every error names the file.

        Parameters
        ----------
        path : str or Path, optional
            The TOML file; default ``config/registers.toml`` shipped with the package.

        Returns
        -------
        RegisterMap

        Raises
        ------
        ConfigError
            Malformed file, unknown keys, bad types or access, overlapping addresses, limits that
            name no register, flag bits that differ from :data:`BIT_FLAGS`; the message names
            the file and the register (``registers.toml: register faults: bits ...``).
        """
        p = Path(default_path("registers.toml") if path is None else path)
        doc = load_toml(p)
        with naming_file(p):
            return cls.from_dict(doc)

    @classmethod
    def from_dict(cls, doc: Mapping[str, object]) -> RegisterMap:
        """A register map from a parsed TOML document (errors name the register, not a file).

        Raises
        ------
        ConfigError
            As :meth:`load`, without the file name.
        """
        top = Section(doc, "")
        m = top.section("map", required=False)
        unit_id = m.integer("unit_id", DEFAULT_UNIT_ID, lo=0, hi=255)
        word_order = m.string("word_order", WORD_ORDERS[0], choices=WORD_ORDERS)
        codes = m.raw("function_codes", list(HOLDING_FUNCTION_CODES))
        if not isinstance(codes, list) or not all(
            isinstance(c, int) and not isinstance(c, bool) for c in codes
        ):
            raise ConfigError(f"map.function_codes must be a list of integers, got {codes!r}")
        m.reject_unknown()
        raw = top.raw("register")
        if not isinstance(raw, list):
            raise ConfigError("register must be an array of tables ([[register]])")
        regs = [_parse_register(entry, f"register[{i}]") for i, entry in enumerate(raw)]
        heads = _parse_heads(top.section("heads", required=False), top.has("heads"), regs)
        top.reject_unknown()
        return cls(
            regs, unit_id=unit_id, word_order=word_order, function_codes=codes, heads=heads
        )

    def _validate_limits(self, reg: Register) -> None:
        for key in ("min", "max"):
            lim = getattr(reg, key)
            if isinstance(lim, str):
                if lim == reg.name:
                    raise ConfigError(f"register {reg.name}: {key} names the register itself")
                if lim not in self.registers:
                    raise ConfigError(f"register {reg.name}: {key} names unknown register {lim!r}")
            elif lim is not None:
                try:
                    _check_value(reg, lim)
                except RegisterRangeError as exc:
                    raise ConfigError(f"register {reg.name}: {key}: {exc}") from None
        if isinstance(reg.min, (int, float)) and isinstance(reg.max, (int, float)):
            if reg.min > reg.max:
                raise ConfigError(f"register {reg.name}: min {reg.min} > max {reg.max}")

    # ------------------------------------------------------------------ lookup
    def __getitem__(self, name: str) -> Register:
        """The register called ``name`` (``KeyError`` naming it otherwise)."""
        try:
            return self.registers[name]
        except KeyError:
            raise KeyError(f"unknown register {name!r}") from None

    def __contains__(self, name: object) -> bool:
        return name in self.registers

    def __iter__(self):
        return iter(sorted(self.registers.values(), key=lambda r: r.address))

    def __getstate__(self) -> dict[str, object]:
        """The map's state without its decode plans (``struct.Struct`` does not pickle).

        A map goes to other processes (the PLC simulator's server process is spawned with
        it) whether or not it has decoded words yet; the plans are built again there.
        """
        state = self.__dict__.copy()
        state["_plans"] = {}
        return state

    def span(self) -> tuple[int, int]:
        """First address and number of 16-bit registers covered (gaps included)."""
        return self._span

    def at(self, address: int) -> Register | None:
        """The register covering ``address`` or ``None`` (a gap or outside the map)."""
        return self._by_address.get(address)

    def _reg(self, name: str) -> Register:
        reg = self.registers.get(name)
        if reg is None:
            raise ValueError(f"unknown register {name!r}")
        return reg

    def markdown_table(self) -> str:
        """The map as Markdown (``docs/register_map.md`` holds it; a test compares).

        The single map's registers, then (a map with ``[heads]``) the head block: one row per
        block register with its offset and its address in block 0.
        """
        return _markdown(list(self), self.heads)

    # ------------------------------------------------------------------ codec
    def encode(self, name: str, value: float | int) -> list[int]:
        """Register words holding ``value``.

        Parameters
        ----------
        name : str
            Register name.
        value : float or int
            The value; integers for ``u16``/``u32``/``i32`` (integral floats accepted), any finite
            float32-representable number for ``f32`` (rounded to float32).

        Returns
        -------
        list of int, length ``count``
            Words 0..65535 in the map's word order.

        Raises
        ------
        RegisterRangeError
            (a ``ValueError``) naming the register when the value does not fit the type.
        """
        reg = self._reg(name)
        v = _check_value(reg, value)
        if reg.type == "u16":
            return [int(v)]
        if reg.type == "f32":
            raw = struct.unpack(">I", struct.pack(">f", v))[0]
        elif reg.type == "i32":
            raw = int(v) & 0xFFFF_FFFF
        else:
            raw = int(v)
        hi, lo = raw >> 16, raw & 0xFFFF
        return [hi, lo] if self.word_order == "big" else [lo, hi]

    def decode(self, name: str, words: Sequence[int]) -> float | int:
        """Value held by ``words`` (``count`` words in the map's word order).

        Returns
        -------
        float or int
            ``float`` for ``f32`` (the exact float32 value), ``int`` otherwise.

        Raises
        ------
        ValueError
            Wrong number of words or a word outside 0..65535, naming the register.
        """
        reg = self._reg(name)
        ws = [int(w) for w in words]
        if len(ws) != reg.count:
            raise ValueError(f"register {name}: expected {reg.count} words, got {len(ws)}")
        if any(not 0 <= w <= 0xFFFF for w in ws):
            raise ValueError(f"register {name}: words must be 0..65535, got {ws}")
        if reg.type == "u16":
            return ws[0]
        hi, lo = (ws[0], ws[1]) if self.word_order == "big" else (ws[1], ws[0])
        raw = (hi << 16) | lo
        if reg.type == "u32":
            return raw
        if reg.type == "i32":
            return raw - 0x1_0000_0000 if raw & 0x8000_0000 else raw
        return float(struct.unpack(">f", struct.pack(">I", raw))[0])

    def encode_block(self, values: Mapping[str, float | int]) -> list[int]:
        """Words of the whole span (``span()``); registers missing from ``values`` and gaps are 0.

        Raises
        ------
        ValueError
            An unknown register name or a value that does not fit its type.
        """
        first, count = self._span
        out = [0] * count
        for name, value in values.items():
            reg = self._reg(name)
            out[reg.address - first : reg.address - first + reg.count] = self.encode(name, value)
        return out

    def decode_block(
        self, words: Sequence[int], start: int | None = None
    ) -> dict[str, float | int]:
        """Values of every register lying wholly inside ``words`` read from address ``start``.

        Parameters
        ----------
        words : sequence of int
            Consecutive register words.
        start : int, optional
            Address of ``words[0]``; default the first address of the span.

        Returns
        -------
        dict
            Register name to value, in address order.
        """
        s = self._span[0] if start is None else int(start)
        out = _decode_planned(self, words, s)
        return _decode_each(self, words, s) if out is None else out

    # ------------------------------------------------------------------ limits and writes
    def limits(self, name: str, values: Mapping[str, float | int]) -> tuple[float, float]:
        """Lower and upper write limit of ``name``, resolving limits that name other registers.

        Parameters
        ----------
        name : str
            Register name.
        values : mapping
            Current register values (used only for limits that name another register).

        Returns
        -------
        (lo, hi) : tuple of float
            The type's range where no limit is given.

        Raises
        ------
        ValueError
            A referenced register has no value in ``values``.
        """
        reg = self._reg(name)
        if reg.type == "f32":
            type_lo, type_hi = -_F32_MAX, _F32_MAX
        else:
            type_lo, type_hi = _INT_RANGE[reg.type]
        out = []
        for lim, default in ((reg.min, type_lo), (reg.max, type_hi)):
            if lim is None:
                out.append(default)
            elif isinstance(lim, str):
                if lim not in values:
                    raise ValueError(f"register {name}: limit register {lim} has no current value")
                out.append(values[lim])
            else:
                out.append(lim)
        return out[0], out[1]

    def check_write(
        self, name: str, value: float | int, current_values: Mapping[str, float | int]
    ) -> float | int:
        """Check that writing ``value`` to ``name`` is allowed; return the value as stored.

        The value is checked as it will be stored (an ``f32`` is rounded to float32 first), so a
        value that passes can be encoded and read back unchanged.

        Raises
        ------
        RegisterAccessError
            The register is read-only (Modbus exception 02).
        RegisterRangeError
            The value does not fit the type or lies outside ``limits`` (exception 03).
        """
        reg = self._reg(name)
        if not reg.writable:
            raise RegisterAccessError(f"register {name} is read-only")
        stored = self.decode(name, self.encode(name, value))
        lo, hi = self.limits(name, current_values)
        if reg.type == "f32":  # compare as stored: a limit read back from an f32 register passes
            lo, hi = _as_f32(lo), _as_f32(hi)
        if not lo <= stored <= hi:
            raise RegisterRangeError(f"register {name}: {value!r} outside [{lo}, {hi}]")
        return stored

    def parse_write(
        self,
        address: int,
        words: Sequence[int],
        current_values: Mapping[str, float | int],
    ) -> dict[str, float | int]:
        """Turn a Modbus write (function 6 or 16) into register values, checking every rule.

        The whole write is refused when any part is refused (no partial writes).

        Parameters
        ----------
        address : int
            First address written.
        words : sequence of int
            The words written.
        current_values : mapping
            Current register values (for limits naming other registers).

        Returns
        -------
        dict
            Register name to the accepted value, for every register the write covers.

        Raises
        ------
        RegisterAccessError
            The write touches a gap, a read-only register, or only part of a 32-bit register.
        RegisterRangeError
            A value outside its limits.
        """
        a0 = int(address)
        n = len(words)
        if n == 0:
            raise RegisterAccessError("empty write")
        covered: list[Register] = []
        for a in range(a0, a0 + n):
            reg = self._by_address.get(a)
            if reg is None:
                raise RegisterAccessError(f"address {a} holds no register")
            if not covered or covered[-1] is not reg:
                covered.append(reg)
        for reg in covered:
            if reg.address < a0 or reg.last_address >= a0 + n:
                raise RegisterAccessError(
                    f"register {reg.name}: a write must cover all {reg.count} words"
                )
            if not reg.writable:
                raise RegisterAccessError(f"register {reg.name} is read-only")
        merged = dict(current_values)
        decoded = {
            reg.name: self.decode(reg.name, words[reg.address - a0 : reg.address - a0 + reg.count])
            for reg in covered
        }
        merged.update(decoded)
        return {name: self.check_write(name, v, merged) for name, v in decoded.items()}


class WriteTarget(Protocol):
    """What a PLC applies accepted writes to (``plant_sim.machine.machine.Machine`` is one)."""

    def set_feed_setpoint(self, feed_mm_s: float) -> None:
        """New feed setpoint, mm/s; ``ValueError`` when the machine refuses it."""

    def set_service_heartbeat(self, value: int) -> None:
        """New service heartbeat (0..65535); feeds the PLC's watchdog."""


WRITE_DISPATCH: Mapping[str, Callable[[WriteTarget, float | int], None]] = MappingProxyType(
    {
        "feed_setpoint_mm_s": lambda target, v: target.set_feed_setpoint(float(v)),
        "heartbeat_service": lambda target, v: target.set_service_heartbeat(int(v)),
    }
)
"""What the PLC does with an accepted write, by register name (every ``rw`` register of the
shipped map has an entry; a test checks)."""


def apply_writes(target: WriteTarget, accepted: Mapping[str, float | int]) -> None:
    """Apply the values :meth:`RegisterMap.parse_write` accepted to ``target``, in order.

    Parameters
    ----------
    target : WriteTarget
        The machine (or anything with its ``set_*`` methods).
    accepted : mapping
        Register name to value, as returned by ``parse_write``.

    Raises
    ------
    RegisterAccessError
        A register without an entry in :data:`WRITE_DISPATCH` (Modbus exception 02).
    RegisterRangeError
        The target refused the value with ``ValueError`` (exception 03); names the register.
    """
    for name in accepted:
        if name not in WRITE_DISPATCH:
            raise RegisterAccessError(f"register {name}: the PLC applies no writes to it")
    for name, value in accepted.items():
        try:
            WRITE_DISPATCH[name](target, value)
        except RegisterRangeError:
            raise
        except ValueError as exc:
            raise RegisterRangeError(f"register {name}: {exc}") from None


class HeadWriteTarget(Protocol):
    """What a PLC applies accepted writes of a head block to (``Machine``, ``Moulder``)."""

    def set_spindle_setpoint(self, head: int, rpm: float) -> None:
        """New spindle setpoint of head ``head``, rpm; ``ValueError`` when refused."""


HEAD_WRITE_DISPATCH: Mapping[str, Callable[[HeadWriteTarget, int, float | int], None]] = (
    MappingProxyType(
        {
            "spindle_setpoint_rpm": lambda target, head, v: target.set_spindle_setpoint(
                head, float(v)
            ),
        }
    )
)
"""What the PLC does with an accepted write to a head block, by register name (every ``rw``
register of the shipped block has an entry; a test checks)."""


def apply_head_writes(
    target: HeadWriteTarget, head: int, accepted: Mapping[str, float | int]
) -> None:
    """Apply values a head view's ``parse_write`` accepted to head ``head`` of ``target``.

    Raises
    ------
    RegisterAccessError
        A register without an entry in :data:`HEAD_WRITE_DISPATCH` (exception 02).
    RegisterRangeError
        The target refused the value with ``ValueError`` (exception 03); names the register.
    """
    for name in accepted:
        if name not in HEAD_WRITE_DISPATCH:
            raise RegisterAccessError(f"register {name} of head {head}: the PLC applies no "
                                      "writes to it")
    for name, value in accepted.items():
        try:
            HEAD_WRITE_DISPATCH[name](target, head, value)
        except RegisterRangeError:
            raise
        except ValueError as exc:
            raise RegisterRangeError(f"register {name} of head {head}: {exc}") from None


@dataclass(frozen=True)
class _DecodePlan:
    """One struct unpacking of a block's words into its registers' values (big word order)."""

    words: struct.Struct
    values: struct.Struct
    names: tuple[str, ...]


_NO_PLAN = object()
_MAX_PLANS = 64
"""Decode plans a map keeps (one per ``(start, words)`` read)."""
_VALUE_CODES = {"u16": "H", "u32": "I", "i32": "i", "f32": "f"}


def _decode_planned(rmap: RegisterMap, words: Sequence[int],
                    start: int) -> dict[str, float | int] | None:
    """:meth:`RegisterMap.decode_block` in one struct unpacking (its plan kept on the map).

    ``None`` when there is no plan (word order little) or the words do not pack (a word outside
    0..65535 or not an integer: :func:`_decode_each`'s checks then name it).
    """
    key = (start, len(words))
    plan = rmap._plans.get(key, _NO_PLAN)
    if plan is _NO_PLAN:
        plan = _decode_plan(rmap, start, len(words))
        if len(rmap._plans) < _MAX_PLANS:  # the reads a client makes, not every fuzzed one
            rmap._plans[key] = plan
    if plan is None:
        return None
    try:
        raw = plan.words.pack(*words)
    except struct.error:
        return None
    return dict(zip(plan.names, plan.values.unpack(raw), strict=True))


def _decode_each(rmap: RegisterMap, words: Sequence[int], s: int) -> dict[str, float | int]:
    """:meth:`RegisterMap.decode_block` register by register (with its decode's checks)."""
    end = s + len(words)
    out: dict[str, float | int] = {}
    for reg in rmap:
        if reg.address >= s and reg.last_address < end:
            i = reg.address - s
            out[reg.name] = rmap.decode(reg.name, words[i : i + reg.count])
    return out


def _decode_plan(rmap: RegisterMap, start: int, count: int) -> _DecodePlan | None:
    """The plan decoding ``count`` words read from ``start`` (``None``: word order little).

    Big-endian words packed as bytes are the registers' big-endian values one after the other:
    ``>f`` of a float32's two words is the exact float32 value :meth:`RegisterMap.decode`
    gives, ``>I`` / ``>i`` / ``>H`` its integers; gaps and registers cut by the block's ends
    are skipped.
    """
    if rmap.word_order != "big":
        return None
    fmt, names, at = [">"], [], start
    for reg in rmap:
        if reg.address >= start and reg.last_address < start + count:
            if reg.address > at:
                fmt.append(f"{2 * (reg.address - at)}x")
            fmt.append(_VALUE_CODES[reg.type])
            names.append(reg.name)
            at = reg.address + reg.count
    if start + count > at:
        fmt.append(f"{2 * (start + count - at)}x")
    return _DecodePlan(words=struct.Struct(f">{count}H"), values=struct.Struct("".join(fmt)),
                       names=tuple(names))


def _parse_register(entry: object, where: str, offset_of: str = "") -> Register:
    """One ``[[register]]`` entry (``offset_of``: a ``[[heads.register]]`` entry, by offset)."""
    if not isinstance(entry, Mapping):
        raise ConfigError(f"{where} must be a table")
    label = entry.get("name") if isinstance(entry.get("name"), str) else where
    s = Section(entry, f"{'heads.' if offset_of else ''}register {label}")
    name = s.string("name")
    if not name.isidentifier():
        raise ConfigError(f"register {name!r}: name must be an identifier")
    rtype = s.string("type", choices=tuple(TYPES))
    key = "offset" if offset_of else "address"
    reg = Register(
        name=name,
        address=s.integer(key, lo=0, hi=0xFFFF - TYPES[rtype] + 1),
        type=rtype,
        access=s.string("access", choices=ACCESS),
        count=TYPES[rtype],
        min=_limit(s, "min"),
        max=_limit(s, "max"),
        unit=s.string("unit", Register.unit),
        description=s.string("description", Register.description),
        bits=_bits(s, rtype),
    )
    s.reject_unknown()
    if reg.access == "ro" and (reg.min is not None or reg.max is not None):
        raise ConfigError(f"register {name}: min/max only make sense on rw registers")
    return reg


def _parse_heads(s: Section, present: bool, single: Sequence[Register]) -> HeadBlock | None:
    """The ``[heads]`` table: block geometry and ``[[heads.register]]`` entries.

    An entry naming a register of the single map gives only ``name`` and ``offset``: the
    register's type, access, limits, unit, description and bits are written once, there.
    """
    if not present:
        return None
    base = s.integer("base", lo=0, hi=0xFFFF)
    stride = s.integer("stride", lo=1, hi=0x1_0000)
    count = s.integer("count", lo=1, hi=0x1_0000)
    read_across = s.boolean("read_across", False)
    raw = s.raw("register")
    s.reject_unknown()
    if base + stride * count - 1 > 0xFFFF:
        raise ConfigError(
            f"heads: {count} blocks of {stride} words from {base} end past address 65535"
        )
    if not isinstance(raw, list) or not raw:
        raise ConfigError("heads.register must be a non-empty array of tables ([[heads.register]])")
    by_name = {r.name: r for r in single}
    regs = []
    for i, entry in enumerate(raw):
        where = f"heads.register[{i}]"
        if isinstance(entry, Mapping) and entry.get("name") in by_name:
            name = str(entry["name"])
            extra = sorted(set(entry) - {"name", "offset"})
            if extra:
                raise ConfigError(
                    f"heads.register {name}: {extra[0]} is given by the [[register]] entry "
                    f"{name} (a block entry naming a register has only name and offset)"
                )
            offset = Section(entry, f"heads.register {name}").integer("offset", lo=0)
            regs.append(replace(by_name[name], address=offset))
        else:
            regs.append(_parse_register(entry, where, offset_of="heads"))
    for r in regs:
        if r.last_address >= stride:
            raise ConfigError(
                f"heads.register {r.name}: offset {r.address} + {r.count} words exceeds the "
                f"stride {stride}"
            )
    return HeadBlock(base=base, stride=stride, count=count, registers=tuple(regs),
                     read_across=read_across)


def _validate_heads(whole: RegisterMap, heads: HeadBlock) -> None:
    """Refuse blocks that overlap the single map or each other (views check the rest)."""
    names = [r.name for r in heads.registers]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"heads.register {dup[0]}: duplicate name")
    end = heads.base + heads.stride * heads.count
    for reg in whole:
        if reg.address < end and reg.last_address >= heads.base:
            raise ConfigError(
                f"heads: blocks {heads.base}..{end - 1} overlap register {reg.name} "
                f"(address {reg.address})"
            )


def _head_view(whole: RegisterMap, heads: HeadBlock, i: int) -> RegisterMap:
    """Build head ``i``'s view of ``whole`` (:meth:`RegisterMap.for_head`)."""
    names = set(heads.names)
    view = RegisterMap(
        [*(r for r in whole._single if r.name not in names), *heads.placed(i)],
        unit_id=whole.unit_id,
        word_order=whole.word_order,
        function_codes=sorted(whole.function_codes),
        heads=heads,
        head=i,
    )
    view._single = whole._single
    view._common_span = whole._common_span
    view._whole = whole
    return view


def _markdown(registers: Sequence[Register], heads: HeadBlock | None) -> str:
    """The Markdown tables of :meth:`RegisterMap.markdown_table`."""
    rows = [
        "| address | name | type | words | access | min | max | unit | description |",
        "|---:|---|---|---:|---|---|---|---|---|",
    ]
    rows += [f"| {r.address} | {_row(r)}" for r in registers]
    if heads is not None:
        h = heads
        rows += [
            "",
            f"Head block: head i at {h.base} + {h.stride} i, {h.count} blocks "
            f"({h.base}..{h.base + h.stride * h.count - 1}); {h.used} words used per block.",
            "",
            "| offset | head 0 | name | type | words | access | min | max | unit | description |",
            "|---:|---:|---|---|---:|---|---|---|---|---|",
        ]
        for r in sorted(h.registers, key=lambda r: r.address):
            rows.append(f"| {r.address} | {h.base + r.address} | {_row(r)}")
    return "\n".join(rows) + "\n"


def _row(r: Register) -> str:
    """A Markdown table row of ``r`` from its name on."""
    lo = "" if r.min is None else (f"`{r.min}`" if isinstance(r.min, str) else str(r.min))
    hi = "" if r.max is None else (f"`{r.max}`" if isinstance(r.max, str) else str(r.max))
    text = r.description
    if r.bits:
        listed = ", ".join(f"{i} `{b}`" for i, b in enumerate(r.bits))
        text = f"{text}. Bits: {listed}" if text else f"Bits: {listed}"
    return f"`{r.name}` | {r.type} | {r.count} | {r.access} | {lo} | {hi} | {r.unit} | {text} |"


def _as_f32(x: float) -> float:
    return float(np.float32(x)) if abs(x) <= _F32_MAX else x


def _limit(s: Section, key: str) -> Limit:
    if not s.has(key):
        return None
    val = s.raw(key)
    if isinstance(val, bool) or not isinstance(val, (int, float, str)):
        raise ConfigError(f"{s.key(key)} must be a number or a register name, got {val!r}")
    return val


def _bits(s: Section, rtype: str) -> tuple[str, ...]:
    if not s.has("bits"):
        return ()
    val = s.raw("bits")
    if not isinstance(val, list) or not all(isinstance(b, str) for b in val):
        raise ConfigError(f"{s.key('bits')} must be a list of bit names, got {val!r}")
    width = 16 * TYPES[rtype]
    if len(val) > width:
        raise ConfigError(f"{s.key('bits')}: {len(val)} names for a {width}-bit register")
    for b in val:
        if not b.isidentifier():
            raise ConfigError(f"{s.key('bits')}: {b!r} is not an identifier")
    if len(set(val)) != len(val):
        raise ConfigError(f"{s.key('bits')}: duplicate names")
    return tuple(val)


def _validate_bits(reg: Register) -> None:
    """ConfigError unless ``reg``'s bits suit its type and match its flag enum (if it has one)."""
    flags = BIT_FLAGS.get(reg.name)
    if reg.bits and reg.type not in ("u16", "u32"):
        raise ConfigError(f"register {reg.name}: bits only on u16 or u32 registers")
    if flags is not None and tuple(reg.bits) != flag_names(flags):
        raise ConfigError(
            f"register {reg.name}: bits must be {list(flag_names(flags))} "
            f"(protocol.registers.{flags.__name__}), got {list(reg.bits)}"
        )
