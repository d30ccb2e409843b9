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
import math
import struct
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
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


BIT_FLAGS: Mapping[str, type[enum.IntFlag]] = MappingProxyType(
    {"machine_state": MachineState, "faults": PlcFault}
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
    ) -> None:
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
            self._validate_bits(reg)
        first = min(r.address for r in self.registers.values())
        last = max(r.last_address for r in self.registers.values())
        self._span = (first, last - first + 1)

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
        regs = []
        for i, entry in enumerate(raw):
            if not isinstance(entry, Mapping):
                raise ConfigError(f"register[{i}] must be a table")
            label = entry.get("name") if isinstance(entry.get("name"), str) else f"register[{i}]"
            s = Section(entry, f"register {label}")
            name = s.string("name")
            if not name.isidentifier():
                raise ConfigError(f"register {name!r}: name must be an identifier")
            rtype = s.string("type", choices=tuple(TYPES))
            reg = Register(
                name=name,
                address=s.integer("address", lo=0, hi=0xFFFF - TYPES[rtype] + 1),
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
            regs.append(reg)
        top.reject_unknown()
        return cls(regs, unit_id=unit_id, word_order=word_order, function_codes=codes)

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

    def _validate_bits(self, reg: Register) -> None:
        flags = BIT_FLAGS.get(reg.name)
        if reg.bits and reg.type not in ("u16", "u32"):
            raise ConfigError(f"register {reg.name}: bits only on u16 or u32 registers")
        if flags is not None and tuple(reg.bits) != flag_names(flags):
            raise ConfigError(
                f"register {reg.name}: bits must be {list(flag_names(flags))} "
                f"(protocol.registers.{flags.__name__}), got {list(reg.bits)}"
            )

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
        """The map as a Markdown table (``docs/register_map.md`` holds it; a test compares)."""
        rows = [
            "| address | name | type | words | access | min | max | unit | description |",
            "|---:|---|---|---:|---|---|---|---|---|",
        ]
        for r in self:
            lo = "" if r.min is None else (f"`{r.min}`" if isinstance(r.min, str) else str(r.min))
            hi = "" if r.max is None else (f"`{r.max}`" if isinstance(r.max, str) else str(r.max))
            text = r.description
            if r.bits:
                listed = ", ".join(f"{i} `{b}`" for i, b in enumerate(r.bits))
                text = f"{text}. Bits: {listed}" if text else f"Bits: {listed}"
            rows.append(
                f"| {r.address} | `{r.name}` | {r.type} | {r.count} | {r.access} | {lo} | {hi} "
                f"| {r.unit} | {text} |"
            )
        return "\n".join(rows) + "\n"

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
        end = s + len(words)
        out: dict[str, float | int] = {}
        for reg in self:
            if reg.address >= s and reg.last_address < end:
                i = reg.address - s
                out[reg.name] = self.decode(reg.name, words[i : i + reg.count])
        return out

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
